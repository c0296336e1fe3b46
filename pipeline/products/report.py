"""The QA report (issue 5): one self-contained HTML page per calibration and its flights.

Every plot is a pure function of stored results -- the calibration store (opened with
:func:`pipeline.storage.store.open_calibration`) or an apply ``OUT`` folder (``run.json``,
``reflectance.zarr``, ``raw.zarr``) -- and returns a :class:`matplotlib.figure.Figure`. Figures
are built without pyplot (no global figure registry, no backend switch in the caller's
process) and rendered with the Agg canvas only.

- :func:`write_report` writes ``report.html`` (PNG plots embedded as base64 data URIs, inline
  CSS, a Content-Security-Policy that forbids every network load) atomically, and
  ``calibration.json`` beside it when a calibration is given.
- :func:`report_markdown` gives the same warnings and tables as markdown (Prefect artifacts);
  :func:`report_dict` the same as a JSON-able dict.
- :func:`calibration_warnings` / :func:`flight_warnings`: :class:`QAWarning` with numbers, each
  against a named threshold below.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import matplotlib
import numpy as np
import xarray as xr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from mscal_core.errors import InputError
from mscal_core.illumination import colour_change, split_level
from mscal_core.reflectance import eq15, ndvi, otsu_ndvi_threshold, vegetation_mask
from mscal_core.registration import local_motion

from pipeline.ingest.catalog import Camera, load_camera
from pipeline.storage.store import open_calibration
from pipeline.storage.atomic import write_text_atomic

# --------------------------------------------------------------------------- thresholds

#: Saturated pixels carry no radiometry (Eq. 15 gives NaN). Above 1 % of the reflector pixels
#: of a calibration dataset, or of a flight's pixels, the exposure was too long.
SATURATED_FRACTION_MAX = 0.01
#: The sweep should observe at least 80 % of the usable DN range [black level, saturation):
#: outside what it saw, U is extrapolated, not measured (Eq. 6 has no samples there).
SWEEP_COVERAGE_MIN = 0.8
#: Flight DN above the highest DN the sweep observed use the extrapolated part of U; more
#: than 0.1 % of the flight's pixels there means the sweep missed the bright end.
FLIGHT_DN_OUTSIDE_SWEEP_MAX = 0.001
#: More than a fifth of the marker views without the marker means the geometry coverage of
#: the vignetting fit is thinner than planned (check marker id, focus, framing).
MARKER_MISSING_FRACTION_MAX = 0.2
#: The illumination fit (Eq. 13) averages over the reflector pixels; below 10 000 pixels
#: (about 100 x 100, a twelfth of the Ximea band grid) B(x) covers too little to judge the light.
MIN_REFLECTOR_PIXELS = 10_000
#: Below half of the band grid observed, V is mostly the smooth radial fill, not measured.
VIGNETTING_OBSERVED_MIN = 0.5
#: Residuals: about 3x what the fits reach on sound data (synthetic demo session: response
#: 3.0 DN rms = the sensor noise, vignetting 0.8-1.0 %, illumination 1.5 %). Above them the
#: scene moved during the sweep, a marker pose is wrong, or the light changed between images.
RESPONSE_RESIDUAL_RMS_DN_MAX = 9.0
VIGNETTING_RESIDUAL_RMS_MAX = 0.03
ILLUMINATION_RESIDUAL_RMS_MAX = 0.05
#: Reflector images taken minutes apart under the same sky differ in median brightness by a
#: few per cent (demo: 1.06 vs 0.90); a factor 1.5 points to a wrong exposure_ms or gain.
REFLECTOR_BRIGHTNESS_RATIO_MAX = 1.5
#: A flight frame whose exposure-normalised level (median (DN - black) / t) is more than a
#: factor 2 off the flight's median: clouds change the light by less over one flight, a
#: wrong exposure_ms or gain by more.
FRAME_LEVEL_RATIO_MAX = 2.0
#: The light's colour (S with its level removed, ``mscal_core.illumination.colour_change``)
#: may change by at most 2 % in any band between consecutive reflector captures. The light
#: is interpolated between captures (issue 8); if a change was not linear in time, the
#: interpolated colour can be off by up to about half of it mid-way, and mscal aims at 1 %.
#: Above it, capture the reflector more often or re-fly in steadier light.
CAPTURE_COLOUR_CHANGE_MAX = 0.02
#: Panel and sun sensor (DLS) on the same capture (factory apply, issue 6): their factor ratio
#: carries the DLS's tilt and cosine error, one number for all bands; its spread across bands
#: (max/min - 1) is a disagreement in colour that goes straight into every index. Above 5 %
#: the two references give NDVI differing by more than about 0.02 on vegetation: keep the panel.
PANEL_DLS_COLOUR_SPREAD_MAX = 0.05
#: Band registration (issue 9): the median distance of the registered captures' transforms
#: to the session transform of a band. Captures of one flight at one altitude agree to a few
#: tenths of a pixel (synthetic rigs: < 0.3 px); above 1 px the captures saw the rig from
#: different distances (parallax: a panel capture at 1 m beside flight captures) or one
#: registration went wrong, and frames that were not registered themselves take a median
#: that fits none of them.
REGISTRATION_SPREAD_MAX_PX = 1.0

# --------------------------------------------------------------------------- sampling bounds

#: Frames read for histograms and DN coverage (evenly spaced over the flight).
HIST_MAX_FRAMES = 12
#: Pixels per band per frame in histograms (a regular stride over the band grid).
HIST_MAX_PIXELS = 20_000
#: Frames read for the exposure-consistency check (one chunk read per frame).
LEVEL_MAX_FRAMES = 400
#: Frames shown as NDVI quick-looks.
NDVI_MAX_FRAMES = 3
#: Rows of the HTML/markdown frame table (quarantined frames are always listed).
TABLE_MAX_ROWS = 300

PNG_DPI = 80


@dataclass(frozen=True)
class QAWarning:
    """One finding with its number: ``value`` compared with ``threshold`` (same unit).

    (Not called ``Warning``: that would shadow the builtin warning category in this module.)
    """

    code: str
    message: str
    value: float
    threshold: float


# --------------------------------------------------------------------------- inputs


@dataclass
class FlightResults:
    """The stored results of one ``mscal apply`` OUT folder (arrays stay lazy)."""

    out: Path
    run: dict[str, Any]
    reflectance: xr.Dataset
    raw: xr.Dataset | None
    camera: Camera | None

    @property
    def name(self) -> str:
        return Path(str(self.run.get("flight") or self.out)).name or self.out.name


def open_flight(out: str | Path) -> FlightResults:
    """Open an apply OUT folder; :class:`InputError` naming what is missing."""
    out = Path(out)
    run_path = out / "run.json"
    if not run_path.is_file():
        raise InputError("no run.json: not an 'mscal apply' output folder", path=out,
                         hint="run 'mscal apply FLIGHT_DIR --calibration CALIB.zarr -o OUT' first")
    try:
        run = json.loads(run_path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"run.json is unreadable ({type(exc).__name__})", path=run_path,
                         hint="run 'mscal apply' again to rewrite it") from None
    if not (out / "reflectance.zarr").is_dir():
        raise InputError("reflectance.zarr is missing", path=out, hint="run 'mscal apply' again")
    refl = xr.open_zarr(out / "reflectance.zarr")
    raw = xr.open_zarr(out / "raw.zarr") if (out / "raw.zarr").is_dir() else None
    camera = None
    name = refl.attrs.get("camera")
    if name:
        try:
            camera = load_camera(str(name))
        except InputError:
            camera = None
    return FlightResults(out, run, refl, raw, camera)


def _calibration(calibration: str | Path | xr.Dataset | None) -> xr.Dataset | None:
    if calibration is None or isinstance(calibration, xr.Dataset):
        return calibration
    return open_calibration(calibration)


# --------------------------------------------------------------------------- figure helpers


def _grid(n: int) -> tuple[int, int]:
    cols = math.ceil(math.sqrt(n))
    return math.ceil(n / cols), cols


def _panel_figure(n: int, panel_in: float = 2.0, extra_w: float = 0.0) -> tuple[Figure, list[Any]]:
    """A figure with ``n`` panels on a near-square grid; unused grid cells are not created."""
    rows, cols = _grid(n)
    w, h = cols * panel_in + extra_w, rows * panel_in * 0.8 + 0.6
    fig = Figure(figsize=(w, h))
    # A fixed layout: the constrained layout engine costs seconds on 25 panels.
    fig.subplots_adjust(left=0.03, right=1 - (extra_w + 0.1) / w, bottom=0.04, top=1 - 0.55 / h,
                        wspace=0.25, hspace=0.45)
    axes = [fig.add_subplot(rows, cols, k + 1) for k in range(n)]
    return fig, axes


def _band_titles(ds: xr.Dataset) -> list[str]:
    wl = ds["wavelength"].values if "wavelength" in ds.coords else np.arange(ds.sizes["band"])
    return [f"{float(w):g} nm" for w in wl]


def _few_ticks(ax: Any, xticks: Sequence[float] | None = None) -> None:
    """Three ticks per axis at most: tick objects are most of the rendering time of a
    25-panel figure."""
    if xticks is not None:
        ax.set_xticks(list(xticks))
    else:
        ax.xaxis.set_major_locator(MaxNLocator(3))
    ax.yaxis.set_major_locator(MaxNLocator(3))
    ax.tick_params(labelsize=6)


def _image_axes(ax: Any) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def figure_png(fig: Figure) -> bytes:
    """PNG bytes of ``fig`` (Agg canvas); the figure is cleared afterwards."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    fig.clear()
    return buf.getvalue()


# --------------------------------------------------------------------------- calibration plots


def _stage(ds: xr.Dataset, stage: str) -> dict[str, Any]:
    return dict(ds.attrs.get(stage) or {})


def _residuals(ds: xr.Dataset, stage: str) -> dict[str, Any]:
    return dict(_stage(ds, stage).get("residuals") or {})


def plot_inverse_response(ds: xr.Dataset) -> Figure:
    """Inverse response U(k) per band (paper Fig. 5): solid where the sweep observed DN,
    dotted where U is extrapolated; black level and saturation marked; fit rms in the title."""
    U = ds["inverse_response"].values
    k = np.arange(U.shape[1])
    res = _residuals(ds, "response")
    observed = res.get("observed_dn") or [[0, U.shape[1] - 1]] * U.shape[0]
    rms = res.get("residual_rms_dn") or [float("nan")] * U.shape[0]
    black = ds["black_level"].values if "black_level" in ds else np.zeros(U.shape[0])
    sat = ds["saturation_dn"].values if "saturation_dn" in ds else np.full(U.shape[0], U.shape[1] - 1)
    fig, axes = _panel_figure(U.shape[0])
    for b, (ax, title) in enumerate(zip(axes, _band_titles(ds))):
        lo, hi = int(observed[b][0]), int(observed[b][1])
        inside = (k >= lo) & (k <= hi)
        ax.plot(k, np.where(inside, U[b], np.nan), color="C0", lw=1.2)
        ax.plot(k, np.where(inside, np.nan, U[b]), color="C0", lw=1.0, ls=":")
        ax.axvspan(lo, hi, color="C2", alpha=0.12)
        ax.axvline(float(black[b]), color="0.4", lw=0.6)
        ax.axvline(float(sat[b]), color="C3", lw=0.6)
        ax.set_title(f"{title}  rms {float(rms[b]):.1f} DN", fontsize=7)
        _few_ticks(ax, (0, len(k) // 2, len(k) - 1))
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
    fig, axes = _panel_figure(len(stack), panel_in=2.2, extra_w=0.8)
    im = None
    for ax, img, title in zip(axes, stack, titles):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=7)
        _image_axes(ax)
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
    return _shared_image_grid(V, _band_titles(ds), "Vignetting V (Eq. 8-10), max 1 per band, shared scale",
                              "viridis", lo, 1.0, "V")


def plot_coverage(ds: xr.Dataset) -> Figure:
    """How many views saw each pixel in the vignetting fit (``vignetting_count``), per band,
    shared scale; blank where no view saw it (V is a smooth fill there)."""
    count = ds["vignetting_count"].values.astype(np.float32)
    count[count == 0] = np.nan
    top = float(np.nanmax(count)) if np.isfinite(count).any() else 1.0
    return _shared_image_grid(count, _band_titles(ds), "Coverage: views seeing each pixel (blank = none)",
                              "magma", 0.0, max(top, 1.0), "views")


def plot_spectral_factor(ds: xr.Dataset) -> Figure:
    """Spectral factor S against wavelength (paper Fig. 1b)."""
    wl = ds["wavelength"].values.astype(float)
    S = ds["spectral_factor"].values.astype(float)
    order = np.argsort(wl)
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
    """The light over the session (issue 8): above, S of every band at each reflector capture
    relative to the first capture's; below, the brightness level of each capture and, for
    flights applied with light varying in time, of each frame; every flight frame's time is
    marked (ticks at the bottom of both panels). Time in minutes from the first capture."""
    s = ds["capture_spectral_factor"].values.astype(float)
    tc = _seconds(ds["capture_time"].values)
    level = ds["capture_level"].values.astype(float)
    names = [str(n) for n in ds["capture_name"].values]
    t0 = float(np.nanmin(tc)) if np.isfinite(tc).any() else 0.0
    x = (tc - t0) / 60.0 if np.isfinite(tc).all() else np.arange(tc.size, dtype=float)
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


def _reflector_images(ds: xr.Dataset) -> list[str]:
    if "reflector_file" in ds.coords:
        return [str(v) for v in ds["reflector_file"].values]
    return [str(i) for i in range(ds.sizes.get("reflector_image", 0))]


def plot_brightness(ds: xr.Dataset) -> Figure:
    """Reflector brightness B(x) of each reflector image (paper Fig. 7e/f), shared scale."""
    B = ds["reflector_brightness"].values
    lo, hi = np.nanpercentile(B, [1, 99]) if np.isfinite(B).any() else (0.0, 2.0)
    names = _reflector_images(ds)
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
    names = _reflector_images(ds)
    allv = np.concatenate([np.concatenate([r["eq15"].ravel(), r["eq16"].ravel()]) for r in rows])
    lo, hi = np.nanpercentile(allv, [1, 99]) if np.isfinite(allv).any() else (0.0, 1.0)
    fig = Figure(figsize=(3.2 * len(rows) + 0.8, 5.0), layout="constrained")
    axes = []
    im = None
    for row, (key, label) in enumerate((("eq16", "Eq. 16 baseline"), ("eq15", "Eq. 15"))):
        for k, r in enumerate(rows):
            ax = fig.add_subplot(2, len(rows), row * len(rows) + k + 1)
            im = ax.imshow(r[key], cmap="RdBu_r", vmin=float(lo), vmax=float(hi), interpolation="nearest")
            extra = f" / {names[r['reference']]}" if key == "eq16" else ""
            ax.set_title(f"{label}: {names[k]}{extra}\nspread {r[key + '_spread']:.1%}", fontsize=7)
            _image_axes(ax)
            axes.append(ax)
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.6, label="reflectance")
    b = rows[0]["band"] if rows else 0
    wl = float(ds["wavelength"].values[b]) if rows else float("nan")
    fig.suptitle(f"Reflector at {wl:g} nm: true reflectance is uniform; structure is an artefact", fontsize=9)
    return fig


# --------------------------------------------------------------------------- calibration warnings


def _marker_missing(ds: xr.Dataset, stage: str) -> tuple[int, int]:
    st = _stage(ds, stage)
    missing = sum(1 for s in st.get("skipped", []) if "not found" in str(s.get("reason", "")))
    total = len(st.get("inputs") or {}) or missing
    return missing, total


def _band_name(ds: xr.Dataset, b: int) -> str:
    return f"{float(ds['wavelength'].values[b]):g} nm"


def _worst(values: Sequence[float], largest: bool = True) -> tuple[int, float]:
    arr = np.asarray(values, dtype=float)
    if arr.size == 0 or not np.isfinite(arr).any():
        return -1, float("nan")
    b = int(np.nanargmax(arr) if largest else np.nanargmin(arr))
    return b, float(arr[b])


def sweep_coverage(ds: xr.Dataset) -> np.ndarray:
    """Per band, the fraction of the usable DN range [black level, saturation) that the
    sweep observed (NaN where the store does not record the observed range)."""
    observed = _residuals(ds, "response").get("observed_dn")
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


def calibration_warnings(ds: xr.Dataset) -> list[QAWarning]:
    """Every finding on a calibration store, with its number and threshold."""
    out: list[QAWarning] = []
    for stage in ("vignetting", "illumination"):
        b, frac = _worst(_residuals(ds, stage).get("saturated_fraction") or [])
        if b >= 0 and frac > SATURATED_FRACTION_MAX:
            out.append(QAWarning("saturated_fraction",
                                 f"{stage}: {frac:.1%} of the reflector pixels saturated at {_band_name(ds, b)}",
                                 frac, SATURATED_FRACTION_MAX))
        missing, total = _marker_missing(ds, stage)
        if total and missing / total > MARKER_MISSING_FRACTION_MAX:
            out.append(QAWarning("marker_not_found", f"{stage}: marker not found in {missing} of {total} views",
                                 missing / total, MARKER_MISSING_FRACTION_MAX))
    if "inverse_response" in ds:
        b, cov = _worst(sweep_coverage(ds), largest=False)
        if b >= 0 and cov < SWEEP_COVERAGE_MIN:
            lo, hi = _residuals(ds, "response")["observed_dn"][b]
            out.append(QAWarning("sweep_dn_range",
                                 f"the sweep observed DN {lo}-{hi} at {_band_name(ds, b)}: {cov:.0%} of the usable "
                                 f"range; U is extrapolated above and below", cov, SWEEP_COVERAGE_MIN))
        b, rms = _worst(_residuals(ds, "response").get("residual_rms_dn") or [])
        if b >= 0 and rms > RESPONSE_RESIDUAL_RMS_DN_MAX:
            out.append(QAWarning("response_residual", f"response fit residual {rms:.1f} DN rms at {_band_name(ds, b)}",
                                 rms, RESPONSE_RESIDUAL_RMS_DN_MAX))
    vres = _residuals(ds, "vignetting")
    b, rms = _worst(vres.get("residual_rms") or [])
    if b >= 0 and rms > VIGNETTING_RESIDUAL_RMS_MAX:
        out.append(QAWarning("vignetting_residual", f"vignetting fit residual {rms:.1%} rms at {_band_name(ds, b)}",
                             rms, VIGNETTING_RESIDUAL_RMS_MAX))
    b, frac = _worst(vres.get("observed_fraction") or [], largest=False)
    if b >= 0 and frac < VIGNETTING_OBSERVED_MIN:
        out.append(QAWarning("vignetting_coverage",
                             f"only {frac:.0%} of the band grid was seen by enough views at {_band_name(ds, b)} "
                             f"({vres.get('views_used', '?')} views used); the rest of V is a smooth fill",
                             frac, VIGNETTING_OBSERVED_MIN))
    ires = _residuals(ds, "illumination")
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
                                 f"the light's colour changed {change[c]:.1%} (at {_band_name(ds, worst)}) between "
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


# --------------------------------------------------------------------------- flight data


def sample_indices(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices evenly spaced over ``range(n)`` (first and last included)."""
    if n <= 0:
        return np.zeros(0, dtype=int)
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int))


def _stride(shape: Sequence[int], max_pixels: int) -> int:
    return max(1, math.ceil(math.sqrt(shape[-2] * shape[-1] / max_pixels)))


def _sampled(da: xr.DataArray, frames: np.ndarray, max_pixels: int) -> np.ndarray:
    """``da[frames, ..., ::s, ::s]`` in memory, one frame at a time (bounded memory)."""
    s = _stride(da.shape, max_pixels)
    return np.stack([np.asarray(da.isel(frame=int(f)).values[..., ::s, ::s]) for f in frames])


def _role_bands(flight: FlightResults) -> tuple[int, int] | None:
    cam = flight.camera
    if cam is None or not {"red", "nir"} <= set(cam.index_bands):
        return None
    return cam.band_for_wavelength(cam.index_bands["red"]), cam.band_for_wavelength(cam.index_bands["nir"])


def frame_rows(flight: FlightResults) -> list[dict[str, Any]]:
    """One row per frame of ``reflectance.zarr`` (exposure, time, GPS, saturated pixels), then
    one per quarantined frame with its reason (from ``run.json``)."""
    ds = flight.reflectance
    sat = (flight.run.get("saturated_pixels") or {}).get("per_frame") or {}
    cols = {c: ds[c].values for c in ("exposure_ms", "time", "lat", "lon", "alt_m") if c in ds.coords}
    rows = []
    for i, name in enumerate(str(f) for f in ds["frame"].values):
        row: dict[str, Any] = {"frame": name, "status": "ok"}
        for c, vals in cols.items():
            row[c] = _coord_text(c, vals[i])
        row["saturated_pixels"] = sat.get(name)
        rows.append(row)
    for q in flight.run.get("quarantined") or []:
        rows.append({"frame": str(q.get("file")), "status": "quarantined", "reason": str(q.get("reason", ""))})
    return rows


def _coord_text(name: str, value: Any) -> str:
    """A frame coordinate as shown in the table: ISO time to the second, GPS to 1e-7 degrees
    (about 1 cm), empty where unknown."""
    if name == "time":
        return "" if np.isnat(value) else str(value)[:19]
    v = float(value)
    if not math.isfinite(v):
        return ""
    return f"{v:.7f}" if name in ("lat", "lon") else f"{v:g}"


def frame_levels(flight: FlightResults, calibration: xr.Dataset | None = None) -> dict[str, float]:
    """Exposure-normalised level ``median(DN - black) / t`` of each checked frame at the QA
    band (up to :data:`LEVEL_MAX_FRAMES`, evenly spaced); empty without ``raw.zarr``."""
    raw = flight.raw
    if raw is None or "dn" not in raw:
        return {}
    b = _qa_band(flight)
    black = float(calibration["black_level"].values[b]) if calibration is not None and "black_level" in calibration else 0.0
    t = (raw["exposure_ms"] * (raw["gain"] if "gain" in raw.coords else 1.0)).values.astype(float)
    names = [str(f) for f in raw["frame"].values]
    out = {}
    for f in sample_indices(len(names), LEVEL_MAX_FRAMES):
        dn = np.asarray(raw["dn"].isel(frame=int(f), band=b).values, dtype=float)
        out[names[f]] = float(np.median(dn - black) / t[f]) if t[f] > 0 else float("nan")
    return out


def _qa_band(flight: FlightResults) -> int:
    roles = _role_bands(flight)
    if roles is not None:
        return roles[1]
    return int(flight.reflectance.sizes.get("band", 1)) // 2


def dn_outside_sweep(flight: FlightResults, calibration: xr.Dataset) -> tuple[float, int]:
    """Fraction of sampled flight DN above the highest unsaturated DN the sweep observed
    (and below saturation), and the worst band."""
    observed = _residuals(calibration, "response").get("observed_dn")
    raw = flight.raw
    if not observed or raw is None or "dn" not in raw:
        return float("nan"), -1
    frames = sample_indices(raw.sizes["frame"], HIST_MAX_FRAMES)
    dn = _sampled(raw["dn"], frames, HIST_MAX_PIXELS)  # (frame, band, h, w)
    sat = calibration["saturation_dn"].values if "saturation_dn" in calibration else np.full(dn.shape[1], np.inf)
    frac = np.array([np.mean((dn[:, b] > observed[b][1]) & (dn[:, b] < sat[b])) for b in range(dn.shape[1])])
    b = int(np.argmax(frac))
    return float(frac[b]), b


def flight_warnings(flight: FlightResults, calibration: xr.Dataset | None = None) -> list[QAWarning]:
    """Findings on one flight: quarantined frames, saturation, DN beyond the sweep,
    frames whose exposure contradicts their brightness."""
    out: list[QAWarning] = []
    run = flight.run
    q = run.get("quarantined") or []
    if q:
        names = ", ".join(str(x.get("file")) for x in q[:5]) + (" ..." if len(q) > 5 else "")
        out.append(QAWarning("quarantined_frames", f"{len(q)} of {run.get('frames_in', '?')} frames quarantined: {names}",
                             float(len(q)), 0.0))
    shape = flight.reflectance["reflectance"].shape if "reflectance" in flight.reflectance else (0,)
    n_pix = float(np.prod(shape))
    total = float((run.get("saturated_pixels") or {}).get("total", 0))
    if n_pix and total / n_pix > SATURATED_FRACTION_MAX:
        out.append(QAWarning("saturated_fraction", f"{total / n_pix:.1%} of the flight's pixels saturated",
                             total / n_pix, SATURATED_FRACTION_MAX))
    if calibration is not None:
        frac, b = dn_outside_sweep(flight, calibration)
        if b >= 0 and frac > FLIGHT_DN_OUTSIDE_SWEEP_MAX:
            hi = _residuals(calibration, "response")["observed_dn"][b][1]
            out.append(QAWarning("flight_dn_outside_sweep",
                                 f"{frac:.2%} of the flight's DN at {_band_name(calibration, b)} are above the "
                                 f"sweep's highest DN {hi}: U is extrapolated there", frac, FLIGHT_DN_OUTSIDE_SWEEP_MAX))
    levels = frame_levels(flight, calibration)
    vals = np.array([v for v in levels.values() if np.isfinite(v) and v > 0])
    if vals.size >= 3:
        med = float(np.median(vals))
        ratio = {n: max(v / med, med / v) for n, v in levels.items() if np.isfinite(v) and v > 0}
        bad = sorted((n for n, r in ratio.items() if r > FRAME_LEVEL_RATIO_MAX), key=lambda n: -ratio[n])
        if bad:
            worst = ratio[bad[0]]
            out.append(QAWarning("exposure_inconsistent",
                                 f"{len(bad)} frame(s) off the flight's exposure-normalised level by up to "
                                 f"{worst:.1f}x: {', '.join(bad[:5])}; check their exposure_ms and gain",
                                 worst, FRAME_LEVEL_RATIO_MAX))
    return out


# --------------------------------------------------------------------------- flight plots


def ndvi_pairs(flight: FlightResults) -> list[dict[str, Any]]:
    """Raw-DN NDVI and calibrated NDVI of up to :data:`NDVI_MAX_FRAMES` frames."""
    roles = _role_bands(flight)
    ds = flight.reflectance
    if roles is None or flight.raw is None or "ndvi" not in ds:
        return []
    red, nir = roles
    names = [str(f) for f in ds["frame"].values]
    raw_names = [str(f) for f in flight.raw["frame"].values]
    out = []
    for f in sample_indices(len(names), NDVI_MAX_FRAMES):
        if names[f] not in raw_names:
            continue
        r = raw_names.index(names[f])
        dn = flight.raw["dn"].isel(frame=r, band=[red, nir]).values.astype(np.float64)
        out.append({"frame": names[f], "raw": ndvi(dn[0], dn[1]),
                    "calibrated": np.asarray(ds["ndvi"].isel(frame=int(f)).values, dtype=np.float64)})
    return out


def plot_ndvi(flight: FlightResults) -> Figure:
    """NDVI from raw DN vs calibrated NDVI, and their Otsu segmentations (paper Fig. 1e/f):
    one row per shown frame, four panels each."""
    pairs = ndvi_pairs(flight)
    fig = Figure(figsize=(11, 2.4 * max(len(pairs), 1) + 0.5), layout="constrained")
    if not pairs:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, "no NDVI: camera without red/NIR roles or raw.zarr missing", ha="center")
        ax.axis("off")
        return fig
    for i, p in enumerate(pairs):
        for j, (key, kind) in enumerate((("raw", "raw DN"), ("calibrated", "calibrated"))):
            ax = fig.add_subplot(len(pairs), 4, 4 * i + j + 1)
            ax.imshow(p[key], cmap="RdYlGn", vmin=-1, vmax=1, interpolation="nearest")
            ax.set_title(f"{p['frame']}: NDVI {kind}", fontsize=7)
            _image_axes(ax)
            thr = otsu_ndvi_threshold(p[key])  # the stored vegetation_mask's segmentation
            ax = fig.add_subplot(len(pairs), 4, 4 * i + j + 3)
            ax.imshow(vegetation_mask(p[key]) == 1, cmap="Greens", vmin=0, vmax=1, interpolation="nearest")
            ax.set_title(f"Otsu on {kind} (NDVI >= {thr:.2f})", fontsize=7)
            _image_axes(ax)
    fig.suptitle("NDVI quick-looks: raw DN vs calibrated (paper Fig. 1e/f)", fontsize=9)
    return fig


def plot_track(flight: FlightResults) -> Figure:
    """Frame positions (lon, lat) in flight order; first frame a square, last a triangle."""
    ds = flight.reflectance
    fig = Figure(figsize=(5.5, 4.5), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    lat = ds["lat"].values.astype(float) if "lat" in ds.coords else np.array([])
    lon = ds["lon"].values.astype(float) if "lon" in ds.coords else np.array([])
    ok = np.isfinite(lat) & np.isfinite(lon)
    if not ok.any():
        ax.text(0.5, 0.5, "no GPS positions in the frames", ha="center", va="center")
        ax.axis("off")
        return fig
    order = np.flatnonzero(ok)
    ax.plot(lon[ok], lat[ok], "-", color="0.7", lw=0.8)
    sc = ax.scatter(lon[ok], lat[ok], c=order, cmap="viridis", s=14, zorder=3)
    ax.plot(lon[order[0]], lat[order[0]], "s", mfc="none", mec="k", ms=9)
    ax.plot(lon[order[-1]], lat[order[-1]], "^", mfc="none", mec="k", ms=9)
    ax.set_aspect(1 / max(math.cos(math.radians(float(np.nanmean(lat[ok])))), 1e-3), adjustable="datalim")
    ax.ticklabel_format(useOffset=False)
    ax.tick_params(labelsize=6)
    ax.set_xlabel("longitude (°)")
    ax.set_ylabel("latitude (°)")
    fig.colorbar(sc, ax=ax, label="frame number")
    ax.set_title(f"Track: {int(ok.sum())} of {len(ok)} frames with GPS", fontsize=9)
    return fig


def plot_histograms(flight: FlightResults) -> Figure:
    """Reflectance histogram per band over a sample of frames and pixels (at most
    :data:`HIST_MAX_FRAMES` frames x :data:`HIST_MAX_PIXELS` pixels per band)."""
    ds = flight.reflectance
    frames = sample_indices(ds.sizes["frame"], HIST_MAX_FRAMES)
    r = _sampled(ds["reflectance"], frames, HIST_MAX_PIXELS)  # (frame, band, h, w)
    finite = r[np.isfinite(r)]
    lo, hi = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
    edges = np.linspace(float(lo), float(max(hi, lo + 1e-6)), 61)
    fig, axes = _panel_figure(r.shape[1], panel_in=1.9)
    for b, (ax, title) in enumerate(zip(axes, _band_titles(ds))):
        v = r[:, b][np.isfinite(r[:, b])]
        counts, _ = np.histogram(v, bins=edges)
        ax.stairs(counts, edges, fill=True, color="C0")  # one artist, not one bar per bin
        ax.set_title(f"{title} (median {np.median(v) if v.size else float('nan'):.3g})", fontsize=7)
        _few_ticks(ax)
        ax.set_yticks([])
    fig.suptitle(f"Reflectance per band ({len(frames)} of {ds.sizes['frame']} frames, "
                 f"pixel stride {_stride(ds['reflectance'].shape, HIST_MAX_PIXELS)})", fontsize=9)
    return fig


# --------------------------------------------------------------------------- the report model


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[Any]]
    note: str = ""


@dataclass
class Section:
    """One part of the report: warnings, tables, and figure builders (rendered only for HTML)."""

    title: str
    anchor: str
    warnings: list[QAWarning] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[tuple[str, Callable[[], Figure]]] = field(default_factory=list)


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.{digits}g}"
    return str(v)


def _per_band(res: dict[str, Any], key: str, b: int) -> Any:
    vals = res.get(key)
    return vals[b] if isinstance(vals, list) and b < len(vals) else None


def band_table(ds: xr.Dataset) -> Table:
    """Per band: wavelength, S, black level, saturation, observed DN, fit residuals."""
    r, v = _residuals(ds, "response"), _residuals(ds, "vignetting")
    cov = sweep_coverage(ds) if "inverse_response" in ds else np.full(ds.sizes["band"], np.nan)
    rows = []
    for b in range(ds.sizes["band"]):
        obs = _per_band(r, "observed_dn", b)
        rows.append([
            str(ds["band_name"].values[b]) if "band_name" in ds.coords else str(b),
            float(ds["wavelength"].values[b]),
            float(ds["spectral_factor"].values[b]) if "spectral_factor" in ds else None,
            float(ds["black_level"].values[b]) if "black_level" in ds else None,
            int(ds["saturation_dn"].values[b]) if "saturation_dn" in ds else None,
            f"{obs[0]}-{obs[1]}" if obs else None,
            float(cov[b]),
            _per_band(r, "residual_rms_dn", b),
            _per_band(v, "residual_rms", b),
            _per_band(v, "observed_fraction", b),
        ])
    return Table("Bands", ["band", "wavelength nm", "S", "black DN", "saturation DN", "sweep DN",
                           "sweep coverage", "response rms DN", "vignetting rms", "V observed"], rows)


def skipped_table(ds: xr.Dataset) -> Table:
    rows = [[stage, s.get("file"), s.get("reason")] for stage in ("response", "vignetting", "illumination")
            for s in _stage(ds, stage).get("skipped", [])]
    return Table("Frames skipped by the fits", ["stage", "file", "reason"], rows,
                 note="" if rows else "none")


def _band_label(ds: xr.Dataset, b: int) -> str:
    """``Green (560 nm)``: the band's name and wavelength (multi-lens cameras name their bands)."""
    if "band_name" in ds.coords:
        return f"{ds['band_name'].values[b]} ({_band_name(ds, b)})"
    return _band_name(ds, b)


def _registration(ds: xr.Dataset) -> dict[str, Any]:
    rec = ds.attrs.get("registration")
    return rec if isinstance(rec, dict) else {}


def registration_table(ds: xr.Dataset) -> Table | None:
    """Per band of a registered store (``mscal register``): what the session transform does
    at the image centre (shift, rotation, scale; :func:`mscal_core.registration.local_motion`),
    how many captures passed the thresholds and their weakest figures, and the captures'
    spread about the session transform. None for stores without a registration."""
    if "band_transform" not in ds:
        return None
    rec = _registration(ds)
    shape = rec.get("shape") or [0, 0]
    centre = ((float(shape[1]) - 1) / 2, (float(shape[0]) - 1) / 2)
    fallback = np.asarray(ds["registration_fallback"].values, dtype=bool) if "registration_fallback" in ds else None
    n_cap = int(ds.sizes.get("capture", 0))

    def weakest(var: str, b: int, fn: Callable[[np.ndarray], float]) -> float | None:
        if var not in ds or fallback is None:
            return None
        vals = np.asarray(ds[var].values[:, b], dtype=np.float64)[~fallback[:, b]]
        vals = vals[np.isfinite(vals)]
        return float(fn(vals)) if vals.size else None

    rows = []
    for b in range(ds.sizes["band"]):
        dx, dy, rot, scale = local_motion(ds["band_transform"].values[b], centre)
        passed = int(n_cap - fallback[:, b].sum()) if fallback is not None else None
        spread = float(ds["registration_spread_px"].values[b]) if "registration_spread_px" in ds else None
        rows.append([_band_label(ds, b) + (" (reference)" if b == rec.get("reference_index") else ""),
                     round(dx, 2), round(dy, 2), round(rot, 3), round(scale, 4),
                     f"{passed}/{n_cap}" if passed is not None else None,
                     weakest("registration_ecc", b, np.min), weakest("registration_inliers", b, np.min),
                     weakest("registration_residual_px", b, np.max), spread])
    th = rec.get("thresholds") or {}
    note = (f"session transform of each band onto {rec.get('reference_band')} at the image centre; "
            f"captures pass with gradient correlation >= {th.get('min_ecc')}, >= {th.get('min_inliers')} "
            f"feature inliers and <= {th.get('max_residual_px')} px residual; weakest figures over the captures "
            f"that passed; spread = median distance of their transforms to the session's")
    if rec.get("registered_of"):
        note += f"; {n_cap} of {rec['registered_of']} captures registered"
    return Table("Band registration", ["band", "shift x px", "shift y px", "rotation deg", "scale", "captures passed",
                                       "min gradient corr.", "min inliers", "max residual px", "spread px"], rows,
                 note=note)


def registration_fallback_table(ds: xr.Dataset) -> Table | None:
    """Captures with a band that failed the thresholds (they use the session transform for it)."""
    if "band_transform" not in ds:
        return None
    rows = [[f.get("capture"), ", ".join(f.get("bands") or []), f.get("reason")]
            for f in _registration(ds).get("fallbacks") or []]
    return Table("Captures that fell back to the session transform", ["capture", "bands", "reason"], rows,
                 note="" if rows else "none")


def registration_warnings(ds: xr.Dataset) -> list[QAWarning]:
    """Captures that fell back, and bands whose captures disagree by more than
    :data:`REGISTRATION_SPREAD_MAX_PX`."""
    if "band_transform" not in ds:
        return []
    out: list[QAWarning] = []
    fallbacks = _registration(ds).get("fallbacks") or []
    n_cap = int(ds.sizes.get("capture", 0))
    if fallbacks:
        named = "; ".join(f"{f.get('capture')}: {', '.join(f.get('bands') or [])}" for f in fallbacks[:5])
        more = f" and {len(fallbacks) - 5} more" if len(fallbacks) > 5 else ""
        out.append(QAWarning(
            "registration_fallback",
            f"{len(fallbacks)} of {n_cap} registered captures failed the thresholds for some band and use the "
            f"session transform there ({named}{more}); check those captures' NDVI edges",
            float(len(fallbacks)), 0.0))
    if "registration_spread_px" in ds:
        spread = np.asarray(ds["registration_spread_px"].values, dtype=np.float64)
        b, worst = _worst([float(v) if np.isfinite(v) else float("nan") for v in spread])
        if b >= 0 and worst > REGISTRATION_SPREAD_MAX_PX:
            out.append(QAWarning(
                "registration_spread",
                f"the registered captures disagree by {worst:.1f} px at {_band_label(ds, b)}: parallax between "
                "captures at different distances (e.g. a panel capture beside flight captures) or a failed "
                "registration; frames that were not registered take the session transform, so register captures "
                "from the flight's altitude",
                worst, REGISTRATION_SPREAD_MAX_PX))
    return out


def calibration_section(ds: xr.Dataset, flights: Sequence["FlightResults"] = ()) -> Section:
    tables = [band_table(ds), skipped_table(ds)]
    tables += [t for t in (registration_table(ds), registration_fallback_table(ds)) if t is not None]
    sec = Section(f"Calibration: {ds.attrs.get('camera', '?')}", "calibration",
                  calibration_warnings(ds) + registration_warnings(ds), tables)
    plots: list[tuple[str, str, Callable[[xr.Dataset], Figure]]] = [
        ("inverse_response", "Inverse response per band", plot_inverse_response),
        ("vignetting", "Vignetting per band", plot_vignetting),
        ("vignetting_count", "Coverage of the vignetting fit", plot_coverage),
        ("spectral_factor", "Spectral factor", plot_spectral_factor),
        ("reflector_brightness", "Reflector brightness", plot_brightness),
        ("reflector_dn", "Reflector: Eq. 15 vs the Eq. 16 baseline", plot_reflector_correction),
    ]
    for var, caption, fn in plots:
        if var in ds:
            sec.figures.append((caption, (lambda fn=fn: fn(ds))))
    if "capture_spectral_factor" in ds and ds.sizes.get("capture", 1) > 1:
        sec.figures.append(("Light over time: reflector captures and flight frames",
                            lambda: plot_light_over_time(ds, flights)))
    return sec


def _panel_dls(panel: dict[str, Any]) -> dict[str, float]:
    ratio = panel.get("panel_over_dls") or {}
    return {b: float(v) for b, v in ratio.items() if v is not None and math.isfinite(float(v)) and float(v) > 0}


def reference_table(run: dict[str, Any], band_names: Sequence[str] = ()) -> Table | None:
    """The reflectance reference of a factory apply (run.json ``reference``): per panel capture
    and band, the panel's factor (Eq. 11-14 split and plain mean) beside the sun sensor's
    ``pi / E`` on the same capture and their ratio, bands in ``band_names`` order (the
    camera's; run.json keeps them sorted by name). None for runs without one."""
    rec = run.get("reference")
    if not isinstance(rec, dict):
        return None
    if rec.get("route") != "panel":
        return Table("Reflectance reference", ["route", "formula"], [[rec.get("route"), rec.get("formula")]],
                     note="each capture's own sun-sensor reading; no panel to compare it with "
                          "(give --panel-reflectance to use and compare a panel capture)")
    rows = []
    for p in rec.get("panels") or []:
        split = p.get("factor_split") or {}
        order = [b for b in band_names if b in split] + sorted(b for b in split if b not in band_names)
        for band in order:
            k = split[band]
            rows.append([p.get("capture"), band, k, (p.get("factor_mean") or {}).get(band),
                         (p.get("factor_dls") or {}).get(band), (p.get("panel_over_dls") or {}).get(band)])
    return Table("Reflectance reference: panel vs sun sensor",
                 ["panel capture", "band", "k panel (S/B split)", "k panel (mean)", "k DLS (pi/E)", "panel / DLS"],
                 rows, note=f"{rec.get('formula')}; a panel/DLS ratio equal in all bands is the DLS's tilt "
                            "(brightness only), a spread across bands changes every index")


def reference_warnings(run: dict[str, Any]) -> list[QAWarning]:
    """A panel capture whose panel/DLS factor ratio spreads across bands by more than
    :data:`PANEL_DLS_COLOUR_SPREAD_MAX`."""
    rec = run.get("reference")
    out: list[QAWarning] = []
    if not isinstance(rec, dict):
        return out
    for p in rec.get("panels") or []:
        ratio = _panel_dls(p)
        if len(ratio) < 2:
            continue
        lo, hi = min(ratio, key=ratio.__getitem__), max(ratio, key=ratio.__getitem__)
        spread = ratio[hi] / ratio[lo] - 1.0
        if spread > PANEL_DLS_COLOUR_SPREAD_MAX:
            out.append(QAWarning(
                "panel_dls_colour", f"panel {p.get('capture')}: panel and sun sensor disagree in colour by "
                f"{spread:.0%} (panel/DLS {ratio[lo]:.3f} at {lo} to {ratio[hi]:.3f} at {hi}); reflectance uses "
                "the panel, a DLS-only flight of this camera would carry that error into its indices",
                spread, PANEL_DLS_COLOUR_SPREAD_MAX))
    return out


def flight_section(flight: FlightResults, calibration: xr.Dataset | None) -> Section:
    rows = frame_rows(flight)
    ok = [r for r in rows if r["status"] == "ok"]
    bad = [r for r in rows if r["status"] != "ok"]
    shown = ok[:TABLE_MAX_ROWS]
    cols = ["frame", "time", "exposure_ms", "lat", "lon", "alt_m", "saturated_pixels", "status"]
    table = Table("Frames", cols, [[r.get(c) for c in cols] for r in shown],
                  note=f"first {len(shown)} of {len(ok)} frames; all in run.json" if len(ok) > len(shown) else "")
    qtable = Table("Quarantined frames", ["frame", "reason"], [[r["frame"], r.get("reason")] for r in bad],
                   note="" if bad else "none")
    run = flight.run
    summary = Table("Run", ["frames in", "frames out", "quarantined", "saturated pixels", "seconds"], [[
        run.get("frames_in"), run.get("frames_out"), len(bad),
        (run.get("saturated_pixels") or {}).get("total"), (run.get("timings_s") or {}).get("total")]])
    tables = [summary, qtable]
    warns = flight_warnings(flight, calibration)
    ref = reference_table(run, flight.camera.band_names if flight.camera is not None else ())
    if ref is not None:
        tables.append(ref)
        warns += reference_warnings(run)
    sec = Section(f"Flight: {flight.name}", f"flight-{flight.name}", warns, tables + [table])
    sec.figures += [
        ("NDVI quick-looks", lambda: plot_ndvi(flight)),
        ("Track", lambda: plot_track(flight)),
        ("Reflectance histograms", lambda: plot_histograms(flight)),
    ]
    return sec


def build_sections(calibration: str | Path | xr.Dataset | None = None,
                   flights: Iterable[str | Path | FlightResults] = (), stats: Any = None) -> list[Section]:
    """The report's sections; nothing is rendered yet. ``stats``: an ``mscal stats`` table
    (DataFrame or its Parquet/CSV path) for the season plots."""
    ds = _calibration(calibration)
    fl = [f if isinstance(f, FlightResults) else open_flight(f) for f in flights]
    if ds is None and not fl and stats is None:
        raise InputError("nothing to report",
                         hint="give --calibration CALIB.zarr, --flight OUT_DIR and/or --stats TABLE.parquet")
    sections = [calibration_section(ds, fl)] if ds is not None else []
    sections += [flight_section(f, ds) for f in fl]
    if stats is not None:
        sections += season_sections(stats)
    return sections


# --------------------------------------------------------------------------- season (issue 10)


def _stats_table(stats: Any) -> Any:
    if isinstance(stats, (str, Path)):
        from pipeline.products.zonal import read_table

        return read_table(stats)
    return stats


def season_series(table: Any, field_id: str, index: str) -> Any:
    """The rows of one field and index that have numbers and a date, by date: what
    :func:`plot_season` draws (a DataFrame with ``date``, ``flight``, ``mean``, ``median``,
    ``p10``, ``p90``, ``valid_fraction``)."""
    import pandas as pd

    t = table[(table["field_id"] == field_id) & (table["index"] == index) & (table["n_valid"] > 0)]
    t = t[t["date"].notna()].copy()
    t["date"] = pd.to_datetime(t["date"])
    return t.sort_values(["date", "flight"], kind="stable")[
        ["date", "flight", "mean", "median", "p10", "p90", "valid_fraction"]].reset_index(drop=True)


def plot_season(table: Any, field_id: str, index: str) -> Figure:
    """One field through the season: the median of ``index`` per flight (line), the p10-p90
    spread (band) and the mean (dashed), from the ``mscal stats`` table (:func:`season_series`)."""
    t = season_series(table, field_id, index)
    fig = Figure(figsize=(6.0, 2.6))
    ax = fig.add_subplot(1, 1, 1)
    if len(t):
        x = t["date"].to_numpy()
        ax.fill_between(x, t["p10"].to_numpy(float), t["p90"].to_numpy(float), color="tab:green", alpha=0.25,
                        label="p10-p90", linewidth=0)
        ax.plot(x, t["median"].to_numpy(float), "o-", color="tab:green", label="median", markersize=4)
        ax.plot(x, t["mean"].to_numpy(float), "--", color="k", linewidth=0.8, label="mean")
        ax.legend(fontsize=6, loc="best")
    else:
        ax.text(0.5, 0.5, "no flight with valid pixels and a date", ha="center", va="center", transform=ax.transAxes)
    ax.set_title(f"field {field_id}: {index}", fontsize=8)
    ax.set_ylabel(index, fontsize=7)
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.tick_params(labelsize=6)
    fig.autofmt_xdate()
    fig.tight_layout()
    return fig


def season_sections(stats: Any) -> list[Section]:
    """One section per index of an ``mscal stats`` table: a table of the fields (flights with
    numbers, rows without a date, rows whose status is not ``ok`` with the status) and the
    season plot of each field that has numbers."""
    table = _stats_table(stats)
    out = []
    for index in sorted(set(table["index"])):
        t = table[table["index"] == index]
        rows, figures = [], []
        for fid in dict.fromkeys(t["field_id"]):
            ft = t[t["field_id"] == fid]
            good = ft[ft["n_valid"] > 0]
            undated = int(good["date"].isna().sum())
            problems = sorted({f"{s}" for s in ft["status"] if s != "ok"})
            rows.append([fid, int(len(good)), undated, "; ".join(problems)])
            if len(good) - undated > 0:
                figures.append((f"field {fid}: {index} per flight (median, p10-p90, mean)",
                                lambda fid=fid, index=index: plot_season(table, fid, index)))
        note = ("Rows without a date are in the table but not on the plots. Statuses other than ok: see "
                "'mscal stats' in the README.")
        out.append(Section(f"Season: {index}", f"season-{index}",
                           tables=[Table(f"fields ({index})", ["field", "flights with values", "without date",
                                                               "other statuses"], rows, note)],
                           figures=figures))
    return out


def write_season_report(stats: Any, out_html: str | Path, title: str | None = None) -> Path:
    """A self-contained page of the season plots of an ``mscal stats`` table, atomically."""
    out_html = Path(out_html)
    write_text_atomic(out_html, sections_html(season_sections(stats), title or "mscal season report"))
    return out_html


# --------------------------------------------------------------------------- machine-readable


def calibration_summary(ds: xr.Dataset) -> dict[str, Any]:
    """``calibration.json``: per-band fit numbers, stage summaries, warnings."""
    t = band_table(ds)
    stages = {}
    for stage in ("response", "vignetting", "illumination"):
        st = _stage(ds, stage)
        if st:
            stages[stage] = {"residuals": st.get("residuals", {}), "skipped": st.get("skipped", []),
                             "inputs": len(st.get("inputs") or {}), "seconds": st.get("seconds")}
    out: dict[str, Any] = {
        "camera": ds.attrs.get("camera"), "mscal_version": ds.attrs.get("mscal_version"),
        "created_utc": ds.attrs.get("created_utc"), "fits": ds.attrs.get("fits", []),
        "bands": [dict(zip(t.columns, row)) for row in t.rows], "stages": stages,
        "warnings": [asdict(w) for w in calibration_warnings(ds)],
    }
    if "capture_spectral_factor" in ds:
        change = colour_change(ds["capture_spectral_factor"].values)
        out["reflector_captures"] = [
            {"name": str(ds["capture_name"].values[c]),
             "time": None if np.isnat(ds["capture_time"].values[c]) else str(ds["capture_time"].values[c])[:23] + "Z",
             "level": float(ds["capture_level"].values[c]),
             "irradiance": None if not np.isfinite(ds["capture_irradiance"].values[c]) else float(ds["capture_irradiance"].values[c]),
             "colour_change_from_previous": None if c == 0 else float(change[c - 1])}
            for c in range(ds.sizes["capture"])]
    if "reflector_dn" in ds:
        out["reflector_eq15_vs_eq16"] = [
            {"image": _reflector_images(ds)[r["image"]], "eq15_spread": r["eq15_spread"], "eq16_spread": r["eq16_spread"]}
            for r in reflector_corrections(ds)]
    return json.loads(json.dumps(out, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def report_dict(calibration: str | Path | xr.Dataset | None = None,
                flights: Iterable[str | Path | FlightResults] = ()) -> dict[str, Any]:
    """The report's warnings and tables as a JSON-able dict (no figures)."""
    return _sections_dict(build_sections(calibration, flights))


def _sections_dict(sections: Sequence[Section]) -> dict[str, Any]:
    return {"sections": [{
        "title": s.title, "warnings": [asdict(w) for w in s.warnings],
        "tables": [{"title": t.title, "columns": t.columns, "rows": [[_fmt(v) for v in r] for r in t.rows], "note": t.note}
                   for t in s.tables],
        "figures": [c for c, _ in s.figures]} for s in sections]}


def _md_cell(v: Any) -> str:
    return _fmt(v).replace("|", "\\|").replace("\n", " ")


def report_markdown(calibration: str | Path | xr.Dataset | None = None,
                    flights: Iterable[str | Path | FlightResults] = (), title: str | None = None) -> str:
    """The report's warnings and tables as markdown (e.g. a Prefect markdown artifact)."""
    return sections_markdown(build_sections(calibration, flights), title)


def sections_markdown(sections: Sequence[Section], title: str | None = None) -> str:
    lines = [f"# {title or 'mscal QA report'}", ""]
    for s in sections:
        lines += [f"## {s.title}", ""]
        if s.warnings:
            lines += ["| warning | message | value | threshold |", "| --- | --- | --- | --- |"]
            lines += [f"| {w.code} | {_md_cell(w.message)} | {_fmt(w.value)} | {_fmt(w.threshold)} |" for w in s.warnings]
        else:
            lines.append("No warnings.")
        lines.append("")
        for t in s.tables:
            lines += [f"### {t.title}", ""]
            if t.rows:
                lines += ["| " + " | ".join(t.columns) + " |", "|" + " --- |" * len(t.columns)]
                lines += ["| " + " | ".join(_md_cell(v) for v in r) + " |" for r in t.rows]
            if t.note:
                lines.append(f"_{t.note}_")
            lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- HTML

CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1300px;color:#222;padding:0 1em}
h1{font-size:1.5em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;font-size:.8em;margin:.5em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#f0f0f0}
td:first-child,th:first-child{text-align:left}
.warn{background:#fff4e0;border-left:4px solid #e69500;padding:.4em .8em;margin:.3em 0}
.ok{background:#e8f6e8;border-left:4px solid #3a3;padding:.4em .8em}
.quarantined td{background:#fde8e8}
figure{margin:1em 0}img{max-width:100%;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
.note{font-size:.8em;color:#666}
"""

#: Counts images that failed to decode once the page has loaded (checked by the slow test).
BROKEN_IMAGES_SCRIPT = (
    "window.addEventListener('load',function(){var n=0;"
    "document.querySelectorAll('img').forEach(function(i){if(!i.complete||i.naturalWidth===0){n++;}});"
    "document.body.setAttribute('data-broken-images',String(n));});"
)

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"


def _html_table(t: Table) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in t.columns)
    body = []
    for r in t.rows:
        cls = ' class="quarantined"' if "quarantined" in r else ""
        body.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in r) + "</tr>")
    note = f'<p class="note">{html.escape(t.note)}</p>' if t.note else ""
    table = f"<table><tr>{head}</tr>{''.join(body)}</table>" if t.rows else ""
    return f"<h3>{html.escape(t.title)}</h3>{table}{note}"


def _html_warnings(ws: Sequence[QAWarning]) -> str:
    if not ws:
        return '<p class="ok">No warnings.</p>'
    return "".join(f'<p class="warn"><b>{html.escape(w.code)}</b>: {html.escape(w.message)} '
                   f"(value {_fmt(w.value)}, threshold {_fmt(w.threshold)})</p>" for w in ws)


def _html_figure(caption: str, build: Callable[[], Figure]) -> str:
    png = base64.b64encode(figure_png(build())).decode("ascii")
    alt = html.escape(caption)
    return (f'<figure><img src="data:image/png;base64,{png}" alt="{alt}">'
            f"<figcaption>{alt}</figcaption></figure>")


def sections_html(sections: Sequence[Section], title: str) -> str:
    """The whole page: inline CSS, embedded PNGs, no external resource of any kind."""
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f'<meta http-equiv="Content-Security-Policy" content="{CSP}">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<nav>" + " · ".join(f'<a href="#{html.escape(s.anchor)}">{html.escape(s.title)}</a>' for s in sections) + "</nav>",
    ]
    for s in sections:
        parts.append(f'<section id="{html.escape(s.anchor)}"><h2>{html.escape(s.title)}</h2>')
        parts.append(_html_warnings(s.warnings))
        parts += [_html_table(t) for t in s.tables]
        parts += [_html_figure(c, fn) for c, fn in s.figures]
        parts.append("</section>")
    parts.append(f"<script>{BROKEN_IMAGES_SCRIPT}</script></body></html>")
    return "\n".join(parts)


def write_report(out_html: str | Path, *, calibration: str | Path | xr.Dataset | None = None,
                 flights: Iterable[str | Path | FlightResults] = (), title: str | None = None,
                 stats: Any = None) -> Path:
    """Write the self-contained ``out_html`` (atomically); with a calibration, also
    ``calibration.json`` beside it; with ``stats`` (an ``mscal stats`` table), the season
    plots. Returns the HTML path."""
    return write_report_and_markdown(out_html, calibration=calibration, flights=flights, title=title,
                                     stats=stats)[0]


def write_report_and_markdown(out_html: str | Path, *, calibration: str | Path | xr.Dataset | None = None,
                              flights: Iterable[str | Path | FlightResults] = (), title: str | None = None,
                              stats: Any = None) -> tuple[Path, str]:
    """:func:`write_report`, also returning the page's warnings and tables as markdown (for a
    Prefect artifact), from the same sections (the plots are made once)."""
    out_html = Path(out_html)
    ds = _calibration(calibration)
    sections = build_sections(ds, flights, stats)
    title = title or "mscal QA report" + (f": {ds.attrs.get('camera')}" if ds is not None else "")
    page = sections_html(sections, title)
    if ds is not None:
        write_text_atomic(out_html.parent / "calibration.json", json.dumps(calibration_summary(ds), indent=2))
    write_text_atomic(out_html, page)
    return out_html, sections_markdown(sections, title)
