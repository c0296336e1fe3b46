"""The sun sensor's reading made horizontal: per capture and band the irradiance on
the horizontal ground from the sensor's reading, the sun's position and the sensor's
orientation, and one sun-sensor level per frame or capture for the field path (calibrate and
apply both use :func:`capture_levels` / :func:`record_levels`, so that a reflector capture and a
flight capture are measured alike).

The maths is :mod:`mscal_core.sunsensor`; here the tags are read and the sun placed. The
panel part (panels anchored by the sensor, warnings) is :mod:`pipeline.apply.sunlight`.

Per band file, the reading ``E_meas`` is the camera's own (:func:`pipeline.ingest.meta.
reflectance_factor` gives ``k = c / E_meas``: ``pi / E`` for MicaSense, ``1 / E`` for the
relative sensors) and the correction ``f = E_h / E_meas``: the tilted-sensor model
(:func:`mscal_core.sunsensor.horizontal_irradiance`) with the sensor's orientation and the
diffuse ratio, unless the camera compensated the reading itself (correction 1) or its sensor
measured the direct/scattered split. What is maker's lives in the maker's module and is
registered on its ``pipeline.ingest.cameras.registry.Maker``: the orientation tags
(``attitude``: MicaSense's DLS, Parrot's sunshine sensor, DJI's aircraft; tried lowest rank
first across makers, then the aircraft's ``Camera:Yaw/Pitch/Roll`` every maker shares), the
measured split and its horizontal reading (``sun_split``, ``split_correction``: MicaSense
DLS 2), the self-compensated reading (``compensated``: DJI) and the factor of a reading with
no fixed scale (``sun_factor``: Sentera's ILS counts, which serve only the change between
panels).

Without a sun position (no time or GPS) or orientation the correction is 1 (the raw reading)
or the level-sensor one, and run.json says which (``sun_sensor``). Without a measured split
(DLS 1, Sequoia, Sentera) the diffuse ratio is the clear sky's 1/6, or, when the caller asks
(``fit_ratio``: the factory path's panel routes, never its ``dls`` route, whose reflectance must
not depend on the flight) and on a flight of at least :data:`FIT_MIN_CAPTURES` captures at
changing attitudes, fitted per band so that the horizontal irradiance does not jump when the
aircraft turns (``sun_sensor.diffuse_ratio``).

**Field path levels** (:func:`capture_levels`, :func:`record_levels`): one number per frame or
capture, the geometric mean over its reflectance bands of ``E_meas,b f_b`` (the horizontal
irradiance in the reading's own unit; the geometric mean, like the level ``beta`` of
:func:`mscal_core.illumination.split_level`). The diffuse ratio is the clear sky's 1/6 (or a
DLS 2's measured split), never fitted from a flight: a capture's level depends on its own files
only, so the calibrate side and the apply side of the same capture agree. frames.csv
``irradiance`` wins where given (the user's number, its orientation unknown: used raw); files
the factory reader does not understand give their raw XMP ``Irradiance``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.sunsensor import CLEAR_SKY_DIFFUSE_RATIO, fit_diffuse_ratio, horizontal_irradiance

from pipeline.ingest.camera_meta import read_file_metas, sun_sensor_xmp, xmp_irradiance
from pipeline.ingest.cameras.registry import AttitudeSource, SunSplit, attitude_sources, by_order, maker_of
from pipeline.ingest.exif import NAT, time_ns
from pipeline.ingest.grouping import Capture
from pipeline.ingest.meta import CaptureMeta, reflectance_factor
from pipeline.ingest.session import FrameRecord
from pipeline.ingest.solar import solar_position
from pipeline.ingest.xmp import Xmp, jpeg_xmp_packet

#: The sky's diffuse ratio is fitted per band from the flight's readings
#: (:func:`mscal_core.sunsensor.fit_diffuse_ratio`) when at least this many captures have a
#: reading, an orientation and the sun's position, and the fit lowers the roughness of the
#: horizontal irradiance by at least :data:`FIT_GAIN_MIN` against the clear sky's 1/6.
FIT_MIN_CAPTURES = 10
FIT_GAIN_MIN = 0.25


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


#: The aircraft's attitude in the XMP ``Camera`` namespace (degrees) that several makers write
#: (Parrot, Sentera): tried after every maker's own :class:`AttitudeSource`.
AIRCRAFT_ATTITUDE = AttitudeSource(
    90, "Camera:Yaw/Pitch/Roll", lambda x: x.angles(("Yaw", "Pitch", "Roll"), ("Camera",), degrees=True))


def sensor_orientation(x: Xmp) -> Orientation | None:
    """The sun sensor's orientation from its own tags, else the aircraft's: the first of the
    makers' attitude sources (:func:`pipeline.ingest.cameras.registry.attitude_sources`), then
    :data:`AIRCRAFT_ATTITUDE`, that the file holds."""
    for source in (*attitude_sources(), AIRCRAFT_ATTITUDE):
        found = source.read(x)
        if found is not None:
            return Orientation(*found, source.name)
    return None


def measured_split(x: Xmp) -> SunSplit | None:
    """A sun sensor's own direct/scattered split (the first maker's ``sun_split`` that finds one), or None."""
    for maker in by_order():
        split = maker.sun_split(x) if maker.sun_split is not None else None
        if split is not None:
            return split
    return None


def _split_correction(x: Xmp, split: SunSplit, el: float) -> float | None:
    """The correction of a reading that is the split's own horizontal irradiance (the makers'
    ``split_correction``), None for a tilted reading."""
    for maker in by_order():
        corr = maker.split_correction(x, split, el) if maker.split_correction is not None else None
        if corr is not None:
            return corr
    return None


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


@dataclass(frozen=True)
class _TiltCase:
    """A band file whose correction is the tilt model's (:func:`band_correction`): computed
    for every such file of the flight in one :func:`horizontal_irradiance` call."""

    el: float
    az: float
    orient: Orientation
    ratio: float
    model: str


def band_correction(x: Xmp, el: float, az: float, orient: Orientation | None,
                     sky_ratio: float = CLEAR_SKY_DIFFUSE_RATIO, sky: str = "clear-sky diffuse ratio 1/6"
                     ) -> tuple[float, float, float, str] | _TiltCase:
    """``E_h / E_meas`` of one band file, the tilt and incidence (radians) and the model used
    (``sky_ratio``: the diffuse ratio without a measured split, named ``sky``); for the tilt
    model, what it needs (:func:`_tilt_corrections` computes them all at once)."""
    compensated = compensated_model(x)
    if compensated is not None:
        return 1.0, float("nan"), float("nan"), compensated
    split = measured_split(x)
    has_sun = math.isfinite(el) and math.isfinite(az)
    corr = _split_correction(x, split, el) if split is not None and has_sun else None
    if corr is not None:  # the reading is the split's horizontal value: recomputed with the right sun
        return corr, float("nan"), float("nan"), "dls2 direct+scattered"
    if not has_sun:
        return 1.0, float("nan"), float("nan"), "raw reading (no sun position: time or GPS missing)"
    ratio = sky_ratio if split is None else split.scattered / split.direct
    o = orientation_or_level(orient)
    name = "tilt model, measured diffuse ratio" if split is not None else f"tilt model, {sky}"
    return _TiltCase(el, az, o, ratio, f"{name}; orientation {o.source}")


def compensated_model(x: Xmp) -> str | None:
    """run.json's ``sun_sensor`` model of a reading the camera already made independent of its
    attitude (a maker's ``compensated``: DJI's ``drone-dji:Irradiance``), None for any other."""
    for maker in by_order():
        if maker.compensated is not None and maker.compensated(x):
            return maker.compensated_model
    return None


def camera_compensated(x: Xmp) -> bool:
    """True for a reading the camera already made independent of its attitude (:func:`compensated_model`)."""
    return compensated_model(x) is not None


def _tilt_corrections(cases: Sequence[_TiltCase]) -> list[tuple[float, float, float, str]]:
    """:func:`band_correction`'s result of each tilt-model case, from one vectorised call
    (one call per band file cost 1.5 ms: 37 s of a 5,000-capture, 5-band flight)."""
    if not cases:
        return []
    col = {f: np.array([getattr(c, f) for c in cases], np.float64) for f in ("el", "az", "ratio")}
    ypr = np.array([(c.orient.yaw, c.orient.pitch, c.orient.roll) for c in cases], np.float64)
    h = horizontal_irradiance(np.ones(len(cases)), col["el"], col["az"], ypr[:, 0], ypr[:, 1], ypr[:, 2],
                              diffuse_ratio=col["ratio"])
    return [(float(h.factor[i]), float(h.tilt[i]), float(h.incidence[i]), c.model) for i, c in enumerate(cases)]


def orientation_or_level(orient: Orientation | None) -> Orientation:
    """The orientation, or a level sensor when none is known."""
    return orient if orient is not None else Orientation(0.0, 0.0, 0.0, "none (level assumed)")


def sensor_light(captures: Sequence[Capture], times: np.ndarray, *, fit_ratio: bool = True) -> SensorLight:
    """The sun sensor of every capture (see the module docstring); ``times`` datetime64 per
    capture. ``fit_ratio`` False: the diffuse ratio is never fitted from the captures (the
    clear sky's 1/6 or a measured split), so each capture's result depends on its own files only."""
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
            kb = band_factor(meta)
            if kb is None:
                continue
            k[c, b] = kb
            kept = sun_sensor_xmp(meta)  # the properties read with the file's metadata
            xmps[c, b] = x = kept if kept is not None else file_xmp(meta.path)
            o = None if camera_compensated(x) else sensor_orientation(x)  # no ratio fit from those
            if o is not None and not np.isfinite(ypr[c, 0]):
                ypr[c] = (o.yaw, o.pitch, o.roll)
    ratios, sources = _sky_ratios(k, el, az, ypr, xmps, fit_ratio)
    found = {cb: band_correction(x, float(el[cb[0]]), float(az[cb[0]]), sensor_orientation(x),
                                  ratios[cb[1]], sources[cb[1]]) for cb, x in xmps.items()}
    tilted = [cb for cb, v in found.items() if isinstance(v, _TiltCase)]
    found.update(zip(tilted, _tilt_corrections([found[cb] for cb in tilted])))  # type: ignore[misc]
    factor = np.full((n_c, n_b), np.nan)
    corr = np.full((n_c, n_b), np.nan)
    tilt = np.full(n_c, np.nan)
    inc = np.full(n_c, np.nan)
    models = []
    for c in range(n_c):
        model = "no sun-sensor reading"
        for b in range(n_b):
            if (c, b) not in found:
                continue
            corr[c, b], t, i, model = found[c, b]  # type: ignore[misc]
            factor[c, b] = k[c, b] / corr[c, b]
            if not np.isfinite(tilt[c]):
                tilt[c], inc[c] = t, i
        models.append(model)
    with np.errstate(divide="ignore", invalid="ignore"):
        irr = 1.0 / factor
    return SensorLight(factor, corr, irr, np.degrees(el), np.degrees(tilt), np.degrees(inc), tuple(models),
                       tuple(float(r) for r in ratios), tuple(sources))


def _sky_ratios(k: np.ndarray, el: np.ndarray, az: np.ndarray, ypr: np.ndarray,
                xmps: dict[tuple[int, int], Xmp], fit: bool = True) -> tuple[list[float], list[str]]:
    """Per band the diffuse ratio used without a measured split: fitted from the flight's
    readings (:data:`FIT_MIN_CAPTURES`, :data:`FIT_GAIN_MIN`), else the clear sky's 1/6."""
    n_b = k.shape[1]
    ratios = [CLEAR_SKY_DIFFUSE_RATIO] * n_b
    sources = ["clear-sky diffuse ratio 1/6"] * n_b
    split = any(measured_split(x) is not None for x in xmps.values())
    for b in range(n_b):
        usable = np.isfinite(k[:, b]) & np.isfinite(el) & np.isfinite(ypr[:, 0])
        if not fit or split or np.count_nonzero(usable) < FIT_MIN_CAPTURES:
            continue
        with np.errstate(divide="ignore"):
            fit = fit_diffuse_ratio(1.0 / k[:, b], el, az, ypr[:, 0], ypr[:, 1], ypr[:, 2])
        if np.isfinite(fit.roughness_at) and fit.roughness <= (1.0 - FIT_GAIN_MIN) * fit.roughness_at:
            ratios[b] = fit.ratio
            sources[b] = (f"diffuse ratio {fit.ratio:.3f} fitted on {fit.n} captures (roughness "
                          f"{fit.roughness:.2e} vs {fit.roughness_at:.2e} at 1/6)")
    return ratios, sources


def band_factor(meta: CaptureMeta) -> float | None:
    """``k_b`` of a band's own reading before the correction: its maker's ``sun_factor`` for a
    reading with no fixed scale (Sentera's ILS counts: ``1 / E``, the panel sets the scale), else
    :func:`pipeline.ingest.meta.reflectance_factor`; None without a usable reading."""
    try:
        factor = maker_of(meta.radiometry).sun_factor
    except KeyError:
        factor = None
    return (factor or reflectance_factor)(meta)


# --------------------------------------------------------------------------- field path levels

#: What a calibration store's ``capture_irradiance`` attribute ``sun_sensor_model`` says when
#: its levels come from :func:`record_levels` (absent: raw readings, a store from before).
SUN_SENSOR_MODEL = "horizontal"
#: The attribute's name on ``capture_irradiance``.
SUN_SENSOR_MODEL_ATTR = "sun_sensor_model"
#: Earlier mscal versions wrote :data:`SUN_SENSOR_MODEL` followed by a note in parentheses
#: (the same levels, the same computation): a value of this form reads as it. Part of the store
#: format, not to be written again.
SUN_SENSOR_MODEL_FORMER = re.compile(r"horizontal \([^()]*\)")


def stored_sun_sensor_model(attrs: Mapping[str, Any]) -> str | None:
    """The ``sun_sensor_model`` of a store's ``capture_irradiance`` attributes: a former value
    (:data:`SUN_SENSOR_MODEL_FORMER`) read as :data:`SUN_SENSOR_MODEL`; None when absent (raw
    readings, a store from before horizontal levels)."""
    model = attrs.get(SUN_SENSOR_MODEL_ATTR)
    if model is None:
        return None
    return SUN_SENSOR_MODEL if SUN_SENSOR_MODEL_FORMER.fullmatch(str(model)) else str(model)


@dataclass(frozen=True)
class Levels:
    """One sun-sensor level per frame or capture (NaN: none) and how each was obtained."""

    value: np.ndarray
    source: tuple[str, ...]


def capture_time(capture: Capture) -> np.datetime64:
    """The time of a capture's first band file (its EXIF time; NaT without one)."""
    ns = time_ns(capture.metas[0].time) if capture.metas else NAT
    return np.datetime64("NaT", "ns") if ns == NAT else np.datetime64(ns, "ns")


def capture_levels(captures: Sequence[Capture]) -> Levels:
    """The horizontal sun-sensor level of every capture (module docstring, "Field path
    levels"): the geometric mean over its reflectance bands of ``E_meas,b`` times
    :func:`sensor_light`'s correction (the diffuse ratio not fitted), at the capture's own
    time (:func:`capture_time`); NaN unless every reflectance band has a reading."""
    value = np.full(len(captures), np.nan)
    source = ["no sun-sensor reading"] * len(captures)
    by_bands: dict[int, list[int]] = {}
    for c, cap in enumerate(captures):  # sensor_light wants one band count per call
        by_bands.setdefault(len(cap.metas), []).append(c)
    for idx in by_bands.values():
        caps = [captures[c] for c in idx]
        light = sensor_light(caps, np.array([capture_time(cap) for cap in caps], dtype="datetime64[ns]"),
                             fit_ratio=False)
        for j, c in enumerate(idx):
            level = _level(caps[j].metas, light.correction[j])
            if np.isfinite(level):
                value[c], source[c] = level, f"horizontal: {light.model[j]}"
    return Levels(value, tuple(source))


def _level(metas: Sequence[CaptureMeta], correction: np.ndarray) -> float:
    """Geometric mean over the reflectance bands of ``E_meas f`` (NaN if a band has none)."""
    vals = [m.irradiance * f if m.irradiance is not None else np.nan
            for m, f in zip(metas, correction) if m.reflectance_band]
    arr = np.asarray(vals, dtype=np.float64)
    if arr.size == 0 or not np.all(np.isfinite(arr) & (arr > 0)):
        return float("nan")
    return float(np.exp(np.mean(np.log(arr))))


def raw_level(files: Sequence[Path]) -> float | None:
    """The raw level of a frame the factory reader does not understand: the geometric mean of
    its files' XMP ``Irradiance`` (:func:`pipeline.ingest.camera_meta.xmp_irradiance`; one file:
    its reading), None unless every file has one."""
    vals = [xmp_irradiance(f) for f in files]
    if not vals or any(v is None for v in vals):
        return None
    return float(np.exp(np.mean(np.log(np.asarray(vals, dtype=np.float64)))))


def record_capture(rec: FrameRecord) -> Capture | None:
    """A frame's files read as a factory capture (:func:`pipeline.ingest.camera_meta.
    read_file_metas`), or None when a file's tags are not a camera's the reader knows."""
    metas: list[CaptureMeta] = []
    try:
        for f in rec.files:
            metas.extend(read_file_metas(f))
    except FrameError:
        return None
    return Capture(name=rec.name, capture_id=rec.name, metas=tuple(metas)) if metas else None


def record_levels(records: Sequence[FrameRecord]) -> Levels:
    """The sun-sensor level of every frame record (calibrate's reflector frames, a snapshot
    flight's frames): frames.csv ``irradiance`` where given (raw: the user's number); else,
    for files the factory reader understands, :func:`capture_levels`; else :func:`raw_level`."""
    value = np.full(len(records), np.nan)
    source = ["no sun-sensor reading"] * len(records)
    todo: list[tuple[int, Capture]] = []
    for r, rec in enumerate(records):
        if rec.irradiance is not None:
            value[r], source[r] = rec.irradiance, "frames.csv irradiance (raw: orientation unknown)"
            continue
        cap = record_capture(rec)
        if cap is not None and any(m.irradiance is not None for m in cap.metas):
            todo.append((r, cap))
            continue
        raw = raw_level(rec.files)
        if raw is not None:
            value[r], source[r] = raw, "XMP Irradiance (raw: tags not a known camera's)"
    if todo:
        levels = capture_levels([cap for _, cap in todo])
        for (r, _), v, src in zip(todo, levels.value, levels.source):
            value[r], source[r] = v, src
    return Levels(value, tuple(source))


__all__ = ["AIRCRAFT_ATTITUDE", "FIT_GAIN_MIN", "FIT_MIN_CAPTURES", "SUN_SENSOR_MODEL", "SUN_SENSOR_MODEL_ATTR",
           "SUN_SENSOR_MODEL_FORMER", "Levels", "Orientation", "SensorLight", "band_factor", "camera_compensated",
           "capture_levels", "capture_time", "compensated_model", "file_xmp", "measured_split", "orientation_or_level",
           "raw_level", "record_capture", "record_levels", "sensor_light", "sensor_orientation",
           "stored_sun_sensor_model"]
