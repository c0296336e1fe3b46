"""Field calibration of a multi-lens camera (one file per band per capture, MicaSense-style):
U, V and S per lens, each lens with its own intrinsics and marker pose, on synthetic sessions
with known truth (pipeline.sim.multilens), against the snapshot camera's accuracy targets
(tests/pipeline/calibrate/test_calibrate.py, docs/benchmarks.md)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr
import yaml

from mscal_core.errors import FrameError, SessionError
from mscal_core.geometry import Intrinsics
from pipeline.calibrate.intrinsics import with_intrinsics
from pipeline.ingest.captures import read_capture_table
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.intrinsics import intrinsics_from_file
from pipeline.ingest.session import load_session
from pipeline.run.cli import main
from pipeline.sim.multilens import evaluate_multilens, write_multilens_session

MICASENSE = Path(__file__).resolve().parents[4] / "shared" / "data" / "micasense-rededge"


def _pixel_error(a: Intrinsics, b: Intrinsics, shape: tuple[int, int]) -> float:
    """Largest distance (px) between where two intrinsics put the same rays, over the image."""
    import cv2

    h, w = shape
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(pts, a.matrix, a.dist_coeffs)
    obj = np.concatenate([rays.reshape(-1, 2), np.ones((rays.shape[0], 1))], axis=1)
    back, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), b.matrix, b.dist_coeffs)
    return float(np.max(np.linalg.norm(back.reshape(-1, 2) - pts.reshape(-1, 2), axis=1)))


@pytest.fixture(scope="module")
def small_ml(tmp_path_factory) -> tuple[Path, Path]:
    """A small multi-lens session (5 lenses of 240 x 320, 8-frame sweep, 14 views, 2 reflector
    and 2 panel captures, ChArUco board captures) and its calibration by `mscal calibrate`."""
    root = tmp_path_factory.mktemp("multilens")
    session = write_multilens_session(root / "session", seed=0, size="small", board_views=16, board_folder="board")
    calib = root / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    return session, calib


def test_small_multilens_session_round_trip(small_ml) -> None:
    session, calib = small_ml
    err = evaluate_multilens(session, calib)
    # the snapshot camera's small-session targets (test_calibrate.test_small_session_round_trip)
    assert err["response_max_error"] < 0.02
    assert err["vignetting_rms_error_observed"] < 0.02
    assert err["spectral_factor_max_error"] < 0.02
    assert err["check"]["panel_abs_error"] < 0.015
    assert err["check"]["panel_abs_error_uncalibrated"] > 3 * err["check"]["panel_abs_error"]
    # each lens's coverage counts its own views (14), the fit's informative observations a subset
    ds = xr.open_zarr(calib).load()
    cov = ds["vignetting_coverage"].values
    assert cov.shape == ds["vignetting"].shape and 0 < cov.max() <= 14
    assert np.all(cov >= ds["vignetting_count"].values)


def test_store_keeps_each_lens_intrinsics_from_the_band_files(small_ml) -> None:
    session, calib = small_ml
    ds = xr.open_zarr(calib).load()
    truth = np.load(session / "truth.npz")
    assert ds["intrinsics"].attrs["source"].startswith("metadata of ")
    assert list(ds["intrinsics_param"].values) == ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    np.testing.assert_allclose(ds["intrinsics"].values[:, :4], truth["camera_intrinsics"], rtol=1e-6)
    np.testing.assert_allclose(ds["intrinsics"].values[:, 4:], truth["camera_dist"], atol=1e-9)
    # every lens found the marker with its own pose: no capture was lost to a band
    assert ds.attrs["vignetting"]["residuals"]["views_used"] == [14] * 5 or \
        min(ds.attrs["vignetting"]["residuals"]["views_used"]) >= 12


def test_captures_read_per_band_exposure_from_exif(small_ml) -> None:
    session, _ = small_ml
    cam = load_camera("micasense-rededge")
    recs = read_capture_table(session / "vignetting", cam)
    truth = np.load(session / "truth.npz")
    assert [r.name for r in recs][:2] == ["IMG_1000", "IMG_1001"]
    assert len(recs[0].band_files) == 5 and recs[0].band_files[3].name == "IMG_1000_4.tif"
    np.testing.assert_allclose([[r.band_exposure(b) for b in range(5)] for r in recs],
                               truth["vignetting_exposure_ms"], rtol=1e-9)
    assert recs[0].time == "2017-06-14T09:35:00"


def test_frames_csv_per_capture_overrides_metadata(small_ml, tmp_path) -> None:
    session, _ = small_ml
    folder = tmp_path / "r"
    shutil.copytree(session / "response", folder)
    (folder / "frames.csv").write_text("file,exposure_ms,gain\nIMG_0000,2.5,2\nIMG_0001_3.tif,7,1\n")
    cam = load_camera("micasense-rededge")
    recs = read_capture_table(folder, cam)
    assert recs[0].band_effective_exposure is None and recs[0].effective_exposure == 5.0
    truth = np.load(session / "truth.npz")["response_exposure_ms"]
    assert recs[1].band_exposure(2) == 7.0 and recs[1].band_exposure(0) == pytest.approx(truth[1, 0])
    (folder / "frames.csv").write_text("file,exposure_ms\nIMG_9999,2.5\n")
    with pytest.raises(FrameError, match="IMG_9999, which is neither a capture nor a band file"):
        read_capture_table(folder, cam)


def test_a_missing_band_file_is_named(small_ml, tmp_path) -> None:
    session, _ = small_ml
    folder = tmp_path / "v"
    shutil.copytree(session / "vignetting", folder)
    (folder / "IMG_1003_4.tif").unlink()
    with pytest.raises(FrameError) as err:
        read_capture_table(folder, load_camera("micasense-rededge"))
    assert "IMG_1003_1.tif" in str(err.value) and "band file(s) 4 missing" in str(err.value)


def test_fit_intrinsics_from_charuco_captures_per_lens(small_ml, tmp_path, capsys) -> None:
    session, _ = small_ml
    out = tmp_path / "intr.zarr"
    assert main(["fit", "intrinsics", str(session / "board"), "--fix-k3", "-o", str(out)]) == 0
    assert "views per band" in capsys.readouterr().out
    ds = xr.open_zarr(out).load()
    truth = np.load(session / "truth.npz")
    shape = (240, 320)
    for b in range(5):
        fitted = Intrinsics(*ds["intrinsics"].values[b, :4], dist=tuple(ds["intrinsics"].values[b, 4:]))
        true = Intrinsics(*truth["camera_intrinsics"][b], dist=tuple(truth["camera_dist"][b]))
        assert abs(fitted.fx / true.fx - 1) < 0.01, b
        # where each lens sends a ray, over the whole image (corners extrapolated beyond the
        # board's corners; 320-px images, 16 board captures: 0.6-2 px measured)
        assert _pixel_error(true, fitted, shape) < 2.5, b
    assert max(ds.attrs["intrinsics"]["rms_px"]) < 0.3
    # the session then takes them from the store when session.yaml gives none
    resolved, source = with_intrinsics(load_session(session), ds)
    assert source == "calibration store"
    assert resolved.intrinsics_for(2).fx == pytest.approx(float(ds["intrinsics"].values[2, 0]))


def test_fit_intrinsics_needs_a_board(small_ml, tmp_path, capsys) -> None:
    session, _ = small_ml
    folder = tmp_path / "b"
    shutil.copytree(session / "board", folder)
    (folder / "board.yaml").unlink()
    assert main(["fit", "intrinsics", str(folder), "--camera", "micasense-rededge", "-o", str(tmp_path / "x.zarr")]) == 2
    assert "no board given" in capsys.readouterr().err


def test_session_yaml_intrinsics_per_band(tmp_path) -> None:
    text = {"camera": "micasense-rededge", "reflector": {"reflectance": 0.5, "size_m": [0.5, 0.5]},
            "marker": {"dictionary": "DICT_4X4_50", "id": 3, "size_m": 0.1}}
    per_band = {name: {"fx": 1440.0 + b, "fy": 1440.0 + b, "cx": 640.0, "cy": 480.0, "dist": [-0.1, 0.14, 0, 0, -0.02]}
                for b, name in enumerate(["Blue", "Green", "Red", "NIR", "Red edge"])}
    (tmp_path / "session.yaml").write_text(yaml.safe_dump({**text, "intrinsics": per_band}))
    s = load_session(tmp_path)
    assert s.intrinsics is None and [s.intrinsics_for(b).fx for b in range(5)] == [1440.0, 1441.0, 1442.0, 1443.0, 1444.0]
    # keys may be file suffixes too; a band left out is named
    per_suffix = {str(b + 1): v for b, v in enumerate(per_band.values())}
    (tmp_path / "session.yaml").write_text(yaml.safe_dump({**text, "intrinsics": per_suffix}))
    assert load_session(tmp_path).intrinsics_for(4).fx == 1444.0
    del per_suffix["4"]
    (tmp_path / "session.yaml").write_text(yaml.safe_dump({**text, "intrinsics": per_suffix}))
    with pytest.raises(SessionError, match=r"intrinsics: missing key\(s\) NIR \(allowed keys: .*NIR or 4"):
        load_session(tmp_path)
    # no intrinsics anywhere: said when the fit needs them, naming session.yaml
    (tmp_path / "session.yaml").write_text(yaml.safe_dump(text))
    with pytest.raises(SessionError, match="session.yaml: intrinsics are missing"):
        with_intrinsics(load_session(tmp_path))


def test_metadata_intrinsics_of_the_rededge_sample() -> None:
    f = MICASENSE / "IMG_0000_1.tif"
    if not f.is_file():
        pytest.skip(f"MicaSense sample files not found in {MICASENSE}")
    intr = intrinsics_from_file(f)
    # XMP PerspectiveFocalLength 1449.358 px (no unit tag), PrincipalPoint "2.35363,1.79947" mm,
    # EXIF FocalPlaneXResolution 266.666667 px/mm; PerspectiveDistortion [k1, k2, k3, p1, p2]
    assert intr.fx == pytest.approx(1449.3582467) and intr.fy == intr.fx
    assert intr.cx == pytest.approx(2.35363 * 266.666667, rel=1e-6) and intr.cy == pytest.approx(1.79947 * 266.666667, rel=1e-6)
    assert intr.dist == pytest.approx((-0.0967965553, 0.1404189347, 0.0002758384, 0.0006600730, -0.0229808426))


@pytest.mark.slow
def test_multilens_calibration_with_board_intrinsics(small_ml, tmp_path) -> None:
    """`mscal calibrate --calibration` with intrinsics fitted from the board instead of the
    band files' metadata: the same targets."""
    session, _ = small_ml
    intr, calib = tmp_path / "intr.zarr", tmp_path / "calib.zarr"
    assert main(["fit", "intrinsics", str(session / "board"), "--fix-k3", "-o", str(intr)]) == 0
    assert main(["calibrate", str(session), "--calibration", str(intr), "-o", str(calib)]) == 0
    ds = xr.open_zarr(calib).load()
    assert ds["intrinsics"].attrs["source"] == "calibration store"
    err = evaluate_multilens(session, ds)
    assert err["response_max_error"] < 0.02
    assert err["vignetting_rms_error_observed"] < 0.02
    assert err["spectral_factor_max_error"] < 0.02
    assert err["check"]["panel_abs_error"] < 0.015


@pytest.mark.long  # ~10 min on 2 cores (writing the session alone ~4 min): make test-long
def test_full_size_multilens_session_meets_the_targets(tmp_path) -> None:
    """RedEdge-size lenses (960 x 1280), 12-frame sweep, 28 views, 3 reflector and 3 panel
    captures: the snapshot camera's full-session targets."""
    session = write_multilens_session(tmp_path / "session", seed=3, size="full", shape=(960, 1280))
    calib = tmp_path / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    err = evaluate_multilens(session, calib)
    assert err["response_max_error"] <= 0.02
    assert err["vignetting_rms_error"] <= 0.015
    assert err["spectral_factor_max_error"] <= 0.01
    assert err["check"]["panel_abs_error"] <= 0.01


def test_sd_card_subfolders_are_captures_too(small_ml, tmp_path) -> None:
    session, _ = small_ml
    folder = tmp_path / "r"
    for k, f in enumerate(sorted((session / "response").glob("*.tif"))):
        sub = folder / "SET" / ("000" if f.name < "IMG_0004" else "001")
        sub.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, sub / f.name)
    recs = read_capture_table(folder, load_camera("micasense-rededge"))
    assert [r.name for r in recs][:1] == ["SET/000/IMG_0000"] and [r.name for r in recs][-1] == "SET/001/IMG_0007"
    assert len(recs) == 8


def test_the_rededge_sample_reads_as_captures_with_per_band_exposure() -> None:
    if not (MICASENSE / "IMG_0000_1.tif").is_file():
        pytest.skip(f"MicaSense sample files not found in {MICASENSE}")
    recs = read_capture_table(MICASENSE, load_camera("micasense-rededge"))
    assert [r.name for r in recs][:2] == ["IMG_0000", "IMG_0001"]
    # EXIF ExposureTime 472500/1e9 s of IMG_0000_1.tif, ISOSpeed 100; each lens its own exposure
    assert recs[0].band_exposure(0) == pytest.approx(0.4725) and recs[0].band_exposure(3) == pytest.approx(1.8)
    assert recs[0].time == "2017-10-19T20:40:39.200173789"  # DateTimeOriginal + SubsecTime


def test_fit_intrinsics_of_the_snapshot_band_grid(tmp_path, capsys) -> None:
    """The snapshot camera: one lens, every band image of a ChArUco frame detected and moved to
    the band grid by its band's offset, one calibration from all (10 frames x 25 bands)."""
    import tifffile

    from mscal_core.intrinsics import Board
    from pipeline.sim.world.rig import snapshot_board_views
    from pipeline.sim.world.scene import make_truth

    truth = make_truth(0)
    board = Board("charuco", (7, 5), 0.06, 0.045)
    img = board.charuco().generateImage((7 * 120, 5 * 120), marginSize=0)
    folder = tmp_path / "board"
    folder.mkdir()
    for k, frame in enumerate(snapshot_board_views(truth, img, (0.42, 0.30), n_views=10, distance_m=(0.45, 0.7))):
        tifffile.imwrite(folder / f"board_{k:02d}.tif", frame)
    out = tmp_path / "intr.zarr"
    assert main(["fit", "intrinsics", str(folder), "--camera", "ximea-mq022hg-sm5x5-nir", "--board", "charuco",
                 "--squares", "7x5", "--square-m", "0.06", "--marker-m", "0.045", "-o", str(out)]) == 0
    ds = xr.open_zarr(out).load()
    values = ds["intrinsics"].values
    assert values.shape == (25, 9) and np.all(values == values[0])  # one lens for every band
    cam = truth.camera
    fitted = Intrinsics(*values[0, :4], dist=tuple(values[0, 4:]))
    assert abs(fitted.fx / cam.fx - 1) < 0.003 and abs(fitted.cx - cam.cx) < 1.0 and abs(fitted.cy - cam.cy) < 1.0
    assert _pixel_error(Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.dist), fitted, cam.grid_shape) < 0.5
    assert min(ds.attrs["intrinsics"]["views"]) >= 8


def test_a_session_board_folder_gives_the_intrinsics(small_ml, tmp_path) -> None:
    """SESSION/intrinsics/ with a board.yaml: fitted from the board images when session.yaml
    and the store give none (before the band files' metadata)."""
    session, _ = small_ml
    root = tmp_path / "s"
    root.mkdir()
    shutil.copy(session / "session.yaml", root)
    shutil.copytree(session / "board", root / "intrinsics")
    resolved, source = with_intrinsics(load_session(root))
    assert source == "board images in intrinsics/"
    truth = np.load(session / "truth.npz")
    fx = [resolved.intrinsics_for(b).fx for b in range(5)]
    np.testing.assert_allclose(fx, truth["camera_intrinsics"][:, 0], rtol=0.01)


def test_metadata_intrinsics_of_the_sentera_d4k_sample(tmp_path) -> None:
    """Sentera Double 4K JPEG: XMP PerspectiveFocalLength 5.4 (mm: Pix4D's schema, the EXIF
    FocalLength 27/5 mm), PrincipalPoint "3.100, 2.325" mm, EXIF FocalPlaneXResolution
    64516129/10000 px per cm (1.55 um pixels), PerspectiveDistortion "-0.093, 0.122, 0, 0, 0";
    one lens for the file's bands, taken by the field calibration when session.yaml gives none."""
    f = MICASENSE.parent / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if not f.is_file():
        pytest.skip(f"Sentera sample files not found in {f.parent}")
    px_per_mm = 6451.6129 / 10
    intr = intrinsics_from_file(f)
    assert intr.fx == pytest.approx(5.4 * px_per_mm, rel=1e-6) and intr.fx == pytest.approx(3483.87, abs=0.01)
    assert intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (pytest.approx(3.1 * px_per_mm, rel=1e-6), pytest.approx(2.325 * px_per_mm, rel=1e-6))
    assert (intr.cx, intr.cy) == (pytest.approx(2000, abs=0.01), pytest.approx(1500, abs=0.01))  # the 4000 x 3000 centre
    assert intr.dist == pytest.approx((-0.093, 0.122, 0.0, 0.0, 0.0))
    session = tmp_path / "s"
    (session / "vignetting").mkdir(parents=True)
    shutil.copyfile(f, session / "vignetting" / f.name)
    (session / "session.yaml").write_text(yaml.safe_dump({
        "camera": "sentera-d4k-ndre", "reflector": {"reflectance": 0.5, "size_m": [0.5, 0.5]},
        "marker": {"dictionary": "DICT_4X4_50", "id": 3, "size_m": 0.1}}))
    resolved, source = with_intrinsics(load_session(session))
    assert source == "metadata of IMG_00006" and resolved.intrinsics == intr
    assert resolved.intrinsics_for(0) == resolved.intrinsics_for(1) == intr


def test_metadata_intrinsics_of_dji_dewarp_data(tmp_path) -> None:
    """DJI: DewarpData fx, fy, cx, cy (offsets from CalibratedOpticalCenterX/Y), k1, k2, p1,
    p2, k3 (OpenCV's order), as the guide's camera matrix for cv2.undistort."""
    from tests import camera_files as cf

    if not cf.DATA.is_dir():
        pytest.skip("MicaSense sample files not found")
    intr = intrinsics_from_file(cf.dji_p4m(tmp_path / "p4m") / "DJI_0011.TIF")
    assert (intr.fx, intr.fy) == (1949.45, 1939.77) and (intr.cx, intr.cy) == (640.0 + 28, 480.0 - 17)
    assert intr.dist == (-0.4082, 0.3418, 0.00068, 0.00068, -0.3540)


def _set_serial(folder: Path, serial: str) -> None:
    """Overwrite EXIF BodySerialNumber in every band file of ``folder`` (another camera body)."""
    for p in sorted(folder.glob("*.tif")):
        with tifffile.TiffFile(p, mode="r+b") as tif:
            tif.pages[0].tags[42033].overwrite(serial)


def _radiance(out: Path) -> np.ndarray:
    with xr.open_zarr(out / "reflectance.zarr") as ds:
        return ds["radiance"].values


def test_a_later_flight_of_the_same_camera_body_gets_its_field_calibration(tmp_path) -> None:
    """``mscal calibrate`` records the session's store in the calibration library under the
    band files' serial number. A card flight of that camera body taken later (the session's
    check captures, 09:50 against the session's 09:45, as the card holds them: Make, Model and
    the MicaSense factory model in the files) gets it: the factory model with the field
    response and vignetting, as ``mscal apply --field-calibration`` gives; the same flight
    from another camera body gets the factory model alone."""
    from pipeline.calibrate.library import default_library_root, store_digest
    from pipeline.ingest.products import Products
    from pipeline.run import card
    from pipeline.run.runner import apply_card_flight

    session = write_multilens_session(tmp_path / "session", seed=2, size="small", shape=(120, 160),
                                      serial="RE0000007", factory_tags=True)
    calib = tmp_path / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    flight = tmp_path / "card"
    shutil.copytree(session / "check", flight)
    plan = card.plan_card(flight, default_library_root())
    assert (plan.camera, plan.serial, plan.factory) == ("micasense-rededge", "RE0000007", True)
    f = plan.flights[0]
    assert f.calibration == "factory+field" and f.calibration_source.startswith("calibration library")
    assert store_digest(f.field_calibration) == store_digest(calib)
    radiance = Products(radiance=True)
    res = apply_card_flight(plan, f, tmp_path / "out", products=radiance)
    assert (res["frames_out"], res["calibration"]) == (2, "factory+field")
    assert main(["apply", str(session / "check"), "--calibration", "factory", "--field-calibration", str(calib),
                 "-o", str(tmp_path / "alone"), "--products", "radiance"]) == 0
    np.testing.assert_array_equal(_radiance(tmp_path / "out"), _radiance(tmp_path / "alone"))

    _set_serial(flight, "RE0000008")
    other = card.plan_card(flight, default_library_root())
    assert other.serial == "RE0000008" and other.flights[0].calibration == "factory"
    assert "no field calibration of micasense-rededge serial RE0000008" in other.flights[0].calibration_source
    apply_card_flight(other, other.flights[0], tmp_path / "other", products=radiance)
    ratio = np.nanmedian(_radiance(tmp_path / "out") / _radiance(tmp_path / "other"))
    assert abs(ratio - 1) > 0.05  # the field response and vignetting did change the radiance
