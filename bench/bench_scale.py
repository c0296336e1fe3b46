#!/usr/bin/env python
"""Scale benchmark: apply throughput and peak memory vs frames and Dask workers,
calibration time vs vignetting views; the I/O floor beside each.

Usage::

    .venv/bin/python bench/bench_scale.py [--quick] [--out docs/benchmarks.md]

Every measured command runs in its own fresh process (``bench_calibrate.run_measured``: wall,
CPU and peak RSS of that process alone). Measured in the same run:

1. **Frames, full resolution** (the camera mscal is built for: 2048 x 1088 raw mosaic, 25
   bands): ``mscal apply`` on flights of ``--frames`` frames, each beside the I/O floor on the
   same files (read + decode every frame, write a float32 array of the reflectance's size).
2. **Frames, small** (``--small-frames``, up to 5000): the same on 256 x 320 8-bit RGB frames
   (``generic-rgb8`` camera, a calibration store with U = identity, V = 1, S = 1, no index
   maps because that camera has no NIR band), through the Python API
   (``pipeline.apply.flight.apply_flight``). Disk: a full-resolution frame is 4.4 MB in and 13.7 MB
   out, so 5000 of them need ~90 GB; the small frames need ~1.9 MB per frame. Each run's
   outputs (and the floor's) are deleted before the next; the flight of the largest count is
   written once and the smaller counts use its first N frames (a ``frames.csv`` of N rows in
   a folder of hard links). Every frame has its own content (``mscal apply`` quarantines
   duplicates): the full-resolution frames get fresh random least-significant bits, the
   small ones a distinct TIFF description. A count is skipped, and the table says so, when
   the free disk space is less than its estimate plus 5 GB.
3. **Dask**: ``apply_flight`` on the full-resolution flight inside ``distributed.Client`` of a
   ``LocalCluster`` with 1, 2 and 4 single-threaded worker processes (cluster start-up
   included in the wall time and shown apart); peak RSS = the client process + the sum of
   the workers' peaks (each worker reports its own ``ru_maxrss``).
4. **Calibration vs views**: ``mscal calibrate`` on one full synthetic session whose
   ``vignetting/`` keeps its first N views (hard links), beside the I/O floor of reading and
   demosaicking the same calibration frames.

The markdown section replaces the text between ``<!-- bench_scale:start -->`` and
``<!-- bench_scale:end -->`` of ``--out``. ``--quick``: 20 and 60 full-resolution frames,
100 and 400 small frames, Dask 1 and 2 workers on 60 frames, the small session with 4 and 8
views; output under ``build/bench-quick/`` unless ``--out`` is given.

Importing this module runs nothing.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import bench_calibrate as bc

SECTION_KEY = "bench_scale"
DEFAULT_OUT = ROOT / "docs" / "benchmarks.md"
QUICK_DIR = ROOT / "build" / "bench-quick"

FULL = {"frames": (100, 600, 2400), "small_frames": (100, 1000, 5000), "dask_frames": 600, "workers": (1, 2, 4),
        "views": (10, 20, 40), "session": "full"}
QUICK = {"frames": (20, 60), "small_frames": (100, 400), "dask_frames": 60, "workers": (1, 2),
         "views": (4, 8), "session": "small"}

#: Disk per frame (MB), measured on this code: full resolution in 4.4 (uint16 mosaic), out
#: 13.7 (apply) or 8.9 (floor); small frames in 0.25, out 1.7.
MB_PER_FRAME = {"full": (4.4, 13.7), "small": (0.25, 1.7)}
DISK_MARGIN_GB = 5.0
SMALL_SHAPE = (256, 320)


# --------------------------------------------------------------------------- inputs


def make_full_flight(src: Path, dst: Path, n: int, seed: int = 0) -> Path:
    """``n`` full-resolution frames cycled from ``src``'s, each with fresh random LSBs."""
    import bench_apply

    return bench_apply.make_flight(src, dst, n, seed=seed)


def make_small_flight(dst: Path, n: int, shape: tuple[int, int] = SMALL_SHAPE, seed: int = 0) -> Path:
    """``n`` 8-bit RGB frames of ``shape``: one random image, a distinct TIFF description each."""
    import numpy as np
    import tifffile

    dst.mkdir(parents=True, exist_ok=True)
    img = np.random.default_rng(seed).integers(8, 250, (*shape, 3), dtype=np.uint8)
    with (dst / "frames.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "exposure_ms"])
        for i in range(n):
            name = f"IMG_{i:05d}.tif"
            tifffile.imwrite(dst / name, img, description=f"bench frame {i}")
            w.writerow([name, "1.0"])
    return dst


def subset_flight(src: Path, dst: Path, n: int) -> Path:
    """A flight folder of the first ``n`` frames of ``src`` (hard links, no copies)."""
    rows = list(csv.DictReader((src / "frames.csv").open()))[:n]
    if len(rows) < n:
        raise ValueError(f"{src} has {len(rows)} frames, {n} wanted")
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    with (dst / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            os.link(src / r["file"], dst / r["file"])
            w.writerow(r)
    return dst


def subset_views(session: Path, dst: Path, n: int) -> Path:
    """A session sharing ``session``'s files (hard links) whose ``vignetting/`` keeps its first ``n`` views."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(session, dst, copy_function=os.link, ignore=shutil.ignore_patterns("flights"))
    subset_flight(session / "vignetting", dst / "vignetting", n)
    return dst


def small_calibration(path: Path, shape: tuple[int, int] = SMALL_SHAPE) -> Path:
    """A ``generic-rgb8`` calibration store with U = DN, V = 1, S = 1 (throughput only)."""
    import numpy as np

    from pipeline.ingest.catalog import load_camera
    from pipeline.storage.store import new_dataset, write_store

    cam = load_camera("generic-rgb8")
    nb, levels = cam.n_bands, 2**cam.bit_depth
    ds = new_dataset(cam)
    ds.coords["dn"] = np.arange(levels, dtype=np.int32)
    ds["inverse_response"] = (("band", "dn"), np.tile(np.arange(levels, dtype=float), (nb, 1)))
    ds["vignetting"] = (("band", "y", "x"), np.ones((nb, *shape)))
    ds["spectral_factor"] = ("band", np.ones(nb))
    ds["saturation_dn"] = ("band", np.full(nb, levels - 1, np.int32))
    ds["black_level"] = ("band", np.zeros(nb))
    ds.attrs["notes"] = "bench_scale throughput store: U = DN, V = 1, S = 1 (not a calibration)"
    return write_store(ds, path)


def free_gb(path: Path) -> float:
    return shutil.disk_usage(path).free / 1e9


def disk_needed_gb(kind: str, n: int) -> float:
    """Disk a count needs at its peak: the inputs and one run's outputs (MB_PER_FRAME)."""
    din, dout = MB_PER_FRAME[kind]
    return n * (din + dout) / 1e3


# --------------------------------------------------------------------------- children


def child_floor(flight: str, out: str, kind: str) -> None:
    """I/O floor: read + decode every frame, write a float32 array of the reflectance's size."""
    import numpy as np

    if kind == "full":
        import bench_apply

        bench_apply.child_floor(flight, out)
        return
    import tifffile

    Path(out).mkdir(parents=True, exist_ok=True)
    for r in csv.DictReader((Path(flight) / "frames.csv").open()):
        raw = tifffile.imread(Path(flight) / r["file"])
        arr = np.empty((raw.shape[2], *raw.shape[:2]), np.float32)
        arr[0, 0, 0] = raw[0, 0, 0]
        arr.tofile(Path(out) / (Path(r["file"]).stem + ".f32"))


def child_apply(flight: str, calib: str, out: str, kind: str) -> None:
    """``apply_flight`` through the Python API (the small frames need no indices)."""
    from pipeline.apply.flight import apply_flight
    from pipeline.apply.options import ApplyOptions
    from pipeline.ingest.products import Products

    opts = ApplyOptions(products=Products(indices=())) if kind == "small" else ApplyOptions()
    res = apply_flight(flight, calib, out, opts)
    print(json.dumps({"frames_out": res.run["frames_out"], "quarantined": len(res.quarantined)}))


def _peak_rss_kib() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def child_dask(flight: str, calib: str, out: str, workers: str) -> None:
    """``apply_flight`` on a LocalCluster of ``workers`` single-threaded worker processes."""
    from distributed import Client, LocalCluster

    from pipeline.apply.flight import apply_flight

    t0 = time.perf_counter()
    with LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=None,
                      local_directory=str(Path(out).parent / "dask-scratch")) as cluster, Client(cluster) as client:
        client.wait_for_workers(int(workers), timeout=120)
        t1 = time.perf_counter()
        res = apply_flight(flight, calib, out)
        t2 = time.perf_counter()
        worker_rss = client.run(_peak_rss_kib)
    print(json.dumps({"startup_s": t1 - t0, "apply_s": t2 - t1, "frames_out": res.run["frames_out"],
                      "worker_peak_rss_kib": sorted(worker_rss.values())}))


def child_views_floor(session: str) -> None:
    bc._child_io_floor(session)


# --------------------------------------------------------------------------- runs


def _me(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), "--child", *args]


def _last_json(run: bc.Run) -> dict[str, Any]:
    return json.loads(run.stdout.strip().splitlines()[-1])


def measure_frames(kind: str, counts: Sequence[int], big: Path, calib: Path, work: Path, log=print) -> list[dict]:
    """Floor then ``mscal apply`` (full) / ``apply_flight`` (small) per count; outputs deleted in between."""
    rows = []
    mscal = bc.mscal_command()
    for n in counts:
        need = disk_needed_gb(kind, n)
        free = free_gb(work)
        row: dict[str, Any] = {"kind": kind, "frames": n}
        if free < need + DISK_MARGIN_GB:
            row["skipped"] = f"needs ~{need:.0f} GB of disk, {free:.0f} GB free"
            log(f"[{kind} {n}] skipped: {row['skipped']}")
            rows.append(row)
            continue
        flight = subset_flight(big, work / f"flight-{kind}-{n}", n)
        floor = bc._check(bc.run_measured(_me("floor", str(flight), str(work / "floor"), kind)), f"floor {kind} {n}")
        bc.discard(work / "floor")  # emptied, not deleted: see bench_calibrate.discard
        out = work / "out"
        if kind == "full":
            cmd = [*mscal, "apply", str(flight), "--calibration", str(calib), "-o", str(out)]
        else:
            cmd = _me("apply", str(flight), str(calib), str(out), kind)
        ap = bc._check(bc.run_measured(cmd, timeout=4 * 3600), f"apply {kind} {n}")
        row["out_mb_per_frame"] = _du_mb(out) / n
        bc.discard(out)
        shutil.rmtree(flight, ignore_errors=True)  # hard links: deleting them frees no inode
        row.update(floor=floor, apply=ap)
        log(f"[{kind} {n}] apply {ap.wall_s:.1f} s ({n / ap.wall_s:.1f} frames/s, {ap.maxrss_mib:.0f} MiB), "
            f"floor {floor.wall_s:.1f} s")
        rows.append(row)
    return rows


def _du_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def measure_dask(workers: Sequence[int], big: Path, n: int, calib: Path, work: Path, log=print) -> list[dict]:
    rows = []
    flight = subset_flight(big, work / "flight-dask", n)
    try:
        for k in workers:
            out = work / "out-dask"
            run = bc._check(bc.run_measured(_me("dask", str(flight), str(calib), str(out), str(k))), f"dask {k}")
            info = _last_json(run)
            bc.discard(out)
            shutil.rmtree(work / "dask-scratch", ignore_errors=True)
            rss = run.maxrss_mib + sum(info["worker_peak_rss_kib"]) / 1024.0
            rows.append({"workers": k, "frames": n, "run": run, "startup_s": info["startup_s"],
                         "apply_s": info["apply_s"], "total_rss_mib": rss,
                         "worker_rss_mib": [v / 1024.0 for v in info["worker_peak_rss_kib"]]})
            log(f"[dask {k}] apply {info['apply_s']:.1f} s + start-up {info['startup_s']:.1f} s, {rss:.0f} MiB")
    finally:
        shutil.rmtree(flight, ignore_errors=True)
    return rows


def measure_views(session: Path, views: Sequence[int], work: Path, keep: Path | None = None, log=print) -> list[dict]:
    """``mscal calibrate`` per view count; the store of the run with every view is moved to ``keep``."""
    import xarray as xr

    total = len(list(csv.DictReader((session / "vignetting" / "frames.csv").open())))

    rows = []
    mscal = bc.mscal_command()
    for n in views:
        sdir = subset_views(session, work / f"session-{n}", n)
        floor = bc._check(bc.run_measured(_me("views-floor", str(sdir))), f"views floor {n}")
        cal = work / f"calib-{n}.zarr"
        run = bc._check(bc.run_measured([*mscal, "calibrate", str(sdir), "-o", str(cal)]), f"calibrate {n} views")
        attrs = xr.open_zarr(cal).attrs
        stages = {k: float((attrs.get(k) or {}).get("seconds", float("nan")))
                  for k in ("response", "vignetting", "illumination")}
        skipped = len((attrs.get("vignetting") or {}).get("skipped", []))
        if keep is not None and n >= total and not keep.exists():
            shutil.move(str(cal), str(keep))  # the flights below are applied with it
        shutil.rmtree(cal, ignore_errors=True)
        shutil.rmtree(sdir, ignore_errors=True)
        rows.append({"views": n, "floor": floor, "run": run, "stages": stages, "skipped": skipped})
        log(f"[views {n}] calibrate {run.wall_s:.1f} s (vignetting {stages['vignetting']:.1f} s), floor {floor.wall_s:.1f} s")
    return rows


# --------------------------------------------------------------------------- markdown


def frame_table(rows: Sequence[dict], kind: str) -> str:
    lines = [
        "| frames | `apply` wall (s) | frames/s | I/O floor wall (s) | apply / floor | `apply` CPU (s) | "
        "`apply` peak RSS (MiB) | I/O floor peak RSS (MiB) | output (MB/frame) | 1-min load before |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        cell = f'<a id="scale-{kind}-{r["frames"]}"></a>{r["frames"]}'
        if "skipped" in r:
            lines.append(f"| {cell} | skipped: {r['skipped']} |" + " |" * 8)
            continue
        ap, fl, n = r["apply"], r["floor"], r["frames"]
        lines.append(f"| {cell} | {ap.wall_s:.1f} | {n / ap.wall_s:.1f} | {fl.wall_s:.1f} | {ap.wall_s / fl.wall_s:.2f}x "
                     f"| {ap.cpu_s:.1f} | {ap.maxrss_mib:.0f} | {fl.maxrss_mib:.0f} | {r['out_mb_per_frame']:.1f} "
                     f"| {ap.load_before[0]:.2f} |")
    return "\n".join(lines)


def flatness(rows: Sequence[dict]) -> str:
    done = [r for r in rows if "skipped" not in r]
    if len(done) < 2:
        return ""
    a, b = done[0], done[-1]
    growth = b["apply"].maxrss_mib / a["apply"].maxrss_mib - 1
    rate = (b["frames"] / b["apply"].wall_s) / (a["frames"] / a["apply"].wall_s)
    return (f"{b['frames']} vs {a['frames']} frames: peak RSS {b['apply'].maxrss_mib:.0f} vs "
            f"{a['apply'].maxrss_mib:.0f} MiB ({growth:+.1%}); throughput {rate:.2f}x")


def dask_table(rows: Sequence[dict], local: dict | None) -> str:
    lines = [
        "| scheduler | wall (s) | of which cluster start-up (s) | apply (s) | frames/s (apply) | speed-up vs 1 worker "
        "| peak RSS, all processes (MiB) | workers' peaks (MiB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    one = next((r for r in rows if r["workers"] == 1), None)
    if local is not None:
        ap = local["apply"]
        lines.append(f'| <a id="scale-dask-local"></a>`mscal apply` default (local threads, no cluster) | {ap.wall_s:.1f} | 0 '
                     f"| {ap.wall_s:.1f} | {local['frames'] / ap.wall_s:.1f} | "
                     f"{(one['apply_s'] / ap.wall_s) if one else float('nan'):.2f}x | {ap.maxrss_mib:.0f} | |")
    for r in rows:
        sp = one["apply_s"] / r["apply_s"] if one else float("nan")
        lines.append(f'| <a id="scale-dask-{r["workers"]}"></a>LocalCluster, {r["workers"]} worker(s) | '
                     f"{r['run'].wall_s:.1f} | {r['startup_s']:.1f} | {r['apply_s']:.1f} | {r['frames'] / r['apply_s']:.1f} "
                     f"| {sp:.2f}x | {r['total_rss_mib']:.0f} | {', '.join(f'{v:.0f}' for v in r['worker_rss_mib'])} |")
    return "\n".join(lines)


def views_table(rows: Sequence[dict]) -> str:
    lines = [
        "| vignetting views | `mscal calibrate` wall (s) | CPU (s) | stage: response (s) | stage: vignetting (s) "
        "| stage: illumination (s) | peak RSS (MiB) | I/O floor wall (s) | calibrate / floor | views skipped |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        run, fl, st = r["run"], r["floor"], r["stages"]
        lines.append(f'| <a id="scale-views-{r["views"]}"></a>{r["views"]} | {run.wall_s:.1f} | {run.cpu_s:.1f} | '
                     f"{st['response']:.1f} | {st['vignetting']:.1f} | {st['illumination']:.1f} | {run.maxrss_mib:.0f} "
                     f"| {fl.wall_s:.1f} | {run.wall_s / fl.wall_s:.1f}x | {r['skipped']} |")
    return "\n".join(lines)


def render(res: dict, cfg: dict, quick: bool, command: str, info: dict[str, str], started: str,
           loads: dict[str, str], wall_s: float) -> str:
    full_rows = res["frames_full"]
    local = next((r for r in full_rows if "skipped" not in r and r["frames"] == cfg["dask_frames"]), None)
    parts = [
        '<a id="bench-scale"></a>',
        "",
        "## Scale" + (" (quick smoke run)" if quick else ""),
        "",
        f"Produced by `bench/bench_scale.py`; a later run replaces this section. Run started {started}, "
        f"{wall_s / 60:.1f} min.",
        "",
        "```",
        command,
        "```",
        "",
        "Machine: " + "; ".join([f"{info['nproc']} CPUs ({info['cpu']})", f"{info['memory']} RAM", info["os"],
                                  f"Python {info['python']}", f"numpy {info['numpy']}", f"OpenCV {info['opencv']}"])
        + f". Code: git {info['git']}. Load (`uptime`): at start `{loads['start']}`; at end `{loads['end']}`. "
        "Each command runs in its own fresh process (wall, CPU and peak RSS of that process alone); the frames are "
        "in the page cache. Ratios to the I/O floor measured beside each row are the claim; absolute times depend "
        "on the machine and its load.",
        "",
        "### Apply vs number of frames, full resolution",
        "",
        "2048 x 1088 raw mosaic, 10-bit, 25 bands of 217 x 409 (the synthetic session's flight frames cycled, each "
        "with its own random least-significant bits). `mscal apply FLIGHT --calibration CALIB -o OUT` writes "
        "raw.zarr, reflectance.zarr (reflectance, ndvi, mask: the default products), 8 photogrammetry TIFFs and 1 NDVI TIFF per "
        "frame. The I/O floor reads and decodes every frame and writes a float32 array of the reflectance's size. "
        "2,400 frames (the memory check) fit on this machine's disk; 5,000 would not (4.4 MB in and 13.7 MB "
        "out per frame), hence the small-frame table below.",
        "",
        frame_table(full_rows, "full"),
        "",
    ]
    fl = flatness(full_rows)
    if fl:
        parts += [f"Flatness, full resolution: {fl}.", ""]
    small = res["frames_small"]
    parts += [
        "### Apply vs number of frames, small frames (to 5000)",
        "",
        f"{SMALL_SHAPE[0]} x {SMALL_SHAPE[1]} 8-bit RGB frames (`generic-rgb8` camera), a throughput-only "
        "calibration store (U = DN, V = 1, S = 1), no index maps (the camera has no NIR band); "
        "`pipeline.apply.flight.apply_flight` through the Python API (what `mscal apply` calls). Per-frame work is "
        "small, so this table shows the per-frame overhead and whether memory stays flat over thousands of "
        "frames. Each run's outputs are emptied and moved aside before the next (not deleted: "
        "`discard()` in bench_calibrate.py).",
        "",
        frame_table(small, "small"),
        "",
    ]
    fl = flatness(small)
    if fl:
        parts += [f"Flatness, small frames: {fl}.", ""]
    parts += [
        "### Dask LocalCluster",
        "",
        f"`apply_flight` on {cfg['dask_frames']} full-resolution frames inside `distributed.Client(LocalCluster("
        "n_workers=k, threads_per_worker=1))` (what `mscal run --dask-address` does with a running scheduler). "
        "Wall is the whole process (imports, cluster start-up, the pass, shut-down); apply is the pass alone; "
        "the first row is the `mscal apply` process of the same frames in the table above (its wall also "
        "counts start-up, so its speed-up is a lower bound). Peak RSS adds the client process's peak and "
        f"each worker's own peak. This machine has {info['nproc']} CPUs: more workers than CPUs only share them.",
        "",
        dask_table(res["dask"], local),
        "",
        "### Calibration time vs vignetting views",
        "",
        f"One `pipeline.sim.synth.write_session(size=\"{cfg['session']}\", seed=0)` session; `vignetting/` keeps its "
        "first N views (hard links; the synthetic sequence puts views without the marker among them). I/O floor: "
        "read and demosaic every frame of `response/`, `vignetting/` and `reflector/`, nothing else.",
        "",
        views_table(res["views"]),
        "",
    ]
    return "\n".join(parts)


# --------------------------------------------------------------------------- main


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="small counts (smoke run, < 2 min); output under build/bench-quick")
    p.add_argument("--frames", type=int, nargs="+", default=None, help="full-resolution counts (default 100 600 2400)")
    p.add_argument("--small-frames", type=int, nargs="+", default=None, help="small-frame counts (default 100 1000 5000)")
    p.add_argument("--workers", type=int, nargs="+", default=None, help="Dask worker counts (default 1 2 4)")
    p.add_argument("--views", type=int, nargs="+", default=None, help="vignetting view counts (default 10 20 40)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def config(a: argparse.Namespace) -> dict:
    cfg = dict(QUICK if a.quick else FULL)
    for k in ("frames", "small_frames", "workers", "views"):
        if getattr(a, k) is not None:
            cfg[k] = tuple(getattr(a, k))
    if cfg["dask_frames"] not in cfg["frames"]:
        cfg["dask_frames"] = min(cfg["frames"])
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    raw = list(sys.argv[1:] if argv is None else argv)
    a = parse_args(raw)
    sys.path.insert(0, str(ROOT))
    if a.child:
        kind, *rest = a.child
        {"floor": child_floor, "apply": child_apply, "dask": child_dask, "views-floor": child_views_floor}[kind](*rest)
        return 0
    cfg = config(a)
    out = a.out or (QUICK_DIR / "benchmarks.md" if a.quick else DEFAULT_OUT)
    command = shlex.join([".venv/bin/python", "bench/bench_scale.py", *raw])
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    loads = {"start": bc._uptime()}
    info = bc.machine_info()
    t0 = time.perf_counter()
    log = lambda m: print(m, flush=True)
    work = Path(tempfile.mkdtemp(prefix="mscal-bench-scale-", dir=a.workdir))
    res: dict[str, Any] = {}
    try:
        session = work / "session"
        log(f"synthesizing a {cfg['session']} session")
        bc._check(bc.run_measured([sys.executable, str(HERE / "bench_calibrate.py"), "--_child", "synth",
                                   str(session), "0", cfg["session"]]), "synthesis")
        calib = work / "calib.zarr"
        res["views"] = measure_views(session, cfg["views"], work, calib, log)
        if not calib.exists():
            bc._check(bc.run_measured([*bc.mscal_command(), "calibrate", str(session), "-o", str(calib)]), "calibrate")
        nmax = max(cfg["frames"])
        if free_gb(work) >= nmax * MB_PER_FRAME["full"][0] / 1e3 + DISK_MARGIN_GB:
            big = make_full_flight(session / "flights" / "field", work / "flight-full", nmax, seed=1)
        else:
            big = make_full_flight(session / "flights" / "field", work / "flight-full", min(cfg["frames"]), seed=1)
        log(f"full-resolution flight of {len(list(big.glob('*.tif')))} frames written")
        res["frames_full"] = measure_frames("full", cfg["frames"], big, calib, work, log)
        res["dask"] = measure_dask(cfg["workers"], big, cfg["dask_frames"], calib, work, log)
        shutil.rmtree(big, ignore_errors=True)
        small_cal = small_calibration(work / "calib-small.zarr")
        big_small = make_small_flight(work / "flight-small", max(cfg["small_frames"]))
        res["frames_small"] = measure_frames("small", cfg["small_frames"], big_small, small_cal, work, log)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    loads["end"] = bc._uptime()
    md = render(res, cfg, a.quick, command, info, started, loads, time.perf_counter() - t0)
    print(md)
    bc.write_section(out, md, SECTION_KEY)
    print(f"wrote section {SECTION_KEY} of {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
