"""Reflectance of the target scene: Eq. 15, panel normalisation and NDVI (no I/O).

- (15) ``R_lambda(x) = U_lambda(I_lambda(x)) / (t V_lambda(x) S(lambda) B(x))``

``B`` of the target scene is unknown (the light during the flight is not that of the
reflector images), so R from Eq. 15 is relative: one unknown scalar per frame. Normalise it
with a region of known reflectance (:func:`normalise_to_panel`) or use ratios / indices
(:func:`ndvi`, segmented by :func:`vegetation_mask`) that need no normalisation.

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .errors import InputError

__all__ = [
    "NDVI_RANGE", "eq15", "keep_valid", "ndvi", "normalise_to_panel", "otsu_ndvi_threshold", "vegetation_mask",
]

#: NDVI outside this range is NaN (``catalogs/indices/ndvi.yaml``: ``valid_range``).
NDVI_RANGE = (-1.0, 1.0)


def _per_frame(value: np.ndarray | float, dn_shape: tuple[int, ...], name: str) -> np.ndarray:
    """Broadcastable form of an exposure / brightness: scalar, per frame, or an array."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 1 and len(dn_shape) == 4 and arr.size == dn_shape[0] and arr.size > 1:
        arr = arr.reshape(-1, 1, 1, 1)
    try:
        np.broadcast_shapes(arr.shape, dn_shape)
    except ValueError:
        raise InputError(
            f"{name} of shape {arr.shape} does not fit DN of shape {dn_shape}: give a scalar, "
            f"one value per frame, or an array that broadcasts to the DN"
        ) from None
    return arr


def eq15(
    dn: np.ndarray,
    inverse_response: np.ndarray,
    exposure: np.ndarray | float,
    vignetting: np.ndarray,
    spectral_factor: np.ndarray,
    brightness: np.ndarray | float = 1.0,
    *,
    saturation_dn: int | None = None,
) -> np.ndarray:
    """Return the reflectance of Eq. 15, ``R = U(I) / (t V S B)``, vectorised over bands and frames.

    Parameters
    ----------
    dn : numpy.ndarray
        Integer DN, (n_bands, H, W) or (n_frames, n_bands, H, W) (band axis = the third from
        last).
    inverse_response : numpy.ndarray
        U: (2**bits,) shared by all bands or (n_bands, 2**bits), one per band ("every band is
        its own camera"). Negative values are treated as 0.
    exposure : numpy.ndarray or float
        t (> 0): scalar, (n_frames,) for a frame stack, or an array broadcasting to ``dn`` (e.g.
        (n_bands, 1, 1) for per-band exposures).
    vignetting : numpy.ndarray
        V: (n_bands, H, W) (or broadcastable, e.g. (H, W) for one band).
    spectral_factor : numpy.ndarray
        S: (n_bands,).
    brightness : numpy.ndarray or float
        B: scalar (default 1, i.e. relative reflectance), (n_frames,), or an array broadcasting
        to ``dn`` (e.g. a brightness map (H, W)).
    saturation_dn : int, optional
        DN at or above it are saturated and give NaN; None means ``len(U) - 1`` (``dn_max``,
        saturated by the project's convention); pass ``len(U)`` to keep every DN.

    Returns
    -------
    numpy.ndarray
        float32 reflectance, the shape of ``dn``. Never negative or inf: U = 0 gives 0; V, S or
        B that are not positive and finite give NaN.

    Raises
    ------
    InputError
        For DN outside the response table, non-integer DN, non-positive exposure or mismatched
        shapes.

    Notes
    -----
    Eq. 15 of [1]_, ``R_lambda(x) = U_lambda(I_lambda(x)) / (t V_lambda(x) S(lambda) B(x))``.
    B of the target scene is unknown, so R is relative: one scalar per frame
    (:func:`normalise_to_panel`).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    d = np.asarray(dn)
    if d.ndim not in (3, 4):
        raise InputError(
            f"DN must be (n_bands, H, W) or (n_frames, n_bands, H, W), got shape {d.shape}"
        )
    if not np.issubdtype(d.dtype, np.integer):
        integral = np.issubdtype(d.dtype, np.floating) and bool(
            np.all(np.isfinite(d)) and np.all(d == np.round(d))
        )
        if not integral:
            raise InputError(f"DN must be integers, got dtype {d.dtype} with non-integer values")
    d = d.astype(np.int64, copy=False)
    n_bands = d.shape[-3]
    u = np.asarray(inverse_response, dtype=np.float64)
    if u.ndim == 1:
        u = u[None, :]
    if u.ndim != 2 or u.shape[0] not in (1, n_bands) or u.shape[1] < 2:
        raise InputError(
            f"inverse response must be (2**bits,) or ({n_bands}, 2**bits), got shape "
            f"{np.asarray(inverse_response).shape}"
        )
    n_dn = u.shape[1]
    if d.size and (d.min() < 0 or d.max() >= n_dn):
        raise InputError(
            f"DN {int(d.min())}..{int(d.max())} outside the response table 0..{n_dn - 1}",
            hint="is the calibration for this camera's bit depth?",
        )
    u = np.where(np.isfinite(u), np.maximum(u, 0.0), np.nan)
    sat = n_dn - 1 if saturation_dn is None else int(saturation_dn)

    band = np.arange(n_bands).reshape(-1, 1, 1) if u.shape[0] > 1 else np.zeros((1, 1, 1), np.int64)
    energy = u[band, d]  # U(I), broadcast over frames

    t = _per_frame(exposure, d.shape, "exposure")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError("exposure times must be positive and finite")
    v = np.asarray(vignetting, dtype=np.float64)
    s = np.asarray(spectral_factor, dtype=np.float64).ravel()
    if s.size not in (1, n_bands):
        raise InputError(f"spectral_factor must have {n_bands} values, got {s.size}")
    s = s.reshape(-1, 1, 1)
    b = _per_frame(brightness, d.shape, "brightness")
    try:
        np.broadcast_shapes(v.shape, d.shape)
    except ValueError:
        raise InputError(
            f"vignetting of shape {v.shape} does not fit DN of shape {d.shape}"
        ) from None

    denom = t * v * s * b
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        bad = (~(np.isfinite(v) & (v > 0)) | ~(np.isfinite(s) & (s > 0))
               | ~(np.isfinite(b) & (b > 0)))
        out = energy / denom
    out = np.where(bad | (d >= sat) | ~np.isfinite(out), np.nan, out)
    return out.astype(np.float32)


def normalise_to_panel(
    reflectance: np.ndarray,
    panel_mask: np.ndarray,
    panel_reflectance: np.ndarray | float,
) -> np.ndarray:
    """Scale relative reflectance so a panel of known reflectance reads its true value.

    Parameters
    ----------
    reflectance : numpy.ndarray
        (n_bands, H, W) or (n_frames, n_bands, H, W), e.g. from :func:`eq15`.
    panel_mask : numpy.ndarray
        (H, W) bool, or (n_frames, H, W) for a panel that moves.
    panel_reflectance : numpy.ndarray or float
        Scalar or (n_bands,).

    Returns
    -------
    numpy.ndarray
        float32, the shape of ``reflectance``. A band whose panel pixels are all NaN gives NaN
        for that band.

    Raises
    ------
    InputError
        On shapes that do not fit, a non-positive panel reflectance or an empty panel mask.

    Notes
    -----
    For each frame and band the factor is ``panel_reflectance / median(R over the panel)``
    (median: robust to a few bad pixels; NaN pixels ignored). This removes the unknown per-frame
    brightness B of Eq. 15 [1]_ (and, per band, any residual spectral error).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    r = np.asarray(reflectance, dtype=np.float64)
    if r.ndim not in (3, 4):
        raise InputError(
            f"reflectance must be (n_bands, H, W) or (n_frames, n_bands, H, W), got {r.shape}"
        )
    squeeze = r.ndim == 3
    if squeeze:
        r = r[None]
    n_frames, n_bands, h, w = r.shape
    mask = np.asarray(panel_mask, dtype=bool)
    if mask.shape == (h, w):
        mask = np.broadcast_to(mask, (n_frames, h, w))
    if mask.shape != (n_frames, h, w):
        raise InputError(f"panel mask of shape {mask.shape} does not fit images of {h}x{w}")
    ref = np.asarray(panel_reflectance, dtype=np.float64).ravel()
    if ref.size == 1:
        ref = np.repeat(ref, n_bands)
    if ref.size != n_bands or not np.all(np.isfinite(ref)) or np.any(ref <= 0):
        raise InputError(
            f"panel reflectance must be {n_bands} positive values, got {panel_reflectance!r}"
        )
    out = np.empty_like(r)
    for f in range(n_frames):
        if not mask[f].any():
            raise InputError(f"the panel mask of frame {f} is empty", hint="check the panel region")
        out[f] = r[f] * _panel_factor(r[f][:, mask[f]], ref)[:, None, None]
    if squeeze:
        out = out[0]
    return out.astype(np.float32)


def _panel_factor(panel: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per band ``ref / median`` of the finite panel pixels ``panel`` (n_bands, n_panel).

    NaN for a band without a finite, positive median.
    """
    n_bands = panel.shape[0]
    finite = np.isfinite(panel)
    med = np.full(n_bands, np.nan)
    has = finite.any(axis=1)
    if has.any():
        med[has] = np.nanmedian(np.where(finite, panel, np.nan)[has], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(med > 0, ref / med, np.nan)


def keep_valid(values: np.ndarray, valid_range: tuple[float, float] | None = None) -> np.ndarray:
    """Return ``values`` (same dtype) with NaN where not finite or outside ``valid_range``.

    The edge rule of every spectral index: the catalog's ``valid_range``
    (``catalogs/indices/*.yaml``, inclusive) and :func:`ndvi`.

    Parameters
    ----------
    values : numpy.ndarray
        Floating-point values of an index.
    valid_range : tuple of float, optional
        ``(lo, hi)``, inclusive; None keeps every finite value.

    Returns
    -------
    numpy.ndarray
        The dtype and shape of ``values``.
    """
    out = np.asarray(values)
    if valid_range is None:
        keep = np.isfinite(out)
    else:  # lo <= v <= hi is false for NaN, and for +-inf within finite bounds: 3 passes, not 6
        lo, hi = valid_range
        keep = out >= lo
        keep &= out <= hi
        if not (math.isfinite(lo) and math.isfinite(hi)):
            keep &= np.isfinite(out)
    return _nan_where_not(out, keep)


def _nan_where_not(values: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Return ``np.where(keep, values, nan)`` in the dtype of ``values``, byte for byte.

    NaN is the dtype's own ``nan``. For float32 / float64 by bit masks (keep the bits, or put
    NaN's) instead of numpy's ``where`` with a scalar: :func:`keep_valid` of a 1280x960 float32
    NDVI 0.88 -> 0.63 ms of CPU (1.31 -> 0.63 with 5 % of it NaN).
    """
    dt = values.dtype
    if values.ndim == 0 or dt.kind != "f" or dt.itemsize not in (4, 8) or not dt.isnative:
        return np.where(keep, values, np.nan).astype(dt, copy=False)
    bits = np.dtype(f"u{dt.itemsize}")
    mask = keep.astype(bits)
    np.negative(mask, out=mask)  # every bit set where kept
    out = np.bitwise_and(values.view(bits), mask)
    np.invert(mask, out=mask)
    mask &= np.array(np.nan, dt).view(bits)
    out |= mask
    return out.view(dt)


def ndvi(red: np.ndarray, nir: np.ndarray) -> np.ndarray:
    """Return the NDVI ``(nir - red) / (nir + red)``, NaN-safe, in [-1, 1].

    Parameters
    ----------
    red, nir : numpy.ndarray
        Reflectance (or any linear signal) of the red and near-infrared bands.

    Returns
    -------
    numpy.ndarray
        NaN where either input is NaN / inf, where ``nir + red == 0``, and where the value
        falls outside [-1, 1] (only possible when a reflectance is negative: noise or a bad
        calibration), the rule of ``catalogs/indices/ndvi.yaml`` (``valid_range: [-1, 1]``)
        that the stored ``ndvi``, the NDVI TIFFs and the index maps follow
        (:func:`keep_valid`). float32 if both inputs are float32, else float64.

    Notes
    -----
    A ratio: the unknown brightness B of Eq. 15 cancels, so NDVI needs no panel [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    a = np.asarray(red)
    b = np.asarray(nir)
    dtype = np.float32 if (a.dtype == np.float32 and b.dtype == np.float32) else np.float64
    r = a.astype(np.float64)
    n = b.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (n - r) / (n + r)
    return keep_valid(out, NDVI_RANGE).astype(dtype)


def vegetation_mask(ndvi: np.ndarray) -> np.ndarray:
    """Return the paper's vegetation segmentation: Otsu's threshold of the NDVI of one frame.

    Parameters
    ----------
    ndvi : numpy.ndarray
        NDVI of one frame (:func:`ndvi`), NaN where not defined.

    Returns
    -------
    numpy.ndarray
        uint8 the shape of ``ndvi``: 1 vegetation, 0 not, 255 where NDVI is not defined (every
        pixel 255 when fewer than two are defined).

    Notes
    -----
    NDVI is quantised to 256 levels (``uint8((ndvi + 1) * 127.5)``) and OpenCV's Otsu [2]_ picks
    the level; a pixel is vegetation above it, i.e. from :func:`otsu_ndvi_threshold` up. The
    paper segments plants this way to compare calibrated and raw NDVI [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    .. [2] N. Otsu, "A threshold selection method from gray-level histograms", IEEE Trans.
           Systems, Man, and Cybernetics 9(1), 1979.
    """
    ok = np.isfinite(ndvi)
    n_ok = np.count_nonzero(ok)
    if n_ok < 2:
        return np.full(np.shape(ndvi), 255, dtype=np.uint8)
    # the levels of every pixel (an undefined one's is overwritten below): the defined pixels
    # are gathered only as levels, for Otsu, and nothing is scattered back
    with np.errstate(invalid="ignore"):
        scaled = _ndvi_levels(np.asarray(ndvi))
    if n_ok == ok.size:
        return (scaled > _otsu_level(scaled)).view(np.uint8)
    out = (scaled > _otsu_level(scaled[ok])).view(np.uint8)
    out |= np.logical_not(ok).view(np.uint8) * np.uint8(255)
    return out


def otsu_ndvi_threshold(ndvi: np.ndarray) -> float:
    """Return the NDVI from which :func:`vegetation_mask` calls a pixel vegetation.

    Parameters
    ----------
    ndvi : numpy.ndarray
        NDVI of one frame, NaN where not defined.

    Returns
    -------
    float
        ``t`` with vegetation where ``ndvi >= t`` on the 256 levels, ``(level + 1) / 127.5 - 1``
        for Otsu's level; NaN when fewer than two pixels are defined.

    References
    ----------
    .. [1] N. Otsu, "A threshold selection method from gray-level histograms", IEEE Trans.
           Systems, Man, and Cybernetics 9(1), 1979.
    """
    v = np.asarray(ndvi)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return (_otsu_level(_ndvi_levels(v)) + 1.0) / 127.5 - 1.0


def _ndvi_levels(values: np.ndarray) -> np.ndarray:
    return np.clip((values + 1.0) * 127.5, 0, 255).astype(np.uint8)


def _otsu_level(levels: np.ndarray) -> float:
    thr, _ = cv2.threshold(levels.reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(thr)


def eq15_tables(
    inverse_response: np.ndarray, vignetting: np.ndarray, spectral_factor: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Precompute the factors of Eq. 15 for :func:`eq15_fast`: ``R = (U(I) / S) * (1 / V) / t``.

    Parameters
    ----------
    inverse_response : numpy.ndarray
        (n_bands, 2**bits) U.
    vignetting : numpy.ndarray
        (n_bands, H, W) V.
    spectral_factor : numpy.ndarray
        (n_bands,) S.

    Returns
    -------
    lut : numpy.ndarray
        (n_bands, 2**bits) float32 ``max(U, 0) / S`` (NaN where S is not positive).
    inv_v : numpy.ndarray
        (n_bands, H, W) float32 ``1 / V`` (NaN where V is not positive and finite).

    Raises
    ------
    InputError
        When the shapes do not fit.

    Notes
    -----
    Eq. 15 of [1]_, ``R = U(I) / (t V S B)`` with ``B = 1``, regrouped as
    ``(U(I) / S) * (1 / V) / t``: the two tables are computed once per calibration and reused
    for every frame.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    u = np.asarray(inverse_response, dtype=np.float64)
    s = np.asarray(spectral_factor, dtype=np.float64).reshape(-1, 1)
    v = np.asarray(vignetting, dtype=np.float64)
    if u.ndim != 2 or v.ndim != 3 or not (u.shape[0] == v.shape[0] == s.shape[0]):
        raise InputError(
            f"inverse response {u.shape}, vignetting {v.shape} and spectral factor {s.shape[0]} do not fit"
        )
    with np.errstate(divide="ignore", invalid="ignore"):
        lut = np.where(np.isfinite(u) & (s > 0) & np.isfinite(s), np.maximum(u, 0.0) / s, np.nan)
        inv_v = np.where(np.isfinite(v) & (v > 0), 1.0 / v, np.nan)
    return lut.astype(np.float32), inv_v.astype(np.float32)


def _output_array(out: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """Return the array :func:`eq15_fast` writes its result into.

    ``out`` itself if it can take a float32 result of ``shape`` in place (writeable,
    C-contiguous), a new array if None; InputError otherwise.
    """
    if out is None:
        return np.empty(shape, dtype=np.float32)
    if out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous or not out.flags.writeable:
        raise InputError(f"out must be writeable C-contiguous float32 {shape}, got {out.dtype} {out.shape}")
    return out


def eq15_fast(
    dn: np.ndarray, lut: np.ndarray, inv_v: np.ndarray, exposure: np.ndarray | float, saturation_dn: int,
    band_scale: np.ndarray | None = None, out: np.ndarray | None = None,
) -> np.ndarray:
    """Return Eq. 15 for a stack of frames with the tables of :func:`eq15_tables` (float32 throughout).

    Parameters
    ----------
    dn : numpy.ndarray
        (n_frames, n_bands, H, W) unsigned integers.
    lut, inv_v : numpy.ndarray
        The tables of :func:`eq15_tables`.
    exposure : numpy.ndarray or float
        t (n_frames,) or scalar, positive.
    saturation_dn : int
        NaN where ``I >= saturation_dn``.
    band_scale : numpy.ndarray, optional
        (n_frames, n_bands) or (n_bands,): a per-frame, per-band factor folded into each frame's
        table at no extra cost per pixel, ``R = lut[b][I] k_b / t * inv_v[b]``. None (default)
        computes exactly what it did without the argument.
    out : numpy.ndarray, optional
        C-contiguous float32 array the shape of ``dn`` to write the result into (a caller's
        buffer, e.g. one aligned for direct I/O); None (default): a new array.

    Returns
    -------
    numpy.ndarray
        float32 ``R = lut[b][I] * inv_v[b] / t``, the shape of ``dn`` (``out`` if given).

    Raises
    ------
    InputError
        For DN that are not unsigned integers of 4 dimensions, non-positive or non-finite
        exposures, a ``band_scale`` that does not fit or is not positive, tables that do
        not fit, or an ``out`` that is not C-contiguous float32 of the shape of ``dn``.

    Notes
    -----
    Agrees with :func:`eq15` to float32 rounding; about 6x faster (a table lookup per band, no
    float64). The light of a frame that differs from the calibration's S enters as
    ``k_b = S(lambda_b) / S(lambda_b, tau)``: Eq. 15 with ``S(lambda, tau)`` in place of S [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    d = np.asarray(dn)
    if d.ndim != 4 or not np.issubdtype(d.dtype, np.unsignedinteger):
        raise InputError(f"DN must be unsigned integers (n_frames, n_bands, H, W), got {d.dtype} {d.shape}")
    t = np.broadcast_to(np.asarray(exposure, dtype=np.float64).reshape(-1), (d.shape[0],))
    if not np.all(np.isfinite(t) & (t > 0)):
        raise InputError("exposure times must be positive and finite")
    k = None
    if band_scale is not None:
        k = np.asarray(band_scale, dtype=np.float64)
        try:
            k = np.broadcast_to(k.reshape(-1, d.shape[1]) if k.ndim == 1 else k, d.shape[:2])
        except ValueError:
            raise InputError(f"band_scale of shape {np.shape(band_scale)} does not fit {d.shape[0]} frames x {d.shape[1]} bands") from None
        if not np.all(np.isfinite(k) & (k > 0)):
            raise InputError("band_scale must be positive and finite")
    out = _output_array(out, d.shape)
    sat = max(0, min(int(saturation_dn), lut.shape[1]))
    for f in range(d.shape[0]):
        # 1/t and the saturation mask folded into the frame's table: NaN from DN >= saturation
        # propagates through the product, so each band is one lookup and one multiply
        if k is None:
            table = lut * np.float32(1.0 / t[f])
        else:
            table = lut * (k[f] / t[f]).astype(np.float32)[:, None]
        table[:, sat:] = np.nan
        top = int(d[f].max(initial=0))
        if top >= lut.shape[1]:
            raise InputError(
                f"DN {top} outside the response table 0..{lut.shape[1] - 1}",
                hint="is the calibration for this camera's bit depth?",
            )
        for b in range(d.shape[1]):
            o = out[f, b]
            # bounds checked once per frame above: numpy's own check per lookup ("raise")
            # made the lookup ~1.5x slower (5.9 against 4.0 ms a full-resolution frame)
            np.take(table[b], d[f, b], out=o, mode="clip")
            o *= inv_v[b]
    return out
