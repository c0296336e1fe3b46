"""The illumination stage (Eq. 11-14) on the small synthetic session: which reflector pixels it
takes when the vignetting fit filled part of V."""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.calibrate.illumination_stage import fit_illumination_frames
from pipeline.ingest.session import load_session


def _s_error(s: np.ndarray, s_true: np.ndarray) -> float:
    ratio = s / s_true
    return float(np.max(np.abs(ratio / np.median(ratio) - 1.0)))


def test_s_is_taken_where_v_was_observed(small) -> None:
    """V right on the left part of the grid and off by -5..+5 % band by band elsewhere (what
    a radial fill extrapolated from few views does): S from every reflector pixel takes that
    error band by band; with ``vignetting_observed`` marking the left part, S is as with the
    true V."""
    session_dir, calib = small
    truth = np.load(session_dir / "truth.npz")
    ds = xr.open_zarr(calib).load()
    session = load_session(session_dir)
    u, sat = ds["inverse_response"].values, ds["saturation_dn"].values
    v_true = truth["vignetting"]
    n_bands, h, w = v_true.shape
    seen = np.zeros((h, w), dtype=bool)
    seen[:, : int(0.55 * w)] = True
    off = 1.0 + 0.05 * np.sin(np.arange(n_bands) * 2.1)[:, None, None]
    v_filled = np.where(seen[None], v_true, v_true * off)
    observed = np.broadcast_to(seen, v_true.shape)
    s_true = truth["spectral_factor"]

    true_fit = fit_illumination_frames(session, u, sat, v_true)
    plain_fit = fit_illumination_frames(session, u, sat, v_filled)
    kept_fit = fit_illumination_frames(session, u, sat, v_filled, vignetting_observed=observed)
    exact = _s_error(true_fit.fit.spectral_factor, s_true)
    plain = _s_error(plain_fit.fit.spectral_factor, s_true)
    kept = _s_error(kept_fit.fit.spectral_factor, s_true)
    print(f"S error: true V {exact:.4f}, V filled wrong {plain:.4f}, observed pixels only {kept:.4f}")
    assert plain > 0.02
    assert kept < exact + 0.003 and kept < 0.01
    # B, each image's brightness and the reflector pixels are still every pixel's: the images'
    # brightness ratio (the QA report's exposure check) is the one the true V gives
    fraction = kept_fit.report.residuals["spectral_factor_pixel_fraction"]
    print(f"S from {fraction:.1%} of the reflector pixels")
    assert 0.1 < fraction < 0.9
    assert true_fit.report.residuals["spectral_factor_pixel_fraction"] == 1.0
    assert kept_fit.report.residuals["reflector_pixels"] == true_fit.report.residuals["reflector_pixels"]
    ib_true = np.asarray(true_fit.report.residuals["image_brightness"])
    ib_kept = np.asarray(kept_fit.report.residuals["image_brightness"])
    spread_true, spread_kept = ib_true.max() / ib_true.min(), ib_kept.max() / ib_kept.min()
    assert abs(spread_kept / spread_true - 1.0) < 0.01
    maps_true, maps_kept = true_fit.brightness_maps, kept_fit.brightness_maps
    assert np.array_equal(np.isfinite(maps_true), np.isfinite(maps_kept))
    # too few observed reflector pixels (fewer than MIN_REFLECTOR_PIXELS): all of them, as before
    none = np.zeros_like(observed)
    fallback = fit_illumination_frames(session, u, sat, v_filled, vignetting_observed=none).fit.spectral_factor
    assert _s_error(fallback, s_true) == plain
