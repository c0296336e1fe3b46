"""The synthetic snapshot camera: distorted pinhole, band mosaic, poses (see :mod:`pipeline.sim.world.scene`)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from mscal_core.mosaic import band_offsets, remosaic

CAMERA_NAME = "ximea-mq022hg-sm5x5-nir"


XIMEA_WAVELENGTHS_NM = (
    (615, 623, 608, 790, 686),
    (816, 828, 803, 791, 700),
    (765, 778, 752, 739, 714),
    (653, 662, 645, 636, 678),
    (867, 864, 857, 845, 670),
)


FAR = 1.0e6  # plane coordinate given to rays that miss the plane (weights are zeroed there)


def _distort(x: np.ndarray, y: np.ndarray, dist: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV radial + tangential distortion of normalised image coordinates."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def _undistort(
    xd: np.ndarray, yd: np.ndarray, dist: Sequence[float], iterations: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`_distort` by Newton's method (exact to ~1e-13 for this lens)."""
    k1, k2, p1, p2, k3 = dist
    x = np.array(xd, dtype=np.float64, copy=True)
    y = np.array(yd, dtype=np.float64, copy=True)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        e = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * e - b * b
        x -= (e * fx - b * fy) / det
        y -= (a * fy - b * fx) / det
    return x, y


@functools.lru_cache(maxsize=4)
def _sensor_rays(fx, fy, cx, cy, dist, grid_shape, pattern_shape):
    """Normalised undistorted ray coordinates of every sensor pixel centre of the band grid.

    Sensor pixel (ys, xs) is band-grid point (xs / C, ys / R). Returns ``xn, yn`` (Hs, Ws)
    float32 (1e-5 band-grid pixels) and their derivatives per sensor pixel
    ``dxn/dxs, dxn/dys, dyn/dxs, dyn/dys``
    (float32), used to place sub-pixel samples by a first-order Taylor step.
    """
    h, w = grid_shape
    rows, cols = pattern_shape
    hs, ws = h * rows, w * cols
    gx = (np.arange(ws, dtype=np.float64) / cols - cx) / fx
    gy = (np.arange(hs, dtype=np.float64) / rows - cy) / fy
    xd, yd = np.meshgrid(gx, gy)
    xn, yn = _undistort(xd, yd, dist)
    derivs = tuple(
        np.gradient(a, axis=ax).astype(np.float32) for a in (xn, yn) for ax in (1, 0)
    )
    xn, yn = xn.astype(np.float32), yn.astype(np.float32)
    for a in (xn, yn, *derivs):
        a.setflags(write=False)
    return xn, yn, derivs


@dataclass(frozen=True)
class SnapshotCamera:
    """The paper's Ximea MQ022HG-IM-SM5X5-NIR: 5 x 5 snapshot mosaic, 10 bit.

    Intrinsics are for the band grid (217 x 409): ``fx, fy, cx, cy`` in band-grid pixels and
    OpenCV ``dist = (k1, k2, p1, p2, k3)``. Band index ``r*5 + c``; wavelengths per band in
    ``wavelengths_nm`` (SPEC.md, paper Fig. 3).
    """

    name: str = CAMERA_NAME
    fx: float = 436.0
    fy: float = 436.0
    cx: float = 204.0
    cy: float = 108.0
    dist: tuple[float, float, float, float, float] = (-0.12, 0.05, 0.0012, -0.0008, 0.0)
    grid_shape: tuple[int, int] = (217, 409)
    sensor_shape: tuple[int, int] = (1088, 2048)
    pattern_shape: tuple[int, int] = (5, 5)
    bits: int = 10
    wavelengths_nm: tuple[float, ...] = tuple(float(w) for row in XIMEA_WAVELENGTHS_NM for w in row)

    @property
    def n_bands(self) -> int:
        """Number of bands (the cells of the mosaic pattern)."""
        return self.pattern_shape[0] * self.pattern_shape[1]

    @property
    def matrix(self) -> np.ndarray:
        """Camera matrix ``K`` (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion coefficients (5,)."""
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def wavelengths(self) -> np.ndarray:
        """Band centre wavelengths (nm) as float64."""
        return np.asarray(self.wavelengths_nm, dtype=np.float64)

    @property
    def band_offsets(self) -> np.ndarray:
        """(n_bands, 2) offsets (dx, dy) of each band's samples on the band grid."""
        return band_offsets(self.pattern_shape)

    def band_index(self, wavelength_nm: float) -> int:
        """Return the index of the band nearest to ``wavelength_nm``."""
        return int(np.argmin(np.abs(self.wavelengths - wavelength_nm)))

    def intrinsics_dict(self) -> dict:
        """Return the intrinsics as plain numbers (fx, fy, cx, cy, dist, ...)."""
        return {
            "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx),
            "cy": float(self.cy), "dist": [float(d) for d in self.dist],
        }

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> band-grid image points (N, 2) (x = column, y = row)."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        xd, yd = _distort(x, y, self.dist)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)

    def rays(self, image_points: np.ndarray) -> np.ndarray:
        """Band-grid image points (N, 2) -> normalised undistorted coordinates (N, 2)."""
        pts = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
        xd = (pts[:, 0] - self.cx) / self.fx
        yd = (pts[:, 1] - self.cy) / self.fy
        x, y = _undistort(xd, yd, self.dist)
        return np.stack([x, y], axis=1)

    def sensor_rays(self):
        """Return the cached ``(xn, yn, derivatives)`` for every sensor pixel of the band grid."""
        return _sensor_rays(
            float(self.fx), float(self.fy), float(self.cx), float(self.cy),
            tuple(float(d) for d in self.dist), tuple(self.grid_shape), tuple(self.pattern_shape),
        )

    def split_bands(self, sensor_image: np.ndarray) -> np.ndarray:
        """(..., Hs, Ws) sensor-grid image -> (..., n_bands, H, W) band stack (index r*C + c)."""
        h, w = self.grid_shape
        rows, cols = self.pattern_shape
        lead = sensor_image.shape[:-2]
        a = sensor_image.reshape(*lead, h, rows, w, cols)
        a = np.moveaxis(a, (-3, -1), (-4, -3))  # (..., rows, cols, h, w)
        return np.ascontiguousarray(a).reshape(*lead, rows * cols, h, w)

    def mosaic(self, band_stack: np.ndarray, fill: int = 0) -> np.ndarray:
        """(n_bands, H, W) band stack -> raw sensor frame (mosaic.remosaic)."""
        return remosaic(band_stack, self.pattern_shape, self.sensor_shape, fill=fill)


@dataclass(frozen=True)
class Pose:
    """Plane (marker) frame -> camera: ``X_cam = R X_plane + t`` (cv2.solvePnP convention)."""

    rvec: np.ndarray
    tvec: np.ndarray

    @staticmethod
    def from_matrix(R: np.ndarray, t: np.ndarray) -> Pose:
        """Build a pose from a rotation matrix and a translation."""
        rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
        return Pose(rvec.reshape(3), np.asarray(t, dtype=np.float64).reshape(3))

    @property
    def R(self) -> np.ndarray:
        """Rotation matrix (plane -> camera)."""
        R, _ = cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64).reshape(3, 1))
        return R

    @property
    def camera_centre(self) -> np.ndarray:
        """Camera centre in the plane frame."""
        return -self.R.T @ np.asarray(self.tvec, dtype=np.float64)

    def to_camera(self, points_plane: np.ndarray) -> np.ndarray:
        """Map plane points (N, 3) into camera coordinates."""
        p = np.asarray(points_plane, dtype=np.float64).reshape(-1, 3)
        return p @ self.R.T + np.asarray(self.tvec, dtype=np.float64)


def rot(axis: Sequence[float], angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    R, _ = cv2.Rodrigues((a * angle).reshape(3, 1))
    return R


# The camera looking straight at the printed marker / straight down at the field: camera x =
# plane x, camera y (image down) = -plane y, camera z = -plane z.
FRONTAL = np.diag([1.0, -1.0, -1.0])


def intersect_plane(pose: Pose, xn: np.ndarray, yn: np.ndarray):
    """Rays (xn, yn, 1) in the camera frame -> plane points (u, v); ``ok`` where hit in front.

    Computed in the dtype of ``xn`` (float32 for the renderer: ~1e-6 m at 100 m).
    """
    R = [[float(a) for a in row] for row in pose.R]
    C = [float(a) for a in pose.camera_centre]
    dx = R[0][0] * xn + R[1][0] * yn + R[2][0]
    dy = R[0][1] * xn + R[1][1] * yn + R[2][1]
    dz = R[0][2] * xn + R[1][2] * yn + R[2][2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (-C[2]) / dz
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, s, 0)
    u = np.where(ok, C[0] + s * dx, FAR).astype(xn.dtype, copy=False)
    v = np.where(ok, C[1] + s * dy, FAR).astype(xn.dtype, copy=False)
    return u, v, ok
