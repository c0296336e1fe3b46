"""Factory radiometric metadata of one band file, pure Python (no exiftool), for every camera
maker mscal knows (:mod:`pipeline.ingest.cameras`).

A TIFF's EXIF (Make, Model, ExposureTime, ISO, FNumber, BlackLevel, Orientation, GPS,
DateTimeOriginal + SubsecTime) is read with tifffile, a JPEG's with exifread; the XMP packet
with :mod:`pipeline.ingest.xmp` (attributes, elements, rdf:Seq/Bag/Alt, numbers in one
``rdf:li``, namespaces by URI). Which maker reads a file, and so which radiometric model it
gets (``CaptureMeta.radiometry``), follows from its tags: the first maker whose ``claims``
holds (:func:`pipeline.ingest.cameras.dispatch.read_tags`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from mscal_core.errors import FrameError

from pipeline.ingest.cameras import registry
from pipeline.ingest.cameras.dispatch import read_tags
from pipeline.ingest.exif import EXIF_CODES, jpeg_exif
from pipeline.ingest.meta import FIRMWARE_HINT, CaptureMeta, TagContext, clean_text, int_tag
from pipeline.ingest.xmp import TagError, Xmp, jpeg_xmp_packet, legacy_properties


def xmp_properties(packet: bytes | str, path: Path | str) -> dict[str, Any]:
    """Properties of an XMP packet in the Camera and MicaSense namespaces, by local name
    (kept for its callers; new code uses :class:`pipeline.ingest.xmp.Xmp`)."""
    return legacy_properties(packet, path)



def read_capture_meta(path: str | Path) -> CaptureMeta:
    """Factory metadata of one single-band file; :class:`FrameError` naming the file and tag
    if its radiance cannot be computed. (Multi-channel files: :func:`read_file_metas`.)"""
    metas = read_file_metas(path)
    return metas[0]


def read_file_metas(path: str | Path) -> list[CaptureMeta]:
    """Factory metadata of every band a file holds (one for TIFF band files, one per kept
    channel of a Sentera JPEG)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError("file does not exist", path=path)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return _read_jpeg(path)
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) == 0:  # header read, but the first IFD lies past the end of the file
                raise FrameError("TIFF has no readable image directory (file truncated?)", path=path,
                                 hint="copy the file again from the camera's card")
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}
            shape = (int(page.imagelength), int(page.imagewidth))
            bits = int(page.bitspersample)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise FrameError(f"not a readable TIFF ({type(exc).__name__}: {exc})", path=path,
                         hint="copy the file again from the camera's card") from None
    if 700 not in tags:
        raise FrameError("no XMP packet (TIFF tag 700)", path=path, hint=FIRMWARE_HINT)
    return [meta_from_tags(path, tags, shape, bits)]


def meta_from_tags(path: Path, tags: dict[int, Any], shape: tuple[int, int], bits: int) -> CaptureMeta:
    """Build and check a :class:`CaptureMeta` from a TIFF's tag values keyed by tag code."""
    xmp = Xmp.parse(tags[700], path)
    exif = dict(tags[34665]) if isinstance(tags.get(34665), dict) else {}  # an EXIF IFD tifffile could not follow: none
    for name, code in EXIF_CODES.items():  # EXIF tags a camera wrote into IFD0 (Sentera 6X)
        if name not in exif and code in tags:
            exif[name] = tags[code]
    ctx = TagContext(
        path=path, xmp=xmp, exif=exif, gps=dict(tags[34853]) if isinstance(tags.get(34853), dict) else {},
        shape=shape, bits=bits, make=clean_text(tags.get(271)), model=clean_text(tags.get(272)), software=clean_text(tags.get(305)),
        serial=clean_text(exif.get("BodySerialNumber") or tags.get(50735)), orientation=int_tag(tags.get(274), 1),
        black_tag=tags.get(50714),
    )
    metas = _with_sun_sensor_props(ctx, read_tags(ctx))
    return metas[0]


#: Local names of the XMP properties the shared sun-sensor model reads whatever the maker: the
#: aircraft's ``Camera:Yaw/Pitch/Roll`` (:data:`pipeline.ingest.sunsensor.AIRCRAFT_ATTITUDE`).
SHARED_SUN_SENSOR_XMP = frozenset({"Yaw", "Pitch", "Roll"})


def sun_sensor_xmp_names() -> frozenset[str]:
    """Local names of the XMP properties read by the sun-sensor model (orientation, a measured
    split, a maker's own reading): every maker's
    (:attr:`pipeline.ingest.cameras.registry.Maker.sun_sensor_xmp`) and the shared ones
    (:data:`SHARED_SUN_SENSOR_XMP`). They are kept on each band's metadata, so the sun sensor
    reads no file a second time."""
    return registry.sun_sensor_xmp_names() | SHARED_SUN_SENSOR_XMP


def _with_sun_sensor_props(ctx: TagContext, metas: list[CaptureMeta]) -> list[CaptureMeta]:
    names = sun_sensor_xmp_names()
    props = tuple((ns, name, tuple(v) if isinstance(v, list) else v)
                  for (ns, name), v in ctx.xmp.props.items() if name in names)
    return [replace(m, sun_sensor_props=props) for m in metas]


def sun_sensor_xmp(meta: CaptureMeta) -> Xmp | None:
    """The XMP properties of ``meta``'s file that the sun-sensor model reads
    (:func:`sun_sensor_xmp_names`), as kept when the file was read; None for metadata made
    otherwise (read the file's XMP then)."""
    if meta.sun_sensor_props is None:
        return None
    return Xmp({(ns, name): list(v) if isinstance(v, tuple) else v for ns, name, v in meta.sun_sensor_props},
               meta.path)




#: How band files' metadata are read, in the fingerprints of runs on them: a change here gives
#: the same files and options other results, so an earlier run is not reused as up to date.
METADATA_READING = ("2026-12-05: exposure times in UTC when the file says so; XMP Albedo panels; 12-bit files by their "
                    "depth; EXIF values that are none (zero denominators, empty fields) left out; GPS 0/0, void or "
                    "unreachable: no position")



def _read_jpeg(path: Path) -> list[CaptureMeta]:
    """A JPEG of a multi-channel camera (Sentera Double 4K): EXIF with exifread, XMP from APP1."""
    data = path.read_bytes()
    if data[:2] != b"\xff\xd8":
        raise FrameError("not a JPEG file", path=path)
    packet = jpeg_xmp_packet(data)
    if packet is None:
        raise FrameError("no XMP packet (JPEG APP1 http://ns.adobe.com/xap/1.0/)", path=path, hint=FIRMWARE_HINT)
    exif, gps = jpeg_exif(data, path)
    width = int_tag(exif.get("ExifImageWidth"), 0)
    height = int_tag(exif.get("ExifImageLength"), 0)
    if not (0 < width <= 1 << 16 and 0 < height <= 1 << 16):  # a JPEG is at most 65535 pixels a side
        width = height = 0
    if not (width and height):
        import cv2

        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FrameError("JPEG could not be decoded", path=path)
        height, width = img.shape[:2]
    ctx = TagContext(
        path=path, xmp=Xmp.parse(packet, path), exif=exif, gps=gps, shape=(height, width), bits=8,
        make=clean_text(exif.get("Make")), model=clean_text(exif.get("Model")), software=clean_text(exif.get("Software")),
        serial=clean_text(exif.get("BodySerialNumber")), orientation=int_tag(exif.get("Orientation"), 1), black_tag=None,
    )
    return _with_sun_sensor_props(ctx, read_tags(ctx))


# --------------------------------------------------------------------------- irradiance


def xmp_irradiance(path: str | Path) -> float | None:
    """The XMP ``Irradiance`` (downwelling light sensor) of a TIFF frame, else None.

    Reads only the first page's tags (no pixels); a file that is not a TIFF or has no XMP
    packet, or whose packet has no Irradiance, gives None (most cameras do not write one).
    A present but unusable value (not a number, not positive) raises :class:`FrameError`
    naming the file.
    """
    import tifffile

    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(700)
            packet = None if tag is None else tag.value
    except (tifffile.TiffFileError, ValueError, OSError, IndexError):  # IndexError: truncated, no IFD
        return None
    if packet is None:
        return None
    try:
        x = Xmp.parse(packet, path)
    except FrameError:
        return None
    try:
        values = x.numbers("Irradiance")
    except TagError as exc:
        raise FrameError(f"XMP {exc.reason}", path=path,
                         hint="the sun sensor reading is unusable; remove the frame or give an irradiance column in frames.csv") from None
    if not values:
        return None
    if not (math.isfinite(values[0]) and values[0] > 0):
        raise FrameError(f"XMP Irradiance {values[0]!r} is not a positive number", path=path,
                         hint="the sun sensor reading is unusable; remove the frame or give an irradiance column in frames.csv")
    return float(values[0])
