"""A ChArUco board in place of the single marker: session.yaml's strict ``marker`` key and
calibrate's pose of a rendered board (band-grid offset included)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mscal_core import charuco, geometry
from mscal_core.errors import MscalError
from pipeline.calibrate.views import exclude_half, marker_pose
from pipeline.ingest.session import load_session

SESSION_YAML = """\
camera: ximea-mq022hg-sm5x5-nir
intrinsics: {fx: 436.0, fy: 436.0, cx: 204.0, cy: 108.0, dist: [-0.12, 0.05, 0.0012, -0.0008, 0.0]}
reflector: {reflectance: 0.5, size_m: [0.5, 0.5]}
marker: {type: charuco, squares_x: 7, squares_y: 5, square_mm: 40, marker_mm: 30, dictionary: DICT_4X4_50}
"""


def _session(tmp_path: Path, text: str = SESSION_YAML):
    (tmp_path / "session.yaml").write_text(text)
    return load_session(tmp_path)


def test_charuco_marker_key(tmp_path) -> None:
    s = _session(tmp_path)
    board = s.marker.board
    assert board == charuco.CharucoSpec(7, 5, 0.04, 0.03, "DICT_4X4_50")
    assert s.marker.size_m == pytest.approx(0.28) and s.marker.border_m == 0.0
    assert s.marker.label == "ChArUco board 7x5 DICT_4X4_50"
    # the board (its larger side) is the reflector's excluded centre, with the margin
    assert exclude_half(s) == pytest.approx(0.14 + 0.005)
    # the single marker reads as before, with or without type: aruco
    s = _session(tmp_path, SESSION_YAML.replace(
        "{type: charuco, squares_x: 7, squares_y: 5, square_mm: 40, marker_mm: 30, dictionary: DICT_4X4_50}",
        "{type: aruco, dictionary: DICT_4X4_50, id: 3, size_m: 0.1}"))
    assert s.marker.board is None and s.marker.label == "marker DICT_4X4_50 id 3"


@pytest.mark.parametrize("edit, message", [
    (("marker_mm: 30", "marker_mm: 30, id: 3"), "marker (type charuco): unknown key(s) id"),
    (("square_mm: 40, ", ""), "marker (type charuco): missing key(s) square_mm"),
    (("marker_mm: 30", "marker_mm: 45"), "0 < marker < square"),
    (("squares_x: 7", "squares_x: 1"), "marker.squares_x must be an integer of at least 2"),
    (("type: charuco", "type: april"), "marker.type must be one of aruco, charuco, got 'april'"),
    (("square_mm: 40", "square_mm: 80"), "the board and its border cover the whole reflector"),
    (("DICT_4X4_50}", "DICT_NOPE}"), "marker.dictionary 'DICT_NOPE' is not an OpenCV"),
])
def test_bad_charuco_marker_key(tmp_path, edit, message) -> None:
    with pytest.raises(MscalError) as err:
        _session(tmp_path, SESSION_YAML.replace(*edit))
    assert message in str(err.value)


def _render(spec: charuco.CharucoSpec, pose: geometry.Pose, intr: geometry.Intrinsics,
            offset: tuple[float, float]) -> np.ndarray:
    """The board on the gray reflector, pixel (i, j) seeing image point (j + dx, i + dy)
    (4 x 4 rays per pixel through the distorted pinhole)."""
    per, (w, h), shape = 80, spec.size_m, (217, 409)
    img = spec.board().generateImage((spec.squares_x * per, spec.squares_y * per)).astype(np.float32) / 255
    acc = np.zeros(shape)
    for dy in (np.arange(4) + 0.5) / 4 - 0.5:
        for dx in (np.arange(4) + 0.5) / 4 - 0.5:
            uv = geometry.pixels_to_plane(pose, intr, shape, (offset[0] + dx, offset[1] + dy))
            col = np.nan_to_num((uv[..., 0] + w / 2) / spec.square_m * per - 0.5).astype(np.float32)
            row = np.nan_to_num((h / 2 - uv[..., 1]) / spec.square_m * per - 0.5).astype(np.float32)
            val = cv2.remap(img, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            acc += np.where((np.abs(uv[..., 0]) < w / 2) & (np.abs(uv[..., 1]) < h / 2), 0.05 + 0.85 * val, 0.5)
    return np.rint(acc / 16 * 900).astype(np.uint16)


def test_calibrate_poses_a_rendered_board(tmp_path) -> None:
    s = _session(tmp_path)
    R = cv2.Rodrigues(np.array([0.5, 0.2, 0.0]))[0] @ np.diag([1.0, -1.0, -1.0])  # 31 deg tilt
    truth = geometry.Pose(cv2.Rodrigues(R)[0].ravel(), [0.02, 0.01, 0.65])
    offset = (0.4, 0.4)  # the band-grid detection image's mean band offset
    img = _render(s.marker.board, truth, s.intrinsics, offset)
    choice = marker_pose(img, s.marker, s.intrinsics, [], offset)
    assert choice is not None and choice.solution == 0 and choice.by == "reprojection"
    angle = np.degrees(np.arccos(np.clip((np.trace(truth.rotation.T @ choice.pose.rotation) - 1) / 2, -1, 1)))
    assert angle < 0.3
    assert np.linalg.norm(choice.pose.tvec - truth.tvec) < 0.002 * np.linalg.norm(truth.tvec)
    # the reflector's edges, beyond the board, land within 0.5 px of where they are
    edge = np.array([[x, y] for x in (-0.25, 0.25) for y in np.linspace(-0.25, 0.25, 11)])
    px = geometry.project_to_pixels(edge, choice.pose, s.intrinsics)
    assert np.abs(px - geometry.project_to_pixels(edge, truth, s.intrinsics)).max() < 0.5
    assert marker_pose(np.full((217, 409), 450, np.uint16), s.marker, s.intrinsics, [], offset) is None
