"""The report model: :class:`Section` (title, warnings, tables, figures) and
:class:`Table`; the sections of a calibration and of a flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import xarray as xr
from mscal_core.homography import local_motion

from pipeline.ingest.sunsensor import stored_sun_sensor_model
from pipeline.products.report.calibration import (
    band_name_of,
    calibration_warnings,
    plot_brightness,
    plot_coverage,
    plot_inverse_response,
    plot_light_over_time,
    plot_reflector_correction,
    plot_spectral_factor,
    plot_vignetting,
    stage_residuals,
    stage_results,
    sweep_coverage,
    worst_of,
)
from pipeline.products.report.coregistration import coregistration_tables, coregistration_warnings
from pipeline.products.report.flight import flight_warnings, frame_rows, plot_histograms, plot_ndvi, plot_track
from pipeline.products.report.inputs import FlightResults
from pipeline.products.report.table import Table
from pipeline.products.report.thresholds import (
    PANEL_DLS_COLOUR_SPREAD_MAX,
    REGISTRATION_SPREAD_MAX_PX,
    TABLE_MAX_ROWS,
    QAWarning,
)
from pipeline.storage.run_layout import run_value

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- the report model


@dataclass
class Section:
    """One part of the report: warnings, tables, and figure builders (rendered only for HTML)."""

    title: str
    anchor: str
    warnings: list[QAWarning] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[tuple[str, Callable[[], Figure]]] = field(default_factory=list)


def fmt_value(v: Any, digits: int = 4) -> str:
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
    r, v = stage_residuals(ds, "response"), stage_residuals(ds, "vignetting")
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
            for s in stage_results(ds, stage).get("skipped", [])]
    return Table("Frames skipped by the fits", ["stage", "file", "reason"], rows,
                 note="" if rows else "none")


def _band_label(ds: xr.Dataset, b: int) -> str:
    """``Green (560 nm)``: the band's name and wavelength (multi-lens cameras name their bands)."""
    if "band_name" in ds.coords:
        return f"{ds['band_name'].values[b]} ({band_name_of(ds, b)})"
    return band_name_of(ds, b)


def _registration(ds: xr.Dataset) -> dict[str, Any]:
    rec = ds.attrs.get("registration")
    return rec if isinstance(rec, dict) else {}


def registration_table(ds: xr.Dataset) -> Table | None:
    """Per band of a registered store (``mscal register``): what the session transform does
    at the image centre (shift, rotation, scale; :func:`mscal_core.homography.local_motion`),
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
        b, worst = worst_of([float(v) if np.isfinite(v) else float("nan") for v in spread])
        if b >= 0 and worst > REGISTRATION_SPREAD_MAX_PX:
            out.append(QAWarning(
                "registration_spread",
                f"the registered captures disagree by {worst:.1f} px at {_band_label(ds, b)}: parallax between "
                "captures at different distances (e.g. a panel capture beside flight captures) or a failed "
                "registration; frames that were not registered take the session transform, so register captures "
                "from the flight's altitude",
                worst, REGISTRATION_SPREAD_MAX_PX))
    return out


def capture_level_table(ds: xr.Dataset) -> Table | None:
    """Per reflector capture: its time, brightness level and sun-sensor level, and how the
    sensor level was obtained (store attribute ``sun_sensor_model``). None when no
    capture has a sensor level."""
    if "capture_irradiance" not in ds:
        return None
    irr = np.asarray(ds["capture_irradiance"].values, dtype=np.float64)
    if not np.isfinite(irr).any():
        return None
    model = stored_sun_sensor_model(ds["capture_irradiance"].attrs) or "raw reading (store written before horizontal levels)"
    names = ds["capture_name"].values if "capture_name" in ds else range(irr.size)
    times = ds["capture_time"].values if "capture_time" in ds else [None] * irr.size
    levels = ds["capture_level"].values if "capture_level" in ds else [np.nan] * irr.size
    rows = [[str(n), None if t is None or np.isnat(t) else str(np.datetime_as_string(t, unit="s")),
             float(lv), None if not np.isfinite(e) else float(e)]
            for n, t, lv, e in zip(names, times, levels, irr)]
    return Table("Sun-sensor level of each reflector capture", ["capture", "time (UTC)", "level of S", "sun-sensor level"],
                 rows, note=f"sun-sensor level: {model}; a flight frame's light is scaled by its own level over the "
                            "captures' (interpolated in time)")


def calibration_section(ds: xr.Dataset, flights: Sequence["FlightResults"] = ()) -> Section:
    tables = [band_table(ds), skipped_table(ds)]
    tables += [t for t in (capture_level_table(ds),) if t is not None]
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


#: run.json ``reference`` keys saying why a light reference before the one used was not used.
REFERENCE_WHY = ("albedo", "albedo_panel_unusable", "panel_serial_none", "panel_serial_unknown", "panel_serial_unusable")


def reference_table(run: dict[str, Any], band_names: Sequence[str] = ()) -> Table | None:
    """The reflectance reference of a factory apply (run.json ``reference``): per panel capture
    and band, the panel's factor (Eq. 11-14 split and plain mean) beside the sun sensor's
    ``pi / E`` on the same capture and their ratio, bands in ``band_names`` order (the
    camera's; run.json keeps them sorted by name). None for runs without one."""
    rec = run_value(run, "reference")
    if not isinstance(rec, dict):
        return None
    # why the references before this one (the camera's Albedo, the panel's serial) were not used
    why = "; ".join(f"{k.replace('_', ' ')}: {rec[k]}" for k in REFERENCE_WHY if rec.get(k))
    if rec.get("route") not in ("panel", "panel-dls"):
        return Table("Reflectance reference", ["route", "formula"], [[rec.get("route"), rec.get("formula")]],
                     note="each capture's own sun-sensor reading; no panel to compare it with "
                          "(give --panel-reflectance to use and compare a panel capture)" + (f". {why}" if why else ""))
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
                 rows, note=(f"panel reflectance: {rec['panel_reflectance']}. " if rec.get("panel_reflectance") else "")
                 + f"{rec.get('formula')}; a panel/DLS ratio equal in all bands is the DLS's tilt "
                   "(brightness only), a spread across bands changes every index" + (f". {why}" if why else ""))


def time_warnings(run: dict[str, Any]) -> list[QAWarning]:
    """Capture times on two clocks (run.json ``capture_times``: some in UTC because the files
    say their zone, some as written): the sun's position and the light between panels are off
    by the time zone for the latter."""
    out: list[QAWarning] = []
    times = run_value(run, "capture_times")
    if isinstance(times, dict) and times.get("utc") and times.get("as_written"):
        first = times.get("first") or {}
        out.append(QAWarning(
            "mixed_time_zones", f"{times['utc']} capture(s) have their time in UTC (e.g. {first.get('utc')}) and "
            f"{times['as_written']} as written, zone unknown (e.g. {first.get('as_written')}): the sun's position and "
            "the light between panels may be off by the time zone for the latter; check those files' "
            "OffsetTimeOriginal / drone-dji:UTCAtExposure tags", float(times["as_written"]), 0.0))
    return out


def reference_warnings(run: dict[str, Any]) -> list[QAWarning]:
    """A panel capture whose panel/DLS factor ratio spreads across bands by more than
    :data:`PANEL_DLS_COLOUR_SPREAD_MAX`; panel captures seen in the folder but not used; a run
    without reflectance (route ``none``: radiance only, why and how to get it), band files of
    the sun-sensor route without a usable reading (run.json ``reflectance_missing``), and the
    camera's own panel captures (XMP Albedo) that could not be used."""
    rec = run_value(run, "reference")
    out: list[QAWarning] = []
    if not isinstance(rec, dict):
        return out
    if rec.get("route") == "none":
        frames = int(run.get("frames_out") or 0)
        why = f" ({rec['reason']})" if rec.get("reason") else ""
        out.append(QAWarning(
            "no_reflectance", f"reflectance and indices are NaN in all {frames} frame(s), radiance only: no panel "
            f"given and the sun sensor gives no usable reflectance{why}: {rec.get('hint', 'give --panel-reflectance TARGET')}",
            float(frames), 0.0))
    missing = run_value(run, "reflectance_missing") or []
    if missing:
        first = missing[0]
        captures = len({m.get("capture") for m in missing})
        # runs before the products choice wrote the radiance always
        kept = "radiance kept" if (run.get("products") or {"radiance": True}).get("radiance") else \
            "radiance written with --products radiance"
        out.append(QAWarning(
            "reflectance_missing", f"{len(missing)} band file(s) of {captures} capture(s) have no usable sun-sensor "
            f"reading: their reflectance and the indices using them are NaN, {kept} (run.json "
            f"reflectance_missing; first {first.get('file')}: {first.get('reason')}); a panel capture with "
            "--panel-reflectance TARGET gives every band reflectance", float(len(missing)), 0.0))
    if rec.get("albedo_panel_unusable"):
        out.append(QAWarning(
            "albedo_panel_unusable", f"the camera's panel capture(s) (XMP Albedo) could not be used "
            f"({rec['albedo_panel_unusable']}): reflectance comes from the {rec.get('route')} route instead; name the "
            "panel capture with --panel, or give --panel-reflectance TARGET", 1.0, 0.0))
    seen = rec.get("panels_seen") or []
    if seen and rec.get("route") != "panel":
        source = "the sun sensor (DLS)" if rec.get("route") == "dls" else "nothing (radiance only)"
        out.append(QAWarning(
            "panel_not_used", f"{len(seen)} panel capture(s) in the folder ({', '.join(seen[:5])}) but reflectance "
            f"comes from {source}: {rec.get('panel_hint', 'give --panel-reflectance TARGET')}",
            float(len(seen)), 0.0))
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


def _band_order(values: dict[str, Any], band_names: Sequence[str]) -> list[str]:
    return [b for b in band_names if b in values] + sorted(b for b in values if b not in band_names)


def light_tables(run: dict[str, Any], band_names: Sequence[str] = ()) -> list[Table]:
    """The light of a factory apply over time (run.json ``light``): per panel capture
    and band the panel's irradiance beside the sun sensor's (tilt-corrected) and their ratio;
    per frame the light it was given. [] for runs without one."""
    rec = run_value(run, "light")
    if not isinstance(rec, dict):
        return []
    unit = rec.get("irradiance_unit", "")
    rows = []
    for p in rec.get("panels_over_time") or []:
        panel, sensor = p.get("panel_irradiance") or {}, p.get("sensor_irradiance") or {}
        for band in _band_order(panel, band_names):
            e_p, e_s = panel.get(band), sensor.get(band)
            rows.append([p.get("capture"), band, e_p, e_s, (e_p / e_s) if e_p and e_s else None])
    drift = rec.get("panel_sensor_drift") or {}
    tables = [Table("Light over time: panels and sun sensor", ["panel capture", "band", f"panel E ({unit})",
                    "sun sensor E (tilt-corrected)", "panel / sensor"], rows,
                    note="panel/sensor drift per band (max/min - 1 over the panels): "
                         + ", ".join(f"{b} {drift[b]:.1%}" for b in _band_order(drift, band_names) if drift[b] is not None))]
    frames = rec.get("frame_irradiance") or {}
    if frames:
        first = next(iter(frames.values()))
        order = _band_order(first, band_names)
        shown = list(frames.items())[:TABLE_MAX_ROWS]
        tables.append(Table(f"Light at each frame ({unit})", ["frame", *order, "sun sensor used"],
                            [[n, *[v.get(b) for b in order], (rec.get("sensor_used") or {}).get(n)] for n, v in shown],
                            note=f"first {len(shown)} of {len(frames)} frames; all in run.json light"
                            if len(frames) > len(shown) else rec.get("route", "")))
    return tables


def light_warnings(run: dict[str, Any]) -> list[QAWarning]:
    """run.json ``light.warnings``: panels and sun sensor disagreeing on the light's change, a
    sensor tilted too far (each with its number and threshold)."""
    rec = run_value(run, "light")
    if not isinstance(rec, dict):
        return []
    return [QAWarning(str(w.get("code")), str(w.get("message")), float(w.get("value")), float(w.get("threshold")))
            for w in rec.get("warnings") or []]


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
    tables += light_tables(run, flight.camera.band_names if flight.camera is not None else ())
    tables += coregistration_tables(run, flight.camera.band_names if flight.camera is not None else ())
    warns += light_warnings(run) + time_warnings(run) + coregistration_warnings(run)
    sec = Section(f"Flight: {flight.name}", f"flight-{flight.name}", warns, tables + [table])
    sec.figures += [
        ("NDVI quick-looks", lambda: plot_ndvi(flight)),
        ("Track", lambda: plot_track(flight)),
        ("Reflectance histograms", lambda: plot_histograms(flight)),
    ]
    return sec


