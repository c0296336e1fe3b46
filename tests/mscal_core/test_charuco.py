"""Tests of mscal_core.charuco: a ChArUco board rendered through a distorted pinhole, found and posed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mscal_core import charuco, geometry
from mscal_core.errors import InputError

#: The session camera's band grid (focal length, principal point, distortion).
INTR = geometry.Intrinsics(436.0, 436.0, 204.0, 108.0, (-0.12, 0.05, 0.0012, -0.0008, 0.0))
SHAPE = (217, 409)
SPEC = charuco.CharucoSpec(squares_x=7, squares_y=5, square_m=0.04, marker_m=0.03, dictionary="DICT_4X4_50")


def _pose(tilt_deg: float, axis=(1.0, 0.4, 0.0), t=(0.03, -0.01, 0.6)) -> geometry.Pose:
    frontal = np.diag([1.0, -1.0, -1.0])  # camera looking straight at the printed board
    a = np.asarray(axis) / np.linalg.norm(axis)
    R = cv2.Rodrigues(a * np.deg2rad(tilt_deg))[0] @ frontal
    return geometry.Pose(cv2.Rodrigues(R)[0].ravel(), t)


def render_board(pose: geometry.Pose, spec: charuco.CharucoSpec = SPEC, ss: int = 4, noise: float = 0.0,
                 seed: int = 0) -> np.ndarray:
    """10-bit image of the board (on a 0.5 gray reflector) seen from ``pose`` through the
    distorted pinhole: every pixel the mean of ``ss x ss`` rays' plane points, looked up in
    OpenCV's own board image (80 px per square)."""
    per = 80
    w, h = spec.size_m
    img = spec.board().generateImage((spec.squares_x * per, spec.squares_y * per)).astype(np.float32) / 255.0
    acc = np.zeros(SHAPE)
    for dy in (np.arange(ss) + 0.5) / ss - 0.5:
        for dx in (np.arange(ss) + 0.5) / ss - 0.5:
            uv = geometry.pixels_to_plane(pose, INTR, SHAPE, (dx, dy))
            col = (uv[..., 0] + w / 2) / spec.square_m * per - 0.5
            row = (h / 2 - uv[..., 1]) / spec.square_m * per - 0.5
            inside = (np.abs(uv[..., 0]) < w / 2) & (np.abs(uv[..., 1]) < h / 2)
            val = cv2.remap(img, np.nan_to_num(col).astype(np.float32), np.nan_to_num(row).astype(np.float32),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            acc += np.where(inside, 0.05 + 0.85 * val, 0.5)
    dn = acc / ss**2 * 900 + np.random.default_rng(seed).normal(0, noise, SHAPE)
    return np.clip(np.rint(dn), 0, 1023).astype(np.uint16)


def _angle_deg(a: geometry.Pose, b: geometry.Pose) -> float:
    c = (np.trace(a.rotation.T @ b.rotation) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def test_board_points_are_centred_with_v_up():
    pts = charuco.board_points(SPEC)
    assert pts.shape == ((SPEC.squares_x - 1) * (SPEC.squares_y - 1), 3)
    np.testing.assert_allclose(pts.mean(axis=0), 0.0, atol=1e-7)  # OpenCV keeps float32
    # OpenCV's corner 0 is one square in from the top-left: (-W/2 + s, +H/2 - s) here
    np.testing.assert_allclose(pts[0], [-0.14 + 0.04, 0.10 - 0.04, 0.0], atol=1e-7)
    np.testing.assert_allclose(charuco.board_points(SPEC, [1])[0], [-0.06, 0.06, 0.0], atol=1e-7)


@pytest.mark.parametrize("tilt", [0.0, 30.0, 50.0])
def test_rendered_board_is_found_and_posed(tilt):
    truth = _pose(tilt)
    img = render_board(truth, noise=4.0, seed=int(tilt))
    found = charuco.detect_charuco(img, SPEC)
    assert found is not None
    corners, ids = found
    assert ids.size == 24  # every inner corner of the 7 x 5 board
    true_px = geometry.project_to_pixels(charuco.board_points(SPEC, ids)[:, :2], truth, INTR)
    err = np.linalg.norm(corners - true_px, axis=1)
    assert err.mean() < 0.15 and err.max() < 0.4  # measured 0.08-0.11 mean
    choice = charuco.charuco_pose(corners, ids, SPEC, INTR)
    # a face-on plane's tilt is the least determined (1.0 deg measured); oblique: 0.04-0.1 deg
    assert _angle_deg(choice.pose, truth) < (1.5 if tilt == 0.0 else 0.3)
    assert np.linalg.norm(choice.pose.tvec - truth.tvec) < 0.002 * np.linalg.norm(truth.tvec)
    assert choice.solution == 0 and choice.reprojection_px[0] < 0.2
    # the mirrored solution reprojects clearly worse once the corners span the board
    if tilt >= 30.0:
        assert choice.reprojection_px[1] > 3 * choice.reprojection_px[0]
        assert _angle_deg(choice.alternative, truth) > 20.0


def test_board_not_in_view_and_bad_specs():
    assert charuco.detect_charuco(np.full(SHAPE, 500, np.uint16), SPEC) is None
    with pytest.raises(InputError):
        charuco.CharucoSpec(1, 5, 0.04, 0.03, "DICT_4X4_50")
    with pytest.raises(InputError):
        charuco.CharucoSpec(5, 5, 0.04, 0.05, "DICT_4X4_50")
    with pytest.raises(InputError):
        charuco.CharucoSpec(5, 5, 0.04, 0.03, "DICT_NOPE")
    with pytest.raises(InputError):
        charuco.charuco_pose(np.zeros((3, 2)), np.arange(3), SPEC, INTR)
