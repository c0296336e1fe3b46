"""Camera intrinsics from images of a calibration board (OpenCV), pure arrays.

Boards: a ChArUco board (``cv2.aruco.CharucoBoard``, found with ``cv2.aruco.CharucoDetector``:
its ArUco markers identify every inner chessboard corner, so partly visible boards count) or
a plain checkerboard (``cv2.findChessboardCornersSB``, the whole board must be in view).
:func:`calibrate` is ``cv2.calibrateCamera`` with the 5-coefficient OpenCV model
``[k1, k2, p1, p2, k3]``, the model :class:`mscal_core.geometry.Intrinsics` holds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .errors import FitError, InputError
from .geometry import Intrinsics

#: A view needs at least this many board corners to constrain a pose.
MIN_CORNERS = 8


@dataclass(frozen=True)
class Board:
    """A calibration board.

    ``kind`` "charuco" or "checkerboard"; ``squares`` (columns, rows) of squares; ``square_m``
    square side; ChArUco: ``marker_m`` marker side and ``dictionary``.
    """

    kind: str
    squares: tuple[int, int]
    square_m: float
    marker_m: float | None = None
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        """Check the board (:class:`InputError` on an unknown kind, size or dictionary)."""
        if self.kind not in ("charuco", "checkerboard"):
            raise InputError(f"board kind must be charuco or checkerboard, got {self.kind!r}")
        if min(self.squares) < 2 or self.square_m <= 0:
            raise InputError(f"board needs at least 2 x 2 squares of positive size, got {self.squares} x {self.square_m}")
        if self.kind == "charuco":
            if self.marker_m is None or not 0 < self.marker_m < self.square_m:
                raise InputError("a ChArUco board's marker_m must be positive and smaller than square_m")
            if not isinstance(getattr(cv2.aruco, self.dictionary, None), int):
                raise InputError(f"unknown ArUco dictionary {self.dictionary!r}")

    def charuco(self) -> cv2.aruco.CharucoBoard:
        """Build the OpenCV ``CharucoBoard`` of this board."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(tuple(self.squares), float(self.square_m), float(self.marker_m), d)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [0.5, 99.5])
    return np.clip(np.rint((img - lo) / max(hi - lo, 1e-9) * 255.0), 0, 255).astype(np.uint8)


def detect_board(image: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray] | None:
    """Find the board corners in one image.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` single-band image of any dtype (stretched to 8 bits between its 0.5th and
        99.5th percentiles).
    board : Board
        The board looked for.

    Returns
    -------
    tuple of numpy.ndarray or None
        ``(object points (N, 3) metres on the board, image points (N, 2) px)``, float64; None
        when the board is not found or (ChArUco) fewer than :data:`MIN_CORNERS` corners are.

    Raises
    ------
    InputError
        When the image is not single-band.

    Notes
    -----
    ChArUco: ``cv2.aruco.CharucoDetector`` (partly visible boards count); checkerboard:
    ``cv2.findChessboardCornersSB`` on the ``(columns - 1, rows - 1)`` inner corners (the whole
    board must be in view).
    """
    if np.ndim(image) != 2:
        raise InputError(f"expected a single-band image, got shape {np.shape(image)}")
    gray = _to_uint8(image)
    if board.kind == "charuco":
        cb = board.charuco()
        corners, ids, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        obj = cb.getChessboardCorners()[np.asarray(ids).ravel()]
        return obj.astype(np.float64), np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    inner = (board.squares[0] - 1, board.squares[1] - 1)
    ok, corners = cv2.findChessboardCornersSB(gray, inner, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    gx, gy = np.meshgrid(np.arange(inner[0]), np.arange(inner[1]))
    obj = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * board.square_m
    return obj.astype(np.float64), np.asarray(corners, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class IntrinsicsFit:
    """Result of :func:`calibrate`: the intrinsics, the reprojection rms (px) and the views used."""

    intrinsics: Intrinsics
    rms_px: float  # reprojection error rms (cv2.calibrateCamera)
    views: int


def calibrate(views: Sequence[tuple[np.ndarray, np.ndarray]], shape: tuple[int, int],
              guess: Intrinsics | None = None, fix_k3: bool = False) -> IntrinsicsFit:
    """Fit the intrinsics with ``cv2.calibrateCamera`` on board views.

    Parameters
    ----------
    views : sequence of tuple of numpy.ndarray
        ``[(object (N, 3), image (N, 2)), ...]`` as from :func:`detect_board`; views with fewer
        than :data:`MIN_CORNERS` corners are left out.
    shape : tuple of int
        ``(H, W)`` of the images.
    guess : Intrinsics, optional
        Starting intrinsics (``CALIB_USE_INTRINSIC_GUESS``).
    fix_k3 : bool
        Keep ``k3 = 0`` (few or small views: ``k2`` and ``k3`` trade off and extrapolate badly to
        the image corners).

    Returns
    -------
    IntrinsicsFit
        The intrinsics (OpenCV's 5-coefficient model ``[k1, k2, p1, p2, k3]``), the reprojection
        rms (px) and the number of views used.

    Raises
    ------
    FitError
        With fewer than 3 usable views (the principal point and distortion are not constrained
        by fewer), or when the fit does not converge to finite values.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE Trans. Pattern
           Analysis and Machine Intelligence 22(11), 2000 (the method of ``cv2.calibrateCamera``).
    """
    views = [(o, i) for o, i in views if len(o) >= MIN_CORNERS]
    if len(views) < 3:
        raise FitError(f"only {len(views)} image(s) with the board found; intrinsics need at least 3",
                       hint="take 10-20 sharp images of the board at different angles, filling the frame in turn")
    obj = [np.asarray(o, dtype=np.float32).reshape(-1, 1, 3) for o, _ in views]
    img = [np.asarray(i, dtype=np.float32).reshape(-1, 1, 2) for _, i in views]
    h, w = int(shape[0]), int(shape[1])
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    k = None
    d = None
    if guess is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
        k, d = guess.matrix.copy(), guess.dist_coeffs.copy()
    rms, k, d, _, _ = cv2.calibrateCamera(obj, img, (w, h), k, d, flags=flags)
    d = np.asarray(d, dtype=np.float64).ravel()[:5]
    if not np.all(np.isfinite(k)) or not np.all(np.isfinite(d)):
        raise FitError("the board calibration did not converge", hint="use more images, tilted 20-45 deg")
    return IntrinsicsFit(Intrinsics(fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], dist=tuple(d)), float(rms), len(views))


__all__ = ["Board", "IntrinsicsFit", "MIN_CORNERS", "calibrate", "detect_board"]
