"""Inverse camera response U from an exposure sweep of a static scene (Eq. 5-7).

Image formation (Eq. 3-4): ``I_i(x) = C(t_i E(x))``, i.e. ``U(I_i(x)) = t_i E(x)`` with
``U = C^{-1}``. Each band is its own camera. The paper estimates U and E by minimising

    (Eq. 5)  M(U, E) = sum_i sum_x (U(I_i(x)) - t_i E(x))^2

alternating its two closed-form minimisers

    (Eq. 6)  U(k) = sum_{(i,x) in Omega_k} t_i E(x) / |Omega_k|,  Omega_k = {(i, x): I_i(x) = k}
    (Eq. 7)  E(x) = sum_i t_i U(I_i(x)) / sum_i t_i^2

This plain alternation is kept as ``method="alternating"``. It treats the noise as if it were
on ``U(I)`` while it is on the DN, and converges to a biased fixed point (PAPER.md measured
13-24 % worst error in U on its 10-bit sweeps; 3-5 % on the synthetic sweeps of our tests).

The default ``method="forward"`` models the noise where it is. It fits the forward response
``C`` (monotone piecewise linear in the exposure energy ``x``: ``C(0)`` plus segment slopes
``>= 0``, knots at even DN steps, a light second-difference prior) and ``E`` per pixel by
weighted least squares on the DN:

    M(C, E) = sum_i sum_x w_ix (I_i(x) - C(t_i E(x)))^2 + prior(C),
    w = 1 / (a + b (C(t_i E(x)) - black))            (read + shot noise variance of the DN)

Each iteration takes (b) the C update given E, the errors-in-DN analogue of Eq. 6, which is
a bounded linear least-squares problem because C is linear in its parameters, jointly with
(a) the E update of every pixel linearised (the Eq. 7 analogue), E eliminated through its
Schur complement (a Gauss-Newton step on both, with backtracking), then a per-pixel
Gauss-Newton step on E alone. ``a, b`` are re-estimated from the residuals (leverage
corrected); the knots are re-spread evenly in DN a few times. Finally ``U = C^{-1}`` on the
DN grid; ``C(0)`` is the estimated black level, so ``U = 0`` there.

Gauge (docs/architecture.md): ``U[k] = 0`` at/below black, ``U[k_ref] = k_ref - black`` with
``k_ref = dn_max // 2``. Saturated samples (``>= saturation_dn``, default ``dn_max``) and
clipped samples (``0`` or ``dn_max``) are excluded; DN never observed are filled monotonically
(linear extrapolation above the highest observed DN).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import lsq_linear

from .errors import FitError, InputError

METHODS = ("forward", "alternating")


@dataclass(frozen=True)
class ResponseFit:
    """Result of one band's response fit (Eq. 5-7)."""

    inverse_response: np.ndarray  # U(k), (2**bits,) float64, monotone, gauge of the module
    black_level: float  # DN where U = 0
    saturation_dn: int  # samples >= this are saturated
    observed_dn: tuple[int, int]  # lowest and highest unsaturated DN used
    residual_rms_dn: float  # rms of I - C(t E) over the samples used (DN)
    method: str  # "forward" or "alternating"
    iterations: int
    n_samples: int  # unsaturated samples used


# =============================================================================== validation


def _validate(dn: np.ndarray, exposure: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes and values; return ``(dn as int32 (n_frames, n_pixels), t float64)``."""
    if not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 16:
        raise InputError(f"bit depth must be an integer 1..16, got {bits!r}")
    dn = np.asarray(dn)
    t = np.asarray(exposure, dtype=np.float64).ravel()
    if dn.ndim != 2 or dn.shape[0] != t.size or dn.shape[1] == 0:
        raise InputError(
            f"response samples must be (n_frames, n_pixels) with one exposure per frame; got "
            f"samples {dn.shape} and {t.size} exposures"
        )
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        bad = int(np.flatnonzero(~np.isfinite(t) | (t <= 0))[0])
        raise InputError(
            f"frame {bad} has exposure {t[bad]:g}; exposures must be positive "
            "(effective exposure = exposure_ms * gain)"
        )
    if not np.issubdtype(dn.dtype, np.integer):
        if not np.all(np.isfinite(dn)) or np.any(dn != np.round(dn)):
            raise InputError("response samples must be integer DN")
    dn_max = 2**bits - 1
    if dn.min() < 0 or dn.max() > dn_max:
        raise InputError(
            f"DN outside 0..{dn_max} for a {bits}-bit camera (range {dn.min()}..{dn.max()}); "
            "check the camera's bit depth"
        )
    return dn.astype(np.int32), t


def _usable(dn: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """Samples that carry information: below saturation and not a clipped value (0, dn_max)."""
    return (dn < saturation_dn) & (dn < dn_max) & (dn > 0)


def _usable_sweep(dn: np.ndarray, t: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """:func:`_usable`, also dropping a pixel's samples at exposures >= the shortest one at
    which it is already saturated (noise can pull a saturated pixel just below the clip)."""
    sat = (dn >= saturation_dn) | (dn >= dn_max)
    t_sat = np.where(sat, t[:, None], np.inf).min(axis=0)
    return _usable(dn, saturation_dn, dn_max) & (t[:, None] < t_sat[None, :])


# =============================================================================== consistency


def check_exposure_consistency(dn: np.ndarray, exposure: np.ndarray, bits: int) -> list[int]:
    """Indices of frames whose brightness contradicts their exposure.

    For every pair of frames with exposures ``t_a >= 1.25 t_b`` the longer frame must not be
    darker: its median DN may not fall below the shorter one's by more than
    ``max(1, 0.5 % of dn_max)``. Offending frames are removed greedily (the frame in most
    contradictions first; ties go to the frame farthest from a monotone fit of median DN on
    exposure) until none is left; the removed indices are returned, sorted.
    """
    dn, t = _validate(dn, exposure, bits)
    dn_max = 2**bits - 1
    med = np.median(dn, axis=1).astype(np.float64)
    tol = max(1.0, 0.005 * dn_max)
    longer = t[:, None] >= 1.25 * t[None, :]  # [a, b]: a clearly longer than b
    bad = longer & (med[:, None] < med[None, :] - tol)
    order = np.argsort(t, kind="stable")
    alive = np.ones(t.size, dtype=bool)
    removed: list[int] = []
    while True:
        live = bad & alive[:, None] & alive[None, :]
        counts = live.sum(axis=0) + live.sum(axis=1)
        if counts.max() == 0:
            return sorted(removed)
        idx = order[alive[order]]
        fitted = np.empty(t.size)
        fitted[idx] = _pava(med[idx], np.ones(idx.size))
        dev = np.abs(med - fitted)
        cand = np.flatnonzero(counts == counts.max())
        worst = int(cand[np.argmax(dev[cand])])
        alive[worst] = False
        removed.append(worst)


def _pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted isotonic (non-decreasing) least-squares fit of ``y`` (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[float] = []
    lens: list[int] = []
    for yi, wi in zip(y.tolist(), w.tolist()):
        vals.append(yi)
        wts.append(wi)
        lens.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum if wsum > 0 else vals[-1]
            n = lens[-2] + lens[-1]
            del vals[-1], wts[-1], lens[-1]
            vals[-1], wts[-1], lens[-1] = v, wsum, n
    return np.repeat(np.array(vals), lens)


# =============================================================================== sample selection


def _select_pixels(
    dn: np.ndarray, usable: np.ndarray, max_pixels: int, seed: int
) -> np.ndarray:
    """Indices of at most ``max_pixels`` pixels with >= 2 usable samples spanning the
    brightness range: half evenly spaced in summed DN (a monotone proxy of E), the rest
    drawn at random (seeded)."""
    eligible = np.flatnonzero(usable.sum(axis=0) >= 2)
    if eligible.size <= max_pixels:
        return eligible
    proxy = dn[:, eligible].sum(axis=0, dtype=np.int64).astype(np.float64)
    order = np.argsort(proxy, kind="stable")
    targets = np.linspace(proxy[order[0]], proxy[order[-1]], max_pixels // 2)
    pos = np.clip(np.searchsorted(proxy[order], targets), 0, order.size - 1)
    spread = np.unique(order[pos])
    rest = np.setdiff1d(np.arange(eligible.size), spread, assume_unique=True)
    rng = np.random.default_rng(seed)
    extra = rng.choice(rest, size=max_pixels - spread.size, replace=False)
    return np.sort(eligible[np.concatenate([spread, extra])])


def _linear_init(
    d: np.ndarray, m: np.ndarray, t: np.ndarray, lo: int, hi: int
) -> tuple[float, np.ndarray]:
    """Least-squares start ``I = b + t E`` with a common intercept b (black level guess) on
    the samples in the lower 75 % of the observed DN range (away from the shoulder).

    For each pixel the slope is profiled out: ``b = sum_x 1'(1-P_x) d_x / sum_x 1'(1-P_x) 1``
    with ``P_x`` the projection on the pixel's exposures; then ``E_x = sum t (d - b) / sum t^2``
    (over all its usable samples when it has none in the lower range).
    """
    low = m & (d <= lo + 0.75 * (hi - lo))
    mf = low.astype(np.float64)
    tt = t[:, None] * mf
    n = mf.sum(0)
    st, stt = tt.sum(0), (tt * t[:, None]).sum(0)
    sd, std = (d * mf).sum(0), (tt * d).sum(0)
    ok = n >= 2
    num = np.sum(sd[ok] - st[ok] * std[ok] / stt[ok])
    den = np.sum(n[ok] - st[ok] ** 2 / stt[ok])
    b = float(num / den) if den > 1e-9 else float(np.min(d[m]))
    b = min(b, float(lo))
    use = np.where(n >= 1, mf, m.astype(np.float64))
    tu = t[:, None] * use
    e = (tu * (d - b)).sum(0) / np.maximum((tu * t[:, None]).sum(0), 1e-300)
    return b, np.maximum(e, 0.0)


# =============================================================================== forward model


@dataclass(frozen=True)
class _Curve:
    """Monotone piecewise-linear ``C(x)``: values ``c`` at knots ``xk`` (``xk[0] = 0``),
    extended linearly beyond the last knot with the last slope."""

    xk: np.ndarray
    c: np.ndarray

    @cached_property
    def slopes(self) -> np.ndarray:
        return np.diff(self.c) / np.diff(self.xk)

    @cached_property
    def _lut(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Segment of the start of each of 4096 even bins over [0, x_K], and the knots with
        the last one at +inf (the last segment is unbounded)."""
        n = 4096
        starts = np.arange(n) * (self.xk[-1] / n)
        lut = np.clip(np.searchsorted(self.xk, starts, side="right") - 1, 0, self.xk.size - 2)
        ext = self.xk.copy()
        ext[-1] = np.inf
        return lut, ext, n / self.xk[-1]

    def segment(self, x: np.ndarray) -> np.ndarray:
        """Index k of the segment ``x_k <= x < x_{k+1}`` (0 below, K-1 above): a lookup
        table then forward steps over the knots that share a bin."""
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
    """``sum a * phi(x)`` where ``phi(x) = [1, ramp_0(x), ..., ramp_{K-1}(x)]`` is the basis of
    the piecewise-linear C (``ramp_k = min(max(x - x_k, 0), Δ_k)``, the last ramp unbounded).

    Without ``rows``: a vector (K+1,). With ``rows`` (group index of every sample, e.g. the
    pixel): a matrix (n_rows, K+1) of per-group sums. O(n + n_rows K). ``seg`` is the
    segment of every x (:meth:`_Curve.segment`)."""
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


def _prior(xk: np.ndarray, seg_weight: float, total_weight: float, smoothness: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic prior ``theta' P theta - 2 p' theta`` on ``theta = [C(0), s_0 .. s_{K-1}]``:

    - light smoothness ``lam sum_k ((s_{k+1} - s_k) (Δ_k + Δ_{k+1}) / 2)^2`` with
      ``lam = smoothness * mean segment weight``: a change of slope, in DN over the local knot
      spacing (knots sit at even DN steps, so this is scale-free: a relative change of slope
      times the DN step), weighs like ``smoothness`` times one segment's data,
    - the scale gauge ``mu (sum_k s_k Δ_k - x_K)^2`` (C rises by x_K over the knots: mean
      slope 1), ``mu = total weight``: it only pins the scale direction, which the data
      leave (almost) free, without stiffening the system.
    """
    K = xk.size - 1
    dx = np.diff(xk)
    D = np.diff(np.eye(K), axis=0)
    P = np.zeros((K + 1, K + 1))
    D *= ((dx[:-1] + dx[1:]) / 2)[:, None]
    P[1:, 1:] = smoothness * seg_weight * (D.T @ D)
    mu = total_weight
    P[1:, 1:] += mu * np.outer(dx, dx)
    p = np.concatenate([[0.0], mu * xk[-1] * dx])
    return P, p


def _solve_bounded(M: np.ndarray, b: np.ndarray, lb: np.ndarray) -> np.ndarray:
    """``argmin theta' M theta - 2 b' theta`` subject to ``theta >= lb`` (M positive
    definite): the unconstrained solution if feasible, else BVLS on the Cholesky factor."""
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


def _theta_of(curve: _Curve) -> np.ndarray:
    return np.concatenate([[curve.c[0]], curve.slopes])


def _curve_of(theta: np.ndarray, xk: np.ndarray) -> _Curve:
    return _Curve(xk=xk, c=theta[0] + np.concatenate([[0.0], np.cumsum(theta[1:] * np.diff(xk))]))


def _joint_step(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
    prior: tuple[np.ndarray, np.ndarray], s_min: float, joint: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton step on (C, E) jointly, E eliminated by its Schur complement
    (``joint=False``: the exact C-step for fixed E, E unchanged).

    C is linear in ``theta`` (``C(x) = phi(x)' theta``); E enters through ``J = t C'(t E)``.
    For a trial ``theta`` the best linearised update of pixel x is
    ``dE_x = sum_i w J (I - phi' theta) / h_x``, ``h_x = sum_i w J^2``, which leaves the
    reduced problem ``theta' (M - sum_x g_x g_x' / h_x + P) theta - 2 theta' (b - sum_x g_x
    q_x / h_x)`` with ``g_x = sum_i w J phi``, ``q_x = sum_i w J I``: solved with slopes
    ``>= s_min``. Returns the proposed ``(theta, E)``."""
    xk = curve.xk
    n_f, n_p = d.shape
    x = t[:, None] * e[None, :]
    _, s = curve(x)
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
    Gh = G[ok] / h[ok, None]
    M = _normal_matrix(xs, seg, ws, xk) - np.einsum("ij,ik->jk", G[ok], Gh) + prior[0]
    b = _ramp_stats(xs, seg, ws * ds, xk) - Gh.T @ q[ok] + prior[1]
    lb = np.concatenate([[-np.inf], np.full(xk.size - 1, s_min)])
    theta = _solve_bounded(M, b, lb)
    c, _ = _curve_of(theta, xk)(x)
    de = np.where(ok, np.bincount(pix, ws * Js * (ds - c[on]), n_p) / np.where(ok, h, 1.0), 0.0)
    return theta, np.maximum(e + de, 0.0)


def _cost(d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
          prior: tuple[np.ndarray, np.ndarray]) -> float:
    """``sum w (I - C(t E))^2`` plus the prior."""
    c, _ = curve(t[:, None] * e[None, :])
    th = _theta_of(curve)
    return float(np.sum(w * (d - c) ** 2) + th @ prior[0] @ th - 2 * prior[1] @ th)


def _fit_energy(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve, steps: int
) -> np.ndarray:
    """E-step (errors-in-DN analogue of Eq. 7): per pixel, Gauss-Newton on
    ``sum_i w_i (I_i - C(t_i E))^2``:  ``E += sum w J r / sum w J^2``, ``J = t_i C'(t_i E)``,
    halving a pixel's step while it does not reduce its cost. ``w`` is 0 on unusable samples."""
    def pix_cost(ee: np.ndarray) -> np.ndarray:
        c, _ = curve(t[:, None] * ee[None, :])
        return (w * (d - c) ** 2).sum(0)

    cost = pix_cost(e)
    for _ in range(steps):
        c, s = curve(t[:, None] * e[None, :])
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


def _noise_model(r: np.ndarray, mu: np.ndarray, leverage: np.ndarray, floor: float
                 ) -> tuple[float, float]:
    """Fit ``var(I) = a + b * mu`` (read + shot noise, ``mu = C - black``) to the squared
    residuals, each divided by ``1 - leverage`` (the share of the sample's noise absorbed by
    its pixel's fitted E), averaged in 16 quantile bins of mu; two weighted passes,
    ``a >= floor``."""
    keep = leverage < 0.9
    r2 = r[keep] ** 2 / (1.0 - leverage[keep])
    mu = mu[keep]
    if r2.size < 10:
        return max(float(np.mean(r ** 2)) if r.size else 1.0, floor), 0.0
    edges = np.unique(np.quantile(mu, np.linspace(0, 1, 17)))
    if edges.size < 3:
        return max(float(r2.mean()), floor), 0.0
    k = np.clip(np.searchsorted(edges, mu, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1).astype(np.float64)
    ok = cnt > 0
    mv = np.bincount(k, r2, edges.size - 1)[ok] / cnt[ok]
    mm = np.bincount(k, mu, edges.size - 1)[ok] / cnt[ok]
    X = np.stack([np.ones_like(mm), mm], 1)
    sw = np.sqrt(cnt[ok]) / np.maximum(mv, floor)
    for _ in range(2):
        sol = lsq_linear(X * sw[:, None], mv * sw, bounds=([floor, 0.0], [np.inf, np.inf])).x
        sw = np.sqrt(cnt[ok]) / np.maximum(X @ sol, floor)
    return float(sol[0]), float(sol[1])


def _knots_for(curve: _Curve, hi_dn: float, n_seg: int) -> np.ndarray:
    """Knots ``x`` evenly spaced in DN between the curve's black level and ``hi_dn``."""
    levels = np.linspace(curve.c[0], max(hi_dn, curve.c[0] + n_seg), n_seg + 1)
    xk = curve.inverse(levels)
    xk[0] = 0.0
    xk = np.maximum.accumulate(xk)
    if np.any(np.diff(xk) <= 0):
        xk = np.linspace(0.0, xk[-1], n_seg + 1)
    return xk


def fit_response(
    dn: np.ndarray,
    exposure: np.ndarray,
    bits: int,
    *,
    method: str = "forward",
    saturation_dn: int | None = None,
    max_pixels: int = 4000,
    seed: int = 0,
    smoothness: float = 0.05,
    max_iter: int = 60,
    tol: float = 1e-4,
) -> ResponseFit:
    """Fit the inverse response U of one band from a sweep (Eq. 5-7).

    ``dn`` ``(n_frames, n_pixels)`` integer samples of a static scene, ``exposure``
    ``(n_frames,)`` effective exposures (ms * gain). ``method="forward"`` (default) fits the
    forward response with the noise on the DN (see module docstring), iterating

    - (a) ``E(x) = argmin_E sum_i w (I_i(x) - C(t_i E))^2`` (Gauss-Newton; Eq. 7 analogue),
    - (b) ``C = argmin_C sum_{i,x} w (I_i(x) - C(t_i E(x)))^2 + prior``, C monotone
      (Eq. 6 analogue), taken jointly with a linearised (a),

    ``w = 1/(a + b (C - black))`` re-estimated from the residuals, until U changes by less
    than ``tol`` (relative to U at the top) or ``max_iter``. ``smoothness`` weighs the
    second-difference prior on C against one knot segment's data. ``method="alternating"``
    runs the paper's plain Eq. 6/7 (:func:`fit_response_alternating`). Pixels (at most
    ``max_pixels``, half evenly spread over the brightness range, the rest drawn with
    ``seed``) with >= 2 usable samples are used.

    Raises ``InputError`` on bad shapes or non-positive exposures, ``FitError`` on fewer than
    2 distinct exposures, frames whose brightness contradicts their exposure
    (:func:`check_exposure_consistency`), or no unsaturated samples.
    """
    if method not in METHODS:
        raise InputError(f"unknown response method {method!r}; use one of {', '.join(METHODS)}")
    d_all, t = _validate(dn, exposure, bits)
    dn_max = 2**bits - 1
    sat = dn_max if saturation_dn is None else int(saturation_dn)
    if not 1 <= sat <= dn_max:
        raise InputError(f"saturation_dn must be in 1..{dn_max}, got {saturation_dn}")
    _check_sweep(d_all, t, bits)
    usable_all = _usable_sweep(d_all, t, sat, dn_max)
    if not usable_all.any():
        raise FitError(
            "no unsaturated samples in the sweep: every DN is 0 or saturated",
            hint="add shorter exposures (or check the saturation level)",
        )
    observed = (int(d_all[usable_all].min()), int(d_all[usable_all].max()))
    cols = _select_pixels(d_all, usable_all, max_pixels, seed)
    if cols.size == 0:
        raise FitError(
            "no pixel has unsaturated samples in 2 or more frames",
            hint="add exposures so that each brightness is seen unsaturated at least twice",
        )
    d = d_all[:, cols].astype(np.float64)
    m = usable_all[:, cols]
    if np.unique(d[m]).size < 3:
        raise FitError(
            f"the sweep shows only {np.unique(d[m]).size} distinct unsaturated DN",
            hint="use a scene with a range of brightness and several exposures",
        )
    if method == "alternating":
        return _alternating(d, m, t, bits, sat, observed)
    return _forward(d, m, t, bits, sat, observed, smoothness, max_iter, tol)


def _check_sweep(d: np.ndarray, t: np.ndarray, bits: int) -> None:
    n_t = np.unique(t).size
    if n_t < 2:
        raise FitError(
            f"the sweep has {n_t} distinct exposure(s); the response fit needs at least 2",
            hint="capture the static scene at several exposure times",
        )
    bad = check_exposure_consistency(d, t, bits)
    if bad:
        names = ", ".join(f"frame {i} (exposure {t[i]:g})" for i in bad)
        raise FitError(
            f"brightness contradicts exposure for {names}",
            hint="fix their exposure times or drop frames taken while the scene or light changed",
        )


def _forward(
    d: np.ndarray,
    m: np.ndarray,
    t: np.ndarray,
    bits: int,
    sat: int,
    observed: tuple[int, int],
    smoothness: float,
    max_iter: int,
    tol: float,
) -> ResponseFit:
    """The errors-in-DN fit of :func:`fit_response` on the selected samples ``d[m]``."""
    dn_max = 2**bits - 1
    lo, hi = observed
    n_seg = int(np.clip((hi - lo) // 4, 4, 64))
    b0, e = _linear_init(d, m, t, lo, hi)
    xk = np.linspace(0.0, max(hi - b0, 1.0), n_seg + 1)
    curve = _Curve(xk=xk, c=b0 + xk)
    mf = m.astype(np.float64)
    a_var, b_var = 1.0, 0.0
    s_min = 1e-4
    grid = np.linspace(lo, lo + 0.95 * (hi - lo), 129)  # convergence: U relative to mid-range
    prev_u = _relative_u(curve, grid)
    reknot_at = (1, 3, 6)
    settle = 7  # last re-knot / noise-model update; weights frozen afterwards
    it = 0
    for it in range(1, max_iter + 1):
        if it in reknot_at:
            curve, e = _reknot(curve, e, t, m, hi, n_seg)
        if it <= settle:
            mu, _ = curve(t[:, None] * e[None, :])
            w = mf / (a_var + b_var * np.maximum(mu - curve.c[0], 0.0))
            prior = _prior(curve.xk, w.sum() / n_seg, w.sum(), smoothness)
        theta_new, e_new = _joint_step(d, w, t, e, curve, prior, s_min)
        curve, e, gain = _line_search(d, w, t, e, curve, prior, theta_new, e_new)
        if gain == 0.0:  # Gauss-Newton stalled on a kink: an exact block step on C instead
            theta_new, e_new = _joint_step(d, w, t, e, curve, prior, s_min, joint=False)
            curve, e, gain = _line_search(d, w, t, e, curve, prior, theta_new, e_new)
        e = _fit_energy(d, w, t, e, curve, steps=1)
        if it <= 3 or it in (5, settle):
            a_var, b_var = _noise_update(d, m, w, t, e, curve)
        u = _relative_u(curve, grid)
        change = float(np.max(np.abs(u - prev_u)))
        prev_u = u
        # stop on a small change of U, or once the cost decrease is far below the noise
        if it > settle and (change < tol or gain < 2e-5 * float(mf.sum())):
            break
    black = float(curve.c[0])
    u_raw = curve.inverse(np.arange(dn_max + 1, dtype=np.float64))
    U = _finalise(u_raw, black, hi, bits)
    mu, _ = curve(t[:, None] * e[None, :])
    rms = float(np.sqrt(np.mean((d - mu)[m] ** 2)))
    return ResponseFit(U, black, sat, observed, rms, "forward", it, int(m.sum()))


def _relative_u(curve: _Curve, grid: np.ndarray) -> np.ndarray:
    """``C^{-1}`` on a DN grid relative to its value at the grid's middle (gauge-free)."""
    u = curve.inverse(grid)
    return u / max(float(u[grid.size // 2]), 1e-300)


def _noise_update(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve
) -> tuple[float, float]:
    """Re-estimate the DN noise model from the residuals (see :func:`_noise_model`), the
    leverage of a sample being ``w J^2 / sum_i w J^2`` over its pixel, ``J = t C'(t E)``."""
    mu, s = curve(t[:, None] * e[None, :])
    wj2 = w * (t[:, None] * s) ** 2
    lev = wj2 / np.maximum(wj2.sum(0), 1e-300)
    return _noise_model((d - mu)[m], np.maximum(mu - curve.c[0], 0.0)[m], lev[m], 1 / 12)


def _reknot(
    curve: _Curve, e: np.ndarray, t: np.ndarray, m: np.ndarray, hi: int, n_seg: int
) -> tuple[_Curve, np.ndarray]:
    """Move the knots to even DN steps of the current curve (C projected onto them), then
    rescale x so that C rises by x_K over the knots (scale gauge: mean slope 1)."""
    x = t[:, None] * e[None, :]
    xk = _knots_for(curve, hi, n_seg)
    xk[-1] = max(xk[-1], float(x[m].max()) * (1 + 1e-9))
    c, _ = curve(xk)
    scale = (c[-1] - c[0]) / xk[-1]
    return _Curve(xk=xk * scale, c=c), e * scale


def _line_search(
    d: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
    prior: tuple[np.ndarray, np.ndarray], theta_new: np.ndarray, e_new: np.ndarray,
) -> tuple[_Curve, np.ndarray, float]:
    """Backtrack along the step until the cost decreases (step 1, 1/2, ... 1/16); returns the
    accepted (or unchanged) curve and E and the cost decrease (0 if none)."""
    cost0 = _cost(d, w, t, e, curve, prior)
    th0 = _theta_of(curve)
    for frac in (1.0, 0.5, 0.25, 0.125, 0.0625):
        cv = _curve_of(th0 + frac * (theta_new - th0), curve.xk)
        ee = np.maximum(e + frac * (e_new - e), 0.0)
        cost = _cost(d, w, t, ee, cv, prior)
        if cost < cost0:
            return cv, ee, cost0 - cost
    return curve, e, 0.0


# =============================================================================== plain Eq. 6/7


def fit_response_alternating(
    dn: np.ndarray,
    exposure: np.ndarray,
    bits: int,
    *,
    saturation_dn: int | None = None,
    max_pixels: int = 4000,
    seed: int = 0,
) -> ResponseFit:
    """The paper's plain alternation of Eq. 6 and Eq. 7 (``method="alternating"``).

    ``U(k) = mean over Omega_k of t_i E(x)`` (Eq. 6) and ``E(x) = sum_i t_i U(I_i(x)) /
    sum_i t_i^2`` (Eq. 7) over usable samples, from the linear start ``U(k) = k - b`` (b from
    a common-intercept line fit), the scale gauge ``U(k_ref) = k_ref - b`` fixed each
    iteration, unobserved DN interpolated. Converges to a biased fixed point (the noise is
    on I, not on U(I)); kept for reference and comparison.
    """
    return fit_response(
        dn, exposure, bits, method="alternating", saturation_dn=saturation_dn,
        max_pixels=max_pixels, seed=seed,
    )


def _alternating(
    d: np.ndarray,
    m: np.ndarray,
    t: np.ndarray,
    bits: int,
    sat: int,
    observed: tuple[int, int],
    max_iter: int = 500,
    tol: float = 1e-7,
) -> ResponseFit:
    dn_max = 2**bits - 1
    k_ref = dn_max // 2
    lo, hi = observed
    b0, _ = _linear_init(d, m, t, lo, hi)
    di = d.astype(np.intp)
    mf = m.astype(np.float64)
    karr = np.arange(dn_max + 1, dtype=np.float64)
    counts = np.bincount(di[m], minlength=dn_max + 1).astype(np.float64)
    seen = np.flatnonzero(counts > 0)
    U = np.maximum(karr - b0, 0.0)
    tt = (mf * t[:, None] ** 2).sum(0)
    target = k_ref - b0 if k_ref > b0 else 1.0
    it = 0
    for it in range(1, max_iter + 1):
        e = (mf * t[:, None] * U[di]).sum(0) / np.where(tt > 0, tt, 1.0)  # Eq. 7
        x = t[:, None] * e[None, :]
        sums = np.bincount(di[m], x[m], dn_max + 1)
        u_seen = sums[seen] / counts[seen]  # Eq. 6
        U_new = np.interp(karr, seen, u_seen)
        ref = np.interp(k_ref, seen, u_seen)
        if ref <= 0:
            ref = float(U_new.max()) / max(target, 1.0) if U_new.max() > 0 else 1.0
        U_new *= target / ref  # scale gauge
        change = np.max(np.abs(U_new - U)) / max(abs(target), 1.0)
        U = U_new
        if change < tol:
            break
    # monotone (weighted isotonic fit), black level where U crosses 0
    u_seen = _pava(U[seen], counts[seen])
    black = _zero_crossing(seen.astype(np.float64), u_seen)
    pos = seen > black
    xs = np.concatenate([[black], seen[pos]])
    us = np.concatenate([[0.0], np.maximum(u_seen[pos], 0.0)])
    u_raw = np.interp(karr, xs, us)
    U_fin = _finalise(u_raw, black, hi, bits)
    # DN residual of the fixed point, with E in the final gauge
    e = (mf * t[:, None] * U_fin[di]).sum(0) / np.where(tt > 0, tt, 1.0)
    mu = predict_dn(U_fin, t[:, None] * e[None, :])
    rms = float(np.sqrt(np.mean((d - mu)[m] ** 2)))
    return ResponseFit(U_fin, black, sat, observed, rms, "alternating", it, int(m.sum()))


def _zero_crossing(k: np.ndarray, u: np.ndarray) -> float:
    """DN where a monotone U sampled at ``k`` reaches 0 (linear extrapolation of the lowest
    tenth of the samples when U is positive everywhere)."""
    if u[0] <= 0:
        j = int(np.flatnonzero(u <= 0)[-1])
        if j + 1 < u.size and u[j + 1] > u[j]:
            return float(k[j] + (k[j + 1] - k[j]) * (0 - u[j]) / (u[j + 1] - u[j]))
        return float(k[j])
    n = max(2, u.size // 10)
    slope, icpt = np.polyfit(k[:n], u[:n], 1)
    return float(np.clip(-icpt / slope, 0.0, k[0])) if slope > 0 else float(k[0])


# =============================================================================== shared


def _finalise(u_raw: np.ndarray, black: float, hi: int, bits: int) -> np.ndarray:
    """U on every DN: 0 at/below black, ``u_raw`` up to the highest observed DN ``hi``,
    linear extrapolation above it (slope of the top 5 % of the observed range), monotone,
    scaled to the gauge ``U[k_ref] = k_ref - black``."""
    dn_max = 2**bits - 1
    k_ref = dn_max // 2
    if not black < k_ref:
        raise FitError(
            f"estimated black level {black:.1f} DN is above mid-range ({k_ref} DN)",
            hint="the sweep is too dark: add longer exposures or a brighter scene",
        )
    k = np.arange(dn_max + 1, dtype=np.float64)
    u = np.where(k <= black, 0.0, np.maximum(u_raw, 0.0))
    span = max(4, int(0.05 * (hi - black)))
    base = max(hi - span, int(np.floor(black)) + 1)
    if hi < dn_max and hi > base:
        slope = max((u[hi] - u[base]) / (hi - base), 0.0)
        u[hi + 1 :] = u[hi] + slope * (k[hi + 1 :] - hi)
    u = np.maximum.accumulate(u)
    if u[k_ref] <= 0:
        raise FitError("the fitted response is flat at mid-range", hint="check the sweep frames")
    return u * ((k_ref - black) / u[k_ref])


def predict_dn(inverse_response: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """Expected DN for an exposure energy ``x = t E`` in U's units: ``C(x) = U^{-1}(x)``.

    Monotone linear interpolation of the pairs ``(U[k], k)`` (plateaus of U map to their mean
    DN). When U has a zero plateau (U = 0 at/below black), zero energy maps to the black level
    extrapolated from the first two positive values. Clipped to ``[first DN, dn_max]``.
    """
    U = np.asarray(inverse_response, dtype=np.float64)
    k = np.arange(U.size, dtype=np.float64)
    vals, inv = np.unique(U, return_inverse=True)
    kk = np.bincount(inv, k) / np.bincount(inv)
    if vals[0] <= 0 and vals.size >= 3:
        slope = (kk[2] - kk[1]) / (vals[2] - vals[1])
        kk[0] = max(min(kk[1] - slope * vals[1], kk[1]), 0.0)
    x = np.asarray(energy, dtype=np.float64)
    return np.interp(x, vals, kk, left=kk[0], right=k[-1])


def predict_heldout_rms(
    inverse_response: np.ndarray,
    dn_ref: np.ndarray,
    t_ref: float,
    dn_heldout: np.ndarray,
    t_heldout: float,
    *,
    saturation_dn: int | None = None,
) -> float:
    """RMS DN error predicting a held-out frame from a reference frame through U.

    ``predicted = C(U(I_ref) / t_ref * t_heldout)`` (Eq. 4 both ways), compared with the
    held-out DN on pixels unsaturated and unclipped in both frames. Works with any monotone
    U whose scale is arbitrary (e.g. OpenCV's Debevec response column).
    """
    U = np.asarray(inverse_response, dtype=np.float64)
    dn_max = U.size - 1
    sat = dn_max if saturation_dn is None else int(saturation_dn)
    a = np.asarray(dn_ref).astype(np.intp).ravel()
    b = np.asarray(dn_heldout).astype(np.float64).ravel()
    ok = _usable(a, sat, dn_max) & _usable(b.astype(np.intp), sat, dn_max)
    if not ok.any():
        raise FitError("no pixel is unsaturated in both the reference and held-out frame")
    pred = predict_dn(U, U[a[ok]] / t_ref * t_heldout)
    return float(np.sqrt(np.mean((pred - b[ok]) ** 2)))
