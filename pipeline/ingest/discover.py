"""Discovery of a flight folder: which frames can be ingested, and which are quarantined.

Calibration folders are read strictly (:func:`pipeline.ingest.session.read_frame_table` raises on the
first bad frame). A flight is processed as far as possible instead: every frame that cannot be
used is *quarantined* with a one-line reason naming the file, and the rest go on. Discovery
finds what the frame table and the folder listing reveal without decoding any pixels:

- listed in ``frames.csv`` but the file does not exist;
- no exposure time (no row value and no EXIF ExposureTime), zero or negative exposure or gain,
  a value that is not a number, a time that is not ISO 8601, lat/lon out of range;
- listed twice in ``frames.csv`` (both rows are ambiguous, the frame is left out);
- not an image file (a listed file whose suffix is not one of the image formats);
- two files with the same frame name (file stem), e.g. ``IMG_1.tif`` and ``IMG_1.png``.

Problems only decoding reveals (truncated or unreadable files, wrong size for the camera, DN
beyond the bit depth) are found by :mod:`pipeline.ingest.raw` while it reads each frame; they are
quarantined the same way. A ``frames.csv`` that cannot be read as a whole (a required column
missing, not UTF-8) is still an error: :class:`~mscal_core.errors.SessionError`.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from mscal_core.errors import FrameError, InputError, MscalError

from pipeline.ingest.catalog import Camera
from pipeline.ingest.session import FRAMES_CSV, IMAGE_SUFFIXES, FrameRecord, read_frame_table

__all__ = ["Discovery", "discover_flight", "quarantine_entry"]


@dataclass
class Discovery:
    """Frames of a flight that may be ingested (sorted by file name) and those quarantined."""

    frames: list[FrameRecord] = field(default_factory=list)
    quarantined: list[dict[str, str]] = field(default_factory=list)
    # positions left out (no GPS fix, out of the flight's reach): run.json metadata_problems
    metadata_problems: list[dict[str, object]] = field(default_factory=list)


def quarantine_entry(file: str, error: MscalError | str) -> dict[str, str]:
    """``{"file": name, "reason": one line}``; the reason always names the file."""
    reason = str(error)
    if file and file not in reason:
        reason = f"{file}: {reason}"
    return {"file": file, "reason": reason}


def discover_flight(flight_dir: str | Path, camera: Camera) -> Discovery:
    """Frames of ``flight_dir`` with their metadata; unusable ones quarantined, not raised.

    Raises :class:`SessionError` if the folder does not exist, holds no frames at all, or its
    ``frames.csv`` is unreadable as a whole; :class:`InputError` for cameras that write one
    file per band (a frame is then a capture of several files: :mod:`pipeline.apply.captures`).
    """
    flight_dir = Path(flight_dir)
    if camera.layout.kind == "file_per_band":
        raise InputError(
            f"camera {camera.name} writes one file per band; flight ingest reads one file per frame",
            path=flight_dir,
            hint="its captures are read by 'mscal apply' itself (pipeline.apply.captures.find_captures)",
        )
    found = Discovery()

    def on_frame_error(name: str, exc: FrameError) -> None:
        found.quarantined.append(quarantine_entry(name, exc))

    records = read_frame_table(flight_dir, on_frame_error=on_frame_error,
                               on_position_problem=lambda p: found.metadata_problems.append(p.as_dict()))

    by_stem: dict[str, list[FrameRecord]] = defaultdict(list)
    for rec in records:
        if rec.path.suffix.lower() not in IMAGE_SUFFIXES:
            found.quarantined.append(
                quarantine_entry(
                    rec.path.name,
                    f"{rec.path.name}: not an image file (listed in {FRAMES_CSV}; frames are "
                    f"{', '.join(IMAGE_SUFFIXES)})",
                )
            )
            continue
        by_stem[rec.name].append(rec)
    for stem, recs in by_stem.items():
        if len(recs) == 1:
            found.frames.append(recs[0])
            continue
        names = ", ".join(r.path.name for r in recs)
        for r in recs:
            found.quarantined.append(
                quarantine_entry(
                    r.path.name,
                    f"{r.path.name}: frame name {stem!r} is used by several files ({names}); "
                    "rename or remove all but one",
                )
            )
    found.frames.sort(key=lambda r: r.path.name)
    found.quarantined.sort(key=lambda q: q["file"])
    return found
