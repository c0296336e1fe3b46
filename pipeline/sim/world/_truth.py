"""The camera truth of a synthetic session (response, vignetting, spectral factor) and the frame set."""

from __future__ import annotations

import datetime as _dt
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._camera import SnapshotCamera
from ._targets import CharucoBoardSpec, MarkerSpec
from .sensor import SensorModel

# Default session start (UTC) for the frame time stamps; the field near Zurich.
SESSION_START = _dt.datetime(2017, 6, 14, 9, 30, 0, tzinfo=_dt.timezone.utc)


def _make_sensor(bits: int) -> SensorModel:
    return SensorModel(bits=int(bits))


def _vignetting(camera: SnapshotCamera, rng: np.random.Generator, falloff_min: float = 0.37,
                centre_shift_px: tuple[float, float] = (0.0, 0.0)):
    """Per-band off-centre radial vignetting ``V = (1 + k rho^2)^-2`` (cos^4-like), max 1.

    Centre offset per band: a smooth function of wavelength (lateral chromatic shift) plus
    filter-to-filter jitter, within (+-15, +-8) band-grid pixels of the image centre, plus a
    common ``centre_shift_px`` (the optical axis off the sensor centre; default none).
    Strength: mean falloff at the four corners ``falloff_min`` to ``falloff_min + 0.07``
    (default 37-44 %), smooth in wavelength plus jitter.
    """
    h, w = camera.grid_shape
    wl = camera.wavelengths
    x01 = (wl - 600.0) / 275.0
    phase = rng.uniform(0, 2 * np.pi, 2)
    dx = 9.0 * np.sin(2.5 * x01 + phase[0]) + rng.normal(0, 3.0, wl.size)
    dy = 5.0 * np.sin(2.0 * x01 + phase[1]) + rng.normal(0, 1.5, wl.size)
    dx, dy = np.clip(dx, -15, 15), np.clip(dy, -8, 8)
    falloff = falloff_min + 0.05 * x01 + rng.normal(0, 0.01, wl.size)
    falloff = np.clip(falloff, falloff_min, falloff_min + 0.07)
    offs = camera.band_offsets
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    V = np.empty((wl.size, h, w))
    centres = np.stack([camera.cx + dx + float(centre_shift_px[0]),
                        camera.cy + dy + float(centre_shift_px[1])], axis=1)
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

    Attributes
    ----------
    seed : int
        Seed of the truth.
    camera : SnapshotCamera
        The camera.
    sensor : SensorModel
        The sensor (true U, noise).
    vignetting : numpy.ndarray
        (n_bands, H, W) V_true, max 1 per band, evaluated at each band's own sample positions.
    vignetting_centre : numpy.ndarray
        Centre of the vignetting falloff.
    spectral_factor : numpy.ndarray
        (n_bands,) S_true.
    reflector_reflectance : numpy.ndarray
        (n_bands,) R_s.
    reflector_size_m : tuple of float
        ``(w, h)`` of the reflector.
    marker : MarkerSpec or CharucoBoardSpec
        The ArUco marker (or ChArUco board) on the reflector.
    sun_brightness : float
        Brightness of the sun in the energy units of the module docstring.
    """

    seed: int
    camera: SnapshotCamera
    sensor: object
    vignetting: np.ndarray
    vignetting_centre: np.ndarray
    spectral_factor: np.ndarray
    reflector_reflectance: np.ndarray
    reflector_size_m: tuple[float, float]
    marker: MarkerSpec | CharucoBoardSpec
    sun_brightness: float

    @property
    def inverse_response(self) -> np.ndarray:
        """True inverse response ``U`` of every band (n_bands, 2**bits)."""
        U = np.asarray(self.sensor.inverse_response(), dtype=np.float64)
        return np.tile(U, (self.camera.n_bands, 1))

    @property
    def black_level(self) -> float:
        """The sensor's black level (DN)."""
        return float(self.sensor.black_level)

    @property
    def dn_max(self) -> int:
        """The largest DN of the camera's bit depth."""
        return 2 ** int(self.camera.bits) - 1


def make_truth(
    seed: int = 0,
    *,
    camera: SnapshotCamera | None = None,
    sensor=None,
    reflector_reflectance: float | Sequence[float] = 0.5,
    reflector_size_m: tuple[float, float] = (0.5, 0.5),
    marker: MarkerSpec | CharucoBoardSpec | None = None,
    vignetting_falloff: float = 0.37,
    vignetting_shift_px: tuple[float, float] = (0.0, 0.0),
) -> SyntheticTruth:
    """Draw a seeded camera truth: V_true (off-centre, per band), S_true, sensor (U_true).

    Parameters
    ----------
    seed : int
        Seed of the truth.
    camera : SnapshotCamera, optional
        Default: the Ximea 5 x 5 snapshot camera of the paper.
    sensor : SensorModel, optional
        Default: the project's sensor model at the camera's bit depth.
    reflector_reflectance : float or sequence of float
        R_s, one value (gray) or one per band.
    reflector_size_m : tuple of float
        ``(w, h)`` of the reflector.
    marker : MarkerSpec or CharucoBoardSpec, optional
        Marker (or ChArUco board) on the reflector; default ``MarkerSpec()``.
    vignetting_falloff : float
        Smallest mean corner falloff of V over the bands (the bands span it to +0.07).
    vignetting_shift_px : tuple of float
        Common shift (x, y) of every band's vignetting centre, band-grid pixels.

    Returns
    -------
    SyntheticTruth
        The truth.
    """
    camera = camera or SnapshotCamera()
    marker = marker or MarkerSpec()
    sensor = sensor if sensor is not None else _make_sensor(camera.bits)
    rng = np.random.default_rng([seed, 1])
    V, centres = _vignetting(camera, rng, vignetting_falloff, vignetting_shift_px)
    S = _spectral_factor(camera.wavelengths, rng)
    rho = np.broadcast_to(np.asarray(reflector_reflectance, dtype=np.float64),
                          (camera.n_bands,)).copy()
    return SyntheticTruth(
        seed=seed, camera=camera, sensor=sensor, vignetting=V, vignetting_centre=centres,
        spectral_factor=S, reflector_reflectance=rho,
        reflector_size_m=(float(reflector_size_m[0]), float(reflector_size_m[1])),
        marker=marker, sun_brightness=float(rng.uniform(260.0, 320.0)),
    )


@dataclass
class FrameSet:
    """Frames of one dataset: band stacks of DN, exposures, per-frame metadata and truth.

    Attributes
    ----------
    kind : str
        ``"response"``, ``"vignetting"``, ``"reflector"`` or ``"flight"``.
    dn : list of numpy.ndarray
        (n_bands, H, W) uint16 band stacks (``raw(k)`` gives the sensor mosaic).
    exposure_ms : numpy.ndarray
        (n,) exposures.
    names : list of str
        File stems.
    meta : list of dict
        Per-frame dicts with ``time`` (ISO 8601) and, for flights, ``lat``, ``lon``, ``alt_m``.
    truth : dict
        Truth arrays (see the dataset functions).
    camera : SnapshotCamera
        The camera.
    black_level : int
        Black level of the sensor (DN).
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
        """Return the number of frames."""
        return len(self.dn)

    def raw(self, k: int) -> np.ndarray:
        """Raw (1088, 2048) uint16 mosaic of frame k; unused sensor rows/cols at black."""
        return self.camera.mosaic(self.dn[k], fill=self.black_level)


def session_time(offset_s: float) -> str:
    t = SESSION_START + _dt.timedelta(seconds=float(offset_s))
    return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def round_ms(t: float) -> float:
    return float(round(t, 4))  # 0.1 us: what frames.csv stores, and what is rendered


def _gauge(truth: SyntheticTruth) -> float:
    """Return ``a`` with ``U_true(C(x)) = a x``: the sensor's energy x in the U gauge (~1)."""
    s = truth.sensor
    k = int(s.k_ref) if hasattr(s, "k_ref") else truth.dn_max // 2
    return float(np.asarray(s.inverse_response())[k] / float(s.x_for_dn(k)))


def expose_frame(truth: SyntheticTruth, energy: np.ndarray, t: float, rng) -> np.ndarray:
    """DN of energy rate ``energy`` (U gauge: ``U_true(I) = t E`` up to noise) over ``t`` ms."""
    return np.asarray(truth.sensor.expose(energy / _gauge(truth), t, rng), dtype=np.uint16)


def exposure_for(truth: SyntheticTruth, e_max: float, fraction: float) -> float:
    """Exposure (ms, rounded to 0.1 us) putting energy rate ``e_max`` at ``fraction`` of range."""
    x = float(truth.sensor.x_for_dn(fraction * truth.dn_max)) * _gauge(truth)
    return round_ms(x / e_max)
