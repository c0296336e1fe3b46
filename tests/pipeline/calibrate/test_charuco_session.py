"""A field session with a ChArUco board in place of the single marker, end to end: the
simulator writes it (``write_session(marker="charuco")``), ``mscal calibrate`` finds the board
in its views through the ChArUco path and fits U, V and S within the targets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

from pipeline.run.cli import main
from pipeline.sim.evaluate import evaluate_calibration
from pipeline.sim.synth import write_session

#: A small ChArUco session written (~40 s) and calibrated (~20 s) once: both tests on one worker.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("charuco_session")]


@pytest.fixture(scope="module")
def charuco_small(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("charuco")
    session = write_session(root / "session", seed=0, size="small", marker="charuco")
    calib = root / "cal.zarr"
    assert main(["calibrate", str(session), "-o", str(calib), "-q"]) == 0
    return session, calib


def test_charuco_session_calibrates_within_targets(charuco_small) -> None:
    session, calib = charuco_small
    assert yaml.safe_load((session / "session.yaml").read_text())["marker"]["type"] == "charuco"
    err = evaluate_calibration(session, calib)
    # measured on seed 0: U 0.0053, V 0.0073 (0.0106 where observed), S 0.0082
    assert err["response_max_error"] <= 0.02
    assert err["vignetting_rms_error"] <= 0.015
    assert err["spectral_factor_max_error"] <= 0.01


def test_views_were_found_through_the_charuco_path(charuco_small) -> None:
    """The vignetting stage's report names the board and every view's corners; the view
    planned with the board out of frame is skipped, all the others are used."""
    session, calib = charuco_small
    ds = xr.open_zarr(calib)
    truth = np.load(session / "truth.npz")
    rep = ds.attrs["vignetting"]
    assert rep["residuals"]["marker"] == {"type": "charuco", "label": "ChArUco board 4x4 DICT_4X4_50"}
    poses = rep["residuals"]["marker_poses"]
    in_frame = [f"{n}.tif" for n, ok in zip(truth["vignetting_names"], truth["vignetting_marker_in_frame"]) if ok]
    assert sorted(p["file"] for p in poses) == sorted(in_frame) and len(in_frame) == 7
    # a 4 x 4 board has 9 inner corners: all found in every view, as the simulator found them
    assert [p["corners"] for p in poses] == [9] * 7
    assert truth["vignetting_board_corners"][truth["vignetting_marker_in_frame"]].tolist() == [9] * 7
    assert all(p["by"] == "reprojection" and p["reprojection_px"][0] < 0.5 for p in poses)
    skipped = {s["file"]: s["reason"] for s in rep["skipped"]}
    assert skipped == {"view_04.tif": "ChArUco board 4x4 DICT_4X4_50 not found"}
    assert not truth["vignetting_marker_in_frame"][4]
    # the reflector images' board too
    assert [p["corners"] for p in ds.attrs["illumination"]["residuals"]["marker_poses"]] == [9, 9]
