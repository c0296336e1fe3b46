"""MicaSense band files (pipeline.ingest.cameras.micasense): thermal and panchromatic bands, the DLS 2
irradiance and its scale, 12-bit files, the legacy RedEdge exposure."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.factory import thermal_kelvin
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance
from tests import camera_files as cf
from tests.micasense_data import require_data


def test_thermal_and_pan_bands_are_read_not_used(tmp_path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "apt", altum_pt=True)
    lwir = read_capture_meta(folder / "IMG_0000_7.tif")
    pan = read_capture_meta(folder / "IMG_0000_6.tif")
    assert (lwir.radiometry, lwir.shape, lwir.reflectance_band) == ("thermal", (120, 160), False)
    assert (pan.radiometry, pan.shape, pan.reflectance_band) == ("panchro", (1200, 1600), False)
    assert factory_radiance(lwir, np.full((120, 160), 29315, np.uint16))[0, 0] == pytest.approx(293.15)
    assert thermal_kelvin(np.array([27315]))[0] == pytest.approx(273.15)


def test_dls2_horizontal_irradiance_and_its_scale() -> None:
    """DLS 2 firmware: HorizontalIrradiance x IrradianceScaleToSIUnits (0.01 when the scale tag
    is missing, as micasense/imageprocessing metadata.py assumes)."""
    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    path = cf.band_file("0000", 2)
    tags = {}
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    x = tags[700].decode()
    x = cf.drop_element(x, "Camera:Irradiance")
    tags[700] = cf.add_camera_element(x, "<Camera:HorizontalIrradiance>123.0</Camera:HorizontalIrradiance>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(1.23)
    tags[700] = cf.add_camera_element(tags[700].decode(), "<Camera:IrradianceScaleToSIUnits>0.001</Camera:IrradianceScaleToSIUnits>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(0.123)


def test_dls2_legacy_irradiance_takes_the_files_scale() -> None:
    """DLS 2 firmware also writes the legacy ``Camera:Irradiance`` beside HorizontalIrradiance,
    in the same uW cm-2 nm-1 ("DLS2 irradiance units",
    https://github.com/micasense/imageprocessing/issues/47): it is scaled like the other
    irradiance tags of the file (0.01 without IrradianceScaleToSIUnits), not read as W m-2 nm-1.
    A DLS 1 file (the sample: no HorizontalIrradiance) keeps its reading as it is."""
    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    path = cf.band_file("0000", 2)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    dls1 = meta_from_tags(path, tags, (960, 1280), 16).irradiance
    x = cf.drop_element(tags[700].decode(), "Camera:Irradiance")
    x = cf.add_camera_element(x, "<Camera:Irradiance>95.74</Camera:Irradiance>")
    x = cf.add_camera_element(x, "<Camera:HorizontalIrradiance>88.5</Camera:HorizontalIrradiance>")
    tags[700] = x.encode()
    m = meta_from_tags(path, tags, (960, 1280), 16)
    assert m.irradiance == pytest.approx(0.9574) and not m.problems
    tags[700] = cf.add_camera_element(x, "<Camera:IrradianceScaleToSIUnits>0.001</Camera:IrradianceScaleToSIUnits>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(0.09574)
    tags[700] = cf.add_camera_element(x, "<Camera:IrradianceScaleToSIUnits>-1</Camera:IrradianceScaleToSIUnits>").encode()
    bad = meta_from_tags(path, tags, (960, 1280), 16)
    assert bad.irradiance is None and any("IrradianceScaleToSIUnits" in str(p) for p in bad.problems)
    assert 0.5 < dls1 < 2.0  # the sample's DLS 1 reading, W m-2 nm-1, unscaled


def test_rededge_12bit_band_file_is_read_and_clips_at_4095(tmp_path) -> None:
    """A RedEdge band file saved as a packed 12-bit TIFF (BitsPerSample 12, uncompressed; MicaSense's
    "12-bit or 16-bit format") decodes to the sensor's DN, the 16-bit file's >> 4; its factory
    radiance is the 16-bit file's wherever neither is clipped, and it clips at 4095 (its own
    depth's top), the 16-bit file at the catalog's 65520."""
    from pipeline.apply.factory import camera_clip_dn
    from pipeline.ingest.tiff import decode_frame, read_raw

    require_data()
    src = cf.band_file("0001", 1)
    dst = cf.rededge_12bit(src, tmp_path / "IMG_0001_1.tif")
    m16, m12 = read_capture_meta(src), read_capture_meta(dst)
    assert (m16.bits_per_sample, m12.bits_per_sample) == (16, 12)
    assert (m16.black_level, m12.black_level) == (4800.0, 300.0)
    assert decode_frame(dst.read_bytes(), dst)[1] == 12  # the BitsPerSample from the decode's own parse
    dn16, dn12 = read_raw(src), read_raw(dst)
    assert dn12.dtype == np.uint16 and int(dn12.max()) == 4095
    np.testing.assert_array_equal(dn12, dn16 >> 4)
    sat = camera_clip_dn(catalog.load_camera("micasense-rededge"))
    assert (sat, m16.clipped_from(sat), m12.clipped_from(sat)) == (65520, 65520, 4095)
    clipped16, clipped12 = dn16 >= m16.clipped_from(sat), dn12 >= m12.clipped_from(sat)
    assert int(clipped12.sum()) == int(clipped16.sum()) == 1829  # IMG_0001 Blue: sky glint
    np.testing.assert_array_equal(clipped12, clipped16)
    r16, r12 = factory_radiance(m16, dn16), factory_radiance(m12, dn12)
    np.testing.assert_allclose(r12[~clipped12], r16[~clipped16], rtol=1e-12, atol=0)
    assert float(np.median(r12[~clipped12])) == pytest.approx(float(np.median(r16[~clipped16])), rel=1e-12)


def test_legacy_rededge_exposure_is_corrected_as_micasense_does() -> None:
    """Some legacy RedEdge firmware wrote ExposureTime 1/6329 s for an exposure of 0.274 ms
    (micasense/imageprocessing metadata.py ``exposure()``, every model but Altum): radiance
    would be 1.73x too high. Other exposures, and Altum's 1/6329 s, are kept."""
    from pipeline.ingest.camera_meta import meta_from_tags
    from pipeline.ingest.cameras.micasense import micasense_exposure

    require_data()
    path = cf.band_file("0000", 2)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    exif = dict(tags[34665])
    own = meta_from_tags(path, tags, (960, 1280), 16).exposure_s
    assert own != pytest.approx(0.000274, abs=1e-6)
    exif["ExposureTime"] = (1, 6329)
    tags[34665] = exif
    assert meta_from_tags(path, tags, (960, 1280), 16).exposure_s == 0.000274
    assert micasense_exposure(1 / 6329, "Altum") == pytest.approx(1 / 6329)
    assert micasense_exposure(1 / 6000, "RedEdge") == pytest.approx(1 / 6000)


def test_rededge_12bit_files_reach_the_field_fits_in_sensor_dn(tmp_path) -> None:
    """Calibration's reads (read_bands, stored_bands from bytes, as ingest reads them) shift each
    band file by what it stores: a 16-bit RedEdge file by the catalog's 4, a packed 12-bit one
    not at all; both give the same sensor DN. Shifting the 12-bit file by 4 too (the catalog's
    shift for every file) gave DN / 16, silently: a 4095 highlight became 255."""
    from pipeline.ingest.session import FrameRecord, read_bands, stored_bands
    from pipeline.ingest.tiff import sample_bits

    require_data()
    cam = catalog.load_camera("micasense-rededge")
    assert (cam.shift_for(None), cam.shift_for(16), cam.shift_for(12), cam.shift_for(14)) == (4, 4, 0, 2)
    assert catalog.load_camera("generic-rgb8").shift_for(16) == 0
    src16 = [cf.band_file("0001", b) for b in range(1, 6)]
    src12 = [cf.rededge_12bit(p, tmp_path / p.name) for p in src16]
    assert [sample_bits(p) for p in (src16[0], src12[0])] == [16, 12]
    assert sample_bits(src12[0].read_bytes()) == 12 and sample_bits(b"\xff\xd8\xff\xe0") is None
    rec16, rec12 = (FrameRecord(path=f[0], exposure_ms=1.0, band_files=tuple(f), capture="IMG_0001")
                    for f in (src16, src12))
    b16, b12 = read_bands(rec16, cam), read_bands(rec12, cam)
    assert b12.shape == (5, 960, 1280) and int(b12.max()) == 4095
    np.testing.assert_array_equal(b12, b16)
    for p16, p12 in zip(src16, src12):
        np.testing.assert_array_equal(stored_bands(p12.read_bytes(), p12, cam), stored_bands(p16.read_bytes(), p16, cam))
    mixed = FrameRecord(path=src12[0], exposure_ms=1.0, band_files=(src12[0], *src16[1:]), capture="IMG_0001")
    np.testing.assert_array_equal(read_bands(mixed, cam), b16)
