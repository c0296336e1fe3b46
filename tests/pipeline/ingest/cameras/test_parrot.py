"""Parrot Sequoia band files (pipeline.ingest.cameras.parrot): the reader, the sunshine sensor and the
position from the capture's RGB JPEG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mscal_core.vendors import sunshine_irradiance
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.meta import no_reflectance_reason
from tests import camera_files as cf

DATA_ROOT = Path(__file__).parents[4].parent / "shared" / "data"


def test_sequoia_reader() -> None:
    path = DATA_ROOT / "parrot-sequoia" / "IMG_180413_080658_0000_NIR.TIF"
    if not path.is_file():
        pytest.skip("no Sequoia sample")
    m = read_capture_meta(path)
    assert (m.make, m.model, m.radiometry, m.band_name, m.wavelength_nm) == ("Parrot", "Sequoia", "sequoia", "NIR", 790)
    assert m.maker_tag("sensor_model") == (271665.8, 5008.3, 2581.1)  # one rdf:li of three comma-separated numbers
    assert m.iso == 621 and m.exposure_s == pytest.approx(0.003, rel=1e-6) and m.f_number == pytest.approx(2.2, rel=1e-6)
    assert m.orientation == 3 and m.rig_camera_index == 3 and m.capture_id == "BE5AB0ABA969E1CB424A394AA2FD3208"
    assert len(m.vignetting_polynomial_2d) == 15 and len(m.vignetting_polynomial_2d_exponents) == 30
    # sunshine: 10 records CH0 = 14 at gain index 1, 100 ms; golden CH0 sensitivity 656.1082
    assert m.irradiance == pytest.approx(14 / 100 / 656.1082, rel=1e-9)
    assert m.lat is None and m.features()["position"] is False


def test_sequoia_without_golden_sensitivities_has_radiance_but_no_sun_sensor_reading(tmp_path) -> None:
    """Firmware that wrote no Camera:IrradianceSensitivitiesGolden: the radiance model is the
    same, the sunshine reading is none (the bands' readings cannot be put on one scale) and
    the reason names the tag; the intact file keeps its reading."""
    if not cf.SEQUOIA.is_dir():
        pytest.skip("no Sequoia sample")
    folder = cf.sequoia_without_golden(tmp_path / "old")
    name = "IMG_180413_080658_0000_NIR.TIF"
    m, intact = read_capture_meta(folder / name), read_capture_meta(cf.SEQUOIA / name)
    assert m.maker_tag("sensor_model") == intact.maker_tag("sensor_model") == (271665.8, 5008.3, 2581.1)
    dn = np.full(m.shape, 20000, np.uint16)
    np.testing.assert_array_equal(factory_radiance(m, dn), factory_radiance(intact, dn))
    assert m.irradiance is None and intact.irradiance == pytest.approx(14 / 100 / 656.1082, rel=1e-9)
    (problem,) = m.problems
    assert (problem.tag, problem.value, problem.feature) == ("XMP IrradianceSensitivitiesGolden", "(missing)", "sun_sensor")
    assert problem.file == str(folder / name)
    why = no_reflectance_reason(m)
    assert why.startswith("XMP IrradianceSensitivitiesGolden = '(missing)': not in the file") and "one scale" in why
    assert no_reflectance_reason(intact) is None and m.features()["sun_sensor_reading"] is False


def test_sunshine_gain_from_calibration_table() -> None:
    # table: gain index 1 reads 737 counts in 600 ms, index 2 reads 12340 (16.7x the gain)
    cal = {1: 737 / 600, 2: 12340 / 600}
    e1 = sunshine_irradiance([100], [1], [100], cal)
    e2 = sunshine_irradiance([100 * 12340 / 737], [2], [100], cal)
    assert e1 == pytest.approx(1.0) and e2 == pytest.approx(1.0)
    with pytest.raises(ValueError):
        sunshine_irradiance([65535], [1], [100], cal)


def _sequoia_with_rgb(folder: Path, gps: dict | None) -> Path:
    """The real Sequoia capture (its TIFFs: GPSStatus V, no position) and beside it the
    capture's ``_RGB.JPG`` with ``gps`` (PIL's GPS IFD keys) or without a GPS IFD."""
    from PIL import Image

    src = DATA_ROOT / "parrot-sequoia"
    if not src.is_dir():
        pytest.skip("no Sequoia sample")
    folder.mkdir(parents=True)
    for p in src.glob("*.TIF"):
        (folder / p.name).write_bytes(p.read_bytes())
    ex = Image.Exif()
    ex[0x010F], ex[0x0110] = "Parrot", "Sequoia"
    if gps is not None:
        ex.get_ifd(0x8825).update(gps)
    Image.new("RGB", (64, 48), (120, 130, 140)).save(folder / "IMG_180413_080658_0000_RGB.JPG", exif=ex)
    return folder


def test_sequoia_position_from_the_captures_rgb_jpeg(tmp_path) -> None:
    """Sequoia writes GPS only into the capture's RGB JPEG (OpenDroneMap contrib/sequoia): the
    band files, which have none, take its position; without a fix there, they stay unplaced."""
    from pipeline.ingest.grouping import group_captures

    camera = catalog.load_camera("parrot-sequoia")
    folder = _sequoia_with_rgb(tmp_path / "a", {1: "S", 2: (47.0, 30.0, 0.0), 3: "W", 4: (7.0, 36.0, 0.0), 5: 0, 6: 420.0})
    caps, problems = group_captures(folder, camera)
    assert problems == [] and len(caps) == 1 and len(caps[0].metas) == 4
    assert [(m.lat, m.lon, m.alt_m) for m in caps[0].metas] == [(pytest.approx(-47.5), pytest.approx(-7.6), 420.0)] * 4
    caps, _ = group_captures(_sequoia_with_rgb(tmp_path / "b", None), camera)
    assert all(m.lat is None and m.lon is None for m in caps[0].metas)
