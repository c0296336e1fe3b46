"""Light that changes during a flight: the illumination of each flight frame.

The calibration store holds, per reflector capture, its spectral factor ``S_c(lambda)``
(Eq. 11-14), time and sun-sensor irradiance (``capture_*`` variables, see
``docs/architecture.md``). A flight frame at time ``tau`` gets the light interpolated between
the captures (``nearest`` or ``linear`` in time) and, when the frames carry irradiance
readings, the brightness level scaled by the sensor between the captures
(:func:`mscal_core.illumination.frame_illumination`). Eq. 15 then uses ``S(lambda, tau)``; it
is folded into each frame's table as the factor ``k_b(tau) = S(lambda_b) / S(lambda_b, tau)``
on the store's ``spectral_factor`` (:func:`mscal_core.reflectance.eq15_fast`).

Sun-sensor level of a frame or capture: for a store whose ``capture_irradiance``
says ``sun_sensor_model = "horizontal"`` (:func:`sun_sensor_model`), the level the
calibration used for its reflector captures, from the same function
(:func:`pipeline.ingest.sunsensor.record_levels` for frames, :func:`pipeline.ingest.sunsensor.
capture_levels` for one-file-per-band captures): frames.csv ``irradiance`` as given, else the
sun sensor's horizontal irradiance (sun position, sensor tilt), the geometric mean over the
bands. For an older store, the raw readings it was made with: the ``irradiance`` column of the
flight's frames.csv, else the XMP ``Irradiance`` of a TIFF frame, and for a capture the mean of
its bands' readings (:func:`pipeline.ingest.grouping.capture_irradiance`), so that it gives
what it gave. run.json's ``illumination.sun_sensor_level`` says which.

A store with one capture and no irradiance (every store written before captures over time) gives no
plan: apply computes exactly what it did before.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import xarray as xr
from mscal_core.errors import FrameError, InputError
from mscal_core.illumination import INTERPOLATION_MODES, frame_illumination

from pipeline.ingest.camera_meta import xmp_irradiance
from pipeline.ingest.grouping import Capture, capture_irradiance
from pipeline.ingest.session import FRAMES_CSV, FrameRecord, read_frame_table
from pipeline.ingest.sunsensor import SUN_SENSOR_MODEL, Levels, capture_levels, record_levels, stored_sun_sensor_model

__all__ = ["IlluminationPlan", "INTERPOLATION_MODES", "calibration_captures", "flight_irradiance",
           "flight_levels", "frame_levels", "illumination_plan", "sun_sensor_model", "varies_in_time", "DEFAULT_MODE"]

#: Linear in time: a drift (the sun rising, haze building up) is followed between captures;
#: ``nearest`` is for captures that bracket abrupt changes (a cloud bank arriving).
DEFAULT_MODE = "linear"
#: run.json ``illumination.sun_sensor_level`` of a store from before horizontal levels.
RAW_LEVELS = ("raw readings: the store's capture_irradiance predates horizontal levels (no sun_sensor_model); "
              "recalibrate for horizontal levels")


@dataclass(frozen=True)
class Captures:
    """The reflector captures of a calibration store."""

    spectral_factor: np.ndarray  # (n_captures, n_bands)
    time_s: np.ndarray  # (n_captures,) s since the epoch, NaN if unknown
    irradiance: np.ndarray  # (n_captures,) NaN if none
    names: tuple[str, ...]


def calibration_captures(calib: xr.Dataset) -> Captures:
    """Per-capture S, time and irradiance of a store; a store without ``capture_*`` variables
    (written before captures over time) is one capture with the store's S, no time and no irradiance."""
    if "capture_spectral_factor" not in calib:
        return Captures(np.asarray(calib["spectral_factor"].values, dtype=np.float64)[None],
                        np.array([np.nan]), np.array([np.nan]), ("reflector",))
    times = calib["capture_time"].values.astype("datetime64[ns]")
    t = np.where(np.isnat(times), np.nan, times.astype(np.int64) / 1e9)
    return Captures(
        np.asarray(calib["capture_spectral_factor"].values, dtype=np.float64),
        t.astype(np.float64),
        np.asarray(calib["capture_irradiance"].values, dtype=np.float64),
        tuple(str(n) for n in calib["capture_name"].values),
    )


def varies_in_time(calib: xr.Dataset) -> bool:
    """Whether the store's light can change over a flight: several captures, or a capture with
    an irradiance reading (then frames' readings scale its level)."""
    caps = calibration_captures(calib)
    return caps.spectral_factor.shape[0] > 1 or bool(np.any(np.isfinite(caps.irradiance)))


def sun_sensor_model(calib: xr.Dataset) -> str | None:
    """How the store's ``capture_irradiance`` was computed: :data:`pipeline.ingest.sunsensor.
    SUN_SENSOR_MODEL` for the horizontal levels, None for an older store (raw)."""
    if "capture_irradiance" not in calib:
        return None
    return stored_sun_sensor_model(calib["capture_irradiance"].attrs)


def _flight_records(flight_dir: Path) -> dict[str, FrameRecord] | None:
    records = {}
    try:
        for rec in read_frame_table(flight_dir, require_files=False, on_frame_error=lambda *_: None):
            records[rec.name] = rec
    except InputError:
        return None
    return records


def flight_levels(flight_dir: Path, names: Sequence[str]) -> Levels:
    """Horizontal sun-sensor level of each frame (by frame name = file stem; NaN where none):
    :func:`pipeline.ingest.sunsensor.record_levels` of the flight's frame table, the function
    calibrate used for the reflector frames."""
    records = _flight_records(flight_dir)
    if records is None:
        return Levels(np.full(len(names), np.nan), ("no frame table",) * len(names))
    found = [(f, records[str(n)]) for f, n in enumerate(names)
             if str(n) in records and (records[str(n)].irradiance is not None or records[str(n)].path.is_file())]
    value = np.full(len(names), np.nan)
    source = ["no sun-sensor reading"] * len(names)
    try:
        levels = record_levels([rec for _, rec in found])
    except FrameError:  # some frame's reading is unusable: the others keep theirs, it none
        levels = Levels(*map(np.array, zip(*(_one_level(rec) for _, rec in found)))) if found else Levels(np.zeros(0), ())
    for (f, _), v, src in zip(found, levels.value, levels.source):
        value[f], source[f] = v, src
    return Levels(value, tuple(source))


def _one_level(rec: FrameRecord) -> tuple[float, str]:
    try:
        one = record_levels([rec])
    except FrameError as exc:
        return float("nan"), f"unusable sun-sensor reading: {exc.reason}"
    return float(one.value[0]), one.source[0]


def flight_irradiance(flight_dir: Path, names: Sequence[str]) -> np.ndarray:
    """Raw sun-sensor reading of each frame (by frame name = file stem; NaN where none),
    for stores from before horizontal levels: frames.csv ``irradiance``, else the file's XMP
    Irradiance. Frames the table cannot describe are left NaN (discovery quarantines them)."""
    records = _flight_records(flight_dir)
    if records is None:
        return np.full(len(names), np.nan)
    out = np.full(len(names), np.nan)
    for f, name in enumerate(names):
        rec = records.get(str(name))
        if rec is None:
            continue
        value = rec.irradiance
        if value is None and rec.path.is_file():
            try:
                value = xmp_irradiance(rec.path)
            except FrameError:
                value = None
        if value is not None:
            out[f] = value
    return out


@dataclass(frozen=True)
class IlluminationPlan:
    """The light of each frame of one apply pass.

    ``scale`` (n_frames, n_bands) ``k_b = S(lambda_b) / S(lambda_b, tau)``: what Eq. 15's
    reflectance with the store's S is multiplied by; ``level`` (n_frames,) ``beta(tau)``;
    ``irradiance`` (n_frames,) the readings (NaN none); ``irradiance_used`` (n_frames,) bool."""

    mode: str
    scale: np.ndarray
    level: np.ndarray
    irradiance: np.ndarray
    irradiance_used: np.ndarray
    captures: tuple[str, ...]
    sun_sensor_level: str = RAW_LEVELS  # how the levels were computed
    irradiance_source: tuple[str, ...] = ()  # per frame, when known

    def digest(self) -> str:
        """sha256 of the factors: part of the run's fingerprint (a changed reading re-applies)."""
        return hashlib.sha256(np.ascontiguousarray(self.scale, dtype=np.float64).tobytes()).hexdigest()

    def summary(self, frames: Sequence[str]) -> dict[str, Any]:
        """What ``run.json`` records."""
        return {
            "mode": self.mode,
            "captures": list(self.captures),
            "frames_with_irradiance": int(np.count_nonzero(self.irradiance_used)),
            "sun_sensor_level": self.sun_sensor_level,
            **({"irradiance_sources": {src: self.irradiance_source.count(src)
                                       for src in dict.fromkeys(self.irradiance_source)}}
               if self.irradiance_source else {}),
            "per_frame": {
                str(n): {"level": round(float(self.level[f]), 6),
                         "scale": [round(float(v), 6) for v in self.scale[f]],
                         "irradiance": None if not np.isfinite(self.irradiance[f]) else float(self.irradiance[f])}
                for f, n in enumerate(frames)
            },
        }


def frame_levels(calib: xr.Dataset, frames: Sequence[str], flight_dir: Path,
                 captures: Sequence[Capture] | None = None) -> tuple[Levels, str]:
    """The sun-sensor level of each frame computed as the store's ``capture_irradiance`` was
    (module docstring) and what run.json says of it. ``captures``: the frames are these
    one-file-per-band captures (in order), else they are read from the flight's frame table."""
    model = sun_sensor_model(calib)
    if model == SUN_SENSOR_MODEL:
        levels = capture_levels(captures) if captures is not None else flight_levels(flight_dir, frames)
        return levels, (f"{model}: frames.csv irradiance as given, else the sun sensor's horizontal irradiance "
                        "(sun position, sensor tilt; geometric mean over the bands), as for the store's captures")
    if captures is not None:
        raw = np.array([np.nan if capture_irradiance(c) is None else capture_irradiance(c) for c in captures])
    else:
        raw = flight_irradiance(flight_dir, frames)
    text = RAW_LEVELS if model is None else f"raw readings: the store's sun_sensor_model {model!r} is not known here"
    return Levels(raw, ()), text


def illumination_plan(calib: xr.Dataset, frames: Sequence[str], times: np.ndarray, flight_dir: Path,
                      mode: str = DEFAULT_MODE, irradiance: np.ndarray | None = None,
                      captures: Sequence[Capture] | None = None) -> IlluminationPlan | None:
    """Per-frame light of a flight (``frames`` names, ``times`` datetime64), or None when the
    store's light does not vary in time (:func:`varies_in_time`): Eq. 15 as before.

    Raises InputError naming the flight's frames.csv when several captures must be
    interpolated and frames have no time. The frames' sun-sensor levels: ``irradiance`` when
    the caller gives them (used as they are), else :func:`frame_levels` (of ``captures`` when
    the frames are one-file-per-band captures, else of the flight's frames).
    """
    if mode not in INTERPOLATION_MODES:
        raise InputError(f"--illumination {mode!r}: use one of {', '.join(INTERPOLATION_MODES)}")
    if not varies_in_time(calib):
        return None
    caps = calibration_captures(calib)
    t = np.asarray(times).astype("datetime64[ns]")
    t_s = np.where(np.isnat(t), np.nan, t.astype(np.int64) / 1e9)
    if irradiance is None:
        levels, how = frame_levels(calib, frames, flight_dir, captures)
    else:
        levels, how = Levels(np.asarray(irradiance, dtype=np.float64), ()), "as given by the caller"
    irr = levels.value
    if caps.spectral_factor.shape[0] > 1 and not np.all(np.isfinite(t_s)):
        missing = [str(frames[f]) for f in np.flatnonzero(~np.isfinite(t_s))[:3]]
        raise InputError(
            f"frame(s) {', '.join(missing)} have no time, but the calibration has "
            f"{caps.spectral_factor.shape[0]} reflector captures ({', '.join(caps.names)}) whose light is "
            "interpolated to each frame's time",
            path=flight_dir / FRAMES_CSV,
            hint="add a time column (ISO 8601) to frames.csv, or calibrate with one reflector capture",
        )
    light = frame_illumination(caps.spectral_factor, caps.time_s, t_s, mode,
                               capture_irradiance=caps.irradiance, frame_irradiance=irr)
    if caps.spectral_factor.shape[0] == 1 and not light.irradiance_used.any():
        return None  # one capture and no frame reading: the light is the store's S
    reference = np.asarray(calib["spectral_factor"].values, dtype=np.float64)
    return IlluminationPlan(mode=mode, scale=reference[None, :] / light.spectral_factor, level=light.level,
                            irradiance=irr, irradiance_used=light.irradiance_used, captures=caps.names,
                            sun_sensor_level=how, irradiance_source=levels.source)
