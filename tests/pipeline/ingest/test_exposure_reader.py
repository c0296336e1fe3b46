"""One reader of a band file's exposure and gain for calibrate and apply. A DJI P4
Multispectral file says ISO 200 in its EXIF and SensorGain 1 in its XMP (as real P4M files
do): DJI's radiometric model takes SensorGain, so a field calibration must too, or its t is
twice apply's."""

from __future__ import annotations

import struct
from pathlib import Path

import exifread
import numpy as np
import pytest
import tifffile

from pipeline.apply.captures import find_captures
from pipeline.apply.executor import band_exposures
from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.captures import band_file_record, exif_band_record, read_capture_table
from pipeline.ingest.catalog import load_camera
from tests import camera_files as cf
from tests.micasense_data import require_data

ISO_SPEED = 34867  # EXIF ISOSpeed (LONG), what the RedEdge files the builders start from carry


def set_iso(path: Path, iso: int) -> None:
    """Rewrite the EXIF ISOSpeed of a TIFF in place."""
    with tifffile.TiffFile(path) as tif:
        assert tif.byteorder == "<" and not tif.is_bigtiff
        entry = tif.pages[0].tags[34665].offset
    with path.open("r+b") as fh:
        fh.seek(entry + 8)
        (ifd,) = struct.unpack("<I", fh.read(4))
        fh.seek(ifd)
        (n,) = struct.unpack("<H", fh.read(2))
        for k in range(n):
            fh.seek(ifd + 2 + 12 * k)
            tag, kind, count = struct.unpack("<HHI", fh.read(8))
            if tag == ISO_SPEED:
                assert kind == 4 and count == 1
                fh.write(struct.pack("<I", iso))
                return
    raise AssertionError(f"{path} has no EXIF ISOSpeed")


@pytest.fixture()
def p4m(tmp_path: Path) -> Path:
    require_data()
    folder = cf.dji_p4m(tmp_path / "p4m")
    for p in sorted(folder.glob("DJI_*.TIF")):
        set_iso(p, 200)
    return folder


def test_dji_band_file_exposure_is_apply_s(p4m: Path) -> None:
    path = p4m / "DJI_0011.TIF"
    with path.open("rb") as fh:
        assert str(exifread.process_file(fh, details=False)["EXIF ISOSpeed"]) == "200"
    meta = read_file_metas(path)[0]
    assert (meta.exposure_s, meta.gain) == (pytest.approx(472.5e-6), 1.0)  # XMP ExposureTime 472.5 us, SensorGain 1
    rec = band_file_record(path)
    assert rec.effective_exposure == pytest.approx(0.4725, rel=1e-12)
    assert rec.effective_exposure == pytest.approx(meta.exposure_s * 1e3 * meta.gain, rel=1e-12)
    assert exif_band_record(path).effective_exposure == pytest.approx(0.945, rel=1e-12)  # ISO 200: twice


def test_calibration_and_apply_see_one_exposure_per_band(p4m: Path) -> None:
    camera = load_camera("dji-p4-multispectral")
    records = read_capture_table(p4m, camera)
    captures = find_captures(p4m, camera).captures
    assert [r.capture for r in records] == [c.name for c in captures] == ["001", "002"]
    for rec, cap in zip(records, captures):
        calib_t = np.array([rec.band_exposure(b) for b in range(camera.n_bands)])
        np.testing.assert_allclose(calib_t, band_exposures(cap), rtol=1e-12)
        np.testing.assert_allclose(calib_t, 0.4725, rtol=1e-12)


def test_files_without_factory_metadata_keep_the_exif_rule(tmp_path: Path) -> None:
    """The real RedEdge files with their XMP radiometric calibration removed: apply cannot read
    them; calibration reads EXIF ExposureTime x ISOSpeed / 100 as before."""
    require_data()
    path = cf.rewrite(cf.band_file("0000", 1), tmp_path / "IMG_0000_1.tif",
                      lambda x: cf.drop_element(x, "MicaSense:RadiometricCalibration"))
    set_iso(path, 400)
    rec = band_file_record(path)
    assert rec.exposure_ms == pytest.approx(189 / 400, rel=1e-12) and rec.gain == 4.0
