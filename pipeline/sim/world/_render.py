"""Rendering a scene through the synthetic camera, and reading its ArUco marker (or ChArUco
board) back."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ._camera import Pose, SnapshotCamera, intersect_plane
from ._targets import CharucoBoardSpec, MarkerSpec

#: Chessboard corners a ChArUco view needs to count as found (as calibrate's pose needs).
MIN_BOARD_CORNERS = 6


@dataclass
class Render:
    """Result of :func:`render` for one pose, per band on the band grid.

    Attributes
    ----------
    channels : numpy.ndarray
        (K, n_bands, H, W) float32: footprint integral of ``B x area`` of each material (ground
        texture included); radiance per band is ``S * sum_k channels_k * R_k``.
    labels : numpy.ndarray
        (n_bands, H, W) uint8 hard label at each sample centre (255 where the ray misses the
        plane).
    edge : numpy.ndarray
        (n_bands, H, W) bool: the sample's footprint (or a neighbour's) straddles a hard edge or
        lies within the lens PSF's reach (3 sigma) of one, so it is not a pure sample of its
        label.
    sensor_u, sensor_v : numpy.ndarray
        (Hs, Ws) plane point of every sensor pixel centre (see :meth:`plane_uv`).
    pattern_shape : tuple of int
        The camera's mosaic pattern.
    reach_px : int
        The PSF reach in sensor pixels.
    """

    channels: np.ndarray
    labels: np.ndarray
    edge: np.ndarray
    sensor_u: np.ndarray
    sensor_v: np.ndarray
    pattern_shape: tuple[int, int]
    reach_px: int = 1

    def light_times_reflectance(self, reflectance: np.ndarray) -> np.ndarray:
        """``B x R`` per band (n_bands, H, W) float64 for material spectra (K, n_bands)."""
        return np.einsum("kbhw,kb->bhw", self.channels, reflectance, dtype=np.float64)

    def pure(self, label: int) -> np.ndarray:
        """(H, W) band-grid pixels whose samples in every band lie well inside ``label``."""
        return np.all((self.labels == label) & ~self.edge, axis=0)

    def plane_uv(self, band: int) -> tuple[np.ndarray, np.ndarray]:
        """Plane point (u, v) of each pixel centre of ``band``, (H, W) each (1e6 on a miss)."""
        rows, cols = self.pattern_shape
        r, c = divmod(int(band), cols)
        return self.sensor_u[r::rows, c::cols], self.sensor_v[r::rows, c::cols]


def render(camera: SnapshotCamera, pose: Pose, scene, *, supersample: int = 4,
           psf_sigma_px: float = 1.2) -> Render:
    """Render a planar ``scene`` seen from ``pose`` through the distorted pinhole.

    Parameters
    ----------
    camera : SnapshotCamera
        The camera.
    pose : Pose
        Pose of the scene plane in the camera frame.
    scene : ReflectorScene or FieldScene
        Anything with ``evaluate(u, v)`` returning material weights and labels.
    supersample : int
        Edge pixels are re-evaluated on a ``supersample x supersample`` grid over the sensor
        pixel (100 % fill factor) and averaged.
    psf_sigma_px : float
        Gaussian lens PSF in sensor pixels (0.24 band-grid pixels by default).

    Returns
    -------
    Render
        Material channels, labels and edge flags per band.

    Notes
    -----
    Every sensor pixel centre (band-grid point ``(xs/5, ys/5)``) is back-projected and
    intersected with the plane; pixels whose 3 x 3 neighbourhood crosses a hard label edge are
    supersampled; the PSF is applied to the material channels (radiance is linear in them),
    then the sensor grid is split into bands.
    """
    xn, yn, (dxx, dxy, dyx, dyy) = camera.sensor_rays()
    u, v, ok = intersect_plane(pose, xn, yn)
    w, lab = scene.evaluate(u, v)
    w *= ok
    lab = np.where(ok, lab, 255).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    edge = cv2.dilate(lab, kernel) != cv2.erode(lab, kernel)
    iy, ix = np.nonzero(edge)
    if iy.size and supersample > 1:
        n = supersample
        off = (np.arange(n) + 0.5) / n - 0.5
        ox, oy = np.meshgrid(off, off)
        ox, oy = ox.ravel().astype(np.float32), oy.ravel().astype(np.float32)
        sx = xn[iy, ix][:, None] + dxx[iy, ix][:, None] * ox + dxy[iy, ix][:, None] * oy
        sy = yn[iy, ix][:, None] + dyx[iy, ix][:, None] * ox + dyy[iy, ix][:, None] * oy
        su, sv, sok = intersect_plane(pose, sx, sy)
        ws_, _ = scene.evaluate(su, sv)
        ws_ *= sok
        w[:, iy, ix] = ws_.mean(axis=-1)
    if psf_sigma_px > 0:
        for k in range(w.shape[0]):
            w[k] = cv2.GaussianBlur(w[k], (0, 0), psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    reach = int(math.ceil(3.0 * psf_sigma_px)) + 1
    near = cv2.dilate(edge.astype(np.uint8), disk_kernel(reach)).astype(bool)
    return Render(
        channels=camera.split_bands(w),
        labels=camera.split_bands(lab),
        edge=camera.split_bands(near),
        sensor_u=u, sensor_v=v, pattern_shape=tuple(camera.pattern_shape), reach_px=reach,
    )


def disk_kernel(radius: int) -> np.ndarray:
    """Return a filled disk structuring element of ``radius`` pixels (uint8)."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def detect_marker_corners(image: np.ndarray, marker: MarkerSpec | CharucoBoardSpec,
                          min_marker_distance_rate: float = 0.05) -> np.ndarray | None:
    """Find the ArUco corners of ``marker`` in a band image (any dtype), for checks.

    Parameters
    ----------
    image : numpy.ndarray
        One band.
    marker : MarkerSpec or CharucoBoardSpec
        The marker (or board: :func:`detect_board_corners`, its corners without their ids).
    min_marker_distance_rate : float
        OpenCV's ``minMarkerDistanceRate``.

    Returns
    -------
    numpy.ndarray or None
        (4, 2) corners (a board: (N, 2) chessboard corners, N >= ``MIN_BOARD_CORNERS``), or
        None.

    Notes
    -----
    0.5-99.5 percentile stretch to 8 bits, ``CORNER_REFINE_SUBPIX`` (window 3). OpenCV's default
    ``minMarkerDistanceRate`` (0.125) merges the marker with the outline of its white paper when
    the paper border is narrower than ~0.35 marker sides, and then keeps the paper outline
    (which does not decode): the marker is lost in some views. 0.05 avoids that.
    """
    if isinstance(marker, CharucoBoardSpec):
        found = detect_board_corners(image, marker, min_marker_distance_rate)
        return None if found is None else found[0]
    img8 = _stretch(image)
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, marker.dictionary))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 3
    params.cornerRefinementMaxIterations = 50
    params.cornerRefinementMinAccuracy = 0.01
    params.minMarkerDistanceRate = float(min_marker_distance_rate)
    det = cv2.aruco.ArucoDetector(d, params)
    corners, ids, _ = det.detectMarkers(img8)
    if ids is None:
        return None
    for c, i in zip(corners, ids.ravel()):
        if int(i) == marker.id:
            return c.reshape(4, 2).astype(np.float64)
    return None


def _stretch(image: np.ndarray) -> np.ndarray:
    """0.5-99.5 percentile stretch of a band image to 8 bits."""
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [0.5, 99.5])
    return np.clip(np.rint((img - lo) / max(hi - lo, 1e-9) * 255.0), 0, 255).astype(np.uint8)


def detect_board_corners(image: np.ndarray, board: CharucoBoardSpec,
                         min_marker_distance_rate: float = 0.05) -> tuple[np.ndarray, np.ndarray] | None:
    """Find a ChArUco board's chessboard corners in a band image (any dtype), for checks.

    Returns
    -------
    tuple or None
        ``(corners (N, 2), ids (N,))`` from ``cv2.aruco.CharucoDetector`` (markers found, the
        corners between them interpolated and refined on the saddle points), or None with
        fewer than ``MIN_BOARD_CORNERS``.
    """
    params = cv2.aruco.DetectorParameters()
    params.minMarkerDistanceRate = float(min_marker_distance_rate)
    det = cv2.aruco.CharucoDetector(board.board(), cv2.aruco.CharucoParameters(), params)
    corners, ids, _, _ = det.detectBoard(_stretch(image))
    if ids is None or corners is None or len(ids) < MIN_BOARD_CORNERS:
        return None
    return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64)


def marker_pose_from_image(image: np.ndarray, band: int, camera: SnapshotCamera,
                           marker: MarkerSpec | CharucoBoardSpec) -> Pose | None:
    """Estimate the pose of the marker seen in one band image.

    Parameters
    ----------
    image : numpy.ndarray
        One band.
    band : int
        Its index (for the band's offset on the band grid).
    camera : SnapshotCamera
        The camera.
    marker : MarkerSpec or CharucoBoardSpec
        The marker (or board).

    Returns
    -------
    Pose or None
        ArUco corners (+ the band's offset) and ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` with
        corners TL, TR, BR, BL = (-s/2, +s/2), (+s/2, +s/2), (+s/2, -s/2), (-s/2, -s/2). None if
        the marker is not found. A board: its chessboard corners and ``SOLVEPNP_IPPE`` (the
        solution of smaller reprojection error).
    """
    if isinstance(marker, CharucoBoardSpec):
        found = detect_board_corners(image, marker)
        if found is None:
            return None
        obj = marker.corners_m()[found[1]]
        ok, rvec, tvec = cv2.solvePnP(obj, (found[0] + camera.band_offsets[band]).reshape(-1, 1, 2),
                                      camera.matrix, camera.dist_coeffs, flags=cv2.SOLVEPNP_IPPE)
        return Pose(rvec.reshape(3), tvec.reshape(3)) if ok else None
    c = detect_marker_corners(image, marker)
    if c is None:
        return None
    c = c + camera.band_offsets[band]
    h = 0.5 * marker.size_m
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    ok, rvec, tvec = cv2.solvePnP(obj, c.reshape(4, 1, 2), camera.matrix, camera.dist_coeffs,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        return None
    return Pose(rvec.reshape(3), tvec.reshape(3))


def pose_error(estimate: Pose, truth: Pose) -> tuple[float, float]:
    """Return the rotation error in degrees and the relative translation error of ``estimate``.

    Parameters
    ----------
    estimate, truth : Pose
        The estimated and the true pose.

    Returns
    -------
    tuple of float
        ``(rotation error in degrees, |t_est - t_true| / |t_true|)``.
    """
    dR = truth.R.T @ estimate.R
    ang = math.degrees(math.acos(float(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    rel = float(np.linalg.norm(estimate.tvec - truth.tvec) / np.linalg.norm(truth.tvec))
    return ang, rel
