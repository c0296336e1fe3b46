"""Per-pixel quality of Eq. 15 reflectance: which pixels to trust (no I/O).

Eq. 15, ``R = U(I) / (t V S B)``, is only as good as its parts at each pixel: U where the
response was fitted and is well determined, V where the vignetting was observed. A pixel whose
DN lies on the response's shoulder (U steep and poorly determined near the clip), outside the
DN range the response sweep covered, or where no view observed the vignetting, gets a value
that nothing marks. This module gives each such pixel a bit of a uint8 mask (0 = trusted;
:data:`FLAGS`), folded into tables the way :func:`mscal_core.reflectance.eq15_fast` folds
saturation: a uint8 flag per band and DN (:func:`dn_flag_table`), a uint8 flag per band and
pixel (:func:`pixel_flag_table`), NaN in the reflectance tables where flagged
(:func:`mask_tables`), so a frame costs one uint8 lookup per pixel (:func:`frame_flags`).

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

import cv2
import numpy as np

from .errors import InputError

__all__ = [
    "CENSOR_HIGH", "CENSOR_LOW", "DEFAULT_BOUND", "DEFAULT_FIT_BOUND", "FLAGS", "MAX_FLAGGED_SHARE", "dn_flag_table", "flag_counts", "frame_flags",
    "censor_dn", "mask_tables", "pixel_flag_table", "region_median", "shoulder_mask",
]

#: The bits of the quality mask, in bit order (CF ``flag_masks`` / ``flag_meanings``).
FLAGS = {
    "saturated": 1,  # DN >= the clip
    "response_shoulder": 2,  # relative uncertainty of U(DN) above the bound
    "outside_sweep": 4,  # DN outside the range the response sweep covered
    "vignetting_unobserved": 8,  # no view observed V at the pixel
    "not_coregistered": 16,  # the band failed the co-registration check of the frame
    "no_value": 32,  # NaN for any other reason
    "below_sweep": 64,  # with outside_sweep: the DN is under the sweep's range, its value below the trusted
}

#: The flags that censor a pixel from above: its true value lies above those of the region's
#: valid pixels (it read at or beyond the top of what U is trusted for), so a region's median
#: counts it as +inf (:func:`region_median`), unless it carries :data:`CENSOR_LOW` too.
CENSOR_HIGH = FLAGS["saturated"] | FLAGS["response_shoulder"] | FLAGS["outside_sweep"]

#: The flag that censors a pixel from below: it read under the sweep's range, so a region's
#: median counts it as -inf (:func:`region_median`).
CENSOR_LOW = FLAGS["below_sweep"]

#: A region with this share of its pixels flagged or more is flagged as a whole
#: (:func:`region_median`).
MAX_FLAGGED_SHARE = 0.5

#: :func:`frame_flags` looks up only the NaN pixels of a band when they are fewer than one in
#: this many (a gather per NaN pixel costs several times a lookup of the whole band's pixel).
SPARSE = 8

#: Default bound on the relative uncertainty of U (``response_uncertainty``) above which a DN
#: is on the response's shoulder.
DEFAULT_BOUND = 0.03

#: Bound on the fit's own share of U's relative uncertainty (``response_fit_uncertainty``)
#: above which a DN on the upper branch is on the shoulder too: that share is systematic, the
#: same for every pixel at the DN, so a region's mean keeps it whole while it averages one
#: reading's noise away; a third of the 1 % a region's reflectance is held to, so its
#: three-sigma reach stays within it (on harsh sweeps the worst DN of a band was 2.1-3.5 times
#: the stated share off).
DEFAULT_FIT_BOUND = 0.01 / 3


def dn_flag_table(n_bands: int, n_dn: int, saturation_dn: int, response_uncertainty: np.ndarray | None = None,
                  bound: float = DEFAULT_BOUND, dn_range: np.ndarray | None = None,
                  fit_uncertainty: np.ndarray | None = None, fit_bound: float = DEFAULT_FIT_BOUND) -> np.ndarray:
    """Return the flags of every DN of every band: clipped, on the shoulder, outside (and below) the sweep.

    Parameters
    ----------
    n_bands : int
        Bands.
    n_dn : int
        Entries of the response table (``2**bits``).
    saturation_dn : int
        DN at or above it are ``saturated`` (the rule of :func:`mscal_core.reflectance.eq15_fast`).
    response_uncertainty : numpy.ndarray, optional
        (n_bands, n_dn) relative uncertainty of U, NaN outside the fitted range; a DN on the
        response's upper branch whose value is above ``bound`` is ``response_shoulder``
        (:func:`shoulder_mask`; NaN is not: ``dn_range`` says where the fit is). None: not
        checked.
    bound : float
        Largest relative uncertainty of U that is trusted (> 0).
    dn_range : numpy.ndarray, optional
        (n_bands, 2) inclusive ``(low, high)`` DN the response sweep covered; a DN outside is
        ``outside_sweep``, and one under ``low`` ``below_sweep`` too. None: not checked.
    fit_uncertainty : numpy.ndarray, optional
        (n_bands, n_dn) the fit's own share of ``response_uncertainty`` (systematic: the same
        for every pixel at the DN); above ``fit_bound`` on the upper branch, a DN is
        ``response_shoulder`` too (:func:`shoulder_mask`). None: not checked.
    fit_bound : float
        Largest fit share trusted (> 0).

    Returns
    -------
    numpy.ndarray
        uint8 (n_bands, n_dn): the OR of the bits of :data:`FLAGS` that apply to band b at DN.

    Raises
    ------
    InputError
        For tables that do not have ``n_bands`` rows of ``n_dn`` entries, or a bound that is
        not positive.

    Notes
    -----
    U of Eq. 15 of [1]_, ``R = U(I) / (t V S B)``, enters the reflectance linearly, so its
    relative uncertainty is that of R at the pixel: a bound on it is a bound on R's error from U.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    for name, value in (("response uncertainty bound", bound), ("response fit uncertainty bound", fit_bound)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(f"the {name} must be positive, got {value!r}")
    out = np.zeros((n_bands, n_dn), np.uint8)
    out[:, max(0, min(int(saturation_dn), n_dn)):] |= FLAGS["saturated"]
    if response_uncertainty is not None:
        unc = np.asarray(response_uncertainty, dtype=np.float64)
        fit = None if fit_uncertainty is None else np.asarray(fit_uncertainty, dtype=np.float64)
        for name, table in (("response uncertainty", unc), ("response fit uncertainty", fit)):
            if table is not None and table.shape != (n_bands, n_dn):
                raise InputError(f"{name} of shape {table.shape} does not fit {n_bands} bands x {n_dn} DN")
        out[shoulder_mask(unc, bound, fit, fit_bound)] |= FLAGS["response_shoulder"]
    if dn_range is not None:
        rng = np.asarray(dn_range).reshape(-1, 2)
        if rng.shape[0] != n_bands:
            raise InputError(f"response DN range of shape {np.shape(dn_range)} does not fit {n_bands} bands")
        dn = np.arange(n_dn)
        below = dn[None, :] < rng[:, :1]
        out[below | (dn[None, :] > rng[:, 1:])] |= FLAGS["outside_sweep"]
        out[below] |= FLAGS["below_sweep"]
    return out


def shoulder_mask(response_uncertainty: np.ndarray, bound: float = DEFAULT_BOUND,
                  fit_uncertainty: np.ndarray | None = None, fit_bound: float = DEFAULT_FIT_BOUND) -> np.ndarray:
    """Return where each band's DN is on the response's shoulder.

    A DN is on the shoulder when it lies above the DN of least relative uncertainty of U and
    that uncertainty is above ``bound``, or above the DN where the fit's own share of it is
    least and that share is above ``fit_bound``.

    Parameters
    ----------
    response_uncertainty : numpy.ndarray
        (n_bands, n_dn) relative uncertainty of U per DN, NaN outside the fitted range
        (``inf`` where U is 0, and where U is not determined near the top of the range: on the
        upper branch, ``inf`` is above any bound).
    bound : float
        Largest relative uncertainty of U that is trusted.
    fit_uncertainty : numpy.ndarray, optional
        (n_bands, n_dn) the fit's own share of ``response_uncertainty`` (the standard
        deviation of log U from the fit, without one reading's noise); NaN: not checked.
    fit_bound : float
        Largest fit share trusted.

    Returns
    -------
    numpy.ndarray
        bool (n_bands, n_dn); all False for a band with no finite uncertainty.

    Notes
    -----
    The relative uncertainty of U(I) in Eq. 15 of [1]_, ``R = U(I) / (t V S B)``, is large at
    both ends of the DN range: at dim readings because U(I) is small beside the noise of one
    reading (an absolute error of R that stays small, passed on by Eq. 15 as it is), and on
    the shoulder near the clip because U is steep there and poorly determined, so a small
    error of the DN or of the fit is a large error of R. Only the upper branch, the DN above
    the one where the relative uncertainty is least, is the shoulder; a dim pixel is not
    flagged for its noise. One reading's noise averages away over a region's pixels, the fit's
    own share does not: every pixel at the DN shares it, so a panel's mean or a field's median
    keeps it whole. Its bound is the one a region's value is held to (``fit_bound``), the
    total's the one a pixel's is.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    unc = np.asarray(response_uncertainty, dtype=np.float64)
    out = np.zeros(unc.shape, bool)
    for b in range(unc.shape[0]):
        finite = np.isfinite(unc[b])
        if not finite.any():
            continue
        least = int(np.argmin(np.where(finite, unc[b], np.inf)))
        out[b, least:] = ~np.isnan(unc[b, least:]) & (unc[b, least:] > bound)  # inf: not determined
        if fit_uncertainty is not None:  # its own upper branch: above the DN where it is least
            fit = np.asarray(fit_uncertainty[b], dtype=np.float64)
            known = np.isfinite(fit) & ~np.isnan(unc[b])
            if known.any():
                low = int(np.argmin(np.where(known, fit, np.inf)))
                out[b, low:] |= known[low:] & (fit[low:] > fit_bound)
    return out


def pixel_flag_table(coverage: np.ndarray) -> np.ndarray:
    """Return the ``vignetting_unobserved`` flag of every pixel of every band.

    Parameters
    ----------
    coverage : numpy.ndarray
        (n_bands, H, W) views that observed V at each pixel.

    Returns
    -------
    numpy.ndarray
        uint8 (n_bands, H, W): ``FLAGS["vignetting_unobserved"]`` where ``coverage == 0``, else 0.

    Notes
    -----
    V of Eq. 15 of [1]_ (fitted by Eq. 8-10) is interpolated or extrapolated where no view of
    the reflector fell: R there rests on no measurement of V.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    c = np.asarray(coverage)
    return np.where(c == 0, np.uint8(FLAGS["vignetting_unobserved"]), np.uint8(0)).astype(np.uint8)


def mask_tables(lut: np.ndarray, inv_v: np.ndarray, dn_flags: np.ndarray, pixel_flags: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Return the tables of :func:`mscal_core.reflectance.eq15_tables` with NaN where flagged.

    Parameters
    ----------
    lut : numpy.ndarray
        (n_bands, n_dn) float32 ``U / S``.
    inv_v : numpy.ndarray
        (n_bands, H, W) float32 ``1 / V``.
    dn_flags : numpy.ndarray
        (n_bands, n_dn) uint8 of :func:`dn_flag_table`.
    pixel_flags : numpy.ndarray, optional
        (n_bands, H, W) uint8 of :func:`pixel_flag_table`; None: ``inv_v`` unchanged.

    Returns
    -------
    lut : numpy.ndarray
        float32 copy of ``lut``, NaN where ``dn_flags`` is not 0.
    inv_v : numpy.ndarray
        float32 copy of ``inv_v``, NaN where ``pixel_flags`` is not 0 (``inv_v`` itself when None).

    Raises
    ------
    InputError
        When the shapes do not fit.

    Notes
    -----
    Eq. 15 of [1]_ as :func:`mscal_core.reflectance.eq15_fast` computes it,
    ``R = lut[b][I] / t * inv_v[b]``: NaN in either factor makes R NaN, so the flagged pixels
    are NaN at no extra cost per pixel.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    if np.shape(dn_flags) != np.shape(lut):
        raise InputError(f"DN flags {np.shape(dn_flags)} do not fit the response table {np.shape(lut)}")
    table = np.where(np.asarray(dn_flags) != 0, np.float32(np.nan), lut).astype(np.float32)
    if pixel_flags is None:
        return table, inv_v
    if np.shape(pixel_flags) != np.shape(inv_v):
        raise InputError(f"pixel flags {np.shape(pixel_flags)} do not fit the vignetting {np.shape(inv_v)}")
    return table, np.where(np.asarray(pixel_flags) != 0, np.float32(np.nan), inv_v).astype(np.float32)


def frame_flags(dn: np.ndarray, dn_flags: np.ndarray, pixel_flags: np.ndarray | None = None,
                out: np.ndarray | None = None, reflectance: np.ndarray | None = None) -> np.ndarray:
    """Return the quality mask of one frame: ``q[b] = dn_flags[b][I_b] | pixel_flags[b]``.

    Parameters
    ----------
    dn : numpy.ndarray
        (n_bands, H, W) unsigned integer DN, below ``dn_flags.shape[1]``.
    dn_flags : numpy.ndarray
        (n_bands, n_dn) uint8 of :func:`dn_flag_table`.
    pixel_flags : numpy.ndarray, optional
        (n_bands, H, W) uint8 of :func:`pixel_flag_table`; None: none.
    out : numpy.ndarray, optional
        C-contiguous uint8 array the shape of ``dn`` to write into.
    reflectance : numpy.ndarray, optional
        (n_bands, H, W) Eq. 15 of ``dn`` with the tables of :func:`mask_tables` (NaN wherever a
        flag is set): in a band with few NaN pixels (fewer than one in :data:`SPARSE`) the
        flags are looked up only there, 0 elsewhere (the same mask at a cost that follows the
        NaN pixels). None: looked up everywhere.

    Returns
    -------
    numpy.ndarray
        uint8 (n_bands, H, W), ``out`` if given.

    Raises
    ------
    InputError
        For DN that are not unsigned integers (n_bands, H, W), DN beyond the table, or tables
        that do not fit.

    Notes
    -----
    One uint8 lookup per pixel (and an OR with the per-pixel flags): the flags of Eq. 15's U
    and V of [1]_ per DN and per pixel, computed once per calibration.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    d = np.asarray(dn)
    if d.ndim != 3 or not np.issubdtype(d.dtype, np.unsignedinteger) or d.shape[0] != dn_flags.shape[0]:
        raise InputError(f"DN must be unsigned integers ({dn_flags.shape[0]}, H, W), got {d.dtype} {d.shape}")
    if pixel_flags is not None and pixel_flags.shape != d.shape:
        raise InputError(f"pixel flags {pixel_flags.shape} do not fit DN {d.shape}")
    top = int(d.max(initial=0))
    if top >= dn_flags.shape[1]:
        raise InputError(f"DN {top} outside the flag table 0..{dn_flags.shape[1] - 1}",
                         hint="is the calibration for this camera's bit depth?")
    if reflectance is not None and np.shape(reflectance) != d.shape:
        raise InputError(f"reflectance {np.shape(reflectance)} does not fit DN {d.shape}")
    if out is None:
        out = np.empty(d.shape, np.uint8)
    for b in range(d.shape[0]):
        pix = None if pixel_flags is None else pixel_flags[b]
        if reflectance is None or not _sparse_lookup(d[b], dn_flags[b], pix, np.isnan(reflectance[b]), out[b]):
            np.take(dn_flags[b], d[b], out=out[b], mode="clip")  # bounds checked above
            if pix is not None:
                np.bitwise_or(out[b], pix, out=out[b])
    return out


def _sparse_lookup(dn: np.ndarray, dn_flags: np.ndarray, pixel_flags: np.ndarray | None, nan: np.ndarray,
                   out: np.ndarray) -> bool:
    """Look one band's flags up at its ``nan`` pixels only (0 elsewhere) if they are few.

    Few: fewer than one in :data:`SPARSE` (a gather per pixel costs several times a whole-band
    lookup). Returns False, nothing written, otherwise.
    """
    n_nan = np.count_nonzero(nan)
    if n_nan * SPARSE >= nan.size:
        return False
    out[...] = 0
    if n_nan:
        at = np.flatnonzero(nan)
        flags = dn_flags[dn.ravel()[at]]
        if pixel_flags is not None:
            flags |= pixel_flags.ravel()[at]
        out.ravel()[at] = flags
    return True


def flag_counts(quality: np.ndarray) -> list[dict[str, int]]:
    """Return, per band, the pixels that carry each flag (flags of no pixel left out).

    Parameters
    ----------
    quality : numpy.ndarray
        (n_bands, H, W) uint8 mask of :data:`FLAGS` bits.

    Returns
    -------
    list of dict
        One ``{flag name: pixels}`` per band; a pixel with several bits counts under each.

    Notes
    -----
    One histogram of the 256 values per band with a flagged pixel (OpenCV's ``calcHist``, 3-4x
    numpy's ``bincount``), none for a band without.
    """
    q = np.ascontiguousarray(quality, dtype=np.uint8)
    out: list[dict[str, int]] = []
    for b in range(q.shape[0]):
        if not np.count_nonzero(q[b]):
            out.append({})
            continue
        hist = cv2.calcHist([q[b]], [0], None, [256], [0, 256]).ravel().astype(np.int64)
        codes = np.nonzero(hist)[0]
        counts = {name: int(hist[codes[(codes & bit) != 0]].sum()) for name, bit in FLAGS.items()}
        out.append({k: v for k, v in counts.items() if v})
    return out


def region_median(values: np.ndarray, quality: np.ndarray, max_flagged_share: float = MAX_FLAGGED_SHARE,
                  censor_at: np.ndarray | None = None) -> np.ndarray:
    """Return the median of a region's reflectance that the quality flags do not bias.

    A pixel flagged by a bit of :data:`CENSOR_HIGH` (saturated, on the response's shoulder,
    above the sweep) counts as +inf, one flagged :data:`CENSOR_LOW` (below the sweep) as -inf,
    a pixel with another flag (or without a finite value) is left out; the region is flagged
    as a whole (NaN) when ``max_flagged_share`` of its pixels or more carry a flag.

    Parameters
    ----------
    values : numpy.ndarray
        ``(..., n)`` reflectance of the region's ``n`` pixels (e.g. one row per band); the
        values of flagged pixels are not read (NaN or kept, as ``--keep-flagged`` keeps them).
    quality : numpy.ndarray
        uint8 mask of :data:`FLAGS` bits, the shape of ``values`` (or broadcastable to it).
    max_flagged_share : float
        Share of flagged pixels (any bit, or not finite) from which the region is flagged, in
        ``(0, 1]``.
    censor_at : numpy.ndarray, optional
        The shape of ``values``: for a pixel flagged by :data:`CENSOR_HIGH`, the lowest value it
        can have (the value it would have at the highest trusted DN: its own V sets it); NaN
        or +inf: above every valid value. Other pixels' entries are not read. None: every
        censored pixel lies above every valid value.

    Returns
    -------
    numpy.ndarray
        float64 of shape ``values.shape[:-1]`` (a 0-d array for 1-d ``values``): the median,
        NaN where the region is flagged or empty.

    Raises
    ------
    InputError
        When ``quality`` or ``censor_at`` do not broadcast to ``values`` or
        ``max_flagged_share`` is not in ``(0, 1]``.

    Notes
    -----
    The shoulder flag of Eq. 15 of [1]_, ``R = U(I) / (t V S B)``, cuts a region's DN
    distribution at a DN: of a uniform panel whose readings straddle it, the pixels left
    valid are those whose noise read low, and the median of the valid pixels alone is biased
    low. Their true values are not known but are above the cut, so the median of the ``m``
    counted pixels (``v`` valid values sorted, ``c`` censored high, ``m = v + c``) is the
    order statistic of ``v`` it would be with the censored pixels in place:

    ``median = (x_(floor((m-1)/2)) + x_(floor(m/2))) / 2``, with ``x`` the sorted valid values
    (0-based) followed by ``c`` times +inf,

    unbiased as long as the censored pixels lie above the median, which holds while fewer than
    half are censored and the region's DN vary by the noise alone. They also vary with V
    across the region, so the pixels a DN cut flags are partly those of highest V, whose values
    are not above the others' (harsh full-size session 3: a 0.9 panel 46 % flagged read 3 %
    high): a smaller ``max_flagged_share`` keeps that bias small. With ``f`` flagged pixels of
    ``n`` (``c`` of them censored, the rest left out), the region is flagged when
    ``f >= max_flagged_share * n``; for a share of at most 0.5, ``c < m / 2`` and the median is
    finite.

    With ``censor_at``, each censored pixel's value is known to lie above its own bound
    ``c_i``, and the median is that of the Kaplan-Meier (product-limit) estimate of the
    values' distribution [2]_: with the valid values and the bounds sorted together (a value
    before a bound it equals), each valid value ``x_(k)`` multiplies the share above it by
    ``1 - 1 / r_k`` (``r_k`` the entries not yet passed), a bound only leaves the count;
    the median is the first valid value where that share reaches 1/2 (the mean with the next
    valid value where it is 1/2 exactly: the ordinary median without censoring). A pixel
    flagged for its high V is then no longer counted as above the others, and the estimate
    holds beyond half the pixels censored (a 0.9 panel over a 20 % V gradient, 1.5 % noise,
    46 % cut at one DN: 0.9003, counting them above 0.9177).

    .. [2] E. L. Kaplan and P. Meier, "Nonparametric estimation from incomplete
           observations", Journal of the American Statistical Association 53, 1958.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    if not 0 < max_flagged_share <= 1:
        raise InputError(f"the flagged share of a region must be in (0, 1], got {max_flagged_share!r}")
    v = np.asarray(values, dtype=np.float64)
    try:
        q = np.broadcast_to(np.asarray(quality), v.shape)
    except ValueError:
        raise InputError(f"quality of shape {np.shape(quality)} does not fit the values {v.shape}") from None
    n = v.shape[-1]
    if n == 0:
        return np.full(v.shape[:-1], np.nan)
    low = (q & CENSOR_LOW) != 0
    censored = ((q & CENSOR_HIGH) != 0) & ~low
    valid = (q == 0) & np.isfinite(v)
    if censor_at is not None:
        return _product_limit_median(v, valid, censored, low, censor_at, max_flagged_share)
    flagged = n - np.count_nonzero(valid, axis=-1)
    c = np.count_nonzero(censored, axis=-1) + np.count_nonzero(low, axis=-1)
    m = np.count_nonzero(valid, axis=-1) + c
    # -inf (read below), valid values, then +inf (censored high and left out)
    x = np.sort(np.where(valid, v, np.where(low, -np.inf, np.inf)), axis=-1)
    lo = np.clip((m - 1) // 2, 0, n - 1)[..., None]
    hi = np.clip(m // 2, 0, n - 1)[..., None]
    with np.errstate(invalid="ignore"):
        med = 0.5 * (np.take_along_axis(x, lo, -1) + np.take_along_axis(x, hi, -1))[..., 0]
    return np.where((m > 0) & (flagged < max_flagged_share * n) & np.isfinite(med), med, np.nan)


def _product_limit_median(v: np.ndarray, valid: np.ndarray, censored: np.ndarray, low: np.ndarray,
                          censor_at: np.ndarray, max_flagged_share: float) -> np.ndarray:
    """Return :func:`region_median` with per-pixel bounds: the Kaplan-Meier median per row."""
    try:
        at = np.broadcast_to(np.asarray(censor_at, np.float64), v.shape)
    except ValueError:
        raise InputError(f"censor bounds of shape {np.shape(censor_at)} do not fit the values {v.shape}") from None
    n = v.shape[-1]
    flat = [a.reshape(-1, n) for a in (v, valid, censored, low, at)]
    out = np.array([_km_median(*rows) if n - np.count_nonzero(rows[1]) < max_flagged_share * n else np.nan
                    for rows in zip(*flat)])
    return out.reshape(v.shape[:-1])


def _km_median(v: np.ndarray, valid: np.ndarray, censored: np.ndarray, low: np.ndarray, at: np.ndarray) -> float:
    """Return the product-limit median of one region (:func:`region_median`), NaN when undetermined."""
    n_low = int(np.count_nonzero(low))
    bounds = at[censored]
    x = np.concatenate([np.full(n_low, -np.inf), v[valid], np.where(np.isnan(bounds), np.inf, bounds)])
    event = np.arange(x.size) < x.size - bounds.size
    if not x.size:
        return float("nan")
    order = np.lexsort((~event, x))  # by value; a value before a bound it equals
    x, event = x[order], event[order]
    left = x.size - np.arange(x.size)
    share = np.cumprod(np.where(event, 1.0 - 1.0 / left, 1.0))
    hit = np.flatnonzero(event & (share <= 0.5 + 1e-12))
    if not hit.size:
        return float("nan")
    k = int(hit[0])
    med = float(x[k])
    if abs(share[k] - 0.5) <= 1e-12:
        after = np.flatnonzero(event[k + 1:])
        if after.size:
            med = float(0.5 * (x[k] + x[k + 1 + after[0]]))
    return med if np.isfinite(med) else float("nan")  # among the readings below: not known


def censor_dn(dn: np.ndarray, dn_flags: np.ndarray) -> np.ndarray:
    """Return, per pixel, the DN that bounds a reading censored from above.

    Parameters
    ----------
    dn : numpy.ndarray
        (n_bands, ...) integer DN of a frame.
    dn_flags : numpy.ndarray
        (n_bands, n_dn) the flags of every DN (:func:`dn_flag_table`).

    Returns
    -------
    numpy.ndarray
        The shape and dtype of ``dn``: a reading flagged by :data:`CENSOR_HIGH` (not
        :data:`CENSOR_LOW`) gets the highest trusted DN (without such a flag) under it, the
        reading a pixel just under the cut would give, so Eq. 15 of it at the pixel is the
        least its reflectance can be (:func:`region_median`'s ``censor_at``); every other
        pixel keeps its DN, as does a reading with no trusted DN under it.

    Raises
    ------
    InputError
        When ``dn`` has not one row per band of ``dn_flags``.
    """
    d = np.asarray(dn)
    table = np.asarray(dn_flags)
    if table.ndim != 2 or d.shape[:1] != table.shape[:1]:
        raise InputError(f"DN of shape {d.shape} do not fit flag tables of shape {table.shape}")
    trusted = (table & CENSOR_HIGH) == 0
    # per band and DN: the highest trusted DN at or below it (-1: none)
    last = np.maximum.accumulate(np.where(trusted, np.arange(table.shape[1]), -1), axis=1)
    flat = np.clip(d, 0, table.shape[1] - 1).reshape(d.shape[0], -1)
    bound = np.take_along_axis(last, flat, axis=1).reshape(d.shape)
    return np.where(bound >= 0, bound, d).astype(d.dtype)
