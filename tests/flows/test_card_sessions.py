"""Flights as they come off the camera's card, through ``mscal run`` and ``mscal serve``: no
field session, the camera from the files, the light reference with no options."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.run.cli import main
from pipeline.run.inbox import READY, STATE_FILE
from tests.camera_files import dji_card
from tests.micasense_data import require_data

pytestmark = pytest.mark.xdist_group("flows")

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _ms_card(root: Path) -> Path:
    """The MicaSense sample as an SD card tree: ``ms1/0000SET/000/IMG_000*_*.tif``."""
    d = root / "0000SET" / "000"
    d.mkdir(parents=True)
    for f in sorted(require_data().glob("IMG_000*_*.tif")):
        shutil.copy(f, d / f.name)
    return root


def _reflectance(flight: Path) -> np.ndarray:
    with xr.open_zarr(flight / "reflectance.zarr") as ds:
        return ds["reflectance"].values


@pytest.mark.slow
def test_run_on_a_card_uses_its_panel_with_no_option(first_run: Path, tmp_path: Path, capsys) -> None:
    """``mscal run CARD -o OUT``: one flight per SET folder, factory radiometry, the panel's
    reflectance from its QR serial, equal to apply with that target named."""
    card = _ms_card(tmp_path / "ms1")
    out = tmp_path / "out"
    assert main(["run", str(card), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    run = json.loads((out / "run.json").read_text())
    assert run["kind"] == "card" and run["status"] == "done" and run["calibration"] is None
    assert run["card"]["camera"] == "micasense-rededge" and run["card"]["serial"] == "1777777"
    f = run["flights"]["0000SET"]
    assert (f["frames_in"], f["frames_out"], f["calibration"]) == (2, 2, "factory")
    assert "no field calibration of micasense-rededge serial 1777777" in f["calibration_source"]
    assert f["reference"]["route"] == "panel-dls"
    assert "RP02-1603036-SC" in f["reference"]["panel_reflectance"]
    assert "flight 0000SET: radiometry factory" in captured.err and "light reference panel-dls" in captured.err
    assert (out / "flights" / "0000SET" / "reflectance.zarr").is_dir()
    assert "panel reflectance: panel serial RP02-1603036-SC (QR code of IMG_0000)" in (out / "report.html").read_text()
    alone = tmp_path / "alone"
    assert main(["apply", str(card), "--calibration", "factory", "--panel-reflectance",
                 "micasense-rp02-1603036-sc", "-o", str(alone)]) == 0
    np.testing.assert_array_equal(_reflectance(out / "flights" / "0000SET"), _reflectance(alone))


@pytest.mark.slow
def test_serve_takes_card_folders_of_every_kind_and_names_what_it_passes_over(
        flow_session: Path, first_run: Path, tmp_path: Path, capsys) -> None:
    """One look at an inbox holding a MicaSense card, a Sequoia capture, a DJI P4M card (RGB
    JPGs with EXIF thumbnails beside the bands) and a snapshot field session: all four
    processed; an empty folder, a folder still being copied and a stray file are named with
    the reason, and a folder of no known camera fails alone."""
    inbox, root = tmp_path / "inbox", tmp_path / "processed"
    _ms_card(inbox / "ms1")
    shutil.copytree(DATA / "parrot-sequoia", inbox / "sequoia")
    dji_card(inbox / "p4m")
    shutil.copytree(flow_session, inbox / "field")
    (inbox / "unknown").mkdir()
    (inbox / "unknown" / "notes.txt").write_text("no images here")
    for name in ("ms1", "sequoia", "p4m", "field", "unknown"):
        (inbox / name / READY).write_text("")
    (inbox / "empty").mkdir()
    _ms_card(inbox / "copying")  # no READY, just modified: still being copied
    (inbox / "stray.tif").write_bytes(b"II*\0")
    old = time.time() - 3600
    for p in (inbox / "copying").rglob("*"):
        os.utime(p, None)
    os.utime(inbox / "stray.tif", (old, old))

    assert main(["serve", "--inbox", str(inbox), "-o", str(root), "--once", "--settle-seconds", "600"]) == 0
    out = capsys.readouterr().out
    state = json.loads((root / STATE_FILE).read_text())
    status = {n: s["status"] for n, s in state["sessions"].items()}
    assert status == {"ms1": "done", "sequoia": "done", "p4m": "done", "field": "done", "unknown": "failed"}
    assert "no TIFF with factory radiometric metadata" in state["sessions"]["unknown"]["detail"]
    assert sorted(state["waiting"]) == ["copying", "empty", "stray.tif"]
    assert "still being copied" in state["waiting"]["copying"]["reason"]
    assert "empty folder" in state["waiting"]["empty"]["reason"]
    assert "not a folder" in state["waiting"]["stray.tif"]["reason"]
    for name in ("ms1", "sequoia", "p4m", "field", "unknown", "copying", "empty", "stray.tif"):
        assert name in out
    flights = {"ms1": "0000SET", "sequoia": "flight", "p4m": "flight"}
    for name, flight in flights.items():
        run = json.loads((root / name / "run.json").read_text())
        assert run["kind"] == "card" and run["status"] == "done", name
        assert (root / name / "report.html").is_file()
        assert (root / name / "flights" / flight / "reflectance.zarr" / "zarr.json").is_file()
    p4m = json.loads((root / "p4m" / "run.json").read_text())["flights"]["flight"]
    assert p4m["frames_out"] == 2 and sorted(s["file"] for s in p4m["skipped"]) == [
        "DCIM/100MEDIA/DJI_0010.JPG", "DCIM/100MEDIA/DJI_0020.JPG"]
    assert json.loads((root / "field" / "run.json").read_text())["calibration_cached"] is True
    # mscal run on the same card gives what serve gave
    assert main(["run", str(inbox / "ms1"), "-o", str(tmp_path / "run")]) == 0
    np.testing.assert_array_equal(_reflectance(tmp_path / "run" / "flights" / "0000SET"),
                                  _reflectance(root / "ms1" / "flights" / "0000SET"))

    # the catalog: one valid STAC item per flight, camera model and serial in its properties
    assert main(["catalog", str(root)]) == 0
    capsys.readouterr()
    items = {p.stem: json.loads(p.read_text()) for p in (root / "stac").glob("*/items/*.json")}
    assert sorted(items) == ["field__field", "field__orchard", "ms1__0000SET", "p4m__flight", "sequoia__flight"]
    props = items["ms1__0000SET"]["properties"]
    assert (props["mscal:camera_model"], props["mscal:camera_serial"]) == ("RedEdge", "1777777")
    assert props["mscal:radiometry"] == "factory" and props["mscal:light_reference"] == "panel-dls"
    assert items["sequoia__flight"]["properties"]["mscal:camera_serial"] == "PI040378AA6C000181"
    assert main(["catalog", str(root), "--validate-only"]) == 0


def test_frames_of_a_snapshot_camera_take_the_library_calibration_of_their_serial(
        flow_session: Path, first_run: Path, tmp_path: Path) -> None:
    """A snapshot camera's frames with frames.csv and a session.yaml naming the camera and its
    serial (no factory radiometry): the library's calibration of that serial fitted before the
    flight is the whole radiometry (Eq. 15), with the outputs of the field run; one fitted after
    the flight is not used, and with none the folder is refused with the reason."""
    from datetime import datetime, timezone

    from mscal_core.errors import InputError
    from pipeline.calibrate.library import record
    from pipeline.run import card
    from pipeline.run.runner import apply_card_flight

    from .conftest import assert_same_flight_outputs

    flight = tmp_path / "frames"
    shutil.copytree(flow_session / "flights" / "field", flight)
    (flight / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\nserial: XI-0042\n")
    lib = tmp_path / "library"
    before = datetime(2017, 6, 14, 9, 45, tzinfo=timezone.utc)  # the flight: 09:50 that day
    record(first_run / "calibration.zarr", camera="ximea-mq022hg-sm5x5-nir", serial="XI-0042", session_time=before,
           library_root=lib)
    plan = card.plan_card(flight, lib)
    f = plan.flights[0]
    assert (f.name, f.calibration, f.start) == ("flight", "field", "2017-06-14T09:50:00Z")
    assert apply_card_flight(plan, f, tmp_path / "out")["frames_out"] == 3
    assert_same_flight_outputs(first_run / "flights" / "field", tmp_path / "out")

    late = tmp_path / "late"
    record(first_run / "calibration.zarr", camera="ximea-mq022hg-sm5x5-nir", serial="XI-0042",
           session_time=datetime(2017, 6, 15, tzinfo=timezone.utc), library_root=late)
    with pytest.raises(InputError, match="no field calibration of ximea-mq022hg-sm5x5-nir serial XI-0042 fitted "
                                         "before the flight"):
        card.plan_card(flight, late)
