"""The default errors-in-DN fit of the forward response C (``method="forward"``)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import numpy as np

from ._common import ResponseFit, finalise, linear_init, residual_profile
from ._curve import (
    Curve,
    fit_energy,
    joint_step,
    line_search,
    normal_information,
    prior_quadratic,
    reknot,
    relative_u,
    relaxed_prior_curve,
)
from ._noise import censored_outlier_weights, censored_terms, hidden_saturation_top, noise_update, outlier_weights
from ._uncertainty import fit_log_std, response_uncertainty

#: Samples of highest energy whose mean DN bounds the fitted range (:func:`_fitted_range`).
TOP_SAMPLES = 10


#: Adaptive prior weight (see :func:`fit_response`): ``smoothness * (sigma / SIGMA_REF)^SIGMA_POW
#: * (period / PERIOD_REF)^PERIOD_POW`` with ``sigma`` the robust DN noise relative to the DN
#: range and ``period`` the exposure step (:func:`exposure_period`, natural log).
SIGMA_REF = 0.005


SIGMA_POW = 3.0


SIGMA_MAX = 0.08  # noise factor at most (0.08 / 0.005)^3 = 4096


ADAPT_FROM = 3  # iterations with the base weight (times the period factor) first


PERIOD_REF = float(np.log(2.0))


PERIOD_POW = 2.0


#: The fit's own uncertainty of U includes how far U moves when the smoothness prior is made
#: this many times weaker (:func:`_uncertainty`): an order of magnitude.
PRIOR_RELAX = 10.0


def exposure_period(exposure: np.ndarray, tol: float = 0.2) -> float:
    """Return the exposure step of a sweep, ``log`` of the ratio.

    Parameters
    ----------
    exposure : numpy.ndarray
        Exposures of the sweep (any order; repeats allowed).
    tol : float
        Allowed deviation of a step from a whole multiple of the period, in periods.

    Returns
    -------
    float
        The largest ``g`` such that every step between consecutive distinct exposures is (within
        ``tol`` of) a whole multiple of ``g``; ``log 2`` without a step above 0.05.

    Notes
    -----
    Brackets are geometric (1/1000, 1/500, ... or third stops), so every exposure ratio is a
    power of the step; U is then determined by the data only up to a factor that is periodic in
    ``log x`` with this period, which the prior must resolve.
    """
    lt = np.unique(np.log(np.asarray(exposure, dtype=np.float64)))
    steps = np.diff(lt)
    steps = steps[steps > 0.05]
    if steps.size == 0:
        return PERIOD_REF
    best = float(steps.min())
    for g in sorted({float(d / k) for d in steps for k in (1, 2, 3, 4)}, reverse=True):
        if g < best:
            break
        ratio = steps / g
        if np.all(np.abs(ratio - np.round(ratio)) <= tol) and np.all(np.round(ratio) >= 1):
            return g
    return best


def forward_fit(
    d: np.ndarray,
    m: np.ndarray,
    t: np.ndarray,
    bits: int,
    sat: int,
    observed: tuple[int, int],
    smoothness: float,
    max_iter: int,
    tol: float,
    robust: bool = True,
    prior: str = "adaptive",
    g2: np.ndarray | None = None,
    cen: tuple[np.ndarray, np.ndarray] | None = None,
) -> ResponseFit:
    """Run the errors-in-DN fit of :func:`fit_response` on selected samples.

    The errors-in-DN fit of :func:`fit_response` on the selected samples ``d[m]`` (and the
    censored samples ``cen = (low, high)``, see :func:`censored_terms`).
    """
    dn_max = 2**bits - 1
    lo, hi = observed
    n_seg = int(np.clip((hi - lo) // 4, 4, 64))
    b0, e = linear_init(d, m, t, lo, hi)
    xk = np.linspace(0.0, max(hi - b0, 1.0), n_seg + 1)
    curve = Curve(xk=xk, c=b0 + xk)
    mf = m.astype(np.float64)
    rob = np.ones_like(mf)
    period = exposure_period(t)
    a_var, b_var, c_var = 1.0, 0.0, 0.0
    g2 = np.zeros_like(mf) if g2 is None else g2
    s_min = 1e-4
    grid = np.linspace(lo, lo + 0.95 * (hi - lo), 129)  # convergence: U relative to mid-range
    prev_u = relative_u(curve, grid)
    reknot_at = (1, 3, 6)
    settle = 7  # last re-knot / noise-model update; weights frozen afterwards
    it = 0
    dw = d  # working samples: observed, and censored ones as pseudo-observations
    info = None  # information matrix of C's parameters, E marginalised (from the last joint step)
    for it in range(1, max_iter + 1):
        if it in reknot_at:
            curve, e = reknot(curve, e, t, m, hi, n_seg)
        if it <= settle:
            mu, _ = curve.at(t, e)
            var = a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + c_var * g2
            w = w_obs = mf * rob / var
            sm = smoothness
            if prior == "adaptive":
                sm = _adaptive_smoothness(smoothness, it, var, m & (rob > 0), hi - curve.c[0], period)
            # the prior as a function of its scale gauge's weight (0: the smoothness part alone)
            prior_at = partial(prior_quadratic, curve.xk, w.sum() / n_seg, smoothness=sm,
                               slopes=None if prior == "linear" else curve.slopes)
            quad = prior_at(w.sum())
        noise = (a_var, b_var, c_var * g2)
        if cen is not None and it >= 2:  # refreshed every iteration (a Newton step on them)
            dw, wc = censored_terms(d, cen, t, e, curve, noise, sat)
            w = w_obs + wc * rob
        curve, e, gain, info = _step(dw, w, t, e, curve, quad, s_min)
        e = fit_energy(dw, w, t, e, curve, steps=1)
        if it <= 3 or it in (5, settle):
            a_var, b_var, c_var = noise_update(d, m, w, t, e, curve, robust, g2)
            if robust and it >= 3:
                rob = _robust_weights(d, m, w, t, e, curve, (a_var, b_var, c_var * g2), sat, cen)
        u = relative_u(curve, grid)
        change = float(np.max(np.abs(u - prev_u)))
        prev_u = u
        # stop on a small change of U, or once the cost decrease is far below the noise
        if it > settle and (change < tol or gain < 2e-5 * float(mf.sum())):
            break
    black = float(curve.c[0])
    u_curve = curve.inverse(np.arange(dn_max + 1, dtype=np.float64))
    u_raw = u_curve
    if robust:
        noise = (a_var, b_var, c_var * g2)
        u_raw = hidden_saturation_top(u_curve, d, t, e, curve, noise, sat, lo, hi)
    U = finalise(u_raw, black, hi, bits)
    # where the top was raised, U is the curve's or Eq. 6's: their difference is part of U's uncertainty
    u_curve_gauged = finalise(u_curve, black, hi, bits)
    mu, _ = curve.at(t, e)
    rms = float(np.sqrt(np.mean((d - mu)[m] ** 2)))
    fitted = _fitted_range(d, m, t, e, cen)
    # the last step's matrix, unless it was not a joint one (then it does not marginalise E)
    info = info if info is not None else normal_information(dw, w, t, e, curve, quad)
    u_weak = _relaxed_u(curve, info, prior_at(0.0), s_min, hi, bits)
    moves = ([] if u_raw is u_curve else [(U, u_curve_gauged)]) + [(u_curve_gauged, u_weak)]
    fit_std, unc = _uncertainty(U, curve, info, fitted, (a_var, b_var), bits, moves)
    return ResponseFit(U, black, sat, observed, rms, "forward", it, int(m.sum()), residual_profile(d, mu, m, bits),
                       fitted, (a_var, b_var), fit_std, unc)


def _fitted_range(d: np.ndarray, m: np.ndarray, t: np.ndarray, e: np.ndarray,
                  cen: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[int, int]:
    """Return the DN range the sweep determines U on.

    From the used samples' lowest DN up to the lower of their highest DN and the mean DN of
    the :data:`TOP_SAMPLES` samples of highest energy (saturated ones included, at the clip).
    The DN above are noise draws above the highest energies' mean DN, not energies of their
    own: U there is C extrapolated beyond the data (on a sweep that stops short of the clip, on
    a steep shoulder, ~2 sigma of the DN noise, 15-20 DN, where U was up to 13 % low while the
    information matrix, whose last segment is a line, said 2 %). A sweep that saturates its
    brightest pixels is determined up to its highest DN.
    """
    x = t[:, None] * e[None, :]
    used = m if cen is None else (m | cen[1])
    xs, ds = x[used], d[used]
    top = np.argsort(xs)[-TOP_SAMPLES:]
    lo, hi = int(d[m].min()), int(d[m].max())
    return lo, max(lo, min(hi, int(np.floor(ds[top].mean()))))


def _relaxed_u(curve: Curve, info: np.ndarray, smooth: tuple[np.ndarray, np.ndarray], s_min: float, hi: int,
               bits: int) -> np.ndarray:
    """U of the curve after :func:`relaxed_prior_curve` with the prior :data:`PRIOR_RELAX` times weaker.

    ``smooth``: the smoothness part ``(P_s, p_s)`` of the prior in ``info``
    (:func:`prior_quadratic` without the scale gauge), the part that is relaxed.
    """
    weak = relaxed_prior_curve(curve, info, smooth, 1.0 - 1.0 / PRIOR_RELAX, s_min)
    return finalise(weak.inverse(np.arange(2**bits, dtype=np.float64)), float(weak.c[0]), hi, bits)


def _uncertainty(U: np.ndarray, curve: Curve, info: np.ndarray, fitted: tuple[int, int],
                 noise: tuple[float, float], bits: int, moves: Sequence[tuple[np.ndarray, np.ndarray]] = ()
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(fit_std, uncertainty)`` of U on every DN (:func:`fit_log_std`, :func:`response_uncertainty`).

    ``info``: the information matrix of C's parameters with E marginalised (data and prior).
    ``moves``: pairs ``(U_a, U_b)`` whose relative difference ``|U_a - U_b| / U_a`` is added in
    quadrature to ``fit_std``, in order: U and the curve's alone where
    :func:`hidden_saturation_top` raised U's top, and U of the curve and U after
    :func:`relaxed_prior_curve` (prior :data:`PRIOR_RELAX` times weaker).

    ``fit_log_std`` is the posterior standard deviation with the prior taken as a Gaussian: it
    counts the prior as information, so where few samples reach (a shoulder that only the
    sweep's longest exposure samples, a thousandth of a knot segment's mean data weight) the
    prior sets U's shape and its pull, a bias of U, is not in it (harsh sweeps: U 0.5-0.65 %
    off on average over noise draws at DN 950 of a band while it said 0.37 %; with E fixed to
    the truth the same, with a 10 times weaker prior +0.26 % within 0.49 %). The relaxed
    curve's move is that pull as the data see it.
    """
    dn_max = 2**bits - 1
    fit_std = np.full(dn_max + 1, np.nan)
    k = np.arange(fitted[0], fitted[1] + 1)
    fit_std[k] = fit_log_std(curve, info, k, dn_max // 2)
    for a, b in moves:
        with np.errstate(divide="ignore", invalid="ignore"):
            moved = np.where(a > 0, np.abs(a - b) / a, 0.0)
        fit_std[k] = np.hypot(fit_std[k], moved[k])
    return fit_std, response_uncertainty(U, float(curve.c[0]), noise, fitted, np.nan_to_num(fit_std))


def _adaptive_smoothness(
    smoothness: float, it: int, var: np.ndarray, kept: np.ndarray, span: float, period: float
) -> float:
    """Weight of the ``"adaptive"`` prior at iteration ``it``.

    ``smoothness`` times the noise factor ``(sigma / SIGMA_REF)^SIGMA_POW`` (``sigma`` the rms
    noise of the ``kept`` samples over the DN ``span``, at most ``SIGMA_MAX``) and the
    exposure-step factor ``(period / PERIOD_REF)^PERIOD_POW``.
    """
    # the noise factor only once the curve has been fitted (a first curve far off inflates
    # the noise, whose prior would then freeze it), and bounded
    sigma_rel = SIGMA_REF
    if it > ADAPT_FROM:
        span = max(span, 1.0)
        sigma_rel = min(float(np.sqrt(var[kept].mean())) / span, SIGMA_MAX)
    return (smoothness * (sigma_rel / SIGMA_REF) ** SIGMA_POW
            * (period / PERIOD_REF) ** PERIOD_POW)


def _step(
    dw: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    quad: tuple[np.ndarray, np.ndarray], s_min: float,
) -> tuple[Curve, np.ndarray, float, np.ndarray | None]:
    """One joint Gauss-Newton step on (C, E) with backtracking.

    Where it stalls (on a kink of C), an exact block step on C for fixed E instead. Returns
    ``(C, E, cost decrease, information)``: the information matrix of C's parameters with E
    marginalised (:func:`normal_information`) at the start of the step, None after a block step.
    """
    theta_new, e_new, info = joint_step(dw, w, t, e, curve, quad, s_min)
    curve, e, gain = line_search(dw, w, t, e, curve, quad, theta_new, e_new)
    if gain == 0.0:
        theta_new, e_new, _ = joint_step(dw, w, t, e, curve, quad, s_min, joint=False)
        curve, e, gain = line_search(dw, w, t, e, curve, quad, theta_new, e_new)
        info = None
    return curve, e, gain, info


def _robust_weights(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    noise: tuple[float, float, np.ndarray], sat: int, cen: tuple[np.ndarray, np.ndarray] | None,
) -> np.ndarray:
    """Return the outlier weights of observed and censored samples.

    Outlier weights of the observed samples and, with ``cen``, of the censored ones (a censored
    sample deep on the wrong side of its bound is an outlier too).
    """
    a_var, b_var, extra = noise
    rob = outlier_weights(d, m, w, t, e, curve, a_var, b_var, extra)
    if cen is not None:
        rob = np.maximum(rob, censored_outlier_weights(cen, t, e, curve, noise, sat))
    return rob
