"""A ChArUco board in place of the single marker: detection and pose (no I/O).

A ChArUco board (a chessboard whose white squares carry ArUco markers) gives tens of corners
spread over the board instead of a single marker's 4: the pose is over-determined, the corners
(chessboard saddle points) are located without the bias of a marker's convex corners, and the
planar ambiguity of one small square ([1]_) does not arise once the corners span the board.

Board frame: the marker frame of :mod:`mscal_core.geometry` (``docs/architecture.md``): the
board's centre at the origin, plane ``z = 0``, ``u`` to the right and ``v`` **up** as printed.
OpenCV's board frame has its origin at the board's top-left corner and ``y`` down; a board
point ``(X, Y)`` is ``(u, v) = (X - W/2, H/2 - Y)`` here (``W x H`` the board's size), a
rotation by 180 deg about ``u`` plus a shift, so poses keep their handedness.

References
----------
.. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
       International Journal of Computer Vision, 109(3), 252-286, 2014.
.. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .errors import FitError, InputError
from .geometry import Intrinsics, Pose, _to_uint8, aruco_dictionary, project_to_pixels
from .marker import PoseChoice

__all__ = ["CharucoSpec", "MIN_CORNERS", "board_points", "detect_charuco", "charuco_pose"]

#: Interpolated chessboard corners a view needs for a pose.
MIN_CORNERS = 6


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board: ``squares_x x squares_y`` squares of ``square_m``, markers of ``marker_m``.

    Attributes
    ----------
    squares_x, squares_y : int
        Squares across and down the board (at least 2 each).
    square_m, marker_m : float
        Side of a square and of the marker inside a white square (metres, ``marker_m <
        square_m``).
    dictionary : str
        OpenCV ArUco dictionary name of the markers, e.g. ``"DICT_4X4_50"``.

    Raises
    ------
    InputError
        On sizes that do not make a board, or an unknown dictionary.
    """

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str

    def __post_init__(self) -> None:
        """Validate the board's counts and sizes."""
        if int(self.squares_x) < 2 or int(self.squares_y) < 2:
            raise InputError(f"a ChArUco board needs at least 2 x 2 squares, got {self.squares_x} x {self.squares_y}")
        if not (np.isfinite(self.square_m) and np.isfinite(self.marker_m) and 0 < self.marker_m < self.square_m):
            raise InputError(
                f"ChArUco sizes must satisfy 0 < marker < square, got marker {self.marker_m!r} m, "
                f"square {self.square_m!r} m"
            )
        aruco_dictionary(self.dictionary)

    @property
    def size_m(self) -> tuple[float, float]:
        """``(W, H)``: the board's width and height in metres."""
        return (int(self.squares_x) * float(self.square_m), int(self.squares_y) * float(self.square_m))

    def board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board of this spec."""
        return cv2.aruco.CharucoBoard((int(self.squares_x), int(self.squares_y)), float(self.square_m),
                                      float(self.marker_m), aruco_dictionary(self.dictionary))


def board_points(spec: CharucoSpec, ids: np.ndarray | None = None) -> np.ndarray:
    """Return the board's chessboard corners in the board frame (centre at the origin, ``v`` up).

    Parameters
    ----------
    spec : CharucoSpec
        The board.
    ids : numpy.ndarray, optional
        Corner ids (OpenCV's numbering); all corners if None.

    Returns
    -------
    numpy.ndarray
        (N, 3) float64 ``(X - W/2, H/2 - Y, 0)`` of OpenCV's corners ``(X, Y, 0)``.
    """
    xyz = np.asarray(spec.board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    if ids is not None:
        xyz = xyz[np.asarray(ids, dtype=np.intp).ravel()]
    w, h = spec.size_m
    return np.stack([xyz[:, 0] - w / 2, h / 2 - xyz[:, 1], np.zeros(len(xyz))], axis=1)


def detect_charuco(image: np.ndarray, spec: CharucoSpec,
                   min_corners: int = MIN_CORNERS) -> tuple[np.ndarray, np.ndarray] | None:
    """Find the board's chessboard corners in an image.

    Parameters
    ----------
    image : numpy.ndarray
        2-D image of any dtype (stretched to 8 bits as for a single marker).
    spec : CharucoSpec
        The board.
    min_corners : int
        Fewest corners returned (default :data:`MIN_CORNERS`, what a pose needs; 1 to count
        the corners of a view that has too few).

    Returns
    -------
    tuple or None
        ``(corners (N, 2) float64 pixels, ids (N,) int)`` of the interpolated corners, or None
        when fewer than ``min_corners`` are found.

    Notes
    -----
    ``cv2.aruco.CharucoDetector``: the markers are detected, each white square's neighbours
    give the chessboard corners by a local homography, and every corner is refined to sub-pixel
    accuracy on the saddle point (``cornerSubPix``), where a symmetric blur leaves no bias.
    The corners are refined again on the image itself with a window of half side ``0.8 m s``
    (at least 2 px; ``s`` the corners' median spacing in pixels, ``m = (square - marker) / (2
    square)`` the white margin between a corner and its markers' corners), so that no marker
    edge enters it: OpenCV's own window reached them on small boards (on the band grid of
    the synthetic sessions: corner error rms 0.21 px, max 1.2 px; with this window 0.07 px and
    0.3 px).
    ``tryRefineMarkers``: markers rejected as candidates are looked for again where the
    board's layout puts them (``refineDetectedMarkers``); on a snapshot camera's band grid,
    where a 45 mm marker's cells are ~2 px at 1.5 m, this recovers the one or two markers a
    view loses (a corner needs both its neighbouring markers).
    """
    gray = _to_uint8(image)
    params = cv2.aruco.DetectorParameters()
    params.minMarkerDistanceRate = 0.05
    board_params = cv2.aruco.CharucoParameters()
    board_params.tryRefineMarkers = True
    detector = cv2.aruco.CharucoDetector(spec.board(), board_params, params)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or corners is None or len(ids) < max(int(min_corners), 1):
        return None
    pts = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
    if len(pts) >= 2:
        pts = _refine_saddles(np.asarray(image, dtype=np.float32), pts, spec)
    return pts.astype(np.float64), np.asarray(ids, dtype=np.int64).ravel()


def _refine_saddles(image: np.ndarray, corners: np.ndarray, spec: CharucoSpec) -> np.ndarray:
    """Refine chessboard corners on their saddle points, the window inside the white margins.

    The window stays inside the white margin between a corner and the four markers' corners
    around it (``cornerSubPix`` on the image itself, not its 8-bit stretch).
    """
    d = np.linalg.norm(corners[:, None, :] - corners[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))  # ~ a square's side in pixels (the shorter, foreshortened)
    margin = 0.5 * (float(spec.square_m) - float(spec.marker_m)) / float(spec.square_m)
    half = max(2, int(0.8 * margin * spacing))
    if not np.isfinite(spacing) or 2 * half + 1 >= min(image.shape):
        return corners
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 0.001)
    out = cv2.cornerSubPix(image, corners.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), crit).reshape(-1, 2)
    # a corner that left its window (drawn to a marker's edge) keeps OpenCV's
    moved = np.linalg.norm(out - corners, axis=1) > half
    out[moved] = corners[moved]
    return out


def charuco_pose(corners: np.ndarray, ids: np.ndarray, spec: CharucoSpec, intrinsics: Intrinsics) -> PoseChoice:
    """Estimate the board's pose from its interpolated corners.

    Parameters
    ----------
    corners : numpy.ndarray
        (N, 2) pixels (on the image points the intrinsics apply to).
    ids : numpy.ndarray
        (N,) their ids (:func:`detect_charuco`).
    spec : CharucoSpec
        The board.
    intrinsics : Intrinsics
        The band grid's (or lens's) intrinsics.

    Returns
    -------
    PoseChoice
        ``X_cam = R X_board + t`` in the board frame of this module; ``solution`` and ``by``
        as for a single marker, over the two solutions of ``SOLVEPNP_IPPE``.

    Raises
    ------
    InputError
        On fewer than :data:`MIN_CORNERS` corners or mismatched arrays.
    FitError
        If no pose is found with the board in front of the camera (e.g. collinear corners).

    Notes
    -----
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE)`` on all the corners: IPPE [1]_ for a plane with
    any number of points gives the two candidate poses, each refined by OpenCV; the one of
    smaller RMS reprojection error is taken, which over a board's spread of corners separates
    them (the paper's ``pi_i`` [2]_ is then the board's pose).

    References
    ----------
    .. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
           International Journal of Computer Vision, 109(3), 252-286, 2014.
    .. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(ids).ravel()
    if pts.shape[0] != ids.size or ids.size < MIN_CORNERS or not np.all(np.isfinite(pts)):
        raise InputError(f"a ChArUco pose needs at least {MIN_CORNERS} finite corners with their ids, "
                         f"got {pts.shape[0]} corners and {ids.size} ids")
    obj = board_points(spec, ids)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, pts.reshape(-1, 1, 2), intrinsics.matrix,
                                                 intrinsics.dist_coeffs, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error as exc:
        raise FitError(f"no board pose found from the detected corners ({exc.err})") from None
    cands: list[tuple[float, Pose]] = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        pose = Pose(np.ravel(rvec), np.ravel(tvec))
        if np.any((obj @ pose.rotation.T + pose.tvec)[:, 2] <= 0):
            continue
        err = project_to_pixels(obj[:, :2], pose, intrinsics) - pts
        cands.append((float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), pose))
    if not cands:
        raise FitError("no board pose puts the board in front of the camera",
                       hint="check the intrinsics and the board's sizes")
    cands.sort(key=lambda c: c[0])
    if len(cands) == 1:
        return PoseChoice(cands[0][1], None, 0, (cands[0][0], float("nan")), "single")
    return PoseChoice(cands[0][1], cands[1][1], 0, (cands[0][0], cands[1][0]), "reprojection")
