"""Calibrate's marker poses on full-size sessions: a view given the mirrored IPPE solution is
taken back with the other one when that one agrees with the other views; a session of oblique,
far views (where the single-solution path took mirrored poses) meets the vignetting target."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import xarray as xr

from mscal_core import marker
from pipeline.run.cli import main
from pipeline.sim.evaluate import evaluate_calibration
from pipeline.sim.synth import write_synthesized
from pipeline.sim.world.scene import synthesize_session, vignetting_views


def _tilts_deg(rvecs: np.ndarray, tvecs: np.ndarray) -> np.ndarray:
    """Angle between each marker's normal and its line of sight."""
    import cv2

    out = []
    for r, t in zip(rvecs, tvecs):
        n = cv2.Rodrigues(np.asarray(r, dtype=np.float64))[0][:, 2]
        out.append(np.degrees(np.arccos(abs(n @ t) / np.linalg.norm(t))))
    return np.array(out)


@pytest.mark.slow
@pytest.mark.xdist_group("full_session")
def test_a_mirrored_pose_is_taken_back_by_consistency(full_session, tmp_path, monkeypatch) -> None:
    session = full_session
    truth = np.load(session / "truth.npz")
    found = truth["vignetting_marker_in_frame"]
    tilts = np.where(found, _tilts_deg(truth["vignetting_rvec"], truth["vignetting_tvec"]), -1.0)
    k = int(np.argmax(tilts))  # the most oblique view: its mirror is tens of degrees off
    assert tilts[k] > 30.0
    name = f"{truth['vignetting_names'][k]}.tif"
    t_true = truth["vignetting_tvec"][k]
    original = marker.pose_in_image

    def mirrored_for_one_view(*args, **kwargs):
        choice = original(*args, **kwargs)
        if np.linalg.norm(choice.pose.tvec - t_true) < 0.05 * np.linalg.norm(t_true):
            return choice.swapped("reprojection")  # as if the corners had chosen the mirror
        return choice

    monkeypatch.setattr(marker, "pose_in_image", mirrored_for_one_view)
    calib = tmp_path / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    attrs = xr.open_zarr(calib).attrs["vignetting"]
    assert name not in {s["file"] for s in attrs["skipped"]}
    record = next(p for p in attrs["residuals"]["marker_poses"] if p["file"] == name)
    assert record["by"] == "consistency"
    assert sum(p["by"] == "consistency" for p in attrs["residuals"]["marker_poses"]) == 1
    assert evaluate_calibration(session, calib)["vignetting_rms_error"] < 0.015


@pytest.mark.long  # a full-size oblique session written and calibrated, ~65 s: make test-long
def test_oblique_far_views_meet_the_vignetting_target(tmp_path) -> None:
    # the full-size session of seed 2 with its 40 vignetting views drawn tilted up to 50 deg
    # (35 by default) at 1.3-2.0 m (0.8-1.6): markers of 20-35 px. Before both IPPE solutions
    # were kept and the corners taken from the edges, 2 of its 38 poses were mirrored (one
    # 100 deg off, neither screened out) and V missed by 2.08 % RMS; now 0.77 %.
    synth = synthesize_session(2, size="full")
    views = vignetting_views(synth.truth, seed=2, n_views=40, n_missing=2, max_tilt_deg=50.0, distance_m=(1.3, 2.0))
    session = write_synthesized(dataclasses.replace(synth, vignetting=views), tmp_path / "session")
    calib = tmp_path / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    attrs = xr.open_zarr(calib).attrs["vignetting"]
    assert attrs["residuals"]["views_used"] == 38
    assert np.median(attrs["residuals"]["residual_rms"]) < 0.015  # 2.3 % before
    assert evaluate_calibration(session, calib)["vignetting_rms_error"] < 0.01
