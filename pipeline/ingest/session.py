"""Session folders (SPEC.md): session.yaml, frame tables and frame files.

Reading is strict and names the file at fault: a session that cannot be trusted stops here
with a one-line reason, before any fit runs.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Callable

import numpy as np
from mscal_core.errors import CatalogError, FrameError, InputError, SessionError
from mscal_core.geometry import Intrinsics
from mscal_core.mosaic import demosaic
from pydantic import BeforeValidator, Field

from pipeline.ingest.catalog import Camera, Reflectance, ReflectanceSpec, load_camera, read_yaml, reflectance_spec
from pipeline.ingest.exif import (
    dms_to_degrees,
    exif_time_utc,
    exifread_tags,
    parse_iso,
    rational,
    signed_gps,
    utc_naive,
)
from pipeline.ingest.gps import placed_records
from pipeline.ingest.markers import Dictionary, MarkerId, MarkerSpec, parse_marker
from pipeline.ingest.products import yaml_choice
from pipeline.ingest.schema import Strict, Text, check, finite_number, items, number, show_key, validate
from pipeline.ingest.tiff import decode_frame
from pipeline.ingest.xmp import TagProblem

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg")  # JPEG: ordinary cameras (generic-rgb8)
FRAMES_CSV = "frames.csv"
TIME_RANGE = (1678, 2261)  # the years int64 nanoseconds (the datacube's time axis) can hold
MAX_NAME = 255  # the longest file name most file systems take


# --------------------------------------------------------------------------- session.yaml


@dataclass(frozen=True)
class ReflectorSpec:
    reflectance: ReflectanceSpec
    size_m: tuple[float, float]


@dataclass(frozen=True)
class Session:
    root: Path
    camera: Camera
    intrinsics: Intrinsics | None  # None: not in session.yaml (band_intrinsics, the store or metadata give them)
    reflector: ReflectorSpec
    marker: MarkerSpec
    panel_polygon: tuple[tuple[float, float], ...] | None = None  # session.yaml panel.polygon
    panel_marker: "PanelMarker | None" = None  # session.yaml panel.marker (+ size_m, offset_m)
    band_intrinsics: tuple[Intrinsics, ...] | None = None  # session.yaml intrinsics per band
    products: dict[str, Any] | None = None  # session.yaml products: the keys given (pipeline.ingest.products)

    def intrinsics_for(self, band: int) -> Intrinsics | None:
        """session.yaml's intrinsics of band ``band`` (per band, else the one for all), or None."""
        if self.band_intrinsics is not None:
            return self.band_intrinsics[band]
        return self.intrinsics

    @property
    def response_dir(self) -> Path:
        return self.root / "response"

    @property
    def vignetting_dir(self) -> Path:
        return self.root / "vignetting"

    @property
    def reflector_dir(self) -> Path:
        return self.root / "reflector"

    def flight_dirs(self) -> list[Path]:
        d = self.root / "flights"
        return sorted(p for p in d.iterdir() if p.is_dir()) if d.is_dir() else []


class IntrinsicsModel(Strict):
    """session.yaml's ``{fx, fy, cx, cy, dist}`` of one lens (pixels; OpenCV's distortion order)."""

    fx: number(positive=True)  # type: ignore[valid-type]
    fy: number(positive=True)  # type: ignore[valid-type]
    cx: number()  # type: ignore[valid-type]
    cy: number()  # type: ignore[valid-type]
    dist: items(lambda v: finite_number(v) is not None,  # type: ignore[valid-type]
                "[k1, k2, p1, p2, k3] (OpenCV order; 4, 5 or 8 numbers)", float, lambda n: n in (4, 5, 8)) = (0.0,) * 5


def parse_intrinsics(data: Any, path: Path) -> Intrinsics:
    """session.yaml ``intrinsics: {fx, fy, cx, cy, dist}`` (one band's, or all bands')."""
    return intrinsics_of(validate(IntrinsicsModel, data, path, SessionError, prefix="intrinsics"))


def intrinsics_of(m: IntrinsicsModel) -> Intrinsics:
    """The :class:`Intrinsics` of a validated ``{fx, fy, cx, cy, dist}``."""
    return Intrinsics(fx=m.fx, fy=m.fy, cx=m.cx, cy=m.cy, dist=m.dist + (0.0,) * (5 - len(m.dist)))


@dataclass(frozen=True)
class PanelMarker:
    """A reflectance panel found through an ArUco/AprilTag marker printed in its plane:
    the panel is the ``panel_size_m`` rectangle centred at ``offset_m`` in the marker frame
    (u right, v up as printed; :func:`mscal_core.panel.panel_from_marker`)."""

    dictionary: str  # an OpenCV name: DICT_4X4_50, DICT_APRILTAG_36h11, ...
    id: int
    size_m: float  # black square side
    panel_size_m: tuple[float, float]
    offset_m: tuple[float, float]


@dataclass(frozen=True)
class PanelConfig:
    """session.yaml ``panel``: a pixel polygon and/or a marker that locates the panel."""

    polygon: tuple[tuple[float, float], ...] | None = None
    marker: PanelMarker | None = None


PANEL_EXAMPLE = ("panel: {marker: {dictionary: DICT_APRILTAG_36h11, id: 7, size_m: 0.06}, "
                 "size_m: [0.15, 0.15], offset_m: [0.12, 0.0]}  or  panel: {polygon: [[x, y], ...]}")


#: A panel corner ``[x, y]`` in pixels.
_Corner = items(lambda v: finite_number(v) is not None and 0 <= v <= 1e6, "[x, y]: pixel coordinates from 0 to 1e6",
                float, lambda n: n == 2)
_Polygon = Annotated[tuple[_Corner, ...], Field(min_length=3)]  # type: ignore[valid-type]


class _PanelMarker(Strict):
    dictionary: Dictionary
    id: MarkerId  # type: ignore[valid-type]
    size_m: number(positive=True)  # type: ignore[valid-type]


class _Panel(Strict):  # a key given as null is no value: no "| None"
    polygon: _Polygon = None  # type: ignore[assignment]
    marker: _PanelMarker = None  # type: ignore[assignment]
    size_m: Annotated[items(lambda v: finite_number(v) is not None and v > 0,  # type: ignore[valid-type]
                            "[w, h] in metres (or one side), positive numbers", float, lambda n: n == 2),
                      BeforeValidator(lambda v: v if isinstance(v, list) else [v, v])] = None
    offset_m: items(lambda v: finite_number(v) is not None,  # type: ignore[valid-type]
                    "[du, dv] in metres (two numbers)", float, lambda n: n == 2) = (0.0, 0.0)


def parse_panel(data: Any, path: Path) -> PanelConfig:
    """session.yaml ``panel``: ``polygon`` (pixel corners, :func:`parse_panel_polygon`) and/or
    ``marker: {dictionary, id, size_m}`` with the panel's ``size_m`` (``[w, h]`` or one side)
    and ``offset_m`` (``[du, dv]`` of its centre from the marker's, default ``[0, 0]``); the
    panel rectangle must not cover the marker."""
    m = validate(_Panel, data, path, SessionError, prefix="panel")
    if m.polygon is None and m.marker is None:
        raise SessionError("panel needs a polygon or a marker", path=path, hint=PANEL_EXAMPLE)
    polygon = None if m.polygon is None else _enclosing(m.polygon, path)
    if m.marker is None:
        if {"size_m", "offset_m"} & m.model_fields_set:
            raise SessionError("panel.size_m and panel.offset_m go with panel.marker", path=path, hint=PANEL_EXAMPLE)
        return PanelConfig(polygon=polygon)
    if m.size_m is None:
        raise SessionError("panel.marker needs the panel's size_m ([w, h] in metres)", path=path, hint=PANEL_EXAMPLE)
    (w, h), (du, dv), msize = m.size_m, m.offset_m, m.marker.size_m
    if abs(du) < (w + msize) / 2 and abs(dv) < (h + msize) / 2:
        raise SessionError("the panel rectangle covers the marker", path=path,
                           hint="give panel.offset_m: where the panel's centre is from the marker's, in metres")
    return PanelConfig(polygon=polygon, marker=PanelMarker(m.marker.dictionary, m.marker.id, msize, (w, h), (du, dv)))


class _PanelPolygon(Strict):
    polygon: _Polygon  # type: ignore[valid-type]


def parse_panel_polygon(data: Any, path: Path) -> tuple[tuple[float, float], ...]:
    """session.yaml ``panel: {polygon: [[x, y], ...]}``: at least 3 (x, y) pixel corners."""
    return _enclosing(validate(_PanelPolygon, data, path, SessionError, prefix="panel").polygon, path)


def _enclosing(corners: tuple[tuple[float, float], ...], path: Path) -> tuple[tuple[float, float], ...]:
    """``corners``, which must enclose an area."""
    xs, ys = zip(*corners)
    if abs(sum(xs[i] * ys[i - 1] - xs[i - 1] * ys[i] for i in range(len(corners)))) < 2.0:
        raise SessionError(f"panel.polygon {[list(c) for c in corners]} encloses no area", path=path)
    return corners


class _Reflector(Strict):
    reflectance: Reflectance
    size_m: items(lambda v: finite_number(v) is not None and v > 0,  # type: ignore[valid-type]
                  "[width_m, height_m] (positive numbers)", float, lambda n: n == 2)


#: session.yaml's ``serial``: the serial number of a camera whose frames carry none (text, or
#: a number YAML read from an unquoted serial).
CameraSerial = Annotated[str, check(lambda v: isinstance(v, (str, int)) and not isinstance(v, bool) and bool(str(v).strip()),
                                    "must be the camera's serial number as text", lambda v: str(v).strip(),
                                    hint='e.g. serial: "RE02-1234567" (quoted)')]


class _SessionYaml(Strict):
    camera: Text
    reflector: _Reflector
    marker: Any  # parse_marker
    intrinsics: Any = None  # parse_intrinsics, or per band: parse_band_intrinsics
    panel: Any = None  # parse_panel
    products: Any = None  # pipeline.ingest.products.yaml_choice
    name: Any = None
    notes: Any = None
    serial: CameraSerial | None = None  # read by pipeline.calibrate.library


def load_session(root: str | Path) -> Session:
    """Read and validate ``SESSION/session.yaml``."""
    root = Path(root)
    if not root.is_dir():
        raise SessionError("session folder not found", path=root, hint="pass the folder that holds session.yaml")
    path = root / "session.yaml"
    if not path.is_file():
        raise SessionError("session.yaml is missing", path=path, hint="see SPEC.md for its keys")
    data = read_yaml(path, SessionError)
    m = validate(_SessionYaml, data, path, SessionError, label="session.yaml")
    try:
        camera = load_camera(m.camera)
    except CatalogError as exc:  # say which file named it, and which catalog file is at fault
        if exc.path is not None:
            raise SessionError(f"camera {m.camera!r}: its catalog entry {exc.path} is invalid: "
                               f"{exc.reason}", path=path, hint=exc.hint or "fix that catalog file") from None
        raise SessionError(f"camera: {exc.reason}", path=path,
                           hint=exc.hint or "name a camera of catalogs/cameras/, or add its entry there") from None
    intr: Intrinsics | None = None
    band_intr: tuple[Intrinsics, ...] | None = None
    raw_intr = m.intrinsics
    if isinstance(raw_intr, dict) and raw_intr and not {"fx", "fy", "cx", "cy"} & set(raw_intr):
        from pipeline.ingest.intrinsics import parse_band_intrinsics

        keys = [[b.name] + ([str(b.file_suffix)] if b.file_suffix is not None else []) for b in camera.bands]
        band_intr = parse_band_intrinsics(raw_intr, keys, path, IntrinsicsModel, intrinsics_of)
    elif raw_intr is not None:
        intr = parse_intrinsics(raw_intr, path)
    w, h = m.reflector.size_m
    reflector = ReflectorSpec(reflectance=reflectance_spec(m.reflector.reflectance, path, "reflector.reflectance"),
                              size_m=(w, h))
    marker = parse_marker(m.marker, path, reflector.size_m)
    panel = parse_panel(m.panel, path) if m.panel is not None else PanelConfig()
    return Session(
        root=root, camera=camera, intrinsics=intr, reflector=reflector, marker=marker, panel_polygon=panel.polygon,
        panel_marker=panel.marker, band_intrinsics=band_intr, products=yaml_choice(m.products, path),
    )


def session_yaml_near(folder: str | Path) -> Path | None:
    """The session.yaml of a frame folder: in ``folder`` or up to two levels above it
    (``SESSION/response/``, ``SESSION/flights/<name>/``), the nearest; None if there is none."""
    folder = Path(folder)
    for d in (folder, folder.parent, folder.parent.parent):
        if (d / "session.yaml").is_file():
            return d / "session.yaml"
    return None


def panel_config_near(folder: str | Path) -> tuple[PanelConfig, Path] | None:
    """The ``panel`` of the session.yaml near ``folder`` (:func:`session_yaml_near`), with its
    path; None if that session.yaml says none, or there is none. Only ``panel`` is read: a
    folder of factory captures needs no other session key."""
    path = session_yaml_near(folder)
    if path is None:
        return None
    data = read_yaml(path, SessionError)
    if isinstance(data, dict) and data.get("panel") is not None:
        return parse_panel(data["panel"], path), path
    return None


# --------------------------------------------------------------------------- frame tables


@dataclass(frozen=True)
class FrameRecord:
    """One frame and its metadata (from frames.csv, or the file's EXIF where no row exists)."""

    path: Path
    exposure_ms: float
    gain: float = 1.0
    time: str | None = None
    lat: float | None = None
    lon: float | None = None
    alt_m: float | None = None
    irradiance: float | None = None  # sun-sensor reading (frames.csv column), any unit, > 0
    # A capture of a one-file-per-band camera (pipeline.ingest.captures): its band files in
    # the camera's band order (``path`` is the first), its name, and each band's own
    # exposure x gain (ms) when the bands were exposed differently (MicaSense: per lens).
    band_files: tuple[Path, ...] | None = None
    capture: str | None = None
    band_effective_exposure: tuple[float, ...] | None = None
    gps_status: str | None = None  # EXIF GPSStatus as written (V: void, no fix: pipeline.ingest.gps)

    @property
    def effective_exposure(self) -> float:
        """Exposure time x linear gain (ms); the ``t`` of the paper's equations."""
        return self.exposure_ms * self.gain

    def band_exposure(self, band: int) -> float:
        """The ``t`` of band ``band``: its own exposure x gain for a capture whose bands were
        exposed separately, else :attr:`effective_exposure`."""
        if self.band_effective_exposure is not None:
            return self.band_effective_exposure[band]
        return self.effective_exposure

    @property
    def files(self) -> tuple[Path, ...]:
        """Every file of the frame (a capture's band files)."""
        return self.band_files if self.band_files is not None else (self.path,)

    @property
    def name(self) -> str:
        return self.capture if self.capture is not None else self.path.stem


def _parse_float(text: str, csv_path: Path, line: int, column: str) -> float | None:
    text = (text or "").strip()
    if not text:
        return None
    try:
        v = float(text)
    except ValueError:
        raise FrameError(f"line {line}: {column} {text!r} is not a number", path=csv_path) from None
    if not math.isfinite(v):
        raise FrameError(f"line {line}: {column} {text!r} is not finite", path=csv_path)
    return v


def _check_exposure(rec: FrameRecord, where: Path, line: int | None = None) -> None:
    at = f"line {line}: " if line else ""
    if not rec.exposure_ms > 0:
        raise FrameError(
            f"{at}frame {rec.path.name} has exposure_ms {rec.exposure_ms:g}; it must be positive",
            path=where,
            hint="fix the exposure in frames.csv or remove the frame",
        )
    if not rec.gain > 0:
        raise FrameError(f"{at}frame {rec.path.name} has gain {rec.gain:g}; it must be positive", path=where)


def read_frame_table(
    folder: str | Path,
    *,
    require_files: bool = True,
    on_frame_error: Callable[[str, FrameError], None] | None = None,
    on_position_problem: Callable[[TagProblem], None] | None = None,
) -> list[FrameRecord]:
    """Frames of a folder with their exposure and position (SPEC.md, Session folder).

    ``frames.csv`` (columns ``file,exposure_ms`` required; ``gain,time,lat,lon,alt_m,irradiance``
    optional) is read first; image files without a row fall back to their EXIF tags. A frame
    with no exposure anywhere, a zero or negative exposure, or a listed file that does not
    exist raises :class:`FrameError` naming the file.

    With ``on_frame_error`` (flights: process as far as possible) such a frame is instead
    reported as ``on_frame_error(file_name, error)`` and left out; a frame listed twice is
    left out entirely (its metadata is ambiguous). A table that cannot be read as a whole
    (missing column, not UTF-8) still raises :class:`SessionError`.

    A written position that is none (:func:`pipeline.ingest.gps.placed_records`: no GPS fix,
    or out of the flight's reach) is left out, and given to ``on_position_problem``.
    """
    dropped: set[str] = set()  # frames reported to on_frame_error: no EXIF fallback either

    def frame_error(name: str, exc: FrameError) -> None:
        if on_frame_error is None:
            raise exc
        dropped.add(name)
        on_frame_error(name, exc)

    folder = Path(folder)
    if not folder.is_dir():
        raise SessionError("frame folder not found", path=folder)
    csv_path = folder / FRAMES_CSV
    records: dict[str, FrameRecord] = {}
    if csv_path.is_file():
        try:
            with csv_path.open(newline="", encoding="utf-8-sig") as fh:
                reader = csv.DictReader(fh)
                _check_columns([c.strip() for c in (reader.fieldnames or [])], csv_path)
                for line, row in enumerate(reader, start=2):
                    row = {(k or "").strip(): (v or "") for k, v in row.items()}
                    name = row["file"].strip()
                    try:
                        rec = _table_row(folder, csv_path, line, row, name, records, require_files)
                    except FrameError as exc:
                        if name in records:  # listed twice: neither row can be trusted
                            del records[name]
                        frame_error(name or f"{FRAMES_CSV} line {line}", exc)
                        continue
                    if name not in dropped:
                        records[name] = rec
        except UnicodeDecodeError:
            raise SessionError("not a UTF-8 text file", path=csv_path) from None
        except csv.Error as exc:  # e.g. a field over the csv module's size limit (131072 characters)
            raise SessionError(f"not a readable CSV table (line {reader.line_num}: {exc})", path=csv_path,
                               hint="frames.csv is a comma-separated table: file,exposure_ms,...") from None
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in IMAGE_SUFFIXES and p.name not in records and p.name not in dropped:
            try:
                records[p.name] = exif_record(p)
            except FrameError as exc:
                frame_error(p.name, exc)
    if not records and not dropped:
        raise SessionError(
            "no frames found",
            path=folder,
            hint=f"put {', '.join(IMAGE_SUFFIXES)} frames and a frames.csv in the folder",
        )
    # a position written without a fix, or one the flight could not have reached: none
    return placed_records(sorted(records.values(), key=lambda r: r.path.name), on_position_problem)


def _check_columns(cols: list[str], csv_path: Path) -> None:
    """frames.csv's header: ``file`` and ``exposure_ms`` present, no column twice."""
    twice = sorted({c for c in cols if c and cols.count(c) > 1})
    if twice:
        raise SessionError(f"column(s) {', '.join(map(repr, twice))} given twice", path=csv_path,
                           hint="keep one column of each name")
    for need in ("file", "exposure_ms"):
        if need not in cols:
            raise SessionError(
                f"column {need!r} is missing (columns: {', '.join(map(show_key, cols)) or 'none'})",
                path=csv_path,
                hint="frames.csv needs at least file,exposure_ms",
            )


def _table_row(
    folder: Path,
    csv_path: Path,
    line: int,
    row: dict[str, str],
    name: str,
    records: dict[str, FrameRecord],
    require_files: bool,
) -> FrameRecord:
    """One validated frames.csv row (:class:`FrameError` naming the line and the frame)."""
    if not name:
        raise FrameError(f"line {line}: empty file name", path=csv_path)
    if name in (".", "..") or "/" in name or "\\" in name or not name.isprintable() or len(name.encode()) > MAX_NAME:
        raise FrameError(f"line {line}: file {name[:80]!r} is not the name of a file in this folder", path=csv_path,
                         hint="frames.csv lists the frames of its own folder by file name, without a path")
    exp = _parse_float(row["exposure_ms"], csv_path, line, "exposure_ms")
    if exp is None:
        raise FrameError(
            f"line {line}: frame {name} has no exposure_ms",
            path=csv_path,
            hint="every frame needs its exposure time; mscal never guesses one",
        )
    gain = _parse_float(row.get("gain", ""), csv_path, line, "gain")
    rec = FrameRecord(
        path=folder / name,
        exposure_ms=exp,
        gain=1.0 if gain is None else gain,
        time=_parse_time(row.get("time", ""), csv_path, line),
        lat=_parse_float(row.get("lat", ""), csv_path, line, "lat"),
        lon=_parse_float(row.get("lon", ""), csv_path, line, "lon"),
        alt_m=_parse_float(row.get("alt_m", ""), csv_path, line, "alt_m"),
        irradiance=_parse_float(row.get("irradiance", ""), csv_path, line, "irradiance"),
    )
    _check_exposure(rec, csv_path, line)
    if rec.irradiance is not None and rec.irradiance <= 0:
        raise FrameError(f"line {line}: frame {name} has irradiance {rec.irradiance:g}; it must be positive",
                         path=csv_path, hint="leave the cell empty when the sun sensor gave no reading")
    if rec.lat is not None and not -90 <= rec.lat <= 90:
        raise FrameError(f"line {line}: lat {rec.lat} outside [-90, 90]", path=csv_path)
    if rec.lon is not None and not -180 <= rec.lon <= 180:
        raise FrameError(f"line {line}: lon {rec.lon} outside [-180, 180]", path=csv_path)
    if name in records:
        raise FrameError(f"line {line}: frame {name} is listed twice", path=csv_path)
    if require_files and not rec.path.is_file():
        raise FrameError(
            f"line {line}: frame {name} is listed but the file does not exist",
            path=csv_path,
            hint="restore the file or remove its row",
        )
    return rec

def _parse_time(text: str, csv_path: Path, line: int) -> str | None:
    """An ISO 8601 time the datacube's time axis can hold (int64 ns: 1678-2261)."""
    text = (text or "").strip()
    if not text:
        return None
    try:
        dt, _ = utc_naive(parse_iso(text))
    except (ValueError, OverflowError):  # OverflowError: 0001-01-01T00:00:00+01:00 is before year 1 in UTC
        raise FrameError(f"line {line}: time {text!r} is not ISO 8601", path=csv_path,
                         hint="e.g. 2017-06-14T09:50:00Z") from None
    if not TIME_RANGE[0] <= dt.year <= TIME_RANGE[1]:
        raise FrameError(f"line {line}: time {text!r} is outside the years {TIME_RANGE[0]}-{TIME_RANGE[1]}",
                         path=csv_path, hint="e.g. 2017-06-14T09:50:00Z")
    return text


def exif_record(path: Path) -> FrameRecord:
    """A :class:`FrameRecord` from a file's EXIF tags (ExposureTime, ISO, GPS, DateTimeOriginal),
    each as :func:`pipeline.ingest.exif.exifread_tags` gives it (what is not a value left out);
    a position that is no number is left out, an exposure that is none raises."""
    try:
        with path.open("rb") as fh:
            tags = exifread_tags(fh)
    except OSError as exc:
        raise FrameError(f"cannot read: {exc.strerror}", path=path) from None
    except Exception:  # exifread raises a zoo of errors on corrupt files
        tags = {}
    exp = tags.get("EXIF ExposureTime")
    if exp is None:
        raise FrameError(
            "no exposure time: the frame has no row in frames.csv and no EXIF ExposureTime",
            path=path,
            hint="add a row 'file,exposure_ms' for it to frames.csv",
        )
    iso = tags.get("EXIF ISOSpeedRatings")
    try:
        exposure_s = rational(exp)
        gain = rational(iso) / 100.0 if iso else 1.0
    except (TypeError, ValueError, ZeroDivisionError, IndexError, OverflowError):
        raise FrameError(f"EXIF ExposureTime {str(exp)[:40]!r} or ISOSpeedRatings {str(iso)[:40]!r} is not a number",
                         path=path, hint="add a row 'file,exposure_ms' for it to frames.csv") from None
    has_pos = "GPS GPSLatitude" in tags and "GPS GPSLongitude" in tags
    try:
        lat, lon, alt = signed_gps(
            dms_to_degrees(tags["GPS GPSLatitude"]) if has_pos else None, tags.get("GPS GPSLatitudeRef"),
            dms_to_degrees(tags["GPS GPSLongitude"]) if has_pos else None, tags.get("GPS GPSLongitudeRef"),
            rational(tags["GPS GPSAltitude"]) if "GPS GPSAltitude" in tags else None,
            tags.get("GPS GPSAltitudeRef") in (1, b"\x01"),
        )
    except (TypeError, ValueError, ZeroDivisionError, IndexError, OverflowError):
        lat = lon = alt = None
    if lat is None or lon is None or not (math.isfinite(lat) and math.isfinite(lon)):
        lat = lon = None
    status = tags.get("GPS GPSStatus")
    status = str(getattr(status, "values", status)).strip("\x00 ") if status is not None else None
    if alt is not None and not math.isfinite(alt):
        alt = None
    time = exif_time_utc(tags.get("EXIF DateTimeOriginal"), offset=tags.get("EXIF OffsetTimeOriginal"))
    rec = FrameRecord(path=path, exposure_ms=exposure_s * 1000.0, gain=gain, time=time, lat=lat, lon=lon, alt_m=alt,
                      gps_status=status)
    _check_exposure(rec, path)
    return rec


# --------------------------------------------------------------------------- frame files


def stored_bands(source: bytes | bytearray | memoryview | Path, path: Path | str, camera: Camera) -> np.ndarray:
    """One frame file's band stack in sensor DN (:func:`to_bands` of :func:`decode_frame`), shifted
    by what the file itself stores (its BitsPerSample): a 16-bit RedEdge file by 4, a 12-bit one
    not at all."""
    if isinstance(source, Path) and not source.is_file():
        raise FrameError("frame file does not exist", path=path)
    img, bits = decode_frame(source, path)
    return to_bands(img, camera, path, stored_bits=bits if camera.dn_shift else None)


def to_bands(img: np.ndarray, camera: Camera, path: Path | str = "", stored_bits: int | None = None) -> np.ndarray:
    """Split a stored frame into the camera's band stack ``(band, H, W)`` (uint16 sensor DN);
    ``stored_bits``: the file's bits per sample, which sets the shift to sensor DN
    (:meth:`Camera.shift_for`; None: the catalog's)."""
    lay = camera.layout
    if lay.kind == "mosaic":
        if img.ndim != 2:
            raise FrameError(f"expected a single-channel mosaic, got shape {img.shape}", path=path)
        if camera.sensor is not None and img.shape != camera.sensor:
            raise FrameError(
                f"frame is {img.shape[1]}x{img.shape[0]} but camera {camera.name} has a "
                f"{camera.sensor[1]}x{camera.sensor[0]} sensor",
                path=path,
                hint="is session.yaml naming the right camera?",
            )
        assert lay.pattern is not None
        bands = demosaic(img, lay.pattern, lay.origin, lay.grid)
    elif lay.kind in ("multichannel", "file_per_capture"):  # the second: bands are some channels (Sentera)
        order = [int(b.channel) for b in camera.bands]  # type: ignore[arg-type]
        if img.ndim != 3 or img.shape[2] <= max(order):
            raise FrameError(
                f"expected {max(order) + 1} channels, got shape {img.shape}",
                path=path,
                hint=f"camera {camera.name} stores one band per channel",
            )
        bands = np.moveaxis(img[:, :, order], 2, 0)
    else:
        if img.ndim != 2:
            raise FrameError(f"expected a single-band image, got shape {img.shape}", path=path)
        bands = img[None]
    shift = camera.shift_for(stored_bits)
    if shift:  # e.g. MicaSense: 12-bit DN stored in the high bits of 16-bit samples
        bands = np.right_shift(bands, shift)
    top = int(bands.max(initial=0))
    if top > camera.dn_max:
        raise FrameError(
            f"DN {top} exceed the {camera.bit_depth}-bit range of camera {camera.name}",
            path=path,
            hint="DN must be in the low bits; check the camera's bit_depth",
        )
    return np.ascontiguousarray(bands, dtype=np.uint16)


def read_bands(rec: FrameRecord | Path, camera: Camera) -> np.ndarray:
    """Read one frame and split it into bands (:class:`FrameError` naming the file); a
    capture of a one-file-per-band camera is read band file by band file."""
    if isinstance(rec, FrameRecord) and rec.band_files is not None:
        bands = [stored_bands(Path(f), f, camera)[0] for f in rec.band_files]
        for f, b in zip(rec.band_files[1:], bands[1:]):
            if b.shape != bands[0].shape:
                raise FrameError(f"band image is {b.shape[1]}x{b.shape[0]}, the capture's first band "
                                 f"{bands[0].shape[1]}x{bands[0].shape[0]}", path=f)
        return np.stack(bands)
    path = rec.path if isinstance(rec, FrameRecord) else Path(rec)
    return stored_bands(path, path, camera)



__all__ = [
    "FrameRecord",
    "InputError",
    "MarkerSpec",
    "ReflectorSpec",
    "Session",
    "exif_record",
    "load_session",
    "read_bands",
    "stored_bands",
    "read_frame_table",
    "session_yaml_near",
    "to_bands",
]
