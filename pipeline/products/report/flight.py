"""Frames of one apply output: the table, light levels, DN outside the sweep, the
warnings (:func:`flight_warnings`) and the plots (NDVI with the stored vegetation mask's
segmentation, track, histograms).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import xarray as xr
from mscal_core.reflectance import ndvi, otsu_ndvi_threshold, vegetation_mask

from pipeline.ingest.medians import DN_MEDIAN, median_uint16
from pipeline.products.report.calibration import band_name_of, stage_residuals
from pipeline.products.report.figures import band_titles, few_ticks, image_axes, panel_figure
from pipeline.products.report.inputs import FlightResults
from pipeline.products.report.thresholds import (
    FLIGHT_DN_OUTSIDE_SWEEP_MAX,
    FRAME_LEVEL_RATIO_MAX,
    HIST_MAX_FRAMES,
    HIST_MAX_PIXELS,
    LEVEL_MAX_FRAMES,
    NDVI_MAX_FRAMES,
    SATURATED_FRACTION_MAX,
    QAWarning,
)
from pipeline.storage.chunks import FrameChunks

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- flight data


def sample_indices(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices evenly spaced over ``range(n)`` (first and last included)."""
    if n <= 0:
        return np.zeros(0, dtype=int)
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int))


def _stride(shape: Sequence[int], max_pixels: int) -> int:
    return max(1, math.ceil(math.sqrt(shape[-2] * shape[-1] / max_pixels)))


def _sampled(da: xr.DataArray, frames: np.ndarray, max_pixels: int, chunks: FrameChunks | None = None) -> np.ndarray:
    """``da[frames, ..., ::s, ::s]`` in memory, one whole frame decoded at a time per thread
    (bounded memory): straight from the whole-frame chunk files of ``chunks``
    (:func:`_chunk_files`), a thread per core (file reads and blosc release the GIL), else
    through xarray one frame at a time. Through xarray the 12 raw frames of the warnings that
    ``mscal apply`` prints took 0.15 s after every 600-frame run; from the files 0.02-0.03 s."""
    s = _stride(da.shape, max_pixels)
    if chunks is not None:
        try:
            return np.stack(_thread_map(lambda f: chunks.read(int(f))[..., ::s, ::s].copy(), frames))
        except FileNotFoundError:  # a frame without its chunk: zarr gives the fill value
            pass
    return np.stack([np.asarray(da.isel(frame=int(f)).values[..., ::s, ::s]) for f in frames])


def _thread_map(fn: Callable[[Any], np.ndarray], items: Sequence[Any]) -> list[np.ndarray]:
    """``[fn(x) for x in items]``, on a thread per core."""
    n = min(len(items), os.cpu_count() or 1)
    if n <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(fn, items))


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
    frames = [int(f) for f in sample_indices(len(names), LEVEL_MAX_FRAMES)]
    if DN_MEDIAN in raw:  # written with each frame: no frame decoded again
        med = _stored_medians(flight, b, frames)
        for m, f in zip(med, frames):
            out[names[f]] = float((m - black) / t[f]) if t[f] > 0 else float("nan")
        return out
    for f, dn in _qa_bands(flight, b, frames):
        out[names[f]] = _level(dn, black, t[f])
    return out


def _stored_medians(flight: FlightResults, b: int, frames: Sequence[int]) -> np.ndarray:
    """The stored median DN of band ``b`` in each of ``frames`` (raw.zarr's ``dn_median``, one
    small chunk per frame): only those frames' chunks, read straight from their files where the
    layout allows (:class:`pipeline.storage.chunks.FrameChunks`), else through xarray. Reading
    every frame's chunk through xarray took 0.19 s of a 600-frame apply's summary and grew with
    the flight; 400 chunks through zarr 0.15 s; straight from the files a tenth of that."""
    da = flight.raw[DN_MEDIAN]
    chunks = _chunk_files(flight, DN_MEDIAN)
    if chunks is not None:
        try:
            return np.array([chunks.read(f)[b] for f in frames], dtype=np.float64)
        except FileNotFoundError:  # a frame without its chunk: zarr gives the fill value
            pass
    return np.asarray(da.isel(band=b, frame=list(frames)).values, dtype=np.float64)


def _level(dn: np.ndarray, black: float, t: float) -> float:
    """``median(DN - black) / t`` of one band. Without a black level, DN of 16 bits or fewer
    take :func:`median_uint16` (the same value as ``np.median`` of their float64 copy)."""
    if not t > 0:
        return float("nan")
    if black == 0.0 and dn.dtype.kind == "u" and dn.dtype.itemsize <= 2 and dn.size:
        return float(median_uint16(dn) / t)
    return float(np.median(np.asarray(dn, dtype=float) - black) / t)


def _chunk_files(flight: FlightResults, name: str, store: str = "raw.zarr") -> FrameChunks | None:
    """The whole-frame chunk files of ``store``'s ``name`` (frame, band, ...), where its layout
    is one :class:`pipeline.storage.chunks.FrameChunks` reads and matches the opened array
    (dims, shape, dtype, and values as stored: no scale, offset or fill value other than NaN
    for xarray to apply); None: read it through xarray."""
    da = (flight.raw if store == "raw.zarr" else flight.reflectance)[name]
    chunks = FrameChunks.open(flight.out / store / name)
    fill = da.encoding.get("_FillValue")
    as_stored = (not {"scale_factor", "add_offset"} & set(da.encoding)
                 and (fill is None or (da.dtype.kind == "f" and np.isnan(fill))))
    ok = (chunks is not None and da.dims[:2] == ("frame", "band") and chunks.shape == da.shape
          and chunks.dtype == da.dtype and as_stored)
    return chunks if ok else None


def _qa_bands(flight: FlightResults, b: int, frames: Sequence[int]):  # a generator
    """``(frame, DN of band b)`` of each of ``frames``: straight from the whole-frame chunk
    files where raw.zarr's layout allows (:class:`pipeline.storage.chunks.FrameChunks`: one
    read and decode per frame, no dask graph), else a few frames per dask read."""
    dn = flight.raw["dn"]
    chunks = _chunk_files(flight, "dn")
    if chunks is not None:
        for f in frames:
            yield f, chunks.read(f)[b]
        return
    # a few frames per read: one dask compute decodes their chunks in parallel (one read per
    # frame cost ~10 ms of scheduling each, 3 s on a 300-frame flight)
    for start in range(0, len(frames), LEVEL_READ_BATCH):
        batch = list(frames[start:start + LEVEL_READ_BATCH])
        block = dn.isel(band=b).isel(frame=batch).values
        for i, f in enumerate(batch):
            yield f, block[i]


LEVEL_READ_BATCH = 8  # frames decoded per read in frame_levels (8 full-resolution bands: ~35 MB)


def _qa_band(flight: FlightResults) -> int:
    roles = _role_bands(flight)
    if roles is not None:
        return roles[1]
    return int(flight.reflectance.sizes.get("band", 1)) // 2


def dn_outside_sweep(flight: FlightResults, calibration: xr.Dataset) -> tuple[float, int]:
    """Fraction of sampled flight DN above the highest unsaturated DN the sweep observed
    (and below saturation), and the worst band."""
    observed = stage_residuals(calibration, "response").get("observed_dn")
    raw = flight.raw
    if not observed or raw is None or "dn" not in raw:
        return float("nan"), -1
    frames = sample_indices(raw.sizes["frame"], HIST_MAX_FRAMES)
    dn = _sampled(raw["dn"], frames, HIST_MAX_PIXELS, _chunk_files(flight, "dn"))  # (frame, band, h, w)
    sat = calibration["saturation_dn"].values if "saturation_dn" in calibration else np.full(dn.shape[1], np.inf)
    frac = np.array([np.mean((dn[:, b] > observed[b][1]) & (dn[:, b] < sat[b])) for b in range(dn.shape[1])])
    b = int(np.argmax(frac))
    return float(frac[b]), b


#: At most this many per-frame lines on flagged pixels (:func:`flagged_pixels`), then one naming
#: the frames left.
MAX_FLAGGED_LINES = 20
#: Frames the last line of :func:`flagged_pixels` names before "...".
MAX_MORE_FRAMES = 10
#: What each flag of ``reflectance.zarr/quality`` (run.json ``quality``) warned of says of its
#: pixels. Not warned of per frame: ``saturated`` (its own warning, ``saturated_fraction``) and
#: ``no_value`` (it holds the borders the bands' alignment leaves on every frame).
FLAGGED = {
    "response_shoulder": "on the response's shoulder",
    "outside_sweep": "outside the response sweep's DN range",
    "vignetting_unobserved": "where no view observed the vignetting",
    "not_coregistered": "of a band that failed the co-registration check",
}


def flagged_pixels(run: dict[str, Any], limit: int = MAX_FLAGGED_LINES) -> list[QAWarning]:
    """One warning per frame and flag of :data:`FLAGGED` in run.json ``quality``, naming every
    band it flags with its pixels ("frame IMG_0003: 1,234 pixels on the response's shoulder in
    2 bands (b670 1,000, b678 234), set to NaN"; the value is the pixels), at most ``limit``
    then one naming the frames left (a flight of many frames on the shoulder still names each
    band of the first ``limit`` lines, not the first frame's bands only)."""
    q = run.get("quality") or {}
    kept = "kept" if q.get("keep_flagged") else "set to NaN"
    out, frames = [], []
    for frame, bands in (q.get("frames") or {}).items():
        for flag, says in FLAGGED.items():
            per_band = {band: int(flags[flag]) for band, flags in bands.items() if flags.get(flag)}
            if not per_band:
                continue
            n = sum(per_band.values())
            named = ", ".join(f"{band} {v:,}" for band, v in per_band.items())
            out.append(QAWarning(f"flagged_{flag}", f"frame {frame}: {n:,} pixels {says} in {len(per_band)} "
                                                    f"band{'s' if len(per_band) > 1 else ''} ({named}), {kept}",
                                 float(n), 0.0))
            frames.append(frame)
    if len(out) > limit:
        more, left = out[limit:], list(dict.fromkeys(frames[limit:]))
        names = ", ".join(left[:MAX_MORE_FRAMES]) + (" ..." if len(left) > MAX_MORE_FRAMES else "")
        out = out[:limit] + [QAWarning("flagged_more", f"and {len(more)} more frame/flag counts of flagged pixels in "
                                                       f"{len(left)} frame(s): {names} (run.json quality.frames)",
                                       float(sum(w.value for w in more)), 0.0)]
    return out


def flight_warnings(flight: FlightResults, calibration: xr.Dataset | None = None) -> list[QAWarning]:
    """Findings on one flight: quarantined frames, saturation, DN beyond the sweep,
    frames whose exposure contradicts their brightness, pixels the quality mask flags
    (:func:`flagged_pixels`)."""
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
            hi = stage_residuals(calibration, "response")["observed_dn"][b][1]
            out.append(QAWarning("flight_dn_outside_sweep",
                                 f"{frac:.2%} of the flight's DN at {band_name_of(calibration, b)} are above the "
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
    return out + flagged_pixels(run)


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
    from matplotlib.figure import Figure

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
            image_axes(ax)
            thr = otsu_ndvi_threshold(p[key])  # the stored vegetation_mask's segmentation
            ax = fig.add_subplot(len(pairs), 4, 4 * i + j + 3)
            ax.imshow(vegetation_mask(p[key]) == 1, cmap="Greens", vmin=0, vmax=1, interpolation="nearest")
            ax.set_title(f"Otsu on {kind} (NDVI >= {thr:.2f})", fontsize=7)
            image_axes(ax)
    fig.suptitle("NDVI quick-looks: raw DN vs calibrated (paper Fig. 1e/f)", fontsize=9)
    return fig


def plot_track(flight: FlightResults) -> Figure:
    """Frame positions (lon, lat) in flight order; first frame a square, last a triangle."""
    ds = flight.reflectance
    from matplotlib.figure import Figure

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
    r = _sampled(ds["reflectance"], frames, HIST_MAX_PIXELS,
                 _chunk_files(flight, "reflectance", "reflectance.zarr"))  # (frame, band, h, w)
    finite = r[np.isfinite(r)]
    lo, hi = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
    edges = np.linspace(float(lo), float(max(hi, lo + 1e-6)), 61)
    fig, axes = panel_figure(r.shape[1], panel_in=1.9)
    for b, (ax, title) in enumerate(zip(axes, band_titles(ds))):
        v = r[:, b][np.isfinite(r[:, b])]
        counts, _ = np.histogram(v, bins=edges)
        ax.stairs(counts, edges, fill=True, color="C0")  # one artist, not one bar per bin
        ax.set_title(f"{title} (median {np.median(v) if v.size else float('nan'):.3g})", fontsize=7)
        few_ticks(ax)
        ax.set_yticks([])
    fig.suptitle(f"Reflectance per band ({len(frames)} of {ds.sizes['frame']} frames, "
                 f"pixel stride {_stride(ds['reflectance'].shape, HIST_MAX_PIXELS)})", fontsize=9)
    return fig


