"""Dataset 1 of a session: the exposure sweep of a static scene (Eq. 5-7)."""

from __future__ import annotations

import numpy as np

from ._targets import PeriodicNoise
from ._truth import FrameSet, SyntheticTruth, expose_frame, exposure_for, round_ms, session_time

#: ``stop_fraction`` places this quantile of the sweep's energy (all bands and pixels): the
#: brightest 0.5 % go above it (to the clip), so the DN near the top are sparse.
STOP_QUANTILE = 0.995


def response_sweep(truth: SyntheticTruth, *, seed: int = 0, n_frames: int = 14,
                   step: float = 1.66, decades: float = 2.5,
                   start_fraction: tuple[float, float] = (0.30, 0.40),
                   stop_fraction: float | None = None) -> FrameSet:
    """Render an exposure sweep of a static scene with a fixed camera (input of Eq. 5-7).

    The scene is a smooth random texture whose radiance spans ``decades`` decades (log-uniform
    histogram), with a smooth per-band colour variation; ``E_b(x) = V_b(x) S_b L_b(x)``. The
    shortest exposure puts the brightest pixel at 30-40 % of range; exposures grow by ``step``
    (``t_i = t_0 step^i``, rounded to 0.1 us), so the longest saturates most pixels.

    Parameters
    ----------
    truth : SyntheticTruth
        The camera truth (:func:`make_truth`).
    seed : int
        Seed of the dataset (with the truth's, it fixes every random draw).
    n_frames : int
        Number of exposures.
    step : float
        Ratio of consecutive exposures.
    decades : float
        Span of the scene's radiance in decades.
    start_fraction : tuple of float
        Range of the brightest pixel's share of the DN range in the shortest exposure.
    stop_fraction : float, optional
        Instead, the share of the DN range of the sweep's :data:`STOP_QUANTILE` energy in the
        *longest* exposure (the sweep then ends there: few samples above it, the brightest
        0.5 %); None: as ``start_fraction`` says.

    Returns
    -------
    FrameSet
        ``kind="response"``; truth: ``energy`` (n_bands, H, W) float32 energy rate E (linear
        DN / ms).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
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
    t0 = exposure_for(truth, float(energy.max()), rng.uniform(*start_fraction))
    if stop_fraction is not None:  # t0 drawn all the same: the noise stream stays the same
        # the scene dimmed so that the shortest exposure is again ~0.3 ms (0.1 us rounding)
        top = float(np.quantile(energy, STOP_QUANTILE))
        t_first = exposure_for(truth, top, float(stop_fraction)) / step ** (n_frames - 1)
        energy = (energy * min(t_first / 0.3, 1.0)).astype(np.float32)
        top = float(np.quantile(energy, STOP_QUANTILE))
        t0 = exposure_for(truth, top, float(stop_fraction)) / step ** (n_frames - 1)
    exposures = np.array([round_ms(t0 * step**i) for i in range(n_frames)])
    dn = [expose_frame(truth, energy, t, rng) for t in exposures]
    return FrameSet(
        kind="response", dn=dn, exposure_ms=exposures,
        names=[f"sweep_{i:02d}" for i in range(n_frames)],
        meta=[{"time": session_time(2.0 * i)} for i in range(n_frames)],
        truth={"energy": energy}, camera=cam, black_level=int(round(truth.black_level)),
    )
