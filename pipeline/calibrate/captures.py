"""Reflector captures: how the frames of ``reflector/`` split into captures taken under one
light (subfolders, or gaps in the frame times), and each capture's time and sun-sensor level
(the function apply uses for the flight's frames)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mscal_core.errors import SessionError

from pipeline.ingest.captures import read_frames
from pipeline.ingest.catalog import Camera
from pipeline.ingest.exif import NAT, time_ns
from pipeline.ingest.session import FRAMES_CSV, IMAGE_SUFFIXES, FrameRecord, read_frame_table
from pipeline.ingest.sunsensor import record_levels

#: Reflector frames more than this apart in time are different captures (seconds). A capture
#: (a few images of the reflector, turned or re-framed) takes well under a minute; the
#: captures of a session (before, during, after a flight) are minutes apart. Frames of
#: one folder without times are one capture; subfolders of ``reflector/`` are always one
#: capture each, whatever their times.
CAPTURE_GAP_S = 120.0


@dataclass(frozen=True)
class ReflectorCapture:
    """Reflector images taken under one light: ``frames`` are indices into the records of
    :func:`reflector_captures`; ``time_s`` the mean frame time (s since the epoch, UTC; NaN
    if unknown); ``irradiance`` the median sun-sensor level of its frames, None if any frame
    has none: frames.csv ``irradiance`` where given (raw), else the horizontal irradiance of the
    files' sun sensor, the geometric mean over the bands
    (:func:`pipeline.ingest.sunsensor.record_levels`, the function apply uses for the flight's
    frames and captures; the store marks it with ``sun_sensor_model``); ``irradiance_source``
    how the frames' levels were obtained (one per distinct source)."""

    name: str
    frames: tuple[int, ...]
    time_s: float
    irradiance: float | None
    folder: Path
    irradiance_source: tuple[str, ...] = ()


def _time_s(rec: FrameRecord) -> float:
    ns = time_ns(rec.time)
    return float("nan") if ns == NAT else ns / 1e9


def reflector_captures(folder: Path, camera: Camera | None = None) -> tuple[list[FrameRecord], list[ReflectorCapture]]:
    """The frames of ``reflector/`` and how they split into captures.

    Subfolders of ``folder`` that hold frames are one capture each (named after the
    subfolder); frames directly in ``folder`` are a capture too (named ``reflector``).
    Without subfolders, the frames are split where consecutive frame times are more than
    :data:`CAPTURE_GAP_S` apart (frames.csv ``time`` or EXIF DateTimeOriginal); frames
    without times are one capture. Records keep their folder's order (sorted by name), so a
    session with one capture reads exactly as before. Captures are sorted by time.
    """
    subs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")) if folder.is_dir() else []
    groups: list[tuple[str, Path, list[FrameRecord]]] = []
    has_top = any(p.is_file() and (p.suffix.lower() in IMAGE_SUFFIXES or p.name == FRAMES_CSV)
                  for p in folder.iterdir()) if folder.is_dir() else False
    def read(where: Path, recursive: bool) -> list[FrameRecord]:
        # a multi-lens camera's captures (band files) are the frames; else one file, one frame
        return read_frames(where, camera, recursive=recursive) if camera is not None else read_frame_table(where)

    if not subs or has_top:
        groups.append(("reflector", folder, read(folder, not subs)))
    for sub in subs:
        groups.append((sub.name, sub, read(sub, True)))
    records: list[FrameRecord] = []
    captures: list[ReflectorCapture] = []

    def add(name: str, where: Path, idx: list[int]) -> None:
        times = np.array([_time_s(records[i]) for i in idx])
        irr = record_levels([records[i] for i in idx])
        time_s = float(np.mean(times)) if np.all(np.isfinite(times)) else float("nan")
        level = float(np.median(irr.value)) if irr.value.size and np.all(np.isfinite(irr.value)) else None
        captures.append(ReflectorCapture(name, tuple(idx), time_s, level, where, tuple(dict.fromkeys(irr.source))))

    for name, where, recs in groups:
        first = len(records)
        records.extend(recs)
        idx = list(range(first, len(records)))
        if len(groups) > 1:
            add(name, where, idx)
            continue
        times = np.array([_time_s(r) for r in recs])
        known = np.isfinite(times)
        if not known.any():
            add(name, where, idx)
            continue
        if not known.all():
            missing = ", ".join(recs[i].path.name for i in np.flatnonzero(~known)[:3])
            raise SessionError(
                f"reflector frame(s) {missing} have no time while others do: the frames cannot be "
                "split into captures",
                path=where / FRAMES_CSV,
                hint="give every reflector frame a time, or put each capture in its own subfolder of reflector/",
            )
        order = np.argsort(times, kind="stable")
        cut = np.flatnonzero(np.diff(times[order]) > CAPTURE_GAP_S) + 1
        parts = np.split(order, cut)
        for k, part in enumerate(parts):
            add(name if len(parts) == 1 else f"capture_{k}", where, sorted(first + int(i) for i in part))
    if len(captures) > 1:
        undated = [c.name for c in captures if not np.isfinite(c.time_s)]
        if undated:
            raise SessionError(
                f"reflector capture(s) {', '.join(undated)} have no time: several captures need times to "
                "interpolate the light between them",
                path=folder,
                hint="add a time column (ISO 8601) to their frames.csv",
            )
        captures.sort(key=lambda c: c.time_s)
    return records, captures
