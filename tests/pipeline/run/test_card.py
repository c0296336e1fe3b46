"""A flight folder as it comes off the camera's card, as a session: camera, serial, flights."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mscal_core.errors import InputError, SessionError
from pipeline.run import card
from pipeline.run.runner import apply_card_flight
from tests.micasense_data import require_data

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"


def _t(*secs: float | None) -> np.ndarray:
    base = np.datetime64("2026-06-01T10:00:00", "ns")
    return np.array([np.datetime64("NaT", "ns") if s is None else base + np.timedelta64(int(s * 1e9), "ns")
                     for s in secs])


def test_split_by_time_cuts_at_gaps_and_keeps_untimed_captures_with_their_neighbour() -> None:
    groups = card.split_by_time(_t(0, 60, 3000, 3060, None), 1800)
    assert [g.tolist() for g in groups] == [[0, 1], [2, 3, 4]]
    # out of name order in time: grouped by time, each group in name order
    assert [g.tolist() for g in card.split_by_time(_t(3000, 0, 3100, 50), 1800)] == [[1, 3], [0, 2]]
    assert [g.tolist() for g in card.split_by_time(_t(None, None), 60)] == [[0, 1]]
    assert [g.tolist() for g in card.split_by_time(_t(0, 1799, 3598), 1800)] == [[0, 1, 2]]  # gap not exceeded
    assert card.split_by_time(_t(), 60) == []


def _card(root: Path, sets: tuple[str, ...] = ("0000SET",)) -> Path:
    """The sample's two captures as an SD card writes them: both in one SET folder, or the
    panel capture in the first and the flight capture in the second."""
    src = require_data()
    for k, s in enumerate(sets):
        d = root / s / "000"
        d.mkdir(parents=True)
        pattern = "IMG_000*_*.tif" if len(sets) == 1 else f"IMG_000{k}_*.tif"
        for f in sorted(src.glob(pattern)):
            shutil.copy(f, d / f.name)
    return root


def test_a_micasense_card_is_one_flight_per_set_folder_camera_and_serial_from_the_files(tmp_path: Path) -> None:
    root = _card(tmp_path / "ms1", ("0000SET", "0001SET"))
    assert not card.is_field_session(root)
    plan = card.plan_card(root, tmp_path / "library")
    assert (plan.camera, plan.make, plan.model, plan.serial) == ("micasense-rededge", "MicaSense", "RedEdge", "1777777")
    assert plan.factory
    assert [f.name for f in plan.flights] == ["0000SET", "0001SET"]
    assert [Path(f.folder).name for f in plan.flights] == ["0000SET", "0001SET"]
    f = plan.flights[0]
    assert f.captures == () and f.calibration == "factory" and f.field_calibration is None
    assert "no field calibration of micasense-rededge serial 1777777" in f.calibration_source
    assert f.start is not None and f.start == f.end < plan.flights[1].start  # the panel capture, then the flight
    # the plan survives Prefect's JSON round trip
    again = card.plan_from_record(json.loads(json.dumps(card.plan_record(plan))))
    assert again == plan


def test_captures_further_apart_than_the_gap_are_separate_flights(tmp_path: Path) -> None:
    root = _card(tmp_path / "ms1")
    (root / "session.yaml").write_text("flight_gap_minutes: 0.5\nfield_calibration: none\n")
    plan = card.plan_card(root, tmp_path / "library")
    assert [(f.name, f.captures) for f in plan.flights] == [("0000SET-1", ("IMG_0000",)), ("0000SET-2", ("IMG_0001",))]
    assert plan.flights[0].calibration_source == "session.yaml field_calibration: none"
    res = apply_card_flight(plan, plan.flights[1], tmp_path / "out")
    assert (res["frames_in"], res["frames_out"], res["calibration"]) == (1, 1, "factory")
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["frames_out"] == 1


def test_card_session_yaml_is_checked_and_named(tmp_path: Path) -> None:
    root = _card(tmp_path / "ms1")
    (root / "session.yaml").write_text("camera: micasense-rededge\nmarker_id: 3\n")
    with pytest.raises(SessionError, match=r"session\.yaml: .*unknown key\(s\) marker_id"):
        card.load_card_settings(root)
    (root / "session.yaml").write_text("reference: sun\n")
    with pytest.raises(SessionError, match="reference 'sun' is not one of auto, panel, dls, panel-dls"):
        card.load_card_settings(root)
    (root / "session.yaml").write_text("field_calibration: nowhere.zarr\n")
    with pytest.raises(SessionError, match="field_calibration 'nowhere.zarr': no such store"):
        card.load_card_settings(root)
    (root / "session.yaml").write_text("flight_gap_minutes: 0\n")
    with pytest.raises(SessionError, match="flight_gap_minutes must be a positive number"):
        card.load_card_settings(root)
    for text, message in [("camera: micasense-rededge\nmarker_id: 3\n", "allowed keys: camera, field_calibration, "),
                          ("flight_gap_minutes: soon\n", "flight_gap_minutes must be a positive number, got 'soon'"),
                          ("- camera\n", "must be a YAML mapping of keys to values, got ['camera']")]:
        (root / "session.yaml").write_text(text)
        with pytest.raises(SessionError) as err:
            card.load_card_settings(root)
        assert str(err.value).startswith(f"{root / 'session.yaml'}: ") and message in str(err.value)


def test_folders_that_are_not_one_cameras_card_are_refused_with_the_reason(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    (empty / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="no TIFF with factory radiometric metadata"):
        card.plan_card(empty, tmp_path / "library")
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frames.csv").write_text("file,exposure_ms\nf0.tif,1.0\n")
    with pytest.raises(InputError, match="frames with frames.csv but no camera"):
        card.plan_card(frames, tmp_path / "library")
    (frames / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\nserial: X1\n")
    with pytest.raises(InputError, match="no factory radiometry of ximea-mq022hg-sm5x5-nir and no field calibration"):
        card.plan_card(frames, tmp_path / "library")
    d4k = DATA / "sentera-d4k"
    if d4k.is_dir():
        with pytest.raises(InputError, match="captures of 2 cameras"):
            card.plan_card(d4k, tmp_path / "library")


def test_a_field_session_is_not_a_card(tmp_path: Path) -> None:
    (tmp_path / "response").mkdir()
    (tmp_path / "session.yaml").write_text("camera: micasense-rededge\n")
    assert card.is_field_session(tmp_path)
    (tmp_path / "response").rmdir()
    assert not card.is_field_session(tmp_path)


def test_captures_beside_set_folders_are_a_flight_of_their_own(tmp_path: Path) -> None:
    src = require_data()
    root = tmp_path / "ms1"
    (root / "0000SET" / "000").mkdir(parents=True)
    for f in src.glob("IMG_0000_*.tif"):
        shutil.copy(f, root / "0000SET" / "000" / f.name)
    for f in src.glob("IMG_0001_*.tif"):
        shutil.copy(f, root / f.name)
    plan = card.plan_card(root, tmp_path / "library")
    assert [(f.name, Path(f.folder).name, f.captures) for f in plan.flights] == [
        ("flight", "ms1", ("IMG_0001",)), ("0000SET", "0000SET", ())]
    res = apply_card_flight(plan, plan.flights[0], tmp_path / "out")
    assert (res["frames_in"], res["frames_out"]) == (1, 1)  # not the SET folder's capture too


def test_set_folders_of_one_name_in_two_places_are_two_flights(tmp_path: Path) -> None:
    src = require_data()
    root = tmp_path / "cards"
    for sub, cap in (("cardA", "IMG_0000"), ("cardB", "IMG_0001")):
        d = root / sub / "0000SET" / "000"
        d.mkdir(parents=True)
        for f in src.glob(f"{cap}_*.tif"):
            shutil.copy(f, d / f.name)
    plan = card.plan_card(root, tmp_path / "library")
    assert [f.name for f in plan.flights] == ["cardA_0000SET", "cardB_0000SET"]


def test_a_field_session_without_its_session_yaml_is_not_taken_for_a_card(tmp_path: Path) -> None:
    root = _card(tmp_path / "sess")
    (root / "response").mkdir()
    with pytest.raises(SessionError, match=r"session\.yaml: session\.yaml is missing beside response/"):
        card.plan_card(root, tmp_path / "library")


def test_session_yaml_serial_and_panel_reflectance_are_checked(tmp_path: Path) -> None:
    root = _card(tmp_path / "ms1")
    (root / "session.yaml").write_text("serial: RE-OTHER-999\n")
    with pytest.raises(SessionError, match="serial 'RE-OTHER-999' is not the files' serial number '1777777'"):
        card.plan_card(root, tmp_path / "library")
    (root / "session.yaml").write_text("serial: 1777777\n")  # the same: fine
    assert card.plan_card(root, tmp_path / "library").serial == "1777777"
    (root / "session.yaml").write_text("panel_reflectance: rp02-typo\n")
    with pytest.raises(SessionError, match=r"ms1/session\.yaml: .*rp02-typo"):
        card.load_card_settings(root)


def test_frame_times_of_a_snapshot_flight_are_taken_in_utc(tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frames.csv").write_text("file,exposure_ms,time\nf0.tif,1.0,2026-06-01T12:00:00+02:00\n"
                                       "f1.tif,1.0,2026-06-01T10:30:00Z\n")
    for name in ("f0.tif", "f1.tif"):
        (frames / name).write_bytes(b"II*\0")  # the plan reads frames.csv only
    (frames / "calib.zarr").mkdir()
    (frames / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\nfield_calibration: calib.zarr\n")
    f = card.plan_card(frames, tmp_path / "library").flights[0]
    assert (f.start, f.end, f.calibration) == ("2026-06-01T10:00:00Z", "2026-06-01T10:30:00Z", "field")
    assert f.field_calibration == str((frames / "calib.zarr").resolve())


def test_a_failed_card_flight_keeps_what_its_plan_said() -> None:
    from pipeline.run.runner import failed_card_flight

    flight = {"name": "0000SET-2", "folder": "/card/0000SET", "captures": ["IMG_0001"], "start": "t0", "end": "t1",
              "calibration": "factory", "field_calibration": None, "calibration_source": "none known"}
    rec = failed_card_flight(flight, InputError("no complete capture"))
    assert rec["status"] == "failed" and rec["reason"] == "no complete capture"
    assert (rec["captures"], rec["start"], rec["calibration"], rec["calibration_source"]) == (
        ["IMG_0001"], "t0", "factory", "none known")
