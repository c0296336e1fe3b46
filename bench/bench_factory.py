"""Benchmark of ``mscal apply --calibration factory`` on a survey of MicaSense captures,
beside a hand-written numpy loop of the manufacturer's model, measured in the same run.

    .venv/bin/python bench/bench_factory.py [--captures 1000] [--repeat 3] [--settle 20] [--quick]

The survey is built from the real RedEdge flight capture in ``../shared/data/micasense-rededge``
(``IMG_0001_{1..5}.tif``): ``--captures`` byte copies of its five band files, each copy with
its own random least-significant bits in the pixel strips and its own CaptureId (same length,
in the XMP and in MicaSense's private tag), so that every file has its own content and every
capture its own identity. Every command sees the files in the page cache.

Measured, each in its own fresh process (wall, CPU, peak RSS of that process alone; see
``bench_calibrate.run_measured``):

- the hand loop: per band file, EXIF + XMP parsed (tifffile tags, the XMP by regular
  expressions), MicaSense's model (black level, a1 / gain / exposure with the row-gradient terms
  a2, a3, the radial vignetting polynomial, map cached per band), reflectance from the sun
  sensor (``pi L / Irradiance``); one 5-band float32 ``.npy`` per capture; single-threaded;
- ``mscal apply CAPTURES --calibration factory --reference dls -o OUT`` (the default products:
  raw.zarr, reflectance.zarr with reflectance, NDVI and the vegetation mask, the photogrammetry
  and NDVI TIFFs, run.json; no radiance cube: docs/products.md);
- the write floor: the files of apply's last OUT (paths, sizes, order) written again the way
  apply writes them, with nothing computed (``bench_apply.child_writes``): what the device
  and the file system cost for apply's bytes alone, beside the wall the 2.0x target allows.

The loop and apply run ``--repeat`` times each, alternating, and the median of each counts.
Target: apply >= 2.0x faster than the loop.

Disk: a capture takes ~12 MB of band files and ~54 MB of apply outputs, so 1,000 captures need
~66 GB. The script measures both on a 4-capture probe first and, when ``--captures`` does not
fit in the work folder's free space, measures the largest count that does and says so in its
output and in the section (fewer than 40 fitting is an error).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_calibrate as bc  # shared measurement and markdown helpers
from bench_apply import median_run, output_manifest, settle, write_floor_label, write_floor_rows

SECTION_KEY = "bench_factory"
ROOT = HERE.parent
SAMPLE = ROOT.parent / "shared" / "data" / "micasense-rededge"
CAPTURE = "IMG_0001"
BANDS = 5


def make_survey(dst: Path, n: int, seed: int = 0) -> Path:
    """``n`` captures of five band files from the sample flight capture (module docstring)."""
    import tifffile

    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    for b in range(1, BANDS + 1):
        src = SAMPLE / f"{CAPTURE}_{b}.tif"
        raw = bytearray(src.read_bytes())
        with tifffile.TiffFile(src) as tf:
            page = tf.pages[0]
            offsets, counts = page.dataoffsets, page.databytecounts
            xmp = page.tags[700].value
            xmp = xmp.decode() if isinstance(xmp, bytes) else xmp
        cid = re.search(r"<MicaSense:CaptureId>([^<]+)</MicaSense:CaptureId>", xmp).group(1).encode()
        start, stop = offsets[0], offsets[-1] + counts[-1]
        assert stop - start == sum(counts), "the strips are expected to be contiguous"
        for i in range(n):
            noise = rng.integers(0, 2, size=(stop - start) // 2, dtype=np.uint16)
            pixels = np.frombuffer(bytes(raw[start:stop]), np.uint16) ^ noise
            out = bytearray(raw)
            out[start:stop] = pixels.tobytes()
            new_id = f"{i:0{len(cid)}d}".encode()[-len(cid):]
            out = out.replace(cid, new_id)
            (dst / f"IMG_{i:04d}_{b}.tif").write_bytes(out)
    return dst


# --------------------------------------------------------------------------- the hand loop

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def _xmp_values(xmp: str, tag: str) -> list[float]:
    m = re.search(rf"<[A-Za-z]+:{tag}>(.*?)</[A-Za-z]+:{tag}>", xmp, re.S)
    if m is None:
        m = re.search(rf'[A-Za-z]+:{tag}="([^"]*)"', xmp)
    return [float(v) for v in re.findall(_NUM, m.group(1))] if m else []


def loop_radiance(path: Path, vignetting: dict[tuple, np.ndarray]) -> tuple[np.ndarray, float]:
    """Radiance (W m-2 sr-1 nm-1) of one band file by MicaSense's model, and its sun-sensor
    Irradiance; ``vignetting`` caches the map per (shape, centre, polynomial)."""
    import tifffile

    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        dn = page.asarray().astype(np.float64)
        exif = page.tags["ExifTag"].value
        xmp = page.tags[700].value
        xmp = xmp.decode() if isinstance(xmp, bytes) else xmp
        black = float(np.mean(page.tags["BlackLevel"].value))
    t = exif["ExposureTime"][0] / exif["ExposureTime"][1]
    gain = float(exif["ISOSpeed"]) / 100.0
    a1, a2, a3 = _xmp_values(xmp, "RadiometricCalibration")
    cx, cy = _xmp_values(xmp, "VignettingCenter")
    poly = tuple(_xmp_values(xmp, "VignettingPolynomial"))
    h, w = dn.shape
    key = (h, w, cx, cy, poly)
    v = vignetting.get(key)
    if v is None:
        yy, xx = np.mgrid[0:h, 0:w]
        r = np.hypot(xx - cx, yy - cy)
        v = vignetting[key] = 1.0 / (1.0 + sum(k * r ** (i + 1) for i, k in enumerate(poly)))
    y = np.arange(h, dtype=np.float64)[:, None]
    row = 1.0 / (1.0 + a2 * y / t - a3 * y)
    radiance = np.maximum(v * row * (dn - black) / 65536.0 / (gain * t) * a1, 0.0)
    return radiance, _xmp_values(xmp, "Irradiance")[0]


def child_loop(captures: str, out: str) -> None:
    """MicaSense's published model by hand: one 5-band float32 reflectance file per capture."""
    src, dst = Path(captures), Path(out)
    dst.mkdir(parents=True, exist_ok=True)
    groups: dict[str, list[Path]] = {}
    for p in sorted(src.glob("IMG_*_*.tif")):
        groups.setdefault(p.stem.rsplit("_", 1)[0], []).append(p)
    vignetting: dict[tuple, np.ndarray] = {}
    for name, files in groups.items():
        stack = []
        for f in sorted(files, key=lambda q: int(q.stem.rsplit("_", 1)[1])):
            radiance, irradiance = loop_radiance(f, vignetting)
            stack.append(np.pi * radiance / irradiance)
        np.save(dst / f"{name}.npy", np.stack(stack).astype(np.float32))


# --------------------------------------------------------------------------- run and report


def _py(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


PROBE_CAPTURES = 4
DISK_MARGIN_B = 2e9


def allocated_bytes(path: Path) -> int:
    """Disk blocks a tree takes (``du``), not its files' apparent sizes."""
    return sum(p.lstat().st_blocks * 512 for p in path.rglob("*"))


def disk_per_capture(workdir: Path, mscal: list[str]) -> tuple[float, float]:
    """Bytes one capture takes on disk: its band files, and what ``mscal apply`` writes for it,
    measured on a probe survey of ``PROBE_CAPTURES`` captures (so the figure follows whatever
    apply writes; its per-flight files are counted against those few captures: an over-estimate)."""
    probe, out = workdir / "probe", workdir / "probe-out"
    make_survey(probe, PROBE_CAPTURES, seed=99)
    bc._check(bc.run_measured([*mscal, "apply", str(probe), "--calibration", "factory", "--reference", "dls",
                               "-o", str(out)]), "probe apply")
    per_in, per_out = allocated_bytes(probe) / PROBE_CAPTURES, allocated_bytes(out) / PROBE_CAPTURES
    bc.discard(probe)
    bc.discard(out)
    return per_in, per_out


def captures_that_fit(asked: int, per_in: float, per_out: float, free: float) -> int:
    """The largest count <= ``asked`` whose survey and one run's outputs fit in ``free`` bytes
    with ``DISK_MARGIN_B`` to spare (the loop's outputs, smaller than apply's, are emptied
    before apply runs)."""
    return max(0, min(asked, int((free - DISK_MARGIN_B) // (per_in + per_out))))


def sub_survey(survey: Path, dst: Path, n: int) -> Path:
    """The first ``n`` captures of ``survey`` as hard links in ``dst`` (no new bytes on disk;
    ``discard`` leaves linked files whole)."""
    dst.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        for b in range(1, BANDS + 1):
            os.link(survey / f"IMG_{i:04d}_{b}.tif", dst / f"IMG_{i:04d}_{b}.tif")
    return dst


def run(captures: int, workdir: Path, log=print, settle_s: float = 20.0, repeat: int = 3,
        scaling: Sequence[int] = ()) -> dict:
    mscal = bc.mscal_command()
    per_in, per_out = disk_per_capture(workdir, mscal)
    free = float(shutil.disk_usage(workdir).free)
    fit = captures_that_fit(captures, per_in, per_out, free)
    disk = {"asked": captures, "fit": fit, "free_gb": free / 1e9, "in_mb": per_in / 1e6, "out_mb": per_out / 1e6}
    if fit < captures:
        need = captures * (per_in + per_out) + DISK_MARGIN_B
        msg = (f"{captures} captures need ~{need / 1e9:.0f} GB on {workdir} ({per_in / 1e6:.1f} MB in + "
               f"{per_out / 1e6:.1f} MB of apply outputs per capture), {free / 1e9:.0f} GB free")
        if fit < PROBE_CAPTURES * 10:
            raise SystemExit(f"bench_factory: {msg}; free disk space or pass --workdir on a larger disk")
        log(f"WARNING: {msg}: measuring {fit} captures instead (the section says so)")
    captures = fit
    survey = make_survey(workdir / "captures", captures, seed=1)
    log(f"{captures} captures ({captures * BANDS} files) written to {survey}")
    res: dict = {"captures": captures, "settle_s": settle_s, "repeat": max(1, repeat),
                 "loop_runs": [], "apply_runs": [], "disk": disk}
    out = workdir / "out"
    for _ in range(max(1, repeat)):  # the captures read once after each rest (settle: the VM pages out idle memory)
        settle(settle_s, warm=(survey,))
        res["loop_runs"].append(bc._check(bc.run_measured(_py("--child", "loop", str(survey), str(workdir / "loop"))),
                                          "hand loop"))
        bc.discard(workdir / "loop")
        settle(settle_s, warm=(survey,))
        res["apply_runs"].append(bc._check(bc.run_measured(
            [*mscal, "apply", str(survey), "--calibration", "factory", "--reference", "dls", "-o", str(out)]),
            "mscal apply --calibration factory"))
        if len(res["apply_runs"]) == max(1, repeat):  # the last run's files: the write floor's input
            manifest = output_manifest(out)
            (workdir / "manifest.json").write_text(json.dumps(manifest))
        bc.discard(out)
    res["loop"], res["apply"] = median_run(res["loop_runs"]), median_run(res["apply_runs"])
    res["scaling"] = []
    for n in sorted({k for k in scaling if 0 < k < captures}):  # captures/s at fewer captures, same files
        sub = sub_survey(survey, workdir / f"captures-{n}", n)
        settle(settle_s, warm=(sub,))
        res["scaling"].append((n, bc._check(bc.run_measured(
            [*mscal, "apply", str(sub), "--calibration", "factory", "--reference", "dls", "-o", str(out)]),
            f"mscal apply --calibration factory ({n} captures)")))
        bc.discard(out)
        bc.discard(sub)
    bc.discard(survey)  # room for the write floor's copy of apply's outputs
    settle(settle_s, warm=(workdir / "manifest.json",))
    res["writes"] = bc._check(bc.run_measured(
        [sys.executable, str(HERE / "bench_apply.py"), "--child", "writes", str(workdir / "manifest.json"),
         str(workdir / "writes")]), "write floor")
    res["writes_mb"], res["writes_files"] = sum(size for _, size in manifest) / 1e6, len(manifest)
    bc.discard(workdir / "writes")
    log(f"factory apply {res['apply'].wall_s:.1f} s, hand loop {res['loop'].wall_s:.1f} s")
    return res


def _disk_lines(disk: dict | None) -> list[str]:
    if not disk:
        return []
    note = (f"Disk per capture (measured on a {PROBE_CAPTURES}-capture probe): {disk['in_mb']:.1f} MB of band files, "
            f"{disk['out_mb']:.1f} MB of apply outputs; {disk['free_gb']:.0f} GB free on the work disk.")
    if disk["fit"] < disk["asked"]:
        note += (f" **{disk['asked']} captures were asked; {disk['fit']} fit, and the figures below are for "
                 f"{disk['fit']}**: captures/s is the figure to carry over.")
    return ["", note]


def render(res: dict, command: str) -> str:
    info = bc.machine_info()
    n, lp, ap = res["captures"], res["loop"], res["apply"]
    speedup = lp.wall_s / ap.wall_s
    lines = [
        "## Factory apply benchmark",
        "",
        f"Produced by `bench/bench_factory.py`; a later run replaces this section. Run "
        f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')}.",
        "",
        "```",
        command,
        "```",
        "",
        f"Machine: {info['nproc']} CPUs ({info['cpu']}); {info['memory']} RAM; {info['os']}; Python {info['python']}; "
        f"numpy {info['numpy']}. Code: git {info['git']}.",
        "",
        f"Survey: {n} MicaSense RedEdge captures ({n * BANDS} band files of 1280 x 960, 16-bit), byte copies of the "
        "real flight capture `IMG_0001` with distinct pixels and CaptureIds. Reflectance from the sun sensor "
        f"(`--reference dls`). Before each command: the previous one's outputs emptied and moved aside (not deleted: "
        f"see `discard()` in bench_calibrate.py), `sync`, then {res['settle_s']:.0f} s of rest. The loop and apply "
        "alternate; the median run of each counts.",
        *_disk_lines(res.get("disk")),
        "",
        f"| command ({n} captures) | wall (s) | captures/s | CPU (s) | CPU / wall | peak RSS (MiB) | 1-min load before |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, r, runs, aid in (
            ("hand-written numpy loop of MicaSense's model (EXIF + XMP per file, vignetting cached per band, one "
             "5-band float32 file per capture)", lp, res["loop_runs"], "factory-loop"),
            ("`mscal apply --calibration factory --reference dls` (the default products)", ap, res["apply_runs"],
             "factory-mscal"),
            *([(write_floor_label(res), res["writes"], [], "factory-write-floor")] if "writes" in res else [])):
        each = f" (median; runs: {', '.join(f'{x.wall_s:.1f}' for x in runs)})" if len(runs) > 1 else ""
        lines.append(f'| <a id="{aid}"></a>{label}{each} | {r.wall_s:.1f} | {n / r.wall_s:.1f} | {r.cpu_s:.1f} | '
                     f"{r.cpu_s / r.wall_s:.2f} | {r.maxrss_mib:.0f} | {r.load_before[0]:.2f} |")
    lines += [
        "",
        "| figure | value | target | result |",
        "|---|---:|---:|:---:|",
        f'| <a id="factory-vs-loop"></a>loop wall / factory apply wall | {speedup:.2f}x | >= 2.0x | '
        f"{'PASS' if speedup >= 2.0 else 'FAIL'} |",
        *(write_floor_rows("factory", "factory apply", ap.wall_s, lp.wall_s, res["writes"].wall_s) if "writes" in res else []),
        f'| <a id="factory-rss"></a>factory apply peak RSS | {ap.maxrss_mib:.0f} MiB | <= 1024 MiB | '
        f"{'PASS' if ap.maxrss_mib <= 1024 else 'FAIL'} |",
    ]
    if res.get("scaling"):
        lines += [
            "",
            "Captures/s against the survey's length: `mscal apply` on the first N captures of the same survey (hard "
            "links, the same rest before each run), one run each, beside the median run above.",
            "",
            "| captures | wall (s) | captures/s | CPU (s) | peak RSS (MiB) | captures/s / the full survey's |",
            "|---:|---:|---:|---:|---:|---:|",
        ]
        for k, r in [*res["scaling"], (n, ap)]:
            lines.append(f"| {k} | {r.wall_s:.1f} | {k / r.wall_s:.1f} | {r.cpu_s:.1f} | {r.maxrss_mib:.0f} | "
                         f"{(k / r.wall_s) / (n / ap.wall_s):.2f} |")
        worst = min(k / r.wall_s for k, r in res["scaling"]) / (n / ap.wall_s)
        best = max(k / r.wall_s for k, r in res["scaling"]) / (n / ap.wall_s)
        flat = 0.9 <= worst and best <= 1.1
        lines += ["", f'<a id="factory-flat"></a>Captures/s at fewer captures is {worst:.2f}-{best:.2f}x the full '
                  f"survey's: {'flat within 10 %' if flat else 'not flat within 10 %'}."]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--captures", type=int, default=1000)
    p.add_argument("--repeat", type=int, default=None, help="alternating runs of each (default 3; --quick: 1)")
    p.add_argument("--settle", type=float, default=None, help="seconds of rest before each command (default 20; "
                                                              "--quick: 0)")
    p.add_argument("--quick", action="store_true", help="40 captures, one run each")
    p.add_argument("--scaling", type=int, nargs="*", default=(300,), metavar="N",
                   help="also apply the first N captures, for captures/s against length (default 300; --quick: 10)")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        kind, *rest = a.child
        if kind == "loop":
            child_loop(*rest)
        return 0
    if not SAMPLE.is_dir():
        print(f"bench_factory: {SAMPLE} not found: the benchmark needs the real MicaSense sample", file=sys.stderr)
        return 2
    if a.quick:
        a.captures = 40
        a.scaling = [10]
    command = shlex.join([".venv/bin/python", "bench/bench_factory.py", *(argv if argv is not None else sys.argv[1:])])
    with tempfile.TemporaryDirectory(prefix="mscal-bench-factory-", dir=a.workdir) as tmp:
        res = run(a.captures, Path(tmp), settle_s=a.settle if a.settle is not None else (0.0 if a.quick else 20.0),
                  repeat=a.repeat if a.repeat is not None else (1 if a.quick else 3), scaling=a.scaling)
    body = render(res, command)
    print(body)
    bc.write_section(a.out, body, SECTION_KEY)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
