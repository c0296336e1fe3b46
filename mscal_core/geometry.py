"""Marker detection, marker pose and the pixel <-> reflector-plane mapping (no I/O).

The vignetting fit (Eq. 8-10) needs, for every image i of the gray reflector, the map
``pi_i: p -> x`` from a point ``p`` of the reflector plane to a pixel ``x``. The paper gets it
from the pose of the ArUco marker printed at the centre of the reflector (OpenCV) and the
camera intrinsics. Here the pose comes from :func:`estimate_pose` (``SOLVEPNP_IPPE_SQUARE``),
:func:`project_to_pixels` is ``pi_i`` itself and :func:`pixels_to_plane` is its inverse on the
pixel grid (ray / plane intersection), which is what the vignetting fit uses: every observed
pixel is mapped once to the plane cell that contains its centre.

Marker frame (see ``docs/architecture.md``): marker centre at the origin, plane ``z = 0``,
``u`` to the right and ``v`` **up** as seen printed; corners in the order top-left
``(-s/2, +s/2)``, top-right ``(+s/2, +s/2)``, bottom-right ``(+s/2, -s/2)``, bottom-left
``(-s/2, -s/2)``. Pixel ``(i, j)`` of a band has its centre at image point
``(x, y) = (j + dx, i + dy)`` (OpenCV convention: integer coordinates are pixel centres),
``(dx, dy)`` being the band's offset on the band grid (:func:`mscal_core.mosaic.band_offsets`).

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import FitError, InputError

__all__ = [
    "Intrinsics",
    "Pose",
    "detect_marker",
    "estimate_pose",
    "image_points_to_plane",
    "marker_object_points",
    "pixels_to_plane",
    "project_to_pixels",
    "reflector_cells",
    "reflector_mask",
    "reflector_window",
    "window_of_cells",
]

# Undistortion (cv2.undistortPoints) is iterative; the default 5 iterations leave errors of
# 1e-3 px and more with strong distortion. These criteria make it exact to ~1e-10.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# |cos| of the angle between a ray and the plane below which the ray is called parallel.
_PARALLEL_EPS = 1e-9
#: Largest half window of the corners' sub-pixel refinement (pixels) ...
CORNER_WINDOW_PX = 4
#: ... and the largest as a fraction of the marker's module (one cell of its bit grid).
CORNER_WINDOW_MODULES = 1.0


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole + OpenCV distortion intrinsics of the band grid.

    Attributes
    ----------
    fx, fy, cx, cy : float
        Focal lengths and principal point in band-grid pixels.
    dist : tuple of float
        ``(k1, k2, p1, p2, k3)`` (OpenCV order). A shorter ``dist`` is padded with zeros.

    Raises
    ------
    InputError
        On anything but finite numbers.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        """Validate the focal lengths, principal point and distortion."""
        values = []
        for name in ("fx", "fy", "cx", "cy"):
            try:
                value = float(getattr(self, name))
            except (TypeError, ValueError):
                raise InputError(
                    f"camera intrinsics: {name} must be a number, got {getattr(self, name)!r}",
                    hint="check the camera's intrinsics in its catalog entry",
                ) from None
            if not np.isfinite(value):
                raise InputError(
                    f"camera intrinsics: {name} must be finite, got {value}",
                    hint="check the camera's intrinsics in its catalog entry",
                )
            values.append(value)
            object.__setattr__(self, name, value)
        if values[0] <= 0 or values[1] <= 0:
            raise InputError(
                f"camera intrinsics: focal lengths must be positive, got fx={values[0]}, "
                f"fy={values[1]}",
                hint="check the camera's intrinsics in its catalog entry (band-grid pixels)",
            )
        try:
            dist = np.asarray(self.dist, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise InputError(
                f"camera intrinsics: dist must be 5 numbers [k1, k2, p1, p2, k3], "
                f"got {self.dist!r}",
                hint="check the camera's intrinsics in its catalog entry",
            ) from None
        if dist.size > 5 or not np.all(np.isfinite(dist)):
            raise InputError(
                f"camera intrinsics: dist must be at most 5 finite numbers [k1, k2, p1, p2, k3], "
                f"got {self.dist!r}",
                hint="check the camera's intrinsics in its catalog entry",
            )
        dist = np.concatenate([dist, np.zeros(5 - dist.size)])
        object.__setattr__(self, "dist", tuple(float(d) for d in dist))

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (float64)."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion vector ``(5,)`` float64: ``k1, k2, p1, p2, k3``."""
        return np.asarray(self.dist, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Pose:
    """Pose of the marker frame in the camera frame: ``X_cam = R(rvec) @ X_marker + tvec``.

    Attributes
    ----------
    rvec : numpy.ndarray
        (3,) Rodrigues rotation vector (float64 copy).
    tvec : numpy.ndarray
        (3,) translation in metres (float64 copy).

    Raises
    ------
    InputError
        Unless both are 3 finite numbers.
    """

    rvec: np.ndarray
    tvec: np.ndarray

    def __post_init__(self) -> None:
        """Validate ``rvec`` and ``tvec`` (3 finite numbers each)."""
        for name in ("rvec", "tvec"):
            value = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise InputError(f"pose: {name} must be 3 finite numbers, got {value!r}")
            value = value.copy()
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    @property
    def rotation(self) -> np.ndarray:
        """Rotation matrix (3, 3) marker -> camera."""
        return cv2.Rodrigues(self.rvec)[0]


def marker_object_points(marker_size_m: float) -> np.ndarray:
    """Return the marker corners in the marker frame, order TL, TR, BR, BL.

    Parameters
    ----------
    marker_size_m : float
        Side ``s`` of the marker in metres.

    Returns
    -------
    numpy.ndarray
        (4, 3) float64 ``(-s/2, +s/2, 0), (+s/2, +s/2, 0), (+s/2, -s/2, 0), (-s/2, -s/2, 0)``: the
        order ``SOLVEPNP_IPPE_SQUARE`` requires and ArUco detection returns.
    """
    h = 0.5 * float(marker_size_m)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]], dtype=np.float64)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """Robust 8-bit version of a single-band image for the marker detector.

    Linear stretch of the 0.5th..99.5th percentiles of the finite values to 0..255, so a
    10-bit (or any) DN range, a dark exposure or a few saturated pixels all give a usable
    contrast. Non-finite pixels become 0.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (1, 3, 4):
        img = img[..., :3].astype(np.float64).mean(axis=2)
    if img.ndim != 2:
        raise InputError(
            f"marker detection needs a single-band image (H, W), got shape {img.shape}"
        )
    data = img.astype(np.float64, copy=False)
    finite = np.isfinite(data)
    if not finite.any():
        return np.zeros(data.shape, dtype=np.uint8)
    lo, hi = np.percentile(data[finite], [0.5, 99.5])
    if hi <= lo:
        lo, hi = float(data[finite].min()), float(data[finite].max())
    if hi <= lo:
        return np.zeros(data.shape, dtype=np.uint8)
    scaled = (np.where(finite, data, lo) - lo) * (255.0 / (hi - lo))
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


def aruco_dictionary(dictionary: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined ArUco dictionary of a name such as ``"DICT_4X4_50"``; :class:`InputError` if unknown."""
    name = str(dictionary).strip()
    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(value, int):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise InputError(
            f"unknown ArUco dictionary {dictionary!r}",
            hint=f"use one of OpenCV's names, e.g. {', '.join(known[:4])}, ...",
        )
    return cv2.aruco.getPredefinedDictionary(value)


def detect_marker(image: np.ndarray, dictionary: str, marker_id: int) -> np.ndarray | None:
    """Find ArUco marker ``marker_id`` of ``dictionary`` in an image.

    Parameters
    ----------
    image : numpy.ndarray
        2-D image of any dtype (e.g. 10-bit DN); stretched to 8 bits (0.5-99.5 percentiles).
    dictionary : str
        OpenCV ArUco dictionary name, e.g. ``"DICT_4X4_50"``.
    marker_id : int
        The marker's id.

    Returns
    -------
    numpy.ndarray or None
        The corners (4, 2) float64 ``(x, y)`` pixels in the order top-left, top-right,
        bottom-right, bottom-left of the printed marker, or None if the id is not found. If the
        id is found more than once the largest one wins.

    Raises
    ------
    InputError
        For an unknown dictionary name or a non-2-D image.

    Notes
    -----
    Detected with ``cv2.aruco.ArucoDetector`` and the corners refined to sub-pixel accuracy
    (``CORNER_REFINE_SUBPIX``, half window ``min(CORNER_WINDOW_PX, CORNER_WINDOW_MODULES x
    module side)``). The paper takes the pose of each reflector image from this
    marker [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    detector_dict = aruco_dictionary(dictionary)
    gray = _to_uint8(image)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    # cornerSubPix's half window is min(cornerRefinementWinSize, relative x the marker's module
    # side in pixels). OpenCV's relative default (0.3) shrinks it to 1 px on band-grid markers
    # (modules of 4-8 px), which left 0.44 px mean corner error on the synthetic sessions; up to
    # one module (never reaching the inner bits), at most 4 px, measured 0.21 px.
    params.cornerRefinementWinSize = CORNER_WINDOW_PX
    params.relativeCornerRefinmentWinSize = CORNER_WINDOW_MODULES
    params.cornerRefinementMaxIterations = 50
    params.cornerRefinementMinAccuracy = 0.01
    # OpenCV's default (0.125) drops the marker in favour of the outline of the white paper
    # around it when the paper border is narrow (5-23 % of synthetic views were lost).
    params.minMarkerDistanceRate = 0.05
    detector = cv2.aruco.ArucoDetector(detector_dict, params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return None
    best: np.ndarray | None = None
    best_perimeter = -1.0
    for quad, found in zip(corners, np.asarray(ids).ravel()):
        if int(found) != int(marker_id):
            continue
        quad = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        perimeter = float(np.sum(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
        if perimeter > best_perimeter:
            best, best_perimeter = quad, perimeter
    return best


def estimate_pose(corners: np.ndarray, marker_size_m: float, intrinsics: Intrinsics) -> Pose:
    """Estimate the marker pose from its 4 image corners.

    Parameters
    ----------
    corners : numpy.ndarray
        (4, 2) pixels TL, TR, BR, BL (as :func:`detect_marker` returns), matched to
        :func:`marker_object_points`.
    marker_size_m : float
        Side of the marker in metres.
    intrinsics : Intrinsics
        The band grid's intrinsics.

    Returns
    -------
    Pose
        ``cv2.solvePnP`` with ``SOLVEPNP_IPPE_SQUARE``.

    Raises
    ------
    InputError
        On bad arguments.
    FitError
        If no pose is found or the marker plane would lie (partly) behind the camera.

    Notes
    -----
    The pose of the marker in image ``i`` fixes the map ``pi_i: p -> x`` from the reflector plane
    to the pixels that Eq. 8-10 of [1]_ need (:func:`project_to_pixels`).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    pts = np.asarray(corners, dtype=np.float64)
    if pts.shape != (4, 2) or not np.all(np.isfinite(pts)):
        raise InputError(f"marker corners must be (4, 2) finite pixels, got shape {pts.shape}")
    size = float(marker_size_m)
    if not np.isfinite(size) or size <= 0:
        raise InputError(
            f"marker size must be a positive length in metres, got {marker_size_m!r}",
            hint="check marker_size_m of the reflector target",
        )
    obj = marker_object_points(size)
    ok, rvec, tvec = cv2.solvePnP(
        obj, pts.reshape(4, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs,
        flags=cv2.SOLVEPNP_IPPE_SQUARE,
    )
    if not ok or rvec is None or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        raise FitError("no marker pose found from the detected corners")
    pose = Pose(rvec.ravel(), tvec.ravel())
    corners_cam = obj @ pose.rotation.T + pose.tvec
    if np.any(corners_cam[:, 2] <= 0):
        raise FitError(
            "the estimated marker pose puts the marker behind the camera",
            hint="check the intrinsics and the marker size",
        )
    return pose


def undistorted_rays(points_xy: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Return the viewing rays ``d = (x', y', 1)`` of image points, as normalised coordinates.

    Parameters
    ----------
    points_xy : numpy.ndarray
        (N, 2) image points in pixels.
    intrinsics : Intrinsics
        The band grid's intrinsics.

    Returns
    -------
    numpy.ndarray
        (N, 2) ``(x', y')``.

    Notes
    -----
    ``(x', y')`` inverts the pinhole + OpenCV distortion model (``cv2.undistortPoints``, iterated
    to convergence; OpenCV's default 5 iterations are not exact). The rays depend only on the
    intrinsics and the pixel positions, not on the pose: compute them once per band and reuse
    them for every view (:func:`rays_to_plane`).
    """
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return np.empty((0, 2))
    return cv2.undistortPoints(
        pts.reshape(-1, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs,
        criteria=_UNDISTORT_CRITERIA,
    ).reshape(-1, 2)


def rays_to_plane(rays: np.ndarray, pose: Pose) -> np.ndarray:
    """Return where rays ``d = (x', y', 1)`` meet the marker plane.

    Parameters
    ----------
    rays : numpy.ndarray
        (N, 2) normalised coordinates.
    pose : Pose
        Pose of the marker.

    Returns
    -------
    numpy.ndarray
        (N, 2) plane points (u, v); NaN where the ray is parallel to the plane or meets it
        behind the camera (``s <= 0``).

    Notes
    -----
    The plane is ``n . X = n . t`` (``n`` = third column of R); the ray meets it at ``X = s d``,
    ``s = (n . t) / (n . d)``, and ``(u, v, 0) = R^T (X - t)``.
    """
    norm = np.asarray(rays, dtype=np.float64).reshape(-1, 2)
    out = np.full(norm.shape, np.nan)
    if norm.shape[0] == 0:
        return out
    rot = pose.rotation
    normal = rot[:, 2]
    t = pose.tvec
    num = float(normal @ t)
    den = norm[:, 0] * normal[0] + norm[:, 1] * normal[1] + normal[2]
    ray_len = np.sqrt(norm[:, 0] ** 2 + norm[:, 1] ** 2 + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / den
    ok = np.isfinite(s) & (np.abs(den) > _PARALLEL_EPS * ray_len) & (s > 0)
    ok &= np.isfinite(norm[:, 0]) & np.isfinite(norm[:, 1])
    # every ray at once (the same arithmetic per element), then NaN where it misses: cheaper
    # than gathering the rays that meet the plane when, as usual, most of them do
    with np.errstate(invalid="ignore", over="ignore"):
        sx, sy, sz = s * norm[:, 0] - t[0], s * norm[:, 1] - t[1], s - t[2]
        out[:, 0] = np.where(ok, rot[0, 0] * sx + rot[1, 0] * sy + rot[2, 0] * sz, np.nan)
        out[:, 1] = np.where(ok, rot[0, 1] * sx + rot[1, 1] * sy + rot[2, 1] * sz, np.nan)
    return out


def image_points_to_plane(points_xy: np.ndarray, pose: Pose, intrinsics: Intrinsics) -> np.ndarray:
    """Map image points to plane points, the inverse of :func:`project_to_pixels`.

    Parameters
    ----------
    points_xy : numpy.ndarray
        (N, 2) image points in pixels.
    pose : Pose
        Pose of the marker.
    intrinsics : Intrinsics
        The band grid's intrinsics.

    Returns
    -------
    numpy.ndarray
        (N, 2) plane points (u, v): :func:`undistorted_rays` then :func:`rays_to_plane`; NaN
        where the ray misses the plane.

    Notes
    -----
    ``pi_i^-1`` of Eq. 8-10 [1]_ for arbitrary image points: the undistorted viewing ray
    ``d = (x', y', 1)`` meets the marker plane ``n . X = n . t`` at ``X = s d``,
    ``s = (n . t) / (n . d)``, and ``(u, v, 0) = R^T (X - t)`` (:func:`rays_to_plane`).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    return rays_to_plane(undistorted_rays(points_xy, intrinsics), pose)


def pixel_rays(
    intrinsics: Intrinsics, shape: tuple[int, int], offset: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Return the viewing rays of every pixel centre as normalised coordinates.

    Parameters
    ----------
    intrinsics : Intrinsics
        The band grid's intrinsics.
    shape : tuple of int
        ``(H, W)`` of the band.
    offset : tuple of float
        ``(dx, dy)``, the band's offset on the band grid: pixel (i, j) looks through image
        point ``(x, y) = (j + dx, i + dy)``.

    Returns
    -------
    numpy.ndarray
        (H, W, 2) normalised coordinates.
    """
    h, w = (int(shape[0]), int(shape[1]))
    if h <= 0 or w <= 0:
        raise InputError(f"image shape must be positive, got {shape!r}")
    dx, dy = float(offset[0]), float(offset[1])
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64) + dx, np.arange(h, dtype=np.float64) + dy)
    pts = np.stack([jj.ravel(), ii.ravel()], axis=1)
    return undistorted_rays(pts, intrinsics).reshape(h, w, 2)


def pixels_to_plane(
    pose: Pose,
    intrinsics: Intrinsics,
    shape: tuple[int, int],
    offset: tuple[float, float] = (0.0, 0.0),
    rays: np.ndarray | None = None,
) -> np.ndarray:
    """Return the plane point (u, v) in metres seen by the centre of every pixel.

    Parameters
    ----------
    pose : Pose
        Pose of the marker.
    intrinsics : Intrinsics
        The band grid's intrinsics.
    shape : tuple of int
        ``(H, W)`` of the band.
    offset : tuple of float
        The band's offset on the band grid (:func:`pixel_rays`).
    rays : numpy.ndarray, optional
        :func:`pixel_rays` precomputed for the same intrinsics, shape and offset (skips it).

    Returns
    -------
    numpy.ndarray
        (H, W, 2) float64; NaN where the ray misses the plane (parallel or behind the camera).

    Notes
    -----
    This is the inverse of the paper's ``pi_i(p) = x`` [1]_ on the pixel grid:
    :func:`pixel_rays` then :func:`rays_to_plane`.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    if rays is None:
        rays = pixel_rays(intrinsics, shape, offset)
    h, w = rays.shape[:2]
    return rays_to_plane(rays.reshape(-1, 2), pose).reshape(h, w, 2)


def project_to_pixels(points_uv: np.ndarray, pose: Pose, intrinsics: Intrinsics) -> np.ndarray:
    """Project plane points to pixels, the paper's ``pi_i``.

    Parameters
    ----------
    points_uv : numpy.ndarray
        (N, 2) plane points (u, v) in metres.
    pose : Pose
        Pose of the marker.
    intrinsics : Intrinsics
        The band grid's intrinsics.

    Returns
    -------
    numpy.ndarray
        (N, 2) image points in pixels: ``cv2.projectPoints`` of ``(u, v, 0)`` with the pose and
        the intrinsics (distortion included). Points behind the camera give meaningless pixels:
        check with the pose first.

    Notes
    -----
    ``pi_i: p -> x`` of Eq. 8-10 [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    uv = np.asarray(points_uv, dtype=np.float64).reshape(-1, 2)
    if uv.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.float64)
    obj = np.concatenate([uv, np.zeros((uv.shape[0], 1))], axis=1).reshape(-1, 1, 3)
    img, _ = cv2.projectPoints(obj, pose.rvec, pose.tvec, intrinsics.matrix, intrinsics.dist_coeffs)
    return img.reshape(-1, 2)


#: Plane samples per side of :func:`reflector_window` (a grid over the whole reflector).
WINDOW_SAMPLES = 33
#: Pixels added on every side of :func:`reflector_window` beyond the sample spacing.
WINDOW_MARGIN_PX = 2.0


def reflector_window(
    pose: Pose,
    intrinsics: Intrinsics,
    shape: tuple[int, int],
    size_m: float | Sequence[float],
    offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[slice, slice]:
    """Rows and columns of a band that can see the reflector: a box around ``pi_i`` of it.

    Parameters
    ----------
    pose : Pose
        Pose of the marker.
    intrinsics : Intrinsics
        The band grid's intrinsics.
    shape : tuple of int
        ``(H, W)`` of the band.
    size_m : float or sequence of float
        Reflector size ``[w, h]`` centred on the marker.
    offset : tuple of float
        The band's offset on the band grid (:func:`pixel_rays`).

    Returns
    -------
    tuple of slice
        ``(rows, cols)``: every pixel whose plane point (:func:`pixels_to_plane`) lies on the
        reflector is inside; the whole band when the box cannot be bounded (part of the
        reflector behind the camera, or its projection folds).

    Notes
    -----
    ``pi_i`` (:func:`project_to_pixels`) of a :data:`WINDOW_SAMPLES` square grid of plane
    points over the whole reflector. A pixel that sees the reflector sees a point of one grid
    cell, and lies in the box of that cell's projected corners (widened by
    :data:`WINDOW_MARGIN_PX` for the curvature of the lens over one cell); the window is the
    union of the boxes of the cells that reach the band. Within the lens's field ``pi_i``
    inverts the pixel rays (both exact to ~1e-10 px), so restricting :func:`pixels_to_plane`
    and everything after it to the window gives the same pixels and plane points as the
    whole band, for less work: the reflector fills a fraction of most views.
    """
    return window_of_cells(reflector_cells(pose, intrinsics, size_m), shape, offset)


def reflector_cells(pose: Pose, intrinsics: Intrinsics, size_m: float | Sequence[float]) -> np.ndarray | None:
    """Pixel boxes of the cells of a grid over the reflector, the first half of :func:`reflector_window`.

    Parameters
    ----------
    pose : Pose
        Pose of the marker.
    intrinsics : Intrinsics
        The band grid's intrinsics.
    size_m : float or sequence of float
        Reflector size ``[w, h]`` centred on the marker.

    Returns
    -------
    numpy.ndarray or None
        ``(4, n, n)``: the least and greatest x, then y, on the band grid of the projected
        corners of each cell of the :data:`WINDOW_SAMPLES` grid (``n = WINDOW_SAMPLES - 1``);
        None when they do not bound the reflector (part of it behind the camera, or a
        projection that is not finite).

    Notes
    -----
    They depend on the pose and the intrinsics only, not on a band's offset: one projection
    serves every band of a band-grid camera (:func:`window_of_cells`).
    """
    sw, sh = size_wh(size_m)
    n = WINDOW_SAMPLES
    uu, vv = np.meshgrid(np.linspace(-sw / 2, sw / 2, n), np.linspace(-sh / 2, sh / 2, n))
    plane = np.stack([uu.ravel(), vv.ravel()], axis=1)
    depth = plane @ pose.rotation[2, :2] + pose.tvec[2]
    if not np.all(depth > 0):
        return None
    xy = project_to_pixels(plane, pose, intrinsics).reshape(n, n, 2)
    if not np.all(np.isfinite(xy)):
        return None
    out = np.empty((4, n - 1, n - 1))
    for i, c in enumerate((xy[..., 0], xy[..., 1])):
        corners = np.stack([c[:-1, :-1], c[1:, :-1], c[:-1, 1:], c[1:, 1:]])
        corners.min(0, out=out[2 * i])
        corners.max(0, out=out[2 * i + 1])
    return out


def window_of_cells(
    cells: np.ndarray | None, shape: tuple[int, int], offset: tuple[float, float] = (0.0, 0.0)
) -> tuple[slice, slice]:
    """Bound the window of :func:`reflector_window` from its cells' boxes (:func:`reflector_cells`).

    Parameters
    ----------
    cells : numpy.ndarray or None
        :func:`reflector_cells` of the pose; None gives the whole band.
    shape : tuple of int
        ``(H, W)`` of the band.
    offset : tuple of float
        The band's offset on the band grid (:func:`pixel_rays`).

    Returns
    -------
    tuple of slice
        ``(rows, cols)``, as :func:`reflector_window`.
    """
    h, w = int(shape[0]), int(shape[1])
    if cells is None:
        return slice(0, h), slice(0, w)
    # a box in pixel indices, widened (x - offset is monotone: the least corner stays least)
    x0, x1 = cells[0] - float(offset[0]) - WINDOW_MARGIN_PX, cells[1] - float(offset[0]) + WINDOW_MARGIN_PX
    y0, y1 = cells[2] - float(offset[1]) - WINDOW_MARGIN_PX, cells[3] - float(offset[1]) + WINDOW_MARGIN_PX
    reach = (x1 >= 0) & (x0 <= w - 1) & (y1 >= 0) & (y0 <= h - 1)
    if not reach.any():
        return slice(0, 0), slice(0, 0)
    rows = slice(max(int(np.floor(y0[reach].min())), 0), min(int(np.ceil(y1[reach].max())) + 1, h))
    cols = slice(max(int(np.floor(x0[reach].min())), 0), min(int(np.ceil(x1[reach].max())) + 1, w))
    return rows, cols


def size_wh(size_m: float | Sequence[float]) -> tuple[float, float]:
    """Validate a reflector size given as one side or ``[width, height]`` (metres).

    Parameters
    ----------
    size_m : float or sequence of float
        One side (a square) or ``[width, height]``.

    Returns
    -------
    tuple of float
        ``(width, height)``.

    Raises
    ------
    InputError
        Unless the size is one or two positive finite numbers.
    """
    arr = np.asarray(size_m, dtype=np.float64).ravel()
    if arr.size == 1:
        arr = np.repeat(arr, 2)
    if arr.size != 2 or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise InputError(
            f"reflector size must be [width, height] positive metres, got {size_m!r}",
            hint="check size_m of the reflector target",
        )
    return float(arr[0]), float(arr[1])


def reflector_mask(
    uv: np.ndarray,
    size_m: float | Sequence[float],
    exclude_half_m: float,
    edge_margin_m: float,
) -> np.ndarray:
    """Mask the pixels that see usable gray reflector.

    Parameters
    ----------
    uv : numpy.ndarray
        (..., 2) plane points of the pixels (:func:`pixels_to_plane`).
    size_m : float or sequence of float
        Reflector size ``[w, h]`` centred on the marker.
    exclude_half_m : float
        Half width of the excluded centre: the marker, its white paper border and a safety
        margin.
    edge_margin_m : float
        Margin kept from the reflector's edge.

    Returns
    -------
    numpy.ndarray
        Bool array of ``uv.shape[:-1]``: True where ``|u| <= w/2 - edge_margin_m`` and
        ``|v| <= h/2 - edge_margin_m`` and NOT ``|u| <= exclude_half_m and |v| <=
        exclude_half_m``. NaN plane points are False.

    Notes
    -----
    These pixels are the reflector pixels of the vignetting fit (the region ``P`` of Eq. 8-10)
    and of the illumination fit (``Omega`` of Eq. 12-14) [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    w, h = size_wh(size_m)
    excl = float(exclude_half_m)
    margin = float(edge_margin_m)
    if not np.isfinite(excl) or excl < 0 or not np.isfinite(margin) or margin < 0:
        raise InputError(
            f"exclude_half_m and edge_margin_m must be non-negative metres, got {exclude_half_m!r},"
            f" {edge_margin_m!r}"
        )
    arr = np.asarray(uv, dtype=np.float64)
    if arr.shape[-1] != 2:
        raise InputError(f"plane points must end in a (u, v) axis of 2, got shape {arr.shape}")
    u, v = arr[..., 0], arr[..., 1]
    with np.errstate(invalid="ignore"):
        au, av = np.abs(u), np.abs(v)
        inside = (au <= 0.5 * w - margin) & (av <= 0.5 * h - margin)
        marker = (au <= excl) & (av <= excl)
    return inside & ~marker
