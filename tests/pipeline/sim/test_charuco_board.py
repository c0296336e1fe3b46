"""The simulator's ChArUco board in place of the single marker: where it is printed, the
session.yaml block calibrate reads, and views whose board calibrate finds at the true pose."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from mscal_core import charuco, geometry
from pipeline.calibrate.views import camera_offsets, detection_image, exclude_half, marker_pose_corners
from pipeline.ingest.session import load_session
from pipeline.sim.synth import marker_yaml, session_marker, session_yaml
from pipeline.sim.varied import VariedParams, params_record, varied_truth
from pipeline.sim.world.scene import (
    CharucoBoardSpec,
    MarkerSpec,
    Pose,
    ReflectorScene,
    SyntheticSession,
    UniformLight,
    make_truth,
    pose_error,
    vignetting_views,
)

BOARD = CharucoBoardSpec()


def test_board_is_printed_centred_on_the_reflector() -> None:
    """OpenCV's top-left square (black) at (-W/2, +H/2), the white square beside it white
    around its marker, the paper border white, the gray reflector beyond."""
    scene = ReflectorScene([600.0, 700.0], 0.5, (0.5, 0.5), BOARD, UniformLight(1.0), ground_seed=0)
    s, (w, h) = BOARD.square_m, BOARD.board_size_m
    assert (w, h) == pytest.approx((0.24, 0.24)) and BOARD.size_m == pytest.approx(0.24)
    margin = 0.5 * (s - BOARD.marker_m)
    pts = {
        "top-left square": (-w / 2 + s / 2, h / 2 - s / 2, ReflectorScene.INK),
        "bottom-right square": (w / 2 - s / 2, -h / 2 + s / 2, ReflectorScene.INK),  # 4 x 4: black too
        "white square's margin": (-w / 2 + s + margin / 2, h / 2 - margin / 2, ReflectorScene.PAPER),
        "marker's black border": (-w / 2 + s + margin + 0.002, h / 2 - margin - 0.002, ReflectorScene.INK),
        "paper border": (w / 2 + BOARD.border_m / 2, 0.0, ReflectorScene.PAPER),
        "beyond the paper": (w / 2 + BOARD.border_m + 0.003, 0.0, ReflectorScene.GRAY),
        "beyond the reflector": (0.26, 0.0, ReflectorScene.GROUND),
    }
    u = np.array([p[0] for p in pts.values()])
    v = np.array([p[1] for p in pts.values()])
    _, lab = scene.evaluate(u, v)
    assert dict(zip(pts, lab.tolist())) == {k: p[2] for k, p in pts.items()}
    # the ink covers the chessboard's black half plus the markers' black cells
    uu, vv = np.meshgrid(np.linspace(-w / 2, w / 2, 481)[:-1] + w / 960, np.linspace(-h / 2, h / 2, 481)[:-1] + h / 960)
    _, lab = scene.evaluate(uu.ravel(), vv.ravel())
    # (8 white squares x (45/60)**2 marker x 20 to 36 black cells of the 6 x 6)
    ink = float(np.mean(lab == ReflectorScene.INK))
    assert 0.656 < ink < 0.78


def test_session_yaml_block_is_what_calibrate_reads(tmp_path) -> None:
    assert session_marker("aruco") is None and session_marker("charuco") == BOARD
    with pytest.raises(ValueError, match="marker must be"):
        session_marker("april")
    truth = make_truth(0, marker=BOARD)
    fake = SyntheticSession(truth=truth, response=None, vignetting=None, reflector=None, size="x")  # type: ignore[arg-type]
    data = session_yaml(fake)
    assert data["marker"] == {"type": "charuco", "squares_x": 4, "squares_y": 4, "square_mm": 60.0,
                              "marker_mm": 45.0, "dictionary": "DICT_4X4_50", "border_mm": 10.0}
    assert marker_yaml(MarkerSpec()) == {"dictionary": "DICT_4X4_50", "id": 3, "size_m": 0.1, "border_m": 0.025}
    (tmp_path / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    s = load_session(tmp_path)
    assert s.marker.board == charuco.CharucoSpec(4, 4, 0.06, 0.045, "DICT_4X4_50")
    # calibrate leaves out the board and its paper border (+ its margin): the printed paper
    half_paper = BOARD.size_m / 2 + BOARD.border_m
    assert exclude_half(s) == pytest.approx(half_paper + 0.005)
    # the board's chessboard corners are where calibrate's board frame puts them
    np.testing.assert_allclose(BOARD.corners_m(), charuco.board_points(s.marker.board), atol=1e-7)


def test_varied_params_carry_the_board() -> None:
    assert isinstance(varied_truth(VariedParams(marker="charuco")).marker, CharucoBoardSpec)
    assert isinstance(varied_truth(VariedParams()).marker, MarkerSpec)
    assert "marker" not in params_record(VariedParams())
    assert params_record(VariedParams(marker="charuco"))["marker"] == "charuco"


@pytest.mark.slow  # 5 board views rendered, ~15 s
def test_views_find_the_board_at_its_true_pose(tmp_path) -> None:
    """Every view with the board in frame: calibrate's ChArUco path (detection image of all
    bands, mscal_core.charuco) finds its 9 corners and the true pose (measured: 0.3-1.3 deg,
    0.02-0.14 % of the distance; the reflector's edges within 0.8 px); the view planned
    without the board has none."""
    truth = make_truth(0, marker=BOARD)
    fs = vignetting_views(truth, seed=0, n_views=5, n_missing=1, supersample=2)
    assert fs.truth["marker_in_frame"].tolist() == [True, True, False, True, True]
    assert fs.truth["board_corners"].tolist() == [9, 9, 0, 9, 9] and fs.truth["rejected_renders"].min() >= 0
    fake = SyntheticSession(truth=truth, response=None, vignetting=None, reflector=None, size="x")  # type: ignore[arg-type]
    (tmp_path / "session.yaml").write_text(yaml.safe_dump(session_yaml(fake), sort_keys=False))
    s = load_session(tmp_path)
    centre = camera_offsets(s.camera).mean(axis=0)
    U = truth.inverse_response
    edge = np.array([[x, y] for x in (-0.25, 0.25) for y in np.linspace(-0.25, 0.25, 11)])
    for k in range(len(fs)):
        img = detection_image(fs.dn[k], U)
        choice, n = marker_pose_corners(img, s.marker, s.intrinsics, [], (float(centre[0]), float(centre[1])))
        if not fs.truth["marker_in_frame"][k]:
            assert choice is None and n == 0
            continue
        assert n == 9 and choice is not None
        true = geometry.Pose(fs.truth["rvec"][k], fs.truth["tvec"][k])
        deg, rel = pose_error(Pose(choice.pose.rvec, choice.pose.tvec), Pose(true.rvec, true.tvec))
        # a convention error (frame flipped, a square off) would be degrees and centimetres
        assert deg < 1.5 and rel < 0.003
        px = geometry.project_to_pixels(edge, choice.pose, s.intrinsics) - geometry.project_to_pixels(edge, true, s.intrinsics)
        assert np.abs(px).max() < 1.0  # the reflector's outline where it is

