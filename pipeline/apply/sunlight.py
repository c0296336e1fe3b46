"""The sun sensor of a real camera, done right (issue 22): horizontal irradiance per capture and
band from the sensor's reading, the sun's position and the sensor's orientation; and the light
of every capture from panel captures anchored by the sensor.

The maths is :mod:`mscal_core.sunsensor`; here the tags are read and the sun placed.

Per band file, the reading ``E_meas`` is the camera's own (:func:`pipeline.ingest.camera_meta.
reflectance_factor` gives ``k = c / E_meas``: ``pi / E`` for MicaSense, ``1 / E`` for the
relative sensors) and the correction ``f = E_h / E_meas``:

- **MicaSense DLS 1** (``Camera:Irradiance``): the tilted-sensor model with the clear-sky
  diffuse ratio 1/6 (MicaSense, "Tutorial 3 - DLS Sensor Basic Usage" and ``micasense/dls.py``
  of micasense/imageprocessing: sun-sensor angle from ``compute_sun_angle``, the diffuser's
  Fresnel transmission, ``dir_dif_ratio = 6``); orientation ``DLS:Yaw/Pitch/Roll`` (radians,
  the DLS's own IMU), else ``Camera:IrradianceYaw/Pitch/Roll`` (degrees).
- **MicaSense DLS 2** (``DLS:DirectIrradiance`` and ``DLS:ScatteredIrradiance``): the sensor
  measures the split; ``E_h = E_dir sin(el) + E_scattered`` with the elevation recomputed from
  time and position (micasense/imageprocessing ``image.py``
  ``compute_horizontal_irradiance_dls2``: "for cases where the camera system did not do it
  correctly"). When the file holds the tilted reading ``Irradiance`` as well, the measured
  ratio ``r = Scattered / Direct`` replaces 1/6 in the tilt model.
- **Parrot Sequoia** sunshine sensor (``Camera:IrradianceList``: records of time, CH0, CH1,
  gain index, integration time, yaw, pitch, roll; Parrot developer forum "Details of
  Irradiance List tag for Sunshine sensor", Parrot's answer: "a linear irradiance sensor with
  no black level"): the tilt model with the sensor's own angles of its last record (degrees),
  else ``Camera:Yaw/Pitch/Roll``.
- **DJI** (``drone-dji:Irradiance`` with ``SensorGainAdjustment``, P4 Multispectral Image
  Processing Guide): the sunlight sensor on top of the aircraft, tilted with it:
  ``drone-dji:FlightYawDegree/FlightPitchDegree/FlightRollDegree``.
- **Sentera** ILS counts (``ILS:*``, Sentera radiometric-corrections repository): the tilt
  model with ``Camera:Yaw/Pitch/Roll``; Sentera's sun sensor gives no reflectance on its own
  (no published conversion), only the change between panels.

Without a sun position (no time or GPS) or orientation the correction is 1 (the raw reading)
or the level-sensor one, and run.json says which (``sun_sensor``). Without a measured split
(DLS 1, Sequoia, DJI, Sentera) the diffuse ratio is the clear sky's 1/6, or, on a flight of
at least :data:`FIT_MIN_CAPTURES` captures at changing attitudes, fitted per band so that the
horizontal irradiance does not jump when the aircraft turns (``sun_sensor.diffuse_ratio``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from mscal_core.illumination import capture_weights
from mscal_core.sunsensor import (
    CLEAR_SKY_DIFFUSE_RATIO,
    anchored_irradiance,
    dls2_horizontal,
    fit_diffuse_ratio,
    horizontal_irradiance,
    ratio_drift,
)

from pipeline.ingest.camera_meta import Capture, CaptureMeta, reflectance_factor, sun_sensor_xmp, sunshine_records
from pipeline.ingest.solar import solar_position
from pipeline.ingest.xmp import TagError, Xmp, jpeg_xmp_packet

#: Above this tilt of the sensor against the vertical, or with the sun behind it, the reading
#: rests on the diffuse model alone: flagged in run.json and the report.
TILT_WARN_DEG = 20.0
#: The sky's diffuse ratio is fitted per band from the flight's readings
#: (:func:`mscal_core.sunsensor.fit_diffuse_ratio`) when at least this many captures have a
#: reading, an orientation and the sun's position, and the fit lowers the roughness of the
#: horizontal irradiance by at least :data:`FIT_GAIN_MIN` against the clear sky's 1/6.
FIT_MIN_CAPTURES = 10
FIT_GAIN_MIN = 0.25
#: Panels and sensor disagree on the light's change when their ratio varies by more than this
#: between panel captures (per band; :func:`mscal_core.sunsensor.ratio_drift`).
RATIO_DRIFT_WARN = 0.03


@dataclass(frozen=True)
class Orientation:
    """The sun sensor's yaw, pitch, roll (radians) and the tags they came from."""

    yaw: float
    pitch: float
    roll: float
    source: str


def file_xmp(path: Path) -> Xmp:
    """The XMP packet of a band file (TIFF tag 700, JPEG APP1), empty when it has none."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        packet = jpeg_xmp_packet(path.read_bytes())
        return Xmp.empty(path) if packet is None else Xmp.parse(packet, path)
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(700)
            return Xmp.empty(path) if tag is None else Xmp.parse(tag.value, path)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError):
        return Xmp.empty(path)


def _angles(x: Xmp, tags: tuple[str, str, str], ns: tuple[str, ...], degrees: bool) -> tuple[float, float, float] | None:
    vals = [x.number(t, ns) for t in tags]
    if any(v is None or not math.isfinite(v) for v in vals):
        return None
    y, p, r = (float(v) for v in vals)  # type: ignore[arg-type]
    return (math.radians(y), math.radians(p), math.radians(r)) if degrees else (y, p, r)


def _sunshine_angles(x: Xmp) -> tuple[float, float, float] | None:
    try:
        recs = sunshine_records(x)
    except TagError:  # named where the reading itself is read (camera_meta); no angles here
        return None
    if not recs:
        return None
    last = recs[-1]
    return math.radians(last[5]), math.radians(last[6]), math.radians(last[7])


def sensor_orientation(x: Xmp) -> Orientation | None:
    """The sun sensor's orientation from its own tags, else the aircraft's (module docstring)."""
    found = _angles(x, ("Yaw", "Pitch", "Roll"), ("DLS",), degrees=False)
    if found is not None:
        return Orientation(*found, "DLS:Yaw/Pitch/Roll")
    found = _angles(x, ("IrradianceYaw", "IrradiancePitch", "IrradianceRoll"), ("Camera", "MicaSense"), degrees=True)
    if found is not None:
        return Orientation(*found, "Camera:IrradianceYaw/Pitch/Roll")
    found = _sunshine_angles(x)
    if found is not None:
        return Orientation(*found, "Camera:IrradianceList (sunshine sensor)")
    found = _angles(x, ("FlightYawDegree", "FlightPitchDegree", "FlightRollDegree"), ("drone-dji",), degrees=True)
    if found is not None:
        return Orientation(*found, "drone-dji:FlightYaw/Pitch/RollDegree")
    found = _angles(x, ("Yaw", "Pitch", "Roll"), ("Camera",), degrees=True)
    if found is not None:
        return Orientation(*found, "Camera:Yaw/Pitch/Roll")
    return None


def _dls2_split(x: Xmp) -> tuple[float, float, float | None] | None:
    """DLS 2 ``DirectIrradiance``, ``ScatteredIrradiance`` and ``HorizontalIrradiance`` (one
    unit: their scale cancels in the ratios used), or None."""
    ns = ("DLS", "Camera", "MicaSense")
    d, s = x.number("DirectIrradiance", ns), x.number("ScatteredIrradiance", ns)
    if d is None or s is None or not (d > 0 and s >= 0):
        return None
    h = x.number("HorizontalIrradiance", ns)
    return float(d), float(s), (float(h) if h is not None and h > 0 else None)


@dataclass(frozen=True)
class SensorLight:
    """The sun sensor of every capture and band (arrays (n_captures, n_bands)).

    ``factor`` ``k_b`` from the sensor alone (``reflectance_factor / correction``; NaN: no
    reading); ``correction`` ``E_h / E_meas``; ``irradiance`` ``1 / factor``, proportional to
    the horizontal irradiance (``E_h / pi`` for MicaSense); per capture the sun's elevation,
    the sensor's tilt and incidence (degrees) and how each was obtained."""

    factor: np.ndarray
    correction: np.ndarray
    irradiance: np.ndarray
    elevation_deg: np.ndarray
    tilt_deg: np.ndarray
    incidence_deg: np.ndarray
    model: tuple[str, ...]
    diffuse_ratio: tuple[float | None, ...] = ()  # per band, the ratio used without a measured split
    ratio_source: tuple[str, ...] = ()

    def record(self, names: Sequence[str], bands: Sequence[str]) -> dict[str, Any]:
        """What run.json says of the sensor per capture (and ``diffuse_ratio`` per band)."""
        out: dict[str, Any] = {}
        if self.diffuse_ratio:
            out["diffuse_ratio"] = {b: {"ratio": _num(r), "source": src}
                                    for b, r, src in zip(bands, self.diffuse_ratio, self.ratio_source)}
        for c, name in enumerate(names):
            out[str(name)] = {
                "model": self.model[c],
                "sun_elevation_deg": _num(self.elevation_deg[c]), "sensor_tilt_deg": _num(self.tilt_deg[c]),
                "sun_incidence_deg": _num(self.incidence_deg[c]),
                "correction": dict(zip(bands, (_num(v) for v in self.correction[c]))),
                "horizontal_irradiance": dict(zip(bands, (_num(v) for v in self.irradiance[c]))),
            }
        return out


def _num(v: float, digits: int = 6) -> float | None:
    return None if not np.isfinite(v) else round(float(v), digits)


def _band_correction(x: Xmp, el: float, az: float, orient: Orientation | None,
                     sky_ratio: float = CLEAR_SKY_DIFFUSE_RATIO, sky: str = "clear-sky diffuse ratio 1/6"
                     ) -> tuple[float, float, float, str]:
    """``E_h / E_meas`` of one band file, the tilt and incidence (radians) and the model used
    (``sky_ratio``: the diffuse ratio without a measured split, named ``sky``)."""
    split = _dls2_split(x)
    has_sun = math.isfinite(el) and math.isfinite(az)
    if split is not None and has_sun and x.number("Irradiance", ("Camera", "MicaSense")) is None:
        d, s, h = split  # the reading is DLS 2's HorizontalIrradiance: recompute it with the right sun
        return (float(dls2_horizontal(d, s, el)) / h if h else 1.0), float("nan"), float("nan"), "dls2 direct+scattered"
    if not has_sun:
        return 1.0, float("nan"), float("nan"), "raw reading (no sun position: time or GPS missing)"
    ratio = sky_ratio if split is None else split[1] / split[0]
    o = orientation_or_level(orient)
    h_irr = horizontal_irradiance(1.0, el, az, o.yaw, o.pitch, o.roll, diffuse_ratio=ratio)
    name = "tilt model, measured diffuse ratio" if split is not None else f"tilt model, {sky}"
    return float(h_irr.factor), float(h_irr.tilt), float(h_irr.incidence), f"{name}; orientation {o.source}"


def orientation_or_level(orient: Orientation | None) -> Orientation:
    """The orientation, or a level sensor when none is known."""
    return orient if orient is not None else Orientation(0.0, 0.0, 0.0, "none (level assumed)")


def sensor_light(captures: Sequence[Capture], times: np.ndarray) -> SensorLight:
    """The sun sensor of every capture (see the module docstring); ``times`` datetime64 per capture."""
    n_c = len(captures)
    n_b = len(captures[0].metas) if captures else 0
    lat = np.array([np.nan if c.metas[0].lat is None else c.metas[0].lat for c in captures], dtype=np.float64)
    lon = np.array([np.nan if c.metas[0].lon is None else c.metas[0].lon for c in captures], dtype=np.float64)
    alt = np.array([np.nan if c.metas[0].alt_m is None else c.metas[0].alt_m for c in captures], dtype=np.float64)
    el, az = solar_position(np.asarray(times, dtype="datetime64[ns]"), lat, lon, alt) if n_c else (np.zeros(0),) * 2
    k = np.full((n_c, n_b), np.nan)
    xmps: dict[tuple[int, int], Xmp] = {}
    ypr = np.full((n_c, 3), np.nan)
    for c, cap in enumerate(captures):
        for b, meta in enumerate(cap.metas):
            kb = reflectance_factor(meta) if meta.radiometry != "sentera" else _sentera_factor(meta)
            if kb is None:
                continue
            k[c, b] = kb
            kept = sun_sensor_xmp(meta)  # the properties read with the file's metadata
            xmps[c, b] = x = kept if kept is not None else file_xmp(meta.path)
            o = sensor_orientation(x)
            if o is not None and not np.isfinite(ypr[c, 0]):
                ypr[c] = (o.yaw, o.pitch, o.roll)
    ratios, sources = _sky_ratios(k, el, az, ypr, xmps)
    factor = np.full((n_c, n_b), np.nan)
    corr = np.full((n_c, n_b), np.nan)
    tilt = np.full(n_c, np.nan)
    inc = np.full(n_c, np.nan)
    models = []
    for c in range(n_c):
        model = "no sun-sensor reading"
        for b in range(n_b):
            if (c, b) not in xmps:
                continue
            x = xmps[c, b]
            corr[c, b], t, i, model = _band_correction(x, float(el[c]), float(az[c]), sensor_orientation(x),
                                                       ratios[b], sources[b])
            factor[c, b] = k[c, b] / corr[c, b]
            if not np.isfinite(tilt[c]):
                tilt[c], inc[c] = t, i
        models.append(model)
    with np.errstate(divide="ignore", invalid="ignore"):
        irr = 1.0 / factor
    return SensorLight(factor, corr, irr, np.degrees(el), np.degrees(tilt), np.degrees(inc), tuple(models),
                       tuple(float(r) for r in ratios), tuple(sources))


def _sky_ratios(k: np.ndarray, el: np.ndarray, az: np.ndarray, ypr: np.ndarray,
                xmps: dict[tuple[int, int], Xmp]) -> tuple[list[float], list[str]]:
    """Per band the diffuse ratio used without a measured split: fitted from the flight's
    readings (:data:`FIT_MIN_CAPTURES`, :data:`FIT_GAIN_MIN`), else the clear sky's 1/6."""
    n_b = k.shape[1]
    ratios = [CLEAR_SKY_DIFFUSE_RATIO] * n_b
    sources = ["clear-sky diffuse ratio 1/6"] * n_b
    split = any(_dls2_split(x) is not None for x in xmps.values())
    for b in range(n_b):
        usable = np.isfinite(k[:, b]) & np.isfinite(el) & np.isfinite(ypr[:, 0])
        if split or np.count_nonzero(usable) < FIT_MIN_CAPTURES:
            continue
        with np.errstate(divide="ignore"):
            fit = fit_diffuse_ratio(1.0 / k[:, b], el, az, ypr[:, 0], ypr[:, 1], ypr[:, 2])
        if np.isfinite(fit.roughness_at) and fit.roughness <= (1.0 - FIT_GAIN_MIN) * fit.roughness_at:
            ratios[b] = fit.ratio
            sources[b] = (f"diffuse ratio {fit.ratio:.3f} fitted on {fit.n} captures (roughness "
                          f"{fit.roughness:.2e} vs {fit.roughness_at:.2e} at 1/6)")
    return ratios, sources


def _sentera_factor(meta: CaptureMeta) -> float | None:
    """Sentera ILS counts: no reflectance on their own, but proportional to the light: ``1 / E``
    serves the panel-anchored route (the panel sets the scale)."""
    e = meta.irradiance
    return None if e is None or not math.isfinite(e) or e <= 0 else 1.0 / e


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


__all__ = ["Orientation", "PanelSensorLight", "SensorLight", "check_times", "file_xmp",
           "light_warnings", "orientation_or_level", "panel_sensor_light", "readings_missing", "seconds",
           "sensor_light", "sensor_orientation", "RATIO_DRIFT_WARN", "TILT_WARN_DEG"]
