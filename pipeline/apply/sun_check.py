"""Sun-sensor magnitudes checked against the sky (run.json ``sun_sensor_check``).

Each absolute sun-sensor reading (W m-2 nm-1 after the file's unit rule, made horizontal by
:func:`pipeline.ingest.sunsensor.sensor_light`) is compared with the clear sky's spectral
irradiance at the capture's sun elevation and the band's wavelength
(:mod:`pipeline.ingest.clear_sky`). The unit rules are the band's maker's
(:attr:`pipeline.ingest.cameras.registry.Maker.sun_unit_rules`; a maker without any: one rule,
W m-2 nm-1 as read). Where a maker documents several that disagree (MicaSense's DLS 2 files
without ``IrradianceScaleToSIUnits``:
:func:`pipeline.ingest.cameras.micasense.dls_unit_rules`), the rule whose value is plausible and
closest to the clear sky is taken (:func:`pipeline.ingest.clear_sky.choose_rule`); every other
file has one rule, checked the same way. A reading no rule puts in
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
from pipeline.ingest.cameras.registry import sun_unit_rules
from pipeline.ingest.clear_sky import MODEL, PLAUSIBLE_RATIO, choose_capture_rule, choose_rule, clear_sky_spectral
from pipeline.ingest.grouping import Capture
from pipeline.ingest.meta import CaptureMeta
from pipeline.ingest.sun_scale import sun_scale
from pipeline.ingest.sunsensor import SensorLight, file_xmp


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
    """A band file's unit rules ``{rule: scale to W m-2 nm-1}`` and the scale the reader applied:
    its maker's (:func:`pipeline.ingest.cameras.registry.sun_unit_rules`, from the sun-sensor XMP
    kept on ``meta``, else the file's), one rule x 1 for a maker without any."""
    return sun_unit_rules(meta.radiometry, lambda: sun_sensor_xmp(meta) or file_xmp(meta.path))


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


__all__ = ["SunCheck", "sun_sensor_check", "unit_rules"]
