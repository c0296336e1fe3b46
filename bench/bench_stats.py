"""Benchmark of ``mscal stats`` (per-field zonal statistics) beside a plain rasterio loop.

    .venv/bin/python bench/bench_stats.py [--mosaics 200] [--size 4000] [--fields 100] [--quick]

Data: ``--mosaics`` synthetic reflectance orthomosaics of ``--size`` x ``--size`` px (Red, NIR as
uint16 reflectance x 32768, nodata 65535, 512 x 512 tiles, DEFLATE; ``pipeline.sim.synth.
write_orthomosaic``), 0.1 m pixels in UTM 33N, each shifted by a random few metres over the same
ground, with a nodata stripe; ``--fields`` square fields on a grid over that ground, in a WGS 84
GeoJSON. ``--distinct`` files are written (default: all); the rest are symbolic links to them
(saves disk, but then the page cache may serve repeated files: say so when quoting figures).

Measured in the same run, each command in its own fresh process (wall, CPU, peak RSS of that
process alone; ``bench_calibrate.run_measured``), both with ``GDAL_CACHEMAX=128`` (MB):

- ``mscal stats --fields F.geojson --index ndvi M1 ... MN -o T --workers 2`` (tiles, one Dask
  task per mosaic on 2 threads);
- the plain loop: for each mosaic, ``src.read()`` of both bands whole, NDVI, and per field
  ``rasterio.features.geometry_mask`` over the whole mosaic and numpy statistics; one process.

Both tables are compared (largest absolute difference of mean/median/p10/p90) to show that they
measure the same thing. ``--quick`` (4 mosaics of 1000 px, 16 fields) checks that the script
works; it writes nothing unless ``--out`` is given, and then under its own markers.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))
import bench_calibrate as bc  # shared measurement and markdown helpers

SECTION_KEY = "bench_stats"
QUICK_SECTION_KEY = "bench_stats_quick"
UTM = "EPSG:32633"
X0, Y0 = 500000.0, 5001000.0
PX = 0.1


def _child_synth(workdir: str, n: int, size: int, n_fields: int, distinct: int, seed: int) -> None:
    from rasterio.warp import transform

    from pipeline.sim.synth import write_orthomosaic

    work = Path(workdir)
    rng = np.random.default_rng(seed)
    side = size * PX
    # fields: a k x k grid of squares inside the ground every mosaic covers (minus 5 % margins)
    k = max(1, int(round(np.sqrt(n_fields))))
    cell = side * 0.9 / k
    feats = []
    for i in range(k):
        for j in range(k):
            x0 = X0 + side * 0.05 + j * cell + cell * 0.1 + 0.013
            y1 = Y0 - side * 0.05 - i * cell - cell * 0.1 - 0.017
            ring = [(x0, y1 - cell * 0.8), (x0 + cell * 0.8, y1 - cell * 0.8), (x0 + cell * 0.8, y1), (x0, y1),
                    (x0, y1 - cell * 0.8)]
            lon, lat = transform(UTM, "EPSG:4326", [p[0] for p in ring], [p[1] for p in ring])
            feats.append({"type": "Feature", "properties": {"id": f"f{i:02d}{j:02d}"},
                          "geometry": {"type": "Polygon", "coordinates": [[[a, b] for a, b in zip(lon, lat)]]}})
    (work / "fields.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    # one NDVI pattern per field cell (smooth ramps) plus per-pixel noise, per mosaic its own
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    paths = []
    for m in range(n):
        p = work / "mosaics" / f"2026-{5 + m // 28:02d}-{1 + m % 28:02d}" / f"ortho_{m:03d}.tif"
        p.parent.mkdir(parents=True, exist_ok=True)
        if m < distinct:
            dx, dy = rng.uniform(-3, 3, 2)
            base = 0.2 + 0.4 * (0.5 + 0.5 * np.sin(6.3 * xx + m * 0.1) * np.cos(4.1 * yy))
            ndvi = np.clip(base + rng.normal(0, 0.02, size=(size, size)).astype(np.float32), -0.5, 0.8)
            invalid = np.zeros((size, size), bool)
            r0 = int(rng.integers(0, size - size // 20))
            invalid[r0:r0 + size // 40, :] = True  # a stripe of nodata
            write_orthomosaic(p, ndvi, crs=UTM, transform=(PX, 0.0, X0 + dx, 0.0, -PX, Y0 + dy), invalid=invalid,
                              seed=seed + m, block=512, compress="deflate", dtype="uint16",
                              date=p.parent.name)
        else:
            p.symlink_to(paths[m % distinct].resolve())
        paths.append(p)
    (work / "mosaics.txt").write_text("\n".join(str(p) for p in paths))


def _child_loop(fields_path: str, list_path: str, out_csv: str) -> None:
    """The plain rasterio loop: whole mosaic in memory, one mask per field."""
    import rasterio
    from rasterio.features import geometry_mask
    from rasterio.warp import transform_geom

    doc = json.loads(Path(fields_path).read_text())
    rows = []
    for path in Path(list_path).read_text().split():
        with rasterio.open(path) as src:
            red, nir = src.read(out_dtype="float32")
            valid = (src.read_masks(1) > 0) & (src.read_masks(2) > 0)
            red /= 32768.0
            nir /= 32768.0
            with np.errstate(divide="ignore", invalid="ignore"):
                ndvi = (nir - red) / (nir + red)
            ndvi[~valid] = np.nan
            for f in doc["features"]:
                g = transform_geom("EPSG:4326", src.crs, f["geometry"])
                inside = ~geometry_mask([g], out_shape=(src.height, src.width), transform=src.transform)
                v = ndvi[inside].astype(np.float64)
                v = v[np.isfinite(v)]
                if v.size == 0:
                    continue
                q = np.quantile(v, [0.5, 0.1, 0.9])
                rows.append((f["properties"]["id"], Path(path).stem, v.mean(), q[0], q[1], q[2]))
    with open(out_csv, "w") as fh:
        fh.write("field_id,flight,mean,median,p10,p90\n")
        for r in rows:
            fh.write(",".join([r[0], r[1], *(f"{x:.12g}" for x in r[2:])]) + "\n")


def compare(table_parquet: Path, loop_csv: Path) -> tuple[int, float]:
    import pandas as pd

    a = pd.read_parquet(table_parquet)
    a = a[a["status"] == "ok"].copy()
    a["flight"] = a["flight"].map(lambda s: Path(s).name)
    b = pd.read_csv(loop_csv, dtype={"field_id": str, "flight": str})
    m = a.merge(b, on=["field_id", "flight"], suffixes=("", "_loop"))
    if len(m) != len(b) or len(m) != len(a):
        raise RuntimeError(f"tables differ in rows: mscal {len(a)}, loop {len(b)}, matched {len(m)}")
    diff = max(float(np.max(np.abs(m[c] - m[c + "_loop"]))) for c in ("mean", "median", "p10", "p90"))
    return len(m), diff


def render(args: argparse.Namespace, command: str, runs: dict, matched: int, diff: float, info: dict,
           loads: tuple[str, str]) -> str:
    st, lp = runs["stats"], runs["loop"]
    mpx = args.mosaics * args.size * args.size / 1e6
    lines = [
        "## Zonal statistics benchmark (`mscal stats`)", "",
        f"Produced by `bench/bench_stats.py`; a later run replaces this section. Run started {loads[0]}.", "",
        "```", command, "```", "",
        f"Machine: {info.get('nproc', '?')} CPUs ({info.get('cpu', '?')}); {info.get('memory', '?')} RAM; "
        f"Python {info.get('python', '?')}. Code: git {info.get('git', '?')}. Load (`uptime`): at start "
        f"`{loads[0]}`; at end `{loads[1]}`. The machine is shared: other work may have run meanwhile.", "",
        f"Data: {args.mosaics} orthomosaics of {args.size} x {args.size} px ({mpx:.0f} Mpx; "
        f"{args.distinct if args.distinct else args.mosaics} distinct files, the rest symbolic links), "
        f"{args.fields} fields. Each command in its own fresh process, `GDAL_CACHEMAX=128`.", "",
        "| method | wall (s) | Mpx/s | mosaics/s | CPU user+sys (s) | peak RSS (MiB) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for label, r in (("`mscal stats --workers 2` (tiles, Dask)", st), ("plain rasterio loop (whole mosaic)", lp)):
        lines.append(f"| {label} | {r.wall_s:.1f} | {mpx / r.wall_s:.1f} | {args.mosaics / r.wall_s:.2f} | "
                     f"{r.cpu_s:.1f} | {r.maxrss_mib:.0f} |")
    lines += ["", f"Ratio: `mscal stats` is {lp.wall_s / st.wall_s:.2f}x the loop's throughput, "
              f"{st.maxrss_mib / lp.maxrss_mib:.2f}x its peak RSS. Same numbers: {matched} (field, mosaic) rows "
              f"matched, largest |difference| of mean/median/p10/p90 {diff:.2e}."]
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mosaics", type=int, default=200)
    p.add_argument("--size", type=int, default=4000)
    p.add_argument("--fields", type=int, default=100)
    p.add_argument("--distinct", type=int, default=0, help="distinct files written (0: all)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="4 mosaics of 1000 px, 16 fields; writes no doc")
    p.add_argument("--out", type=Path, default=None, help=f"markdown to update (default: {bc.DEFAULT_OUT}, not with --quick)")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.quick:
        a.mosaics, a.size, a.fields = 4, 1000, 16
    return a


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        mode, *rest = args.child
        if mode == "synth":
            _child_synth(rest[0], *map(int, rest[1:]))
        elif mode == "loop":
            _child_loop(*rest)
        return 0
    command = shlex.join([".venv/bin/python", "bench/bench_stats.py", *(argv if argv is not None else sys.argv[1:])])
    os.environ["GDAL_CACHEMAX"] = "128"
    os.environ["PYTHONPATH"] = str(ROOT)  # children run this tree's mscal, not another install's
    me = [sys.executable, str(Path(__file__).resolve())]
    distinct = args.distinct or args.mosaics
    with tempfile.TemporaryDirectory(prefix="mscal-bench-stats-", dir=args.workdir) as tmp:
        work = Path(tmp)
        t = time.perf_counter()
        bc._check(bc.run_measured([*me, "--child", "synth", str(work), str(args.mosaics), str(args.size),
                                   str(args.fields), str(distinct), str(args.seed)]), "synthesis")
        print(f"synthesised {args.mosaics} mosaics ({distinct} distinct) in {time.perf_counter() - t:.0f} s", flush=True)
        loads0 = bc._uptime()
        paths = (work / "mosaics.txt").read_text().split()
        runs = {
            "stats": bc._check(bc.run_measured([sys.executable, "-m", "pipeline.run.cli", "stats", "--fields", str(work / "fields.geojson"),
                                                "--index", "ndvi", *paths, "-o", str(work / "table"),
                                                "--workers", str(args.workers)]), "mscal stats"),
            "loop": bc._check(bc.run_measured([*me, "--child", "loop", str(work / "fields.geojson"),
                                               str(work / "mosaics.txt"), str(work / "loop.csv")]), "plain loop"),
        }
        loads1 = bc._uptime()
        matched, diff = compare(work / "table.parquet", work / "loop.csv")
    mpx = args.mosaics * args.size * args.size / 1e6
    for k, r in runs.items():
        print(f"{k:5s}: wall {r.wall_s:.1f} s, {mpx / r.wall_s:.1f} Mpx/s, CPU {r.cpu_s:.1f} s, peak RSS {r.maxrss_mib:.0f} MiB")
    print(f"ratio (loop wall / stats wall): {runs['loop'].wall_s / runs['stats'].wall_s:.2f}x; "
          f"peak RSS stats / loop: {runs['stats'].maxrss_mib / runs['loop'].maxrss_mib:.2f}x; "
          f"{matched} rows matched, max |diff| {diff:.2e}")
    out = args.out if args.out is not None else (None if args.quick else bc.DEFAULT_OUT)
    if out is not None:
        body = render(args, command, runs, matched, diff, bc.machine_info(), (loads0, loads1))
        bc.write_section(out, body, QUICK_SECTION_KEY if args.quick else SECTION_KEY)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
