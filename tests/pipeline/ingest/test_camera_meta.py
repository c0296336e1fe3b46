"""pipeline.ingest.camera_meta on real MicaSense RedEdge files: the values MicaSense's README lists,
the XMP forms (attributes, elements, rdf:Seq), and bad metadata named, never defaulted."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

from mscal_core.errors import FrameError
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import meta_from_tags, read_capture_meta, xmp_properties
from pipeline.ingest.grouping import group_captures
from pipeline.ingest.session import read_bands
from pipeline.ingest.tiff import read_raw
from pipeline.products.writers import build_xmp
from tests.micasense_data import BANDS, FWHM_NM, WAVELENGTHS_NM, band_file


def test_img_0000_1_matches_the_readme() -> None:
    m = read_capture_meta(band_file("0000", 1))
    assert m.shape == (960, 1280) and m.bits_per_sample == 16
    assert m.exposure_s == pytest.approx(0.0004725, rel=1e-9)
    assert m.gain == 1.0
    assert m.black_level == 4800.0
    assert m.dark_row_values == (5092.0, 5082.0, 5049.0, 5063.0)
    assert m.vignetting_center == pytest.approx((676.703, 480.445), abs=1e-3)
    expected_poly = [-3.18819e-05, 1.13807e-07, -2.77768e-09, 9.98118e-12, -1.47039e-14, 7.33410e-18]
    assert m.vignetting_polynomial == pytest.approx(expected_poly, rel=1e-5)
    assert m.radiometric_calibration == pytest.approx((1.4648541e-4, 1.1794107e-7, 1.3974331e-6), rel=1e-6)
    assert (m.lat, m.lon, m.alt_m) == pytest.approx((36.576096, -119.4352689, 101.861), abs=1e-6)
    assert m.time == "2017-10-19T20:40:39.200173789"
    assert m.capture_id == "5v25BtsZg3BQBhVH7Iaz" and m.rig_camera_index == 0
    assert m.irradiance == pytest.approx(1.0848248, rel=1e-6)
    assert m.vignetting_polynomial_2d is None and m.reflect_area is None


@pytest.mark.parametrize("capture", ["0000", "0001"])
def test_band_names_and_wavelengths_of_all_five_bands(capture: str) -> None:
    metas = [read_capture_meta(band_file(capture, b)) for b in range(1, 6)]
    assert tuple(m.band_name for m in metas) == BANDS
    assert tuple(m.wavelength_nm for m in metas) == WAVELENGTHS_NM
    assert tuple(m.fwhm_nm for m in metas) == FWHM_NM
    assert [m.rig_camera_index for m in metas] == [0, 1, 2, 3, 4]
    assert len({m.capture_id for m in metas}) == 1


def test_flight_capture_gain_from_iso() -> None:
    # IMG_0001 bands 3 and 5 were taken at ISO 200
    gains = [read_capture_meta(band_file("0001", b)).gain for b in range(1, 6)]
    assert gains == [1.0, 1.0, 2.0, 1.0, 2.0]


def test_catalog_agrees_with_the_files() -> None:
    cam = catalog.load_camera("micasense-rededge")
    assert cam.bit_depth == 12 and cam.sensor == (960, 1280)
    for band in cam.bands:
        m = read_capture_meta(band_file("0000", int(band.file_suffix)))
        assert (band.name, band.wavelength_nm, band.fwhm_nm) == (m.band_name, m.wavelength_nm, m.fwhm_nm)
        assert m.bits_per_sample == 16 and m.shape == cam.sensor


def test_read_bands_gives_12_bit_dn() -> None:
    cam = catalog.load_camera("micasense-rededge")
    path = band_file("0000", 2)
    raw = read_raw(path)
    bands = read_bands(path, cam)
    assert bands.shape == (1, 960, 1280) and bands.dtype == np.uint16
    assert int(raw.max()) == 65520 and int(bands.max()) == 4095  # saturated green: 0xFFF0 >> 4
    np.testing.assert_array_equal(bands[0].astype(np.uint32) * 16, raw)


def test_xmp_attribute_and_element_forms() -> None:
    packet = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description xmlns:Camera="http://pix4d.com/camera/1.0/" xmlns:MicaSense="http://micasense.com/MicaSense/1.0/"'
        ' xmlns:Other="http://example.com/other/" Camera:BandName="NIR" Camera:ReflectArea="10,20,30,40"'
        ' Other:BandName="not this one">'
        "<MicaSense:RadiometricCalibration><rdf:Seq><rdf:li>1e-4</rdf:li><rdf:li>2e-7</rdf:li>"
        "<rdf:li>3e-6</rdf:li></rdf:Seq></MicaSense:RadiometricCalibration>"
        "<Camera:CentralWavelength>842</Camera:CentralWavelength>"
        "</rdf:Description></rdf:RDF></x:xmpmeta>"
    )
    props = xmp_properties(packet, "x.tif")
    assert props["BandName"] == "NIR"
    assert props["ReflectArea"] == "10,20,30,40"
    assert props["RadiometricCalibration"] == ["1e-4", "2e-7", "3e-6"]
    assert props["CentralWavelength"] == "842"
    # the packets mscal itself writes read back (one-item rdf:Seq band name)
    ours = xmp_properties(build_xmp(band_name="Red", capture_uuid="abc", wavelength_nm=668), "y.tif")
    assert ours["BandName"] == ["Red"] and ours["CentralWavelength"] == ["668"]


def _strip_tag(xmp: bytes, tag: str) -> bytes:
    """The XMP packet without the element ``<MicaSense:tag>...</MicaSense:tag>``, same length."""
    start = xmp.index(f"<MicaSense:{tag}>".encode())
    close = f"</MicaSense:{tag}>".encode()
    end = xmp.index(close) + len(close)
    return xmp[:start] + b" " * (end - start) + xmp[end:]


def test_missing_radiometric_calibration_names_file_and_tag(tmp_path: Path) -> None:
    src = band_file("0000", 1)
    bad = tmp_path / "IMG_0000_1.tif"
    shutil.copyfile(src, bad)
    bad.chmod(0o644)
    with tifffile.TiffFile(bad, mode="r+b") as tif:
        tag = tif.pages[0].tags[700]
        tag.overwrite(_strip_tag(tag.value, "RadiometricCalibration"))
    np.testing.assert_array_equal(tifffile.imread(bad), tifffile.imread(src))  # pixels kept
    with pytest.raises(FrameError) as err:
        read_capture_meta(bad)
    assert str(bad) in str(err.value) and "RadiometricCalibration" in str(err.value)
    assert "firmware" in str(err.value)


def _tags_of(path: Path) -> dict[int, object]:
    with tifffile.TiffFile(path) as tif:
        return {t.code: t.value for t in tif.pages[0].tags.values()}


def test_exposure_in_wrong_units_is_named() -> None:
    path = band_file("0000", 1)
    tags = _tags_of(path)
    tags[34665] = {**tags[34665], "ExposureTime": (4725, 10)}  # 472.5 "s": ms written as s
    with pytest.raises(FrameError, match="ExposureTime 472.5 s"):
        meta_from_tags(path, tags, (960, 1280), 16)


def test_wavelength_in_wrong_units_is_named() -> None:
    path = band_file("0000", 1)
    tags = _tags_of(path)
    tags[700] = tags[700].replace(b"<Camera:CentralWavelength>475<", b"<Camera:CentralWavelength>0.475<")
    with pytest.raises(FrameError, match="CentralWavelength 0.475 is outside 300-1100 nm") as err:
        meta_from_tags(path, tags, (960, 1280), 16)
    assert str(path) in str(err.value)


def test_missing_vignetting_and_black_level_are_named() -> None:
    path = band_file("0000", 1)
    tags = _tags_of(path)
    tags[700] = tags[700].replace(b"Camera:VignettingPolynomial>", b"Camera:VignettingPolynomiaX>")
    with pytest.raises(FrameError, match="no vignetting model"):
        meta_from_tags(path, tags, (960, 1280), 16)
    tags = _tags_of(path)
    del tags[50714]
    tags[700] = _strip_tag(tags[700], "DarkRowValue")
    with pytest.raises(FrameError, match="no EXIF BlackLevel and no XMP DarkRowValue"):
        meta_from_tags(path, tags, (960, 1280), 16)


def test_black_level_falls_back_to_dark_rows() -> None:
    path = band_file("0000", 1)
    tags = _tags_of(path)
    del tags[50714]
    m = meta_from_tags(path, tags, (960, 1280), 16)
    assert m.black_level == pytest.approx((5092 + 5082 + 5049 + 5063) / 4)


def test_group_captures_on_the_real_folder() -> None:
    cam = catalog.load_camera("micasense-rededge")
    captures, problems = group_captures(band_file("0000", 1).parent, cam)
    assert problems == []
    assert [c.name for c in captures] == ["IMG_0000", "IMG_0001"]
    assert [c.capture_id for c in captures] == ["5v25BtsZg3BQBhVH7Iaz", "g2R43Qr5m7EeTFGbkh1W"]
    assert [p.name for p in captures[1].files] == [f"IMG_0001_{b}.tif" for b in range(1, 6)]
    assert [m.band_name for m in captures[0].metas] == list(BANDS)
    # without a camera the suffixes seen in the folder are expected
    assert [c.files for c in group_captures(band_file("0000", 1).parent)[0]] == [c.files for c in captures]


def test_incomplete_capture_is_reported_not_grouped(tmp_path: Path) -> None:
    for b in range(1, 6):
        shutil.copyfile(band_file("0000", b), tmp_path / f"IMG_0000_{b}.tif")
        if b != 4:
            shutil.copyfile(band_file("0001", b), tmp_path / f"IMG_0001_{b}.tif")
    captures, problems = group_captures(tmp_path, catalog.load_camera("micasense-rededge"))
    assert [c.name for c in captures] == ["IMG_0000"]
    assert problems == [{"file": str(tmp_path / "IMG_0001_1.tif"), "reason": "capture IMG_0001: missing band file(s) 4 (NIR)"}]


def test_truncated_band_file_and_copied_capture_give_one_entry_each(tmp_path: Path) -> None:
    for b in range(1, 6):
        for src, dst in (("0000", "0000"), ("0001", "0001"), ("0000", "0003"), ("0001", "0007")):
            shutil.copyfile(band_file(src, b), tmp_path / f"IMG_{dst}_{b}.tif")
    blob = (tmp_path / "IMG_0003_2.tif").read_bytes()
    (tmp_path / "IMG_0003_2.tif").write_bytes(blob[: len(blob) // 3])  # the IFD is at the end: cut off
    captures, problems = group_captures(tmp_path, catalog.load_camera("micasense-rededge"))
    assert [c.name for c in captures] == ["IMG_0000", "IMG_0001"]
    assert [p["file"] for p in problems] == [str(tmp_path / "IMG_0003_2.tif"), str(tmp_path / "IMG_0007_1.tif")]
    assert problems[0]["reason"].startswith("capture IMG_0003: band file IMG_0003_2.tif: TIFF has no readable")
    assert problems[1]["reason"] == "capture IMG_0007: same XMP CaptureId as IMG_0001 (a copy of that capture?)"


def test_capture_of_another_camera_is_reported() -> None:
    folder = band_file("0000", 1).parent
    captures, problems = group_captures(folder, catalog.load_camera("micasense-rededge-mx-dual"))
    assert captures == [] and len(problems) == 2
    assert problems[0]["reason"] == ("capture IMG_0000: missing band file(s) 6 (Blue-444), 7 (Green-531), 8 (Red-650), "
                                     "9 (Red edge-705), 10 (Red edge-740)")
    rededge = catalog.load_camera("micasense-rededge")
    first = dataclasses.replace(rededge.bands[0], name="Coastal")
    swapped = dataclasses.replace(rededge, bands=(first, *rededge.bands[1:]))
    captures, problems = group_captures(folder, swapped)
    assert captures == []
    assert problems[0]["reason"] == (
        "capture IMG_0000: band names differ from camera micasense-rededge: _1 is 'Blue', catalog says 'Coastal'"
    )


@pytest.mark.parametrize("poly", [(-0.01,), (1e300, 1e300, 1e300)])
def test_damaged_vignetting_polynomial_names_the_file(poly) -> None:
    """A VignettingPolynomial whose denominator crosses zero (k1 = -0.01: 1 - 0.01 r < 0 past
    100 px) or overflows (found by the long fuzz profile: a silent map of zeros) is a
    FrameError naming the band file, not a map with negative or zero corrections."""
    from pipeline.ingest.meta import factory_vignetting

    meta = read_capture_meta(band_file("0001", 1))
    v = factory_vignetting(meta)
    assert np.all(np.isfinite(v)) and v.min() >= 1.0  # the real tags: a correction >= 1 everywhere
    bad = dataclasses.replace(meta, vignetting_polynomial=poly)
    with pytest.raises(FrameError, match="vignetting tags") as exc:
        factory_vignetting(bad)
    assert exc.value.path == str(meta.path)
