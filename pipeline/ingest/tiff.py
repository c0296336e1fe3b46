"""Decoding one frame file's pixels: TIFF with tifffile (from the bytes in memory without copying
them, into an array the caller passes), PNG and JPEG with OpenCV (:func:`decode_raw`); and the
BitsPerSample of a TIFF's first image from its header alone (:func:`sample_bits`).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from mscal_core.errors import FrameError


def read_raw(path: str | Path) -> np.ndarray:
    """Pixels of one frame file as stored (TIFF via tifffile; PNG and JPEG via OpenCV, RGB order)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError("frame file does not exist", path=path)
    return decode_raw(path, path)


class BufferStream(io.RawIOBase):
    """A read-only, seekable binary stream over bytes already in memory, for tifffile.

    ``io.BytesIO`` copies every buffer but ``bytes`` on construction: a 4.4 MB snapshot frame in
    the thread's read buffer (:func:`pipeline.ingest.raw.read_whole`, a memoryview) cost about
    0.4 ms more a file that way. Here tifffile's ``readinto`` copies the pixels once, from the
    buffer into the array it decodes into.
    """

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        super().__init__()
        self._view = memoryview(data).cast("B")
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: len(self._view)}[whence]
        if base + offset < 0:
            raise ValueError(f"negative seek position {base + offset}")
        self._pos = base + offset
        return self._pos

    def readinto(self, buffer) -> int:  # any writable buffer: a bytearray, a numpy array
        into = memoryview(buffer).cast("B")
        n = max(0, min(len(into), len(self._view) - self._pos))
        into[:n] = self._view[self._pos:self._pos + n]
        self._pos += n
        return n


def _tiff_file(source: bytes | bytearray | memoryview | Path):
    """A ``tifffile.TiffFile`` of a file or of its bytes in memory (:class:`BufferStream`)."""
    import tifffile

    return tifffile.TiffFile(BufferStream(source) if isinstance(source, (bytes, bytearray, memoryview)) else source)


def tiff_pixels(source: bytes | bytearray | memoryview | Path, out: np.ndarray | None = None
                ) -> tuple[np.ndarray, int]:
    """The pixels of a TIFF and its first image's BitsPerSample, from one parse of the file's
    header. A file of one image (every camera's band or frame file) gives that image, as
    ``TiffFile.pages[0].asarray`` reads it; a file of several gives what ``tifffile.imread``
    gives (its first series, e.g. a stack), which the callers' shape checks then refuse.
    ``out``: an array to decode one image into when it has the image's shape and native dtype
    and is C-contiguous and writable (else a new one is made); the array returned is ``out``
    when it was used.

    One thread decodes (``maxworkers=1``): the callers already decode files in parallel, and an
    uncompressed camera file is one ``readinto``. The first page rather than the first series:
    tifffile's series detection (ImageJ, OME, shaped and a dozen other flavours) cost about
    0.06 ms of the 0.25-0.3 ms a 2.5-4.5 MB file takes (CPU time, tifffile 2026.3.3), and for one
    image it can only add length-1 axes.

    Raises whatever tifffile raises on a corrupt, truncated or unsupported file (:func:`decode_raw`
    turns it into a :class:`FrameError` naming the file).
    """
    with _tiff_file(source) as tif:
        page = tif.pages.first
        if len(tif.pages) != 1:
            return tif.asarray(maxworkers=1), int(page.bitspersample)
        if out is not None and not (out.shape == page.shape and out.dtype == page.dtype
                                    and out.flags.c_contiguous and out.flags.writeable):
            out = None
        return page.asarray(out=out, maxworkers=1), int(page.bitspersample)


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
    stored = "a pixel format"
    try:
        with _tiff_file(source) as tif:
            page = tif.pages.first
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
    """Pixels of a frame file (:func:`decode_frame` without the BitsPerSample)."""
    return decode_frame(source, path, out)[0]


def decode_frame(source: bytes | bytearray | memoryview | Path, path: str | Path, out: np.ndarray | None = None
                 ) -> tuple[np.ndarray, int | None]:
    """Pixels of a frame file, from its bytes or (``source`` a path) from the file itself, and
    the BitsPerSample of a TIFF's first image (None for PNG and JPEG) from the same parse;
    ``path`` names the format by its suffix and the file in errors. ``out``: where a TIFF of that
    shape and dtype is decoded (:func:`tiff_pixels`); the array returned is ``out`` when it was used.

    A JPEG without its end-of-image marker is truncated: libjpeg would silently return the
    decoded part padded with gray, so it is rejected here.

    :class:`FrameError` naming the file when it cannot be decoded: truncated or corrupt (re-copy
    it), stored in a format this installation does not decode (convert it), or not integer DN.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    bits = None
    try:
        if suffix in (".tif", ".tiff"):
            img, bits = tiff_pixels(source, out)
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
    return img, bits


def sample_bits(source: bytes | bytearray | memoryview | Path) -> int | None:
    """BitsPerSample of a TIFF's first image, from its bytes or its file, read from its header
    (tifffile's first page; no pixels read); None when it is not a readable TIFF (:func:`decode_raw`
    then says why). A RedEdge writes its 12-bit DN in the high bits of 16-bit samples, or, set to
    its 12-bit format, as they are in packed 12-bit samples: the decoded arrays are both uint16,
    only the file says which (:meth:`Camera.shift_for`)."""
    try:
        with _tiff_file(source) as tif:
            return int(tif.pages.first.bitspersample)
    except Exception:  # tifffile raises many types on what is not a TIFF or is cut short
        return None
