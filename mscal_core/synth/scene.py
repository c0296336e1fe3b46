"""Scene part of the seeded synthetic forward model: camera, targets, light, datasets.

Physics (equation numbers of Khanna et al., ICRA 2017, summarised in ``PAPER.md``), per band
(wavelength) ``lambda`` and pixel ``x``:

- (1)  ``L(x) = J(x) R(x)``: Lambertian radiance = incident light x reflectance.
- (11) ``J_lambda(p) = S(lambda) B(p)``: the light's colour ``S`` is the same everywhere, only
  its brightness ``B`` varies over the scene (gradient, soft shadow, clouds between frames).
  ``S`` also absorbs the filter sensitivity of each band.
- (2)  ``E(x) = V(x) L(x)``: optical attenuation (vignetting) of the lens per band and pixel.
- (3, 4) ``I(x) = C(t E(x))``, ``U(I) = t E``: the sensor integrates ``E`` over the exposure
  ``t`` and maps it through its response ``C`` (``SensorModel``, with shot and read noise and
  quantisation).

Units: the energy rate ``E = V S B R`` is in "linear DN per millisecond" (the U gauge of
``docs/architecture.md``: ``U(I) ~ I - black`` in the linear part), so ``t E`` is the linear DN
the sensor integrates during ``t`` ms. ``S`` (1.5-2.5) and ``B`` (a few hundred in reflector
scenes) are stored in those units: ``E = V * S * B * R`` holds exactly for every rendered pixel.
``S`` and ``B`` are a product, so a fit recovers them up to one common scalar; ``V`` is
normalised to max 1 per band.

Geometry: a distorted pinhole (OpenCV model, intrinsics of the 217 x 409 band grid) looking at
a plane ``z = 0`` (marker frame of ``docs/architecture.md``: x right, y up as printed, plane
normal towards the camera; ``X_cam = R X_plane + t`` as in ``cv2.solvePnP``). Band (r, c) of
the 5 x 5 snapshot mosaic samples its pixel (i, j) at band-grid point ``(j + c/5, i + r/5)``,
i.e. at sensor pixel ``(5i + r, 5j + c)``. The renderer works on the sensor grid: every sensor
pixel centre is back-projected (own iterative inversion of the distortion, independent of the
fitting code), intersected with the plane and the scene evaluated there; pixels on a hard edge
(reflector edge, paper, marker cells, panels) are supersampled over the sensor pixel's footprint
and a small Gaussian lens PSF is applied before the bands are split.

Nothing here reads or writes files; ``pipeline/sim/synth.py`` writes a session folder.
"""

from __future__ import annotations

import datetime as _dt
import functools
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..mosaic import band_offsets, remosaic
from .sensor import SensorModel

__all__ = [
    "CAMERA_NAME",
    "XIMEA_WAVELENGTHS_NM",
    "DEFAULT_PANELS",
    "FieldScene",
    "FrameSet",
    "GradientShadowLight",
    "LightDrift",
    "MarkerSpec",
    "Panel",
    "PeriodicNoise",
    "Pose",
    "ReflectorScene",
    "Render",
    "SnapshotCamera",
    "SyntheticSession",
    "SyntheticTruth",
    "UniformLight",
    "detect_marker_corners",
    "marker_pose_from_image",
    "pose_error",
    "flight_frames",
    "make_truth",
    "reflector_images",
    "render",
    "response_sweep",
    "soil_reflectance",
    "synthesize_session",
    "vegetation_reflectance",
    "vignetting_views",
]

CAMERA_NAME = "ximea-mq022hg-sm5x5-nir"
XIMEA_WAVELENGTHS_NM = (
    (615, 623, 608, 790, 686),
    (816, 828, 803, 791, 700),
    (765, 778, 752, 739, 714),
    (653, 662, 645, 636, 678),
    (867, 864, 857, 845, 670),
)
NDVI_RED_NM = 670.0
NDVI_NIR_NM = 803.0
# Default session start (UTC) for the frame time stamps; the field near Zurich.
SESSION_START = _dt.datetime(2017, 6, 14, 9, 30, 0, tzinfo=_dt.timezone.utc)
FIELD_LAT_LON = (47.4502, 8.6821)
FIELD_GROUND_ALT_M = 438.0

_FAR = 1.0e6  # plane coordinate given to rays that miss the plane (weights are zeroed there)


# --------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------


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
        return self.pattern_shape[0] * self.pattern_shape[1]

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def wavelengths(self) -> np.ndarray:
        return np.asarray(self.wavelengths_nm, dtype=np.float64)

    @property
    def band_offsets(self) -> np.ndarray:
        """(n_bands, 2) offsets (dx, dy) of each band's samples on the band grid."""
        return band_offsets(self.pattern_shape)

    def band_index(self, wavelength_nm: float) -> int:
        return int(np.argmin(np.abs(self.wavelengths - wavelength_nm)))

    def intrinsics_dict(self) -> dict:
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
        """Cached ``(xn, yn, derivatives)`` for every sensor pixel of the band grid."""
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
        rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
        return Pose(rvec.reshape(3), np.asarray(t, dtype=np.float64).reshape(3))

    @property
    def R(self) -> np.ndarray:
        R, _ = cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64).reshape(3, 1))
        return R

    @property
    def camera_centre(self) -> np.ndarray:
        """Camera centre in the plane frame."""
        return -self.R.T @ np.asarray(self.tvec, dtype=np.float64)

    def to_camera(self, points_plane: np.ndarray) -> np.ndarray:
        p = np.asarray(points_plane, dtype=np.float64).reshape(-1, 3)
        return p @ self.R.T + np.asarray(self.tvec, dtype=np.float64)


def _rot(axis: Sequence[float], angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    R, _ = cv2.Rodrigues((a * angle).reshape(3, 1))
    return R


# The camera looking straight at the printed marker / straight down at the field: camera x =
# plane x, camera y (image down) = -plane y, camera z = -plane z.
_FRONTAL = np.diag([1.0, -1.0, -1.0])


def _intersect(pose: Pose, xn: np.ndarray, yn: np.ndarray):
    """Rays (xn, yn, 1) in the camera frame -> plane points (u, v); ``ok`` where hit in front.

    Computed in the dtype of ``xn`` (float32 for the renderer: ~1e-6 m at 100 m)."""
    R = [[float(a) for a in row] for row in pose.R]
    C = [float(a) for a in pose.camera_centre]
    dx = R[0][0] * xn + R[1][0] * yn + R[2][0]
    dy = R[0][1] * xn + R[1][1] * yn + R[2][1]
    dz = R[0][2] * xn + R[1][2] * yn + R[2][2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (-C[2]) / dz
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, s, 0)
    u = np.where(ok, C[0] + s * dx, _FAR).astype(xn.dtype, copy=False)
    v = np.where(ok, C[1] + s * dy, _FAR).astype(xn.dtype, copy=False)
    return u, v, ok


# --------------------------------------------------------------------------------------------
# Textures, spectra, light
# --------------------------------------------------------------------------------------------


class PeriodicNoise:
    """Smooth, zero-mean, unit-variance periodic noise on the plane (bilinear, seeded)."""

    def __init__(self, rng: np.random.Generator, cell_m: float, corr_cells: float, n: int = 256):
        white = rng.standard_normal((n, n))
        k = np.fft.fftfreq(n)
        kk = k[:, None] ** 2 + k[None, :] ** 2
        filt = np.exp(-0.5 * (2.0 * np.pi * corr_cells) ** 2 * kk)
        field_ = np.real(np.fft.ifft2(np.fft.fft2(white) * filt))
        field_ = (field_ - field_.mean()) / field_.std()
        self.table = field_.astype(np.float32)
        self.cell_m = float(cell_m)
        self.n = n

    def _coords(self, u) -> np.ndarray:
        a = np.asarray(u, dtype=np.float32) * np.float32(1.0 / (self.n * self.cell_m))
        a -= np.floor(a)  # periodic: fraction of the table's period, in [0, 1)
        a *= np.float32(self.n)
        return a

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        mx, my = self._coords(u), self._coords(v)
        shape = mx.shape
        if mx.ndim == 2 and max(shape) < 32000:
            return cv2.remap(self.table, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        size = mx.size
        width = 1024
        rows = -(-size // width)
        pad = rows * width - size
        mx = np.pad(mx.ravel(), (0, pad)).reshape(rows, width)
        my = np.pad(my.ravel(), (0, pad)).reshape(rows, width)
        out = np.concatenate([
            cv2.remap(self.table, mx[r0:r0 + 16000], my[r0:r0 + 16000], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_WRAP).ravel()
            for r0 in range(0, rows, 16000)
        ])
        return out[:size].reshape(shape)


def vegetation_reflectance(wavelength_nm) -> np.ndarray:
    """Green leaf canopy: chlorophyll absorption at ~670 nm, red edge at ~717 nm, NIR plateau.

    About 0.04 at 670 nm and 0.49 at 803 nm (NDVI ~0.86).
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    edge = 1.0 / (1.0 + np.exp(-(wl - 717.0) / 11.0))
    return 0.05 + 0.44 * edge - 0.018 * np.exp(-(((wl - 672.0) / 16.0) ** 2))


def soil_reflectance(wavelength_nm) -> np.ndarray:
    """Dry loam: slowly rising with wavelength, 0.14 at 600 nm to 0.24 at 875 nm."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return 0.14 + 0.10 * (wl - 600.0) / 275.0


@dataclass(frozen=True)
class UniformLight:
    """``B(p) = brightness`` everywhere (the sun on a flat field, one frame)."""

    brightness: float

    def __call__(self, u, v) -> np.ndarray:
        return np.full(np.shape(u), self.brightness, dtype=np.float32)

    def params(self) -> np.ndarray:
        """Same layout as :meth:`GradientShadowLight.params` (no gradient, no shadow)."""
        return np.array([self.brightness, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0])


@dataclass(frozen=True)
class GradientShadowLight:
    """Non-uniform brightness ``B(p)`` on the reflector plane (Eq. 11), constant over time.

    ``B = brightness * g(p) * s(p)``:

    - ``g`` linear along ``gradient_dir`` (radians, in the plane) with ``g_max / g_min =
      gradient_ratio`` over the ``extent_m = (w, h)`` rectangle centred at the origin (so a
      2:1 gradient across the reflector); clamped outside it to stay positive.
    - ``s = 1 - shadow_depth * sigmoid((q - shadow_offset_m) / shadow_softness_m)`` with ``q``
      the coordinate along ``shadow_dir``: a soft shadow edge (penumbra ~4 softness wide).
    """

    brightness: float
    gradient_dir: float = 0.0
    gradient_ratio: float = 2.0
    extent_m: tuple[float, float] = (0.5, 0.5)
    shadow_depth: float = 0.0
    shadow_dir: float = 0.0
    shadow_offset_m: float = 0.0
    shadow_softness_m: float = 0.02

    def gradient(self, u, v) -> np.ndarray:
        u, v = np.asarray(u), np.asarray(v)
        c, s = math.cos(self.gradient_dir), math.sin(self.gradient_dir)
        half = 0.5 * self.extent_m[0] * abs(c) + 0.5 * self.extent_m[1] * abs(s)
        a = (self.gradient_ratio - 1.0) / (self.gradient_ratio + 1.0)
        p = np.clip((u * c + v * s) / half, -1.6, 1.6)
        return 1.0 + a * p

    def shadow(self, u, v) -> np.ndarray:
        u, v = np.asarray(u), np.asarray(v)
        if self.shadow_depth == 0.0:
            return np.ones(np.broadcast(u, v).shape, dtype=np.result_type(u, v))
        q = u * math.cos(self.shadow_dir) + v * math.sin(self.shadow_dir)
        z = np.clip((q - self.shadow_offset_m) / self.shadow_softness_m, -60.0, 60.0)
        return 1.0 - self.shadow_depth / (1.0 + np.exp(-z))

    def __call__(self, u, v) -> np.ndarray:
        """B(u, v), float32 (computed in the dtype of u, v)."""
        return (self.brightness * self.gradient(u, v) * self.shadow(u, v)).astype(np.float32)

    def params(self) -> np.ndarray:
        """(brightness, gradient_dir, gradient_ratio, extent_w, extent_h, shadow_depth,
        shadow_dir, shadow_offset_m, shadow_softness_m); see :meth:`from_params`."""
        return np.array([
            self.brightness, self.gradient_dir, self.gradient_ratio, self.extent_m[0],
            self.extent_m[1], self.shadow_depth, self.shadow_dir, self.shadow_offset_m,
            self.shadow_softness_m,
        ])

    @staticmethod
    def from_params(p) -> GradientShadowLight:
        p = [float(x) for x in p]
        return GradientShadowLight(p[0], p[1], p[2], (p[3], p[4]), p[5], p[6], p[7], p[8])


@dataclass(frozen=True)
class LightDrift:
    """Light whose level and colour drift linearly over a flight (issue 8).

    At time ``tau`` (seconds after ``SESSION_START``) the sun's brightness is multiplied by
    ``level(tau) = 1 + (level_end - 1) f`` and its colour ``S(lambda)`` by
    ``colour(lambda, tau) = 1 + colour_tilt_end f x(lambda)``, with
    ``f = (tau - t0_s) / (t1_s - t0_s)`` (not clamped: the drift goes on before and after)
    and ``x`` from -1 at the shortest to +1 at the longest wavelength: e.g. ``level_end =
    0.8`` is 20 % less light at ``t1_s``, ``colour_tilt_end = 0.02`` a light 2 % redder
    (NIR up, blue-ish bands down) by then.
    """

    t0_s: float
    t1_s: float
    level_end: float = 1.0
    colour_tilt_end: float = 0.0

    def _f(self, tau: float) -> float:
        return (float(tau) - self.t0_s) / (self.t1_s - self.t0_s)

    def level(self, tau: float) -> float:
        return 1.0 + (self.level_end - 1.0) * self._f(tau)

    def colour(self, tau: float, wavelengths: np.ndarray) -> np.ndarray:
        wl = np.asarray(wavelengths, dtype=np.float64)
        x = 2.0 * (wl - wl.min()) / max(float(wl.max() - wl.min()), 1e-9) - 1.0
        return 1.0 + self.colour_tilt_end * self._f(tau) * x


# --------------------------------------------------------------------------------------------
# Planar scenes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MarkerSpec:
    """ArUco marker printed on white paper at the centre of the gray reflector."""

    dictionary: str = "DICT_4X4_50"
    id: int = 3
    size_m: float = 0.10
    border_m: float = 0.025
    paper_reflectance: float = 0.85
    ink_reflectance: float = 0.04

    def bits(self) -> np.ndarray:
        """(n, n) cells incl. the black border, 1 = white, row 0 at the top (+y) as printed."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        n = d.markerSize + 2
        img = cv2.aruco.generateImageMarker(d, self.id, n)
        return (img > 127).astype(np.uint8)


class ReflectorScene:
    """Gray reflector (``size_m``, reflectance ``rho``) with the marker on white paper at its
    centre, lying on a lawn (grass/soil mix) in the plane z = 0, lit by ``light``.

    Hard labels (for edge supersampling and pure-pixel masks): 0 ground, 1 gray reflector,
    2 white paper, 3 black ink.
    """

    material_names = ("soil", "vegetation", "gray_reflector", "white_paper", "black_ink")
    GROUND, GRAY, PAPER, INK = 0, 1, 2, 3

    def __init__(self, wavelengths, reflector_reflectance, size_m, marker: MarkerSpec, light,
                 ground_seed: int):
        wl = np.asarray(wavelengths, dtype=np.float64)
        n = wl.size
        rho = np.broadcast_to(np.asarray(reflector_reflectance, dtype=np.float64), (n,))
        self.reflectance = np.stack([
            soil_reflectance(wl), vegetation_reflectance(wl), rho,
            np.full(n, marker.paper_reflectance), np.full(n, marker.ink_reflectance),
        ])
        self.size_m = (float(size_m[0]), float(size_m[1]))
        self.marker = marker
        self.light = light
        self._bits = marker.bits()
        rng = np.random.default_rng([ground_seed, 7])
        self._cover = PeriodicNoise(rng, 0.01, 3.0)
        self._tex_v = PeriodicNoise(rng, 0.005, 2.0)
        self._tex_s = PeriodicNoise(rng, 0.01, 2.0)

    def evaluate(self, u: np.ndarray, v: np.ndarray):
        """(u, v) plane points (N,) -> weights (K, N) float32 (``B`` x area of each material,
        ground texture included) and hard labels (N,) uint8."""
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        B = self.light(u, v)
        au, av = np.abs(u), np.abs(v)
        s = self.marker.size_m
        half_p = 0.5 * s + self.marker.border_m
        lab = ((au <= 0.5 * self.size_m[0]) & (av <= 0.5 * self.size_m[1])).astype(np.uint8)
        idx = np.flatnonzero((au <= half_p) & (av <= half_p))  # paper: a small subset
        if idx.size:
            pu, pv = u.ravel()[idx], v.ravel()[idx]
            sub = np.full(idx.size, self.PAPER, dtype=np.uint8)
            in_mark = (np.abs(pu) < 0.5 * s) & (np.abs(pv) < 0.5 * s)
            nb = self._bits.shape[0]
            col = np.clip(np.floor((pu + 0.5 * s) / s * nb), 0, nb - 1).astype(np.intp)
            row = np.clip(np.floor((0.5 * s - pv) / s * nb), 0, nb - 1).astype(np.intp)
            sub[in_mark & (self._bits[row, col] == 0)] = self.INK
            lab.ravel()[idx] = sub
        ground = lab == self.GROUND
        cover = np.clip(0.6 + 0.45 * self._cover(u, v), 0.0, 1.0)
        w = np.zeros((5,) + u.shape, dtype=np.float32)
        gB = np.where(ground, B, np.float32(0.0))
        w[0] = gB * (1.0 - cover) * (1.0 + 0.12 * self._tex_s(u, v))
        w[1] = gB * cover * (1.0 + 0.15 * self._tex_v(u, v))
        for k in (self.GRAY, self.PAPER, self.INK):
            w[k + 1] = np.where(lab == k, B, np.float32(0.0))
        return w, lab


@dataclass(frozen=True)
class Panel:
    centre_m: tuple[float, float]
    size_m: float
    reflectance: float


class FieldScene:
    """Crop field (rows of a green crop on soil) with flat gray panels, lit uniformly.

    Ground plane z = 0, u east, v north (metres). Hard labels: 0 ground, 1 + k panel k.
    Materials: soil, vegetation, then one per panel.
    """

    def __init__(self, wavelengths, panels: Sequence[Panel], sun: float, field_seed: int,
                 row_spacing_m: float = 0.75):
        wl = np.asarray(wavelengths, dtype=np.float64)
        n = wl.size
        self.panels = tuple(panels)
        self.material_names = ("soil", "vegetation") + tuple(
            f"panel_{p.reflectance:.2f}" for p in self.panels
        )
        self.reflectance = np.stack(
            [soil_reflectance(wl), vegetation_reflectance(wl)]
            + [np.full(n, p.reflectance) for p in self.panels]
        )
        self.light = UniformLight(float(sun))
        self.row_spacing_m = row_spacing_m
        rng = np.random.default_rng([field_seed, 11])
        self._width = PeriodicNoise(rng, 0.05, 4.0)
        self._gaps = PeriodicNoise(rng, 0.10, 3.0)
        self._weeds = PeriodicNoise(rng, 0.02, 2.5)
        self._tex_v = PeriodicNoise(rng, 0.01, 2.0)
        self._tex_s = PeriodicNoise(rng, 0.02, 2.0)
        self.soft_m = 0.01

    def vegetation_cover(self, u, v) -> np.ndarray:
        sp = np.float32(self.row_spacing_m)
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        f = u / sp
        f -= np.floor(f)
        d = np.abs(f - np.float32(0.5)) * sp  # distance to the nearest row centre
        hw = 0.17 * (1.0 + 0.3 * self._width(u, v)) * np.clip(1.6 + 0.9 * self._gaps(u, v), 0, 1)
        rows = np.clip(0.5 + (hw - d) / self.soft_m, 0.0, 1.0)
        weeds = np.clip(0.5 + (self._weeds(u, v) - 2.2) / 0.15, 0.0, 1.0)
        return np.maximum(rows, weeds)

    def evaluate(self, u: np.ndarray, v: np.ndarray):
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        B = self.light(u, v)
        lab = np.zeros(u.shape, dtype=np.uint8)
        for k, p in enumerate(self.panels):
            inside = (np.abs(u - p.centre_m[0]) <= 0.5 * p.size_m) & (
                np.abs(v - p.centre_m[1]) <= 0.5 * p.size_m)
            lab[inside] = 1 + k
        ground = lab == 0
        cover = self.vegetation_cover(u, v)
        w = np.zeros((2 + len(self.panels),) + u.shape, dtype=np.float32)
        gB = np.where(ground, B, np.float32(0.0))
        w[0] = gB * (1.0 - cover) * (1.0 + 0.10 * self._tex_s(u, v))
        w[1] = gB * cover * (1.0 + 0.12 * self._tex_v(u, v))
        for k in range(len(self.panels)):
            w[2 + k] = np.where(lab == 1 + k, B, np.float32(0.0))
        return w, lab


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


@dataclass
class Render:
    """Result of :func:`render` for one pose, per band on the band grid.

    ``channels`` (K, n_bands, H, W) float32: footprint integral of ``B x area`` of each material
    (ground texture included); radiance per band is ``S * sum_k channels_k * R_k``.
    ``labels`` (n_bands, H, W) uint8 hard label at each sample centre (255 where the ray misses
    the plane); ``edge`` (n_bands, H, W) bool: the sample's footprint (or a neighbour's)
    straddles a hard edge or lies within the lens PSF's reach (3 sigma) of one, so it is not a
    pure sample of its label. ``sensor_u``, ``sensor_v`` (Hs, Ws) plane point of every sensor
    pixel centre (see :meth:`plane_uv`); ``reach_px`` that PSF reach in sensor pixels.
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

    Every sensor pixel centre (band-grid point ``(xs/5, ys/5)``) is back-projected and
    intersected with the plane; pixels whose 3 x 3 neighbourhood crosses a hard label edge are
    re-evaluated on a ``supersample x supersample`` grid over the sensor pixel (100 % fill
    factor) and averaged; a Gaussian lens PSF of ``psf_sigma_px`` sensor pixels (0.24 band-grid
    pixels by default) is applied to the material channels (radiance is linear in them), then
    the sensor grid is split into bands.
    """
    xn, yn, (dxx, dxy, dyx, dyy) = camera.sensor_rays()
    u, v, ok = _intersect(pose, xn, yn)
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
        su, sv, sok = _intersect(pose, sx, sy)
        ws_, _ = scene.evaluate(su, sv)
        ws_ *= sok
        w[:, iy, ix] = ws_.mean(axis=-1)
    if psf_sigma_px > 0:
        for k in range(w.shape[0]):
            w[k] = cv2.GaussianBlur(w[k], (0, 0), psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    reach = int(math.ceil(3.0 * psf_sigma_px)) + 1
    near = cv2.dilate(edge.astype(np.uint8), _disk(reach)).astype(bool)
    return Render(
        channels=camera.split_bands(w),
        labels=camera.split_bands(lab),
        edge=camera.split_bands(near),
        sensor_u=u, sensor_v=v, pattern_shape=tuple(camera.pattern_shape), reach_px=reach,
    )


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def detect_marker_corners(image: np.ndarray, marker: MarkerSpec,
                          min_marker_distance_rate: float = 0.05) -> np.ndarray | None:
    """ArUco corners (4, 2) of ``marker`` in a band image (any dtype), or None. For checks.

    0.5-99.5 percentile stretch to 8 bits, ``CORNER_REFINE_SUBPIX`` (window 3). OpenCV's
    default ``minMarkerDistanceRate`` (0.125) merges the marker with the outline of its white
    paper when the paper border is narrower than ~0.35 marker sides, and then keeps the paper
    outline (which does not decode): the marker is lost in some views. 0.05 avoids that.
    """
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [0.5, 99.5])
    img8 = np.clip(np.rint((img - lo) / max(hi - lo, 1e-9) * 255.0), 0, 255).astype(np.uint8)
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


def marker_pose_from_image(image: np.ndarray, band: int, camera: SnapshotCamera,
                           marker: MarkerSpec) -> Pose | None:
    """Pose of the marker seen in one band image: ArUco corners (+ the band's offset) and
    ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` with corners TL, TR, BR, BL = (-s/2, +s/2),
    (+s/2, +s/2), (+s/2, -s/2), (-s/2, -s/2). None if the marker is not found."""
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
    """(rotation error in degrees, relative translation error) of ``estimate``."""
    dR = truth.R.T @ estimate.R
    ang = math.degrees(math.acos(float(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    rel = float(np.linalg.norm(estimate.tvec - truth.tvec) / np.linalg.norm(truth.tvec))
    return ang, rel


# --------------------------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------------------------


def _make_sensor(bits: int) -> SensorModel:
    return SensorModel(bits=int(bits))


def _vignetting(camera: SnapshotCamera, rng: np.random.Generator):
    """Per-band off-centre radial vignetting ``V = (1 + k rho^2)^-2`` (cos^4-like), max 1.

    Centre offset per band: a smooth function of wavelength (lateral chromatic shift) plus
    filter-to-filter jitter, within (+-15, +-8) band-grid pixels of the image centre. Strength:
    mean falloff at the four corners 37-44 %, smooth in wavelength plus jitter.
    """
    h, w = camera.grid_shape
    wl = camera.wavelengths
    x01 = (wl - 600.0) / 275.0
    phase = rng.uniform(0, 2 * np.pi, 2)
    dx = 9.0 * np.sin(2.5 * x01 + phase[0]) + rng.normal(0, 3.0, wl.size)
    dy = 5.0 * np.sin(2.0 * x01 + phase[1]) + rng.normal(0, 1.5, wl.size)
    dx, dy = np.clip(dx, -15, 15), np.clip(dy, -8, 8)
    falloff = 0.37 + 0.05 * x01 + rng.normal(0, 0.01, wl.size)
    falloff = np.clip(falloff, 0.37, 0.44)
    offs = camera.band_offsets
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    V = np.empty((wl.size, h, w))
    centres = np.stack([camera.cx + dx, camera.cy + dy], axis=1)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
    for b in range(wl.size):
        cxb, cyb = centres[b]
        rho2 = ((jj + offs[b, 0] - cxb) ** 2 + (ii + offs[b, 1] - cyb) ** 2) / camera.fx**2
        c_rho2 = ((corners[:, 0] + offs[b, 0] - cxb) ** 2
                  + (corners[:, 1] + offs[b, 1] - cyb) ** 2) / camera.fx**2
        lo, hi = 0.0, 10.0  # k such that the mean corner value is 1 - falloff
        for _ in range(60):
            k = 0.5 * (lo + hi)
            if np.mean((1 + k * c_rho2) ** -2) > 1 - falloff[b]:
                lo = k
            else:
                hi = k
        vb = (1.0 + k * rho2) ** -2
        V[b] = vb / vb.max()
    return V, centres


def _spectral_factor(wl: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """S(lambda) in [1.5, 2.5]: smooth (sun x sensor QE x filter peak) plus filter variation."""
    x01 = (wl - 600.0) / 275.0
    smooth = 2.0 + 0.28 * np.sin(np.pi * (1.2 * x01 + 0.1)) - 0.1 * x01  # 1.67 .. 2.25
    return np.clip(smooth * (1.0 + rng.normal(0.0, 0.05, wl.size)), 1.52, 2.48)


@dataclass(frozen=True)
class SyntheticTruth:
    """Everything the fits should recover, plus the camera and sensor used to render.

    ``vignetting`` (n_bands, H, W) V_true, max 1 per band, evaluated at each band's own sample
    positions; ``spectral_factor`` (n_bands,) S_true; ``inverse_response`` (n_bands, 2**bits)
    true U (the same sensor for every band); ``reflector_reflectance`` (n_bands,) R_s.
    """

    seed: int
    camera: SnapshotCamera
    sensor: object
    vignetting: np.ndarray
    vignetting_centre: np.ndarray
    spectral_factor: np.ndarray
    reflector_reflectance: np.ndarray
    reflector_size_m: tuple[float, float]
    marker: MarkerSpec
    sun_brightness: float

    @property
    def inverse_response(self) -> np.ndarray:
        U = np.asarray(self.sensor.inverse_response(), dtype=np.float64)
        return np.tile(U, (self.camera.n_bands, 1))

    @property
    def black_level(self) -> float:
        return float(self.sensor.black_level)

    @property
    def dn_max(self) -> int:
        return 2 ** int(self.camera.bits) - 1


def make_truth(
    seed: int = 0,
    *,
    camera: SnapshotCamera | None = None,
    sensor=None,
    reflector_reflectance: float | Sequence[float] = 0.5,
    reflector_size_m: tuple[float, float] = (0.5, 0.5),
    marker: MarkerSpec | None = None,
) -> SyntheticTruth:
    """Seeded camera truth: V_true (off-centre, per band), S_true, sensor (U_true)."""
    camera = camera or SnapshotCamera()
    marker = marker or MarkerSpec()
    sensor = sensor if sensor is not None else _make_sensor(camera.bits)
    rng = np.random.default_rng([seed, 1])
    V, centres = _vignetting(camera, rng)
    S = _spectral_factor(camera.wavelengths, rng)
    rho = np.broadcast_to(np.asarray(reflector_reflectance, dtype=np.float64),
                          (camera.n_bands,)).copy()
    return SyntheticTruth(
        seed=seed, camera=camera, sensor=sensor, vignetting=V, vignetting_centre=centres,
        spectral_factor=S, reflector_reflectance=rho,
        reflector_size_m=(float(reflector_size_m[0]), float(reflector_size_m[1])),
        marker=marker, sun_brightness=float(rng.uniform(260.0, 320.0)),
    )


# --------------------------------------------------------------------------------------------
# Datasets
# --------------------------------------------------------------------------------------------


@dataclass
class FrameSet:
    """Frames of one dataset: band stacks of DN, exposures, per-frame metadata and truth.

    ``dn`` list of (n_bands, H, W) uint16 band stacks (``raw(k)`` gives the sensor mosaic);
    ``exposure_ms`` (n,); ``names`` file stems; ``meta`` per-frame dicts with ``time`` (ISO
    8601) and, for flights, ``lat``, ``lon``, ``alt_m``; ``truth`` arrays (see the dataset
    functions).
    """

    kind: str
    dn: list[np.ndarray]
    exposure_ms: np.ndarray
    names: list[str]
    meta: list[dict]
    truth: dict[str, np.ndarray]
    camera: SnapshotCamera
    black_level: int = 0

    def __len__(self) -> int:
        return len(self.dn)

    def raw(self, k: int) -> np.ndarray:
        """Raw (1088, 2048) uint16 mosaic of frame k; unused sensor rows/cols at black."""
        return self.camera.mosaic(self.dn[k], fill=self.black_level)


def _time(offset_s: float) -> str:
    t = SESSION_START + _dt.timedelta(seconds=float(offset_s))
    return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _round_ms(t: float) -> float:
    return float(round(t, 4))  # 0.1 us: what frames.csv stores, and what is rendered


def _gauge(truth: SyntheticTruth) -> float:
    """``a`` with ``U_true(C(x)) = a x``: the sensor's energy x in the U gauge (~1)."""
    s = truth.sensor
    k = int(s.k_ref) if hasattr(s, "k_ref") else truth.dn_max // 2
    return float(np.asarray(s.inverse_response())[k] / float(s.x_for_dn(k)))


def _expose(truth: SyntheticTruth, energy: np.ndarray, t: float, rng) -> np.ndarray:
    """DN of energy rate ``energy`` (U gauge: ``U_true(I) = t E`` up to noise) over ``t`` ms."""
    return np.asarray(truth.sensor.expose(energy / _gauge(truth), t, rng), dtype=np.uint16)


def _exposure_for(truth: SyntheticTruth, e_max: float, fraction: float) -> float:
    """Exposure (ms, rounded to 0.1 us) putting energy rate ``e_max`` at ``fraction`` of range."""
    x = float(truth.sensor.x_for_dn(fraction * truth.dn_max)) * _gauge(truth)
    return _round_ms(x / e_max)


def response_sweep(truth: SyntheticTruth, *, seed: int = 0, n_frames: int = 14,
                   step: float = 1.66, decades: float = 2.5) -> FrameSet:
    """Exposure sweep of a static scene with a fixed camera (input of Eq. 5-7).

    The scene is a smooth random texture whose radiance spans ``decades`` decades (log-uniform
    histogram), with a smooth per-band colour variation; ``E_b(x) = V_b(x) S_b L_b(x)``. The
    shortest exposure puts the brightest pixel at 30-40 % of range; exposures grow by ``step``
    (``t_i = t_0 step^i``, rounded to 0.1 us), so the longest saturates most pixels.

    truth: ``energy`` (n_bands, H, W) float32 energy rate E (linear DN / ms).
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rng = np.random.default_rng([seed, 2])
    gy, gx = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64),
                         indexing="ij")
    base = PeriodicNoise(rng, 1.0, 7.0, n=512)(gx, gy)
    rank = np.argsort(np.argsort(base.ravel())).reshape(h, w)
    q = (rank + 0.5) / rank.size  # uniform in (0, 1)
    log_l = -decades * (1.0 - q)
    colour = PeriodicNoise(rng, 1.0, 12.0, n=512)
    tint = np.stack([colour(gx + 97.0 * b, gy + 31.0 * b) for b in range(3)])
    coef = rng.normal(0.0, 0.08, (cam.n_bands, 3))
    log_lb = log_l[None] + np.einsum("bk,khw->bhw", coef, tint)
    energy = truth.vignetting * truth.spectral_factor[:, None, None] * 10.0 ** log_lb
    # brightest pixel 1000 linear DN / ms: the shortest exposure is then ~0.3-0.4 ms, so the
    # 0.1 us rounding of the exposures is negligible
    energy = (energy * 1000.0 / energy.max()).astype(np.float32)
    t0 = _exposure_for(truth, float(energy.max()), rng.uniform(0.30, 0.40))
    exposures = np.array([_round_ms(t0 * step**i) for i in range(n_frames)])
    dn = [_expose(truth, energy, t, rng) for t in exposures]
    return FrameSet(
        kind="response", dn=dn, exposure_ms=exposures,
        names=[f"sweep_{i:02d}" for i in range(n_frames)],
        meta=[{"time": _time(2.0 * i)} for i in range(n_frames)],
        truth={"energy": energy}, camera=cam, black_level=int(round(truth.black_level)),
    )


def _random_tilt(rng, max_tilt_deg: float) -> np.ndarray:
    phi = rng.uniform(0, 2 * np.pi)
    # more small tilts than large ones, like a hand-held camera, up to max_tilt_deg
    theta = np.deg2rad(max_tilt_deg) * math.sqrt(rng.uniform(0, 1))
    return _rot([math.cos(phi), math.sin(phi), 0.0], theta)


def _plane_grid(size_m, step_m=0.0025):
    uu = np.arange(-0.5 * size_m[0], 0.5 * size_m[0] + 1e-9, step_m)
    vv = np.arange(-0.5 * size_m[1], 0.5 * size_m[1] + 1e-9, step_m)
    return uu, vv


def _random_light(rng, brightness: float, size_m, shadow: bool = True,
                  nonuniformity: float = 1.0) -> GradientShadowLight:
    """Random 2:1 gradient + soft shadow (35-50 % deep) on the reflector.

    ``nonuniformity`` ``a`` scales how uneven the light is, with the same random draws:
    gradient ratio ``2**a`` and shadow transmission ``(1 - depth)**a`` (``a = 0``: uniform
    light; ``1``: the default; ``2``: a 4:1 gradient and a 58-75 % deep shadow).
    """
    if nonuniformity < 0:
        raise ValueError(f"light nonuniformity must be >= 0, got {nonuniformity}")
    ratio = 2.0 if nonuniformity == 1.0 else 2.0**nonuniformity
    if not shadow:
        return GradientShadowLight(brightness=brightness, gradient_dir=rng.uniform(0, 2 * np.pi),
                                   extent_m=size_m, gradient_ratio=ratio)
    sdir = rng.uniform(0, 2 * np.pi)
    # the shadow edge crosses the reflector so that 20-35 % of it is in shadow
    half = 0.5 * size_m[0] * abs(math.cos(sdir)) + 0.5 * size_m[1] * abs(math.sin(sdir))
    gdir = rng.uniform(0, 2 * np.pi)
    depth = rng.uniform(0.35, 0.5)
    if nonuniformity != 1.0:
        depth = 1.0 - (1.0 - depth) ** nonuniformity
    return GradientShadowLight(
        brightness=brightness, gradient_dir=gdir, gradient_ratio=ratio,
        extent_m=size_m, shadow_depth=depth, shadow_dir=sdir,
        shadow_offset_m=half * rng.uniform(0.3, 0.6), shadow_softness_m=rng.uniform(0.008, 0.015),
    )


def _frame_marker_ok(cam: SnapshotCamera, pose: Pose, marker: MarkerSpec, margin_px: float,
                     min_side_px: float) -> tuple[bool, np.ndarray]:
    s = 0.5 * marker.size_m
    pts = np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]])
    pc = pose.to_camera(pts)
    if np.any(pc[:, 2] <= 0.05):
        return False, np.zeros((4, 2))
    px = cam.project(pc)
    h, w = cam.grid_shape
    inside = np.all((px[:, 0] >= margin_px) & (px[:, 0] <= w - 1 - margin_px)
                    & (px[:, 1] >= margin_px) & (px[:, 1] <= h - 1 - margin_px))
    side = np.min(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1))
    return bool(inside and side >= min_side_px), px


def _pose_through(cam: SnapshotCamera, R: np.ndarray, pixel: np.ndarray, q: np.ndarray,
                  depth: float) -> Pose:
    """Pose with rotation R such that image point ``pixel`` sees plane point ``q`` and the
    marker centre is at camera depth ~``depth``."""
    r = np.append(cam.rays(pixel.reshape(1, 2))[0], 1.0)
    Rq = R @ np.array([q[0], q[1], 0.0])
    lam = depth + Rq[2]
    return Pose.from_matrix(R, lam * r - Rq)


def _facing(pose: Pose, max_view_deg: float) -> bool:
    C = pose.camera_centre
    return C[2] > 0 and C[2] / np.linalg.norm(C) >= math.cos(math.radians(max_view_deg))


def vignetting_views(truth: SyntheticTruth, *, seed: int = 0, n_views: int = 40,
                     n_missing: int = 1, max_tilt_deg: float = 35.0,
                     distance_m: tuple[float, float] = (0.8, 1.6), supersample: int = 4,
                     max_attempts: int = 400, light_nonuniformity: float = 1.0) -> FrameSet:
    """Gray reflector + marker from many viewpoints under fixed non-uniform light (Eq. 8-10).

    The light ``B(p)`` (2:1 gradient + soft shadow) is fixed on the plane, so the radiance
    ``L_b(p) = S_b B(p) R_s`` is the same from every viewpoint (Lambertian). Views are planned
    greedily: each aims a random reflector point (outside the marker and its paper) at the
    least covered part of the image, with a random tilt (<= ``max_tilt_deg`` from the optical
    axis), roll and marker distance in ``distance_m``, and is kept only if the marker projects
    fully inside the frame and is detected by ArUco in bands 0, 12 and 24. ``n_missing`` views
    (spread over the sequence) have the marker out of frame while the reflector is partly in
    view: the pipeline must skip them. Exposure: brightest gray-reflector pixel at 70-85 %.
    ``light_nonuniformity`` scales how uneven the light is (0 uniform, 1 default, 2 a 4:1
    gradient and a deeper shadow; see :func:`_random_light`).

    truth: ``rvec``, ``tvec`` (n, 3); ``marker_in_frame`` (n,) bool; ``pose_error_deg``,
    ``pose_error_rel`` (n,) error of the pose from ArUco + IPPE on band 0 (NaN if missing);
    ``found_default_detector`` (n,) the marker is also found with OpenCV's default
    ``minMarkerDistanceRate`` (see :func:`detect_marker_corners`); ``gray_mask`` (n, H, W)
    pixels on the gray reflector in every band (no edge, marker or paper); ``coverage`` (H, W)
    number of views with the pixel on the gray reflector; ``light`` (9,) light parameters
    (``GradientShadowLight.from_params`` rebuilds it); ``plane_u`` (Nu,), ``plane_v`` (Nv,),
    ``B_plane`` (Nv, Nu) the brightness on a 2.5 mm grid of the reflector (L = S B R_s).
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rng = np.random.default_rng([seed, 3])
    light = _random_light(rng, 0.8 * truth.sun_brightness, truth.reflector_size_m,
                          nonuniformity=light_nonuniformity)
    scene = ReflectorScene(cam.wavelengths, truth.reflector_reflectance, truth.reflector_size_m,
                           truth.marker, light, ground_seed=seed)
    mk = truth.marker
    half_in = 0.5 * mk.size_m + mk.border_m + 0.02
    half_out = np.array(truth.reflector_size_m) * 0.5 - 0.03
    missing_at = set(
        np.linspace(0, n_views - 1, n_missing + 2)[1:-1].round().astype(int).tolist()
    ) if n_missing else set()
    coverage = np.zeros((h, w), dtype=np.int32)
    ch, cw = 14, 26  # coarse coverage cells
    row_starts = np.linspace(0, h, ch + 1).astype(int)[:-1]
    col_starts = np.linspace(0, w, cw + 1).astype(int)[:-1]
    out_dn, exposures, rvecs, tvecs, in_frame, masks = [], [], [], [], [], []
    pose_err, default_ok = [], []
    detect_bands = sorted({0, cam.n_bands // 2, cam.n_bands - 1})
    for k in range(n_views):
        missing = k in missing_at
        for _attempt in range(max_attempts):
            if missing:
                # aim the reflector at an image border; marker centre outside the frame
                side = int(rng.integers(4))
                t_px = np.array([rng.uniform(0, w - 1), rng.uniform(0, h - 1)])
                if side == 0:
                    t_px[0] = rng.uniform(0, 25)
                elif side == 1:
                    t_px[0] = rng.uniform(w - 26, w - 1)
                elif side == 2:
                    t_px[1] = rng.uniform(0, 15)
                else:
                    t_px[1] = rng.uniform(h - 16, h - 1)
            else:
                # least covered pixel of each coarse cell, ties broken at random
                cov = np.minimum.reduceat(np.minimum.reduceat(coverage, row_starts, axis=0),
                                          col_starts, axis=1).astype(np.float64)
                cov += rng.uniform(0, 0.5, cov.shape)
                cy_, cx_ = np.unravel_index(np.argmin(cov), cov.shape)
                t_px = np.array([(cx_ + rng.uniform()) * w / cw, (cy_ + rng.uniform()) * h / ch])
            # a plane point on the gray part of the reflector
            while True:
                q = rng.uniform(-half_out, half_out)
                if np.max(np.abs(q)) >= half_in:
                    break
            yaw = _rot([0, 0, 1], rng.uniform(0, 2 * np.pi))
            R = _random_tilt(rng, max_tilt_deg) @ _FRONTAL @ yaw
            depth = rng.uniform(*distance_m)
            pose = _pose_through(cam, R, t_px, q, depth)
            if not _facing(pose, 60.0):
                continue
            ok, px = _frame_marker_ok(cam, pose, mk, margin_px=4.0, min_side_px=16.0)
            if missing:
                centre = px.mean(axis=0)
                out_by = max(-centre[0], centre[0] - (w - 1), -centre[1], centre[1] - (h - 1))
                behind = pose.to_camera(np.zeros((1, 3)))[0, 2] <= 0.05
                if behind or out_by < 0.6 * np.ptp(px[:, 0]) + 3:
                    continue
            elif not ok:
                continue
            rend = render(cam, pose, scene, supersample=supersample)
            gray = rend.pure(ReflectorScene.GRAY)
            if gray.sum() < (0.03 if missing else 0.05) * h * w:
                continue
            energy = (truth.vignetting * truth.spectral_factor[:, None, None]
                      * rend.light_times_reflectance(scene.reflectance)).astype(np.float32)
            t = _exposure_for(truth, float(energy[:, gray].max()), rng.uniform(0.70, 0.85))
            dn = _expose(truth, energy, t, rng)
            found = [detect_marker_corners(dn[b], mk) is not None for b in detect_bands]
            if missing and any(found):
                continue
            if not missing and not all(found):
                continue
            break
        else:  # pragma: no cover - planning is seeded; this would be a bug in the planner
            raise RuntimeError(f"could not plan vignetting view {k} in {max_attempts} attempts")
        if not missing:
            coverage += gray
            est = marker_pose_from_image(dn[0], 0, cam, mk)
            perr = pose_error(est, pose) if est is not None else (np.nan, np.nan)
            default_found = detect_marker_corners(dn[0], mk, 0.125) is not None
        else:
            perr, default_found = (np.nan, np.nan), False
        pose_err.append(perr)
        default_ok.append(default_found)
        out_dn.append(dn)
        exposures.append(t)
        rvecs.append(pose.rvec)
        tvecs.append(pose.tvec)
        in_frame.append(not missing)
        masks.append(gray)
    uu, vv = _plane_grid(truth.reflector_size_m)
    U, Vg = np.meshgrid(uu, vv)
    n = len(out_dn)
    return FrameSet(
        kind="vignetting", dn=out_dn, exposure_ms=np.array(exposures),
        names=[f"view_{i:02d}" for i in range(n)],
        meta=[{"time": _time(300.0 + 6.0 * i)} for i in range(n)],
        truth={
            "rvec": np.array(rvecs), "tvec": np.array(tvecs),
            "marker_in_frame": np.array(in_frame), "gray_mask": np.array(masks),
            "coverage": coverage,
            "pose_error_deg": np.array([e[0] for e in pose_err]),
            "pose_error_rel": np.array([e[1] for e in pose_err]),
            "found_default_detector": np.array(default_ok), "light": light.params(),
            "plane_u": uu, "plane_v": vv, "B_plane": light(U, Vg),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )


def reflector_images(truth: SyntheticTruth, *, seed: int = 0, n_images: int = 3,
                     distance_m: tuple[float, float] = (0.55, 0.75), max_tilt_deg: float = 12.0,
                     supersample: int = 4, max_attempts: int = 200,
                     times_s: Sequence[float] | None = None, drift: LightDrift | None = None,
                     irradiance: bool = False, name_prefix: str = "reflector_",
                     gradient_ratio: float = 2.0, light_nonuniformity: float = 1.0) -> FrameSet:
    """Gray reflector under the illumination of the flight (input of Eq. 11-14).

    Near-nadir views from 0.55-0.75 m, the reflector filling much of the frame. Each image has
    its own light: sun brightness (x 0.9-1.1) with a 2:1 linear gradient across the reflector
    in a random direction and a soft shadow over 20-35 % of it; the light colour S is the
    flight's. Exposure: brightest gray-reflector pixel at 70-85 %.
    ``light_nonuniformity`` as in :func:`vignetting_views`.

    Light that changes over the flight (issue 8): image ``k`` is taken at ``times_s[k]``
    (seconds after ``SESSION_START``; default 900 + 20 k). With ``drift`` its brightness is
    the sun's times ``drift.level(time)`` (no random factor), its colour ``S`` times
    ``drift.colour(time)``, and the light has a ``gradient_ratio`` gradient but no shadow (the
    reflector fully in the sun, as a capture for the light's level should be). ``irradiance`` writes a
    sun-sensor reading (the brightness, in arbitrary units) into each frame's ``meta``.

    truth: ``rvec``, ``tvec`` (n, 3); ``B`` (n, H, W) float32 brightness at the band-grid pixel
    centres (band 0 sample positions; NaN where the ray misses the plane); ``gray_mask``
    (n, H, W); ``light`` (n, 9) (``GradientShadowLight.from_params``); ``plane_u``,
    ``plane_v``, ``B_plane`` (n, Nv, Nu).
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rng = np.random.default_rng([seed, 4])
    mk = truth.marker
    uu, vv = _plane_grid(truth.reflector_size_m)
    U, Vg = np.meshgrid(uu, vv)
    dns, exposures, rvecs, tvecs, Bs, masks, lights, Bp = [], [], [], [], [], [], [], []
    times = [900.0 + 20.0 * i for i in range(n_images)] if times_s is None else [float(x) for x in times_s]
    S = truth.spectral_factor
    for k in range(n_images):
        jitter = rng.uniform(0.9, 1.1)  # drawn in every case: the seeded stream stays the same
        if drift is None:
            light = _random_light(rng, truth.sun_brightness * jitter, truth.reflector_size_m,
                                  nonuniformity=light_nonuniformity)
        else:
            light = GradientShadowLight(brightness=truth.sun_brightness * drift.level(times[k]),
                                        gradient_dir=rng.uniform(0, 2 * np.pi), gradient_ratio=gradient_ratio,
                                        extent_m=truth.reflector_size_m)
            S = truth.spectral_factor * drift.colour(times[k], cam.wavelengths)
        scene = ReflectorScene(cam.wavelengths, truth.reflector_reflectance,
                               truth.reflector_size_m, mk, light, ground_seed=seed + 17 * k)
        for _attempt in range(max_attempts):
            R = _random_tilt(rng, max_tilt_deg) @ _FRONTAL @ _rot([0, 0, 1], rng.normal(0, 0.15))
            t_px = np.array([cam.cx + rng.normal(0, 15), cam.cy + rng.normal(0, 8)])
            pose = _pose_through(cam, R, t_px, np.zeros(2), rng.uniform(*distance_m))
            ok, _ = _frame_marker_ok(cam, pose, mk, margin_px=6.0, min_side_px=20.0)
            if not ok:
                continue
            rend = render(cam, pose, scene, supersample=supersample)
            gray = rend.pure(ReflectorScene.GRAY)
            energy = (truth.vignetting * S[:, None, None]
                      * rend.light_times_reflectance(scene.reflectance)).astype(np.float32)
            t = _exposure_for(truth, float(energy[:, gray].max()), rng.uniform(0.70, 0.85))
            dn = _expose(truth, energy, t, rng)
            if detect_marker_corners(dn[0], mk) is None:
                continue
            break
        else:  # pragma: no cover
            raise RuntimeError(f"could not plan reflector image {k}")
        u0, v0 = rend.plane_uv(0)
        B = light(u0, v0).astype(np.float32)
        B[(np.abs(u0) >= _FAR / 2)] = np.nan
        dns.append(dn)
        exposures.append(t)
        rvecs.append(pose.rvec)
        tvecs.append(pose.tvec)
        Bs.append(B)
        masks.append(gray)
        lights.append(light.params())
        Bp.append(light(U, Vg))
    meta = [{"time": _time(times[i])} for i in range(n_images)]
    if irradiance:
        for i in range(n_images):
            meta[i]["irradiance"] = float(lights[i][0])  # the brightness the image was rendered with
    return FrameSet(
        kind="reflector", dn=dns, exposure_ms=np.array(exposures),
        names=[f"{name_prefix}{i}" for i in range(n_images)],
        meta=meta,
        truth={
            "rvec": np.array(rvecs), "tvec": np.array(tvecs), "B": np.array(Bs),
            "gray_mask": np.array(masks), "light": np.array(lights),
            "plane_u": uu, "plane_v": vv, "B_plane": np.array(Bp),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )


DEFAULT_PANELS = (
    Panel((-4.5, 0.0), 1.2, 0.05),
    Panel((-1.5, 0.0), 1.2, 0.20),
    Panel((1.5, 0.0), 1.2, 0.50),
    Panel((4.5, 0.0), 1.2, 0.90),
)


def flight_frames(truth: SyntheticTruth, *, seed: int = 0, n_frames: int = 8,
                  name: str = "field", altitude_m: float = 25.0, spacing_m: float = 1.8,
                  panels: Sequence[Panel] = DEFAULT_PANELS, supersample: int = 3,
                  time_offset_s: float = 1200.0, frame_interval_s: float = 2.0,
                  drift: LightDrift | None = None, clouds: bool = True, irradiance: bool = False) -> FrameSet:
    """Nadir-ish survey frames of a crop field with gray panels (target of Eq. 15).

    Frames are taken along a north-going line at ~``altitude_m`` (GSD ~5.7 cm per band-grid
    pixel at 25 m), ``spacing_m`` apart, with small roll/pitch/yaw, so the panel row (v = 0) is
    seen in several frames at different image rows. Light is uniform within a frame,
    ``B = sun_k`` with ``sun_k`` (clouds) unknown to the fit; its colour ``S`` is the one of
    the reflector images. Exposure per frame (auto exposure): brightest pixel at 72-82 %.
    Reflectance: soil and a green crop (rows 0.75 m apart, gaps, weeds; brightness textures
    that scale all bands alike), panels spectrally flat.

    truth: ``rvec``, ``tvec`` (n, 3); ``sun`` (n,); ``reflectance`` (n, n_bands, H, W)
    float16: the true reflectance of each pixel's footprint (= U(I) / (t V S sun));
    ``labels`` (n, H, W) int8: material index (into ``material_names``) where the pixel is pure
    in every band, -1 where mixed; ``material_names`` (M,); ``material_reflectance``
    (issue 8: frame ``k`` is taken at ``time_offset_s + frame_interval_s k``; with ``drift``
    the sun is also multiplied by ``drift.level(time)`` and ``S`` by ``drift.colour(time)``;
    ``clouds=False`` drops the random per-frame factor 0.75-1.15; ``irradiance`` writes the
    frame's sun brightness into its ``meta`` as a sun-sensor reading)
    (M, n_bands); ``ndvi`` (n, H, W) float32 from the 670 / 803 nm bands of ``reflectance``;
    ``panel_reflectance`` (P,); ``panel_centre_m`` (P, 2); ``height_m`` (n,).
    """
    cam = truth.camera
    h, w = cam.grid_shape
    tag = zlib.crc32(name.encode()) & 0x7FFFFFFF
    rng = np.random.default_rng([seed, 5, tag])
    lat0, lon0 = FIELD_LAT_LON
    red, nir = cam.band_index(NDVI_RED_NM), cam.band_index(NDVI_NIR_NM)
    out = {k: [] for k in ("dn", "t", "rvec", "tvec", "sun", "refl", "labels", "ndvi", "height")}
    meta = []
    scene0 = None
    for k in range(n_frames):
        tau = time_offset_s + frame_interval_s * k
        cloud = rng.uniform(0.75, 1.15)  # drawn in every case: the seeded stream stays the same
        sun = truth.sun_brightness * (cloud if clouds else 1.0)
        S = truth.spectral_factor
        if drift is not None:
            sun *= drift.level(tau)
            S = truth.spectral_factor * drift.colour(tau, cam.wavelengths)
        scene = FieldScene(cam.wavelengths, panels, sun, field_seed=seed)
        scene0 = scene0 or scene
        height = altitude_m + rng.normal(0.0, 0.3)
        cu = rng.uniform(-1.5, 1.5)
        cv_ = (k - 0.5 * (n_frames - 1)) * spacing_m + rng.normal(0, 0.2)
        R = (_rot([1, 0, 0], np.deg2rad(np.clip(rng.normal(0, 1.2), -3, 3)))
             @ _rot([0, 1, 0], np.deg2rad(np.clip(rng.normal(0, 1.2), -3, 3)))
             @ _FRONTAL @ _rot([0, 0, 1], np.deg2rad(rng.normal(0, 3.0))))
        pose = Pose.from_matrix(R, -R @ np.array([cu, cv_, height]))
        rend = render(cam, pose, scene, supersample=supersample)
        br = rend.light_times_reflectance(scene.reflectance)
        energy = (truth.vignetting * S[:, None, None] * br).astype(np.float32)
        t = _exposure_for(truth, float(energy.max()), rng.uniform(0.72, 0.82))
        dn = _expose(truth, energy, t, rng)
        refl = br / sun
        labels = np.full((h, w), -1, dtype=np.int8)
        # vegetation / soil purity: cover 1 / 0 everywhere within the PSF's reach
        cover = scene.vegetation_cover(rend.sensor_u, rend.sensor_v)
        disk = _disk(rend.reach_px)
        veg_pure = np.all(cam.split_bands(cv2.erode(cover, disk) >= 1.0), axis=0)
        soil_pure = np.all(cam.split_bands(cv2.dilate(cover, disk) <= 0.0), axis=0)
        ground_pure = rend.pure(0)
        labels[ground_pure & soil_pure] = 0
        labels[ground_pure & veg_pure] = 1
        for p in range(len(panels)):
            labels[rend.pure(1 + p)] = 2 + p
        with np.errstate(divide="ignore", invalid="ignore"):
            ndvi = ((refl[nir] - refl[red]) / (refl[nir] + refl[red])).astype(np.float32)
        out["dn"].append(dn)
        out["t"].append(t)
        out["rvec"].append(pose.rvec)
        out["tvec"].append(pose.tvec)
        out["sun"].append(sun)
        out["refl"].append(refl.astype(np.float16))
        out["labels"].append(labels)
        out["ndvi"].append(ndvi)
        out["height"].append(height)
        meta.append({
            "time": _time(tau),
            "lat": lat0 + cv_ / 111_320.0,
            "lon": lon0 + cu / (111_320.0 * math.cos(math.radians(lat0))),
            "alt_m": FIELD_GROUND_ALT_M + height,
        })
        if irradiance:
            meta[-1]["irradiance"] = float(sun)
    return FrameSet(
        kind="flight", dn=out["dn"], exposure_ms=np.array(out["t"]),
        names=[f"IMG_{i:04d}" for i in range(n_frames)], meta=meta,
        truth={
            "rvec": np.array(out["rvec"]), "tvec": np.array(out["tvec"]),
            "sun": np.array(out["sun"]), "reflectance": np.array(out["refl"]),
            "labels": np.array(out["labels"]), "ndvi": np.array(out["ndvi"]),
            "material_names": np.array(scene0.material_names),
            "material_reflectance": scene0.reflectance,
            "panel_reflectance": np.array([p.reflectance for p in panels]),
            "panel_centre_m": np.array([p.centre_m for p in panels]),
            "height_m": np.array(out["height"]),
            "ndvi_bands": np.array([red, nir]),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )


# --------------------------------------------------------------------------------------------
# A whole session
# --------------------------------------------------------------------------------------------

SIZES = {
    # response frames, response step, vignetting views, missing-marker views, reflector
    # images, flight frames
    "full": dict(n_response=14, step=1.66, n_views=40, n_missing=2, n_reflector=3, n_flight=8),
    "small": dict(n_response=7, step=3.0, n_views=8, n_missing=1, n_reflector=2, n_flight=3),
}


@dataclass
class SyntheticSession:
    """All four datasets of a session plus the camera truth."""

    truth: SyntheticTruth
    response: FrameSet
    vignetting: FrameSet
    reflector: FrameSet
    flights: dict[str, FrameSet] = field(default_factory=dict)
    size: str = "full"

    def truth_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict of truth arrays (what ``truth.npz`` holds).

        Camera: ``wavelength_nm`` (n_bands,), ``inverse_response`` (n_bands, 2**bits),
        ``black_level``, ``bits``, ``vignetting`` (n_bands, H, W) float32,
        ``vignetting_centre`` (n_bands, 2), ``spectral_factor`` (n_bands,),
        ``reflector_reflectance`` (n_bands,), ``intrinsics`` (fx, fy, cx, cy),
        ``dist`` (5,), ``seed``. Per dataset, its FrameSet truth with a prefix ``response_``,
        ``vignetting_``, ``reflector_``, ``flight_<name>_``, plus ``<prefix>exposure_ms``.
        """
        t = self.truth
        cam = t.camera
        out: dict[str, np.ndarray] = {
            "seed": np.array(t.seed),
            "size": np.array(self.size),
            "wavelength_nm": cam.wavelengths,
            "bits": np.array(cam.bits),
            "black_level": np.array(t.black_level),
            "inverse_response": t.inverse_response,
            "vignetting": t.vignetting.astype(np.float32),
            "vignetting_centre": t.vignetting_centre,
            "spectral_factor": t.spectral_factor,
            "reflector_reflectance": t.reflector_reflectance,
            "reflector_size_m": np.array(t.reflector_size_m),
            "intrinsics": np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            "dist": cam.dist_coeffs,
            "sun_brightness": np.array(t.sun_brightness),
        }
        sets = [("response_", self.response), ("vignetting_", self.vignetting),
                ("reflector_", self.reflector)]
        sets += [(f"flight_{name}_", fs) for name, fs in self.flights.items()]
        for prefix, fs in sets:
            out[prefix + "exposure_ms"] = fs.exposure_ms
            out[prefix + "names"] = np.array(fs.names)
            for key, val in fs.truth.items():
                out[prefix + key] = np.asarray(val)
        return out


def synthesize_session(seed: int = 0, *, size: str = "full", n_flight_frames: int | None = None,
                       flights: Sequence[str] = ("field",),
                       reflector_reflectance: float | Sequence[float] = 0.5) -> SyntheticSession:
    """Render all datasets of a session (``size`` "full" or "small", see ``SIZES``)."""
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    cfg = SIZES[size]
    truth = make_truth(seed, reflector_reflectance=reflector_reflectance)
    resp = response_sweep(truth, seed=seed, n_frames=cfg["n_response"], step=cfg["step"])
    vig = vignetting_views(truth, seed=seed, n_views=cfg["n_views"], n_missing=cfg["n_missing"])
    refl = reflector_images(truth, seed=seed, n_images=cfg["n_reflector"])
    nf = cfg["n_flight"] if n_flight_frames is None else int(n_flight_frames)
    fl = {
        name: flight_frames(truth, seed=seed, n_frames=nf, name=name,
                            time_offset_s=1200.0 + 900.0 * i)
        for i, name in enumerate(flights)
    }
    return SyntheticSession(truth=truth, response=resp, vignetting=vig, reflector=refl,
                            flights=fl, size=size)


# Public names of the planning pieces other synthetic cameras reuse (mscal_core.synth.rig):
# one copy of each, no private imports across modules.
FRONTAL = _FRONTAL
rotation = _rot
random_tilt = _random_tilt
random_light = _random_light
pose_through = _pose_through
__all__ += ["FRONTAL", "rotation", "random_tilt", "random_light", "pose_through"]
