"""TIFF decoding through tifffile (tiff.tiff_pixels, decode_frame): the pixels tifffile gives,
from the bytes in memory (tiff.BufferStream, no copy of them), into the caller's array
where it fits, with the BitsPerSample of the same parse; files cut short refused, naming them."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
import tifffile

from pipeline.ingest.tiff import BufferStream, decode_frame, decode_raw, sample_bits, tiff_pixels

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"


def _tiff(arr: np.ndarray, **kw) -> bytes:
    buf = io.BytesIO()
    kw.setdefault("metadata", None)  # no shape description (a camera writes none)
    tifffile.imwrite(buf, arr, **kw)
    return buf.getvalue()


@pytest.mark.parametrize("dtype", ["<u2", ">u2", "u1"])
@pytest.mark.parametrize("rowsperstrip", [None, 1, 7, 64])
def test_same_pixels_as_tifffile(dtype: str, rowsperstrip: int | None) -> None:
    rng = np.random.default_rng(3)
    arr = rng.integers(0, np.iinfo(np.dtype(dtype)).max, size=(61, 37)).astype(dtype)
    data = _tiff(arr, byteorder=np.dtype(dtype).byteorder if dtype != "u1" else "<", rowsperstrip=rowsperstrip,
                 photometric="minisblack")
    ref = tifffile.imread(io.BytesIO(data))
    for source in (data, memoryview(bytearray(data))):  # bytes, and a view of the thread's read buffer
        got, bits = tiff_pixels(source)
        assert bits == 8 * np.dtype(dtype).itemsize
        assert got.dtype == ref.dtype and got.dtype.isnative and got.shape == ref.shape == (61, 37)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(got, arr)
        got[0, 0] = 1  # a writable array of its own, as tifffile's
    assert data == _tiff(arr, byteorder=np.dtype(dtype).byteorder if dtype != "u1" else "<",
                         rowsperstrip=rowsperstrip, photometric="minisblack")  # the source left as it was


def test_real_band_files_match_tifffile() -> None:
    files = sorted((DATA / "micasense-rededge").glob("*.tif")) + sorted((DATA / "parrot-sequoia").glob("*.TIF"))
    if not files:
        pytest.skip("no MicaSense or Sequoia sample")
    for f in files:
        got, bits = tiff_pixels(memoryview(bytearray(f.read_bytes())))
        np.testing.assert_array_equal(got, tifffile.imread(f))
        assert got.dtype == np.uint16 and bits == sample_bits(f) == 16
        assert got.shape == (960, 1280)  # both cameras: 1280 x 960 band files


@pytest.mark.parametrize("kw", [
    {"metadata": {}}, {"metadata": {"exposure_ms": 2.5}}, {"description": '{"shape": [1, 64, 32]}'},
    {"description": "a camera's free text"}, {"imagej": True, "metadata": {"axes": "YX"}}, {"bigtiff": True},
    {"compression": "zlib"}, {"tile": (16, 16)}, {"rowsperstrip": 5},
])
def test_what_tifffile_imread_gives_for_every_kind_of_tiff(kw: dict) -> None:
    """Shape records, ImageJ and free-text descriptions, BigTIFF, compression, tiles: the
    values and dtype tifffile.imread gives, and the image's own 2-D shape (a shape record's
    length-1 axes are not added)."""
    arr = np.arange(64 * 32, dtype=np.uint16).reshape(64, 32)
    data = _tiff(arr, **kw)
    ref = tifffile.imread(io.BytesIO(data))
    got = decode_raw(memoryview(bytearray(data)), "a.tif")
    assert got.shape == (64, 32) and got.dtype == ref.dtype == np.uint16
    np.testing.assert_array_equal(got, ref.reshape(64, 32))
    np.testing.assert_array_equal(got, arr)


def test_several_images_stack_as_imread_does() -> None:
    arr = np.arange(2 * 8 * 6, dtype=np.uint16).reshape(2, 8, 6)
    data = _tiff(arr)
    into = np.zeros((8, 6), np.uint16)  # one image's shape: not the series', so not used
    got, bits = tiff_pixels(data, into)
    assert got.shape == (2, 8, 6) and bits == 16 and not into.any()
    np.testing.assert_array_equal(got, tifffile.imread(io.BytesIO(data)))


def test_decode_raw_truncated_file_still_refused(tmp_path: Path) -> None:
    arr = np.arange(64 * 32, dtype=np.uint16).reshape(64, 32)
    data = _tiff(arr, rowsperstrip=16)
    np.testing.assert_array_equal(decode_raw(data, tmp_path / "a.tif"), arr)
    from mscal_core.errors import FrameError

    for cut in (data[:300], data[:-10], data[:40], b"not a tiff at all"):
        with pytest.raises(FrameError, match="a.tif: unreadable or truncated image") as err:
            decode_raw(memoryview(bytearray(cut)), tmp_path / "a.tif")
        assert "re-copy the file" in str(err.value)
    assert sample_bits(data[:6]) is None and sample_bits(tmp_path / "missing.tif") is None


def test_bits_from_tiffs_only() -> None:
    """decode_frame gives a TIFF's BitsPerSample from its own parse, and None for PNG and JPEG
    (their depth is the decoded dtype's)."""
    import cv2

    arr = (np.arange(12 * 10, dtype=np.uint16).reshape(12, 10) * 500)
    ok, png = cv2.imencode(".png", arr)
    assert ok
    got, bits = decode_frame(png.tobytes(), "a.png")
    assert bits is None and got.dtype == np.uint16
    np.testing.assert_array_equal(got, arr)
    got, bits = decode_frame(_tiff(arr.astype(np.uint8)), "a.TIF")
    assert bits == 8 and got.dtype == np.uint8


def test_decoded_into_the_given_array_when_it_fits() -> None:
    arr = np.arange(61 * 37, dtype=np.uint16).reshape(61, 37)
    data = _tiff(arr, rowsperstrip=8)
    into = np.zeros((61, 37), np.uint16)
    got, bits = tiff_pixels(memoryview(bytearray(data)), into)
    assert got is into and bits == 16
    np.testing.assert_array_equal(into, arr)
    assert decode_raw(data, "a.tif", into) is into
    for other in (np.zeros((37, 61), np.uint16), np.zeros((61, 37), np.uint8),  # wrong shape, wrong type
                  np.zeros((61, 74), np.uint16)[:, ::2]):  # not contiguous
        got, _ = tiff_pixels(data, other)
        assert got is not other and not other.any()  # a new array, the given one untouched
        np.testing.assert_array_equal(got, arr)
    read_only = np.zeros((61, 37), np.uint16)
    read_only.flags.writeable = False
    assert tiff_pixels(data, read_only)[0] is not read_only and not read_only.any()


def test_buffer_stream_reads_and_seeks_like_bytesio() -> None:
    data = bytes(range(256)) * 3
    buf = bytearray(data)
    ours, ref = BufferStream(memoryview(buf)), io.BytesIO(data)
    for whence, offset in ((io.SEEK_SET, 10), (io.SEEK_CUR, 5), (io.SEEK_END, -7), (io.SEEK_END, 20)):
        assert ours.seek(offset, whence) == ref.seek(offset, whence)
        assert ours.tell() == ref.tell()
        assert ours.read(12) == ref.read(12)
    ours.seek(700)
    into = np.zeros(40, np.uint16)  # 80 bytes asked, 68 left
    assert ours.readinto(into) == 68 and ours.tell() == 768
    np.testing.assert_array_equal(into.view(np.uint8)[:68], np.frombuffer(data[700:], np.uint8))
    assert ours.read(5) == b""
    with pytest.raises(ValueError, match="negative seek position"):
        ours.seek(-1)
    buf[0] = 255  # a view of the buffer, not a copy of it
    ours.seek(0)
    assert ours.read(1) == b"\xff"


def test_capture_decoded_into_its_cube() -> None:
    from pipeline.apply.captures import find_captures
    from pipeline.ingest.grouping import read_capture_pixels
    from pipeline.ingest.identify import identify_camera

    folder = DATA / "micasense-rededge"
    if not folder.is_dir():
        pytest.skip("no MicaSense sample")
    cap = find_captures(folder, identify_camera(folder, None).camera).captures[1]
    sha, dns, _ = read_capture_pixels(cap)
    cube = np.zeros((len(cap.metas), 960, 1280), np.uint16)
    sha2, dns2, _ = read_capture_pixels(cap, out=cube)
    assert sha2 == sha
    for b, (a, c) in enumerate(zip(dns, dns2)):
        np.testing.assert_array_equal(a, c)
        assert np.shares_memory(c, cube[b])
    np.testing.assert_array_equal(cube, np.stack(dns))


def test_capture_read_once_per_file_hash_and_a_file_cut_short(monkeypatch) -> None:
    """read_capture_pixels reads each band file once into the thread's buffer (shared with the
    snapshot reader, pipeline.ingest.raw.read_whole): the content hash of the files' bytes in
    band order, each band decoded before the next file reuses the buffer, and a file that ends
    before its stat size (a copy in progress) refused, naming it."""
    import hashlib

    from mscal_core.errors import FrameError
    from pipeline.apply.captures import find_captures
    from pipeline.ingest.grouping import read_capture_pixels
    from pipeline.ingest.identify import identify_camera

    folder = DATA / "micasense-rededge"
    if not folder.is_dir():
        pytest.skip("no MicaSense sample")
    cap = find_captures(folder, identify_camera(folder, None).camera).captures[1]
    sha, dns, _ = read_capture_pixels(cap)
    h = hashlib.sha256()
    for f in cap.files:
        h.update(f.read_bytes())
    assert sha == h.hexdigest()
    for meta, dn in zip(cap.metas, dns):
        np.testing.assert_array_equal(dn, tifffile.imread(meta.path))
    short = cap.files[2]
    real_stat = Path.stat

    def larger(self, *a, **k):
        st = real_stat(self, *a, **k)
        return os.stat_result((*st[:6], st.st_size + 10, *st[7:])) if self == short else st

    monkeypatch.setattr(Path, "stat", larger)
    with pytest.raises(FrameError, match="changed while it was being read") as err:
        read_capture_pixels(cap)
    assert short.name in str(err.value)


def _with_compression(code: int) -> bytes:
    """A small 16-bit TIFF whose Compression tag says ``code`` (the strip left as it is)."""
    import struct

    data = bytearray(_tiff(np.arange(64, dtype=np.uint16).reshape(8, 8), photometric="minisblack"))
    with tifffile.TiffFile(io.BytesIO(bytes(data))) as tif:
        struct.pack_into("<H", data, tif.pages[0].tags[259].valueoffset, code)
    return bytes(data)


def test_a_format_not_decoded_is_named_not_blamed_on_the_copy(tmp_path: Path) -> None:
    """An intact TIFF in a format the decoders do not read: the error names the file, its
    BitsPerSample and Compression and the decoder's words, and says to convert it, not to
    re-copy it (a truncated file keeps the re-copy hint: test_decode_raw_truncated_file_still_refused)."""
    from mscal_core.errors import FrameError

    path = tmp_path / "odd.tif"
    path.write_bytes(_with_compression(60000))
    with pytest.raises(FrameError) as err:
        decode_raw(path.read_bytes(), path)
    text = str(err.value)
    assert text.startswith(f"{path}: TIFF stored with BitsPerSample 16, Compression 60000, which this installation "
                           "cannot decode (ValueError: 60000 is not a known COMPRESSION)")
    assert "convert it to an uncompressed" in text and "re-copy" not in text


def test_12bit_without_imagecodecs_says_to_install_it(tmp_path: Path, monkeypatch) -> None:
    """Packed 12-bit samples decode only through imagecodecs (a dependency): where it is missing
    the error says so and how to install it, naming the file and its BitsPerSample."""
    import sys

    from mscal_core.errors import FrameError
    from tests import camera_files as cf

    src = DATA / "micasense-rededge" / "IMG_0000_2.tif"
    if not src.is_file():
        pytest.skip("no MicaSense sample")
    path = cf.rededge_12bit(src, tmp_path / "IMG_0000_2.tif")

    def without_imagecodecs(*args, **kwargs):  # what tifffile raises when imagecodecs is not installed
        raise NotImplementedError("packints_decode of 12-bit integers requires the 'imagecodecs' package")

    monkeypatch.setattr(tifffile.TiffPage, "asarray", without_imagecodecs)
    monkeypatch.setitem(sys.modules, "imagecodecs", None)
    with pytest.raises(FrameError) as err:
        decode_raw(path.read_bytes(), path)
    assert str(err.value) == (
        f"{path}: TIFF stored with BitsPerSample 12, Compression 1 (NONE) needs the imagecodecs package to decode, "
        "and it is not installed (NotImplementedError: packints_decode of 12-bit integers requires the "
        "'imagecodecs' package) (the file is fine: install mscal's dependencies again, imagecodecs among them: "
        "make setup, or pip install -e . in the checkout)")
