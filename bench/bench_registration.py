"""Band co-registration: accuracy, effect on real data, cost.

    .venv/bin/python bench/bench_registration.py [--seeds 8] [--frames 50] [--quick]

Prints (Markdown) the figures of docs/registration.md:

1. synthetic multi-lens captures (``pipeline.sim.world.multilens``, 240 x 320, 5 RedEdge bands,
   shifts up to 20 px, rotation up to 1 deg, 1 % scale, perspective, 0.5 px bush parallax;
   textured and low-texture fields): residual misalignment of every band against the known
   homography over a 9 x 12 grid of points (rms and max, px);
2. the real MicaSense RedEdge captures in ../shared/data/micasense-rededge (full resolution,
   1280 x 960): registration time, the weakest quality figures, band-to-band gradient
   correlation against NIR before/after, and the NDVI's false edges (mean |grad NDVI|, the
   red and NIR bands from DN minus black level) before/after;
3. the per-frame alignment cost of the apply pass: ``align_bands`` of a 5 x 960 x 1280
   float32 stack with the real capture's transforms (ms/frame, median of ``--frames``).

``--compare-apply RAW_OUT ALIGNED_OUT`` instead compares the outputs of ``mscal apply
--calibration factory`` without and with ``--registration`` (NDVI false edges, gradient
correlation of each band's reflectance with NIR, over the pixels every band covers).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mscal_core import alignment, homography
from mscal_core import registration as reg
from pipeline.sim.world.multilens import REDEDGE_WAVELENGTHS_NM, multilens_capture

DATA = ROOT.parent / "shared" / "data" / "micasense-rededge"


def synthetic(seeds: int) -> None:
    print("| field | seeds | bands | rms px (median / worst) | max px (worst) | all accepted |")
    print("|---|---|---|---|---|---|")
    for texture, label in ((0.12, "textured"), (0.0, "low texture")):
        rms, mx, ok = [], [], True
        for seed in range(seeds):
            cap = multilens_capture(seed, texture=texture)
            regs = reg.register_stack(cap.dn, cap.reference, wavelengths=REDEDGE_WAVELENGTHS_NM)
            for b, r in enumerate(regs):
                if b == cap.reference:
                    continue
                d = homography.transform_distance(r.homography, cap.homographies[b], cap.dn.shape[1:])
                rms.append(float(np.sqrt(np.mean(d**2))))
                mx.append(float(d.max()))
                ok &= reg.accept(r)
        print(f"| {label} | {seeds} | {len(rms)} | {np.median(rms):.3f} / {max(rms):.3f} | {max(mx):.3f} | {ok} |")


def _edges(red: np.ndarray, nir: np.ndarray, mask: np.ndarray) -> float:
    import cv2

    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.nan_to_num(((nir - red) / (nir + red)).astype(np.float32))
    return float(cv2.magnitude(cv2.Sobel(v, cv2.CV_32F, 1, 0), cv2.Sobel(v, cv2.CV_32F, 0, 1))[mask].mean())


def real(frames: int) -> np.ndarray | None:
    import cv2

    from pipeline.ingest.camera_meta import read_capture_meta
    from pipeline.ingest.tiff import read_raw

    if not (DATA / "IMG_0000_1.tif").is_file():
        print(f"(real data not found in {DATA})")
        return None
    names = ("Blue", "Green", "Red", "NIR", "Red edge")
    last = None
    print("| capture | seconds | paths | min ECC | min inliers | max residual px | gradient corr. vs NIR before -> after (B, G, R, RE) | NDVI |grad| before -> after |")
    print("|---|---|---|---|---|---|---|---|")
    for cap in ("0000", "0001"):
        files = [DATA / f"IMG_{cap}_{b}.tif" for b in range(1, 6)]
        stack = np.stack([read_raw(f) for f in files]).astype(np.float32)
        black = np.array([read_capture_meta(f).black_level for f in files])[:, None, None]
        t0 = time.perf_counter()
        regs = reg.register_stack(stack, 3, wavelengths=REDEDGE_WAVELENGTHS_NM)
        dt = time.perf_counter() - t0
        hs = np.stack([r.homography for r in regs])
        al = alignment.align_bands(stack, hs)
        ok = cv2.erode(np.isfinite(al).all(axis=0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        gc = []
        for b in (0, 1, 2, 4):
            before = reg.gradient_correlation(stack[3], stack[b], ok)
            after = reg.gradient_correlation(al[3], np.nan_to_num(al[b]), ok)
            gc.append(f"{before:.2f}->{after:.2f}")
        e0 = _edges(stack[2] - black[2], stack[3] - black[3], ok)
        e1 = _edges(al[2] - black[2], al[3] - black[3], ok)
        others = [r for r in regs if r.method != "identity"]
        paths = " ".join("-".join(names[i][0] if names[i] != "Red edge" else "E" for i in r.path) for r in others)
        print(f"| IMG_{cap} | {dt:.1f} | {paths} | {min(r.ecc for r in others):.2f} | {min(r.n_inliers for r in others)} | "
              f"{max(r.residual_px for r in others):.2f} | {', '.join(gc)} | {e0:.4f} -> {e1:.4f} |")
        last = hs
        if cap == "0001":
            times = []
            for _ in range(frames):
                t0 = time.perf_counter()
                alignment.align_bands(stack, hs)
                times.append(time.perf_counter() - t0)
            print(f"\nalign_bands, 5 x 960 x 1280 float32, transforms of IMG_0001: "
                  f"median {1e3 * np.median(times):.1f} ms/frame over {frames} frames "
                  f"(min {1e3 * min(times):.1f}, max {1e3 * max(times):.1f})")
    return last


def compare_apply(raw_out: Path, aligned_out: Path) -> None:
    """Outputs of ``mscal apply --calibration factory`` without and with ``--registration``."""
    import cv2
    import xarray as xr

    a, b = (xr.open_zarr(p / "reflectance.zarr") for p in (raw_out, aligned_out))
    names = [str(n) for n in a["band_name"].values]
    nir = names.index("NIR")
    others = [k for k in range(len(names)) if k != nir]
    print(f"| capture | NDVI |grad| unaligned -> aligned | gradient corr. vs NIR unaligned -> aligned ({', '.join(names[k] for k in others)}) | covered |")
    print("|---|---|---|---|")
    for f, frame in enumerate(a["frame"].values):
        ra, rb = a["reflectance"].values[f], b["reflectance"].values[f]
        ok = cv2.erode(np.isfinite(rb).all(axis=0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)

        def edges(nd: np.ndarray) -> float:
            v = np.nan_to_num(nd.astype(np.float32))
            return float(cv2.magnitude(cv2.Sobel(v, cv2.CV_32F, 1, 0), cv2.Sobel(v, cv2.CV_32F, 0, 1))[ok].mean())

        gc = [f"{reg.gradient_correlation(np.nan_to_num(ra[nir]), np.nan_to_num(ra[k]), ok):.2f}->"
              f"{reg.gradient_correlation(np.nan_to_num(rb[nir]), np.nan_to_num(rb[k]), ok):.2f}" for k in others]
        print(f"| {frame} | {edges(a['ndvi'].values[f]):.3f} -> {edges(b['ndvi'].values[f]):.3f} | {', '.join(gc)} | {ok.mean():.1%} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--quick", action="store_true", help="2 seeds, 5 frames (a smoke run)")
    ap.add_argument("--compare-apply", nargs=2, type=Path, metavar=("RAW_OUT", "ALIGNED_OUT"),
                    help="only compare two 'mscal apply --calibration factory' outputs, without and with --registration")
    a = ap.parse_args()
    if a.compare_apply:
        compare_apply(*a.compare_apply)
        return
    if a.quick:
        a.seeds, a.frames = 2, 5
    synthetic(a.seeds)
    print()
    real(a.frames)


if __name__ == "__main__":
    main()
