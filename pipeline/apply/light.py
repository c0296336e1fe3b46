"""Light that changes during a flight (issue 8): the illumination of each flight frame.

The calibration store holds, per reflector capture, its spectral factor ``S_c(lambda)``
(Eq. 11-14), time and sun-sensor irradiance (``capture_*`` variables, see
``docs/architecture.md``). A flight frame at time ``tau`` gets the light interpolated between
the captures (``nearest`` or ``linear`` in time) and, when the frames carry irradiance
readings, the brightness level scaled by the sensor between the captures
(:func:`mscal_core.illumination.frame_illumination`). Eq. 15 then uses ``S(lambda, tau)``; it
is folded into each frame's table as the factor ``k_b(tau) = S(lambda_b) / S(lambda_b, tau)``
on the store's ``spectral_factor`` (:func:`mscal_core.reflectance.eq15_fast`).

Irradiance of a frame: the ``irradiance`` column of its folder's frames.csv, else the XMP
``Irradiance`` of a TIFF frame (MicaSense and other cameras with a downwelling light sensor).

A store with one capture and no irradiance (every store written before issue 8) gives no
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
from pipeline.ingest.session import FRAMES_CSV, read_frame_table

__all__ = ["IlluminationPlan", "INTERPOLATION_MODES", "calibration_captures", "flight_irradiance",
           "illumination_plan", "varies_in_time", "DEFAULT_MODE"]

#: Linear in time: a drift (the sun rising, haze building up) is followed between captures;
#: ``nearest`` is for captures that bracket abrupt changes (a cloud bank arriving).
DEFAULT_MODE = "linear"


@dataclass(frozen=True)
class Captures:
    """The reflector captures of a calibration store."""

    spectral_factor: np.ndarray  # (n_captures, n_bands)
    time_s: np.ndarray  # (n_captures,) s since the epoch, NaN if unknown
    irradiance: np.ndarray  # (n_captures,) NaN if none
    names: tuple[str, ...]


def calibration_captures(calib: xr.Dataset) -> Captures:
    """Per-capture S, time and irradiance of a store; a store without ``capture_*`` variables
    (written before issue 8) is one capture with the store's S, no time and no irradiance."""
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


def flight_irradiance(flight_dir: Path, names: Sequence[str]) -> np.ndarray:
    """Sun-sensor reading of each frame (by frame name = file stem; NaN where none): frames.csv
    ``irradiance``, else the file's XMP Irradiance. Frames the table cannot describe are left
    NaN (discovery quarantines them)."""
    records = {}
    try:
        for rec in read_frame_table(flight_dir, require_files=False, on_frame_error=lambda *_: None):
            records[rec.name] = rec
    except InputError:
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

    def digest(self) -> str:
        """sha256 of the factors: part of the run's fingerprint (a changed reading re-applies)."""
        return hashlib.sha256(np.ascontiguousarray(self.scale, dtype=np.float64).tobytes()).hexdigest()

    def summary(self, frames: Sequence[str]) -> dict[str, Any]:
        """What ``run.json`` records."""
        return {
            "mode": self.mode,
            "captures": list(self.captures),
            "frames_with_irradiance": int(np.count_nonzero(self.irradiance_used)),
            "per_frame": {
                str(n): {"level": round(float(self.level[f]), 6),
                         "scale": [round(float(v), 6) for v in self.scale[f]],
                         "irradiance": None if not np.isfinite(self.irradiance[f]) else float(self.irradiance[f])}
                for f, n in enumerate(frames)
            },
        }


def illumination_plan(calib: xr.Dataset, frames: Sequence[str], times: np.ndarray, flight_dir: Path,
                      mode: str = DEFAULT_MODE, irradiance: np.ndarray | None = None) -> IlluminationPlan | None:
    """Per-frame light of a flight (``frames`` names, ``times`` datetime64), or None when the
    store's light does not vary in time (:func:`varies_in_time`): Eq. 15 as before.

    Raises InputError naming the flight's frames.csv when several captures must be
    interpolated and frames have no time. ``irradiance``: the frames' readings when the caller
    has them (one-file-per-band captures: their bands' XMP Irradiance), else read from the
    flight (:func:`flight_irradiance`).
    """
    if mode not in INTERPOLATION_MODES:
        raise InputError(f"--illumination {mode!r}: use one of {', '.join(INTERPOLATION_MODES)}")
    if not varies_in_time(calib):
        return None
    caps = calibration_captures(calib)
    t = np.asarray(times).astype("datetime64[ns]")
    t_s = np.where(np.isnat(t), np.nan, t.astype(np.int64) / 1e9)
    irr = flight_irradiance(flight_dir, frames) if irradiance is None else np.asarray(irradiance, dtype=np.float64)
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
                            irradiance=irr, irradiance_used=light.irradiance_used, captures=caps.names)
