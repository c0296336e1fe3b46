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
``>= 0``, knots at even DN steps, a smoothness prior) and ``E`` per pixel by weighted least
squares on the DN:

    M(C, E) = sum_i sum_x w_ix (I_i(x) - C(t_i E(x)))^2 + censored terms + prior(C),
    w = rho_ix / var_ix,  var = a + b (C(t_i E(x)) - black) + c g_ix^2

Each iteration takes (b) the C update given E, the errors-in-DN analogue of Eq. 6, which is
a bounded linear least-squares problem because C is linear in its parameters, jointly with
(a) the E update of every pixel linearised (the Eq. 7 analogue), E eliminated through its
Schur complement (a Gauss-Newton step on both, with backtracking), then a per-pixel
Gauss-Newton step on E alone. Finally ``U = C^{-1}`` on the DN grid; ``C(0)`` is the
estimated black level, so ``U = 0`` there.

Photographs (8-bit JPEG brackets, handheld) break the clean-sweep assumptions of Eq. 5 in
ways the fit handles explicitly (measured on ``mscal_core.synth.photo``):

- noise model ``var``: read + shot noise ``a + b mu`` plus ``c g^2``, ``g`` the sample's local
  DN gradient (neighbours in the band): a camera shifted by ``s`` pixels between frames moves
  a sample by about ``s g``, so ``c`` (a mean squared shift, 0 on a tripod) is estimated
  from the residuals and edges weigh less where the frames are misaligned; ``a, b, c`` from
  robust (median) binned squared residuals, leverage corrected;
- outliers ``rho``: samples more than 3 standard deviations off the curve taper to weight 0
  at 6 (moving things, parallax, JPEG ringing); Gaussian noise keeps full weight;
- ceilings: a pixel's samples from its first saturated exposure on, or from a value in the
  upper half that a clearly longer exposure does not exceed (stuck below the clip: a colour
  channel clipped before the camera's colour matrix), are not points of the curve;
- censoring: DN 0 (where the neighbours are dark too: a 0 next to an edge is more often a
  shifted edge or a colour-matrix / chroma artefact) and a pixel's first saturated sample
  are censored observations (Tobit terms ``-2 log Phi``, as Newton pseudo-observations), not
  dropped: dropping them keeps only the noise draws that stayed inside the range, biased
  towards mid-range (a black level above 0 and a too flat shoulder);
- hidden saturation: in JPEG photographs a blown highlight is partly 245-254 (ringing);
  where such samples are common the top of U follows the paper's Eq. 6 in the log domain
  (:func:`_hidden_saturation_top`);
- prior: second differences of ``log C'`` against ``log x`` with the best power law projected
  out (every gamma curve and the linear sensor are free), weighted adaptively: the exposure
  ratios of a bracket are powers of one step, which leaves U determined by the data only
  up to a factor periodic in ``log x`` with that step (:func:`exposure_period`), so the
  weight grows with the step squared (2 frames 4 stops apart need a strong prior) and with
  the cube of the robust noise relative to the DN range (misfit of JPEG, sharpening and
  misalignment is absorbed by the prior rather than by wiggles of C).

Large bands (the pipeline passes every pixel, e.g. 9 frames x 24 Mpx) are thinned to a seeded
random subset of candidate pixels before anything else: no full-size temporaries or copies.

Gauge (docs/architecture.md): ``U[k] = 0`` at/below black, ``U[k_ref] = k_ref - black`` with
``k_ref = dn_max // 2``. Saturated (``>= saturation_dn``, default ``dn_max``) and clipped
(``0``) samples enter only as censored terms; DN never observed are filled monotonically
(linear extrapolation above the highest observed DN).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import lsq_linear
from scipy.special import log_ndtr

from .errors import FitError, InputError

METHODS = ("forward", "alternating")
PRIORS = ("adaptive", "loglog", "linear")

#: Bands with more than this many pixels per ``max_pixels`` are first thinned to a seeded
#: random subset of that many candidates (a 24 Mpx band: 100 000 candidates for 4000 pixels).
CANDIDATES_PER_PIXEL = 25


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
    residual_by_dn: np.ndarray | None = None  # rms of I - C(t E) per DN bin (see residual_profile)


RESIDUAL_BINS = 32  # DN bins of ResponseFit.residual_by_dn over 0 .. 2**bits


def residual_profile(dn: np.ndarray, predicted: np.ndarray, used: np.ndarray, bits: int,
                     n_bins: int = RESIDUAL_BINS) -> np.ndarray:
    """RMS of the fit residual ``I - C(t E)`` (Eq. 5) per bin of observed DN.

    ``n_bins`` equal bins over ``0 .. 2**bits``; NaN for a bin without used samples. Its
    sample-weighted mean square is the square of ``ResponseFit.residual_rms_dn``.
    """
    d = np.asarray(dn, dtype=np.float64)[used]
    r2 = (d - np.asarray(predicted, dtype=np.float64)[used]) ** 2
    k = np.clip((d * n_bins / 2**bits).astype(np.int64), 0, n_bins - 1)
    counts = np.bincount(k, minlength=n_bins)
    sums = np.bincount(k, weights=r2, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)


# =============================================================================== validation


def _validate(dn: np.ndarray, exposure: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes and values; return ``(dn (n_frames, n_pixels), t float64)``.

    Integer ``dn`` is returned as given (no copy: the pipeline passes every pixel of a band,
    e.g. 9 frames x 24 Mpx); integer-valued floats are converted to int32."""
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
    lo, hi = dn.min(), dn.max()
    if lo < 0 or hi > dn_max:
        raise InputError(
            f"DN outside 0..{dn_max} for a {bits}-bit camera (range {lo}..{hi}); "
            "check the camera's bit depth"
        )
    if not np.issubdtype(dn.dtype, np.integer):
        dn = dn.astype(np.int32)
    return dn, t


#: Frames larger than this are subsampled (evenly strided) for the per-frame median of
#: :func:`check_exposure_consistency`.
_MEDIAN_PIXELS = 1 << 18


def _usable(dn: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """Samples that carry information: below saturation and not a clipped value (0, dn_max)."""
    return (dn < saturation_dn) & (dn < dn_max) & (dn > 0)


def _usable_sweep(dn: np.ndarray, t: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """:func:`_usable`, also dropping a pixel's samples at exposures >= the shortest one at
    which it has reached its ceiling (see :func:`_sweep_masks`)."""
    return _sweep_masks(dn, t, saturation_dn, dn_max)[0]


def _sweep_masks(
    dn: np.ndarray, t: np.ndarray, saturation_dn: int, dn_max: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(usable, censored_low, censored_high)`` masks of a sweep's samples.

    A pixel's samples at exposures >= the shortest one at which it reached its ceiling are
    not usable:

    - saturated (``>= saturation_dn`` or ``dn_max``): noise (or JPEG ringing) can pull a
      saturated pixel just below the clip at longer exposures;
    - or, in the upper half of the range, not exceeded by a clearly longer exposure
      (``>= 1.25 t``) of the same pixel: a value stuck below the clip (one colour channel
      clipped before the colour matrix of a camera, highlight compression, a pixel that
      changed) is not a point of the response curve.

    Of the others, DN ``0`` samples are censored low (the signal was <= 0.5 DN) and the
    samples at a pixel's first saturated exposure censored high (>= saturation - 0.5), if
    the pixel stopped by saturating: dropping them would leave only the noise draws that
    stayed inside the range near 0 and near the clip, biased towards the middle.
    """
    n = t.size
    order = np.argsort(t, kind="stable")
    ts = t[order]
    d = dn[order]
    sat = (d >= saturation_dn) | (d >= dn_max)
    stop = sat.copy()
    if n > 1:
        suffix_min = np.minimum.accumulate(d[::-1], axis=0)[::-1]
        first_longer = np.searchsorted(ts, 1.25 * ts, side="left")
        half = (dn_max + 1) // 2
        for i in range(n):
            k = int(first_longer[i])
            if k < n:
                stop[i] |= (d[i] >= half) & (suffix_min[k] <= d[i])
    any_stop, any_sat = stop.any(axis=0), sat.any(axis=0)
    t_stop = np.where(any_stop, ts[np.argmax(stop, axis=0)], np.inf)
    t_sat = np.where(any_sat, ts[np.argmax(sat, axis=0)], np.inf)
    before = t[:, None] < t_stop[None, :]
    usable = _usable(dn, saturation_dn, dn_max) & before
    low = (dn == 0) & before
    high = ((dn >= saturation_dn) | (dn >= dn_max)) & (t[:, None] == t_stop[None, :]) & (
        t_sat == t_stop)[None, :]
    return usable, low, high


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
    med = _frame_medians(dn)
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


def _frame_medians(dn: np.ndarray) -> np.ndarray:
    """Median DN of every frame; on an evenly strided subsample of at most about
    ``_MEDIAN_PIXELS`` pixels for large frames (no sorted copy of a whole band)."""
    step = max(1, -(-dn.shape[1] // _MEDIAN_PIXELS))
    return np.median(dn[:, ::step], axis=1).astype(np.float64)


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
    dn: np.ndarray, el: np.ndarray, max_pixels: int, rng: np.random.Generator
) -> np.ndarray:
    """At most ``max_pixels`` of the eligible pixels ``el`` (indices into ``dn``) spanning
    the brightness range: half evenly spaced in summed DN (a monotone proxy of E), the rest
    drawn at random."""
    if el.size <= max_pixels:
        return el
    proxy = dn[:, el].sum(axis=0, dtype=np.int64).astype(np.float64)
    order = np.argsort(proxy, kind="stable")
    targets = np.linspace(proxy[order[0]], proxy[order[-1]], max_pixels // 2)
    pos = np.clip(np.searchsorted(proxy[order], targets), 0, order.size - 1)
    spread = np.unique(order[pos])
    rest = np.setdiff1d(np.arange(el.size), spread, assume_unique=True)
    extra = rng.choice(rest, size=max_pixels - spread.size, replace=False)
    return np.sort(el[np.concatenate([spread, extra])])


def _neighbour_gradient2(dn: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Squared local DN gradient ``((I(p+1) - I(p-1)) / 2)^2`` of every sample of the pixels
    ``cols``, from their neighbours in the flattened band: horizontal neighbours of a
    row-major image (a row boundary pairs a row's end with the next row's start). A camera
    moved by ``s`` pixels between frames changes a sample by about ``s`` times the gradient
    (:func:`_gradient_noise`)."""
    n_pix = dn.shape[1]
    left = dn[:, np.maximum(cols - 1, 0)].astype(np.float64)
    right = dn[:, np.minimum(cols + 1, n_pix - 1)].astype(np.float64)
    return ((right - left) / 2.0) ** 2


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


def _prior(xk: np.ndarray, seg_weight: float, total_weight: float, smoothness: float,
           slopes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic prior ``theta' P theta - 2 p' theta`` on ``theta = [C(0), s_0 .. s_{K-1}]``:

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


def _noise_model(r: np.ndarray, mu: np.ndarray, leverage: np.ndarray, floor: float,
                 robust: bool = False, offset: np.ndarray | None = None) -> tuple[float, float]:
    """Fit ``var(I) = a + b * mu`` (read + shot noise, ``mu = C - black``) to the squared
    residuals, each divided by ``1 - leverage`` (the share of the sample's noise absorbed by
    its pixel's fitted E), less a known ``offset`` (the gradient term), averaged in 16
    quantile bins of mu (``robust``: median / 0.4549, so outliers do not inflate it); two
    weighted passes, ``a >= floor``."""
    keep = leverage < 0.9
    r2 = r[keep] ** 2 / (1.0 - leverage[keep])
    if offset is not None:  # a known part of the variance (gradient term)
        r2 = np.maximum(r2 - offset[keep], 0.0)
    mu = mu[keep]
    if r2.size < 10:
        return max(float(np.mean(r ** 2)) if r.size else 1.0, floor), 0.0
    edges = np.unique(np.quantile(mu, np.linspace(0, 1, 17)))
    if edges.size < 3:
        return max(float(r2.mean()), floor), 0.0
    k = np.clip(np.searchsorted(edges, mu, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1).astype(np.float64)
    ok = cnt > 0
    if robust:  # median / 0.4549 (median of chi2_1): outliers do not inflate the scale
        srt = np.lexsort((r2, k))
        rs = r2[srt]
        starts = np.concatenate([[0], np.cumsum(cnt.astype(np.intp))])
        mid_lo = starts[:-1] + (cnt.astype(np.intp) - 1) // 2
        mid_hi = starts[:-1] + cnt.astype(np.intp) // 2
        top = rs.size - 1
        med = np.where(ok, 0.5 * (rs[np.minimum(mid_lo, top)] + rs[np.minimum(mid_hi, top)]), 0.0)
        mv = med[ok] / 0.4549
    else:
        mv = np.bincount(k, r2, edges.size - 1)[ok] / cnt[ok]
    mm = np.bincount(k, mu, edges.size - 1)[ok] / cnt[ok]
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
    smoothness: float = 0.025,
    max_iter: int = 60,
    tol: float = 1e-4,
    robust: bool = True,
    prior: str = "adaptive",
    gradient_noise: bool = True,
    censored: bool = True,
) -> ResponseFit:
    """Fit the inverse response U of one band from a sweep (Eq. 5-7).

    ``dn`` ``(n_frames, n_pixels)`` integer samples of a static scene (any integer dtype; not
    copied), ``exposure`` ``(n_frames,)`` effective exposures (ms * gain). ``method="forward"``
    (default) fits the forward response with the noise on the DN (see module docstring),
    iterating

    - (a) ``E(x) = argmin_E sum_i w (I_i(x) - C(t_i E))^2`` (Gauss-Newton; Eq. 7 analogue),
    - (b) ``C = argmin_C sum_{i,x} w (I_i(x) - C(t_i E(x)))^2 + prior``, C monotone
      (Eq. 6 analogue), taken jointly with a linearised (a),

    ``w`` = robust weight / noise variance, re-estimated from the residuals (first 7
    iterations), until U changes by less than ``tol`` (relative to U at mid-range) or
    ``max_iter``. ``method="alternating"`` runs the paper's plain Eq. 6/7
    (:func:`fit_response_alternating`). Pixels (at most ``max_pixels``, half evenly spread
    over the brightness range, the rest drawn with ``seed``; from at most
    ``CANDIDATES_PER_PIXEL * max_pixels`` random candidates) with >= 2 usable samples are
    used.

    Options of the forward fit (defaults: all on, measured best on photographs and on
    10-bit sweeps): ``robust`` outlier weights; ``gradient_noise`` the misalignment term
    ``c g^2`` of the noise; ``censored`` DN 0 / first saturated samples as censored terms;
    ``prior`` ``"adaptive"`` (log-log smoothness weighted by noise and exposure step),
    ``"loglog"`` (fixed weight) or ``"linear"`` (second differences of C, the previous
    default, with ``smoothness=0.05``). ``smoothness`` weighs the prior against one knot
    segment's data (``"adaptive"``: at 0.5 % noise and 1-stop steps).

    Raises ``InputError`` on bad shapes or non-positive exposures, ``FitError`` on fewer than
    2 distinct exposures, frames whose brightness contradicts their exposure
    (:func:`check_exposure_consistency`), or no unsaturated samples.
    """
    if method not in METHODS:
        raise InputError(f"unknown response method {method!r}; use one of {', '.join(METHODS)}")
    if prior not in PRIORS:
        raise InputError(f"unknown response prior {prior!r}; use one of {', '.join(PRIORS)}")
    d_all, t = _validate(dn, exposure, bits)
    dn_max = 2**bits - 1
    sat = dn_max if saturation_dn is None else int(saturation_dn)
    if not 1 <= sat <= dn_max:
        raise InputError(f"saturation_dn must be in 1..{dn_max}, got {saturation_dn}")
    _check_sweep(d_all, t, bits)
    # large bands: a seeded random subset of candidate pixels (no full-size temporaries)
    rng = np.random.default_rng(seed)
    n_pix = d_all.shape[1]
    cand = None
    if n_pix > CANDIDATES_PER_PIXEL * max_pixels:
        cand = np.unique(rng.integers(0, n_pix, CANDIDATES_PER_PIXEL * max_pixels))
    sub = d_all if cand is None else d_all[:, cand]
    usable = _usable_sweep(sub, t, sat, dn_max)
    if not usable.any():
        raise FitError(
            "no unsaturated samples in the sweep: every DN is 0 or saturated",
            hint="add shorter exposures (or check the saturation level)",
        )
    observed = (int(sub.min(where=usable, initial=dn_max)), int(sub.max(where=usable, initial=0)))
    el = np.flatnonzero(np.count_nonzero(usable, axis=0) >= 2)
    cols = _select_pixels(d_all, el if cand is None else cand[el], max_pixels, rng)
    if cols.size == 0:
        raise FitError(
            "no pixel has unsaturated samples in 2 or more frames",
            hint="add exposures so that each brightness is seen unsaturated at least twice",
        )
    sel = d_all[:, cols]
    m, cen_lo, cen_hi = _sweep_masks(sel, t, sat, dn_max)
    grad2 = _neighbour_gradient2(d_all, cols)
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
        return _alternating(d, m, t, bits, sat, observed)
    return _forward(d, m, t, bits, sat, observed, smoothness, max_iter, tol, robust, prior, g2,
                    (cen_lo, cen_hi) if censored else None)


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


#: Adaptive prior weight (see :func:`fit_response`): ``smoothness * (sigma / SIGMA_REF)^SIGMA_POW
#: * (period / PERIOD_REF)^PERIOD_POW`` with ``sigma`` the robust DN noise relative to the DN
#: range and ``period`` the exposure step (:func:`exposure_period`, natural log).
SIGMA_REF = 0.005
SIGMA_POW = 3.0
SIGMA_MAX = 0.08  # noise factor at most (0.08 / 0.005)^3 = 4096
ADAPT_FROM = 3  # iterations with the base weight (times the period factor) first
PERIOD_REF = float(np.log(2.0))
PERIOD_POW = 2.0


def exposure_period(exposure: np.ndarray, tol: float = 0.2) -> float:
    """The exposure step of a sweep, ``log`` of the ratio: the largest ``g`` such that every
    step between consecutive distinct exposures is (within ``tol`` of) a whole multiple of
    ``g``. Brackets are geometric (1/1000, 1/500, ... or third stops), so every exposure
    ratio is a power of the step; U is then determined by the data only up to a factor that
    is periodic in ``log x`` with this period, which the prior must resolve."""
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
    robust: bool = True,
    prior: str = "adaptive",
    g2: np.ndarray | None = None,
    cen: tuple[np.ndarray, np.ndarray] | None = None,
) -> ResponseFit:
    """The errors-in-DN fit of :func:`fit_response` on the selected samples ``d[m]``
    (and the censored samples ``cen = (low, high)``, see :func:`_censored_terms`)."""
    dn_max = 2**bits - 1
    lo, hi = observed
    n_seg = int(np.clip((hi - lo) // 4, 4, 64))
    b0, e = _linear_init(d, m, t, lo, hi)
    xk = np.linspace(0.0, max(hi - b0, 1.0), n_seg + 1)
    curve = _Curve(xk=xk, c=b0 + xk)
    mf = m.astype(np.float64)
    rob = np.ones_like(mf)
    period = exposure_period(t)
    a_var, b_var, c_var = 1.0, 0.0, 0.0
    g2 = np.zeros_like(mf) if g2 is None else g2
    s_min = 1e-4
    grid = np.linspace(lo, lo + 0.95 * (hi - lo), 129)  # convergence: U relative to mid-range
    prev_u = _relative_u(curve, grid)
    reknot_at = (1, 3, 6)
    settle = 7  # last re-knot / noise-model update; weights frozen afterwards
    it = 0
    dw = d  # working samples: observed, and censored ones as pseudo-observations
    for it in range(1, max_iter + 1):
        if it in reknot_at:
            curve, e = _reknot(curve, e, t, m, hi, n_seg)
        if it <= settle:
            mu, _ = curve(t[:, None] * e[None, :])
            var = a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + c_var * g2
            w = w_obs = mf * rob / var
            sm = smoothness
            if prior == "adaptive":
                # the noise factor only once the curve has been fitted (a first curve far off
                # inflates the noise, whose prior would then freeze it), and bounded
                sigma_rel = SIGMA_REF
                if it > ADAPT_FROM:
                    span = max(hi - curve.c[0], 1.0)
                    sigma_rel = min(float(np.sqrt(var[m & (rob > 0)].mean())) / span, SIGMA_MAX)
                sm = (smoothness * (sigma_rel / SIGMA_REF) ** SIGMA_POW
                      * (period / PERIOD_REF) ** PERIOD_POW)
            quad = _prior(curve.xk, w.sum() / n_seg, w.sum(), sm,
                          None if prior == "linear" else curve.slopes)
        noise = (a_var, b_var, c_var * g2)
        if cen is not None and it >= 2:  # refreshed every iteration (a Newton step on them)
            dw, wc = _censored_terms(d, cen, t, e, curve, noise, sat)
            w = w_obs + wc * rob
        theta_new, e_new = _joint_step(dw, w, t, e, curve, quad, s_min)
        curve, e, gain = _line_search(dw, w, t, e, curve, quad, theta_new, e_new)
        if gain == 0.0:  # Gauss-Newton stalled on a kink: an exact block step on C instead
            theta_new, e_new = _joint_step(dw, w, t, e, curve, quad, s_min, joint=False)
            curve, e, gain = _line_search(dw, w, t, e, curve, quad, theta_new, e_new)
        e = _fit_energy(dw, w, t, e, curve, steps=1)
        if it <= 3 or it in (5, settle):
            a_var, b_var, c_var = _noise_update(d, m, w, t, e, curve, robust, g2)
            noise = (a_var, b_var, c_var * g2)
            if robust and it >= 3:
                rob = _outlier_weights(d, m, w, t, e, curve, a_var, b_var, noise[2])
                if cen is not None:  # a censored sample deep on the wrong side is an outlier
                    rob = np.maximum(rob, _censored_outlier_weights(cen, t, e, curve, noise, sat))
        u = _relative_u(curve, grid)
        change = float(np.max(np.abs(u - prev_u)))
        prev_u = u
        # stop on a small change of U, or once the cost decrease is far below the noise
        if it > settle and (change < tol or gain < 2e-5 * float(mf.sum())):
            break
    black = float(curve.c[0])
    u_raw = curve.inverse(np.arange(dn_max + 1, dtype=np.float64))
    if robust:
        noise = (a_var, b_var, c_var * g2)
        u_raw = _hidden_saturation_top(u_raw, d, t, e, curve, noise, sat, lo, hi)
    U = _finalise(u_raw, black, hi, bits)
    mu, _ = curve(t[:, None] * e[None, :])
    rms = float(np.sqrt(np.mean((d - mu)[m] ** 2)))
    return ResponseFit(U, black, sat, observed, rms, "forward", it, int(m.sum()), residual_profile(d, mu, m, bits))


#: DN-0 samples are censored only where the local gradient (:func:`_neighbour_gradient2`)
#: is at most this many DN; elsewhere they are dropped.
CENSOR_LOW_MAX_GRADIENT = 1.0

#: Top of U from Eq. 6 where saturated pixels hide below the clip: DN in the upper
#: ``1 - HIDDEN_FROM`` of the observed range where at least ``HIDDEN_FRACTION`` of the
#: samples come from pixels the fit puts clearly (3 sd) above the clip.
HIDDEN_FROM = 0.95
HIDDEN_FRACTION = 0.1


def _hidden_saturation_top(
    u_raw: np.ndarray, d: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
    noise: tuple[float, float, np.ndarray], sat: int, lo: int, hi: int,
) -> np.ndarray:
    """Raise the top of ``u_raw = C^{-1}`` to the paper's Eq. 6, in the log domain,
    ``log U(k) = mean_{(i,x) in Omega_k} log(t_i E(x))``, at the DN ``k`` where saturated
    pixels hide below the clip.

    In JPEG photographs a blown highlight is not all 255: ringing of the compression (and
    sharpening) spreads 245-254 into it. The curve fit rightly treats those samples as
    outliers (their pixel's E puts them far above the clip), so ``C^{-1}(k)`` describes only
    the pixels really at ``k``; but a DN of 250 then more often than not means "saturated",
    and U used to predict or to linearise such a pixel should say so. Where at least
    ``HIDDEN_FRACTION`` of the samples at ``k`` (in the upper part of the range) come from
    pixels with ``C(t E) > sat - 0.5 + 3 sd``, U(k) becomes the larger of the two (then
    monotone). Clean sweeps (no hidden saturation) are unchanged."""
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


def _censored_terms(
    d: np.ndarray, cen: tuple[np.ndarray, np.ndarray], t: np.ndarray, e: np.ndarray,
    curve: _Curve, noise: tuple[float, float, np.ndarray], sat: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Censored (Tobit) samples as weighted pseudo-observations: a sample censored low (DN
    0: the signal was below ``0.5``) or high (first saturated exposure: above ``sat - 0.5``)
    adds ``-2 log Phi(z)``, ``z = s (mu - bound) / sd`` (``s = -1`` low, ``+1`` high,
    ``mu = C(t E)``), to the cost. Its Newton quadratic at the current ``mu`` is
    ``w (y - mu)^2`` with ``w = lam (z + lam) / sd^2`` and ``y = mu + s sd / (z + lam)``,
    ``lam = phi(z) / Phi(z)``: a sample far inside its allowed side weighs nothing, one on
    the wrong side acts like an observation at the bound. Returns ``(samples, weights)`` with
    ``d`` elsewhere and weight 0 there."""
    low, high = cen
    a_var, b_var, extra = noise
    mu, _ = curve(t[:, None] * e[None, :])
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


def _censored_outlier_weights(
    cen: tuple[np.ndarray, np.ndarray], t: np.ndarray, e: np.ndarray, curve: _Curve,
    noise: tuple[float, float, np.ndarray], sat: int,
) -> np.ndarray:
    """Robust weights (``OUTLIER_Z`` taper) of the censored samples from how far the curve
    puts them on the wrong side of their bound, in noise standard deviations; 0 elsewhere."""
    low, high = cen
    z0, z1 = OUTLIER_Z
    a_var, b_var, extra = noise
    mu, _ = curve(t[:, None] * e[None, :])
    sd = np.sqrt(a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra)
    deficit = np.where(low, (mu - 0.5) / sd, np.where(high, (sat - 0.5 - mu) / sd, 0.0))
    u = np.clip((deficit - z0) / (z1 - z0), 0.0, 1.0)
    return np.where(low | high, (1.0 - u * u) ** 2, 0.0)


def _log_phi(a: np.ndarray) -> np.ndarray:
    """Log of the standard normal density."""
    return -0.5 * a * a - 0.5 * np.log(2 * np.pi)


def _relative_u(curve: _Curve, grid: np.ndarray) -> np.ndarray:
    """``C^{-1}`` on a DN grid relative to its value at the grid's middle (gauge-free)."""
    u = curve.inverse(grid)
    return u / max(float(u[grid.size // 2]), 1e-300)


def _leverage(w: np.ndarray, t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Leverage of every sample on its pixel's E: ``w J^2 / sum_i w J^2``, ``J = t C'(t E)``."""
    wj2 = w * (t[:, None] * s) ** 2
    return wj2 / np.maximum(wj2.sum(0), 1e-300)


def _noise_update(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
    robust: bool = False, g2: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """Re-estimate the DN noise model ``var = a + b mu + c g2`` from the residuals (see
    :func:`_noise_model`; ``c = 0`` without ``g2``)."""
    mu, s = curve(t[:, None] * e[None, :])
    lev = _leverage(w, t, s)
    r, above = (d - mu)[m], np.maximum(mu - curve.c[0], 0.0)[m]
    if g2 is None or not np.any(g2[m] > 0):
        return (*_noise_model(r, above, lev[m], 1 / 12, robust), 0.0)
    gm = g2[m]
    a, b, c = 1.0, 0.0, 0.0
    for _ in range(2):
        a, b = _noise_model(r, above, lev[m], 1 / 12, robust, offset=c * gm)
        c = _gradient_noise(r, lev[m], a + b * above, gm)
    return a, b, c


def _gradient_noise(r: np.ndarray, leverage: np.ndarray, base: np.ndarray, g2: np.ndarray) -> float:
    """``c >= 0`` in ``var = base + c g2``: the squared residuals in 8 quantile bins of the
    squared local DN gradient ``g2``, robust (median / 0.4549) minus the mean ``base`` of
    the bin, regressed on the bin's mean ``g2`` (weights: counts / variance^2). ``c`` is
    the mean squared shift (pixels^2) of a scene between frames: 0 on a tripod."""
    keep = leverage < 0.9
    r2 = r[keep] ** 2 / (1.0 - leverage[keep])
    g2, base = g2[keep], base[keep]
    edges = np.unique(np.quantile(g2, np.linspace(0, 1, 9)))
    if edges.size < 3 or r2.size < 64:
        return 0.0
    k = np.clip(np.searchsorted(edges, g2, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    ok = cnt > 0
    srt = np.lexsort((r2, k))
    starts = np.concatenate([[0], np.cumsum(cnt)])[:-1]
    med = r2[srt][np.minimum(starts + cnt // 2, r2.size - 1)] / 0.4549
    gmean = np.bincount(k, g2, edges.size - 1)[ok] / cnt[ok]
    excess = med[ok] - np.bincount(k, base, edges.size - 1)[ok] / cnt[ok]
    wts = cnt[ok] / np.maximum(med[ok], 1e-6) ** 2
    c = float(np.sum(wts * gmean * excess) / max(float(np.sum(wts * gmean * gmean)), 1e-300))
    return max(c, 0.0)


#: Outlier weights: 1 up to ``OUTLIER_Z[0]`` standard deviations, tapering (biweight) to 0
#: at ``OUTLIER_Z[1]``.
OUTLIER_Z = (3.0, 6.0)


def _outlier_weights(
    d: np.ndarray, m: np.ndarray, w: np.ndarray, t: np.ndarray, e: np.ndarray, curve: _Curve,
    a_var: float, b_var: float, extra: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Robust weights of the standardised residuals ``z = (I - C(t E)) / sqrt(var (1 -
    leverage))``: 1 for ``|z| <= z0``, ``(1 - ((|z| - z0) / (z1 - z0))^2)^2`` up to ``z1``,
    0 beyond (``OUTLIER_Z``). Samples a moving object, a shifted edge or a compression
    artefact put far off the curve stop pulling on it, while Gaussian noise keeps full
    weight (efficiency on clean sweeps is that of plain least squares).

    ``var`` is the larger of the noise model ``a + b mu`` and a local robust variance (median
    of the squared residuals in 16 quantile bins of the expected DN, / 0.4549): where the
    current curve is still off in some DN range, its samples are not all rejected at once
    (which would leave that range to the prior)."""
    z0, z1 = OUTLIER_Z
    mu, s = curve(t[:, None] * e[None, :])
    lev = np.minimum(_leverage(w, t, s), 0.9)
    r2 = (d - mu) ** 2 / (1.0 - lev)
    var = a_var + b_var * np.maximum(mu - curve.c[0], 0.0) + extra
    mu_m, r2_m = mu[m], r2[m]
    if mu_m.size >= 64:
        edges = np.unique(np.quantile(mu_m, np.linspace(0, 1, 17)))
        if edges.size >= 3:
            k = np.clip(np.searchsorted(edges, mu_m, side="right") - 1, 0, edges.size - 2)
            srt = np.lexsort((r2_m, k))
            cnt = np.bincount(k, minlength=edges.size - 1)
            starts = np.concatenate([[0], np.cumsum(cnt)])[:-1]
            ok = cnt > 0
            med = r2_m[srt][np.minimum(starts + cnt // 2, r2_m.size - 1)][ok] / 0.4549
            centre = (np.bincount(k, mu_m, edges.size - 1)[ok] / cnt[ok])
            var = np.maximum(var, np.interp(mu, centre, med))
    z = np.sqrt(r2 / var)
    u = np.clip((z - z0) / (z1 - z0), 0.0, 1.0)
    return np.where(m, (1.0 - u * u) ** 2, 0.0)


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
    return ResponseFit(U_fin, black, sat, observed, rms, "alternating", it, int(m.sum()),
                       residual_profile(d, mu, m, bits))


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
