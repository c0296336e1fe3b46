"""The sun sensor's tags per vendor (issue 22): orientation from the sensor's own IMU, else the
aircraft's; DLS 2's measured split; no sun position without time or GPS."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.apply.captures import capture_times, find_captures
from pipeline.apply.sunlight import (
    RATIO_DRIFT_WARN,
    PanelSensorLight,
    file_xmp,
    light_warnings,
    sensor_light,
    sensor_orientation,
)
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.xmp import Xmp
from tests.micasense_data import require_data

SHARED = Path(__file__).parents[3].parent / "shared" / "data"


def _xmp(body: str) -> Xmp:
    packet = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              '<rdf:Description rdf:about="" xmlns:Camera="http://pix4d.com/camera/1.0/" '
              'xmlns:DLS="http://micasense.com/DLS/1.0/" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
              f'{body}/></rdf:RDF></x:xmpmeta>')
    return Xmp.parse(packet.encode(), "t.tif")


@pytest.mark.parametrize("body, source, ypr_deg", [
    ('DLS:Yaw="0.5" DLS:Pitch="-0.1" DLS:Roll="0.05" Camera:Yaw="10" Camera:Pitch="1" Camera:Roll="2"',
     "DLS:Yaw/Pitch/Roll", (math.degrees(0.5), math.degrees(-0.1), math.degrees(0.05))),
    ('Camera:IrradianceYaw="30" Camera:IrradiancePitch="-4" Camera:IrradianceRoll="2"',
     "Camera:IrradianceYaw/Pitch/Roll", (30.0, -4.0, 2.0)),
    ('drone-dji:FlightYawDegree="-120.5" drone-dji:FlightPitchDegree="3.5" drone-dji:FlightRollDegree="-1.25"',
     "drone-dji:FlightYaw/Pitch/RollDegree", (-120.5, 3.5, -1.25)),
    ('Camera:Yaw="89.9" Camera:Pitch="18.7" Camera:Roll="45.4"', "Camera:Yaw/Pitch/Roll", (89.9, 18.7, 45.4)),
])
def test_orientation_from_the_sensor_first_then_the_aircraft(body, source, ypr_deg) -> None:
    o = sensor_orientation(_xmp(body))
    assert o is not None and o.source == source
    np.testing.assert_allclose(np.degrees([o.yaw, o.pitch, o.roll]), ypr_deg, atol=1e-9)
    assert sensor_orientation(_xmp('Camera:BandName="Red"')) is None


def test_real_sequoia_and_sentera_orientations() -> None:
    seq = SHARED / "parrot-sequoia" / "IMG_180413_080658_0000_NIR.TIF"
    sen = SHARED / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if not (seq.is_file() and sen.is_file()):
        pytest.skip("Sequoia/Sentera sample files not found")
    o = sensor_orientation(file_xmp(seq))
    assert o is not None and o.source == "Camera:IrradianceList (sunshine sensor)"
    assert max(abs(o.pitch), abs(o.roll)) < math.radians(45)  # the sunshine sensor's own IMU, near level
    s = sensor_orientation(file_xmp(sen))
    assert s is not None and s.source == "Camera:Yaw/Pitch/Roll"
    np.testing.assert_allclose(np.degrees([s.yaw, s.pitch, s.roll]), [89.9572, 18.7449, 45.4569], atol=1e-3)


def test_sequoia_without_gps_keeps_the_raw_reading() -> None:
    folder = SHARED / "parrot-sequoia"
    if not folder.is_dir():
        pytest.skip("Sequoia sample not found")
    caps = find_captures(folder, identify_camera(folder, None).camera).captures
    light = sensor_light(caps, capture_times(caps))
    assert light.model[0].startswith("raw reading (no sun position")
    np.testing.assert_array_equal(light.correction[np.isfinite(light.correction)], 1.0)
    assert np.isfinite(light.factor).all()


def test_real_rededge_sensor_geometry() -> None:
    """IMG_0000 (panel, hand-held) and IMG_0001 (flight) of 2017-10-19 20:40 UTC at 36.58 N:
    the sun 41.2 deg high (pvlib SPA); the DLS tilted 10.8 and 1.6 deg (its DLS:Pitch/Roll)."""
    folder = require_data()
    caps = find_captures(folder, identify_camera(folder, None).camera).captures
    light = sensor_light(caps, capture_times(caps))
    np.testing.assert_allclose(light.elevation_deg, [41.216, 41.115], atol=0.01)
    np.testing.assert_allclose(light.tilt_deg, [10.806, 1.632], atol=0.01)
    assert light.model[0] == "tilt model, clear-sky diffuse ratio 1/6; orientation DLS:Yaw/Pitch/Roll"
    # E_h = k-scale / factor: pi / factor is the horizontal irradiance in W m-2 nm-1
    raw = np.array([[m.irradiance for m in c.metas] for c in caps])
    np.testing.assert_allclose(math.pi / light.factor, raw * light.correction, rtol=1e-12)


def test_warnings_carry_numbers_and_thresholds() -> None:
    light = PanelSensorLight(factor=np.ones((3, 2)), sensor_used=np.ones((3, 2), bool), ratio=np.ones((3, 2)),
                             drift=np.array([0.01, 0.08]))
    warns = light_warnings(["A", "B", "C"], ["Red", "NIR"], None, light, ["A", "C"])
    assert [(w["code"], w["band"], w["value"], w["threshold"]) for w in warns] == [
        ("panel_sensor_disagree", "NIR", 0.08, RATIO_DRIFT_WARN)]
    assert "8.0%" in warns[0]["message"]
    assert light_warnings(["A"], ["Red", "NIR"], None, light, ["A"]) == []  # one panel: nothing to disagree


def test_report_shows_the_light_and_its_warnings() -> None:
    from pipeline.products.report.sections import light_tables
    from pipeline.products.report.sections import light_warnings as report_warnings

    run = {"light": {
        "route": "panel-dls", "irradiance_unit": "W m-2 nm-1 (pi / k)",
        "panels_over_time": [{"capture": "A", "panel_irradiance": {"NIR": 0.5, "Red": 0.8},
                              "sensor_irradiance": {"NIR": 0.4, "Red": 1.0}}],
        "panel_sensor_drift": {"NIR": 0.08, "Red": 0.0},
        "frame_irradiance": {"A": {"NIR": 0.5, "Red": 0.8}, "B": {"NIR": 0.45, "Red": 0.7}},
        "sensor_used": {"A": True, "B": True},
        "warnings": [{"code": "panel_sensor_disagree", "band": "NIR", "value": 0.08, "threshold": 0.03,
                      "message": "NIR: disagree by 8.0%"}]}}
    over, frames = light_tables(run, ["Red", "NIR"])
    assert over.rows == [["A", "Red", 0.8, 1.0, 0.8], ["A", "NIR", 0.5, 0.4, 1.25]]
    assert "NIR 8.0%" in over.note
    assert frames.columns == ["frame", "Red", "NIR", "sun sensor used"] and frames.rows[1] == ["B", 0.7, 0.45, True]
    (w,) = report_warnings(run)
    assert (w.code, w.value, w.threshold) == ("panel_sensor_disagree", 0.08, 0.03)
    assert light_tables({}, []) == [] and report_warnings({}) == []


def test_panel_dls_without_readings_exits_2(tmp_path, capsys) -> None:
    from pipeline.run.cli import main
    from tests.camera_files import band_file, drop_element, rewrite

    require_data()
    folder = tmp_path / "noirr"
    folder.mkdir()
    for cap in ("0000", "0001"):
        for b in range(1, 6):
            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif",
                    lambda x: drop_element(drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance"))
    args = ["apply", str(folder), "--calibration", "factory", "--panel-reflectance", "micasense-rp02-1603036-sc"]
    assert main([*args, "-o", str(tmp_path / "o"), "--reference", "panel-dls"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--reference panel-dls: no capture in the folder has a sun-sensor reading" in err and "\n" not in err
    assert main([*args, "-o", str(tmp_path / "auto")]) == 0  # auto: the panel alone
    import json

    assert json.loads((tmp_path / "auto" / "run.json").read_text())["reference"]["route"] == "panel"
