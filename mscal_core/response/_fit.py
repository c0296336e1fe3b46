"""The front door of the response fit: check the sweep, choose pixels and masks, run the chosen method."""

from __future__ import annotations

import numpy as np

from ..errors import FitError, InputError
from ._alternating import alternating_fit
from ._common import (
    CANDIDATES_PER_PIXEL,
    ResponseFit,
    neighbour_gradient2,
    select_pixels,
    sweep_masks,
    usable_sweep,
    validate_samples,
)
from ._consistency import check_sweep
from ._forward import forward_fit

#: Methods of :func:`fit_response` and its priors.
METHODS = ("forward", "alternating")
PRIORS = ("adaptive", "loglog", "linear")


#: DN-0 samples are censored only where the local gradient (:func:`neighbour_gradient2`)
#: is at most this many DN; elsewhere they are dropped.
CENSOR_LOW_MAX_GRADIENT = 1.0


def fit_response(
    dn: np.ndarray,
    exposure: np.ndarray,
    bits: int,
    *,
    method: str = "forward",
    saturation_dn: int | None = None,
    max_pixels: int = 4000,
    seed: int = 0,
    smoothness: float = 0.025,
    max_iter: int = 60,
    tol: float = 1e-4,
    robust: bool = True,
    prior: str = "adaptive",
    gradient_noise: bool = True,
    censored: bool = True,
) -> ResponseFit:
    """Fit the inverse response U of one band from an exposure sweep (Eq. 5-7).

    ``method="forward"`` (default) fits the forward response C with the noise on the DN (see
    the package docstring), iterating

    - (a) ``E(x) = argmin_E sum_i w (I_i(x) - C(t_i E))^2`` (Gauss-Newton; Eq. 7 analogue),
    - (b) ``C = argmin_C sum_{i,x} w (I_i(x) - C(t_i E(x)))^2 + prior``, C monotone
      (Eq. 6 analogue), taken jointly with a linearised (a),

    ``w`` = robust weight / noise variance, re-estimated from the residuals (first 7
    iterations), until U changes by less than ``tol`` (relative to U at mid-range) or
    ``max_iter``. ``method="alternating"`` runs the paper's plain Eq. 6/7
    (:func:`fit_response_alternating`). Pixels (at most ``max_pixels``, half evenly spread over
    the brightness range, the rest drawn with ``seed``; from at most
    ``CANDIDATES_PER_PIXEL * max_pixels`` random candidates) with >= 2 usable samples are used.

    Parameters
    ----------
    dn : numpy.ndarray
        ``(n_frames, n_pixels)`` integer samples of a static scene (any integer dtype; not
        copied; integer-valued floats are accepted).
    exposure : numpy.ndarray
        ``(n_frames,)`` effective exposures (ms * gain), positive.
    bits : int
        Bit depth of the camera (1..16); DN run over ``0 .. 2**bits - 1``.
    method : {"forward", "alternating"}
        The errors-in-DN fit (default) or the paper's plain alternation.
    saturation_dn : int, optional
        Samples ``>=`` this are saturated (default ``dn_max``).
    max_pixels : int
        Pixels used at most.
    seed : int
        Seed of the pixel selection.
    smoothness : float
        Weight of the prior against one knot segment's data (``"adaptive"``: at 0.5 % noise and
        1-stop steps).
    max_iter : int
        Iterations at most.
    tol : float
        Stop when U (relative to its value at mid-range) changes by less than this.
    robust : bool
        Outlier weights (samples beyond 3 noise standard deviations taper to weight 0 at 6).
    prior : {"adaptive", "loglog", "linear"}
        ``"adaptive"``: log-log smoothness weighted by noise and exposure step; ``"loglog"``:
        fixed weight; ``"linear"``: second differences of C (the previous default, with
        ``smoothness=0.05``).
    gradient_noise : bool
        The misalignment term ``c g^2`` of the noise.
    censored : bool
        DN 0 and first saturated samples as censored (Tobit) terms.

    Returns
    -------
    ResponseFit
        U on every DN in the gauge ``U[k_ref] = k_ref - black``, ``k_ref = dn_max // 2``, with
        the black level, the residual RMS and its profile over DN.

    Raises
    ------
    InputError
        On bad shapes, non-positive exposures, DN outside the bit depth, an unknown method or
        prior, or ``saturation_dn`` outside ``1..dn_max``.
    FitError
        On fewer than 2 distinct exposures, frames whose brightness contradicts their exposure
        (:func:`check_exposure_consistency`), no unsaturated samples, no pixel unsaturated in 2
        frames, fewer than 3 distinct DN, or a black level above mid-range.

    Notes
    -----
    The options of the forward fit default to all on: measured best on photographs and on
    10-bit sweeps. The paper minimises Eq. 5,
    ``M(U, E) = sum_i sum_x (U(I_i(x)) - t_i E(x))^2``, by alternating Eq. 6,
    ``U(k) = sum_{(i,x) in Omega_k} t_i E(x) / |Omega_k|``, and Eq. 7,
    ``E(x) = sum_i t_i U(I_i(x)) / sum_i t_i^2`` [1]_. That alternation treats the noise as if
    it were on ``U(I)`` and converges to a biased fixed point (13-24 % worst error in U on
    10-bit sweeps, PAPER.md); the forward fit puts the noise on the DN. A Debevec-Malik style
    log-domain least squares with a smoothness term [2]_ reached 0.28 % on the same sweeps but
    degraded to 14-20 % with doubled shot noise.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    .. [2] P. E. Debevec and J. Malik, "Recovering High Dynamic Range Radiance Maps from
           Photographs", Proc. SIGGRAPH 1997.
    """
    if method not in METHODS:
        raise InputError(f"unknown response method {method!r}; use one of {', '.join(METHODS)}")
    if prior not in PRIORS:
        raise InputError(f"unknown response prior {prior!r}; use one of {', '.join(PRIORS)}")
    d_all, t = validate_samples(dn, exposure, bits)
    dn_max = 2**bits - 1
    sat = dn_max if saturation_dn is None else int(saturation_dn)
    if not 1 <= sat <= dn_max:
        raise InputError(f"saturation_dn must be in 1..{dn_max}, got {saturation_dn}")
    check_sweep(d_all, t, bits)
    # large bands: a seeded random subset of candidate pixels (no full-size temporaries)
    rng = np.random.default_rng(seed)
    n_pix = d_all.shape[1]
    cand = None
    if n_pix > CANDIDATES_PER_PIXEL * max_pixels:
        cand = np.unique(rng.integers(0, n_pix, CANDIDATES_PER_PIXEL * max_pixels))
    sub = d_all if cand is None else d_all[:, cand]
    usable = usable_sweep(sub, t, sat, dn_max)
    if not usable.any():
        raise FitError(
            "no unsaturated samples in the sweep: every DN is 0 or saturated",
            hint="add shorter exposures (or check the saturation level)",
        )
    observed = (int(sub.min(where=usable, initial=dn_max)), int(sub.max(where=usable, initial=0)))
    el = np.flatnonzero(np.count_nonzero(usable, axis=0) >= 2)
    cols = select_pixels(d_all, el if cand is None else cand[el], max_pixels, rng)
    if cols.size == 0:
        raise FitError(
            "no pixel has unsaturated samples in 2 or more frames",
            hint="add exposures so that each brightness is seen unsaturated at least twice",
        )
    sel = d_all[:, cols]
    m, cen_lo, cen_hi = sweep_masks(sel, t, sat, dn_max)
    grad2 = neighbour_gradient2(d_all, cols)
    g2 = grad2 if gradient_noise else None
    # DN 0 next to an edge is more often a shifted edge or a colour/chroma artefact than a
    # signal below 0.5 DN: censored only where the neighbours are dark too
    cen_lo &= grad2 <= CENSOR_LOW_MAX_GRADIENT**2
    d = sel.astype(np.float64)
    if np.unique(d[m]).size < 3:
        raise FitError(
            f"the sweep shows only {np.unique(d[m]).size} distinct unsaturated DN",
            hint="use a scene with a range of brightness and several exposures",
        )
    if method == "alternating":
        return alternating_fit(d, m, t, bits, sat, observed)
    return forward_fit(d, m, t, bits, sat, observed, smoothness, max_iter, tol, robust, prior, g2,
                    (cen_lo, cen_hi) if censored else None)


def fit_response_alternating(
    dn: np.ndarray,
    exposure: np.ndarray,
    bits: int,
    *,
    saturation_dn: int | None = None,
    max_pixels: int = 4000,
    seed: int = 0,
) -> ResponseFit:
    """Fit U by the paper's plain alternation of Eq. 6 and Eq. 7 (``method="alternating"``).

    Parameters
    ----------
    dn : numpy.ndarray
        ``(n_frames, n_pixels)`` integer samples of a static scene.
    exposure : numpy.ndarray
        ``(n_frames,)`` effective exposures (ms * gain), positive.
    bits : int
        Bit depth of the camera.
    saturation_dn : int, optional
        Samples ``>=`` this are saturated (default ``dn_max``).
    max_pixels : int
        Pixels used at most.
    seed : int
        Seed of the pixel selection.

    Returns
    -------
    ResponseFit
        As :func:`fit_response`, ``method == "alternating"``.

    Raises
    ------
    InputError, FitError
        As :func:`fit_response`.

    Notes
    -----
    ``U(k) = mean over Omega_k of t_i E(x)`` (Eq. 6) and ``E(x) = sum_i t_i U(I_i(x)) /
    sum_i t_i^2`` (Eq. 7) over usable samples, from the linear start ``U(k) = k - b`` (b from a
    common-intercept line fit), the scale gauge ``U(k_ref) = k_ref - b`` fixed each iteration,
    unobserved DN interpolated. Converges to a biased fixed point (the noise is on I, not on
    U(I)); kept for reference and comparison.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    return fit_response(
        dn, exposure, bits, method="alternating", saturation_dn=saturation_dn,
        max_pixels=max_pixels, seed=seed,
    )
