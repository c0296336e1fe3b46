"""The strip reader of plain camera TIFFs (tiff.plain_tiff_pixels) gives exactly what
tifffile gives, and declines every file it does not fully understand (tifffile reads those)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
import tifffile

from pipeline.ingest.tiff import decode_raw, plain_tiff_pixels

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
    got = plain_tiff_pixels(data)
    ref = tifffile.imread(io.BytesIO(data))
    assert got is not None
    assert got.dtype == ref.dtype and got.dtype.isnative and got.shape == ref.shape == (61, 37)
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(got, arr)
    got[0, 0] = 1  # a writable array of its own, as tifffile's


def test_real_band_files_match_tifffile() -> None:
    files = sorted((DATA / "micasense-rededge").glob("*.tif"))
    if not files:
        pytest.skip("no MicaSense sample")
    for f in files:
        data = f.read_bytes()
        got = plain_tiff_pixels(data)
        assert got is not None, f
        np.testing.assert_array_equal(got, tifffile.imread(f))
        assert got.dtype == np.uint16 and got.shape == (960, 1280)


@pytest.mark.parametrize("rowsperstrip", [None, 5])
def test_tifffile_shape_record_is_read(rowsperstrip: int | None) -> None:
    """Files written by tifffile carry an ImageDescription with its JSON shape record (the
    frames of a Python capture script, the synthetic sessions): for a single 2-D image it
    changes nothing tifffile returns, so they take the strip reader too, with the same pixels."""
    rng = np.random.default_rng(8)
    arr = rng.integers(0, 1024, size=(40, 23)).astype(np.uint16)
    for kw in ({"metadata": {}}, {"metadata": {"exposure_ms": 2.5}}):
        data = _tiff(arr, rowsperstrip=rowsperstrip, **kw)
        assert b'"shape": [40, 23]' in data
        got = plain_tiff_pixels(data)
        assert got is not None
        np.testing.assert_array_equal(got, tifffile.imread(io.BytesIO(data)))
        np.testing.assert_array_equal(plain_tiff_pixels(memoryview(bytearray(data))), arr)  # from a buffer view


def test_declines_what_it_does_not_read() -> None:
    arr = np.arange(64 * 32, dtype=np.uint16).reshape(64, 32)
    assert plain_tiff_pixels(_tiff(arr, compression="zlib")) is None
    assert plain_tiff_pixels(_tiff(arr, tile=(16, 16))) is None
    assert plain_tiff_pixels(_tiff(np.stack([arr, arr]))) is None  # two images
    assert plain_tiff_pixels(_tiff(arr.astype(np.float32))) is None
    assert plain_tiff_pixels(_tiff(arr.astype(np.int16))) is None
    assert plain_tiff_pixels(_tiff(np.dstack([arr, arr, arr]).astype(np.uint8), photometric="rgb")) is None
    # an ImageDescription other than tifffile's shape record of this very image: tifffile's call
    assert plain_tiff_pixels(_tiff(arr, description='{"shape": [1, 64, 32]}')) is None
    assert plain_tiff_pixels(_tiff(arr, description='{"shape": [32, 64]}')) is None
    assert plain_tiff_pixels(_tiff(arr, description="a camera's free text")) is None
    assert plain_tiff_pixels(_tiff(arr, description="{not json")) is None
    assert plain_tiff_pixels(_tiff(arr, imagej=True, metadata={"axes": "YX"})) is None
    assert plain_tiff_pixels(_tiff(arr, bigtiff=True)) is None
    assert plain_tiff_pixels(b"not a tiff at all") is None
    full = _tiff(arr, rowsperstrip=16)
    assert plain_tiff_pixels(full) is not None
    assert plain_tiff_pixels(full[:-10]) is None  # a strip past the end of a truncated file
    assert plain_tiff_pixels(full[:40]) is None


def test_decode_raw_truncated_file_still_refused(tmp_path: Path) -> None:
    arr = np.arange(64 * 32, dtype=np.uint16).reshape(64, 32)
    data = _tiff(arr, rowsperstrip=16)
    np.testing.assert_array_equal(decode_raw(data, tmp_path / "a.tif"), arr)
    from mscal_core.errors import FrameError

    with pytest.raises(FrameError, match="a.tif|unreadable"):
        decode_raw(data[:300], tmp_path / "a.tif")


def test_decoded_into_the_given_array_when_it_fits() -> None:
    arr = np.arange(61 * 37, dtype=np.uint16).reshape(61, 37)
    data = _tiff(arr, rowsperstrip=8)
    into = np.zeros((61, 37), np.uint16)
    assert plain_tiff_pixels(data, into) is into
    np.testing.assert_array_equal(into, arr)
    other = np.zeros((37, 61), np.uint16)  # wrong shape: a new array, the given one untouched
    got = plain_tiff_pixels(data, other)
    assert got is not other and not other.any()
    np.testing.assert_array_equal(got, arr)
    wrong_type = np.zeros((61, 37), np.uint8)
    assert plain_tiff_pixels(data, wrong_type) is not wrong_type and not wrong_type.any()


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

    monkeypatch.setattr(tifffile, "imread", without_imagecodecs)
    monkeypatch.setitem(sys.modules, "imagecodecs", None)
    with pytest.raises(FrameError) as err:
        decode_raw(path.read_bytes(), path)
    assert str(err.value) == (
        f"{path}: TIFF stored with BitsPerSample 12, Compression 1 (NONE) needs the imagecodecs package to decode, "
        "and it is not installed (NotImplementedError: packints_decode of 12-bit integers requires the "
        "'imagecodecs' package) (the file is fine: install mscal's dependencies again, imagecodecs among them: "
        "make setup, or pip install -e . in the checkout)")
