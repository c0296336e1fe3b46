"""Decoding one frame file's pixels: a plain camera TIFF straight from its strips
(:func:`plain_tiff_pixels`, the measured fast path), any other TIFF with tifffile, PNG and
JPEG with OpenCV (:func:`decode_raw`); and the BitsPerSample of a TIFF from its first IFD
(:func:`sample_bits`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from mscal_core.errors import FrameError


def read_raw(path: str | Path) -> np.ndarray:
    """Pixels of one frame file as stored (TIFF via tifffile; PNG and JPEG via OpenCV, RGB order)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError("frame file does not exist", path=path)
    return decode_raw(path, path)


#: IFD0 tags :func:`plain_tiff_pixels` accepts: baseline TIFF, XMP, EXIF and GPS IFDs, DNG
#: black level, GDAL metadata, MicaSense's private tags and opcode list (none changes how
#: tifffile reads the pixels), and an ImageDescription (270) that is tifffile's own shape
#: record of this very image (:func:`_shape_description_fits`). A file with any other tag is
#: left to tifffile.
_PLAIN_TIFF_TAGS = frozenset({
    254, 256, 257, 258, 259, 262, 270, 271, 272, 273, 274, 277, 278, 279, 280, 281, 282, 283, 284, 296, 305, 306,
    339, 700, 34665, 34853, 42112, 42113, 48020, 48021, 48022, 50713, 50714, 50735, 51022,
})
_TIFF_TYPES = {3: "H", 4: "I"}  # SHORT, LONG: the types of the tags read here


def _shape_description_fits(text: bytes, height: int, width: int) -> bool:
    """Whether an ImageDescription leaves the pixels as they are: only the JSON shape record
    that tifffile writes into the files it makes (``{"shape": [H, W], ...}``), for this
    image's own height and width. Every other description (ImageJ, OME-XML, a shape that
    reshapes the image, free text a reader might interpret) is left to tifffile."""
    import json

    body = text.rstrip(b"\0").strip()
    if not body.startswith(b"{"):
        return False
    try:
        record = json.loads(body.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        return False
    return isinstance(record, dict) and record.get("shape") == [height, width]


def _plain_ifd(data: bytes | bytearray | memoryview, e: str, ifd: int
               ) -> tuple[dict[int, tuple[int, ...]], bytes | None] | None:
    """The only IFD of a plain TIFF at offset ``ifd`` (byte order ``e``): the values of the
    tags that say how the pixels are stored, and the ImageDescription's bytes (None: no
    description); None if it is not the only image or has a tag or value
    :func:`plain_tiff_pixels` does not read."""
    import struct

    n = len(data)
    count = struct.unpack_from(e + "H", data, ifd)[0]
    end = ifd + 2 + 12 * count
    if end + 4 > n or struct.unpack_from(e + "I", data, end)[0] != 0:  # one image only
        return None
    tags: dict[int, tuple[int, ...]] = {}
    description = None
    for k in range(count):
        tag, typ, cnt, value = struct.unpack_from(e + "HHI4s", data, ifd + 2 + 12 * k)
        if tag not in _PLAIN_TIFF_TAGS:
            return None
        if tag == 270:  # ASCII, checked once the image's size is known
            at = ifd + 2 + 12 * k + 8 if cnt <= 4 else struct.unpack_from(e + "I", value)[0]
            if typ != 2 or at + cnt > n:
                return None
            description = bytes(data[at:at + cnt])
            continue
        if tag not in (256, 257, 258, 259, 273, 277, 278, 279, 284, 339):
            continue
        if typ not in _TIFF_TYPES or cnt < 1:
            return None
        fmt = f"{e}{cnt}{_TIFF_TYPES[typ]}"
        size = struct.calcsize(fmt)
        if size <= 4:
            tags[tag] = struct.unpack_from(fmt, value)
        else:
            at = struct.unpack_from(e + "I", value)[0]
            if at + size > n:
                return None
            tags[tag] = struct.unpack_from(fmt, data, at)
    return tags, description


def plain_tiff_pixels(data: bytes | bytearray | memoryview, out: np.ndarray | None = None) -> np.ndarray | None:
    """The pixels of a single-image, uncompressed, stripped, one-sample 8- or 16-bit unsigned
    classic TIFF (camera band files such as MicaSense's), straight from its strips: the array
    ``tifffile.imread`` returns for such a file, without building tifffile's page and tag
    objects (about 2 ms of Python per file). None for anything else, or anything unexpected
    (other tags, tiles, compression, several images, strips past the end): then tifffile reads it.
    ``out``: an array to decode into when it has the image's shape and dtype (else a new one).

    Measured against tifffile 2026.3.3 (CPU time a file, one run): 0.20 ms vs 0.40-0.52 ms a
    RedEdge band file, 0.43 ms vs 0.56-0.63 ms a 2048x1088 session frame.

    References: TIFF 6.0 specification (Adobe, 1992), sections 2 (structure), 3 (baseline
    fields) and 8 (StripOffsets, StripByteCounts, RowsPerStrip)."""
    import struct

    n = len(data)
    if n < 8 or data[:4] not in (b"II*\0", b"MM\0*"):
        return None
    e = "<" if data[0] == 0x49 else ">"
    ifd = struct.unpack_from(e + "I", data, 4)[0]
    if ifd < 8 or ifd + 2 > n:
        return None
    read = _plain_ifd(data, e, ifd)
    if read is None:
        return None
    tags, description = read
    try:
        (width,), (height,), (bits,) = tags[256], tags[257], tags[258]
        offsets, counts = tags[273], tags[279]
    except (KeyError, ValueError):
        return None
    if tags.get(259, (1,)) != (1,) or tags.get(277, (1,)) != (1,) or tags.get(339, (1,)) != (1,) \
            or tags.get(284, (1,)) not in ((1,), (2,)) or bits not in (8, 16) or not (width and height):
        return None
    if description is not None and not _shape_description_fits(description, height, width):
        return None
    rows = min(tags.get(278, (height,))[0] or height, height)
    strips = -(-height // rows)
    row_bytes = width * bits // 8
    if len(offsets) != strips or len(counts) != strips:
        return None
    dtype = np.dtype(f"{e}u{bits // 8}")
    for i, (at, nbytes) in enumerate(zip(offsets, counts)):
        if nbytes != min(rows, height - i * rows) * row_bytes or at + nbytes > n:
            return None
    native = dtype.newbyteorder("=")
    if out is None or out.shape != (height, width) or out.dtype != native or not out.flags.c_contiguous:
        out = np.empty((height, width), native)
    flat = out.reshape(-1)
    for i, at in enumerate(offsets):
        r = min(rows, height - i * rows)
        flat[i * rows * width:(i * rows + r) * width] = np.frombuffer(data, dtype, r * width, at)
    return out


#: What tifffile says when a TIFF is intact but stored in a way it cannot decode here: a codec
#: that needs the imagecodecs package (12-bit packed samples, most compressions), or a
#: compression or sample layout that neither implements. Re-copying such a file cannot help.
_UNSUPPORTED_TIFF = ("imagecodecs", "not supported", "not implemented", "is not a known COMPRESSION")


def _unsupported_tiff(exc: Exception, source: bytes | bytearray | memoryview | Path, path: Path
                      ) -> FrameError | None:
    """The FrameError for a TIFF that decoded to an error of its *format*, not of its data
    (:data:`_UNSUPPORTED_TIFF`): its BitsPerSample and Compression, the decoder's words, and
    the real remedy (install imagecodecs, or convert the file); None for any other error
    (truncated or corrupt data: :func:`decode_raw`'s re-copy hint stands)."""
    text = str(exc)
    if not (isinstance(exc, NotImplementedError) or any(s in text for s in _UNSUPPORTED_TIFF)):
        return None
    import io

    import tifffile

    stored = "a pixel format"
    in_memory = isinstance(source, (bytes, bytearray, memoryview))
    try:
        with tifffile.TiffFile(io.BytesIO(source) if in_memory else source) as tif:
            page = tif.pages[0]
            name = getattr(page.compression, "name", None)  # a plain int: a code tifffile does not know
            stored = (f"BitsPerSample {page.bitspersample}, Compression {int(page.compression)}"
                      f"{f' ({name})' if name else ''}")
    except Exception:  # the decoder's own words below still say what it is
        pass
    if "imagecodecs" in text:
        try:
            import imagecodecs  # noqa: F401
        except ImportError:
            return FrameError(
                f"TIFF stored with {stored} needs the imagecodecs package to decode, and it is not installed "
                f"({type(exc).__name__}: {text[:120]})", path=path,
                hint="the file is fine: install mscal's dependencies again, imagecodecs among them: make setup, or "
                     "pip install -e . in the checkout")
    return FrameError(
        f"TIFF stored with {stored}, which this installation cannot decode ({type(exc).__name__}: {text[:120]})",
        path=path,
        hint="the file is fine but in a format mscal does not read: convert it to an uncompressed 8-, 12- or "
             "16-bit TIFF, or remove it from the folder")


def decode_raw(source: bytes | bytearray | memoryview | Path, path: str | Path, out: np.ndarray | None = None
               ) -> np.ndarray:
    """Pixels of a frame file, from its bytes or (``source`` a path) from the file itself;
    ``path`` names the format by its suffix and the file in errors. ``out``: where a plain
    camera TIFF of that shape and dtype is decoded (:func:`plain_tiff_pixels`); the array
    returned is ``out`` when it was used.

    A JPEG without its end-of-image marker is truncated: libjpeg would silently return the
    decoded part padded with gray, so it is rejected here.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import io

            import tifffile

            in_memory = isinstance(source, (bytes, bytearray, memoryview))
            img = plain_tiff_pixels(source, out) if in_memory else None
            if img is None:
                img = tifffile.imread(io.BytesIO(source) if in_memory else source)
        else:
            import cv2

            data = source if isinstance(source, (bytes, bytearray, memoryview)) else Path(source).read_bytes()
            if suffix in (".jpg", ".jpeg") and data[-2:] != b"\xff\xd9":
                raise ValueError("JPEG end-of-image marker missing")
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError("OpenCV could not decode it")
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    except FrameError:
        raise
    except Exception as exc:  # decoders raise many types on truncated/corrupt data
        unsupported = _unsupported_tiff(exc, source, path) if suffix in (".tif", ".tiff") else None
        if unsupported is not None:
            raise unsupported from None
        raise FrameError(
            f"unreadable or truncated image ({type(exc).__name__}: {str(exc)[:120]})",
            path=path,
            hint="re-copy the file from the camera or remove it from the folder",
        ) from None
    img = np.asarray(img)
    if not np.issubdtype(img.dtype, np.integer):
        raise FrameError(f"pixel type {img.dtype} is not integer DN", path=path)
    return img


def sample_bits(source: bytes | bytearray | memoryview | Path) -> int | None:
    """BitsPerSample of a classic TIFF's first image, from its bytes or its file, read from the
    header and the first IFD alone (TIFF 6.0 section 2); None when it is not a classic TIFF,
    has no such tag or is cut short (:func:`decode_raw` then says why). A RedEdge writes its
    12-bit DN in the high bits of 16-bit samples, or, set to its 12-bit format, as they are in
    packed 12-bit samples: the decoded arrays are both uint16, only the file says which
    (:meth:`Camera.shift_for`)."""
    import struct

    if isinstance(source, (bytes, bytearray, memoryview)):
        view = memoryview(source)
        return _ifd0_bits(lambda at, n: bytes(view[at:at + n]))
    try:
        with open(source, "rb") as fh:
            def read(at: int, n: int) -> bytes:
                fh.seek(at)
                return fh.read(n)

            return _ifd0_bits(read)
    except (OSError, struct.error):
        return None


def _ifd0_bits(read: Callable[[int, int], bytes]) -> int | None:
    import struct

    head = read(0, 8)
    if len(head) < 8 or head[:4] not in (b"II*\0", b"MM\0*"):
        return None
    e = "<" if head[0] == 0x49 else ">"
    ifd = struct.unpack(e + "I", head[4:])[0]
    count = read(ifd, 2)
    if len(count) < 2:
        return None
    n = struct.unpack(e + "H", count)[0]
    entries = read(ifd + 2, 12 * n)
    for i in range(len(entries) // 12):
        tag, kind, items = struct.unpack_from(e + "HHI", entries, 12 * i)
        if tag != 258:
            continue
        if kind != 3 or items < 1:  # SHORT, one per sample
            return None
        if items <= 2:
            return int(struct.unpack_from(e + "H", entries, 12 * i + 8)[0])
        value = read(struct.unpack_from(e + "I", entries, 12 * i + 8)[0], 2)
        return int(struct.unpack(e + "H", value)[0]) if len(value) == 2 else None
    return None
