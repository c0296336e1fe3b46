"""The paper's plain alternation of Eq. 6 and Eq. 7 (``method="alternating"``), kept for reference."""

from __future__ import annotations

import numpy as np

from ._common import ResponseFit, finalise, linear_init, pava, predict_dn, residual_profile


def alternating_fit(
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
    b0, _ = linear_init(d, m, t, lo, hi)
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
    u_seen = pava(U[seen], counts[seen])
    black = _zero_crossing(seen.astype(np.float64), u_seen)
    pos = seen > black
    xs = np.concatenate([[black], seen[pos]])
    us = np.concatenate([[0.0], np.maximum(u_seen[pos], 0.0)])
    u_raw = np.interp(karr, xs, us)
    U_fin = finalise(u_raw, black, hi, bits)
    # DN residual of the fixed point, with E in the final gauge
    e = (mf * t[:, None] * U_fin[di]).sum(0) / np.where(tt > 0, tt, 1.0)
    mu = predict_dn(U_fin, t[:, None] * e[None, :])
    rms = float(np.sqrt(np.mean((d - mu)[m] ** 2)))
    # no uncertainty: the plain alternation's bias (PAPER.md) is not modelled, and a noise-only
    # figure would claim more than the fit can back
    return ResponseFit(U_fin, black, sat, observed, rms, "alternating", it, int(m.sum()),
                       residual_profile(d, mu, m, bits), (int(d[m].min()), int(d[m].max())))


def _zero_crossing(k: np.ndarray, u: np.ndarray) -> float:
    """Return the DN where a monotone U reaches 0.

    DN where a monotone U sampled at ``k`` reaches 0 (linear extrapolation of the lowest tenth
    of the samples when U is positive everywhere).
    """
    if u[0] <= 0:
        j = int(np.flatnonzero(u <= 0)[-1])
        if j + 1 < u.size and u[j + 1] > u[j]:
            return float(k[j] + (k[j + 1] - k[j]) * (0 - u[j]) / (u[j + 1] - u[j]))
        return float(k[j])
    n = max(2, u.size // 10)
    slope, icpt = np.polyfit(k[:n], u[:n], 1)
    return float(np.clip(-icpt / slope, 0.0, k[0])) if slope > 0 else float(k[0])
