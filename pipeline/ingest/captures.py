"""Frame folders of one-file-per-band cameras (MicaSense-style) in a session: one capture, one frame.

The camera writes ``IMG_0000_1.tif ... IMG_0000_5.tif`` per capture (the catalog's
``capture_pattern``), possibly into SD-card subfolders (``SET/000/``); a capture is one frame
of the paper's datasets, read as a ``(band, H, W)`` stack. Its exposure, gain and time come
from ``frames.csv`` when the folder has one (a row per capture, ``file`` = the capture name
``IMG_0000`` or any of its band files, or a row per band file), else from each band file's
EXIF ``ExposureTime`` (s), ``ISOSpeed``/``ISOSpeedRatings`` (gain = ISO / 100) and
``DateTimeOriginal`` -- of a file with factory metadata the exposure and gain apply reads
(:func:`band_file_record`: DJI's XMP SensorGain, not its ISO). A multi-lens camera exposes
each lens on its own, so each band keeps its own exposure (:meth:`FrameRecord.band_exposure`). Unlike the factory route
(:func:`pipeline.ingest.grouping.group_captures`), no radiometric calibration tags are
needed: the field calibration replaces them.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

from mscal_core.errors import FrameError, SessionError

from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.catalog import Camera
from pipeline.ingest.exif import exposure_time, rational
from pipeline.ingest.grouping import DEFAULT_CAPTURE_PATTERN
from pipeline.ingest.intrinsics import EXIF_CODES, XMP_TAG, tiff_tags
from pipeline.ingest.meta import xmp_utc_time
from pipeline.ingest.session import FRAMES_CSV, IMAGE_SUFFIXES, FrameRecord, read_frame_table
from pipeline.ingest.xmp import Xmp

EXPOSURE_TIME, ISO_SPEED_RATINGS, ISO_SPEED, DATE_TIME_ORIGINAL, SUBSEC_ORIGINAL = (
    EXIF_CODES[k] for k in ("ExposureTime", "ISOSpeedRatings", "ISOSpeed", "DateTimeOriginal", "SubsecTimeOriginal"))


def is_multilens(camera: Camera) -> bool:
    return camera.layout.kind == "file_per_band"


def read_frames(folder: str | Path, camera: Camera, *, recursive: bool = True) -> list[FrameRecord]:
    """The frames of a session folder for ``camera``: :func:`read_capture_table` for a
    one-file-per-band camera, else :func:`pipeline.ingest.session.read_frame_table`."""
    if is_multilens(camera):
        return read_capture_table(folder, camera, recursive=recursive)
    return read_frame_table(folder)


def band_file_record(path: Path) -> FrameRecord:
    """Exposure, gain and time of one band file: those apply takes (the
    :class:`pipeline.ingest.meta.CaptureMeta` of
    :func:`pipeline.ingest.camera_meta.read_file_metas`: a DJI file's XMP ExposureTime x
    SensorGain, a MicaSense file's EXIF ExposureTime x ISO / 100) when the file has factory
    metadata, so that a field calibration and its apply see one effective exposure; else
    from its EXIF (:func:`exif_band_record`)."""
    try:
        meta = read_file_metas(path)[0]
    except FrameError:  # no factory metadata (a field-only camera): the EXIF rule
        return exif_band_record(path)
    if not (meta.exposure_s > 0 and meta.gain > 0):  # a band read but not modelled (thermal): the EXIF rule
        return exif_band_record(path)
    return FrameRecord(path=path, exposure_ms=meta.exposure_s * 1000.0, gain=meta.gain, time=meta.time)


def exif_band_record(path: Path) -> FrameRecord:
    """Exposure, gain and time of one band file from its EXIF: ExposureTime, ISOSpeed /
    ISOSpeedRatings (gain = ISO / 100), DateTimeOriginal (:class:`FrameError` if it has no
    exposure)."""
    tags = tiff_tags(path)
    if EXPOSURE_TIME not in tags:
        raise FrameError("no exposure time: no frames.csv row and no EXIF ExposureTime", path=path,
                         hint="add a frames.csv with file,exposure_ms (file: the capture name, e.g. IMG_0000)")
    exposure_ms = rational(tags[EXPOSURE_TIME]) * 1000.0
    iso = tags.get(ISO_SPEED) or tags.get(ISO_SPEED_RATINGS)
    if isinstance(iso, tuple):
        iso = iso[0] if iso else None
    gain = float(iso) / 100.0 if iso else 1.0
    packet = tags.get(XMP_TAG)
    utc = None
    if packet is not None:
        try:
            utc = xmp_utc_time(Xmp.parse(packet, path))
        except FrameError:  # a damaged packet: the EXIF time stands
            utc = None
    time = exposure_time(tags.get(DATE_TIME_ORIGINAL),
                         tags.get(SUBSEC_ORIGINAL) or tags.get(EXIF_CODES["SubsecTime"]),  # RedEdge: SubsecTime
                         tags.get(EXIF_CODES["OffsetTimeOriginal"]), utc)
    if not (exposure_ms > 0 and gain > 0):
        raise FrameError(f"EXIF exposure {exposure_ms:g} ms / gain {gain:g} must be positive", path=path)
    return FrameRecord(path=path, exposure_ms=exposure_ms, gain=gain, time=time)


def read_capture_table(folder: str | Path, camera: Camera, *, recursive: bool = True) -> list[FrameRecord]:
    """One :class:`FrameRecord` per complete capture in ``folder`` (and its subfolders when
    ``recursive``), sorted by capture name; see the module docstring. A capture with a band
    file missing, or a band file without an exposure, raises :class:`FrameError` naming it."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SessionError("frame folder not found", path=folder)
    pattern = re.compile(camera.layout.capture_pattern or DEFAULT_CAPTURE_PATTERN)
    suffixes = [str(b.file_suffix) for b in camera.bands]
    files = sorted(folder.rglob("*") if recursive else folder.iterdir())
    groups: dict[str, dict[str, Path]] = {}
    for p in files:
        if not p.is_file() or p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        m = pattern.match(p.name)
        if m is None:
            continue
        rel = p.relative_to(folder).parent
        name = str(rel / m["capture"]) if str(rel) != "." else m["capture"]
        if m["band"] in groups.setdefault(name, {}):
            raise FrameError(f"capture {name}: band {m['band']} twice", path=p)
        groups[name][m["band"]] = p
    if not groups:
        raise SessionError(
            f"no captures of camera {camera.name} found",
            path=folder,
            hint=f"band files named like IMG_0000_{suffixes[0]}.tif (pattern {pattern.pattern})",
        )
    table = _capture_rows(folder, groups, pattern)
    records = []
    for name in sorted(groups):
        bands = groups[name]
        missing = [s for s in suffixes if s not in bands]
        extra = sorted(set(bands) - set(suffixes))
        if missing or extra:
            first = min(bands.values())
            raise FrameError(
                f"capture {name}: " + "; ".join(([f"band file(s) {', '.join(missing)} missing"] if missing else [])
                                                + ([f"unexpected band file(s) {', '.join(extra)}"] if extra else [])),
                path=first, hint=f"camera {camera.name} writes bands {', '.join(suffixes)}; restore or remove the capture",
            )
        band_files = tuple(bands[s] for s in suffixes)
        per_band = []
        for s, f in zip(suffixes, band_files):
            row = table.get(f.name) or table.get(name) or table.get(f"{name}_{s}")
            per_band.append(row if row is not None else band_file_record(f))
        first = per_band[0]
        exposures = tuple(r.effective_exposure for r in per_band)
        records.append(FrameRecord(
            path=band_files[0], exposure_ms=first.exposure_ms, gain=first.gain, time=first.time, lat=first.lat,
            lon=first.lon, alt_m=first.alt_m, irradiance=first.irradiance, band_files=band_files,
            capture=name, band_effective_exposure=None if len(set(exposures)) == 1 else exposures,
        ))
    return records


def _capture_rows(folder: Path, groups: dict[str, dict[str, Path]], pattern: re.Pattern) -> dict[str, FrameRecord]:
    """frames.csv rows keyed by their ``file`` (a capture name or a band file name); empty
    without frames.csv."""
    csv_path = folder / FRAMES_CSV
    if not csv_path.is_file():
        return {}
    with csv_path.open(newline="", encoding="utf-8-sig") as fh:
        names = [(row.get("file") or "").strip() for row in csv.DictReader(fh)]
    known = set(groups) | {p.name for g in groups.values() for p in g.values()}
    unknown = [n for n in names if n and n not in known]
    if unknown:
        raise FrameError(f"frames.csv lists {', '.join(unknown[:3])}, which is neither a capture nor a band file here",
                         path=csv_path, hint="file: the capture name (IMG_0000) or a band file (IMG_0000_1.tif)")
    # read_frame_table validates every row (captures have no file of their own name); band
    # files without a row are read from their EXIF later, so their errors here do not count
    listed = set(names)
    errors: dict[str, FrameError] = {}
    recs = read_frame_table(folder, require_files=False, on_frame_error=lambda n, e: errors.setdefault(n, e))
    for n, e in errors.items():
        if n in listed or n.startswith(FRAMES_CSV):
            raise e
    return {r.path.name: r for r in recs if r.path.name in listed}


__all__ = ["band_file_record", "is_multilens", "read_capture_table", "read_frames"]
