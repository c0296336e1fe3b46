"""The sensor of the synthetic forward model: exposure energy -> DN (Eq. 3, I = C(t E)).

Units: the exposure energy ``x = t * E`` is in "linear DN": in the near-linear part of the
response ``C(x) ~ black + x``. The forward response is built from three monotone pieces,

    f(x) = x * (1 - c * x / (x + R))                   mild CMOS-like compression (c = curvature)
    y(x) = R * (f(x) / R) ** (1 / gamma)               optional display gamma (1 = raw sensor)
    s(y) = y                                  y <= y_s
         = y_s + H * (1 - exp(-(y - y_s) / H)) y > y_s  soft shoulder, slope continuous at y_s
    mu(x) = black + s(y(x))                             analogue signal (may exceed dn_max)
    C(x) = min(mu(x), dn_max)                           expected DN, clipped by the ADC

with ``dn_max = 2**bits - 1``, ``R = dn_max - black`` (the DN range above black),
``y_s = shoulder_start * dn_max - black`` and ``H = 1.5 * (R - y_s)`` (``shoulder_headroom``): the shoulder reaches
``dn_max`` at ``y = y_s + H ln 3`` with a third of the linear slope (a soft knee) and tends to
``dn_max + (R - y_s) / 2``, so far beyond saturation every noisy sample clips to ``dn_max``.
Every piece has a closed-form inverse, so the true inverse response ``U = C^{-1}`` is exact.

Noise (:meth:`SensorModel.expose`): DN = clip(round(mu(x) + n), 0, dn_max),
n ~ N(0, read^2 + k (mu(x) - black)) with ``k = shot_noise_dn_at_full^2 / R``: Poisson-like
shot noise whose variance is proportional to the signal above black (rms
``shot_noise_dn_at_full`` at full scale) plus read noise, added before the ADC clip (as in a
real camera: a saturated pixel reads exactly ``dn_max``), returned as ``uint16``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mscal_core.errors import InputError

SHOULDER_HEADROOM = 1.5
"""Asymptote of the shoulder exponential relative to the DN span from its start to dn_max."""


@dataclass(frozen=True)
class SensorModel:
    """A monochrome pixel: soft-shouldered, mildly non-linear response plus shot/read noise.

    Attributes
    ----------
    bits : int
        Bit depth, 2..16.
    black_level : float
        DN.
    read_noise_dn : float
        DN rms.
    shot_noise_dn_at_full : float
        Shot-noise rms (DN) at full scale; variance proportional to the signal.
    shoulder_start : float
        Fraction of the DN range where a soft shoulder begins.
    curvature : float
        ``c`` in ``f(x) = x (1 - c x / (x + R))``: slope 1 at 0, ``1 - 3c/4`` at R.
    gamma : float
        ``y = R (f / R)^(1/gamma)``; 1 = linear raw sensor (default). An addition to the basic
        sensor that bends the response like an 8-bit display-referred camera (e.g.
        ``bits=8, gamma=2.2, black_level=0``).
    shoulder_headroom : float
        ``H / (R - y_s)``, > 1 (default :data:`SHOULDER_HEADROOM`): the shoulder reaches
        ``dn_max`` at ``y = y_s + H ln(h / (h - 1))`` with ``(h - 1) / h`` of the linear slope; close to 1, a harsh shoulder that compresses a wide energy range into the
        last DN below the clip (e.g. 1.02: ~4 H of energy into
        ``R - y_s`` DN, slope 1/51 at the clip).

    Raises
    ------
    InputError
        On a bit depth outside 2..16, a black level outside the linear range, a shoulder
        or curvature out of range, a non-positive gamma or negative noise.
    """

    bits: int = 10
    black_level: float = 32.0  # DN
    read_noise_dn: float = 1.5  # DN rms
    shot_noise_dn_at_full: float = 9.0  # shot-noise rms (DN) at full scale; variance ∝ signal
    shoulder_start: float = 0.85  # fraction of the DN range where a soft shoulder begins
    curvature: float = 0.05  # c in f(x) = x (1 - c x / (x + R)): slope 1 at 0, 1 - 3c/4 at R
    gamma: float = 1.0  # y = R (f / R)^(1/gamma); 1 = linear raw sensor
    shoulder_headroom: float = SHOULDER_HEADROOM  # asymptote / (dn_max - shoulder start), > 1

    def __post_init__(self) -> None:
        """Validate the bit depth, black level and shoulder."""
        if not 2 <= self.bits <= 16:
            raise InputError(f"sensor bits must be 2..16, got {self.bits}")
        if not 0 <= self.black_level < self.shoulder_start * self.dn_max:
            raise InputError(
                f"black level {self.black_level} must lie in [0, shoulder start "
                f"{self.shoulder_start * self.dn_max:g}) DN"
            )
        if not 0 < self.shoulder_start <= 1:
            raise InputError(f"shoulder_start must be in (0, 1], got {self.shoulder_start}")
        if not 0 <= self.curvature < 1:
            raise InputError(f"curvature must be in [0, 1), got {self.curvature}")
        if not self.shoulder_headroom > 1:
            raise InputError(f"shoulder_headroom must be > 1 (the shoulder must reach the clip), "
                             f"got {self.shoulder_headroom}")
        if self.gamma <= 0 or self.read_noise_dn < 0 or self.shot_noise_dn_at_full < 0:
            raise InputError("gamma must be > 0 and noise levels >= 0")

    # ------------------------------------------------------------------ constants
    @property
    def dn_max(self) -> int:
        """Largest (saturated) DN, ``2**bits - 1``."""
        return 2**self.bits - 1

    @property
    def k_ref(self) -> int:
        """Gauge DN of docs/architecture.md: ``U[k_ref] = k_ref - black``."""
        return self.dn_max // 2

    @property
    def _range(self) -> float:
        return float(self.dn_max - self.black_level)

    @property
    def _y_shoulder(self) -> float:
        return float(self.shoulder_start * self.dn_max - self.black_level)

    @property
    def _headroom(self) -> float:
        return self.shoulder_headroom * (self._range - self._y_shoulder)

    # ------------------------------------------------------------------ pieces
    def _f(self, x: np.ndarray) -> np.ndarray:
        """f(x) = x (1 - c x / (x + R))."""
        r = self._range
        return x * (1.0 - self.curvature * x / (x + r))

    def _f_inv(self, f: np.ndarray) -> np.ndarray:
        """Positive root of (1 - c) x^2 + (R - f) x - f R = 0."""
        r, c = self._range, self.curvature
        b = r - f
        return (-b + np.sqrt(b * b + 4.0 * (1.0 - c) * f * r)) / (2.0 * (1.0 - c))

    def _shoulder(self, y: np.ndarray) -> np.ndarray:
        ys, h = self._y_shoulder, self._headroom
        if h <= 0:
            return y
        return np.where(y <= ys, y, ys + h * -np.expm1(-(np.maximum(y, ys) - ys) / h))

    def _shoulder_inv(self, s: np.ndarray) -> np.ndarray:
        ys, h = self._y_shoulder, self._headroom
        if h <= 0:
            return s
        frac = np.clip((np.maximum(s, ys) - ys) / h, 0.0, 1.0 - 1e-12)
        return np.where(s <= ys, s, ys - h * np.log1p(-frac))

    def _above_black(self, x: np.ndarray) -> np.ndarray:
        """s(y(x)) before the clip: the expected DN above black."""
        r = self._range
        f = self._f(np.maximum(np.asarray(x, dtype=np.float64), 0.0))
        y = f if self.gamma == 1.0 else r * (f / r) ** (1.0 / self.gamma)
        return self._shoulder(y)

    def _x_of_above_black(self, s: np.ndarray) -> np.ndarray:
        r = self._range
        y = self._shoulder_inv(np.clip(s, 0.0, r))
        f = y if self.gamma == 1.0 else r * (y / r) ** self.gamma
        return self._f_inv(f)

    # ------------------------------------------------------------------ public API
    def response(self, x: np.ndarray) -> np.ndarray:
        """Forward response ``C(x)``: exposure energy ``x = t E >= 0`` -> expected DN (float).

        ``C(0) = black``, monotone non-decreasing, soft shoulder above ``shoulder_start`` of
        the DN range, exactly ``dn_max`` beyond saturation (see module docstring).
        """
        return np.minimum(self.analogue_dn(x), float(self.dn_max))

    def analogue_dn(self, x: np.ndarray) -> np.ndarray:
        """``mu(x) = black + s(y(x))``.

        The mean signal before the ADC clip (exceeds ``dn_max`` beyond saturation, up to
        ``dn_max + (R - y_s) / 2``).
        """
        return self.black_level + self._above_black(x)

    def x_for_dn(self, dn: np.ndarray | float) -> np.ndarray:
        """Energy ``x = C^{-1}(dn)`` giving an expected DN.

        0 at/below black, the saturation energy at/above ``dn_max``. For planning scene
        exposures.
        """
        d = np.asarray(dn, dtype=np.float64)
        return self._x_of_above_black(d - self.black_level)

    def inverse_response(self) -> np.ndarray:
        """Return the true ``U[k]`` for every DN ``k = 0 .. dn_max`` in the gauge of docs/architecture.md.

        ``U[k] = a * C^{-1}(k)`` with ``U[k] = 0`` for ``k <= black`` and the scale ``a`` set
        by ``U[k_ref] = k_ref - black``, ``k_ref = dn_max // 2``. float64, length ``2**bits``.
        """
        k = np.arange(self.dn_max + 1, dtype=np.float64)
        u = self.x_for_dn(k)
        u[k <= self.black_level] = 0.0
        return u * ((self.k_ref - self.black_level) / u[self.k_ref])

    def noise_variance(self, expected_dn: np.ndarray) -> np.ndarray:
        """DN noise variance at an expected DN: ``read^2 + shot_full^2 (mu - black) / R``."""
        sig = np.maximum(np.asarray(expected_dn, dtype=np.float64) - self.black_level, 0.0)
        return self.read_noise_dn**2 + self.shot_noise_dn_at_full**2 * sig / self._range

    def expose(self, energy_rate: np.ndarray, t: float, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame: ``clip(round(mu(t E) + n), 0, dn_max)`` as ``uint16``.

        ``n ~ N(0, noise_variance(mu))`` (shot noise Gaussian-approximated, plus read noise),
        added to the analogue signal before the clip, so ``E[DN] = C(t E)`` wherever the
        noise does not reach the clip. ``energy_rate`` is E per pixel (any shape, >= 0),
        ``t`` the exposure (> 0).
        """
        if not np.isfinite(t) or t <= 0:
            raise InputError(f"exposure must be positive, got {t}")
        mu = self.analogue_dn(t * np.asarray(energy_rate, dtype=np.float64))
        noisy = mu + np.sqrt(self.noise_variance(mu)) * rng.standard_normal(mu.shape)
        return np.clip(np.rint(noisy), 0, self.dn_max).astype(np.uint16)
