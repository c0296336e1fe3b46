"""The DN noise model of the errors-in-DN fit: variance, outlier weights, censored and hidden-saturated samples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear
from scipy.special import log_ndtr

from ._curve import Curve


def _bin_order_stats(values: np.ndarray, k: np.ndarray, cnt: np.ndarray, *ranks: np.ndarray,
                     order: np.ndarray | None = None) -> np.ndarray:
    """Return the ``ranks[j]``-th smallest of ``values`` in bin ``j`` (0 where bin ``j`` is empty).

    The same numbers as sorting all samples by (bin, value) and picking
    ``starts[j] + ranks[j]`` (bin medians of :func:`_noise_model`, :func:`_gradient_noise`,
    :func:`outlier_weights`), in O(n): a stable radix sort of the small bin index, then one
    ``np.partition`` per bin. Several rank arrays give one row each. ``order``: that sort
    (:func:`_bin_order`), when it is already known.
    """
    vs = values[_bin_order(k, cnt) if order is None else order]
    out = np.zeros((len(ranks), cnt.size))
    start = 0
    for j, c in enumerate(cnt.tolist()):
        if c > 0:
            want = [min(int(r[j]), c - 1) for r in ranks]
            part = np.partition(vs[start:start + c], sorted(set(want)))
            out[:, j] = part[want]
        start += c
    return out if len(ranks) > 1 else out[0]


def _bin_order(k: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Order the samples by their bin ``k`` (stable: a radix sort when the bins fit a byte)."""
    return np.argsort(k.astype(np.uint8) if cnt.size <= 256 else k, kind="stable")


@dataclass(frozen=True)
class _Bins:
    """Quantile bins of one variable.

    The bin ``k`` of every sample, the counts, and the samples in bin order
    (:func:`_bin_order`).
    """

    k: np.ndarray
    cnt: np.ndarray
    order: np.ndarray


def _quantile_bins(x: np.ndarray, n_bins: int) -> _Bins | None:
    """``x`` in ``n_bins`` bins between its quantiles (ties merged); None below 2 bins."""
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n_bins + 1)))
    if edges.size < 3:
        return None
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    return _Bins(k, cnt, _bin_order(k, cnt))


@dataclass(frozen=True)
class _Residuals:
    """The squared residuals of the noise fits, with their ``mu`` and its 16 quantile bins.

    Each squared residual is divided by ``1 - leverage`` (samples of leverage >= 0.9 left
    out: ``keep``). They do not change while :func:`noise_update` alternates the noise model
    and the gradient term.
    """

    keep: np.ndarray
    r2: np.ndarray
    mu: np.ndarray
    bins: _Bins | None


def _residuals(r: np.ndarray, mu: np.ndarray, leverage: np.ndarray) -> _Residuals:
    keep = leverage < 0.9
    r2 = r[keep] ** 2 / (1.0 - leverage[keep])
    mu = mu[keep]
    return _Residuals(keep, r2, mu, _quantile_bins(mu, 16) if r2.size >= 10 else None)


def _noise_model(r: np.ndarray, res: _Residuals, floor: float, robust: bool = False,
                 offset: np.ndarray | None = None) -> tuple[float, float]:
    """Fit the read + shot noise model ``var(I) = a + b mu`` to residuals.

    Fit ``var(I) = a + b * mu`` (read + shot noise, ``mu = C - black``) to the squared
    residuals ``res`` of ``r`` (:func:`_residuals`: each divided by ``1 - leverage``, the share
    of the sample's noise absorbed by its pixel's fitted E), less a known ``offset`` (the
    gradient term), averaged in 16 quantile bins of mu (``robust``: median / 0.4549, so
    outliers do not inflate it); two weighted passes, ``a >= floor``.
    """
    r2 = res.r2
    if offset is not None:  # a known part of the variance (gradient term)
        r2 = np.maximum(r2 - offset[res.keep], 0.0)
    if r2.size < 10:
        return max(float(np.mean(r ** 2)) if r.size else 1.0, floor), 0.0
    if res.bins is None:
        return max(float(r2.mean()), floor), 0.0
    k, n_bin = res.bins.k, res.bins.cnt
    cnt = n_bin.astype(np.float64)
    ok = cnt > 0
    if robust:  # median / 0.4549 (median of chi2_1): outliers do not inflate the scale
        lo_v, hi_v = _bin_order_stats(r2, k, n_bin, (n_bin - 1) // 2, n_bin // 2, order=res.bins.order)
        med = np.where(ok, 0.5 * (lo_v + hi_v), 0.0)
        mv = med[ok] / 0.4549
    else:
        mv = np.bincount(k, r2, cnt.size)[ok] / cnt[ok]
    mm = np.bincount(k, res.mu, cnt.size)[ok] / cnt[ok]
    X = np.stack([np.ones_like(mm), mm], 1)
    sw = np.sqrt(cnt[ok]) / np.maximum(mv, floor)
    sol = np.array([max(float(np.mean(mv)), floor), 0.0])
    for _ in range(2):
        with np.errstate(invalid="ignore", over="ignore"):
            trial = lsq_linear(X * sw[:, None], mv * sw, bounds=([floor, 0.0], [np.inf, np.inf])).x
        if not np.all(np.isfinite(trial)):
            break
        sol = trial
        sw = np.sqrt(cnt[ok]) / np.maximum(X @ sol, floor)
    return float(sol[0]), float(sol[1])


def noise_update(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    robust: bool = False, g2: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """Re-estimate the DN noise model ``var = a + b mu + c g2``.

    Re-estimate the DN noise model ``var = a + b mu + c g2`` from the residuals (see
    :func:`_noise_model`; ``c = 0`` without ``g2``). With ``g2`` the two are fitted in turn,
    twice; the residuals, their bins and the gradient term's bin medians are made once.
    """
    mu, s = curve.at(t, e)
    lev = _leverage(w, t, s)[m]
    r, above = (d - mu)[m], np.maximum(mu - curve.c[0], 0.0)[m]
    res = _residuals(r, above, lev)
    if g2 is None or not np.any(g2[m] > 0):
        return (*_noise_model(r, res, 1 / 12, robust), 0.0)
    gm = g2[m]
    grad = _gradient_bins(res, gm)
    a, b, c = 1.0, 0.0, 0.0
    for _ in range(2):
        a, b = _noise_model(r, res, 1 / 12, robust, offset=c * gm)
        c = _gradient_noise(grad, a + b * above)
    return a, b, c


@dataclass(frozen=True)
class _GradientBins:
    """The squared residuals of :class:`_Residuals` in 8 quantile bins of the squared DN gradient.

    The bins of the squared local DN gradient ``g2``, and each non-empty bin's robust
    variance (median / 0.4549) and mean ``g2``.
    """

    keep: np.ndarray
    bins: _Bins
    med: np.ndarray
    gmean: np.ndarray


def _gradient_bins(res: _Residuals, g2: np.ndarray) -> _GradientBins | None:
    """:class:`_GradientBins` of ``res`` (None with fewer than 64 residuals or 2 bins)."""
    if res.r2.size < 64:
        return None
    g2 = g2[res.keep]
    bins = _quantile_bins(g2, 8)
    if bins is None:
        return None
    k, cnt = bins.k, bins.cnt
    ok = cnt > 0
    med = _bin_order_stats(res.r2, k, cnt, cnt // 2, order=bins.order) / 0.4549
    gmean = np.bincount(k, g2, cnt.size)[ok] / cnt[ok]
    return _GradientBins(res.keep, bins, med[ok], gmean)


def _gradient_noise(grad: _GradientBins | None, base: np.ndarray) -> float:
    """``c >= 0`` in ``var = base + c g2``.

    The robust variance of each ``g2`` bin (:class:`_GradientBins`) minus the mean ``base``
    of the bin, regressed on the bin's mean ``g2`` (weights: counts / variance^2). ``c`` is
    the mean squared shift (pixels^2) of a scene between frames: 0 on a tripod. 0 without
    bins.
    """
    if grad is None:
        return 0.0
    k, cnt = grad.bins.k, grad.bins.cnt
    ok = cnt > 0
    excess = grad.med - np.bincount(k, base[grad.keep], cnt.size)[ok] / cnt[ok]
    wts = cnt[ok] / np.maximum(grad.med, 1e-6) ** 2
    c = float(np.sum(wts * grad.gmean * excess) / max(float(np.sum(wts * grad.gmean * grad.gmean)), 1e-300))
    return max(c, 0.0)


def _leverage(w: np.ndarray, t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Leverage of every sample on its pixel's E: ``w J^2 / sum_i w J^2``, ``J = t C'(t E)``."""
    wj2 = w * (t[:, None] * s) ** 2
    return wj2 / np.maximum(wj2.sum(0), 1e-300)


#: Outlier weights: 1 up to ``OUTLIER_Z[0]`` standard deviations, tapering (biweight) to 0
#: at ``OUTLIER_Z[1]``.
OUTLIER_Z = (3.0, 6.0)


def outlier_weights(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    a_var: float, b_var: float, extra: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Robust weights of the standardised residuals ``z = (I - C(t E)) / sqrt(var (1 - leverage))``.

    1 for ``|z| <= z0``, ``(1 - ((|z| - z0) / (z1 - z0))^2)^2`` up to ``z1``, 0 beyond
    (``OUTLIER_Z``). Samples a moving object, a shifted edge or a compression artefact put far
    off the curve stop pulling on it, while Gaussian noise keeps full weight (efficiency on
    clean sweeps is that of plain least squares).

    ``var`` is the larger of the noise model ``a + b mu`` and a local robust variance (median
    of the squared residuals in 16 quantile bins of the expected DN, / 0.4549): where the
    current curve is still off in some DN range, its samples are not all rejected at once
    (which would leave that range to the prior).
    """
    z0, z1 = OUTLIER_Z
    mu, s = curve.at(t, e)
    lev = np.minimum(_leverage(w, t, s), 0.9)
    r2 = (d - mu) ** 2 / (1.0 - lev)
    var = a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra
    mu_m, r2_m = mu[m], r2[m]
    if mu_m.size >= 64:
        edges = np.unique(np.quantile(mu_m, np.linspace(0, 1, 17)))
        if edges.size >= 3:
            k = np.clip(np.searchsorted(edges, mu_m, side="right") - 1, 0, edges.size - 2)
            cnt = np.bincount(k, minlength=edges.size - 1)
            ok = cnt > 0
            med = _bin_order_stats(r2_m, k, cnt, cnt // 2)[ok] / 0.4549
            centre = (np.bincount(k, mu_m, edges.size - 1)[ok] / cnt[ok])
            var = np.maximum(var, np.interp(mu, centre, med))
    z = np.sqrt(r2 / var)
    u = np.clip((z - z0) / (z1 - z0), 0.0, 1.0)
    return np.where(m, (1.0 - u * u) ** 2, 0.0)


def censored_terms(
    d: np.ndarray, cen: tuple[np.ndarray, np.ndarray], t: np.ndarray, e: np.ndarray,
    curve: Curve, noise: tuple[float, float, np.ndarray], sat: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Censored (Tobit) samples as weighted pseudo-observations.

    A sample censored low (DN 0: the signal was below ``0.5``) or high (first saturated
    exposure: above ``sat - 0.5``) adds ``-2 log Phi(z)``, ``z = s (mu - bound) / sd``
    (``s = -1`` low, ``+1`` high, ``mu = C(t E)``), to the cost. Its Newton quadratic at the
    current ``mu`` is ``w (y - mu)^2`` with ``w = lam (z + lam) / sd^2`` and
    ``y = mu + s sd / (z + lam)``, ``lam = phi(z) / Phi(z)``: a sample far inside its allowed
    side weighs nothing, one on the wrong side acts like an observation at the bound. Returns
    ``(samples, weights)`` with ``d`` elsewhere and weight 0 there.
    """
    low, high = cen
    a_var, b_var, extra = noise
    mu, _ = curve.at(t, e)
    sd = np.sqrt(a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra)
    dw = d.copy()
    wc = np.zeros_like(d)
    for mask, sign, bound in ((low, -1.0, 0.5), (high, 1.0, sat - 0.5)):
        if mask.any():
            mu_c, sd_c = mu[mask], sd[mask]
            z = sign * (mu_c - bound) / sd_c
            lam = np.exp(_log_phi(z) - log_ndtr(z))
            den = z + lam
            dw[mask] = mu_c + sign * sd_c / den
            wc[mask] = lam * den / (sd_c * sd_c)
    return dw, wc


def censored_outlier_weights(
    cen: tuple[np.ndarray, np.ndarray], t: np.ndarray, e: np.ndarray, curve: Curve,
    noise: tuple[float, float, np.ndarray], sat: int,
) -> np.ndarray:
    """Return robust weights of the censored samples.

    Robust weights (``OUTLIER_Z`` taper) of the censored samples from how far the curve puts
    them on the wrong side of their bound, in noise standard deviations; 0 elsewhere.
    """
    low, high = cen
    z0, z1 = OUTLIER_Z
    a_var, b_var, extra = noise
    mu, _ = curve.at(t, e)
    sd = np.sqrt(a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra)
    deficit = np.where(low, (mu - 0.5) / sd, np.where(high, (sat - 0.5 - mu) / sd, 0.0))
    u = np.clip((deficit - z0) / (z1 - z0), 0.0, 1.0)
    return np.where(low | high, (1.0 - u * u) ** 2, 0.0)


def _log_phi(a: np.ndarray) -> np.ndarray:
    """Log of the standard normal density."""
    return -0.5 * a * a - 0.5 * np.log(2 * np.pi)


#: Top of U from Eq. 6 where saturated pixels hide below the clip: DN in the upper
#: ``1 - HIDDEN_FROM`` of the observed range where at least ``HIDDEN_FRACTION`` of the
#: samples come from pixels the fit puts clearly (3 sd) above the clip.
HIDDEN_FROM = 0.95


HIDDEN_FRACTION = 0.1


def hidden_saturation_top(
    u_raw: np.ndarray, d: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    noise: tuple[float, float, np.ndarray], sat: int, lo: int, hi: int,
) -> np.ndarray:
    """Raise the top of U where saturated pixels hide below the clip.

    Raise the top of ``u_raw = C^{-1}`` to the paper's Eq. 6, in the log domain,
    ``log U(k) = mean_{(i,x) in Omega_k} log(t_i E(x))``, at the DN ``k`` where saturated pixels
    hide below the clip.

    In JPEG photographs a blown highlight is not all 255: ringing of the compression (and
    sharpening) spreads 245-254 into it. The curve fit rightly treats those samples as
    outliers (their pixel's E puts them far above the clip), so ``C^{-1}(k)`` describes only
    the pixels really at ``k``; but a DN of 250 then more often than not means "saturated",
    and U used to predict or to linearise such a pixel should say so. Where at least
    ``HIDDEN_FRACTION`` of the samples at ``k`` (in the upper part of the range) come from
    pixels with ``C(t E) > sat - 0.5 + 3 sd``, U(k) becomes the larger of the two (then
    monotone). Clean sweeps (no hidden saturation) are unchanged.
    """
    k0 = int(np.ceil(lo + HIDDEN_FROM * (hi - lo)))
    sel = (d >= k0) & (d <= hi)
    if not sel.any():
        return u_raw
    x = (t[:, None] * e[None, :])[sel]
    a_var, b_var, extra = noise
    mu, _ = curve(x)
    extra_sel = np.broadcast_to(extra, d.shape)[sel]
    sd = np.sqrt(a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra_sel)
    k = d[sel].astype(np.intp) - k0
    n_k = hi - k0 + 1
    cnt = np.bincount(k, minlength=n_k)
    hidden = np.bincount(k, (mu > sat - 0.5 + 3.0 * sd).astype(np.float64), n_k)
    logx = np.bincount(k, np.log(np.maximum(x, 1e-12)), n_k)
    use = (cnt >= 5) & (hidden >= HIDDEN_FRACTION * cnt)
    if not use.any():
        return u_raw
    out = u_raw.copy()
    ks = np.flatnonzero(use)
    out[k0 + ks] = np.maximum(out[k0 + ks], np.exp(logx[ks] / cnt[ks]))
    out[k0:] = np.maximum.accumulate(out[k0:])
    return out
