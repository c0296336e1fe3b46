"""Per-frame photogrammetry TIFFs: EXIF/GPS/XMP read back the way OpenDroneMap reads them.

OpenDroneMap's ``opendm/photo.py`` (ODM_Photo.parse_exif_values) reads EXIF with
``exifread.process_file`` and XMP by cutting ``<x:xmpmeta ... </x:xmpmeta>`` out of the raw
file bytes and parsing it with ``xmltodict`` (qualified names kept as written: attributes
become ``'@Camera:CaptureUUID'``, elements ``'Camera:BandName'`` with an ``rdf:Seq``/``rdf:li``
inside). ``xmltodict`` is not installed here, so :func:`_odm_xmp` rebuilds that mapping with
expat (no namespace processing), which is what xmltodict does.
"""

from __future__ import annotations

import os
import struct
import warnings
import xml.etree.ElementTree as ET
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import rasterio
import tifffile

from mscal_core.errors import CatalogError
from pipeline.ingest.photo_tags import CameraOptics
from pipeline.products import writers
from pipeline.products.writers import (
    NODATA_UINT16,
    XMP_CAMERA_NS,
    BandTags,
    FrameTags,
    encode_reflectance_uint16,
    write_band_tiff,
    write_ndvi_tiff,
)
from tests.photo_readers import dms_to_decimal as _dms_to_decimal
from tests.photo_readers import exif_tags as _exif
from tests.photo_readers import odm_get_xmp_tag as _odm_get_xmp_tag
from tests.photo_readers import odm_xmp as _odm_xmp

FRAME = FrameTags(
    time="2024-05-01T10:00:00.250Z", lat=47.3977419, lon=8.5455938, alt_m=488.25,
    capture_uuid="5f0c2b9e-8f8e-5a55-9d2a-3f0e7b8c1a22", exposure_ms=2.5,
    camera_make="mscal", camera_model="ximea-mq022hg-sm5x5-nir",
)
BAND = BandTags(name="b670", wavelength_nm=670.0, fwhm_nm=12.5, rig_camera_index=3)


@pytest.fixture(autouse=True)
def _quiet_rasterio():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        yield


def _refl(shape=(217, 409), seed=0) -> np.ndarray:
    r = np.random.default_rng(seed).uniform(0.0, 0.9, shape).astype(np.float32)
    r[0, 0] = np.nan
    r[1, 1] = 0.5
    return r


# --------------------------------------------------------------------------- ODM-style readers


def _walk_tiff(path: Path) -> dict[int, dict[int, tuple[int, int, int]]]:
    """Check the TIFF structure by hand: every IFD and value offset in the file and word-aligned."""
    raw = path.read_bytes()
    assert raw[:4] == b"II*\0"
    size = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1, 11: 4, 12: 8}
    ifds: dict[int, dict[int, tuple[int, int, int]]] = {}
    todo = [struct.unpack_from("<I", raw, 4)[0]]
    while todo:
        off = todo.pop()
        assert off % 2 == 0 and off + 2 <= len(raw)
        (n,) = struct.unpack_from("<H", raw, off)
        entries = {}
        tags = []
        for i in range(n):
            tag, typ, count, val = struct.unpack_from("<HHII", raw, off + 2 + 12 * i)
            tags.append(tag)
            nbytes = size[typ] * count
            if nbytes > 4:
                assert val % 2 == 0, f"tag {tag}: value offset {val} not word-aligned"
                assert val + nbytes <= len(raw), f"tag {tag}: value beyond end of file"
            entries[tag] = (typ, count, val)
            if tag in (34665, 34853):
                assert typ == 4 and count == 1
                todo.append(val)
        assert tags == sorted(tags), "IFD entries must be sorted by tag"
        (nxt,) = struct.unpack_from("<I", raw, off + 2 + 12 * n)
        assert nxt == 0
        ifds[off] = entries
    return ifds


# --------------------------------------------------------------------------- tests


def test_band_tiff_exif_gps_as_odm_reads_them(tmp_path) -> None:
    p = write_band_tiff(tmp_path / "f_b670.tif", _refl(), FRAME, BAND)
    assert p == tmp_path / "f_b670.tif"
    for details in (False, True):  # ODM passes details=True in current photo.py; the brief uses False
        tags = _exif(p, details)
        assert tags["Image Make"].values == "mscal"
        assert tags["Image Software"].values == writers.SOFTWARE
        assert tags["Image Model"].values == "ximea-mq022hg-sm5x5-nir"
        lat = _dms_to_decimal(tags["GPS GPSLatitude"], tags["GPS GPSLatitudeRef"])
        lon = _dms_to_decimal(tags["GPS GPSLongitude"], tags["GPS GPSLongitudeRef"])
        assert lat == pytest.approx(47.3977419, abs=1e-9)
        assert lon == pytest.approx(8.5455938, abs=1e-9)
        assert tags["GPS GPSLatitudeRef"].values == "N" and tags["GPS GPSLongitudeRef"].values == "E"
        alt = tags["GPS GPSAltitude"].values[0]
        assert float(alt.num) / float(alt.den) == pytest.approx(488.25)
        assert tags["GPS GPSAltitudeRef"].values == [0]
        assert tags["GPS GPSVersionID"].values == [2, 3, 0, 0]
        assert tags["EXIF DateTimeOriginal"].values == "2024:05:01 10:00:00"
        assert tags["EXIF SubSecTimeOriginal"].values == "25"
        assert tags["EXIF OffsetTimeOriginal"].values == "+00:00"
        assert "EXIF ExposureTime" not in tags  # the reflectance marker: no photometric exposure for ODM
        assert tags["GPS GPSDate"].values == "2024:05:01"
    # ODM's capture time: DateTimeOriginal as UTC plus "0.<SubSecTime>" seconds
    tags = _exif(p)
    t = datetime.strptime(tags["EXIF DateTimeOriginal"].values, "%Y:%m:%d %H:%M:%S")
    t += timedelta(milliseconds=float(f"0.{int(tags['EXIF SubSecTime'].values)}") * 1e3)
    assert t.replace(tzinfo=timezone.utc) == datetime(2024, 5, 1, 10, 0, 0, 250000, tzinfo=timezone.utc)


def test_band_tiff_xmp_camera_tags(tmp_path) -> None:
    p = write_band_tiff(tmp_path / "f.tif", _refl(), FRAME, BAND)
    # as OpenDroneMap finds them
    (xt,) = _odm_xmp(p)
    assert _odm_get_xmp_tag(xt, ["Camera:BandName", "@Camera:BandName", "FLIR:BandName"]) == "b670"
    assert _odm_get_xmp_tag(xt, ["DLS:SensorId", "@Camera:RigCameraIndex", "Camera:RigCameraIndex"]) == "3"
    assert _odm_get_xmp_tag(
        xt, ["@drone-dji:CaptureUUID", "MicaSense:CaptureId", "@Camera:ImageUniqueID", "@Camera:CaptureUUID"]
    ) == FRAME.capture_uuid
    # the same packet from TIFF tag 700, parsed as namespaced XML
    with tifffile.TiffFile(p) as tf:
        packet = bytes(tf.pages[0].tags[700].value)
    assert packet.startswith(b"<?xpacket begin=") and packet.endswith(b'<?xpacket end="w"?>')
    root = ET.fromstring(packet[packet.find(b"<x:xmpmeta"):packet.find(b"</x:xmpmeta>") + 12])
    rdf = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
    desc = root.find(f"{{{rdf}}}RDF/{{{rdf}}}Description")
    cam = f"{{{XMP_CAMERA_NS}}}"
    assert desc.get(cam + "CaptureUUID") == FRAME.capture_uuid
    assert int(desc.get(cam + "RigCameraIndex")) == 3

    def seq(name):
        return [li.text for li in desc.findall(f"{cam}{name}/{{{rdf}}}Seq/{{{rdf}}}li")]

    assert seq("BandName") == ["b670"]
    assert [float(v) for v in seq("CentralWavelength")] == [670.0]
    assert [float(v) for v in seq("WavelengthFWHM")] == [12.5]


def test_band_tiff_pixels_uint16(tmp_path) -> None:
    r = _refl()
    p = write_band_tiff(tmp_path / "f.tif", r, FRAME, BAND)
    with rasterio.open(p) as ds:
        assert (ds.count, ds.height, ds.width, ds.dtypes[0]) == (1, 217, 409, "uint16")
        assert ds.nodata == NODATA_UINT16
        assert ds.descriptions == ("b670",)
        assert ds.scales[0] == pytest.approx(1 / 32768)
        assert float(ds.tags(1, ns="IMAGERY")["CENTRAL_WAVELENGTH_UM"]) == pytest.approx(0.670)
        # GDAL (libtiff) follows the EXIF and GPS IFDs and finds the XMP packet too
        exif = ds.tags(ns="EXIF")
        assert exif["EXIF_GPSLatitudeRef"] == "N" and exif["EXIF_DateTimeOriginal"] == "2024:05:01 10:00:00"
        assert exif["EXIF_PixelXDimension"] == "409"
        assert "Camera:CaptureUUID" in ds.tags(ns="xml:XMP")["xml:XMP"]
        a = ds.read(1)
    assert a[0, 0] == 65535 and a[1, 1] == 16384
    ok = ~np.isnan(r)
    np.testing.assert_array_equal(a[ok], np.rint(r[ok].astype(np.float64) * 32768).astype(np.uint16))
    with tifffile.TiffFile(p) as tf:
        page = tf.pages[0]
        np.testing.assert_array_equal(page.asarray(), a)
        exif = page.tags["ExifTag"].value
        gps = page.tags["GPSTag"].value
        assert exif["DateTimeOriginal"] == "2024:05:01 10:00:00"
        assert gps["GPSLatitudeRef"] == "N" and len(gps["GPSLatitude"]) == 6  # 3 rationals (num, den)
    _walk_tiff(p)


def test_band_tiff_float32_keeps_nan_and_multi_strip(tmp_path) -> None:
    r = _refl((300, 1000), seed=1)  # 4000-byte rows -> several strips
    p = write_band_tiff(tmp_path / "f.tif", r, FRAME, BAND, dtype="float32")
    with rasterio.open(p) as ds:
        assert ds.dtypes[0] == "float32" and np.isnan(ds.nodata)
        a = ds.read(1)
    np.testing.assert_array_equal(a, r)  # NaN == NaN for assert_array_equal
    ifds = _walk_tiff(p)
    assert ifds[8][273][1] > 1  # StripOffsets count


def test_opencv_reads_them(tmp_path) -> None:
    # ODM measures images (and aligns multispectral bands) with OpenCV when PIL is not enough
    import cv2

    r = _refl()
    a = cv2.imread(str(write_band_tiff(tmp_path / "u.tif", r, FRAME, BAND)), cv2.IMREAD_UNCHANGED)
    assert a.dtype == np.uint16 and a.shape == (217, 409) and a[1, 1] == 16384
    f = cv2.imread(str(write_band_tiff(tmp_path / "f.tif", r, FRAME, BAND, dtype="float32")), cv2.IMREAD_UNCHANGED)
    assert f.dtype == np.float32 and f[1, 1] == 0.5


def test_ifd_offsets_hold_for_tags_of_every_length(tmp_path) -> None:
    """The EXIF and GPS IFDs are placed by IFD0's computed size, each IFD serialised once: with
    names, times and positions of many lengths (odd ones need padding; with and without
    sub-seconds, GPS, lens, rig) every file still reads back, pixels, EXIF and GPS, as
    OpenDroneMap reads them."""
    rng = np.random.default_rng(11)
    refl = _refl((23, 31))
    for k in range(12):
        name = "b" + "x" * int(rng.integers(0, 9))
        frame = FrameTags(
            time=["2024-05-01T10:00:00Z", "2024-05-01T10:00:00.250Z", "2024-05-01T10:00:00.123457", None][k % 4],
            lat=None if k % 5 == 4 else 47.0 + rng.uniform(), lon=8.0 + rng.uniform(),
            alt_m=None if k % 3 == 2 else float(rng.uniform(-5, 900)),
            capture_uuid="u" * int(rng.integers(1, 40)), exposure_ms=2.5,
            camera_make="m" * int(rng.integers(1, 7)), camera_model="model" + "y" * int(rng.integers(0, 5)),
            rig_name=None if k % 2 else "rig" * int(rng.integers(1, 4)),
        )
        optics = None if k % 3 == 0 else CameraOptics(f_number=2.8, focal_length_mm=5.5 + k)
        band = BandTags(name=name, wavelength_nm=600.0 + k, fwhm_nm=None if k % 2 else 10.5, rig_camera_index=k,
                        optics=optics)
        path = write_band_tiff(tmp_path / f"f{k}.tif", refl, frame, band)
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            np.testing.assert_array_equal(page.asarray(), writers.encode_reflectance_uint16(refl))
            exif = page.tags["ExifTag"].value
            assert exif["PixelXDimension"] == 31 and exif["PixelYDimension"] == 23
        tags = _exif(path)
        if frame.lat is None:
            assert "GPS GPSLatitude" not in tags
        else:
            lat = _dms_to_decimal(tags["GPS GPSLatitude"], tags["GPS GPSLatitudeRef"])
            assert lat == pytest.approx(frame.lat, abs=1e-7)
        assert tags["Image Make"].values == frame.camera_make and tags["Image Model"].values == frame.camera_model


def test_encode_uint16_clips_and_marks_nan() -> None:
    v = encode_reflectance_uint16(np.array([-0.1, 0.0, 0.5, 1.0, 1.99997, 2.5, np.inf, np.nan], np.float32))
    assert v.tolist() == [0, 0, 16384, 32768, 65534, 65534, 65534, 65535]


def _encode_by_steps(r: np.ndarray) -> np.ndarray:
    """The encoding spelled out in numpy (scale, round half to even, clip, NaN marked)."""
    v = np.rint(r.astype(np.float32) * np.float32(32768))  # (the encoding as it was before patchNaNs)
    np.clip(v, 0.0, 65534.0, out=v)
    with np.errstate(invalid="ignore"):
        out = v.astype(np.uint16)
    out[np.isnan(v)] = 65535
    return out


def test_encode_uint16_equals_the_numpy_steps_on_ties_edges_and_nan_payloads() -> None:
    ties = (np.arange(0, 65536, dtype=np.float32) + np.float32(0.5)) / np.float32(32768)  # x.5: to even
    edges = np.array([65533.5, 65534.0, 65534.49, 65534.5, 65535.0, 65536.0, 1e30, -0.5, -0.49, -1e30],
                     np.float32) / np.float32(32768)
    odd_nans = np.array([0x7FC00000, 0xFFC00000, 0x7F800001, 0xFFFFFFFF], np.uint32).view(np.float32)
    r = np.concatenate([ties, edges, odd_nans, np.array([np.inf, -np.inf, -0.0, 0.0], np.float32)])  # even length
    with np.errstate(invalid="ignore"):  # a signalling NaN among the payloads
        got = encode_reflectance_uint16(r.reshape(2, -1))
        want = _encode_by_steps(r)
    np.testing.assert_array_equal(got.ravel(), want)
    np.testing.assert_array_equal(encode_reflectance_uint16(r.reshape(2, -1).T), want.reshape(2, -1).T)  # F order
    assert got[0, :4].tolist() == [0, 2, 2, 4]  # 0.5 -> 0, 1.5 -> 2, 2.5 -> 2, 3.5 -> 4


def test_southern_western_below_sea_level_naive_time(tmp_path) -> None:
    fr = FrameTags(time="2023-12-31T23:59:59.05", lat=-33.8568, lon=-70.6483, alt_m=-12.0,
                   capture_uuid="u1", exposure_ms=0.8, camera_make="mscal", camera_model="m")
    tags = _exif(write_band_tiff(tmp_path / "f.tif", _refl(), fr, BAND))
    assert tags["GPS GPSLatitudeRef"].values == "S" and tags["GPS GPSLongitudeRef"].values == "W"
    assert _dms_to_decimal(tags["GPS GPSLatitude"], tags["GPS GPSLatitudeRef"]) == pytest.approx(-33.8568, abs=1e-9)
    assert _dms_to_decimal(tags["GPS GPSLongitude"], tags["GPS GPSLongitudeRef"]) == pytest.approx(-70.6483, abs=1e-9)
    assert tags["GPS GPSAltitudeRef"].values == [1]
    assert float(tags["GPS GPSAltitude"].values[0]) == 12.0
    assert tags["EXIF DateTimeOriginal"].values == "2023:12:31 23:59:59"
    assert tags["EXIF SubSecTimeOriginal"].values == "05"
    assert "EXIF OffsetTimeOriginal" not in tags and "GPS GPSDate" not in tags  # zone unknown
    assert "EXIF ExposureTime" not in tags and "EXIF FNumber" not in tags  # no optics given


def test_zoned_time_is_written_in_utc(tmp_path) -> None:
    fr = FrameTags(time="2024-05-01T12:30:00+02:00", lat=1.0, lon=2.0, alt_m=None, capture_uuid="u",
                   exposure_ms=1.0, camera_make="a", camera_model="b")
    tags = _exif(write_band_tiff(tmp_path / "f.tif", _refl(), fr, BAND))
    assert tags["EXIF DateTimeOriginal"].values == "2024:05:01 10:30:00"
    assert "EXIF SubSecTimeOriginal" not in tags
    assert "GPS GPSAltitude" not in tags and "GPS GPSLatitude" in tags


def test_no_position_time_or_exposure(tmp_path) -> None:
    fr = FrameTags(time=None, lat=float("nan"), lon=None, alt_m=None, capture_uuid="u",
                   exposure_ms=None, camera_make="mscal", camera_model="m")
    p = write_band_tiff(tmp_path / "f.tif", _refl(), fr, BAND)
    tags = _exif(p)
    assert not any(k.startswith("GPS ") for k in tags)
    assert "EXIF DateTimeOriginal" not in tags and "EXIF ExposureTime" not in tags
    assert "Image GPSInfo" not in tags and tags["Image Make"].values == "mscal"
    _walk_tiff(p)
    with rasterio.open(p) as ds:
        assert ds.read(1).shape == (217, 409)


def test_ndvi_tiff(tmp_path) -> None:
    ndvi = np.linspace(-1, 1, 217 * 409, dtype=np.float32).reshape(217, 409)
    ndvi[5, 5] = np.nan
    p = write_ndvi_tiff(tmp_path / "ndvi" / "f.tif", ndvi, FRAME)
    with rasterio.open(p) as ds:
        assert ds.dtypes[0] == "float32" and ds.descriptions == ("ndvi",)
        np.testing.assert_array_equal(ds.read(1), ndvi)
    tags = _exif(p)
    assert "GPS GPSLatitude" in tags and tags["EXIF DateTimeOriginal"].values == "2024:05:01 10:00:00"
    (xt,) = _odm_xmp(p)
    assert _odm_get_xmp_tag(xt, ["Camera:BandName", "@Camera:BandName"]) == "NDVI"
    assert xt["@Camera:CaptureUUID"] == FRAME.capture_uuid
    assert "@Camera:RigCameraIndex" not in xt
    _walk_tiff(p)


def test_bad_inputs(tmp_path) -> None:
    with pytest.raises(ValueError, match="dtype"):
        write_band_tiff(tmp_path / "a.tif", _refl(), FRAME, BAND, dtype="uint8")
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        write_band_tiff(tmp_path / "a.tif", np.zeros((2, 3, 4), np.float32), FRAME, BAND)
    with pytest.raises(CatalogError, match="BandName"):
        write_band_tiff(tmp_path / "a.tif", _refl(), FRAME, BandTags("670", 670.0, None, 0))
    assert list(tmp_path.iterdir()) == []


def test_xml_special_characters_are_escaped(tmp_path) -> None:
    fr = FrameTags(time=None, lat=None, lon=None, alt_m=None, capture_uuid='a<b>&"c',
                   exposure_ms=1.0, camera_make="mscal", camera_model="m")
    p = write_band_tiff(tmp_path / "f.tif", _refl(), fr, BandTags("Red & <edge>", 717.0, None, 1))
    (xt,) = _odm_xmp(p)
    assert xt["@Camera:CaptureUUID"] == 'a<b>&"c'
    assert _odm_get_xmp_tag(xt, ["Camera:BandName"]) == "Red & <edge>"


def test_atomic_write_leaves_nothing_on_failure(tmp_path, monkeypatch) -> None:
    target = tmp_path / "f.tif"
    target.write_bytes(b"old")

    def broken(path, *a, **k):
        Path(path).write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(writers, "write_file", broken)
    with pytest.raises(OSError, match="disk full"):
        write_band_tiff(target, _refl(), FRAME, BAND)
    assert sorted(os.listdir(tmp_path)) == ["f.tif"]
    assert target.read_bytes() == b"old"


OPTICS = CameraOptics(f_number=2.8, focal_length_mm=5.5, focal_plane_resolution=(266.666667, 266.666667),
                      focal_plane_unit=4, focal_length_35mm=40,
                      xmp=(("ModelType", "perspective"), ("PrincipalPoint", "2.4354,1.79714"),
                           ("PerspectiveFocalLength", "1441.1993107495564"),
                           ("PerspectiveDistortion", "-0.1037,0.1303,0.0110,-0.0008,0.0002")))


def test_band_tiff_carries_the_lens_and_the_reflectance_marker(tmp_path) -> None:
    """The band's lens in EXIF (FNumber, FocalLength, focal plane resolution, 35 mm
    equivalent) and XMP (the lens model, verbatim), RigName, MicaSense's capture id, and the
    marker: no ExposureTime (ODM: no photometric exposure), HorizontalIrradiance = pi."""
    fr = FrameTags(time=None, lat=None, lon=None, alt_m=None, capture_uuid="u", exposure_ms=1.0,
                   camera_make="MicaSense", camera_model="RedEdge", rig_name="RedEdge",
                   maker_tags=(("MicaSense", "http://micasense.com/MicaSense/1.0/", "CaptureId", "g2R43Qr5m7EeTFGbkh1W"),))
    band = BandTags("Red edge", 717.0, 10.0, 4, optics=OPTICS)
    p = write_band_tiff(tmp_path / "f.tif", _refl(), fr, band)
    tags = _exif(p, True)
    assert (tags["Image Make"].values, tags["Image Model"].values) == ("MicaSense", "RedEdge")
    assert float(tags["EXIF FNumber"].values[0]) == pytest.approx(2.8)
    assert float(tags["EXIF FocalLength"].values[0]) == pytest.approx(5.5)
    assert float(tags["EXIF FocalPlaneXResolution"].values[0]) == pytest.approx(266.666667, rel=1e-9)
    assert tags["EXIF FocalPlaneResolutionUnit"].values == [4]
    assert tags["EXIF FocalLengthIn35mmFilm"].values == [40]
    assert "EXIF ExposureTime" not in tags and "EXIF ISOSpeed" not in tags and "Image BlackLevel" not in tags
    assert "already reflectance" in tags["Image ImageDescription"].values
    (xt,) = _odm_xmp(p)
    assert _odm_get_xmp_tag(xt, ["Camera:BandName"]) == "Red edge"
    assert _odm_get_xmp_tag(xt, ["@drone-dji:CaptureUUID", "MicaSense:CaptureId", "@Camera:ImageUniqueID",
                                 "@Camera:CaptureUUID"]) == "g2R43Qr5m7EeTFGbkh1W"
    assert _odm_get_xmp_tag(xt, ["@Camera:ModelType", "Camera:ModelType"]) == "perspective"
    assert xt["Camera:RigName"] == "RedEdge" and xt["Camera:PrincipalPoint"] == "2.4354,1.79714"
    assert xt["Camera:PerspectiveFocalLength"] == "1441.1993107495564"
    assert float(xt["Camera:HorizontalIrradiance"]) == pytest.approx(np.pi, rel=1e-15)
    assert "MicaSense:RadiometricCalibration" not in xt and "Camera:Irradiance" not in xt
    assert xt["@mscal:Quantity"] == "reflectance" and float(xt["@mscal:ReflectanceScale"]) == 1 / 32768
    assert xt["@mscal:NoData"] == "65535"


def test_file_band_names_have_no_spaces() -> None:
    assert [writers.file_band_name(n) for n in ("Red edge", "NIR", "b670", "Red edge-705", "near infra red")] == [
        "RedEdge", "NIR", "b670", "RedEdge705", "nearInfraRed"]
    with pytest.raises(CatalogError, match="file name"):
        writers.file_band_name(" - ")
