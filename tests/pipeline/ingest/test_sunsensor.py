"""The sun sensor's tags per vendor: orientation from the sensor's own IMU, else the
aircraft's; DLS 2's measured split; no sun position without time or GPS; and the one sun-sensor
level of a frame or capture that calibrate and apply share."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.ingest.grouping import group_captures
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.sunsensor import capture_time, file_xmp, sensor_light, sensor_orientation
from pipeline.ingest.xmp import Xmp
from tests.micasense_data import require_data

SHARED = Path(__file__).parents[3].parent / "shared" / "data"


def _times(caps) -> np.ndarray:
    return np.array([capture_time(c) for c in caps], dtype="datetime64[ns]")


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
    caps = group_captures(folder, identify_camera(folder, None).camera)[0]
    light = sensor_light(caps, _times(caps))
    assert light.model[0].startswith("raw reading (no sun position")
    np.testing.assert_array_equal(light.correction[np.isfinite(light.correction)], 1.0)
    assert np.isfinite(light.factor).all()


def test_real_rededge_sensor_geometry() -> None:
    """IMG_0000 (panel, hand-held) and IMG_0001 (flight) of 2017-10-19 20:40 UTC at 36.58 N:
    the sun 41.2 deg high (pvlib SPA); the DLS tilted 10.8 and 1.6 deg (its DLS:Pitch/Roll)."""
    folder = require_data()
    caps = group_captures(folder, identify_camera(folder, None).camera)[0]
    light = sensor_light(caps, _times(caps))
    np.testing.assert_allclose(light.elevation_deg, [41.216, 41.115], atol=0.01)
    np.testing.assert_allclose(light.tilt_deg, [10.806, 1.632], atol=0.01)
    assert light.model[0] == "tilt model, clear-sky diffuse ratio 1/6; orientation DLS:Yaw/Pitch/Roll"
    # E_h = k-scale / factor: pi / factor is the horizontal irradiance in W m-2 nm-1
    raw = np.array([[m.irradiance for m in c.metas] for c in caps])
    np.testing.assert_allclose(math.pi / light.factor, raw * light.correction, rtol=1e-12)


def test_frames_csv_irradiance_wins_and_unknown_files_stay_raw(tmp_path) -> None:
    """Field-path levels of frame records: frames.csv ``irradiance`` as given (no orientation
    known), a TIFF whose tags are no camera's the factory reader knows: its raw XMP Irradiance,
    a RedEdge capture: the horizontal level (geometric mean of the bands' ``E_meas f``)."""
    import tifffile

    from pipeline.ingest.captures import read_capture_table
    from pipeline.ingest.catalog import load_camera
    from pipeline.ingest.grouping import group_captures
    from pipeline.ingest.session import FrameRecord
    from pipeline.ingest.sunsensor import capture_levels, record_levels

    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, np.zeros((4, 4), np.uint16), extratags=[(700, "B", 0, (
        b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        b'<rdf:Description xmlns:Camera="http://pix4d.com/camera/1.0/" Camera:Irradiance="2.5"/>'
        b"</rdf:RDF></x:xmpmeta>"), True)])
    camera = load_camera("micasense-rededge")
    rec = read_capture_table(require_data(), camera)[0]
    given = FrameRecord(path=rec.path, exposure_ms=1.0, irradiance=123.0, band_files=rec.band_files, capture="given")
    levels = record_levels([given, FrameRecord(path=plain, exposure_ms=1.0), rec])
    assert levels.value[:2].tolist() == [123.0, 2.5]
    assert levels.source[:2] == ("frames.csv irradiance (raw: orientation unknown)",
                                 "XMP Irradiance (raw: tags not a known camera's)")
    cap = group_captures(require_data(), camera)[0][0]
    light = sensor_light([cap], _times([cap]), fit_ratio=False)
    e_h = np.array([m.irradiance for m in cap.metas]) * light.correction[0]
    assert levels.value[2] == pytest.approx(float(np.exp(np.mean(np.log(e_h)))), rel=1e-12)
    assert levels.value[2] == capture_levels([cap]).value[0]
    np.testing.assert_allclose(light.correction[0], 0.8862, atol=1e-4)  # hand-held, tilted 10.8 deg


def test_dji_irradiance_is_used_as_the_camera_compensated_it() -> None:
    """DJI's drone-dji:Irradiance is the value "after compensation by built-in algorithm"
    (Mavic 3M User Manual; the P4 Multispectral guide's "calibrated sunlight sensor value",
    divided by with no angle term): no tilt model on top of it, whatever the aircraft's
    attitude, while a MicaSense DLS 1 reading at that attitude is corrected."""
    from pipeline.ingest.cameras.dji import DJI_COMPENSATED
    from pipeline.ingest.sunsensor import band_correction, camera_compensated

    el, az = math.radians(40.0), math.radians(150.0)
    dji = _xmp('drone-dji:Irradiance="1210.5" drone-dji:FlightYawDegree="180" drone-dji:FlightPitchDegree="15" '
               'drone-dji:FlightRollDegree="-4"')
    assert camera_compensated(dji)
    corr, tilt, inc, model = band_correction(dji, el, az, sensor_orientation(dji))
    assert (corr, model) == (1.0, DJI_COMPENSATED) and math.isnan(tilt) and math.isnan(inc)
    dls1 = _xmp('Camera:Irradiance="1.08" Camera:IrradianceYaw="180" Camera:IrradiancePitch="15" '
                'Camera:IrradianceRoll="-4"')
    assert not camera_compensated(dls1)
    assert not isinstance(band_correction(dls1, el, az, sensor_orientation(dls1)), tuple)  # the tilt model
