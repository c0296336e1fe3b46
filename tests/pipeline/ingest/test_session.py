"""Session folders: session.yaml, frames.csv and frame files; every bad input named."""

from pathlib import Path

import numpy as np
import pytest
import tifffile

from mscal_core.errors import FrameError, SessionError
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.session import exif_record, load_session, read_bands, read_frame_table

MICASENSE = Path(__file__).resolve().parents[4] / "shared" / "data" / "micasense-rededge"

SESSION_YAML = """\
camera: ximea-mq022hg-sm5x5-nir
intrinsics: {fx: 436.0, fy: 436.0, cx: 204.0, cy: 108.0, dist: [-0.1, 0.02, 0.0, 0.0, 0.0]}
reflector: {reflectance: 0.5, size_m: [0.5, 0.5]}
marker: {dictionary: DICT_4X4_50, id: 3, size_m: 0.10}
"""


def _session(tmp_path: Path, text: str = SESSION_YAML) -> Path:
    (tmp_path / "session.yaml").write_text(text)
    return tmp_path


def test_loads_spec_example(tmp_path) -> None:
    s = load_session(_session(tmp_path))
    assert s.camera.name == "ximea-mq022hg-sm5x5-nir"
    assert s.intrinsics.fx == 436.0 and s.intrinsics.dist[0] == -0.1
    assert s.reflector.size_m == (0.5, 0.5)
    assert s.reflector.reflectance.at(np.array([700.0]))[0] == 0.5
    assert s.marker.id == 3 and s.marker.border_m == pytest.approx(0.025)


def test_reflectance_table(tmp_path) -> None:
    text = SESSION_YAML.replace("reflectance: 0.5", "reflectance: [[600, 0.4], [900, 0.6]]")
    s = load_session(_session(tmp_path, text))
    assert s.reflector.reflectance.at(np.array([750.0]))[0] == pytest.approx(0.5)


@pytest.mark.parametrize(
    "text, error, message",
    [
        (None, SessionError, "session.yaml is missing"),
        ("camera: [unclosed", SessionError, "not valid YAML at line 1"),
        (SESSION_YAML.replace("ximea-mq022hg-sm5x5-nir", "nikon-d1"), SessionError, "unknown camera 'nikon-d1'"),
        # an unclosed bracket on line 3 is only noticed at line 4: both lines are named
        ("camera: x\nreflector:\n  reflectance: [0.5\n  size_m: 1\n", SessionError,
         "not valid YAML at line 3, column 16 (while parsing a flow sequence): expected ',' or ']', but got ':' "
         "at line 4, column 9"),
        (SESSION_YAML + "colour: red\n", SessionError, "unknown key(s) colour"),
        (SESSION_YAML.replace("fx: 436.0", "fx: -1"), SessionError, "intrinsics.fx must be positive"),
        (SESSION_YAML.replace("reflectance: 0.5", "reflectance: 5"), SessionError, "reflector.reflectance must be in (0, 1]"),
        (SESSION_YAML.replace("id: 3", "id: three"), SessionError, "marker.id must be a non-negative integer"),
        # unknown keys, with the allowed ones
        (SESSION_YAML + "colour: red\n", SessionError, "session.yaml: unknown key(s) colour (allowed keys: camera, "
                                                        "marker, reflector, intrinsics, name, notes, panel, products"),
        (SESSION_YAML.replace("fx: 436.0", "skew: 0, fx: 436.0"), SessionError, "intrinsics: unknown key(s) skew"),
        (SESSION_YAML.replace("id: 3", "id: 3, colour: red"), SessionError,
         "marker (type aruco): unknown key(s) colour (allowed keys: dictionary, id, size_m, border_m, type)"),
        # missing keys
        (SESSION_YAML.replace("marker:", "mark:"), SessionError, "session.yaml: missing key(s) marker"),
        (SESSION_YAML.replace("reflectance: 0.5, ", ""), SessionError, "reflector: missing key(s) reflectance"),
        (SESSION_YAML.replace("id: 3", "type: charuco"), SessionError,
         "marker (type charuco): missing key(s) squares_x, squares_y, square_mm, marker_mm"),
        # wrong types
        ("- camera\n", SessionError, "must be a YAML mapping of keys to values, got ['camera']"),
        (SESSION_YAML.replace("size_m: [0.5, 0.5]", "size_m: big"), SessionError,
         "reflector.size_m must be [width_m, height_m] (positive numbers), got 'big'"),
        (SESSION_YAML.replace("reflector: {reflectance: 0.5, size_m: [0.5, 0.5]}", "reflector: 0.5"), SessionError,
         "reflector must be a mapping, got 0.5"),
        (SESSION_YAML.replace("id: 3", "id: 3, type: april"), SessionError,
         "marker.type must be one of aruco, charuco, got 'april'"),
        (SESSION_YAML.replace("DICT_4X4_50", "DICT_9X9_1"), SessionError,
         "marker.dictionary 'DICT_9X9_1' is not an OpenCV ArUco/AprilTag dictionary"),
        (SESSION_YAML.replace("dist: [-0.1, 0.02, 0.0, 0.0, 0.0]", "dist: [-0.1, x]"), SessionError,
         "intrinsics.dist must be [k1, k2, p1, p2, k3] (OpenCV order; 4, 5 or 8 numbers), got [-0.1, 'x']"),
        # out of range
        (SESSION_YAML.replace("size_m: [0.5, 0.5]", "size_m: [0.5, -0.5]"), SessionError,
         "reflector.size_m must be [width_m, height_m] (positive numbers), got [0.5, -0.5]"),
        (SESSION_YAML.replace("size_m: 0.10", "size_m: .nan"), SessionError, "marker.size_m must be a number, got nan"),
        (SESSION_YAML.replace("reflectance: 0.5", "reflectance: [[600, 0.4], [900, 1.6]]"), SessionError,
         "reflector.reflectance[1] must be [wavelength_nm, reflectance]: finite numbers, nm > 0, 0 < reflectance <= 1"),
        (SESSION_YAML + "serial: true\n", SessionError, "serial must be the camera's serial number as text, got True "
         '(e.g. serial: "RE02-1234567" (quoted))'),
        (SESSION_YAML + "serial: ' '\n", SessionError, "serial must be the camera's serial number as text, got ' '"),
        (SESSION_YAML + "serial: [RE02-1]\n", SessionError, "serial must be the camera's serial number as text"),
        (SESSION_YAML + "panel: {marker: {dictionary: DICT_4X4_50, id: 7, size_m: 0.06}, size_m: [0.15, 0]}\n",
         SessionError, "panel.size_m must be [w, h] in metres (or one side), positive numbers, got [0.15, 0]"),
    ],
)
def test_bad_session_yaml(tmp_path, text, error, message) -> None:
    if text is not None:
        _session(tmp_path, text)
    with pytest.raises(error) as err:
        load_session(tmp_path)
    assert message in str(err.value)
    assert "session.yaml" in str(err.value) and "\n" not in str(err.value)


_LENS = {"fx": 1400.0, "fy": 1400.0, "cx": 640.0, "cy": 480.0}


@pytest.mark.parametrize(
    "data, message",
    [
        ({"Blue": _LENS}, "intrinsics: missing key(s) Red Edge (allowed keys: Blue or 1, Red Edge or 5)"),
        ({"Blue": _LENS, "1": _LENS, "5": _LENS}, "intrinsics: band 'Blue' is given twice (as Blue and 1)"),
        ({"Blue": _LENS, "5": _LENS, "NIR": _LENS}, "intrinsics: unknown key(s) NIR (allowed keys: Blue or 1, Red Edge"),
        ({"Blue": {**_LENS, "fx": -1}, "5": _LENS}, "intrinsics.Blue.fx must be positive, got -1"),
        ({"Blue": _LENS, "Red Edge": {"fx": 1.0}}, "intrinsics.Red Edge: missing key(s) fy, cx, cy"),
        ({"Blue": _LENS, "5": {**_LENS, "dist": [1, 2]}}, "intrinsics.5.dist must be [k1, k2, p1, p2, k3]"),
        ([_LENS, _LENS], "intrinsics must be a mapping, got [{"),
    ],
)
def test_bad_band_intrinsics_named_by_key_path(data, message) -> None:
    from pipeline.ingest.intrinsics import parse_band_intrinsics
    from pipeline.ingest.session import IntrinsicsModel, intrinsics_of

    path = Path("session.yaml")
    with pytest.raises(SessionError) as err:
        parse_band_intrinsics(data, [["Blue", "1"], ["Red Edge", "5"]], path, IntrinsicsModel, intrinsics_of)
    assert str(err.value).startswith(f"session.yaml: {message}") and "\n" not in str(err.value)


def test_band_intrinsics_by_name_or_suffix() -> None:
    from pipeline.ingest.intrinsics import parse_band_intrinsics
    from pipeline.ingest.session import IntrinsicsModel, intrinsics_of

    out = parse_band_intrinsics({"5": {**_LENS, "cx": 600.0}, "Blue": _LENS}, [["Blue", "1"], ["Red Edge", "5"]],
                                Path("s.yaml"), IntrinsicsModel, intrinsics_of)
    assert [(i.fx, i.cx) for i in out] == [(1400.0, 640.0), (1400.0, 600.0)]


def test_intrinsics_may_come_later(tmp_path) -> None:
    """Without intrinsics in session.yaml the session loads; the fits take them from a store or
    the band files' metadata, and say so naming session.yaml when none gives them
    (tests/pipeline/calibrate/test_multilens.py)."""
    text = "\n".join(line for line in SESSION_YAML.splitlines() if "intrinsics" not in line)
    s = load_session(_session(tmp_path, text))
    assert s.intrinsics is None and s.band_intrinsics is None and s.intrinsics_for(0) is None


def _frames(folder: Path, rows: str, files=("a.tif", "b.tif")) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for f in files:
        tifffile.imwrite(folder / f, np.full((1088, 2048), 100, np.uint16))
    (folder / "frames.csv").write_text(rows)
    return folder


def test_frame_table(tmp_path) -> None:
    d = _frames(tmp_path / "r", "file,exposure_ms,gain,time,lat,lon,alt_m\na.tif,2.5,2,2026-05-01T10:00:00Z,47.1,8.5,120\nb.tif,5,,,,,\n")
    recs = read_frame_table(d)
    assert [r.path.name for r in recs] == ["a.tif", "b.tif"]
    assert recs[0].effective_exposure == 5.0 and recs[0].lat == 47.1 and recs[0].alt_m == 120
    assert recs[1].gain == 1.0 and recs[1].time is None


@pytest.mark.parametrize(
    "rows, message",
    [
        ("file,exposure_ms\na.tif,0\nb.tif,1\n", "frame a.tif has exposure_ms 0; it must be positive"),
        ("file,exposure_ms\na.tif,-3\nb.tif,1\n", "exposure_ms -3"),
        ("file,exposure_ms\na.tif,\nb.tif,1\n", "frame a.tif has no exposure_ms"),
        ("file,exposure_ms\na.tif,fast\nb.tif,1\n", "exposure_ms 'fast' is not a number"),
        ("file,exposure_ms\na.tif,1\nb.tif,1\nc.tif,1\n", "frame c.tif is listed but the file does not exist"),
        ("file,exposure\na.tif,1\n", "column 'exposure_ms' is missing"),
        ("file,exposure_ms,time\na.tif,1,yesterday\nb.tif,1,\n", "time 'yesterday' is not ISO 8601"),
    ],
)
def test_bad_frame_tables_name_the_file(tmp_path, rows, message) -> None:
    d = _frames(tmp_path / "r", rows)
    with pytest.raises((FrameError, SessionError)) as err:
        read_frame_table(d)
    assert message in str(err.value)
    assert "frames.csv" in str(err.value)


def test_frame_without_row_or_exif_is_named(tmp_path) -> None:
    d = _frames(tmp_path / "r", "file,exposure_ms\na.tif,1\n")
    with pytest.raises(FrameError, match=r"b\.tif: no exposure time"):
        read_frame_table(d)


def test_truncated_and_foreign_frames(tmp_path) -> None:
    cam = load_camera("ximea-mq022hg-sm5x5-nir")
    d = _frames(tmp_path / "r", "file,exposure_ms\na.tif,1\nb.tif,1\n")
    data = (d / "a.tif").read_bytes()
    (d / "a.tif").write_bytes(data[: len(data) // 3])
    with pytest.raises(FrameError, match=r"a\.tif: unreadable or truncated image"):
        read_bands(d / "a.tif", cam)
    (d / "b.tif").write_text("not an image")
    with pytest.raises(FrameError, match=r"b\.tif: unreadable or truncated image"):
        read_bands(d / "b.tif", cam)
    tifffile.imwrite(d / "c.tif", np.full((1088, 2048), 4000, np.uint16))
    with pytest.raises(FrameError, match="DN 4000 exceed the 10-bit range"):
        read_bands(d / "c.tif", cam)
    tifffile.imwrite(d / "d.tif", np.zeros((960, 1280), np.uint16))
    with pytest.raises(FrameError, match="frame is 1280x960 but camera ximea"):
        read_bands(d / "d.tif", cam)


def test_rgb_frames_become_bands(tmp_path) -> None:
    import cv2

    cam = load_camera("generic-rgb8")
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 10, 20, 30  # R, G, B
    cv2.imwrite(str(tmp_path / "x.png"), img[..., ::-1])  # OpenCV writes BGR
    bands = read_bands(tmp_path / "x.png", cam)
    assert bands.shape == (3, 4, 5)
    assert [int(bands[i, 0, 0]) for i in range(3)] == [10, 20, 30]


@pytest.mark.skipif(not MICASENSE.is_dir(), reason="shared data not present")
def test_exif_fallback_on_real_micasense_file() -> None:
    rec = exif_record(MICASENSE / "IMG_0000_1.tif")
    assert rec.exposure_ms == pytest.approx(0.4725)
    assert rec.gain == 1.0
    assert rec.lat == pytest.approx(36.576096, abs=1e-6)
    assert rec.lon == pytest.approx(-119.4352689, abs=1e-6)
    assert rec.alt_m == pytest.approx(101.861, abs=1e-3)
    assert rec.time == "2017-10-19T20:40:39"


def test_truncated_jpeg_is_rejected(tmp_path) -> None:
    import cv2

    cam = load_camera("generic-rgb8")
    img = (np.arange(64 * 48 * 3) % 251).astype(np.uint8).reshape(48, 64, 3)
    cv2.imwrite(str(tmp_path / "ok.jpg"), img)
    assert read_bands(tmp_path / "ok.jpg", cam).shape == (3, 48, 64)
    data = (tmp_path / "ok.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: int(len(data) * 0.8)])
    with pytest.raises(FrameError, match=r"cut\.jpg: unreadable or truncated image .*end-of-image"):
        read_bands(tmp_path / "cut.jpg", cam)
