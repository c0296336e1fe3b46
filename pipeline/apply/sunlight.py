"""Panels over time and a sun sensor: the light of every capture from panel captures
anchored by the sensor.

The sun sensor's reading of each capture and band made horizontal (tags, sun position, tilt
model, the diffuse ratio fitted from the flight on the panel routes: :data:`RATIO_RULES`) is
:func:`pipeline.ingest.sunsensor.sensor_light` (the vendors' tags and documents are listed
there); here the panels anchor it: :func:`panel_sensor_light` and the warnings of
:func:`light_warnings` (run.json ``light``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from mscal_core.illumination import capture_weights
from mscal_core.sunsensor import anchored_irradiance, ratio_drift

from pipeline.ingest.grouping import Capture
from pipeline.ingest.sunsensor import SensorLight

#: Above this tilt of the sensor against the vertical, or with the sun behind it, the reading
#: rests on the diffuse model alone: flagged in run.json and the report.
TILT_WARN_DEG = 20.0
#: Panels and sensor disagree on the light's change when their ratio varies by more than this
#: between panel captures (per band; :func:`mscal_core.sunsensor.ratio_drift`).
RATIO_DRIFT_WARN = 0.03


@dataclass(frozen=True)
class PanelSensorLight:
    """``k_b`` of every capture from panels anchored by the sun sensor, and the figures for
    run.json and the report."""

    factor: np.ndarray  # (n_captures, n_bands)
    sensor_used: np.ndarray  # (n_captures, n_bands) bool
    ratio: np.ndarray  # (n_captures, n_bands) interpolated panel / sensor ratio
    drift: np.ndarray  # (n_bands,) ratio_drift over the panels


def seconds(times: np.ndarray) -> np.ndarray:
    """datetime64 to float seconds since the epoch (NaN for NaT)."""
    t = np.asarray(times).astype("datetime64[ns]")
    return np.where(np.isnat(t), np.nan, t.astype(np.int64) / 1e9)


def panel_sensor_light(panel_factor: np.ndarray, panel_index: Sequence[int], times: np.ndarray,
                       sensor: SensorLight | None, mode: str) -> PanelSensorLight:
    """``k_b(tau)`` of every capture: the panels' light ``1 / k_c`` interpolated in time
    (``mode``), carried between and beyond them by the sensor when ``sensor`` is given
    (:func:`mscal_core.sunsensor.anchored_irradiance`); ``panel_index``: each panel's capture."""
    t = seconds(times)
    ep = 1.0 / np.asarray(panel_factor, dtype=np.float64)
    idx = list(panel_index)
    w = capture_weights(t[idx], t, mode) if len(idx) > 1 else np.ones((t.size, 1))
    if sensor is None:
        es = np.full_like(ep, np.nan)
        ef = np.full((t.size, ep.shape[1]), np.nan)
    else:
        es, ef = sensor.irradiance[idx], sensor.irradiance
    light = anchored_irradiance(ep, es, w, ef)
    return PanelSensorLight(1.0 / light.irradiance, light.sensor_used, light.ratio, ratio_drift(ep, es))


def check_times(captures: Sequence[Capture], times: np.ndarray, n_panels: int, folder: Path) -> None:
    """Several panels are interpolated in time: every capture needs one (InputError naming the folder)."""
    from mscal_core.errors import InputError

    t = seconds(times)
    if n_panels > 1 and not np.all(np.isfinite(t)):
        missing = [captures[f].name for f in np.flatnonzero(~np.isfinite(t))[:3]]
        raise InputError(f"capture(s) {', '.join(missing)} have no time (EXIF DateTimeOriginal), but the light of "
                         f"{n_panels} panel captures is interpolated to each capture's time", path=folder,
                         hint="name one panel capture with --panel, or fix the files' time tags")


def light_warnings(names: Sequence[str], bands: Sequence[str], sensor: SensorLight | None,
                   light: PanelSensorLight | None, panel_names: Sequence[str]) -> list[dict[str, Any]]:
    """Warnings with their numbers and thresholds: panels and sensor disagree on the light's
    change (:data:`RATIO_DRIFT_WARN`); a sensor tilted beyond :data:`TILT_WARN_DEG` or facing
    away from the sun (its reading rests on the diffuse model)."""
    out: list[dict[str, Any]] = []
    if light is not None and len(panel_names) > 1:
        for b, band in enumerate(bands):
            d = float(light.drift[b])
            if np.isfinite(d) and d > RATIO_DRIFT_WARN:
                out.append({"code": "panel_sensor_disagree", "band": band, "value": round(d, 6),
                            "threshold": RATIO_DRIFT_WARN,
                            "message": f"{band}: panels {', '.join(panel_names)} and the sun sensor disagree on the "
                                       f"light's change by {d:.1%} (> {RATIO_DRIFT_WARN:.0%}): the light between them "
                                       "follows the sensor, rescaled linearly"})
    if sensor is not None:
        for c, name in enumerate(names):
            tilt, inc = sensor.tilt_deg[c], sensor.incidence_deg[c]
            if np.isfinite(tilt) and (tilt > TILT_WARN_DEG or inc >= 90.0):
                out.append({"code": "sun_sensor_tilt", "capture": str(name), "value": round(float(tilt), 3),
                            "threshold": TILT_WARN_DEG,
                            "message": f"{name}: sun sensor tilted {tilt:.1f} deg (sun incidence {inc:.1f} deg; warn "
                                       f"above {TILT_WARN_DEG:.0f} deg or 90 deg): its light rests on the diffuse model"})
    return out


def readings_missing(captures: Sequence[Capture]) -> bool:
    """True when no band of any capture has a sun-sensor reading."""
    return not any(m.irradiance is not None and m.irradiance > 0 for c in captures for m in c.metas)


#: run.json ``sun_sensor.diffuse_ratio_rule``: where the tilt model's diffuse ratio (without a
#: measured split) may come from the flight's readings, per route.
RATIO_RULES = {
    "dls": "clear-sky 1/6 (or a DLS 2's measured split), never fitted from the flight: a capture's reflectance "
           "depends on its own files only",
    "panel-dls": "fitted per band from the flight's readings on 10+ captures at changing attitudes (else clear-sky "
                 "1/6): part of the light's interpolation between the panels, which anchor the scale; a capture's "
                 "factor depends on its flight",
    "panel": "as for panel-dls; not used for reflectance (the panels alone set it)",
}

__all__ = ["RATIO_RULES", "PanelSensorLight", "check_times", "light_warnings", "panel_sensor_light", "readings_missing", "seconds",
           "RATIO_DRIFT_WARN", "TILT_WARN_DEG"]
