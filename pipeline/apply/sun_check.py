"""Sun-sensor magnitudes checked against the sky (run.json ``sun_sensor_check``).

Each absolute sun-sensor reading (MicaSense, W m-2 nm-1 after the file's unit rule, made
horizontal by :func:`pipeline.ingest.sunsensor.sensor_light`) is compared with the clear sky's
spectral irradiance at the capture's sun elevation and the band's wavelength
(:mod:`pipeline.ingest.clear_sky`). MicaSense documents two unit rules that disagree on DLS 2
files without ``IrradianceScaleToSIUnits``: its library (micasense/imageprocessing
``metadata.py`` ``irradiance_scale_factor()``) takes their irradiance tags in uW cm-2 nm-1 (x
0.01), but a RedEdge-M with firmware 7.4.0 and a DLS 2 v1.3.0 wrote ``SpectralIrradiance`` 0.77
and ``HorizontalIrradiance`` 0.20 already in W m-2 nm-1 at a sun elevation of 8.5 degrees: read
x 0.01 they were 80 times too low against the flight's own panel. For those files the rule whose
value is plausible and closest to the clear sky is taken (:func:`pipeline.ingest.clear_sky.
choose_rule`); every other file has one rule, checked the same way. A reading no rule puts in
:data:`pipeline.ingest.clear_sky.PLAUSIBLE_RATIO` is warned (``sun_sensor_implausible``, in
run.json ``light.warnings``: the summary and the report). Relative sensors (DJI, Sequoia) are
not in W m-2 nm-1: not checked.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from pipeline.ingest.camera_meta import sun_sensor_xmp
from pipeline.ingest.clear_sky import MODEL, PLAUSIBLE_RATIO, choose_capture_rule, choose_rule, clear_sky_spectral
from pipeline.ingest.grouping import Capture
from pipeline.ingest.meta import CaptureMeta
from pipeline.ingest.sun_scale import sun_scale
from pipeline.ingest.sunsensor import SensorLight, file_xmp
from pipeline.ingest.xmp import TagError

MICASENSE_NS = ("Camera", "MicaSense", "DLS")
LIBRARY_RULE = "x 0.01: uW cm-2 nm-1 (MicaSense library, DLS 2 without IrradianceScaleToSIUnits)"
AS_WRITTEN_RULE = "x 1: W m-2 nm-1 as written (DLS 2 firmware that wrote SI units without the scale tag)"


@dataclass(frozen=True)
class SunCheck:
    """The check of every capture's sun sensor: the factor on each reading (the chosen rule's
    scale over the reader's, 1 where nothing changed), run.json's record and warnings."""

    multiplier: np.ndarray  # (n_captures, n_bands)
    record: dict[str, Any]
    warnings: list[dict[str, Any]]

    def apply(self, sensor: SensorLight) -> SensorLight:
        """``sensor`` with each reading on its chosen unit rule (factor / m, irradiance x m)."""
        if np.all(self.multiplier == 1.0):
            return sensor
        return dataclasses.replace(sensor, factor=sensor.factor / self.multiplier,
                                   irradiance=sensor.irradiance * self.multiplier)


    def panels(self, panels: Sequence[Any], names: Sequence[str]) -> list[Any]:
        """Panel references (``factor_dls``: the sun sensor's factor on the panel capture) with
        each reading on its chosen unit rule, so that panel and sensor compare as read."""
        out = []
        for p in panels:
            m = self.multiplier[list(names).index(p.capture)]
            dls = tuple(None if k is None else k / float(mb) for k, mb in zip(p.factor_dls, m))
            out.append(p if dls == tuple(p.factor_dls) else dataclasses.replace(p, factor_dls=dls))
        return out


def unit_rules(meta: CaptureMeta) -> tuple[dict[str, float], float]:
    """A MicaSense band file's unit rules ``{rule: scale to W m-2 nm-1}`` and the scale the
    reader applied (:func:`pipeline.ingest.cameras.micasense.irradiance_scale`)."""
    x = sun_sensor_xmp(meta) or file_xmp(meta.path)
    try:
        v = x.numbers("IrradianceScaleToSIUnits", MICASENSE_NS)
    except TagError:
        v = None
    if v is not None and math.isfinite(v[0]) and v[0] > 0:
        return {f"x {v[0]:g}: XMP IrradianceScaleToSIUnits": float(v[0])}, float(v[0])
    if x.has("HorizontalIrradiance", MICASENSE_NS):
        return {LIBRARY_RULE: 0.01, AS_WRITTEN_RULE: 1.0}, 0.01
    return {"x 1: W m-2 nm-1 (DLS 1)": 1.0}, 1.0


def sun_sensor_check(captures: Sequence[Capture], sensor: SensorLight, times: np.ndarray,
                     bands: Sequence[str]) -> SunCheck | None:
    """The check of every capture's absolute sun-sensor readings (module docstring); None when
    the camera's sensor is not absolute (nothing to compare in W m-2 nm-1)."""
    n_c, n_b = sensor.factor.shape
    if not captures or not any((s := sun_scale(m.radiometry)) is not None and s.absolute
                               for c in captures for m in c.metas):
        return None
    t = np.asarray(times, dtype="datetime64[ns]")
    doy = np.array([np.nan if np.isnat(v) else float((v.astype("datetime64[D]") - v.astype("datetime64[Y]"))
                                                       .astype(int) + 1) for v in t])
    wl = np.array([[m.wavelength_nm for m in c.metas] for c in captures], dtype=np.float64)
    el = np.broadcast_to(np.asarray(sensor.elevation_deg, np.float64)[:, None], (n_c, n_b))
    clear = clear_sky_spectral(wl, el, np.broadcast_to(doy[:, None], (n_c, n_b)))
    mult = np.ones((n_c, n_b))
    per_capture: dict[str, Any] = {}
    counts: dict[str, int] = {}
    ratios: list[float] = []
    bad: list[tuple[str, str, float, float]] = []
    for c, cap in enumerate(captures):
        row: dict[str, Any] = {}
        band_rules: dict[int, tuple[dict[str, float], float, dict[str, float]]] = {}
        for b, meta in enumerate(cap.metas):
            scale = sun_scale(meta.radiometry)
            if scale is None or not scale.absolute or not np.isfinite(sensor.irradiance[c, b]):
                continue
            rules, used = unit_rules(meta)
            e_h = scale.constant * float(sensor.irradiance[c, b])  # W m-2 nm-1 on the reader's rule
            band_rules[b] = (rules, used, {r: e_h * s / used for r, s in rules.items()})
        # one sun sensor writes one unit: the capture's bands take one rule
        common = choose_capture_rule([v[2] for v in band_rules.values()], [float(clear[c, b]) for b in band_rules])
        for b, (rules, used, readings) in band_rules.items():
            rule, ratio, ok = choose_rule({common: readings[common]} if common in readings else readings,
                                          float(clear[c, b]))
            mult[c, b] = rules[rule] / used
            counts[rule] = counts.get(rule, 0) + 1
            row[bands[b]] = {"rule": rule, "ratio": None if not math.isfinite(ratio) else round(ratio, 4)}
            if math.isfinite(ratio):
                ratios.append(ratio)
            if not ok:
                bad.append((cap.name, bands[b], readings[rule], ratio))
        if row:
            per_capture[cap.name] = row
    record: dict[str, Any] = {
        "model": MODEL, "plausible_ratio": list(PLAUSIBLE_RATIO), "rules": counts,
        "ratio_range": [round(min(ratios), 4), round(max(ratios), 4)] if ratios else None,
        "implausible": len(bad), "captures": per_capture,
    }
    warnings = [] if not bad else [_warning(bad, len(ratios))]
    return SunCheck(mult, record, warnings)


def _warning(bad: Sequence[tuple[str, str, float, float]], n: int) -> dict[str, Any]:
    """run.json ``light.warnings`` entry: readings no unit rule puts in the plausible range."""
    worst = max(bad, key=lambda v: abs(math.log(v[3])) if v[3] > 0 else math.inf)
    lo, hi = PLAUSIBLE_RATIO
    return {"code": "sun_sensor_implausible", "capture": worst[0], "band": worst[1], "value": round(worst[3], 4),
            "threshold": hi if worst[3] > hi else lo,
            "message": f"{len(bad)} of {n} sun-sensor reading(s) lie outside {lo:g}..{hi:g} x the clear sky's "
                       f"irradiance at their sun elevation and wavelength under every unit rule (worst {worst[0]} "
                       f"{worst[1]}: {worst[2]:.4g} W m-2 nm-1, {worst[3]:.3g} x clear sky): the sensor's reflectance "
                       "is suspect (run.json sun_sensor_check); check its unit tags, or use a panel"}


__all__ = ["AS_WRITTEN_RULE", "LIBRARY_RULE", "SunCheck", "sun_sensor_check", "unit_rules"]
