"""The monotone piecewise-linear forward response C of the errors-in-DN fit and its least-squares steps."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import lsq_linear

from ..errors import FitError


@dataclass(frozen=True)
class Curve:
    """Monotone piecewise-linear ``C(x)``.

    Values ``c`` at knots ``xk`` (``xk[0] = 0``), extended linearly beyond the last knot with
    the last slope.
    """

    xk: np.ndarray
    c: np.ndarray

    @cached_property
    def slopes(self) -> np.ndarray:
        return np.diff(self.c) / np.diff(self.xk)

    @cached_property
    def _lut(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Build the segment lookup table of :meth:`segment`.

        Segment of the start of each of 4096 even bins over [0, x_K], and the knots with the
        last one at +inf (the last segment is unbounded).
        """
        n = 4096
        starts = np.arange(n) * (self.xk[-1] / n)
        lut = np.clip(np.searchsorted(self.xk, starts, side="right") - 1, 0, self.xk.size - 2)
        ext = self.xk.copy()
        ext[-1] = np.inf
        return lut, ext, n / self.xk[-1]

    def segment(self, x: np.ndarray) -> np.ndarray:
        """Index k of the segment ``x_k <= x < x_{k+1}`` (0 below, K-1 above).

        A lookup table then forward steps over the knots that share a bin.
        """
        lut, ext, inv = self._lut
        seg = lut[np.clip((x * inv).astype(np.intp), 0, lut.size - 1)]
        need = np.flatnonzero(x >= ext[seg + 1])
        flat = seg.reshape(-1)
        xf = x.reshape(-1)
        while need.size:
            flat[need] += 1
            need = need[xf[need] >= ext[flat[need] + 1]]
        return seg

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(C(x), C'(x))``."""
        seg = self.segment(x)
        s = self.slopes[seg]
        return self.c[seg] + s * (x - self.xk[seg]), s

    def at(self, t: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(C(t_i E_x), C'(t_i E_x))`` of every frame ``i`` and pixel ``x``, read-only.

        The fit evaluates one curve at one ``(t, E)`` several times per iteration (the noise
        model, the outlier weights, the censored samples, the next step's Jacobian and cost):
        for the same two array objects as the last call, the same result is returned. Neither
        ``t`` nor ``E`` is ever changed in place by the fit (each step makes a new E).
        """
        memo = self.__dict__.get("_at")
        if memo is not None and memo[0] is t and memo[1] is e:
            return memo[2]
        mu, s = self(t[:, None] * e[None, :])
        mu.flags.writeable = False
        s.flags.writeable = False
        self.__dict__["_at"] = (t, e, (mu, s))
        return mu, s

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """``C^{-1}(y)`` (C strictly increasing); linear beyond the ends."""
        s = self.slopes
        x = np.interp(y, self.c, self.xk)
        lo, hi = y < self.c[0], y > self.c[-1]
        x[lo] = (y[lo] - self.c[0]) / s[0]
        x[hi] = self.xk[-1] + (y[hi] - self.c[-1]) / s[-1]
        return x


def _ramp_stats(
    x: np.ndarray, seg: np.ndarray, a: np.ndarray, xk: np.ndarray,
    rows: np.ndarray | None = None, n_rows: int = 0,
) -> np.ndarray:
    """Sum a weight times the ramp basis of the piecewise-linear C.

    ``sum a * phi(x)`` where ``phi(x) = [1, ramp_0(x), ..., ramp_{K-1}(x)]`` is the basis of the
    piecewise-linear C (``ramp_k = min(max(x - x_k, 0), Δ_k)``, the last ramp unbounded).

    Without ``rows``: a vector (K+1,). With ``rows`` (group index of every sample, e.g. the
    pixel): a matrix (n_rows, K+1) of per-group sums. O(n + n_rows K). ``seg`` is the
    segment of every x (:meth:`Curve.segment`).
    """
    K = xk.size - 1
    dx = np.diff(xk)
    u = x - xk[seg]
    if rows is None:
        A = np.bincount(seg, a, K)
        B = np.bincount(seg, a * u, K)
        above = np.concatenate([np.cumsum(A[::-1])[::-1][1:], [0.0]])
        return np.concatenate([[A.sum()], dx * above + B])
    flat = rows * K + seg
    out = np.empty((n_rows, K + 1))
    A = np.bincount(flat, a, n_rows * K).reshape(n_rows, K)
    np.cumsum(A, axis=1, out=out[:, 1:])
    out[:, 0] = out[:, -1]
    out[:, 1:] = out[:, :1] - out[:, 1:]  # sum over the segments above k
    out[:, 1:] *= dx
    out[:, 1:] += np.bincount(flat, a * u, n_rows * K).reshape(n_rows, K)
    return out


def _normal_matrix(x: np.ndarray, seg: np.ndarray, w: np.ndarray, xk: np.ndarray) -> np.ndarray:
    """``sum w phi(x) phi(x)^T`` for the ramp basis, accumulated per segment in O(n + K^2)."""
    K = xk.size - 1
    dx = np.diff(xk)
    u = x - xk[seg]
    W = np.bincount(seg, w, K)
    S1 = np.bincount(seg, w * u, K)
    S2 = np.bincount(seg, w * u * u, K)
    Wa = np.concatenate([np.cumsum(W[::-1])[::-1][1:], [0.0]])
    v = dx * Wa + S1  # M[0, k+1], and M[k+1, l+1] = Δ_k v_l for k < l
    M = np.empty((K + 1, K + 1))
    M[0, 0] = W.sum()
    M[0, 1:] = v
    M[1:, 0] = v
    up = np.triu(dx[:, None] * v[None, :], 1)
    M[1:, 1:] = up + up.T
    M[1:, 1:][np.diag_indices(K)] = dx * dx * Wa + S2
    return M


def prior_quadratic(xk: np.ndarray, seg_weight: float, total_weight: float, smoothness: float,
                    slopes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return the quadratic prior ``(P, p)`` on the parameters of C.

    The prior is ``theta' P theta - 2 p' theta`` on ``theta = [C(0), s_0 .. s_{K-1}]``:

    - light smoothness ``lam sum_k ((s_{k+1} - s_k) (Δ_k + Δ_{k+1}) / 2)^2`` with
      ``lam = smoothness * mean segment weight``: a change of slope, in DN over the local knot
      spacing (knots sit at even DN steps, so this is scale-free: a relative change of slope
      times the DN step), weighs like ``smoothness`` times one segment's data.
      With ``slopes`` (the current curve's) the change of slope is measured in the log-log
      domain instead, relative to the best power law ``C' ~ x^q``:
      ``lam min_q sum_k (DN_k (log s_{k+1} - log s_k - q (log x_{k+1} - log x_k)))^2``
      (``x_k`` segment midpoints, ``DN_k`` the DN the two segments span / 2, q projected
      out), linearised at the current slopes. Every power law, a gamma-encoded camera
      (sRGB: ``C' ~ x^(1/2.4 - 1)``) as well as a linear sensor (q = 0), is then a null
      direction of the prior: the data alone choose the exponent,
    - the scale gauge ``mu (sum_k s_k Δ_k - x_K)^2`` (C rises by x_K over the knots: mean
      slope 1), ``mu = total weight``: it only pins the scale direction, which the data
      leave (almost) free, without stiffening the system.
    """
    K = xk.size - 1
    dx = np.diff(xk)
    D = np.diff(np.eye(K), axis=0)
    P = np.zeros((K + 1, K + 1))
    p = np.zeros(K + 1)
    lam = smoothness * seg_weight
    if slopes is None:
        D *= ((dx[:-1] + dx[1:]) / 2)[:, None]
        P[1:, 1:] = lam * (D.T @ D)
    else:
        sh = np.maximum(slopes, 1e-3 * float(np.sum(slopes * dx)) / xk[-1])
        lx = np.log((xk[:-1] + xk[1:]) / 2)
        ls = np.log(sh)
        A = D / sh[None, :]  # d(log s) = ds / s at the current slopes
        c = np.diff(ls) - A @ sh
        scale = (dx[:-1] * sh[:-1] + dx[1:] * sh[1:]) / 2
        A *= scale[:, None]
        c *= scale
        beta = scale * np.diff(lx)  # the power-law direction, q free: projected out
        proj = np.eye(K - 1) - np.outer(beta, beta) / max(float(beta @ beta), 1e-300)
        PA = proj @ A
        P[1:, 1:] = lam * (A.T @ PA)
        p[1:] = -lam * (PA.T @ c)
    mu = total_weight
    P[1:, 1:] += mu * np.outer(dx, dx)
    p[1:] += mu * xk[-1] * dx
    return P, p


def _solve_bounded(M: np.ndarray, b: np.ndarray, lb: np.ndarray) -> np.ndarray:
    """``argmin theta' M theta - 2 b' theta`` subject to ``theta >= lb`` (M positive definite).

    The unconstrained solution if feasible, else BVLS on the Cholesky factor.
    """
    n = M.shape[0]
    scale = max(float(np.trace(M)) / n, 1e-300)
    for ridge in (1e-12, 1e-8, 1e-4):
        try:
            L = np.tril(cho_factor(M + np.eye(n) * (ridge * scale), lower=True)[0])
            break
        except np.linalg.LinAlgError:
            continue
    else:
        raise FitError("the response fit is ill-conditioned", hint="use more pixels or exposures")
    z = solve_triangular(L, b, lower=True)
    theta = solve_triangular(L.T, z, lower=False)
    if np.all(theta >= lb):
        return theta
    return lsq_linear(L.T, z, bounds=(lb, np.inf), method="bvls").x


def _theta_of(curve: Curve) -> np.ndarray:
    return np.concatenate([[curve.c[0]], curve.slopes])


def _curve_of(theta: np.ndarray, xk: np.ndarray) -> Curve:
    return Curve(xk=xk, c=theta[0] + np.concatenate([[0.0], np.cumsum(theta[1:] * np.diff(xk))]))


def joint_step(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    prior: tuple[np.ndarray, np.ndarray], s_min: float, joint: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Take one Gauss-Newton step on (C, E) jointly.

    One Gauss-Newton step on (C, E) jointly, E eliminated by its Schur complement
    (``joint=False``: the exact C-step for fixed E, E unchanged).

    C is linear in ``theta`` (``C(x) = phi(x)' theta``); E enters through ``J = t C'(t E)``.
    For a trial ``theta`` the best linearised update of pixel x is
    ``dE_x = sum_i w J (I - phi' theta) / h_x``, ``h_x = sum_i w J^2``, which leaves the
    reduced problem ``theta' (M - sum_x g_x g_x' / h_x + P) theta - 2 theta' (b - sum_x g_x
    q_x / h_x)`` with ``g_x = sum_i w J phi``, ``q_x = sum_i w J I``: solved with slopes
    ``>= s_min``. Returns the proposed ``(theta, E)`` and the reduced normal matrix (with
    ``joint``: the information matrix of ``theta`` at the current (C, E), see
    :func:`normal_information`).
    """
    xk = curve.xk
    n_f, n_p = d.shape
    x = t[:, None] * e[None, :]
    _, s = curve.at(t, e)
    J = t[:, None] * s
    on = w > 0
    xs, ws, Js, ds = x[on], w[on], J[on], d[on]
    pix = np.broadcast_to(np.arange(n_p), d.shape)[on]
    h = np.bincount(pix, ws * Js * Js, n_p)
    q = np.bincount(pix, ws * Js * ds, n_p)
    seg = curve.segment(xs)
    G = _ramp_stats(xs, seg, ws * Js, xk, pix, n_p)
    ok = h > 1e-12 * max(h.max(), 1e-300)
    if not joint:
        ok[:] = False
    Go = G[ok]
    Gh = Go / h[ok, None]
    # G' G / h as a BLAS product (np.einsum's own loop took a sixth of the whole fit)
    M = _normal_matrix(xs, seg, ws, xk) - Go.T @ Gh + prior[0]
    b = _ramp_stats(xs, seg, ws * ds, xk) - Gh.T @ q[ok] + prior[1]
    lb = np.concatenate([[-np.inf], np.full(xk.size - 1, s_min)])
    theta = _solve_bounded(M, b, lb)
    c, _ = _curve_of(theta, xk)(x)
    de = np.where(ok, np.bincount(pix, ws * Js * (ds - c[on]), n_p) / np.where(ok, h, 1.0), 0.0)
    return theta, np.maximum(e + de, 0.0), M


def normal_information(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    prior: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Return the information matrix of C's parameters with every pixel's E marginalised.

    ``theta = [C(0), s_0 .. s_{K-1}]``: the Schur complement ``M - sum_x g_x g_x' / h_x + P``
    of :func:`joint_step` (the Gauss-Newton normal matrix of (C, E) with E eliminated) plus
    the prior's quadratic ``P``. With ``w = 1 / var`` its inverse is the covariance of
    ``theta`` (the linearised posterior: samples' noise as modelled, the prior as a Gaussian).
    """
    xk = curve.xk
    n_p = d.shape[1]
    x = t[:, None] * e[None, :]
    _, s = curve.at(t, e)
    J = t[:, None] * s
    on = w > 0
    xs, ws, Js = x[on], w[on], J[on]
    pix = np.broadcast_to(np.arange(n_p), d.shape)[on]
    h = np.bincount(pix, ws * Js * Js, n_p)
    seg = curve.segment(xs)
    G = _ramp_stats(xs, seg, ws * Js, xk, pix, n_p)
    ok = h > 1e-12 * max(h.max(), 1e-300)
    Go = G[ok]
    return _normal_matrix(xs, seg, ws, xk) - Go.T @ (Go / h[ok, None]) + prior[0]


def ramp_basis(x: np.ndarray, xk: np.ndarray) -> np.ndarray:
    """``phi(x) = [1, ramp_0(x), ..., ramp_{K-1}(x)]`` of every ``x``: ``C(x) = phi(x)' theta``.

    ``ramp_k = min(max(x - x_k, 0), Δ_k)``, the last ramp unbounded (see :func:`_ramp_stats`).
    """
    x = np.asarray(x, dtype=np.float64)
    dx = np.diff(xk)
    r = np.clip(x[:, None] - xk[None, :-1], 0.0, dx[None, :])
    r[:, -1] = np.maximum(x - xk[-2], 0.0)
    return np.concatenate([np.ones((x.size, 1)), r], axis=1)


def _cost(d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
          prior: tuple[np.ndarray, np.ndarray]) -> float:
    """``sum w (I - C(t E))^2`` plus the prior."""
    c, _ = curve.at(t, e)
    th = _theta_of(curve)
    return float(np.sum(w * (d - c) ** 2) + th @ prior[0] @ th - 2 * prior[1] @ th)


def line_search(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve,
    prior: tuple[np.ndarray, np.ndarray], theta_new: np.ndarray, e_new: np.ndarray,
) -> tuple[Curve, np.ndarray, float]:
    """Backtrack along the step until the cost decreases (step 1, 1/2, ... 1/16).

    Returns the accepted (or unchanged) curve and E and the cost decrease (0 if none).
    """
    cost0 = _cost(d, w, t, e, curve, prior)
    th0 = _theta_of(curve)
    for frac in (1.0, 0.5, 0.25, 0.125, 0.0625):
        cv = _curve_of(th0 + frac * (theta_new - th0), curve.xk)
        ee = np.maximum(e + frac * (e_new - e), 0.0)
        cost = _cost(d, w, t, ee, cv, prior)
        if cost < cost0:
            return cv, ee, cost0 - cost
    return curve, e, 0.0


def _knots_for(curve: Curve, hi_dn: float, n_seg: int) -> np.ndarray:
    """Knots ``x`` evenly spaced in DN between the curve's black level and ``hi_dn``."""
    levels = np.linspace(curve.c[0], max(hi_dn, curve.c[0] + n_seg), n_seg + 1)
    xk = curve.inverse(levels)
    xk[0] = 0.0
    xk = np.maximum.accumulate(xk)
    if np.any(np.diff(xk) <= 0):
        xk = np.linspace(0.0, xk[-1], n_seg + 1)
    return xk


def reknot(
    curve: Curve, e: np.ndarray, t: np.ndarray, m: np.ndarray, hi: int, n_seg: int
) -> tuple[Curve, np.ndarray]:
    """Move the knots to even DN steps of the current curve.

    Move the knots to even DN steps of the current curve (C projected onto them), then rescale x
    so that C rises by x_K over the knots (scale gauge: mean slope 1).
    """
    x = t[:, None] * e[None, :]
    xk = _knots_for(curve, hi, n_seg)
    xk[-1] = max(xk[-1], float(x[m].max()) * (1 + 1e-9))
    c, _ = curve(xk)
    scale = (c[-1] - c[0]) / xk[-1]
    return Curve(xk=xk * scale, c=c), e * scale


def fit_energy(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: Curve, steps: int
) -> np.ndarray:
    """E-step (errors-in-DN analogue of Eq. 7).

    Per pixel, Gauss-Newton on ``sum_i w_i (I_i - C(t_i E))^2``:
    ``E += sum w J r / sum w J^2``, ``J = t_i C'(t_i E)``, halving a pixel's step while it does
    not reduce its cost. ``w`` is 0 on unusable samples.
    """
    def pix_cost(ee: np.ndarray) -> np.ndarray:
        c, _ = curve.at(t, ee)
        return (w * (d - c) ** 2).sum(0)

    cost = pix_cost(e)
    for _ in range(steps):
        c, s = curve.at(t, e)
        jac = t[:, None] * s
        num = (w * jac * (d - c)).sum(0)
        den = (w * jac * jac).sum(0)
        step = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        for _ in range(4):
            trial = np.maximum(e + step, 0.0)
            tc = pix_cost(trial)
            better = tc <= cost
            e = np.where(better, trial, e)
            cost = np.where(better, tc, cost)
            if better.all():
                break
            step = np.where(better, 0.0, step / 2)
    return e


def relative_u(curve: Curve, grid: np.ndarray) -> np.ndarray:
    """``C^{-1}`` on a DN grid relative to its value at the grid's middle (gauge-free)."""
    u = curve.inverse(grid)
    return u / max(float(u[grid.size // 2]), 1e-300)


def relaxed_prior_curve(curve: Curve, info: np.ndarray, smooth: tuple[np.ndarray, np.ndarray],
                        relax: float, s_min: float) -> Curve:
    """C after one Newton step towards the fit with its smoothness prior weakened.

    ``info`` is the information matrix of ``theta = [C(0), s_0 .. s_{K-1}]`` at the fit (data
    with E marginalised plus the whole prior, :func:`normal_information`), ``smooth = (P_s,
    p_s)`` the smoothness part of the prior (:func:`prior_quadratic` without the scale gauge).
    With the smoothness weight multiplied by ``1 - relax`` the cost's gradient at ``theta`` is
    ``-2 relax (P_s theta - p_s)`` (the fit is stationary with the whole prior), its Hessian
    ``2 (info - relax P_s)``; the step ``(info - relax P_s)^+ relax (P_s theta - p_s)`` (slopes
    kept ``>= s_min``) is how far the prior held C where the data alone say otherwise.
    """
    th = _theta_of(curve)
    Ps, ps = smooth
    h = info - relax * Ps
    step = np.linalg.pinv(h, hermitian=True, rcond=1e-13) @ (relax * (Ps @ th - ps))
    th = th + step
    th[1:] = np.maximum(th[1:], s_min)
    return _curve_of(th, curve.xk)
