"""Tests of mscal_core.geometry: intrinsics, marker detection, pose, plane mapping, mask."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mscal_core.errors import FitError, InputError
from mscal_core.geometry import (
    Intrinsics,
    Pose,
    detect_marker,
    estimate_pose,
    image_points_to_plane,
    marker_object_points,
    pixels_to_plane,
    project_to_pixels,
    reflector_cells,
    reflector_mask,
    reflector_window,
    window_of_cells,
)

SHAPE = (217, 409)
K_PLAIN = Intrinsics(fx=420.0, fy=418.0, cx=204.2, cy=108.6)
K_DIST = Intrinsics(
    fx=420.0, fy=418.0, cx=204.2, cy=108.6, dist=(-0.28, 0.09, 0.0012, -0.0007, -0.015)
)


def render_marker(
    pose: Pose,
    intrinsics: Intrinsics,
    marker_size_m: float = 0.1,
    border_m: float = 0.02,
    marker_id: int = 7,
    dictionary: int = cv2.aruco.DICT_4X4_50,
    shape: tuple[int, int] = SHAPE,
    background: float = 0.45,
) -> np.ndarray:
    """10-bit image (uint16) of a marker on white paper on a gray reflector (no distortion)."""
    side_px = 240
    aruco = cv2.aruco.getPredefinedDictionary(dictionary)
    marker = cv2.aruco.generateImageMarker(aruco, marker_id, side_px)
    border_px = int(round(border_m / marker_size_m * side_px))
    sheet = cv2.copyMakeBorder(marker, border_px, border_px, border_px, border_px,
                               cv2.BORDER_CONSTANT, value=255)
    n = sheet.shape[0]
    half = 0.5 * marker_size_m + border_m
    # sheet pixel edges (-0.5 .. n-0.5) <-> plane (-half .. +half), v up
    src = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]], np.float32)
    plane = np.array([[-half, half], [half, half], [half, -half], [-half, -half]])
    # render 4x supersampled then box-average: hi-res A = 4 a + 1.5 (pixel centres integer)
    ss = 4
    dst = (ss * project_to_pixels(plane, pose, intrinsics) + 0.5 * (ss - 1)).astype(np.float32)
    hom = cv2.getPerspectiveTransform(src, dst)
    sheet_f = sheet.astype(np.float32) / 255.0
    size_hi = (shape[1] * ss, shape[0] * ss)
    warped = cv2.warpPerspective(sheet_f, hom, size_hi, flags=cv2.INTER_LINEAR)
    cover = cv2.warpPerspective(np.ones_like(sheet_f), hom, size_hi, flags=cv2.INTER_LINEAR)
    hi = warped + (1.0 - cover) * background
    img = cv2.resize(hi, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(3)
    dn = 60 + 800 * img + rng.normal(0, 4, img.shape)
    return np.clip(np.rint(dn), 0, 1023).astype(np.uint16)


def rotation_angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    rel = cv2.Rodrigues(r1)[0] @ cv2.Rodrigues(r2)[0].T
    return float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))


# --------------------------------------------------------------------------- intrinsics


def test_intrinsics_matrix_and_dist():
    k = Intrinsics(400, 401, 200.5, 100.5, [0.1, -0.01])
    np.testing.assert_array_equal(k.matrix, [[400, 0, 200.5], [0, 401, 100.5], [0, 0, 1]])
    np.testing.assert_array_equal(k.dist_coeffs, [0.1, -0.01, 0, 0, 0])
    assert k.dist == (0.1, -0.01, 0.0, 0.0, 0.0)
    assert Intrinsics(1, 1, 0, 0).dist_coeffs.shape == (5,)


@pytest.mark.parametrize(
    "args",
    [(0, 400, 1, 1), (400, -1, 1, 1), (float("nan"), 400, 1, 1), ("a", 1, 1, 1)],
)
def test_intrinsics_rejects_bad_focal(args):
    with pytest.raises(InputError):
        Intrinsics(*args)


def test_intrinsics_rejects_bad_dist():
    with pytest.raises(InputError):
        Intrinsics(400, 400, 1, 1, (0.1, 0, 0, 0, 0, 0.3))
    with pytest.raises(InputError):
        Intrinsics(400, 400, 1, 1, (np.inf, 0, 0, 0, 0))


# --------------------------------------------------------------------------- plane mapping


def test_marker_object_points_order():
    np.testing.assert_array_equal(
        marker_object_points(0.2),
        [[-0.1, 0.1, 0], [0.1, 0.1, 0], [0.1, -0.1, 0], [-0.1, -0.1, 0]],
    )


def test_image_points_to_plane_inverts_projection_with_distortion():
    pose = Pose(np.array([0.35, -0.25, 0.15]), np.array([0.04, -0.03, 0.75]))
    rng = np.random.default_rng(0)
    uv = rng.uniform(-0.25, 0.25, (2000, 2))
    px = project_to_pixels(uv, pose, K_DIST)
    # cv2.projectPoints is the reference forward model
    obj = np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)
    ref, _ = cv2.projectPoints(obj, pose.rvec, pose.tvec, K_DIST.matrix, K_DIST.dist_coeffs)
    np.testing.assert_allclose(px, ref.reshape(-1, 2), atol=1e-12)
    inside = (px[:, 0] > -1) & (px[:, 0] < SHAPE[1]) & (px[:, 1] > -1) & (px[:, 1] < SHAPE[0])
    assert inside.sum() > 500
    back = image_points_to_plane(px[inside], pose, K_DIST)
    assert np.max(np.abs(back - uv[inside])) < 1e-6


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.4, 0.8)])
def test_pixels_to_plane_round_trip_grid(offset):
    pose = Pose(np.array([-0.2, 0.3, 0.05]), np.array([0.0, 0.02, 0.6]))
    uv = pixels_to_plane(pose, K_DIST, SHAPE, offset=offset)
    assert uv.shape == SHAPE + (2,)
    ok = np.isfinite(uv[..., 0])
    assert ok.all()
    px = project_to_pixels(uv.reshape(-1, 2), pose, K_DIST).reshape(SHAPE + (2,))
    jj, ii = np.meshgrid(np.arange(SHAPE[1]) + offset[0], np.arange(SHAPE[0]) + offset[1])
    assert np.max(np.abs(px[..., 0] - jj)) < 1e-6
    assert np.max(np.abs(px[..., 1] - ii)) < 1e-6


def test_pixels_to_plane_fronto_parallel_scale_and_axes():
    # camera 1 m in front of the marker, marker frame axes = camera axes flipped in y:
    # rotate 180 deg about x so the marker faces the camera with v up.
    pose = Pose(np.array([np.pi, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    k = Intrinsics(500, 500, 200, 100)
    uv = pixels_to_plane(pose, k, (201, 401))
    np.testing.assert_allclose(uv[100, 200], [0.0, 0.0], atol=1e-12)
    # one pixel to the right = +1/500 m in u; one pixel down = -1/500 m in v (v is up)
    np.testing.assert_allclose(uv[100, 201] - uv[100, 200], [0.002, 0.0], atol=1e-12)
    np.testing.assert_allclose(uv[101, 200] - uv[100, 200], [0.0, -0.002], atol=1e-12)


def test_pixels_to_plane_nan_where_ray_misses():
    # plane tilted 80 deg about x, so the upper part of the image looks above the horizon
    pose = Pose(np.array([np.pi - np.radians(80), 0.0, 0.0]), np.array([0.0, 0.0, 0.5]))
    uv = pixels_to_plane(pose, K_PLAIN, SHAPE)
    miss = np.isnan(uv[..., 0])
    assert miss.any() and (~miss).any()
    assert np.array_equal(miss, np.isnan(uv[..., 1]))
    # the plane is behind the camera entirely
    behind = Pose(np.array([np.pi, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]))
    assert np.isnan(pixels_to_plane(behind, K_PLAIN, (5, 7))).all()


def _on_reflector(pose: Pose, k: Intrinsics, size: tuple[float, float], offset=(0.0, 0.0)) -> np.ndarray:
    uv = pixels_to_plane(pose, k, SHAPE, offset=offset)
    with np.errstate(invalid="ignore"):
        return (np.abs(uv[..., 0]) <= size[0] / 2) & (np.abs(uv[..., 1]) <= size[1] / 2)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.4, 0.8), (-0.5, 0.25)])
def test_reflector_window_holds_every_reflector_pixel(offset):
    """Random oblique poses through a strongly distorted lens: every pixel whose plane point is
    on the reflector is inside the window, which is a fraction of the band when the reflector
    is small in the view."""
    rng = np.random.default_rng(5)
    size = (0.5, 0.4)
    small = 0
    for _ in range(24):
        rvec = np.array([np.pi, 0.0, 0.0]) + rng.uniform(-0.6, 0.6, 3)
        tvec = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(0.5, 1.6)])
        pose = Pose(rvec, tvec)
        rows, cols = reflector_window(pose, K_DIST, SHAPE, size, offset)
        on = _on_reflector(pose, K_DIST, size, offset)
        inside = np.zeros(SHAPE, dtype=bool)
        inside[rows, cols] = True
        assert not (on & ~inside).any(), (rvec, tvec)
        if on.any():
            rr, cc = np.nonzero(on)
            # tight: at most the sample spacing plus the margin beyond the reflector's pixels
            assert rows.start >= rr.min() - 20 and cols.start >= cc.min() - 20
        small += inside.sum() < 0.5 * inside.size
    assert small >= 6


def test_reflector_window_whole_band_when_unbounded():
    # part of the reflector behind the camera: no box, the whole band
    grazing = Pose(np.array([np.pi - np.radians(85), 0.0, 0.0]), np.array([0.0, 0.0, 0.3]))
    assert reflector_window(grazing, K_PLAIN, SHAPE, 5.0) == (slice(0, SHAPE[0]), slice(0, SHAPE[1]))
    # the reflector entirely off the image: an empty box, and no pixel sees it
    aside = Pose(np.array([np.pi, 0.0, 0.0]), np.array([3.0, 0.0, 1.0]))
    rows, cols = reflector_window(aside, K_PLAIN, SHAPE, 0.5)
    assert (rows.stop - rows.start) * (cols.stop - cols.start) == 0
    assert not _on_reflector(aside, K_PLAIN, (0.5, 0.5)).any()


def test_reflector_mask():
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 61), np.linspace(-0.2, 0.2, 41))
    uv = np.stack([u, v], axis=-1)
    uv[0, 0] = np.nan
    m = reflector_mask(uv, [0.5, 0.3], exclude_half_m=0.08, edge_margin_m=0.01)
    au, av = np.abs(u), np.abs(v)
    expect = (au <= 0.24 + 1e-12) & (av <= 0.14 + 1e-12) & ~((au <= 0.08) & (av <= 0.08))
    expect[0, 0] = False
    # exact comparisons at the boundaries depend on float rounding of linspace: compare away
    boundary = (np.isclose(au, 0.24) | np.isclose(av, 0.14) | np.isclose(au, 0.08)
                | np.isclose(av, 0.08))
    assert np.array_equal(m[~boundary], expect[~boundary])
    assert not m[20, 30]  # marker centre
    assert m[20, 30 + 15]  # u = 0.15, v = 0
    assert not m[20, 60]  # u = 0.3 outside
    with pytest.raises(InputError):
        reflector_mask(uv, [0.5, -1], 0.08, 0.01)


# --------------------------------------------------------------------------- detection + pose


@pytest.mark.parametrize(
    "rvec_deg, tvec",
    [
        ((155.0, 0.0, 0.0), (0.0, 0.0, 0.6)),
        ((160.0, 15.0, 10.0), (0.05, -0.02, 0.55)),
        ((-150.0, -20.0, 30.0), (-0.08, 0.03, 0.7)),
    ],
)
def test_detect_and_pose_from_rendered_marker(rvec_deg, tvec):
    # rotation: rotate about x by the first angle (facing the camera) then small tilts
    rx, ry, rz = np.radians(rvec_deg)
    rot = (cv2.Rodrigues(np.array([0.0, 0.0, rz]))[0] @ cv2.Rodrigues(np.array([0.0, ry, 0.0]))[0]
           @ cv2.Rodrigues(np.array([rx, 0.0, 0.0]))[0])
    true = Pose(cv2.Rodrigues(rot)[0].ravel(), np.array(tvec))
    img = render_marker(true, K_PLAIN, marker_size_m=0.1)
    corners = detect_marker(img, "DICT_4X4_50", 7)
    assert corners is not None and corners.shape == (4, 2) and corners.dtype == np.float64
    expected = project_to_pixels(marker_object_points(0.1)[:, :2], true, K_PLAIN)
    assert np.max(np.linalg.norm(corners - expected, axis=1)) < 0.5  # pixels, order TL..BL
    pose = estimate_pose(corners, 0.1, K_PLAIN)
    assert rotation_angle_deg(pose.rvec, true.rvec) < 1.0
    assert np.linalg.norm(pose.tvec - true.tvec) < 0.01 * np.linalg.norm(true.tvec)
    # what the vignetting fit needs: the pixel -> plane map over a 0.4 x 0.3 m reflector is
    # right to about a pixel footprint (~1.4 mm here)
    uv_true = pixels_to_plane(true, K_PLAIN, SHAPE)
    uv_est = pixels_to_plane(pose, K_PLAIN, SHAPE)
    on = reflector_mask(uv_true, [0.4, 0.3], 0.06, 0.0)
    assert on.sum() > 5000
    assert np.max(np.linalg.norm(uv_true - uv_est, axis=-1)[on]) < 0.003


def test_detect_marker_wrong_id_and_float_image():
    true = Pose(np.array([np.pi, 0.0, 0.0]), np.array([0.0, 0.0, 0.6]))
    img = render_marker(true, K_PLAIN, marker_id=3)
    assert detect_marker(img, "DICT_4X4_50", 4) is None
    assert detect_marker(img.astype(np.float32) / 1023.0, "DICT_4X4_50", 3) is not None
    assert detect_marker(np.zeros(SHAPE), "DICT_4X4_50", 3) is None


def test_detect_marker_unknown_dictionary():
    with pytest.raises(InputError, match="DICT_FOO"):
        detect_marker(np.zeros((10, 10)), "DICT_FOO", 0)
    with pytest.raises(InputError):
        detect_marker(np.zeros((10, 10)), "__class__", 0)


def test_estimate_pose_rejects_bad_input():
    with pytest.raises(InputError):
        estimate_pose(np.zeros((3, 2)), 0.1, K_PLAIN)
    with pytest.raises(InputError):
        estimate_pose(np.zeros((4, 2)), 0.0, K_PLAIN)


def test_estimate_pose_behind_camera_rejected(monkeypatch):
    import mscal_core.geometry as geometry

    def fake_solve(*args, **kwargs):
        return True, np.array([[np.pi], [0.0], [0.0]]), np.array([[0.0], [0.0], [-0.5]])

    monkeypatch.setattr(geometry.cv2, "solvePnP", fake_solve)
    with pytest.raises(FitError, match="behind"):
        estimate_pose(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float), 0.1, K_PLAIN)


def _window_shifted_first(pose: Pose, k: Intrinsics, size, offset) -> tuple[slice, slice]:
    """reflector_window as first written: the projection shifted by the band's offset, then boxed."""
    n = 33
    uu, vv = np.meshgrid(np.linspace(-size[0] / 2, size[0] / 2, n), np.linspace(-size[1] / 2, size[1] / 2, n))
    xy = project_to_pixels(np.stack([uu.ravel(), vv.ravel()], axis=1), pose, k).reshape(n, n, 2)
    px, py = xy[..., 0] - offset[0], xy[..., 1] - offset[1]
    cx = np.stack([px[:-1, :-1], px[1:, :-1], px[:-1, 1:], px[1:, 1:]])
    cy = np.stack([py[:-1, :-1], py[1:, :-1], py[:-1, 1:], py[1:, 1:]])
    x0, x1, y0, y1 = cx.min(0) - 2.0, cx.max(0) + 2.0, cy.min(0) - 2.0, cy.max(0) + 2.0
    h, w = SHAPE
    reach = (x1 >= 0) & (x0 <= w - 1) & (y1 >= 0) & (y0 <= h - 1)
    if not reach.any():
        return slice(0, 0), slice(0, 0)
    return (slice(max(int(np.floor(y0[reach].min())), 0), min(int(np.ceil(y1[reach].max())) + 1, h)),
            slice(max(int(np.floor(x0[reach].min())), 0), min(int(np.ceil(x1[reach].max())) + 1, w)))


def test_one_projection_serves_every_band_offset():
    """The cells projected once (reflector_cells) give each band offset the window that
    projecting and shifting for that band gives, to the pixel: the main process projects each
    view once for all the bands of a band-grid camera."""
    rng = np.random.default_rng(7)
    size = (0.5, 0.4)
    offsets = [(float(dx), float(dy)) for dx, dy in rng.uniform(-2.0, 2.0, (25, 2))]
    partial = 0
    for _ in range(12):
        pose = Pose(np.array([np.pi, 0.0, 0.0]) + rng.uniform(-0.6, 0.6, 3),
                    np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(0.5, 1.6)]))
        cells = reflector_cells(pose, K_DIST, size)
        assert cells is not None and cells.shape == (4, 32, 32)
        for off in offsets:
            got = window_of_cells(cells, SHAPE, off)
            assert got == _window_shifted_first(pose, K_DIST, size, off) == reflector_window(pose, K_DIST, SHAPE, size, off)
            partial += (got[0].stop - got[0].start) * (got[1].stop - got[1].start) < SHAPE[0] * SHAPE[1]
    assert partial > 100  # windows smaller than the band are compared, not only whole bands
    assert window_of_cells(None, SHAPE, (0.5, 0.5)) == (slice(0, SHAPE[0]), slice(0, SHAPE[1]))
