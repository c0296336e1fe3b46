"""Plots of a calibration store (response, vignetting, coverage, S, light over time,
reflector brightness and correction) and its warnings (:func:`calibration_warnings`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import xarray as xr
from mscal_core.illumination import colour_change, split_level
from mscal_core.reflectance import eq15

from pipeline.products.report.figures import band_titles, few_ticks, image_axes, panel_figure
from pipeline.products.report.inputs import FlightResults
from pipeline.products.report.thresholds import (
    CAPTURE_COLOUR_CHANGE_MAX,
    ILLUMINATION_RESIDUAL_RMS_MAX,
    MARKER_MISSING_FRACTION_MAX,
    MIN_REFLECTOR_PIXELS,
    REFLECTOR_BRIGHTNESS_RATIO_MAX,
    RESPONSE_RESIDUAL_RMS_DN_MAX,
    SATURATED_FRACTION_MAX,
    SWEEP_COVERAGE_MIN,
    VIGNETTING_OBSERVED_MIN,
    VIGNETTING_RESIDUAL_RMS_MAX,
    QAWarning,
)

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- calibration plots


def stage_results(ds: xr.Dataset, stage: str) -> dict[str, Any]:
    return dict(ds.attrs.get(stage) or {})


def stage_residuals(ds: xr.Dataset, stage: str) -> dict[str, Any]:
    return dict(stage_results(ds, stage).get("residuals") or {})


def plot_inverse_response(ds: xr.Dataset) -> Figure:
    """Inverse response U(k) per band (paper Fig. 5): solid where the sweep observed DN,
    dotted where U is extrapolated; black level and saturation marked; fit rms in the title."""
    U = ds["inverse_response"].values
    k = np.arange(U.shape[1])
    res = stage_residuals(ds, "response")
    observed = res.get("observed_dn") or [[0, U.shape[1] - 1]] * U.shape[0]
    rms = res.get("residual_rms_dn") or [float("nan")] * U.shape[0]
    black = ds["black_level"].values if "black_level" in ds else np.zeros(U.shape[0])
    sat = ds["saturation_dn"].values if "saturation_dn" in ds else np.full(U.shape[0], U.shape[1] - 1)
    fig, axes = panel_figure(U.shape[0])
    for b, (ax, title) in enumerate(zip(axes, band_titles(ds))):
        lo, hi = int(observed[b][0]), int(observed[b][1])
        inside = (k >= lo) & (k <= hi)
        ax.plot(k, np.where(inside, U[b], np.nan), color="C0", lw=1.2)
        ax.plot(k, np.where(inside, np.nan, U[b]), color="C0", lw=1.0, ls=":")
        ax.axvspan(lo, hi, color="C2", alpha=0.12)
        ax.axvline(float(black[b]), color="0.4", lw=0.6)
        ax.axvline(float(sat[b]), color="C3", lw=0.6)
        ax.set_title(f"{title}  rms {float(rms[b]):.1f} DN", fontsize=7)
        few_ticks(ax, (0, len(k) // 2, len(k) - 1))
        if "response_residual" in ds:  # the fit's residual along the DN axis, on its own scale
            twin = ax.twinx()
            twin.set_label("<twin>")  # not a panel of its own
            twin.plot(ds["dn_bin"].values, ds["response_residual"].values[b], color="C1", lw=0.8,
                      marker=".", ms=2, label="<residual>")
            twin.tick_params(labelsize=5, colors="C1")
            twin.set_ylim(bottom=0)
    fig.suptitle("Inverse response U(k) (Eq. 5-7): shaded = DN observed in the sweep, "
                 "dotted = extrapolated, red = saturation, orange = rms fit residual per DN bin (DN, right axis)",
                 fontsize=9)
    return fig


def _shared_image_grid(stack: np.ndarray, titles: Sequence[str], suptitle: str, cmap: str,
                       vmin: float, vmax: float, label: str) -> Figure:
    fig, axes = panel_figure(len(stack), panel_in=2.2, extra_w=0.8)
    im = None
    for ax, img, title in zip(axes, stack, titles):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=7)
        image_axes(ax)
    if im is not None:
        right = fig.subplotpars.right
        cax = fig.add_axes((right + 0.01, 0.2, 0.012, 0.6), label="<colorbar>")  # as matplotlib labels its own
        fig.colorbar(im, cax=cax, label=label)
    fig.suptitle(suptitle, fontsize=9)
    return fig


def plot_vignetting(ds: xr.Dataset) -> Figure:
    """Vignetting V per band on one shared colour scale (paper Fig. 6)."""
    V = ds["vignetting"].values
    lo = float(np.nanpercentile(V, 0.5))
    return _shared_image_grid(V, band_titles(ds), "Vignetting V (Eq. 8-10), max 1 per band, shared scale",
                              "viridis", lo, 1.0, "V")


def plot_coverage(ds: xr.Dataset) -> Figure:
    """How many views saw each pixel in the vignetting fit (``vignetting_count``), per band,
    shared scale; blank where no view saw it (V is a smooth fill there)."""
    count = ds["vignetting_count"].values.astype(np.float32)
    count[count == 0] = np.nan
    top = float(np.nanmax(count)) if np.isfinite(count).any() else 1.0
    return _shared_image_grid(count, band_titles(ds), "Coverage: views seeing each pixel (blank = none)",
                              "magma", 0.0, max(top, 1.0), "views")


def plot_spectral_factor(ds: xr.Dataset) -> Figure:
    """Spectral factor S against wavelength (paper Fig. 1b)."""
    wl = ds["wavelength"].values.astype(float)
    S = ds["spectral_factor"].values.astype(float)
    order = np.argsort(wl)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 3.2), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(wl[order], S[order], "o-", color="C1", ms=4)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("S")
    ax.grid(alpha=0.3)
    ax.set_title("Spectral factor S(λ) (Eq. 11-14)", fontsize=9)
    return fig


def _seconds(times: np.ndarray) -> np.ndarray:
    t = np.asarray(times).astype("datetime64[ns]")
    return np.where(np.isnat(t), np.nan, t.astype(np.int64) / 1e9)


def plot_light_over_time(ds: xr.Dataset, flights: Sequence["FlightResults"] = ()) -> Figure:
    """The light over the session: above, S of every band at each reflector capture
    relative to the first capture's; below, the brightness level of each capture and, for
    flights applied with light varying in time, of each frame; every flight frame's time is
    marked (ticks at the bottom of both panels). Time in minutes from the first capture."""
    s = ds["capture_spectral_factor"].values.astype(float)
    tc = _seconds(ds["capture_time"].values)
    level = ds["capture_level"].values.astype(float)
    names = [str(n) for n in ds["capture_name"].values]
    t0 = float(np.nanmin(tc)) if np.isfinite(tc).any() else 0.0
    x = (tc - t0) / 60.0 if np.isfinite(tc).all() else np.arange(tc.size, dtype=float)
    import matplotlib
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 5.0), layout="constrained")
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    wl = ds["wavelength"].values.astype(float)
    cmap = matplotlib.colormaps["turbo"]
    span = max(float(wl.max() - wl.min()), 1.0)
    for b in np.argsort(wl):
        ax1.plot(x, 100.0 * (s[:, b] / s[0, b] - 1.0), "o-", ms=3, lw=0.8,
                 color=cmap((wl[b] - wl.min()) / span), label=f"{wl[b]:.0f} nm" if b in (int(np.argmin(wl)), int(np.argmax(wl))) else None)
    ax1.set_ylabel("S(λ) / S(λ, first) - 1 (%)")
    ax1.set_title("Spectral factor of each band at each reflector capture", fontsize=9)
    ax2.plot(x, level / level[0], "s", color="k", ms=6, label="reflector captures")
    for n, xi, li in zip(names, x, level / level[0]):
        ax2.annotate(n, (xi, li), textcoords="offset points", xytext=(4, 4), fontsize=7)
    for k, f in enumerate(flights):
        ft = _seconds(f.reflectance["time"].values)
        if not np.isfinite(ft).any():
            continue
        fx = (ft - t0) / 60.0
        colour = f"C{k % 10}"
        if "illumination_level" in f.reflectance.coords:
            ax2.plot(fx, f.reflectance["illumination_level"].values / level[0], ".", color=colour, ms=4,
                     label=f"{f.name}: frames")
        for ax in (ax1, ax2):
            ax.plot(fx, np.zeros_like(fx), "|", color=colour, ms=10, transform=ax.get_xaxis_transform(),
                    label=f"{f.name}: frame times" if ax is ax1 else None)
    ax2.set_ylabel("brightness level / first capture's")
    ax2.set_xlabel("minutes from the first capture" if np.isfinite(tc).all() else "capture")
    ax2.set_title("Brightness level (geometric mean of S over the bands)", fontsize=9)
    for ax in (ax1, ax2):
        ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    return fig


def reflector_image_names(ds: xr.Dataset) -> list[str]:
    if "reflector_file" in ds.coords:
        return [str(v) for v in ds["reflector_file"].values]
    return [str(i) for i in range(ds.sizes.get("reflector_image", 0))]


def plot_brightness(ds: xr.Dataset) -> Figure:
    """Reflector brightness B(x) of each reflector image (paper Fig. 7e/f), shared scale."""
    B = ds["reflector_brightness"].values
    lo, hi = np.nanpercentile(B, [1, 99]) if np.isfinite(B).any() else (0.0, 2.0)
    names = reflector_image_names(ds)
    return _shared_image_grid(B, names, "Reflector brightness B(x) (Eq. 14), median 1", "inferno",
                              float(lo), float(hi), "B")


def reflector_corrections(ds: xr.Dataset) -> list[dict[str, Any]]:
    """Per reflector image k, at the stored band: Eq. 15 ``U(I)/(t V S B)`` on its reflector
    pixels, and the Eq. 16 baseline: image k divided per pixel by the next reflector image
    (exposure-normalised DN ratio times R_s, on pixels that are reflector in both). The true
    reflectance is R_s everywhere, so every structure in either map is an artefact; ``spread``
    is (p95 - p5) / median. With one reflector image the baseline divides it by itself."""
    dn = ds["reflector_dn"].values
    B = ds["reflector_brightness"].values
    t = ds["reflector_exposure_ms"].values.astype(float)
    b = int(ds["reflector_dn"].attrs.get("band", 0))
    U, V, S = (ds["inverse_response"].values[b], ds["vignetting"].values[b], ds["spectral_factor"].values[b])
    if "reflector_capture" in ds.coords and "capture_spectral_factor" in ds:  # each image under its capture's light
        S_of = ds["capture_spectral_factor"].values[ds["reflector_capture"].values, b]
    else:
        S_of = np.full(dn.shape[0], S)
    sat = int(ds["saturation_dn"].values[b]) if "saturation_dn" in ds else None
    out = []
    n = dn.shape[0]
    for k in range(n):
        mask = np.isfinite(B[k])
        r15 = eq15(dn[k][None], U, t[k], V[None], np.array([S_of[k]]), np.where(mask, B[k], np.nan)[None],
                   saturation_dn=sat)[0]
        r15 = np.where(mask, r15, np.nan)
        ref = (k + 1) % n
        both = mask & np.isfinite(B[ref])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = (dn[k] / t[k]) / (dn[ref].astype(float) / t[ref])
        rho = float(np.nanmedian(r15))  # Eq. 15 is relative: scale both to the same median
        r16 = np.where(both & np.isfinite(ratio), ratio, np.nan)
        if np.isfinite(r16).any():
            r16 = r16 / np.nanmedian(r16) * rho
        out.append({"image": k, "reference": ref, "band": b, "eq15": r15, "eq16": r16,
                    "eq15_spread": _spread(r15), "eq16_spread": _spread(r16)})
    return out


def _spread(r: np.ndarray) -> float:
    v = r[np.isfinite(r)]
    if v.size < 10:
        return float("nan")
    p5, p50, p95 = np.percentile(v, [5, 50, 95])
    return float((p95 - p5) / p50) if p50 > 0 else float("nan")


def plot_reflector_correction(ds: xr.Dataset) -> Figure:
    """The reflector corrected by Eq. 15 (bottom row) next to the Eq. 16 baseline (top row),
    one column per reflector image, shared colour scale (paper Fig. 7c/d vs g/h)."""
    rows = reflector_corrections(ds)
    names = reflector_image_names(ds)
    allv = np.concatenate([np.concatenate([r["eq15"].ravel(), r["eq16"].ravel()]) for r in rows])
    lo, hi = np.nanpercentile(allv, [1, 99]) if np.isfinite(allv).any() else (0.0, 1.0)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3.2 * len(rows) + 0.8, 5.0), layout="constrained")
    axes = []
    im = None
    for row, (key, label) in enumerate((("eq16", "Eq. 16 baseline"), ("eq15", "Eq. 15"))):
        for k, r in enumerate(rows):
            ax = fig.add_subplot(2, len(rows), row * len(rows) + k + 1)
            im = ax.imshow(r[key], cmap="RdBu_r", vmin=float(lo), vmax=float(hi), interpolation="nearest")
            extra = f" / {names[r['reference']]}" if key == "eq16" else ""
            ax.set_title(f"{label}: {names[k]}{extra}\nspread {r[key + '_spread']:.1%}", fontsize=7)
            image_axes(ax)
            axes.append(ax)
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.6, label="reflectance")
    b = rows[0]["band"] if rows else 0
    wl = float(ds["wavelength"].values[b]) if rows else float("nan")
    fig.suptitle(f"Reflector at {wl:g} nm: true reflectance is uniform; structure is an artefact", fontsize=9)
    return fig


# --------------------------------------------------------------------------- calibration warnings


def _marker_missing(ds: xr.Dataset, stage: str) -> tuple[int, int]:
    st = stage_results(ds, stage)
    missing = sum(1 for s in st.get("skipped", []) if "not found" in str(s.get("reason", "")))
    total = len(st.get("inputs") or {}) or missing
    return missing, total


def band_name_of(ds: xr.Dataset, b: int) -> str:
    return f"{float(ds['wavelength'].values[b]):g} nm"


def worst_of(values: Sequence[float], largest: bool = True) -> tuple[int, float]:
    arr = np.asarray(values, dtype=float)
    if arr.size == 0 or not np.isfinite(arr).any():
        return -1, float("nan")
    b = int(np.nanargmax(arr) if largest else np.nanargmin(arr))
    return b, float(arr[b])


def sweep_coverage(ds: xr.Dataset) -> np.ndarray:
    """Per band, the fraction of the usable DN range [black level, saturation) that the
    sweep observed (NaN where the store does not record the observed range)."""
    observed = stage_residuals(ds, "response").get("observed_dn")
    nb = ds.sizes["band"]
    if not observed:
        return np.full(nb, np.nan)
    dn_max = ds.sizes.get("dn", 2 ** int(ds.attrs.get("bit_depth", 10))) - 1
    black = ds["black_level"].values if "black_level" in ds else np.zeros(nb)
    sat = ds["saturation_dn"].values if "saturation_dn" in ds else np.full(nb, dn_max)
    out = np.empty(nb)
    for b, (lo, hi) in enumerate(observed):
        top, bottom = float(sat[b]) - 1, float(black[b])
        seen = min(hi, top) - max(lo, bottom)
        out[b] = max(seen, 0.0) / max(top - bottom, 1.0)
    return out


def response_residual_limit(ds: xr.Dataset) -> float:
    """:data:`RESPONSE_RESIDUAL_RMS_DN_MAX` in the store's DN: the limit is set for a 10-bit
    sensor, and a sensor of more bits over the same signal counts 2^(bits - 10) times as many
    DN for the same noise (a 12-bit RedEdge x 4, a 16-bit DJI P4M x 64)."""
    levels = ds.sizes.get("dn", 2 ** int(ds.attrs.get("bit_depth", 10)))
    return RESPONSE_RESIDUAL_RMS_DN_MAX * max(levels / 1024.0, 1.0)


def calibration_warnings(ds: xr.Dataset) -> list[QAWarning]:
    """Every finding on a calibration store, with its number and threshold."""
    out: list[QAWarning] = []
    for stage in ("vignetting", "illumination"):
        b, frac = worst_of(stage_residuals(ds, stage).get("saturated_fraction") or [])
        if b >= 0 and frac > SATURATED_FRACTION_MAX:
            out.append(QAWarning("saturated_fraction",
                                 f"{stage}: {frac:.1%} of the reflector pixels saturated at {band_name_of(ds, b)}",
                                 frac, SATURATED_FRACTION_MAX))
        missing, total = _marker_missing(ds, stage)
        if total and missing / total > MARKER_MISSING_FRACTION_MAX:
            out.append(QAWarning("marker_not_found", f"{stage}: marker not found in {missing} of {total} views",
                                 missing / total, MARKER_MISSING_FRACTION_MAX))
    if "inverse_response" in ds:
        b, cov = worst_of(sweep_coverage(ds), largest=False)
        if b >= 0 and cov < SWEEP_COVERAGE_MIN:
            lo, hi = stage_residuals(ds, "response")["observed_dn"][b]
            out.append(QAWarning("sweep_dn_range",
                                 f"the sweep observed DN {lo}-{hi} at {band_name_of(ds, b)}: {cov:.0%} of the usable "
                                 f"range; U is extrapolated above and below", cov, SWEEP_COVERAGE_MIN))
        b, rms = worst_of(stage_residuals(ds, "response").get("residual_rms_dn") or [])
        limit = response_residual_limit(ds)
        if b >= 0 and rms > limit:
            out.append(QAWarning("response_residual", f"response fit residual {rms:.1f} DN rms at {band_name_of(ds, b)}",
                                 rms, limit))
    vres = stage_residuals(ds, "vignetting")
    b, rms = worst_of(vres.get("residual_rms") or [])
    if b >= 0 and rms > VIGNETTING_RESIDUAL_RMS_MAX:
        out.append(QAWarning("vignetting_residual", f"vignetting fit residual {rms:.1%} rms at {band_name_of(ds, b)}",
                             rms, VIGNETTING_RESIDUAL_RMS_MAX))
    b, frac = worst_of(vres.get("observed_fraction") or [], largest=False)
    if b >= 0 and frac < VIGNETTING_OBSERVED_MIN:
        out.append(QAWarning("vignetting_coverage",
                             f"only {frac:.0%} of the band grid was seen by enough views at {band_name_of(ds, b)} "
                             f"({vres.get('views_used', '?')} views used); the rest of V is a smooth fill",
                             frac, VIGNETTING_OBSERVED_MIN))
    ires = stage_residuals(ds, "illumination")
    if "reflector_pixels" in ires and ires["reflector_pixels"] < MIN_REFLECTOR_PIXELS:
        out.append(QAWarning("few_reflector_pixels", f"only {ires['reflector_pixels']} reflector pixels in the "
                             "illumination fit", float(ires["reflector_pixels"]), MIN_REFLECTOR_PIXELS))
    rms = float(ires.get("residual_rms", float("nan")))
    if rms > ILLUMINATION_RESIDUAL_RMS_MAX:
        out.append(QAWarning("illumination_residual", f"illumination fit residual {rms:.1%} rms",
                             rms, ILLUMINATION_RESIDUAL_RMS_MAX))
    if "capture_spectral_factor" in ds and ds.sizes.get("capture", 1) > 1:
        change = colour_change(ds["capture_spectral_factor"].values)
        names = [str(n) for n in ds["capture_name"].values]
        for c in np.flatnonzero(change > CAPTURE_COLOUR_CHANGE_MAX):
            worst = int(np.argmax(np.abs(split_level(ds["capture_spectral_factor"].values[c + 1])[1]
                                         / split_level(ds["capture_spectral_factor"].values[c])[1] - 1.0)))
            out.append(QAWarning("light_colour_changed",
                                 f"the light's colour changed {change[c]:.1%} (at {band_name_of(ds, worst)}) between "
                                 f"reflector captures {names[c]} and {names[c + 1]}: capture the reflector more "
                                 "often, or re-fly in steadier light", float(change[c]), CAPTURE_COLOUR_CHANGE_MAX))
    if ires.get("shared_pixel_fraction") == 0.0:
        out.append(QAWarning("captures_not_shared",
                             "the reflector captures saw the reflector at different parts of the image (too few "
                             "sensor pixels in common to compare them on): the vignetting estimate's error there "
                             "enters the light between captures (0.5 % per band in bench_light); frame the "
                             "reflector alike, centred, in every capture", 0.0, 0.0))
    ib = np.asarray(ires.get("image_brightness") or [], dtype=float)
    ib = ib[np.isfinite(ib) & (ib > 0)]
    if ib.size >= 2 and ib.max() / ib.min() > REFLECTOR_BRIGHTNESS_RATIO_MAX:
        out.append(QAWarning("exposure_inconsistent",
                             f"reflector images differ {ib.max() / ib.min():.2f}x in exposure-normalised brightness: "
                             "check their exposure_ms and gain", float(ib.max() / ib.min()),
                             REFLECTOR_BRIGHTNESS_RATIO_MAX))
    return out


