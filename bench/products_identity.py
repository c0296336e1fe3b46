"""Byte-identity of apply's outputs: another checkout (the reference, e.g. main before a
change) against this one.

    .venv/bin/python bench/products_identity.py --reference ../main --work /tmp/identity

The reference checkout (its own ``.venv``) writes a small synthetic snapshot session
(``pipeline.sim``, seed 0, two flights), calibrates it, and applies it and the factory samples
of ``../shared/data`` (MicaSense RedEdge, Parrot Sequoia, Sentera nRGB and NDRE) twice: with
its default products, and with every opt-in product it supports (the options of the list
below that its ``mscal apply --help`` names). This checkout applies the same flights three
ways: the default products, every opt-in product the camera allows (``--products radiance``
with factory radiometry, ``--indices ndre`` where the bands make it) and ``--no-tiffs``.
Compared, file by file:

- default vs the reference's default: every file byte-identical; the reference may have
  written ``radiance`` and ``ndre`` by default (a checkout before they were opt-in), none is added;
- every opt-in product vs the reference with the same opt-ins: every file byte-identical, none
  missing or added; when the reference supports only some of the opt-ins, the files it could
  not make are listed as "new", not as a difference;
- ``--no-tiffs`` vs default: no TIFF; every other file byte-identical.

``run.json`` and the Zarr metadata (``zarr.json``, listing the variables) may differ and are
reported apart. Exit status 0 when everything else is identical.
"""
from __future__ import annotations

import argparse
import filecmp
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
TIFF_DIRS = ("photogrammetry", "panels", "thermal", "ndvi")
OPT_IN_VARS = ("radiance", "ndre")
FACTORY = {"micasense": "micasense-rededge", "sequoia": "parrot-sequoia", "sentera-ndre": "sentera-d4k/NDRE",
           "sentera-nrgb": "sentera-d4k/nRGB"}
#: The opt-in products of each flight (all the camera allows; the reference wrote all of them).
ALL = {"demo-field": ["--indices", "ndre"], "demo-orchard": ["--indices", "ndre"],
       "sentera-nrgb": ["--products", "radiance"]}  # blue, green, red: no NDVI, no NDRE
ALL_FACTORY = ["--products", "radiance", "--indices", "ndre"]


def mscal(checkout: Path, work: Path, *args: str) -> None:
    env = {**os.environ, "MSCAL_CACHE_DIR": str(work / "cache")}
    subprocess.run([str(checkout / ".venv/bin/python"), "-m", "pipeline.run.cli", "-q", *args], cwd=checkout,
                   env=env, check=True, stdout=subprocess.DEVNULL)


def flights(work: Path, data: Path) -> dict[str, tuple[Path, str]]:
    out = {f"demo-{f}": (work / "session" / "flights" / f, str(work / "calib.zarr")) for f in ("field", "orchard")}
    out.update({name: (data / sub, "factory") for name, sub in FACTORY.items() if (data / sub).is_dir()})
    return out


def opt_ins(name: str) -> list[str]:
    """The options that switch on every opt-in product of flight ``name``."""
    return ALL.get(name, ALL_FACTORY)


def supported(checkout: Path, args: list[str]) -> tuple[list[str], list[str]]:
    """``args`` (option, value pairs) split into those ``checkout``'s ``mscal apply`` has and
    those it has not (an older checkout)."""
    run = subprocess.run([str(checkout / ".venv/bin/python"), "-m", "pipeline.run.cli", "apply", "--help"],
                         cwd=checkout, check=True, capture_output=True, text=True)
    has: list[str] = []
    lacks: list[str] = []
    for option, value in zip(args[::2], args[1::2]):
        (has if option in run.stdout else lacks).extend((option, value))
    return has, lacks


def reference_outputs(ref: Path, work: Path, data: Path) -> dict[str, list[str]]:
    """The reference's outputs (default and every opt-in it supports) under ``work/reference``;
    the opt-in options it lacks, by flight."""
    if not (work / "calib.zarr").is_dir():
        code = (f"from pipeline.sim.synth import write_session; "
                f"write_session({str(work / 'session')!r}, seed=0, size='small', flights=('field', 'orchard'))")
        subprocess.run([str(ref / ".venv/bin/python"), "-c", code], cwd=ref, check=True)
        mscal(ref, work, "calibrate", str(work / "session"), "-o", str(work / "calib.zarr"))
    lacking = {}
    for name, (flight, calib) in flights(work, data).items():
        has, lacking[name] = supported(ref, opt_ins(name))
        for mode, extra in (("default", []), ("all", has)):
            out = work / "reference" / mode / name
            if not (out / "run.json").is_file():
                mscal(ref, work, "apply", str(flight), "--calibration", calib, "-o", str(out), *extra)
    return lacking


def files(root: Path) -> dict[str, Path]:
    return {str(p.relative_to(root)): p for p in root.rglob("*")
            if p.is_file() and "logs" not in p.relative_to(root).parts}


def is_metadata(rel: str) -> bool:
    return rel == "run.json" or rel.endswith("zarr.json")


def compare(a_root: Path, b_root: Path, left_out=lambda rel: False, new: bool = False) -> dict[str, list[str]]:
    """Files of ``a_root`` against ``b_root``; ``left_out(rel)``: files of a that b must not have;
    ``new``: files of b that a lacks are ones a could not make (listed apart, no difference)."""
    a, b = files(a_root), files(b_root)
    res: dict[str, list[str]] = {"identical": [], "differ": [], "metadata_differ": [], "missing": [], "added": [],
                                 "new": []}
    for rel, path in sorted(a.items()):
        if left_out(rel):
            if rel in b:
                res["added"].append(f"{rel} (should be left out)")
        elif rel not in b:
            res["missing"].append(rel)
        elif filecmp.cmp(path, b[rel], shallow=False):
            res["identical"].append(rel)
        else:
            res["metadata_differ" if is_metadata(rel) else "differ"].append(rel)
    res["new" if new else "added"] += sorted(rel for rel in b if rel not in a and not left_out(rel))
    return res


def report(title: str, res: dict[str, list[str]]) -> bool:
    data = [r for r in res["identical"] if not is_metadata(r)]
    ok = not (res["differ"] or res["missing"] or res["added"])
    new = f", new (the reference cannot make them) {len(res['new'])}" if res["new"] else ""
    print(f"  {title}: {len(data)} data files identical (chunks, TIFFs), {len(res['identical']) - len(data)} metadata "
          f"files identical; differing {len(res['differ'])}, missing {len(res['missing'])}, added {len(res['added'])}"
          f"{new}; metadata differing: {', '.join(res['metadata_differ']) or 'none'} -> {'OK' if ok else 'DIFFERENT'}")
    for key in ("differ", "missing", "added", "new"):
        for rel in res[key][:10]:
            print(f"      {key}: {rel}")
    return ok


def opt_in_file(rel: str) -> bool:
    parts = rel.split("/")
    return parts[0] == "reflectance.zarr" and len(parts) > 1 and parts[1] in OPT_IN_VARS


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", type=Path, required=True, help="checkout whose outputs are the reference")
    ap.add_argument("--work", type=Path, required=True, help="folder for the session and every output")
    ap.add_argument("--data", type=Path, default=HERE.parent / "shared" / "data", help="the camera samples")
    args = ap.parse_args(argv)
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    lacking = reference_outputs(args.reference.resolve(), work, args.data)
    ok = True
    for name, (flight, calib) in flights(work, args.data).items():
        print(f"{name}:")
        modes = {"default": [], "all": opt_ins(name), "no-tiffs": ["--no-tiffs"]}
        outs = {}
        for mode, extra in modes.items():
            outs[mode] = work / mode / name
            if not (outs[mode] / "run.json").is_file():
                mscal(HERE, work, "apply", str(flight), "--calibration", calib, "-o", str(outs[mode]), *extra)
        ref = work / "reference"
        ok &= report("default vs reference default (its radiance, ndre left out)",
                     compare(ref / "default" / name, outs["default"], opt_in_file))
        pairs = zip(modes["all"][::2], modes["all"][1::2])
        same = " ".join(f"{o} {v}" for o, v in pairs if o not in lacking[name][::2])
        ok &= report(f"{' '.join(modes['all'])} vs reference with {same or 'its default'}"
                     + (f" (it has no {' '.join(lacking[name][::2])})" if lacking[name] else ""),
                     compare(ref / "all" / name, outs["all"], new=bool(lacking[name])))
        tiffs = [rel for rel in files(outs["no-tiffs"]) if rel.split("/")[0] in TIFF_DIRS]
        ok &= report(f"--no-tiffs vs default ({len(tiffs)} TIFFs written)",
                     compare(outs["default"], outs["no-tiffs"], lambda rel: rel.split("/")[0] in TIFF_DIRS))
        ok &= not tiffs
    print("all identical" if ok else "DIFFERENCES")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
