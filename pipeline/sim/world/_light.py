"""Light on the synthetic scenes: uniform, gradient with a soft shadow, drift over a flight."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class UniformLight:
    """``B(p) = brightness`` everywhere (the sun on a flat field, one frame)."""

    brightness: float

    def __call__(self, u, v) -> np.ndarray:
        """Return the constant brightness at plane points ``(u, v)``."""
        return np.full(np.shape(u), self.brightness, dtype=np.float32)

    def params(self) -> np.ndarray:
        """Return the parameters in the layout of :meth:`GradientShadowLight.params` (no gradient, no shadow)."""
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
        """Return the linear brightness gradient factor at plane points ``(u, v)``."""
        u, v = np.asarray(u), np.asarray(v)
        c, s = math.cos(self.gradient_dir), math.sin(self.gradient_dir)
        half = 0.5 * self.extent_m[0] * abs(c) + 0.5 * self.extent_m[1] * abs(s)
        a = (self.gradient_ratio - 1.0) / (self.gradient_ratio + 1.0)
        p = np.clip((u * c + v * s) / half, -1.6, 1.6)
        return 1.0 + a * p

    def shadow(self, u, v) -> np.ndarray:
        """Return the soft shadow factor at plane points ``(u, v)`` (1 without a shadow)."""
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
        """Return the light's nine parameters.

        (brightness, gradient_dir, gradient_ratio, extent_w, extent_h, shadow_depth, shadow_dir,
        shadow_offset_m, shadow_softness_m); see :meth:`from_params`.
        """
        return np.array([
            self.brightness, self.gradient_dir, self.gradient_ratio, self.extent_m[0],
            self.extent_m[1], self.shadow_depth, self.shadow_dir, self.shadow_offset_m,
            self.shadow_softness_m,
        ])

    @staticmethod
    def from_params(p) -> GradientShadowLight:
        """Rebuild a light from its :meth:`params`."""
        p = [float(x) for x in p]
        return GradientShadowLight(p[0], p[1], p[2], (p[3], p[4]), p[5], p[6], p[7], p[8])


@dataclass(frozen=True)
class LightDrift:
    """Light whose level and colour drift linearly over a flight.

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
        """Return the factor on the sun's brightness at time ``tau``."""
        return 1.0 + (self.level_end - 1.0) * self._f(tau)

    def colour(self, tau: float, wavelengths: np.ndarray) -> np.ndarray:
        """Return the factor on the light's colour ``S`` per wavelength at time ``tau``."""
        wl = np.asarray(wavelengths, dtype=np.float64)
        x = 2.0 * (wl - wl.min()) / max(float(wl.max() - wl.min()), 1e-9) - 1.0
        return 1.0 + self.colour_tilt_end * self._f(tau) * x
