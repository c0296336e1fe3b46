"""The calibration library: every field calibration fitted, by camera and serial number.

A calibration belongs to one camera body. ``mscal calibrate`` (and the post-flight run)
record each store they fit here (:func:`record_fitted`), keyed by the catalog camera and the
camera's serial number (:func:`camera_serial`, from the band files' metadata), with the time
the session's field data was taken (:func:`session_time`). A later flight of the same camera
(same serial) then finds the newest calibration fitted before it (:func:`lookup`,
:func:`find_for_flight`); a flight of another serial, or of unknown serial, never gets one.

Layout under the library root (``<cache>/library``, :func:`default_library_root`)::

    index.json                                   one entry per calibration recorded
    <camera>/<serial or "unknown">/<UTC time>-<hash>.zarr   a copy of the store

Each copy appears whole or not at all (copied under a temporary name, fsynced, renamed); the
index is rewritten atomically while the library's lock is held, so that two processes
recording at once both end up in it. The same calibration (same files) recorded twice is
one entry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

from mscal_core.errors import CalibrationStoreError, FrameError, InputError, MscalError, SessionError

from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.cameras.registry import serial_tags
from pipeline.ingest.captures import read_frames
from pipeline.ingest.catalog import Camera, load_camera, read_yaml
from pipeline.ingest.exif import EXIF_CODES, as_utc, parse_utc
from pipeline.ingest.intrinsics import XMP_TAG, tiff_tags
from pipeline.ingest.session import FRAMES_CSV, IMAGE_SUFFIXES, session_yaml_near
from pipeline.ingest.xmp import Xmp, xmp_of_bytes
from pipeline.storage.atomic import TMP_MARK, atomic_folder, iter_files, write_json_atomic
from pipeline.storage.cache import default_cache_dir
from pipeline.storage.lock import FolderLock
from pipeline.storage.store import file_sha256, open_calibration

log = logging.getLogger(__name__)

__all__ = [
    "LIBRARY_FORMAT",
    "LibraryEntry",
    "camera_serial",
    "default_library_root",
    "entries",
    "file_serial",
    "find_for_flight",
    "frame_times",
    "lookup",
    "record",
    "record_fitted",
    "session_time",
    "store_digest",
]

LIBRARY_FORMAT = "mscal-calibration-library/1"
INDEX_NAME = "index.json"
LOCK_NAME = ".index.lock"
#: How long a process waits for another one that is recording into the library.
LOCK_WAIT_S = 120.0
UNKNOWN_SERIAL = "unknown"
#: The session folders whose frames a field calibration is fitted from.
CALIBRATION_FOLDERS = ("response", "vignetting", "reflector")
#: TIFF tag 50735, DNG CameraSerialNumber (read where EXIF BodySerialNumber is missing).
DNG_CAMERA_SERIAL = 50735
INDEX_FIX = ("move it aside or delete it; the next calibration recorded starts a new index, and the stores "
             "already copied are found again once their sessions are calibrated again")
_ENTRY_KEYS = {"camera": str, "serial": (str, type(None)), "session_time": (str, type(None)), "fitted_utc": str,
               "store": str, "sha256": str, "session": (str, type(None))}


def default_library_root() -> Path:
    """``<cache>/library`` (:func:`pipeline.storage.cache.default_cache_dir`)."""
    return default_cache_dir() / "library"


@dataclass(frozen=True)
class LibraryEntry:
    """One calibration of the library; ``store`` is the absolute path of its copy."""

    camera: str
    serial: str | None
    session_time: datetime | None  # when the session's field data was taken (UTC)
    fitted_utc: datetime
    store: Path
    sha256: str
    session: str | None  # the session folder it was fitted from

    @property
    def time(self) -> datetime:
        """What :func:`lookup` compares with the flight's time: the session's, else the fit's."""
        return self.session_time or self.fitted_utc


# --------------------------------------------------------------------------- serial numbers


def _text(value: Any) -> str | None:
    """A tag's value as stripped text (bytes as Latin-1, NULs removed); None when empty."""
    if isinstance(value, (list, tuple)):
        value = value[0] if value else None
    if value is None:
        return None
    text = value.decode("latin-1", errors="replace") if isinstance(value, bytes) else str(value)
    text = text.strip().strip("\x00").strip()
    return text or None


def _xmp_serial(xmp: Xmp) -> str | None:
    """The camera's serial in the first of the makers' XMP serial tags the packet has
    (:attr:`pipeline.ingest.cameras.registry.Maker.serial_tags`: DJI's
    ``drone-dji:CameraSerialNumber``). MicaSense and Parrot write the camera's serial in EXIF;
    their XMP serials (``DLS:Serial``, ``Camera:SunshineSerialNumber``) are the sun sensor's,
    not the camera's, and are named by no maker."""
    for ns, name in serial_tags():
        serial = _text(xmp.text(name, (ns,)))
        if serial is not None:
            return serial
    return None


def file_serial(path: str | Path) -> str | None:
    """The camera serial number a frame file carries: EXIF ``BodySerialNumber``, else TIFF tag
    50735 (the tags :attr:`CaptureMeta.serial` is read from), else the maker's XMP serial
    (:func:`pipeline.ingest.cameras.registry.serial_tags`); None for a file without one (PNG frames, cameras that write
    none). :class:`FrameError` for a TIFF or JPEG that cannot be read."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        try:
            metas = read_file_metas(path)
            serial = metas[0].serial if metas else None
        except FrameError:  # an ordinary camera's JPEG, without the factory tags read there
            serial = None
        return serial if serial is not None else _xmp_serial(xmp_of_bytes(path.read_bytes(), path))
    if suffix not in (".tif", ".tiff"):
        return None
    tags = tiff_tags(path)
    serial = _text(tags.get(EXIF_CODES["BodySerialNumber"])) or _text(tags.get(DNG_CAMERA_SERIAL))
    if serial is None and tags.get(XMP_TAG) is not None:
        try:
            serial = _xmp_serial(Xmp.parse(tags[XMP_TAG], path))
        except FrameError:  # a damaged packet carries no serial
            serial = None
    return serial


def _camera(camera: Camera | str) -> Camera:
    return load_camera(camera) if isinstance(camera, str) else camera


def _frame_files(folders: Iterable[Path], camera: Camera) -> list[Path]:
    """The frame files under ``folders`` (subfolders too; hidden names left out), only those
    named like the camera's captures when its catalog entry says how."""
    pattern = re.compile(camera.layout.capture_pattern) if camera.layout.capture_pattern else None
    out = []
    for folder in folders:
        for parts, _ in iter_files(folder):
            name = parts[-1]
            if any(p.startswith(".") for p in parts) or Path(name).suffix.lower() not in IMAGE_SUFFIXES:
                continue
            if pattern is None or pattern.match(name):
                out.append(folder.joinpath(*parts))
    return sorted(out)


def _yaml_serial(path: Path) -> str | None:
    """session.yaml's optional top-level ``serial``: the serial of a camera whose frames carry
    none (a snapshot camera's frames.csv session)."""
    data = read_yaml(path, SessionError)
    value = data.get("serial") if isinstance(data, dict) else None
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int)) or not str(value).strip():
        raise SessionError(f"serial must be the camera's serial number as text, got {value!r}", path=path,
                           hint="e.g. serial: \"RE02-1234567\" (quoted)")
    return str(value).strip()


def _sources(folder_or_files: str | Path | Iterable[str | Path]) -> tuple[list[Path], Path | None, bool]:
    """``(folders or files, session.yaml or None, whether they are folders)`` of
    :func:`camera_serial`'s argument."""
    if isinstance(folder_or_files, (str, Path)):
        p = Path(folder_or_files)
        if p.is_file():
            return [p], None, False
        if not p.is_dir():
            raise InputError("folder not found", path=p, hint="pass a session folder, a frame folder or frame files")
        if (p / "session.yaml").is_file():  # a field session: its calibration frames; else its own frames
            field = [p / n for n in CALIBRATION_FOLDERS if (p / n).is_dir()]
            return field or [p], p / "session.yaml", True
        return [p], session_yaml_near(p), True
    return [Path(f) for f in folder_or_files], None, False


def camera_serial(folder_or_files: str | Path | Iterable[str | Path], camera: Camera | str) -> str | None:
    """The serial number of the camera that wrote a session (its response, vignetting and
    reflector frames; a folder with session.yaml and none of those: its own frames), a frame
    folder (a flight) or the frame files given.

    Read from every frame file (:func:`file_serial`); files that cannot be read are left out
    (they are reported where they are used). Where no file carries a serial, the optional
    top-level ``serial:`` of the session's session.yaml; None when neither says one.
    :class:`InputError` when the files name two serials (frames of two cameras), or when
    session.yaml's differs from the files'.
    """
    cam = _camera(camera)
    sources, yaml_path, folders = _sources(folder_or_files)
    files = _frame_files(sources, cam) if folders else sources
    found: dict[str, tuple[str, Path]] = {}  # casefolded serial -> (serial, first file)
    for f in files:
        try:
            serial = file_serial(f)
        except FrameError as exc:
            log.debug("no serial number from %s: %s", f, exc)
            continue
        if serial is not None:
            found.setdefault(serial.casefold(), (serial, f))
    if len(found) > 1:
        (a, fa), (b, fb) = list(found.values())[:2]
        raise InputError(f"frames of two cameras: {fa} has serial number {a}, {fb} has {b}",
                         path=fb.parent, hint="keep the frames of one camera in a session or flight folder")
    stated = _yaml_serial(yaml_path) if yaml_path is not None else None
    if found:
        serial, where = next(iter(found.values()))
        if stated is not None and stated.casefold() != serial.casefold():
            raise SessionError(f"serial is {stated} but the frames say {serial} ({where})", path=yaml_path,
                               hint="correct serial in session.yaml, or remove it: the frames' serial is used")
        return serial
    return stated


# --------------------------------------------------------------------------- times


def _parse_time(text: Any) -> datetime | None:
    if not text:
        return None
    try:
        return parse_utc(str(text))
    except (ValueError, OverflowError):
        return None


def _iso(dt: datetime | None) -> str | None:
    return None if dt is None else as_utc(dt).isoformat().replace("+00:00", "Z")


def _frame_folders(folder: Path, camera: Camera) -> list[Path]:
    """Where :func:`read_frames` reads ``folder``'s frames: itself for a camera whose captures
    are read from subfolders too; else it and each subfolder holding frames (capture
    subfolders of ``reflector/``)."""
    if camera.layout.kind == "file_per_band":
        return [folder]
    out = []
    for d in [folder, *sorted(p for p in folder.rglob("*") if p.is_dir())]:
        if any(part.startswith(".") for part in d.relative_to(folder).parts):
            continue
        if any(p.is_file() and (p.suffix.lower() in IMAGE_SUFFIXES or p.name == FRAMES_CSV) for p in d.iterdir()):
            out.append(d)
    return out


def frame_times(folder: str | Path, camera: Camera | str) -> list[datetime]:
    """The capture times (UTC) of the frames of ``folder`` that have one: frames.csv ``time``,
    else the files' EXIF time (:func:`pipeline.ingest.exif.exposure_time`), as the fits read
    them (:func:`pipeline.ingest.captures.read_frames`). Raises as that does for a folder
    whose frames cannot be read."""
    cam = _camera(camera)
    times = []
    for d in _frame_folders(Path(folder), cam):
        for rec in read_frames(d, cam):
            t = _parse_time(rec.time)
            if t is not None:
                times.append(t)
    return times


def _session_camera(root: Path) -> Camera:
    """The camera session.yaml names (read here, not validated: the fits did that)."""
    path = root / "session.yaml"
    if not path.is_file():
        raise SessionError("session.yaml is missing", path=path, hint="pass the session folder")
    data = read_yaml(path, SessionError)
    if not isinstance(data, dict) or not data.get("camera"):
        raise SessionError("camera is missing", path=path, hint="name the catalog camera: camera: NAME")
    return load_camera(str(data["camera"]))


def session_time(session_dir: str | Path, camera: Camera | str | None = None) -> datetime | None:
    """When the session's field data was taken: the newest capture time (UTC) of its
    response, vignetting and reflector frames (:func:`frame_times`); None when no frame has
    a time. ``camera``: the session's (default: session.yaml's)."""
    root = Path(session_dir)
    cam = _camera(camera) if camera is not None else _session_camera(root)
    times = [t for name in CALIBRATION_FOLDERS if (root / name).is_dir() for t in frame_times(root / name, cam)]
    return max(times, default=None)


# --------------------------------------------------------------------------- the index


def _entry(raw: Any, k: int, root: Path, path: Path) -> LibraryEntry:
    """Entry ``k`` of the index at ``path``, checked."""
    if not isinstance(raw, dict):
        raise InputError(f"entry {k} is not a JSON object", path=path, hint=INDEX_FIX)
    for key, kind in _ENTRY_KEYS.items():
        if not isinstance(raw.get(key), kind):
            raise InputError(f"entry {k}: {key} is missing or not of the right type ({raw.get(key)!r})",
                             path=path, hint=INDEX_FIX)
    fitted = _parse_time(raw["fitted_utc"])
    if fitted is None or (raw["session_time"] is not None and _parse_time(raw["session_time"]) is None):
        raise InputError(f"entry {k}: a time is not ISO 8601 ({raw['fitted_utc']!r}, {raw['session_time']!r})",
                         path=path, hint=INDEX_FIX)
    return LibraryEntry(camera=raw["camera"], serial=raw["serial"], session_time=_parse_time(raw["session_time"]),
                        fitted_utc=fitted, store=root / raw["store"], sha256=raw["sha256"], session=raw["session"])


def _read_index(root: Path) -> list[dict[str, Any]]:
    """The raw entries of ``root/index.json`` (each checked); [] when there is none yet.
    :class:`InputError` naming the file for one that cannot be read."""
    path = root / INDEX_NAME
    if not path.is_file():
        return []
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"the calibration library's index is not valid JSON ({exc})", path=path,
                         hint=INDEX_FIX) from None
    except OSError as exc:
        raise InputError(f"the calibration library's index cannot be read ({exc.strerror})", path=path) from None
    if not isinstance(data, dict) or data.get("format") != LIBRARY_FORMAT or not isinstance(data.get("entries"), list):
        raise InputError(f"not a calibration library index (format {LIBRARY_FORMAT} with a list of entries)",
                         path=path, hint=INDEX_FIX)
    for k, raw in enumerate(data["entries"]):
        _entry(raw, k, root, path)
    return data["entries"]


def entries(library_root: str | Path | None = None) -> list[LibraryEntry]:
    """Every calibration of the library, as recorded (oldest first)."""
    root = Path(library_root) if library_root is not None else default_library_root()
    return [_entry(raw, k, root, root / INDEX_NAME) for k, raw in enumerate(_read_index(root))]


def _same_serial(a: str | None, b: str | None) -> bool:
    return a is not None and b is not None and a.strip().casefold() == b.strip().casefold()


def lookup(camera: Camera | str, serial: str | None, flight_time: datetime | None,
           library_root: str | Path | None = None) -> LibraryEntry | None:
    """The newest calibration of ``camera`` with serial number ``serial`` (the same text, in
    any case) taken at or before ``flight_time`` (its session's time, else when it was
    fitted; a time without a zone is UTC); ``flight_time`` None: the newest. None when there
    is none, and always for ``serial`` None. Entries whose copy is gone are passed over."""
    if serial is None or not serial.strip():
        return None
    name = camera if isinstance(camera, str) else camera.name
    when = None if flight_time is None else as_utc(flight_time)
    found = []
    for e in entries(library_root):
        if e.camera != name or not _same_serial(e.serial, serial) or (when is not None and e.time > when):
            continue
        if not e.store.is_dir():
            log.warning("calibration library: %s is listed but gone; passed over", e.store)
            continue
        found.append(e)
    return max(found, key=lambda e: (e.time, e.fitted_utc), default=None)


# --------------------------------------------------------------------------- recording


def store_digest(store_path: str | Path) -> str:
    """sha256 of a store's files (relative path and content of each; temporaries and lock
    files left out): the same store, copied or not, has the same digest."""
    store = Path(store_path)
    h = hashlib.sha256()
    for parts, _ in sorted(iter_files(store), key=lambda item: item[0]):
        if TMP_MARK in parts[-1] or parts[-1].endswith(".lock"):
            continue
        h.update("/".join(parts).encode() + b"\0" + file_sha256(store.joinpath(*parts)).encode() + b"\n")
    return h.hexdigest()


def _component(text: str) -> str:
    """``text`` as one safe folder name (anything but letters, digits, ``.``, ``_`` and ``-``
    becomes ``_``)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", text.strip())
    return safe.lstrip(".") or "_"


def _skip_temporaries(folder: str, names: list[str]) -> list[str]:
    return [n for n in names if TMP_MARK in n or n.endswith(".lock")]


def record(store_path: str | Path, *, camera: Camera | str, serial: str | None, session_time: datetime | None,
           library_root: str | Path | None = None, session: str | Path | None = None) -> Path:
    """Copy the calibration store ``store_path`` of ``camera`` into the library as
    ``<camera>/<serial or unknown>/<UTC time>-<hash>.zarr`` (the time: ``session_time``, else
    when the store was fitted) and add its entry to ``index.json``; returns the copy's path.
    ``session``: the session folder it was fitted from (default: the store's own record).
    The same store (:func:`store_digest`) recorded again for the same camera and serial adds
    nothing and returns the existing copy. :class:`CalibrationStoreError` for a store that
    is not a calibration of ``camera``."""
    store = Path(store_path)
    camera = camera if isinstance(camera, str) else camera.name
    attrs = open_calibration(store).attrs
    if attrs.get("camera") != camera:
        raise CalibrationStoreError(f"store is for camera {attrs.get('camera')!r}, not {camera!r}", path=store,
                                    hint="record a calibration under the camera it was fitted for")
    digest = store_digest(store)
    fitted = _parse_time(attrs.get("created_utc")) or datetime.now(timezone.utc)
    source = session if session is not None else (attrs.get("session") or None)
    root = Path(library_root) if library_root is not None else default_library_root()
    rel = Path(_component(camera), _component(serial) if serial else UNKNOWN_SERIAL,
               f"{as_utc(session_time or fitted).strftime('%Y%m%dT%H%M%SZ')}-{digest[:12]}.zarr")
    with FolderLock(root, name=LOCK_NAME, wait=LOCK_WAIT_S, what="another mscal process recording a calibration"):
        index = _read_index(root)
        for raw in index:
            same = raw["camera"] == camera and raw["sha256"] == digest and (
                _same_serial(raw["serial"], serial) or (raw["serial"] is None and serial is None))
            if same and (root / raw["store"]).is_dir():
                log.info("calibration library: %s is already recorded as %s", store, raw["store"])
                return root / raw["store"]
        with atomic_folder(root / rel, durable=True) as tmp:
            shutil.copytree(store, tmp, ignore=_skip_temporaries)
        entry = {"camera": camera, "serial": serial, "session_time": _iso(session_time), "fitted_utc": _iso(fitted),
                 "store": rel.as_posix(), "sha256": digest, "session": None if source is None else str(source)}
        kept = [raw for raw in index if raw["store"] != entry["store"]]
        write_json_atomic(root / INDEX_NAME, {"format": LIBRARY_FORMAT, "entries": [*kept, entry]}, sort_keys=False)
    log.info("calibration library: recorded %s as %s", store, rel)
    return root / rel


def record_fitted(store_path: str | Path, session_dir: str | Path, *,
                  library_root: str | Path | None = None) -> Path:
    """Record the calibration ``store_path`` fitted from ``session_dir`` (:func:`record`): its
    camera from the store, the serial from the session's frames (:func:`camera_serial`), the
    session's time (:func:`session_time`). What ``mscal calibrate`` calls once it has
    written its store; returns the library's copy."""
    store = Path(store_path)
    name = open_calibration(store).attrs.get("camera")
    if not name:
        raise CalibrationStoreError("store names no camera (attribute camera)", path=store,
                                    hint="re-create it with 'mscal calibrate'")
    camera = load_camera(str(name))
    root = Path(session_dir)
    return record(store, camera=camera.name, serial=camera_serial(root, camera),
                  session_time=session_time(root, camera), library_root=library_root,
                  session=str(root.resolve()))


def find_for_flight(flight_dir: str | Path, camera: Camera | str,
                    library_root: str | Path | None = None) -> LibraryEntry | None:
    """The library's calibration for a flight folder: :func:`lookup` with the serial of its
    frames (:func:`camera_serial`) and its first capture time; a flight whose times cannot
    be read gets the newest calibration of its camera and serial."""
    cam = _camera(camera)
    serial = camera_serial(flight_dir, cam)
    if serial is None:
        return None
    try:
        start = min(frame_times(flight_dir, cam), default=None)
    except MscalError as exc:
        log.warning("calibration library: the capture times of %s cannot be read (%s); the newest "
                    "calibration of serial %s is used", flight_dir, exc, serial)
        start = None
    return lookup(cam, serial, start, library_root)
