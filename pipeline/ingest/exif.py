"""EXIF values and ISO 8601 times: the one copy of each codec that readers and writers share.

* TIFF RATIONALs (EXIF 2.32, CIPA DC-008-2019, section 4.6.2: two LONGs, numerator then
  denominator) as read by tifffile (``(num, den)`` tuples, or GPS triples flattened to
  ``(n, d, n, d, n, d)``) or by exifread (``Ratio`` objects with ``.num`` / ``.den``), and
  written back (:func:`to_rational`).
* exifread's tags shaped as tifffile gives a TIFF's (:func:`exifread_tags`), what is not a
  value (the thumbnail's bytes, maker notes, empty fields, zero denominators) left out.
* GPS positions as degrees, minutes, seconds (``GPSLatitude``, ``GPSLongitude``: three
  RATIONALs, section 4.6.6) to and from decimal degrees, with the signs from the reference
  tags (``S``, ``W``, ``GPSAltitudeRef`` 1 = below sea level).
* ``DateTimeOriginal`` (``YYYY:MM:DD HH:MM:SS``, the camera's clock) plus
  ``SubSecTimeOriginal`` as ISO 8601 text, in UTC when ``OffsetTimeOriginal`` or DJI's
  ``UTCAtExposure`` says the zone (:func:`exposure_time`).
* ISO 8601 text (frames.csv ``time``, STAC ``datetime``) to :class:`datetime`, to naive UTC,
  and to int64 nanoseconds for the datacube's ``time`` coordinate.
"""

from __future__ import annotations

import math
import numbers
import re
from datetime import datetime, timedelta, timezone
from fractions import Fraction
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from mscal_core.errors import FrameError

#: EXIF tags by the names tifffile gives the EXIF IFD's entries, and their codes (EXIF 2.32).
#: Some cameras (Sentera 6X: "EXIF (IFD0)" in its tag table) write them into IFD0 instead of
#: the EXIF IFD; readers look for them there too.
EXIF_CODES = {
    "ExposureTime": 33434, "FNumber": 33437, "ISOSpeedRatings": 34855, "ISOSpeed": 34867,
    "DateTimeOriginal": 36867, "OffsetTimeOriginal": 36881, "SubsecTime": 37520, "SubsecTimeOriginal": 37521, "FocalLength": 37386,
    "FocalPlaneXResolution": 41486, "FocalPlaneYResolution": 41487, "FocalPlaneResolutionUnit": 41488,
    "ImageUniqueID": 42016, "BodySerialNumber": 42033, "LensModel": 42036,
}

__all__ = [
    "EXIFREAD_GROUPS",
    "EXIF_CODES",
    "NAT",
    "U32",
    "degrees_to_dms",
    "dms_to_degrees",
    "exif_time_utc",
    "exifread_tags",
    "exifread_value",
    "exposure_time",
    "parse_iso",
    "rational",
    "signed_gps",
    "time_ns",
    "to_rational",
    "utc_naive",
]

#: How xarray encodes NaT in an int64 time variable.
NAT = np.iinfo(np.int64).min
#: The largest numerator or denominator of an unsigned TIFF RATIONAL.
U32 = 2**32 - 1


# --------------------------------------------------------------------------- RATIONAL


def rational(value: Any) -> float:
    """A RATIONAL as float: a ``(num, den)`` tuple (tifffile), an object with ``num`` and
    ``den`` (exifread), a sequence of either (the first), or a plain number. A zero
    denominator gives NaN (some firmware writes ``0/0`` for unknown)."""
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if hasattr(value, "values") and not isinstance(value, (list, tuple)):  # an exifread tag
        return rational(value.values[0])
    if isinstance(value, (list, tuple)) and not (len(value) == 2 and all(isinstance(v, numbers.Integral) for v in value)):
        return rational(value[0]) if value else math.nan  # several RATIONALs (e.g. per CFA cell): the first
    if isinstance(value, tuple) and len(value) == 2:
        num, den = value
    elif hasattr(value, "num") and hasattr(value, "den"):
        num, den = value.num, value.den
    else:
        return float(value)
    return float(num) / float(den) if den else math.nan


@lru_cache(maxsize=4096)
def _fraction_of(v: Any) -> tuple[int, int]:
    """The nearest fraction to the number ``v`` whose terms fit 32 bits (unchecked). Cached:
    every TIFF of a frame repeats its GPS position and its lens in rationals, and
    ``Fraction.limit_denominator`` was half the CPU of writing a TIFF header."""
    f = Fraction(v)
    if f.denominator > U32 or f.numerator > U32:
        bound = min(U32, int(U32 / max(float(f), 1.0)))
        f = f.limit_denominator(max(bound, 1))
    return f.numerator, f.denominator


def to_rational(v: Any) -> tuple[int, int]:
    """An unsigned RATIONAL ``(num, den)`` for ``v`` (a ``(num, den)`` tuple is checked and
    kept; a number becomes the nearest fraction whose terms fit 32 bits)."""
    if isinstance(v, tuple):
        n, d = v
    else:
        n, d = _fraction_of(v)
    if not (0 <= n <= U32 and 0 < d <= U32):
        raise ValueError(f"value {v!r} does not fit an unsigned TIFF RATIONAL")
    return int(n), int(d)


# --------------------------------------------------------------------------- exifread

#: The IFDs whose tags mscal reads, by exifread's key prefix: IFD0, the EXIF IFD, the GPS IFD
#: (in this order: a tag of the EXIF IFD wins over IFD0's). The thumbnail's IFD1,
#: Interoperability, sub-IFDs and maker notes are not read.
EXIFREAD_GROUPS = ("Image", "EXIF", "GPS")
_UNDEFINED = 7  # EXIF field type UNDEFINED: bytes, as tifffile gives them
_BLOBS = frozenset({"MakerNote", "UserComment", "PrintIM"})  # vendor data, never a value mscal reads


def exifread_value(name: str, tag: Any) -> Any:
    """An exifread tag's value shaped as tifffile gives it, or None when it is not a value
    mscal can use: not a tag (``JPEGThumbnail``/``TIFFThumbnail`` are the thumbnail's bytes),
    a maker note or other vendor blob, a tag exifread does not name, an empty list or text
    (count 0, or exifread's empty list for a long field), or a RATIONAL with a zero
    denominator (``0/0``: unknown). Text is stripped (bytes that are not UTF-8 read as
    Latin-1), UNDEFINED fields are bytes, FLOAT/DOUBLE items floats, RATIONALs exifread's
    ``Ratio`` (``num``/``den``: :func:`rational`); a one-item list is its item (GPS degrees,
    minutes, seconds stay a list)."""
    values = getattr(tag, "values", None)
    if values is None or name in _BLOBS or name.startswith("Tag 0x"):
        return None
    if isinstance(values, (bytes, bytearray)):
        values = bytes(values).split(b"\x00", 1)[0].decode("latin-1")
    if isinstance(values, str):
        return values.strip().strip("\x00").strip() or None
    if not isinstance(values, list) or not values:
        return None
    if getattr(tag, "field_type", None) == _UNDEFINED:
        try:
            return bytes(values)
        except (TypeError, ValueError):
            return None
    items = []
    for v in values:
        if isinstance(v, tuple):  # FLOAT/DOUBLE: exifread keeps struct.unpack's 1-tuple
            v = v[0] if len(v) == 1 else None
        if v is None or (hasattr(v, "den") and not v.den):
            return None
        items.append(v)
    if len(items) == 1 and name not in ("GPSLatitude", "GPSLongitude"):
        return items[0]
    return items


def exifread_tags(fh: Any) -> dict[str, Any]:
    """The EXIF tags of an open file (JPEG or TIFF) by exifread's keys (``Image Make``,
    ``EXIF ExposureTime``, ``GPS GPSLatitude``), of :data:`EXIFREAD_GROUPS` only, in that
    order, each value :func:`exifread_value` (tags that are no value left out). exifread's
    own exceptions on a corrupt file are the caller's to catch."""
    import exifread

    tags = exifread.process_file(fh, details=False)
    out: dict[str, Any] = {}
    for group in EXIFREAD_GROUPS:
        for key, tag in tags.items():
            head, _, name = key.partition(" ")
            if head == group and (value := exifread_value(name, tag)) is not None:
                out[key] = value
    return out


# --------------------------------------------------------------------------- GPS


def dms_to_degrees(value: Any) -> float:
    """Decimal degrees (unsigned) from a GPS (degrees, minutes, seconds) triple: flat
    ``(n, d, n, d, n, d)`` integers (tifffile), three ``(n, d)`` tuples, or an exifread tag
    or list of ``Ratio``."""
    vals = value.values if hasattr(value, "values") else value
    vals = list(vals)
    if vals and all(isinstance(v, (int, np.integer)) for v in vals):
        parts = [rational((vals[i], vals[i + 1])) for i in range(0, len(vals), 2)]
    else:
        parts = [rational(v) for v in vals]
    return sum(p / 60**k for k, p in enumerate(parts))


def degrees_to_dms(deg: float) -> list[tuple[int, int]]:
    """|deg| as (degrees/1, minutes/1, seconds/1e6) RATIONALs with exact integer carry."""
    micro = round(abs(deg) * 3600 * 1_000_000)
    d, rem = divmod(micro, 3600 * 1_000_000)
    m, s = divmod(rem, 60 * 1_000_000)
    return [(int(d), 1), (int(m), 1), (int(s), 1_000_000)]


def signed_gps(lat: float | None, lat_ref: Any, lon: float | None, lon_ref: Any, alt: float | None,
               below_sea_level: bool) -> tuple[float | None, float | None, float | None]:
    """EXIF GPS degrees and altitude with their signs from the reference tags (S, W, below)."""
    if lat is not None and str(lat_ref or "N").strip().upper().startswith("S"):
        lat = -lat
    if lon is not None and str(lon_ref or "E").strip().upper().startswith("W"):
        lon = -lon
    if alt is not None and below_sea_level:
        alt = -alt
    return lat, lon, alt


# --------------------------------------------------------------------------- times



_EXIF_STAMP = re.compile(r"\s*(\d{4}):(\d{2}):(\d{2}) (\d{2}):(\d{2}):(\d{2})(?:\.(\d+))?\s*$")
_EXIF_OFFSET = re.compile(r"\s*([+-])(\d{2}):(\d{2})\s*$")


def exif_time_utc(date_time: Any, subsec: Any = None, offset: Any = None) -> str | None:
    """The time of an exposure as ISO 8601 text (``2025-05-20T02:12:34.7``): in UTC with ``Z``
    when the zone is known, as written when not.

    ``date_time``: EXIF ``DateTimeOriginal`` (``2025:05:20 10:12:34``, the camera's local
    clock), or a DJI ``drone-dji:UTCAtExposure`` (``2025:05:20 02:12:54.019996``, UTC, with its
    fraction; pass ``offset="+00:00"``); ``subsec``: ``SubSecTimeOriginal`` digits; ``offset``:
    EXIF 2.31 ``OffsetTimeOriginal`` (``+08:00``). An offset that is blank or not ``+HH:MM``
    leaves the zone unknown. None when the time itself is missing or blank."""
    m = _EXIF_STAMP.match(str(date_time or ""))
    if not m:
        return None
    try:  # a camera without a clock writes 0000:00:00 00:00:00: no time
        local = datetime(int(m[1]), int(m[2]), int(m[3]), int(m[4]), int(m[5]), int(m[6]))
    except ValueError:
        return None
    o = _EXIF_OFFSET.match(str(offset or ""))
    sub = m[7] if m[7] is not None else str(subsec or "").strip()
    frac = f".{sub}" if sub.isdigit() else ""
    if o is None or int(o[2]) > 23 or int(o[3]) > 59:
        return f"{local.isoformat(timespec='seconds')}{frac}"
    sign = 1 if o[1] == "+" else -1
    try:
        utc = local - sign * timedelta(hours=int(o[2]), minutes=int(o[3]))
    except OverflowError:  # within hours of year 1 or 9999: not a flight's time
        return None
    return f"{utc.isoformat(timespec='seconds')}{frac}Z"


def exposure_time(date_time: Any, subsec: Any = None, offset: Any = None, utc_at_exposure: Any = None) -> str | None:
    """A band file's exposure time (:func:`exif_time_utc`): DJI's ``drone-dji:UTCAtExposure``
    when it reads as a time (UTC; the file's DateTimeOriginal is the aircraft's local clock),
    else ``DateTimeOriginal`` (+ ``subsec``) in UTC when ``OffsetTimeOriginal`` gives its zone,
    else as written (zone unknown)."""
    utc = exif_time_utc(utc_at_exposure, offset="+00:00") if utc_at_exposure is not None else None
    return utc if utc is not None else exif_time_utc(date_time, subsec, offset)


def parse_iso(text: str) -> datetime:
    """ISO 8601 text as a :class:`datetime` (aware when it has ``Z`` or an offset); raises
    ``ValueError`` when it is not ISO 8601."""
    return datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))


def as_utc(dt: datetime) -> datetime:
    """``dt`` in UTC, aware; a time without a zone is taken as UTC (the frames' and cameras'
    GPS clocks)."""
    return dt.replace(tzinfo=timezone.utc) if dt.tzinfo is None else dt.astimezone(timezone.utc)


def parse_utc(text: str) -> datetime:
    """ISO 8601 text as an aware UTC :class:`datetime` (:func:`parse_iso`, :func:`as_utc`);
    raises ``ValueError`` when it is not ISO 8601."""
    return as_utc(parse_iso(text))


def utc_naive(dt: datetime) -> tuple[datetime, bool]:
    """``(naive datetime, zone_known)``: an aware time converted to UTC, a naive one as is."""
    if dt.tzinfo is not None:
        return dt.astimezone(timezone.utc).replace(tzinfo=None), True
    return dt, False


def time_ns(text: str | None) -> int:
    """ISO 8601 text -> int64 ns since the epoch (UTC when it has an offset); :data:`NAT` if empty."""
    if not text:
        return NAT
    dt, _ = utc_naive(parse_iso(text))
    return int(np.datetime64(dt, "ns").astype(np.int64))


def jpeg_exif(data: bytes, path: Path | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """A JPEG's EXIF and GPS tags, named and shaped as tifffile gives a TIFF's
    (:func:`pipeline.ingest.exif.exifread_tags`: what is not a value -- the thumbnail, a maker
    note, an empty field, a zero denominator -- is left out). IFD0 and the EXIF IFD make one
    dict (the EXIF IFD's tag wins), the GPS IFD the other. EXIF that exifread cannot parse
    raises :class:`FrameError`; a JPEG without EXIF gives two empty dicts."""
    import io

    try:
        tags = exifread_tags(io.BytesIO(data))
    except Exception as exc:  # exifread raises a zoo of errors on corrupt EXIF
        raise FrameError(f"EXIF unreadable ({type(exc).__name__}: {str(exc)[:80]})", path=path,
                         hint="copy the file again from the camera's card") from None
    exif: dict[str, Any] = {}
    gps: dict[str, Any] = {}
    for key, value in tags.items():  # IFD0's, then the EXIF IFD's, then the GPS IFD's
        group, _, name = key.partition(" ")
        name = name.replace("SubSecTime", "SubsecTime")  # exifread's spelling -> tifffile's
        (gps if group == "GPS" else exif)[name] = value
    return exif, gps
