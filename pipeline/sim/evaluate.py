"""Compare a fitted calibration with the truth of a synthetic session (``truth.npz``).

Used by ``mscal demo``, the round-trip tests and the benchmarks. The flight check applies
Eq. 15 with the fitted calibration to the session's synthetic flight frames and reports,
beside it, the Eq. 16 baseline (divide by the reflector's DN, exposure-normalised).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from mscal_core import metrics
from mscal_core.illumination import eq16_reflectance
from mscal_core.reflectance import eq15

from pipeline.calibrate.sweep import read_stack
from pipeline.ingest.session import load_session, read_frame_table


def _panel_labels(names: np.ndarray) -> list[int]:
    return [i for i, n in enumerate(names) if str(n).startswith("panel")]


def evaluate_calibration(session_dir: str | Path, calibration: str | Path | xr.Dataset) -> dict[str, Any]:
    """Errors of each fit and of the flight reflectance against the session's truth."""
    session_dir = Path(session_dir)
    truth = np.load(session_dir / "truth.npz")
    ds = calibration if isinstance(calibration, xr.Dataset) else xr.open_zarr(calibration).load()
    out: dict[str, Any] = {}
    U, Ut = ds["inverse_response"].values, truth["inverse_response"]
    resp = [metrics.response_error(U[b], Ut[b]) for b in range(U.shape[0])]
    out["response_max_error"] = float(max(resp))
    out["response_median_error"] = float(np.median(resp))
    if "vignetting" in ds:
        V, Vt = ds["vignetting"].values, truth["vignetting"]
        obs = ds["vignetting_observed"].values if "vignetting_observed" in ds else None
        out["vignetting_rms_error"] = float(max(metrics.vignetting_rms(V[b], Vt[b]) for b in range(V.shape[0])))
        if obs is not None:
            out["vignetting_rms_error_observed"] = float(
                max(metrics.vignetting_rms(V[b], Vt[b], obs[b]) for b in range(V.shape[0]))
            )
            out["vignetting_observed_fraction"] = float(obs.mean())
    if "spectral_factor" in ds:
        out["spectral_factor_max_error"] = metrics.spectral_factor_error(
            ds["spectral_factor"].values, truth["spectral_factor"]
        )
        flights = [k[len("flight_"):-len("_exposure_ms")] for k in truth.files
                   if k.startswith("flight_") and k.endswith("_exposure_ms")]
        for flight in flights:
            out[f"flight_{flight}"] = evaluate_flight(session_dir, ds, truth, flight)
    return out


def evaluate_flight(session_dir: Path, ds: xr.Dataset, truth: Any, flight: str) -> dict[str, Any]:
    """Eq. 15 vs Eq. 16 on one synthetic flight: panel reflectance after white-panel
    normalisation (one scalar per frame), NDVI of vegetation, panel consistency across frames."""
    session = load_session(session_dir)
    cam = session.camera
    recs = read_frame_table(session_dir / "flights" / flight)
    dn = read_stack(recs, cam)
    t = np.array([r.effective_exposure for r in recs])
    labels = truth[f"flight_{flight}_labels"]
    names = truth[f"flight_{flight}_material_names"]
    panel_rho = truth[f"flight_{flight}_panel_reflectance"]
    sun = truth[f"flight_{flight}_sun"]
    panels = _panel_labels(names)
    white = panels[int(np.argmax(panel_rho))]
    veg = [i for i, n in enumerate(names) if str(n).startswith("veg")][0]
    red, nir = cam.band_for_wavelength(cam.index_bands["red"]), cam.band_for_wavelength(cam.index_bands["nir"])

    r15 = eq15(dn, ds["inverse_response"].values, t, ds["vignetting"].values, ds["spectral_factor"].values,
               saturation_dn=int(ds["saturation_dn"].values.min()) if "saturation_dn" in ds else None)
    # Eq. 16 baseline: exposure-normalised DN divided by the reflector's mean exposure-normalised
    # DN per band (the reflector image does not fill the frame, so a per-pixel ratio is not possible).
    rrecs = read_frame_table(session.reflector_dir)
    rdn = read_stack(rrecs[:1], cam)[0].astype(np.float64) / rrecs[0].effective_exposure
    rmask = truth["reflector_gray_mask"][0]
    refl_level = np.array([np.median(rdn[b][rmask]) for b in range(cam.n_bands)])
    rho_s = session.reflector.reflectance.at(cam.wavelengths)
    r16 = np.stack([eq16_reflectance(dn[f] / t[f], refl_level, rho_s) for f in range(len(recs))]).astype(np.float32)

    def score(r: np.ndarray) -> dict[str, float]:
        panel_err, cv, veg_ndvi_err = [], [], []
        per_frame_k = []
        for f in range(len(recs)):
            m = labels[f] == white
            if m.sum() < 5:
                per_frame_k.append(np.nan)
                continue
            per_band = np.array([np.nanmedian(r[f, b][m]) for b in range(cam.n_bands)])
            per_frame_k.append(float(np.nanmedian(panel_rho.max() / per_band)))
        k = np.array(per_frame_k)
        for p, rho in zip(panels, panel_rho):
            means = []
            for f in range(len(recs)):
                m = labels[f] == p
                if m.sum() < 5 or not np.isfinite(k[f]):
                    continue
                vals = np.array([np.nanmedian(r[f, b][m]) for b in range(cam.n_bands)])
                panel_err.append(np.max(np.abs(vals * k[f] - rho)))
                means.append(vals / sun[f])
            if len(means) >= 2:
                means = np.array(means)
                cv.append(max(metrics.coefficient_of_variation(means[:, b]) for b in range(cam.n_bands)))
        for f in range(len(recs)):
            m = labels[f] == veg
            if m.sum() < 20:
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                nd = (r[f, nir] - r[f, red]) / (r[f, nir] + r[f, red])
            true_nd = truth[f"flight_{flight}_ndvi"][f]
            veg_ndvi_err.append(abs(float(np.nanmean(nd[m]) - np.nanmean(true_nd[m]))))
        return {
            "panel_abs_error": float(max(panel_err)) if panel_err else float("nan"),
            "panel_cv_across_frames": float(max(cv)) if cv else float("nan"),
            "vegetation_ndvi_error": float(max(veg_ndvi_err)) if veg_ndvi_err else float("nan"),
        }

    return {"frames": len(recs), "eq15": score(r15), "eq16": score(r16)}
