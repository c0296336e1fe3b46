"""Compare a fitted calibration with the truth of a synthetic session (``truth.npz``).

Used by ``mscal demo``, the round-trip tests and the benchmarks. The flight check applies
Eq. 15 with the fitted calibration to the session's synthetic flight frames and reports,
beside it, the Eq. 16 baseline (divide by the reflector's DN, exposure-normalised).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from mscal_core import metrics
from mscal_core.illumination import eq16_reflectance
from mscal_core.quality import CENSOR_HIGH, CENSOR_LOW, DEFAULT_BOUND, FLAGS, censor_dn, region_median
from mscal_core.reflectance import eq15

from pipeline.calibrate.sweep import read_stack
from pipeline.ingest.session import load_session, read_frame_table
from pipeline.storage.store import dn_flags_of


def panel_labels(names: np.ndarray) -> list[int]:
    """Labels of a synthetic flight's gray panels (material names starting with ``panel``)."""
    return [i for i, n in enumerate(names) if str(n).startswith("panel")]


def evaluate_calibration(session_dir: str | Path, calibration: str | Path | xr.Dataset,
                         flights: bool = True) -> dict[str, Any]:
    """Errors of each fit and (``flights``) of the flight reflectance against the session's truth."""
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
        names = [k[len("flight_"):-len("_exposure_ms")] for k in truth.files
                 if flights and k.startswith("flight_") and k.endswith("_exposure_ms")]
        for flight in names:
            out[f"flight_{flight}"] = evaluate_flight(session_dir, ds, truth, flight)
    return out


def evaluate_flight(session_dir: Path, ds: xr.Dataset, truth: Any, flight: str,
                    reflectance: np.ndarray | None = None, quality: np.ndarray | None = None,
                    calibration_share: bool = False, max_flagged_share: float | None = None) -> dict[str, Any]:
    """Eq. 15 vs Eq. 16 on one synthetic flight: panel reflectance after panel normalisation
    (one scalar per frame), NDVI of vegetation, panel consistency across frames.

    ``reflectance`` (frame, band, y, x) in the order of the flight's frames.csv: score that
    (e.g. apply's own output, NaN where a pixel is flagged) as the Eq. 15 figure instead of
    Eq. 15 computed here from the calibration; only finite pixels count. ``quality``: its
    mask (apply's ``quality``, with the default bound), so that a panel with pixels flagged high
    is taken on its product-limit median, each such pixel above its bound
    (:func:`censor_bounds`, :func:`panel_value`); None: a NaN pixel is left out, except where
    the DN is saturated (Eq. 15 computed here). ``max_flagged_share``: a panel with that share
    of its pixels flagged or more in a band is not scored there (:func:`panel_value`; None:
    :data:`PANEL_MAX_FLAGGED_SHARE`). ``calibration_share``: add ``panel_cv_calibration`` to
    the Eq. 15 and Eq. 16 figures (:func:`calibration_cv` against Eq. 15 with the session's
    true U, V and S on the same DN)."""
    session = load_session(session_dir)
    cam = session.camera
    recs = read_frame_table(session_dir / "flights" / flight)
    dn = read_stack(recs, cam)
    t = np.array([r.effective_exposure for r in recs])
    labels = truth[f"flight_{flight}_labels"]
    names = truth[f"flight_{flight}_material_names"]
    scene = FlightScene(labels=labels, panels=panel_labels(names),
                        panel_rho=np.asarray(truth[f"flight_{flight}_panel_reflectance"], dtype=np.float64),
                        sun=np.asarray(truth[f"flight_{flight}_sun"], dtype=np.float64),
                        vegetation=[i for i, n in enumerate(names) if str(n).startswith("veg")][0],
                        ndvi=truth[f"flight_{flight}_ndvi"],
                        red=cam.band_for_wavelength(cam.index_bands["red"]),
                        nir=cam.band_for_wavelength(cam.index_bands["nir"]))
    given = reflectance is not None
    if reflectance is None:
        sat = int(ds["saturation_dn"].values.min()) if "saturation_dn" in ds else None
        reflectance = eq15(dn, ds["inverse_response"].values, t, ds["vignetting"].values, ds["spectral_factor"].values,
                           saturation_dn=sat)
        if quality is None and sat is not None:
            quality = np.where(dn >= sat, np.uint8(FLAGS["saturated"]), np.uint8(0))
    # Eq. 16 baseline: exposure-normalised DN divided by the reflector's mean exposure-normalised
    # DN per band (the reflector image does not fill the frame, so a per-pixel ratio is not possible).
    rrecs = read_frame_table(session.reflector_dir)
    rdn = read_stack(rrecs[:1], cam)[0].astype(np.float64) / rrecs[0].effective_exposure
    rmask = truth["reflector_gray_mask"][0]
    refl_level = np.array([np.median(rdn[b][rmask]) for b in range(cam.n_bands)])
    rho_s = session.reflector.reflectance.at(cam.wavelengths)
    r16 = np.stack([eq16_reflectance(dn[f] / t[f], refl_level, rho_s) for f in range(len(recs))]).astype(np.float32)
    bounds = None if quality is None or not given else censor_bounds(dn, t, ds, reflectance, quality)
    share = PANEL_MAX_FLAGGED_SHARE if max_flagged_share is None else max_flagged_share
    out = {"frames": len(recs), "eq15": score_flight(reflectance, scene, quality, bounds, share),
           "eq16": score_flight(r16, scene)}
    if calibration_share:
        exact = eq15(dn, truth["inverse_response"], t, truth["vignetting"], truth["spectral_factor"])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio_bounds = None if bounds is None else bounds / exact
        out["eq15"]["panel_cv_calibration"] = calibration_cv(reflectance, exact, scene, quality, ratio_bounds)
        out["eq16"]["panel_cv_calibration"] = calibration_cv(r16, exact, scene)
    return out


def censor_bounds(dn: np.ndarray, t: np.ndarray, ds: xr.Dataset, reflectance: np.ndarray, quality: np.ndarray,
                  bound: float = DEFAULT_BOUND) -> np.ndarray:
    """The least value each pixel of ``reflectance`` (frame, band, y, x) flagged high by
    ``quality`` can have: Eq. 15 with the calibration ``ds`` of the highest trusted DN under its
    reading (:func:`mscal_core.quality.censor_dn` with the flags apply makes with ``bound``), on
    the scale of ``reflectance`` (times the median ratio of ``reflectance`` to Eq. 15 of the
    frame's own DN over the band's valid pixels: 1 for apply's relative output); NaN elsewhere
    and where no trusted DN is under the reading."""
    U, V, S = ds["inverse_response"].values, ds["vignetting"].values, ds["spectral_factor"].values
    sat = int(ds["saturation_dn"].values.min())
    flags = dn_flags_of(ds, sat, bound)
    out = np.full(reflectance.shape, np.nan, np.float32)
    for f in range(len(dn)):
        high = ((quality[f] & CENSOR_HIGH) != 0) & ((quality[f] & CENSOR_LOW) == 0)
        if not high.any():
            continue
        least = eq15(censor_dn(dn[f], flags)[None], U, t[f:f + 1], V, S, saturation_dn=sat)[0]
        own = eq15(dn[f][None], U, t[f:f + 1], V, S, saturation_dn=sat)[0]
        for b in range(dn.shape[1]):
            ok = (quality[f, b] == 0) & np.isfinite(reflectance[f, b]) & np.isfinite(own[b]) & (own[b] > 0)
            if ok.any() and high[b].any():
                scale = float(np.median(reflectance[f, b][ok] / own[b][ok]))
                out[f, b] = np.where(high[b], least[b] * scale, np.nan)
    return out


def calibration_cv(r: np.ndarray, exact: np.ndarray, scene: FlightScene, quality: np.ndarray | None = None,
                   bounds: np.ndarray | None = None) -> float:
    """The calibration's own share of the cross-frame CV: :func:`score_flight`'s
    ``panel_cv_across_frames`` of ``r / exact`` (frame, band, y, x), with ``exact`` Eq. 15 of the
    same DN with the true U, V and S, and no light to divide by.

    Pixel by pixel the two read the same noisy DN, so the noise cancels in the ratio (up to the
    slope of the fitted U against the true one) and what moves a panel's ratio from frame to
    frame is the calibration: V at the panel's place in each frame, U at each frame's exposure.
    ``quality`` as in :func:`score_flight` (a pixel flagged high counts as high in the ratio too),
    ``bounds`` its bounds in the ratio (the reflectance bound over ``exact``).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (r / exact).astype(np.float32)
    flat = replace(scene, sun=np.ones_like(scene.sun))
    return score_flight(ratio, flat, quality, bounds)["panel_cv_across_frames"]


@dataclass(frozen=True)
class FlightScene:
    """What a synthetic flight's truth says about its frames: material label per pixel
    (frame, y, x), which labels are gray panels and their reflectance, the sun's relative
    brightness per frame, the vegetation label with its true NDVI (frame, y, x), and the
    camera's red and NIR bands."""

    labels: np.ndarray
    panels: list[int]
    panel_rho: np.ndarray
    sun: np.ndarray
    vegetation: int
    ndvi: np.ndarray
    red: int
    nir: int


#: A panel or the vegetation counts in a frame only with at least this many finite pixels.
MIN_PANEL_PIXELS, MIN_VEGETATION_PIXELS = 5, 20
#: ... and a panel only when at least this share of it is in the frame (of its largest pixel
#: count in any frame of the flight). A panel cut by the frame's edge to a few pixels measures
#: the noise of those pixels, not the calibration: on varied session 1 with the TRUE U, V and
#: S, the 0.05 panel's 13 pixels in one frame read 0.0532 and the cross-frame CV was 2.2 %.
MIN_PANEL_SHARE = 0.5

#: A panel with this share of its pixels flagged or more in a band is not scored there (its
#: value there is flagged): its DN vary with V across it as well as with the noise, so where
#: the shoulder flag cuts it, the pixels flagged are partly those of highest V, whose values
#: are not above the others', and its censored median reads high (harsh full-size session 3:
#: a 0.9 panel 46 % flagged, 3 % high). Below a tenth the censored median's bias is a small
#: share of one pixel's noise. With each censored pixel's bound (:func:`censor_bounds`) the
#: median is the product-limit one, which V does not bias; a panel cut further still reads its
#: median on the valid pixels just under the cut, where U is least certain (harsh full-size
#: sessions 0-4 scored up to half flagged, as apply's own panel normalisation keeps,
#: :data:`mscal_core.quality.MAX_FLAGGED_SHARE`: panels 0.0037-0.0103 against 0.0036-0.0060).
PANEL_MAX_FLAGGED_SHARE = 0.1


def panel_value(values: np.ndarray, quality: np.ndarray, censor_at: np.ndarray | None = None,
                max_flagged_share: float = PANEL_MAX_FLAGGED_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """One panel's value per band from its pixels' reflectance ``values`` (band, n) and their
    ``quality`` (the shape of ``values``, or broadcastable to it), and per band how it was taken.

    The mean of the valid pixels (``quality`` 0, finite) where no pixel of the band is flagged
    high; where some are (a bit of :data:`mscal_core.quality.CENSOR_HIGH`: saturated, on the
    shoulder, above the sweep), the censored median of
    :func:`mscal_core.quality.region_median` (the flagged pixels counted as above it: their
    values are missing because they read high, so a mean of the others would be biased low).
    NaN where ``max_flagged_share`` (:data:`PANEL_MAX_FLAGGED_SHARE`, a tenth) of the band's
    pixels or more are flagged, or fewer than
    :data:`MIN_PANEL_PIXELS` are valid. Pixels with another flag are left out of either.
    With ``censor_at`` (the shape of ``values``: each pixel's bound if censored high,
    :func:`censor_bounds`), the product-limit median of ``region_median`` with those bounds.

    Why the mean: a gray panel is one reflectance under one light (the scene's labels keep only
    the pixels no edge reaches through the lens's blur), so its pixels differ by the sensor's
    noise alone, independent and near Gaussian, where the mean has the smallest spread of
    any estimator, ``sigma / sqrt(N)``, and the median's is ``sqrt(pi / 2) ~ 1.25`` times that.
    The median is also tied to the DN's integer steps: a dark panel ~30 DN above black reads
    on a few DN levels 3 % apart, and its median moves by a share of a step when the response
    changes slightly. On varied session 0 with the true U, V and S (the floor), the darkest
    panel's cross-frame CV over the 25 bands was 0.55 % RMS on the median, 0.44 % on the mean
    (from the generator's shot and read noise, ``sigma / sqrt(N)``: 0.46 %); with mscal's
    calibration the median's worst band read 1.02 % where the mean's read 0.33 %.
    MicaSense's own panel code takes the mean of the panel's interior as well.

    Returns
    -------
    tuple of numpy.ndarray
        float64 ``(band,)`` values; int ``(band,)`` states: 0 mean of valid pixels, 1 censored
        median, 2 flagged (NaN).
    """
    vals = np.asarray(values, dtype=np.float64)
    qs = np.broadcast_to(np.asarray(quality), vals.shape)
    valid = (qs == 0) & np.isfinite(vals)
    n_valid = np.count_nonzero(valid, axis=-1)
    high = np.any(qs & CENSOR_HIGH, axis=-1)
    med = region_median(vals, qs, max_flagged_share,
                        censor_at=None if censor_at is None else np.broadcast_to(censor_at, vals.shape))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(valid, vals, 0.0).sum(axis=-1) / n_valid
    out = np.where(np.isfinite(med) & ~high, mean, med)
    out[n_valid < MIN_PANEL_PIXELS] = np.nan
    state = np.where(np.isfinite(out), np.where(high, 1, 0), 2)
    return out, state


def _panel_values(r: np.ndarray, q: np.ndarray, mask: np.ndarray, full: int = 0, bounds: np.ndarray | None = None,
                  max_flagged_share: float = PANEL_MAX_FLAGGED_SHARE) -> tuple[np.ndarray | None, np.ndarray]:
    """:func:`panel_value` of the panel under ``mask`` in ``r`` (band, y, x) with its quality
    ``q`` (``bounds``: the censored pixels' bounds, or None; ``max_flagged_share``). ``(None, ...)`` when the mask has fewer than :data:`MIN_PANEL_PIXELS` pixels or
    :data:`MIN_PANEL_SHARE` of ``full`` (the panel cut by the frame: not counted; state -1) or
    every band is flagged."""
    nb = r.shape[0]
    n = int(mask.sum())
    if n < max(MIN_PANEL_PIXELS, MIN_PANEL_SHARE * full):
        return None, np.full(nb, -1)
    val, state = panel_value(r[:, mask], q[:, mask], None if bounds is None else bounds[:, mask], max_flagged_share)
    return (None if np.isnan(val).all() else val), state


def score_flight(r: np.ndarray, scene: FlightScene, quality: np.ndarray | None = None,
                 bounds: np.ndarray | None = None, max_flagged_share: float = PANEL_MAX_FLAGGED_SHARE
                 ) -> dict[str, float]:
    """Panel error, cross-frame CV and vegetation NDVI error of reflectance ``r`` (frame,
    band, y, x) against ``scene``, and how many panel values (one per panel, frame and band)
    were taken on a censored median or not at all because the panel is flagged in that band.

    A panel's value in a band is :func:`panel_value`: the mean of its valid pixels, or, where
    some of them are flagged high (``quality`` bits of :data:`mscal_core.quality.CENSOR_HIGH`:
    saturated, shoulder, above the sweep), its median with those counted as above it; a panel
    a tenth flagged or more in a band counts as flagged there and is not scored in that band
    (:func:`mscal_core.quality.region_median`: the valid pixels alone of a panel the shoulder
    flag cuts are those whose noise read low). ``quality`` None:
    NaN pixels are left out (flagged, not censored). Each frame is first normalised by one
    scalar: true / measured reflectance of the brightest panel flagged in no band (the white
    panel unless it is flagged), median over bands: the light's brightness B, which Eq. 15
    leaves out. Nor does a panel the frame cuts to less than :data:`MIN_PANEL_SHARE` of it
    count. ``bounds`` (the shape of ``r``, or None): each censored pixel's bound
    (:func:`censor_bounds`), for the product-limit median; ``max_flagged_share``: the share of a
    panel's pixels flagged from which it is not scored (:func:`panel_value`)."""
    n = r.shape[0]
    if quality is None:
        quality = np.where(np.isfinite(r), np.uint8(0), np.uint8(FLAGS["no_value"]))
    order = [p for _, p in sorted(zip(scene.panel_rho, scene.panels), reverse=True)]
    rho_of = dict(zip(scene.panels, scene.panel_rho))
    full = {p: max(int(np.count_nonzero(scene.labels[f] == p)) for f in range(n)) for p in scene.panels}
    def fb(f: int) -> np.ndarray | None:
        return None if bounds is None else bounds[f]

    k = np.full(n, np.nan)
    for f in range(n):
        for p in order:
            val, _ = _panel_values(r[f], quality[f], scene.labels[f] == p, full[p], fb(f), max_flagged_share)
            if val is not None and np.isfinite(val).all():
                k[f] = float(np.median(rho_of[p] / val))
                break
    panel_err, cv, veg_ndvi_err = [], [], []
    censored = flagged = 0
    for p in scene.panels:
        per_frame = []
        for f in range(n):
            val, state = _panel_values(r[f], quality[f], scene.labels[f] == p, full[p], fb(f), max_flagged_share)
            censored += int(np.count_nonzero(state == 1))
            flagged += int(np.count_nonzero(state == 2))
            if val is None or not np.isfinite(k[f]):
                continue
            panel_err.append(float(np.nanmax(np.abs(val * k[f] - rho_of[p]))))
            per_frame.append(val / scene.sun[f])
        if len(per_frame) >= 2:
            arr = np.array(per_frame)
            per_band = [metrics.coefficient_of_variation(arr[:, b]) for b in range(arr.shape[1])
                        if np.isfinite(arr[:, b]).sum() >= 2]
            if per_band:
                cv.append(max(per_band))
    for f in range(n):
        m = scene.labels[f] == scene.vegetation
        with np.errstate(divide="ignore", invalid="ignore"):
            nd = (r[f, scene.nir] - r[f, scene.red]) / (r[f, scene.nir] + r[f, scene.red])
        ok = m & np.isfinite(nd)
        if ok.sum() < MIN_VEGETATION_PIXELS:
            continue
        veg_ndvi_err.append(abs(float(np.mean(nd[ok]) - np.nanmean(scene.ndvi[f][ok]))))
    return {
        "panel_abs_error": float(max(panel_err)) if panel_err else float("nan"),
        "panel_cv_across_frames": float(max(cv)) if cv else float("nan"),
        "vegetation_ndvi_error": float(max(veg_ndvi_err)) if veg_ndvi_err else float("nan"),
        "panels_censored": float(censored),
        "panels_flagged": float(flagged),
    }
