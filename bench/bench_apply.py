"""Benchmark of ``mscal apply`` on a full-resolution flight, beside its baselines.

    .venv/bin/python bench/bench_apply.py [--frames 600] [--large 2400] [--repeat 3] [--settle 65] [--quick]

Measured in the same run, each command in its own fresh process (wall, peak RSS of that
process alone; see ``bench_calibrate.run_measured``):

- the I/O floor: read + decode every raw frame and write a float32 reflectance-sized array
  per frame, nothing else;
- a hand-written per-frame numpy loop: read, demosaic, LUT (U), divide by t V S, save;
- the same loop writing what apply writes by default (raw DN, reflectance, NDVI, vegetation mask,
  the 8 export-band TIFFs and an NDVI TIFF per frame; plain files, no Zarr, no EXIF/XMP):
  context for the loop figure, which compares against a loop that writes 1 file per frame;
- ``mscal apply FLIGHT --calibration CALIB -o OUT``, the default products (ingest into raw.zarr,
  Eq. 15, reflectance.zarr with NDVI and the vegetation mask, 8 photogrammetry TIFFs + 1 NDVI
  TIFF per frame, run.json; docs/products.md);
- ``mscal apply --workers 1`` (one worker) and ``--workers CORES`` (one per core): the scaling
  with cores, and what the default's spare worker adds (``pipeline.apply.execution.spare_workers``);
- ``mscal apply`` again on the finished OUT (nothing to do);
- the write floor: apply's own output files (paths, sizes, order taken from that OUT) written
  as apply writes them (direct I/O, temporary name then rename), one thread per core, nothing
  computed: what the device and the file system cost for apply's bytes alone;
- ``mscal apply`` on a flight ``--large / --frames`` times longer, for memory flatness.

The loop and ``mscal apply`` run ``--repeat`` times each, alternating, and the median run of
each is the figure. Before every measured command the previous outputs are emptied and moved
aside (``bench_calibrate.discard``: not deleted, see there), dirty pages flushed and the machine
left to rest ``--settle`` seconds (see :func:`settle`).

Targets: apply wall <= 1.2 x the I/O floor and >= 2.0 x
faster than the (single-threaded) loop; every core busy: the machine's busy CPU time over the
command's wall >= 0.9 x cores, less the cores busy over ``IDLE_PROBE_S`` of rest just before
(``/proc/stat``: apply's processes and the kernel threads that complete its direct writes and
journal its files; the CPU of apply's own processes is shown beside it); peak RSS
<= 1 GB and flat in the number of frames (within 15 %).
The flight is built from the frames of a small synthetic session, each copy with its own
random least-significant bits (so every file has its own content hash).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_calibrate as bc  # shared measurement and markdown helpers

SECTION_KEY = "bench_apply"

#: Seconds of rest, after the settle, over which the machine's busy cores are measured before
#: each command (the baseline of its "machine busy" figure).
IDLE_PROBE_S = 2.0
ROOT = HERE.parent


def make_flight(src: Path, dst: Path, n: int, seed: int = 0) -> Path:
    """``n`` frames from the frames of ``src`` (cycled), each with fresh random LSBs."""
    import tifffile

    rows = list(csv.DictReader((src / "frames.csv").open()))
    bases = [tifffile.imread(src / r["file"]) for r in rows]
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    with (dst / "frames.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "exposure_ms", "gain", "time", "lat", "lon", "alt_m"])
        for i in range(n):
            k = i % len(rows)
            frame = bases[k] ^ rng.integers(0, 2, size=bases[k].shape, dtype=np.uint16)
            name = f"IMG_{i:05d}.tif"
            tifffile.imwrite(dst / name, frame)
            r = rows[k]
            lat = float(r["lat"]) + 1e-5 * i
            w.writerow([name, r["exposure_ms"], 1, f"2017-06-14T10:{(i // 60) % 60:02d}:{i % 60:02d}Z",
                        f"{lat:.8f}", r["lon"], r["alt_m"]])
    return dst


def child_floor(flight: str, out: str) -> None:
    """I/O floor: read + decode each frame, write a float32 array of the reflectance's size."""
    import tifffile

    from pipeline.ingest.catalog import load_camera

    cam = load_camera("ximea-mq022hg-sm5x5-nir")
    shape = (cam.n_bands, *cam.layout.grid)
    Path(out).mkdir(parents=True, exist_ok=True)
    for r in csv.DictReader((Path(flight) / "frames.csv").open()):
        raw = tifffile.imread(Path(flight) / r["file"])
        arr = np.empty(shape, np.float32)
        arr[0, 0, 0] = raw[0, 0]
        arr.tofile(Path(out) / (Path(r["file"]).stem + ".f32"))


def output_manifest(out: Path) -> list[tuple[str, int]]:
    """Every file of a finished apply OUT as ``(path relative to OUT, size)``, in the order
    the files were written (modification time): the input of :func:`child_writes`."""
    files = [p for p in Path(out).rglob("*") if p.is_file()]
    stats = {p: p.stat() for p in files}
    files.sort(key=lambda p: (stats[p].st_mtime_ns, str(p)))
    return [(str(p.relative_to(out)), stats[p].st_size) for p in files]


def child_writes(manifest: str, out: str, threads: str = "0") -> None:
    """The write floor of apply's own outputs: the files of ``manifest`` (written by a real
    ``mscal apply``), same paths, sizes and order, each written the way apply writes a file
    (:func:`pipeline.storage.directio.write_file` to a temporary name, then renamed), by one
    thread per core and nothing computed. What the device and the file system cost for
    apply's bytes alone."""
    import json
    from concurrent.futures import ThreadPoolExecutor

    from pipeline.storage.directio import aligned_empty, write_file

    entries = [(Path(out) / rel, int(size)) for rel, size in json.loads(Path(manifest).read_text())]
    for folder in sorted({p.parent for p, _ in entries}):
        folder.mkdir(parents=True, exist_ok=True)
    data = aligned_empty((max((s for _, s in entries), default=0),), np.uint8)
    data[:] = np.random.default_rng(0).integers(0, 256, data.size, dtype=np.uint8)

    def one(entry: tuple[Path, int]) -> None:
        path, size = entry
        tmp = path.with_name(f".{path.name}.tmp")
        write_file(tmp, [data[:size]])
        os.replace(tmp, path)

    with ThreadPoolExecutor(int(threads) or os.cpu_count() or 1) as ex:
        for _ in ex.map(one, entries):
            pass


def write_floor_label(res: dict) -> str:
    """The write floor's row label (``res`` holds ``writes_files`` and ``writes_mb``)."""
    return (f"write floor: apply's own {res['writes_files']} files ({res['writes_mb'] / 1e3:.1f} GB), same sizes and "
            "order, direct I/O, one thread per core, nothing computed")


def write_floor_rows(prefix: str, subject: str, apply_wall: float, loop_wall: float, writes_wall: float) -> list[str]:
    """The two figure rows that put the write floor beside ``subject`` (the apply measured)
    and the 2.0x loop target; their anchors are ``{prefix}-vs-write-floor`` and
    ``{prefix}-loop-target``."""
    return [f'| <a id="{prefix}-vs-write-floor"></a>{subject} wall / write floor wall (context: the device and '
            f"file system for apply's bytes alone) | {apply_wall / writes_wall:.2f}x | | |",
            f'| <a id="{prefix}-loop-target"></a>wall the 2.0x loop target allows, beside the write floor | '
            f"{loop_wall / 2:.1f} s vs {writes_wall:.1f} s | | |"]


def _loop_frames(flight: str, calib: str):
    """The obvious per-frame numpy loop: read, demosaic, LUT, divide by t V S; yields
    (frame stem, DN, reflectance) per frame."""
    import tifffile
    import xarray as xr

    from mscal_core.mosaic import demosaic

    ds = xr.open_zarr(calib)
    U = ds["inverse_response"].values
    V = ds["vignetting"].values
    S = ds["spectral_factor"].values
    for r in csv.DictReader((Path(flight) / "frames.csv").open()):
        dn = demosaic(tifffile.imread(Path(flight) / r["file"]), (5, 5), (0, 0), (217, 409))
        t = float(r["exposure_ms"]) * float(r.get("gain") or 1)
        refl = np.empty(dn.shape, np.float32)
        for b in range(dn.shape[0]):
            refl[b] = U[b][dn[b]] / (t * V[b] * S[b])
        refl[dn >= 1023] = np.nan
        yield Path(r["file"]).stem, dn, refl


def child_loop(flight: str, calib: str, out: str) -> None:
    """The obvious per-frame numpy loop: read, demosaic, LUT, divide by t V S, save."""
    Path(out).mkdir(parents=True, exist_ok=True)
    for stem, _, refl in _loop_frames(flight, calib):
        np.save(Path(out) / (stem + ".npy"), refl)


def child_loop_same(flight: str, calib: str, out: str) -> None:
    """The same loop, writing per frame what ``mscal apply`` writes by default (reflectance,
    NDVI, the vegetation mask, the TIFFs), as a hand-written script would: raw DN and the
    float products as .npy, the export bands as uint16 TIFFs
    (reflectance x 32768) and NDVI as a float32 TIFF (tifffile; no EXIF/XMP)."""
    import cv2
    import tifffile

    from pipeline.ingest.catalog import load_camera

    cam = load_camera("ximea-mq022hg-sm5x5-nir")
    red, nir = (cam.band_for_wavelength(cam.index_bands[k]) for k in ("red", "nir"))
    export = [cam.band_names.index(b) for b in cam.export_bands][:8]
    o = Path(out)
    o.mkdir(parents=True, exist_ok=True)
    for stem, dn, refl in _loop_frames(flight, calib):
        with np.errstate(invalid="ignore", divide="ignore"):
            ndvi = (refl[nir] - refl[red]) / (refl[nir] + refl[red])
        u8 = np.nan_to_num((ndvi + 1) * 127.5, nan=0).clip(0, 255).astype(np.uint8)
        _, mask = cv2.threshold(u8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        np.save(o / f"{stem}_raw.npy", dn)
        np.save(o / f"{stem}.npy", refl)
        np.save(o / f"{stem}_ndvi.npy", ndvi)
        np.save(o / f"{stem}_mask.npy", mask)
        for b in export:
            tifffile.imwrite(o / f"{stem}_{cam.band_names[b]}.tif",
                             np.nan_to_num(refl[b] * 32768, nan=65535).clip(0, 65535).astype(np.uint16))
        tifffile.imwrite(o / f"{stem}_ndvi.tif", ndvi)


def _py(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


def settle(seconds: float, warm: Sequence[Path] = ()) -> None:
    """Bring the machine to the same state before each measured command: dirty pages
    flushed, then ``seconds`` of rest, then every file under ``warm`` (the command's inputs)
    read once. On the benchmark VM all three matter (perf profiles, docs/benchmarks.md): the
    guest gives freed memory back to its host within ~20 s, after which the first touch of a
    page costs ~2.8 ms per MB, so a command that started sooner found its pages still backed;
    flushing leaves no earlier command's writeback to the next; and the kernel runs DAMON's
    ``pageout`` scheme (kdamond: memory not accessed for 60 s is paged out, up to 128 MB/s),
    so after 65 s of rest the inputs were partly gone from the page cache: in one run apply
    took 14.3, 21.1 and 16.0 s and the re-run on a finished OUT 17.9 s (4.2 s the day
    before). Previous outputs are emptied, not deleted (``bench_calibrate.discard``): ext4
    makes every file created within 60-360 s of a deletion scan past the deleted inodes."""
    os.sync()
    if seconds > 0:
        time.sleep(seconds)
    warm_files(warm)


def warm_files(paths: Sequence[Path]) -> int:
    """Read every file under ``paths`` (files or folders) into the page cache; returns the
    bytes read."""
    buf = bytearray(8 << 20)
    total = 0
    for top in paths:
        top = Path(top)
        for f in ([top] if top.is_file() else sorted(q for q in top.rglob("*") if q.is_file())):
            with f.open("rb", buffering=0) as fh:
                while k := fh.readinto(buf):
                    total += k
    return total


def median_run(runs: list):  # bench_calibrate.Run
    """The run of median wall time (the lower middle one of an even count)."""
    return sorted(runs, key=lambda r: r.wall_s)[(len(runs) - 1) // 2]


def run(frames: int, large: int, workdir: Path, log=print, settle_s: float = 65.0, repeat: int = 3) -> dict:
    mscal = bc.mscal_command()
    session = workdir / "session"
    log(f"synthesizing a small session in {session}")
    bc._check(bc.run_measured(_py("--child", "synth", str(session))), "synthesis")
    calib = workdir / "calib.zarr"
    bc._check(bc.run_measured([*mscal, "calibrate", str(session), "-o", str(calib)]), "calibrate")
    res: dict = {"frames": frames, "large": large, "settle_s": settle_s, "repeat": max(1, repeat)}
    flight = make_flight(session / "flights" / "field", workdir / "flight", frames, seed=1)
    log(f"flight of {frames} frames written")

    def measured(cmd: list[str], what: str, timeout: float = bc.CHILD_TIMEOUT_S, inputs: Sequence[Path] = ()):
        settle(settle_s, warm=inputs or (flight, calib))
        idle = bc.machine_busy_rate(IDLE_PROBE_S)  # what else keeps the machine busy
        return replace(bc._check(bc.run_measured(cmd, timeout=timeout), what), machine_idle_cores=idle)

    res["floor"] = measured(_py("--child", "floor", str(flight), str(workdir / "floor")), "floor")
    bc.discard(workdir / "floor")
    res["loop_same"] = measured(_py("--child", "loop_same", str(flight), str(calib), str(workdir / "loop_same")),
                                "loop (same products)")
    bc.discard(workdir / "loop_same")
    out = workdir / "out"
    # the two figures of the loop target, interleaved and repeated: on a shared VM one run of
    # either varies by +-25 % from minute to minute; the median of alternating runs does not
    # favour either
    res["loop_runs"], res["apply_runs"] = [], []
    for k in range(max(1, repeat)):
        res["loop_runs"].append(measured(_py("--child", "loop", str(flight), str(calib), str(workdir / "loop")), "loop"))
        bc.discard(workdir / "loop")
        bc.discard(out)
        res["apply_runs"].append(measured([*mscal, "apply", str(flight), "--calibration", str(calib), "-o", str(out)],
                                          "apply"))
    res["loop"], res["apply"] = median_run(res["loop_runs"]), median_run(res["apply_runs"])
    res["rerun"] = measured([*mscal, "apply", str(flight), "--calibration", str(calib), "-o", str(out)], "re-run")
    res["apply_workers"] = json.loads((out / "run.json").read_text())["execution"]["workers"]  # the default's
    manifest = output_manifest(out)
    (workdir / "manifest.json").write_text(json.dumps(manifest))
    bc.discard(out)
    res["writes"] = measured(_py("--child", "writes", str(workdir / "manifest.json"), str(workdir / "writes")),
                             "write floor", inputs=(workdir / "manifest.json",))
    res["writes_mb"] = sum(size for _, size in manifest) / 1e6
    res["writes_files"] = len(manifest)
    bc.discard(workdir / "writes")
    res["apply_1"] = measured([*mscal, "apply", str(flight), "--calibration", str(calib), "-o", str(out),
                               "--workers", "1"], "apply (1 worker)")
    bc.discard(out)
    cores = os.cpu_count() or 1
    res["apply_cores"] = measured([*mscal, "apply", str(flight), "--calibration", str(calib), "-o", str(out),
                                   "--workers", str(cores)], f"apply ({cores} workers)")
    res["apply_cores_n"] = cores
    bc.discard(out)
    log(f"apply on {frames} frames: {res['apply'].wall_s:.1f} s, floor {res['floor'].wall_s:.1f} s, loop {res['loop'].wall_s:.1f} s")
    if large:
        bc.discard(flight)
        big = make_flight(session / "flights" / "field", workdir / "flight_large", large, seed=2)
        res["apply_large"] = measured([*mscal, "apply", str(big), "--calibration", str(calib), "-o",
                                       str(workdir / "out_large")], "apply (large)", timeout=4 * 3600,
                                      inputs=(big, calib))
        bc.discard(workdir / "out_large")
        res["floor_large"] = measured(_py("--child", "floor", str(big), str(workdir / "floor_large")), "floor (large)",
                                      inputs=(big,))
        bc.discard(workdir / "floor_large")
        bc.discard(big)
    return res


def render(res: dict, command: str) -> str:
    info = bc.machine_info()
    f, lp, ap, rr = res["floor"], res["loop"], res["apply"], res["rerun"]
    n = res["frames"]
    ratio_floor = ap.wall_s / f.wall_s
    speedup = lp.wall_s / ap.wall_s
    rows = [  # label, measurement, HTML id of the row (README figures link to it)
        ("I/O floor (read + decode, write float32)", f, "apply-floor"),
        ("per-frame numpy loop (read, demosaic, LUT, divide, save)", lp, "apply-loop"),
        *([("the same loop writing what apply writes (raw, reflectance, ndvi, mask as .npy; 8 band TIFFs "
            "+ NDVI TIFF, no EXIF/XMP)", res["loop_same"], "apply-loop-same")] if "loop_same" in res else []),
        ("`mscal apply`", ap, "apply-mscal"),
        ("`mscal apply` again on the finished OUT", rr, "apply-rerun"),
        *([("`mscal apply --workers 1` (one worker)", res["apply_1"], "apply-one-worker")] if "apply_1" in res else []),
        *([(f"`mscal apply --workers {res['apply_cores_n']}` (one worker per core, no spare)", res["apply_cores"],
            "apply-per-core")] if "apply_cores" in res else []),
        *([(write_floor_label(res), res["writes"], "apply-write-floor")] if "writes" in res else []),
    ]
    cores = int(info["nproc"]) if str(info["nproc"]).isdigit() else os.cpu_count() or 1
    busy = ap.cpu_s / ap.wall_s
    machine_busy = ap.machine_cpu_s / ap.wall_s - (0.0 if math.isnan(ap.machine_idle_cores) else ap.machine_idle_cores)
    lines = [
        "## Apply benchmark",
        "",
        f"Produced by `bench/bench_apply.py`; a later run replaces this section. Run {time.strftime('%Y-%m-%dT%H:%M:%S%z')}.",
        "",
        "```",
        command,
        "```",
        "",
        f"Machine: {info['nproc']} CPUs ({info['cpu']}); {info['memory']} RAM; {info['os']}; Python {info['python']}; "
        f"numpy {info['numpy']}; OpenCV {info['opencv']}. Code: git {info['git']}.",
        "",
        f"Flight: {n} full-resolution frames (2048 x 1088 raw mosaic, 10-bit, 25 bands of 217 x 409), built from the "
        "flight frames of a small synthetic session, each with its own random least-significant bits. Outputs of "
        "`mscal apply` (the default products): raw.zarr, reflectance.zarr (reflectance, ndvi, vegetation_mask), 8 "
        "photogrammetry TIFFs and 1 NDVI TIFF per frame, run.json. The frames are in the page cache for every command (read once after the "
        "rest: the VM pages out memory not accessed for 60 s). Before each "
        "command: the previous command's outputs emptied and moved aside, not deleted (`discard()` in "
        "bench_calibrate.py: on ext4 every file created within 60-360 s of a deletion scans past the deleted "
        f"inodes), `sync`, then {res.get('settle_s', 0):.0f} s of rest (`--settle`; see `settle()` in the script: "
        "a command that starts sooner after another finds that one's freed memory still backed).",
        "",
        f"| command ({n} frames) | wall (s) | frames/s | CPU user (s) | CPU kernel (s) | machine busy (cores; idle before) "
        "| peak RSS (MiB) | 1-min load before |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    runs_of = {"apply-loop": res.get("loop_runs"), "apply-mscal": res.get("apply_runs")}
    for label, r, aid in rows:
        runs = runs_of.get(aid)
        each = f" (median; runs: {', '.join(f'{x.wall_s:.1f}' for x in runs)})" if runs and len(runs) > 1 else ""
        lines.append(f'| <a id="{aid}"></a>{label}{each} |' f" {r.wall_s:.1f} | {n / r.wall_s:.1f} | {r.user_s:.1f} | {r.sys_s:.1f} | "
                     f"{r.machine_cpu_s / r.wall_s:.2f}; {r.machine_idle_cores:.2f} | {r.maxrss_mib:.0f} | {r.load_before[0]:.2f} |")
    lines += [
        "",
        "| figure | value | target | result |",
        "|---|---:|---:|:---:|",
        f'| <a id="apply-vs-floor"></a>apply wall / I/O floor wall | {ratio_floor:.2f}x'
        f" | <= 1.2x | {'PASS' if ratio_floor <= 1.2 else 'FAIL'} |",
        f'| <a id="apply-vs-loop"></a>loop wall / apply wall (the loop: one thread) | {speedup:.2f}x'
        f" | >= 2.0x | {'PASS' if speedup >= 2.0 else 'FAIL'} |",
        f'| <a id="apply-vs-loop-user"></a>loop user CPU / apply wall (the loop without its kernel time: '
        f"page cache and page faults, which this VM makes slow when its memory went back to the host) | "
        f"{lp.user_s / ap.wall_s:.2f}x | >= 2.0x | {'PASS' if lp.user_s / ap.wall_s >= 2.0 else 'FAIL'} |",
        f'| <a id="apply-cpu-own"></a>apply CPU / wall, its own processes ({cores} cores; context) | {busy:.2f} | | |',
        f'| <a id="apply-cores-busy"></a>machine busy / wall during apply, less the idle machine\'s ({cores} cores: '
        "apply's processes and the kernel threads that complete its writes) | "
        f"{machine_busy:.2f} | >= {0.9 * cores:.1f} | {'PASS' if machine_busy >= 0.9 * cores else 'FAIL'} |",
        *([f'| <a id="apply-scaling"></a>apply 1 worker wall / {res.get("apply_workers", cores)} workers wall '
           f"(the default; scaling with cores) | {res['apply_1'].wall_s / ap.wall_s:.2f}x | | |"] if "apply_1" in res else []),
        *([f'| <a id="apply-scaling-cores"></a>apply 1 worker wall / {res["apply_cores_n"]} workers wall (one per '
           f"core) | {res['apply_1'].wall_s / res['apply_cores'].wall_s:.2f}x | | |",
           f'| <a id="apply-spare"></a>apply {res["apply_cores_n"]} workers wall / the default\'s '
           f"({res.get('apply_workers', '?')} workers; the spare's gain) | {res['apply_cores'].wall_s / ap.wall_s:.2f}x | | |"]
          if "apply_1" in res and "apply_cores" in res else []),
        *([f'| <a id="apply-vs-loop-same"></a>same-products loop wall / apply wall (context) | '
           f"{res['loop_same'].wall_s / ap.wall_s:.2f}x | | |"] if "loop_same" in res else []),
        *(write_floor_rows("apply", "apply", ap.wall_s, lp.wall_s, res["writes"].wall_s) if "writes" in res else []),
        f'| <a id="apply-rss"></a>apply peak RSS | {ap.maxrss_mib:.0f} MiB'
        f" | <= 1024 MiB | {'PASS' if ap.maxrss_mib <= 1024 else 'FAIL'} |",
    ]
    if "apply_large" in res:
        al, fl = res["apply_large"], res["floor_large"]
        growth = al.maxrss_mib / ap.maxrss_mib - 1
        lines += [
            f"| apply peak RSS, {res['large']} vs {n} frames | {al.maxrss_mib:.0f} vs {ap.maxrss_mib:.0f} MiB ({growth:+.1%}) "
            f"| within 15 % | {'PASS' if abs(growth) <= 0.15 else 'FAIL'} |",
            f"| apply wall / I/O floor wall, {res['large']} frames | {al.wall_s / fl.wall_s:.2f}x ({al.wall_s:.0f} s vs {fl.wall_s:.0f} s) | <= 2.0x | "
            f"{'PASS' if al.wall_s / fl.wall_s <= 2.0 else 'FAIL'} |",
        ]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--large", type=int, default=2400, help="second, longer flight for memory flatness (0: skip)")
    p.add_argument("--quick", action="store_true", help="60 and 240 frames")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--repeat", type=int, default=None,
                   help="runs of the loop and of apply, interleaved; the median counts (default 3; --quick: 1)")
    p.add_argument("--settle", type=float, default=None,
                   help="seconds of rest after sync before each measured command (default 65; --quick: 0)")
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        kind, *rest = a.child
        if kind == "synth":
            from pipeline.sim.synth import write_session

            write_session(rest[0], seed=5, size="small")
        elif kind == "floor":
            child_floor(*rest)
        elif kind == "loop":
            child_loop(*rest)
        elif kind == "loop_same":
            child_loop_same(*rest)
        elif kind == "writes":
            child_writes(*rest)
        return 0
    if a.quick:
        a.frames, a.large = 60, 240
    command = shlex.join([".venv/bin/python", "bench/bench_apply.py", *(argv if argv is not None else sys.argv[1:])])
    with tempfile.TemporaryDirectory(prefix="mscal-bench-apply-", dir=a.workdir) as tmp:
        res = run(a.frames, a.large, Path(tmp), settle_s=a.settle if a.settle is not None else (0.0 if a.quick else 65.0),
                  repeat=a.repeat if a.repeat is not None else (1 if a.quick else 3))
    body = render(res, command)
    print(body)
    bc.write_section(a.out, body, SECTION_KEY)
    return 0


if __name__ == "__main__":
    sys.exit(main())
