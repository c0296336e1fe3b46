"""Does resampling a snapshot mosaic's bands to its centre position (``--centre-bands``) help?

    .venv/bin/python bench/bench_mosaic_offsets.py [--seeds 2] [--frames 3]

The Ximea 5 x 5 camera's band at mosaic (r, c) samples its pixel (i, j) at band-grid point
``(j + c/5, i + r/5)``: up to 0.4 band-grid pixels (~2.3 cm at 25 m) from the centre band
(2, 2). NDVI mixes 670 nm (mosaic (4, 4)) and 803 nm ((1, 2)), 0.4 px apart in y and x.

For synthetic flight frames (``pipeline.sim.world.scene.flight_frames``, noise and 10-bit
quantisation included) the Eq. 15 reflectance is computed with the TRUE calibration (so only
the band geometry differs), then NDVI

- as the pipeline gives it (each band at its own sample positions), and
- after ``mscal_core.alignment.shift_bands`` (bicubic, exact for quadratics) to the centre,

against the true NDVI of the scene AT THE CENTRE POSITION (the footprint of the centre band's
sensor pixel, rendered from the same pose). Reported: median and 95th percentile of
|NDVI error| over all pixels, over pixels near a vegetation/soil edge (the true NDVI's
gradient above 0.1 per pixel) and over flat pixels.

Vignetting: the fit (Eq. 8-10) already maps every band pixel to the reflector plane at that
band's own sample position (``geometry.pixels_to_plane(..., offset)``). Measured anyway on a
small synthetic session (``--vignetting``): the vignetting stage as it is, against the same
stage fed with centred bands (``shift_bands``, rounded to DN, border pixels kept as they were)
and told every band samples the centre position; rms error of V against the truth per band
(max and median over the 25 bands, pixels the views observed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mscal_core.alignment import mosaic_centre_offsets, shift_bands
from mscal_core.reflectance import eq15
from pipeline.sim.world.scene import (
    DEFAULT_PANELS,
    NDVI_NIR_NM,
    NDVI_RED_NM,
    FieldScene,
    Pose,
    flight_frames,
    make_truth,
    render,
)


def _ndvi(refl: np.ndarray, red: int, nir: int) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return (refl[nir] - refl[red]) / (refl[nir] + refl[red])


def measure(seeds: int, frames: int) -> None:
    rows = {"as is": [], "centred": []}
    masks = []
    for seed in range(seeds):
        truth = make_truth(seed)
        cam = truth.camera
        red, nir = cam.band_index(NDVI_RED_NM), cam.band_index(NDVI_NIR_NM)
        fs = flight_frames(truth, seed=seed, n_frames=frames)
        centre = cam.n_bands // 2
        off = mosaic_centre_offsets(cam.pattern_shape)
        for k in range(frames):
            sun = float(fs.truth["sun"][k])
            refl = eq15(fs.dn[k], truth.inverse_response, fs.exposure_ms[k], truth.vignetting,
                        truth.spectral_factor, brightness=sun, saturation_dn=truth.dn_max)
            scene = FieldScene(cam.wavelengths, DEFAULT_PANELS, sun, field_seed=seed)
            rend = render(cam, Pose(fs.truth["rvec"][k], fs.truth["tvec"][k]), scene, supersample=3)
            true_c = np.einsum("kbhw,kb->bhw", rend.channels[:, [centre] * cam.n_bands], scene.reflectance) / sun
            nd_true = _ndvi(true_c, red, nir).astype(np.float32)
            g = cv2.magnitude(cv2.Sobel(nd_true, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(nd_true, cv2.CV_32F, 0, 1, ksize=1))
            edge = g > 0.1
            inner = np.zeros_like(edge)
            inner[3:-3, 3:-3] = True
            masks.append((edge & inner, ~edge & inner))
            for name, stack in (("as is", refl), ("centred", shift_bands(refl, off))):
                rows[name].append(np.abs(_ndvi(stack, red, nir) - nd_true))
    print("| NDVI error vs truth at the centre position | all: median / p95 | edges: median / p95 | flat: median / p95 |")
    print("|---|---|---|---|")
    for name, errs in rows.items():
        cells = []
        for sel in (None, 0, 1):
            v = np.concatenate([(e[m[sel]] if sel is not None else e[m[0] | m[1]]).ravel() for e, m in zip(errs, masks)])
            v = v[np.isfinite(v)]
            cells.append(f"{np.median(v):.4f} / {np.percentile(v, 95):.4f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    n_edge = sum(int(m[0].sum()) for m in masks)
    n_all = sum(int((m[0] | m[1]).sum()) for m in masks)
    print(f"\n{seeds} seed(s) x {frames} frame(s); edge pixels {n_edge} of {n_all} ({100 * n_edge / n_all:.1f} %)")


def vignetting_fit(seed: int) -> None:
    import tempfile

    import pipeline.calibrate.sweep as sweep
    import pipeline.calibrate.views as views
    import pipeline.calibrate.vignetting_stage as vstage
    from mscal_core import metrics
    from pipeline.ingest.session import load_session
    from pipeline.sim.synth import write_session

    with tempfile.TemporaryDirectory() as tmp:
        session_dir = write_session(Path(tmp) / "s", seed=seed, size="small")
        truth = np.load(session_dir / "truth.npz")
        session = load_session(session_dir)
        U = truth["inverse_response"]
        sat = np.full(U.shape[0], 2 ** int(truth["bits"]) - 1)
        results = {}
        # the frames are read by sweep.read_stack; the band offsets are used by the marker
        # search (views) and by the vignetting fit's band views (vignetting_stage)
        plain_read, plain_offsets = sweep.read_bands, views.camera_offsets
        off = mosaic_centre_offsets((5, 5))

        def centred_read(rec, camera):
            dn = plain_read(rec, camera)
            shifted = shift_bands(dn.astype(np.float64), off)
            return np.where(np.isfinite(shifted), np.clip(np.round(shifted), 0, camera.dn_max), dn).astype(np.uint16)

        for name in ("as is", "centred"):
            if name == "centred":
                sweep.read_bands = centred_read
                views.camera_offsets = vstage.camera_offsets = (
                    lambda camera: np.tile(plain_offsets(camera)[12], (camera.n_bands, 1)))
            try:
                fits, _ = vstage.fit_vignetting_frames(session, U, sat)
            finally:
                sweep.read_bands = plain_read
                views.camera_offsets = vstage.camera_offsets = plain_offsets
            errs = [metrics.vignetting_rms(f.vignetting, truth["vignetting"][b], f.observed) for b, f in enumerate(fits)]
            results[name] = errs
        print("| vignetting rms error vs truth (observed pixels) | max over bands | median over bands |")
        print("|---|---|---|")
        for name, errs in results.items():
            print(f"| {name} | {max(errs):.4f} | {np.median(errs):.4f} |")
        print(f"\nsmall synthetic session, seed {seed}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--vignetting", action="store_true", help="also the vignetting fit on a small session (~30 s)")
    a = ap.parse_args()
    measure(a.seeds, a.frames)
    if a.vignetting:
        print()
        vignetting_fit(0)


if __name__ == "__main__":
    main()
