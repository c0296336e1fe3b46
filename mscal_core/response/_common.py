"""Pieces every response method shares: the result, the sweep masks and gauge, predicting DN through U."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FitError, InputError

#: Bands with more than this many pixels per ``max_pixels`` are first thinned to a seeded
#: random subset of that many candidates (a 24 Mpx band: 100 000 candidates for 4000 pixels).
CANDIDATES_PER_PIXEL = 25


@dataclass(frozen=True)
class ResponseFit:
    """Result of one band's response fit (Eq. 5-7).

    Attributes
    ----------
    inverse_response : numpy.ndarray
        U(k), ``(2**bits,)`` float64, monotone, in the gauge of the package (``U = 0`` at/below
        black, ``U[k_ref] = k_ref - black``).
    black_level : float
        DN where U = 0.
    saturation_dn : int
        Samples ``>=`` this are saturated.
    observed_dn : tuple of int
        Lowest and highest unsaturated DN used.
    residual_rms_dn : float
        RMS of ``I - C(t E)`` over the samples used (DN).
    method : str
        ``"forward"`` or ``"alternating"``.
    iterations : int
        Iterations run.
    n_samples : int
        Unsaturated samples used.
    residual_by_dn : numpy.ndarray or None
        RMS of ``I - C(t E)`` per DN bin (see :func:`residual_profile`).
    fitted_dn : tuple of int or None
        Lowest and highest DN of the samples the fit used, the highest at most the mean DN of
        the samples of highest energy (the forward fit): the range U was fitted on.
    noise_variance : tuple of float or None
        ``(a, b)`` of the fit's DN noise model ``var(I) = a + b (I - black)`` (read + shot).
    fit_uncertainty : numpy.ndarray or None
        ``(2**bits,)`` relative standard uncertainty of U from the fit alone (how well the
        sweep determines U at each DN); NaN outside ``fitted_dn``.
    uncertainty : numpy.ndarray or None
        ``(2**bits,)`` relative standard uncertainty of U at each DN: ``fit_uncertainty`` and
        one reading's noise through U's slope in quadrature (:func:`response_uncertainty`).
        ``noise_variance``, ``fit_uncertainty`` and ``uncertainty`` are given by the forward
        method only (None for the plain alternation, whose bias is not modelled).
    """

    inverse_response: np.ndarray  # U(k), (2**bits,) float64, monotone, gauge of the module
    black_level: float  # DN where U = 0
    saturation_dn: int  # samples >= this are saturated
    observed_dn: tuple[int, int]  # lowest and highest unsaturated DN used
    residual_rms_dn: float  # rms of I - C(t E) over the samples used (DN)
    method: str  # "forward" or "alternating"
    iterations: int
    n_samples: int  # unsaturated samples used
    residual_by_dn: np.ndarray | None = None  # rms of I - C(t E) per DN bin (see residual_profile)
    fitted_dn: tuple[int, int] | None = None  # lowest and highest DN of the samples used
    noise_variance: tuple[float, float] | None = None  # (a, b): var(I) = a + b (I - black)
    fit_uncertainty: np.ndarray | None = None  # relative std of U from the fit alone, per DN
    uncertainty: np.ndarray | None = None  # relative std of U per DN (response_uncertainty)


RESIDUAL_BINS = 32  # DN bins of ResponseFit.residual_by_dn over 0 .. 2**bits


def residual_profile(dn: np.ndarray, predicted: np.ndarray, used: np.ndarray, bits: int,
                     n_bins: int = RESIDUAL_BINS) -> np.ndarray:
    """Return the RMS of the fit residual ``I - C(t E)`` (Eq. 5) per bin of observed DN.

    Parameters
    ----------
    dn : numpy.ndarray
        Observed DN of the samples.
    predicted : numpy.ndarray
        ``C(t E)`` of the same samples.
    used : numpy.ndarray
        Boolean mask of the samples the fit used.
    bits : int
        Bit depth of the camera.
    n_bins : int
        Equal bins over ``0 .. 2**bits``.

    Returns
    -------
    numpy.ndarray
        ``(n_bins,)`` RMS per bin; NaN for a bin without used samples. Its sample-weighted mean
        square is the square of ``ResponseFit.residual_rms_dn``.
    """
    d = np.asarray(dn, dtype=np.float64)[used]
    r2 = (d - np.asarray(predicted, dtype=np.float64)[used]) ** 2
    k = np.clip((d * n_bins / 2**bits).astype(np.int64), 0, n_bins - 1)
    counts = np.bincount(k, minlength=n_bins)
    sums = np.bincount(k, weights=r2, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)


def validate_samples(dn: np.ndarray, exposure: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes and values; return ``(dn (n_frames, n_pixels), t float64)``.

    Integer ``dn`` is returned as given (no copy: the pipeline passes every pixel of a band,
    e.g. 9 frames x 24 Mpx); integer-valued floats are converted to int32.
    """
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


def _usable(dn: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """Mask the samples that carry information: below saturation and not a clipped value (0, dn_max)."""
    return (dn < saturation_dn) & (dn < dn_max) & (dn > 0)


def usable_sweep(dn: np.ndarray, t: np.ndarray, saturation_dn: int, dn_max: int) -> np.ndarray:
    """Mask the usable samples of a sweep, stopping each pixel at its ceiling.

    :func:`_usable`, also dropping a pixel's samples at exposures >= the shortest one at which
    it has reached its ceiling (see :func:`sweep_masks`).
    """
    return sweep_masks(dn, t, saturation_dn, dn_max)[0]


def sweep_masks(
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


def pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
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


def select_pixels(
    dn: np.ndarray, el: np.ndarray, max_pixels: int, rng: np.random.Generator
) -> np.ndarray:
    """At most ``max_pixels`` of the eligible pixels ``el`` (indices into ``dn``) spanning the brightness range.

    Half evenly spaced in summed DN (a monotone proxy of E), the rest drawn at random.
    """
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


def neighbour_gradient2(dn: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Return the squared local DN gradient of every selected sample.

    Squared local DN gradient ``((I(p+1) - I(p-1)) / 2)^2`` of every sample of the pixels
    ``cols``, from their neighbours in the flattened band: horizontal neighbours of a row-major
    image (a row boundary pairs a row's end with the next row's start). A camera moved by ``s``
    pixels between frames changes a sample by about ``s`` times the gradient
    (:func:`_gradient_noise`).
    """
    n_pix = dn.shape[1]
    left = dn[:, np.maximum(cols - 1, 0)].astype(np.float64)
    right = dn[:, np.minimum(cols + 1, n_pix - 1)].astype(np.float64)
    return ((right - left) / 2.0) ** 2


def linear_init(
    d: np.ndarray, m: np.ndarray, t: np.ndarray, lo: int, hi: int
) -> tuple[float, np.ndarray]:
    """Start the fit from a line ``I = b + t E`` with a common intercept.

    Least-squares start ``I = b + t E`` with a common intercept b (black level guess) on the
    samples in the lower 75 % of the observed DN range (away from the shoulder).

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


def finalise(u_raw: np.ndarray, black: float, hi: int, bits: int) -> np.ndarray:
    """U on every DN.

    0 at/below black, ``u_raw`` up to the highest observed DN ``hi``, linear extrapolation above
    it (slope of the top 5 % of the observed range), monotone, scaled to the gauge
    ``U[k_ref] = k_ref - black``.
    """
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
    """Predict the DN for an exposure energy ``x = t E`` in U's units: ``C(x) = U^{-1}(x)``.

    Parameters
    ----------
    inverse_response : numpy.ndarray
        Monotone U on every DN, ``(2**bits,)``.
    energy : numpy.ndarray
        Exposure energies ``x = t E`` in U's units (any shape).

    Returns
    -------
    numpy.ndarray
        Expected DN (float64, same shape as ``energy``), clipped to ``[first DN, dn_max]``.

    Notes
    -----
    Inverts Eq. 4, ``U(I) = t E``: monotone linear interpolation of the pairs ``(U[k], k)``
    (plateaus of U map to their mean DN). When U has a zero plateau (U = 0 at/below black),
    zero energy maps to the black level extrapolated from the first two positive values.
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
    """Return the RMS DN error predicting a held-out frame from a reference frame through U.

    Parameters
    ----------
    inverse_response : numpy.ndarray
        Any monotone U, ``(2**bits,)``, whose scale is arbitrary (e.g. OpenCV's Debevec
        response column [2]_).
    dn_ref, dn_heldout : numpy.ndarray
        DN of the reference and the held-out frame (same pixels).
    t_ref, t_heldout : float
        Their exposures.
    saturation_dn : int, optional
        Samples ``>=`` this are saturated (default ``dn_max``).

    Returns
    -------
    float
        RMS of ``predicted - dn_heldout`` (DN) on pixels unsaturated and unclipped in both frames.

    Raises
    ------
    FitError
        When no pixel is unsaturated in both frames.

    Notes
    -----
    ``predicted = C(U(I_ref) / t_ref * t_heldout)``: Eq. 4, ``U(I) = t E``, both ways [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    .. [2] P. E. Debevec and J. Malik, "Recovering High Dynamic Range Radiance Maps from
           Photographs", Proc. SIGGRAPH 1997.
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
