"""Illumination on the gray reflector, split into colour and brightness: Eq. 11-14, 16.

Model (Eq. 1, 11): on the reflector pixels ``x`` of known reflectance ``R_s(lambda)`` the
radiance ``L_lambda(x) = U_lambda(I)/(t V_lambda(x))`` is

- (11) ``J_lambda(x) = B(x) S(lambda)``, so ``L_lambda(x) = S(lambda) B(x) R_s(lambda)``:
  the light's "colour" ``S`` (which also absorbs each band's filter sensitivity) is the same
  over the reflector, only its brightness ``B`` varies from point to point.
- (12) ``M(S, B) = sum_lambda sum_x (L_lambda(x) - S(lambda) B(x) R_s)^2``
- (13) ``S(lambda) = sum_x L_lambda(x) B(x) R_s / sum_x (B(x) R_s)^2``
- (14) ``B(x) = sum_lambda L_lambda(x) S(lambda) R_s / sum_lambda (S(lambda) R_s)^2``

alternated from ``B(x) = mean over lambda of L_lambda(x)``: a rank-one fit of the
(band x pixel) radiance matrix, with missing entries (e.g. saturated) left out of the sums.

Baseline (Eq. 16): ``R = I_target / I_reflector * R_s`` per band, exact only if the
reflector was uniformly lit (:func:`eq16_reflectance`).

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import FitError, InputError

__all__ = [
    "FrameIllumination",
    "INTERPOLATION_MODES",
    "IlluminationFit",
    "capture_weights",
    "centre_brightness",
    "colour_change",
    "eq16_reflectance",
    "fit_illumination",
    "frame_illumination",
    "shared_reflector_pixels",
    "split_level",
]


@dataclass(frozen=True, eq=False)
class IlluminationFit:
    """Result of :func:`fit_illumination`.

    Attributes
    ----------
    spectral_factor : numpy.ndarray
        (n_bands,) S(lambda).
    brightness : numpy.ndarray
        (n_pix,) B(x) per reflector pixel (NaN where a pixel had no valid band). Gauge (``S B``
        is known up to a scale): ``median(B) = 1`` over all pixels given, so S is the spectral
        factor of the median-lit reflector pixel.
    image_brightness : numpy.ndarray or None
        (n_images,) median B of each image when ``image_index`` was given, else None.
    residual_rms : float
        Relative rms of ``L / (S B R_s) - 1`` over the valid entries.
    iterations : int
        Alternations done.
    converged : bool
        Whether ``tol`` was reached.
    """

    spectral_factor: np.ndarray
    brightness: np.ndarray
    image_brightness: np.ndarray | None
    residual_rms: float
    iterations: int
    converged: bool


def fit_illumination(
    radiance: np.ndarray,
    reflectance: np.ndarray | float,
    *,
    max_iter: int = 500,
    tol: float = 1e-9,
    image_index: np.ndarray | None = None,
    fit_pixels: np.ndarray | None = None,
) -> IlluminationFit:
    """Fit ``L_lambda(x) = S(lambda) B(x) R_s(lambda)`` on reflector pixels (Eq. 12-14).

    Parameters
    ----------
    radiance : numpy.ndarray
        (n_bands, n_pix) ``U(I)/(t V)`` at reflector pixels; NaN / inf entries (saturated,
        masked) are left out of every sum. Several reflector images: concatenate their pixels
        along the second axis (B is per pixel per image, S shared).
    reflectance : numpy.ndarray or float
        R_s per band (n_bands,) or one scalar (a gray reflector).
    max_iter : int
        Alternations at most.
    tol : float
        Stop when the largest relative change of S is below this.
    image_index : numpy.ndarray, optional
        (n_pix,) int, the image of every pixel, to get each image's median brightness.
    fit_pixels : numpy.ndarray, optional
        (n_pix,) bool, the pixels S is fitted from (Eq. 13 and 14 alternate on them only);
        B at every pixel then follows from Eq. 14 with that S, and the gauge and the residual
        are over every pixel. For pixels whose radiance is better known than the others' (for
        example where the vignetting was observed, not filled). None: every pixel.

    Returns
    -------
    IlluminationFit
        S, B (gauge ``median(B) = 1``), the per-image brightness and the residual.

    Raises
    ------
    InputError
        On bad shapes, reflectances, image indices or fit pixels.
    FitError
        When a band has no valid reflector pixel (it cannot be calibrated from these images),
        or S or B come out non-positive.

    Notes
    -----
    Eq. 12, ``M(S, B) = sum_lambda sum_x (L_lambda(x) - S(lambda) B(x) R_s)^2``, is minimised
    by alternating Eq. 13, ``S(lambda) = sum_x L_lambda(x) B(x) R_s / sum_x (B(x) R_s)^2``, and
    Eq. 14, ``B(x) = sum_lambda L_lambda(x) S(lambda) R_s / sum_lambda (S(lambda) R_s)^2``, from
    ``B = mean over lambda of L`` (nanmean) [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    rad, refl, idx = _checked_inputs(radiance, reflectance, image_index)
    sel = _checked_fit_pixels(fit_pixels, rad.shape[1])
    valid = np.isfinite(rad)
    bad_bands = np.flatnonzero(~valid[:, sel].any(axis=1))
    if bad_bands.size:
        raise FitError(
            f"band(s) {bad_bands.tolist()} have no valid reflector pixel (all saturated or masked)",
            hint="use reflector images with a shorter exposure",
        )
    lv = np.where(valid, rad, 0.0)
    m = valid.astype(np.float64)
    r = refl[:, None]
    s, b, pix_ok, iterations, converged = _alternate(lv[:, sel], m[:, sel], r, int(max_iter), tol)
    if not isinstance(sel, slice):  # Eq. 14 with that S at every pixel
        b, pix_ok = _brightness(lv, m, s * refl)
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise FitError(
            "the spectral factors came out non-positive: the reflector radiance is inconsistent",
            hint="check the reflector pixels (mask, saturation) and the vignetting",
        )

    # gauge: median brightness 1
    brightness = np.where(pix_ok, b, np.nan)
    med = float(np.nanmedian(brightness))
    if not np.isfinite(med) or med <= 0:
        raise FitError("the reflector brightness came out non-positive: the data are inconsistent")
    brightness = brightness / med
    s = s * med

    residual_rms = _residual_rms(rad, valid, s * refl, brightness)
    return IlluminationFit(
        spectral_factor=s,
        brightness=brightness,
        image_brightness=None if idx is None else _image_brightness(brightness, idx),
        residual_rms=residual_rms,
        iterations=iterations,
        converged=converged,
    )


def _checked_inputs(
    radiance: np.ndarray, reflectance: np.ndarray | float, image_index: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Check the inputs of :func:`fit_illumination`.

    Return ``(radiance float64, R_s per band, image index or None)``.
    """
    rad = np.asarray(radiance, dtype=np.float64)
    if rad.ndim != 2 or rad.shape[0] < 1 or rad.shape[1] < 1:
        raise InputError(f"radiance must be (n_bands, n_pix), got shape {rad.shape}")
    n_bands, n_pix = rad.shape
    refl = np.asarray(reflectance, dtype=np.float64).ravel()
    if refl.size == 1:
        refl = np.repeat(refl, n_bands)
    if refl.size != n_bands or not np.all(np.isfinite(refl)) or np.any(refl <= 0):
        raise InputError(
            f"reflector reflectance must be {n_bands} positive values (one per band), got "
            f"{np.asarray(reflectance)!r}",
            hint="check the reflector's reflectance in the target catalog",
        )
    idx = None
    if image_index is not None:
        idx = np.asarray(image_index).ravel()
        bad_index = not np.issubdtype(idx.dtype, np.integer) or (idx.size and idx.min() < 0)
        if idx.size != n_pix or bad_index:
            raise InputError(
                f"image_index must be {n_pix} non-negative integers (one per pixel), got "
                f"shape {idx.shape}, dtype {idx.dtype}"
            )
    return rad, refl, idx


def _checked_fit_pixels(fit_pixels: np.ndarray | None, n_pix: int) -> np.ndarray | slice:
    """Return the pixels S is fitted from: a (n_pix,) bool array, or a full slice.

    A full slice for None and also when every pixel is selected (the plain fit's sums, bit for
    bit).
    """
    if fit_pixels is None:
        return slice(None)
    sel = np.asarray(fit_pixels)
    if sel.dtype != bool or sel.shape != (n_pix,):
        raise InputError(f"fit_pixels must be {n_pix} booleans (one per pixel), got shape {sel.shape}, "
                         f"dtype {sel.dtype}")
    if not sel.any():
        raise InputError("fit_pixels selects no pixel", hint="pass None to fit S from every pixel")
    return slice(None) if sel.all() else sel


def _brightness(lv: np.ndarray, m: np.ndarray, sr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return B by Eq. 14 for a given ``S R`` per band, and the pixels that have one.

    ``B = sum_l L S R / sum_l (S R)^2`` over the valid entries (``lv`` the radiance with 0
    where invalid, ``m`` 1 where valid); B is 0 where a pixel has no valid band.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        b = (sr @ lv) / ((sr * sr) @ m)
    ok = np.isfinite(b)
    return np.where(ok, b, 0.0), ok


def _alternate(
    lv: np.ndarray, m: np.ndarray, r: np.ndarray, max_iter: int, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, bool]:
    """Alternate Eq. 13 and Eq. 14 on the valid reflector entries.

    Alternate Eq. 13 and Eq. 14 from ``B = mean over lambda of L`` on the valid entries (``lv``
    the radiance with 0 where invalid, ``m`` 1 where valid, ``r`` R_s as a column). Returns
    ``(S, B, pixels with a B, iterations, converged)``.
    """
    n_bands = lv.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        b = np.sum(lv, axis=0) / np.sum(m, axis=0)  # paper: B = mean over lambda of L
    pix_ok = np.isfinite(b)
    b = np.where(pix_ok, b, 0.0)
    s = np.ones(n_bands)
    iterations = 0
    converged = False
    rc = r[:, 0]
    # R is one number per band, so both sums are matrix-vector products: no (band, pixel)
    # temporaries (35 MB each on 25 bands x 176k pixels, freshly mapped every iteration)
    for iterations in range(1, max_iter + 1):
        # Eq. 13: S = sum_x L B R / sum_x (B R)^2 = R (L B) / (R^2 (M B^2))  (valid entries only)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_new = (rc * (lv @ b)) / (rc * rc * (m @ (b * b)))
        # Eq. 14: B = sum_l L S R / sum_l (S R)^2
        sr = s_new * rc
        with np.errstate(invalid="ignore", divide="ignore"):
            b = (sr @ lv) / ((sr * sr) @ m)
        b = np.where(pix_ok, b, 0.0)
        change = float(np.max(np.abs(s_new - s) / np.abs(s_new)))
        s = s_new
        if change < tol:
            converged = True
            break
    return s, b, pix_ok, iterations, converged


def _residual_rms(rad: np.ndarray, valid: np.ndarray, factor: np.ndarray, brightness: np.ndarray) -> float:
    """Return the RMS of the relative residual ``L / (S R B) - 1`` (NaN without any entry).

    Over the valid finite entries, one band at a time (no (band, pixel) temporaries);
    ``factor`` is ``S R`` per band.
    """
    total, count = 0.0, 0
    for band in range(rad.shape[0]):
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = rad[band] / (factor[band] * brightness) - 1.0
        rel = rel[valid[band] & np.isfinite(rel)]
        total += float(np.sum(rel * rel))
        count += rel.size
    return float(np.sqrt(total / count)) if count else float("nan")


def _image_brightness(brightness: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Median brightness of every reflector image (NaN for an image without a finite B)."""
    n_img = int(idx.max()) + 1 if idx.size else 0
    image_brightness = np.full(n_img, np.nan)
    for k in range(n_img):
        sel = brightness[idx == k]
        if np.isfinite(sel).any():
            image_brightness[k] = float(np.nanmedian(sel))
    return image_brightness


def eq16_reflectance(
    target_dn: np.ndarray,
    reflector_dn: np.ndarray | float,
    reflector_reflectance: np.ndarray | float,
) -> np.ndarray:
    """Return the baseline reflectance of Eq. 16: ``R = I_target / I_reflector * R_s`` per band.

    Parameters
    ----------
    target_dn : numpy.ndarray
        Band axis first: (n_bands, ...) e.g. (n_bands, H, W).
    reflector_dn : numpy.ndarray or float
        One value per band (n_bands,) (e.g. the mean reflector DN) or an array broadcastable to
        ``target_dn`` (e.g. a reflector image (n_bands, H, W): a per-pixel ratio that also
        cancels vignetting).
    reflector_reflectance : numpy.ndarray or float
        R_s, a scalar or (n_bands,).

    Returns
    -------
    numpy.ndarray
        float64 reflectance, the shape of ``target_dn``; NaN where the reflector DN is not
        positive.

    Raises
    ------
    InputError
        On shapes that do not fit.

    Notes
    -----
    Raw DN: the same exposure for target and reflector and a negligible black level are
    assumed, as in the paper's baseline [1]_. Exact only if the reflector image was uniformly
    lit: any brightness gradient or shadow on the reflector is imprinted, inverted, on the
    target reflectance.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    tgt = np.asarray(target_dn, dtype=np.float64)
    if tgt.ndim < 1:
        raise InputError("target_dn must have a band axis first, got a scalar")
    n_bands = tgt.shape[0]
    extra = (1,) * (tgt.ndim - 1)

    def per_band(value: np.ndarray | float, name: str) -> np.ndarray:
        arr = np.asarray(value, dtype=np.float64)
        if arr.ndim == 1 and arr.size == n_bands and tgt.ndim > 1:
            return arr.reshape((n_bands,) + extra)
        try:
            np.broadcast_shapes(arr.shape, tgt.shape)
        except ValueError:
            raise InputError(
                f"{name} of shape {arr.shape} does not fit target_dn of shape {tgt.shape}"
            ) from None
        return arr

    ref = per_band(reflector_dn, "reflector_dn")
    rs = per_band(reflector_reflectance, "reflector_reflectance")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = tgt / ref * rs
    return np.where(np.isfinite(out) & (ref > 0), out, np.nan)


# --------------------------------------------------------------------------- light over time

#: Interpolation of the light between reflector captures (:func:`capture_weights`).
INTERPOLATION_MODES = ("nearest", "linear")


@dataclass(frozen=True, eq=False)
class FrameIllumination:
    """The light of each flight frame, from :func:`frame_illumination`.

    Attributes
    ----------
    spectral_factor : numpy.ndarray
        (n_frames, n_bands) ``S(lambda, tau) = level(tau) colour(lambda, tau)``.
    level : numpy.ndarray
        (n_frames,) the overall brightness level ``beta(tau)``.
    colour : numpy.ndarray
        (n_frames, n_bands) ``s(lambda, tau)``, geometric mean 1 over the bands.
    weights : numpy.ndarray
        (n_frames, n_captures) the capture weights used (rows sum to 1).
    irradiance_used : numpy.ndarray
        (n_frames,) bool: the frame's level came from its irradiance reading.
    """

    spectral_factor: np.ndarray
    level: np.ndarray
    colour: np.ndarray
    weights: np.ndarray
    irradiance_used: np.ndarray


def split_level(spectral_factor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split spectral factors into brightness level and colour: ``S(lambda) = beta s(lambda)``.

    Parameters
    ----------
    spectral_factor : numpy.ndarray
        (n_bands,) or (n_captures, n_bands).

    Returns
    -------
    beta : numpy.ndarray
        ``exp(mean_lambda log S(lambda))`` (the geometric mean over the bands), shape () or
        (n_captures,).
    s : numpy.ndarray
        ``S(lambda) / beta`` (geometric mean 1), the input's shape.

    Raises
    ------
    InputError
        Unless every S is positive and finite.

    Notes
    -----
    ``S`` of Eq. 11-13 [1]_ is known only together with ``B``: a common factor moves between them.
    ``beta`` is the part of it that a change of brightness alone (a passing cloud) changes, ``s``
    the light's colour.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    s = np.asarray(spectral_factor, dtype=np.float64)
    if s.ndim not in (1, 2) or s.shape[-1] < 1 or not np.all(np.isfinite(s) & (s > 0)):
        raise InputError(f"spectral factors must be positive and finite, (n_bands,) or (n, n_bands); got shape {s.shape}")
    level = np.exp(np.mean(np.log(s), axis=-1))
    return level, s / np.expand_dims(level, -1)


def capture_weights(capture_times: np.ndarray, frame_times: np.ndarray, mode: str = "linear") -> np.ndarray:
    """Return the weights ``w[f, c]`` of the reflector captures for each frame time (rows sum to 1).

    Parameters
    ----------
    capture_times, frame_times : numpy.ndarray
        Times in seconds on one clock.
    mode : {"linear", "nearest"}
        ``nearest``: weight 1 on the capture closest in time (the earlier one on a tie).
        ``linear``: between the two captures ``a < b`` that bracket the frame,
        ``w_b = (tau - tau_a) / (tau_b - tau_a)``, ``w_a = 1 - w_b``; before the first and after
        the last capture the light is held at that capture's (no extrapolation).

    Returns
    -------
    numpy.ndarray
        (n_frames, n_captures); with one capture all weights are 1.

    Raises
    ------
    InputError
        For an unknown mode, no capture, NaN times, or two captures at the same time.

    Notes
    -----
    The paper assumes the light constant during a calibration dataset [1]_; over a flight the
    reflector captures' ``S(lambda)`` of Eq. 13 are interpolated in time with these weights
    (:func:`frame_illumination`).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    if mode not in INTERPOLATION_MODES:
        raise InputError(f"illumination interpolation {mode!r}: use one of {', '.join(INTERPOLATION_MODES)}")
    tc = np.asarray(capture_times, dtype=np.float64).ravel()
    tf = np.asarray(frame_times, dtype=np.float64).ravel()
    n_c = tc.size
    if n_c < 1:
        raise InputError("at least one reflector capture is needed")
    w = np.zeros((tf.size, n_c))
    if n_c == 1:
        w[:, 0] = 1.0
        return w
    if not (np.all(np.isfinite(tc)) and np.all(np.isfinite(tf))):
        raise InputError("every reflector capture and flight frame needs a time to interpolate the light")
    order = np.argsort(tc, kind="stable")
    ts = tc[order]
    if np.any(np.diff(ts) <= 0):
        raise InputError(f"two reflector captures have the same time ({ts.tolist()})")
    rows = np.arange(tf.size)
    if mode == "nearest":
        k = np.clip(np.searchsorted(ts, tf, side="left"), 1, n_c - 1)
        later = (ts[k] - tf) < (tf - ts[k - 1])
        w[rows, order[np.where(later, k, k - 1)]] = 1.0
        return w
    clamped = np.clip(tf, ts[0], ts[-1])
    k = np.clip(np.searchsorted(ts, clamped, side="right"), 1, n_c - 1)
    wb = (clamped - ts[k - 1]) / (ts[k] - ts[k - 1])
    w[rows, order[k - 1]] += 1.0 - wb
    w[rows, order[k]] += wb
    return w


def frame_illumination(
    capture_spectral_factor: np.ndarray,
    capture_times: np.ndarray,
    frame_times: np.ndarray,
    mode: str = "linear",
    *,
    capture_irradiance: np.ndarray | None = None,
    frame_irradiance: np.ndarray | None = None,
) -> FrameIllumination:
    """Estimate the light of every frame from the reflector captures and, optionally, an irradiance sensor.

    Parameters
    ----------
    capture_spectral_factor : numpy.ndarray
        (n_captures, n_bands): each capture's S from Eq. 11-14 with median reflector B = 1.
    capture_times, frame_times : numpy.ndarray
        Times in seconds (see :func:`capture_weights`).
    mode : {"linear", "nearest"}
        Interpolation between captures (:func:`capture_weights`).
    capture_irradiance : numpy.ndarray, optional
        (n_captures,) irradiance readings ``E_c`` (any unit, the same sensor as the frames').
    frame_irradiance : numpy.ndarray, optional
        (n_frames,) irradiance readings ``E(tau)``.

    Returns
    -------
    FrameIllumination
        ``S(lambda, tau) = beta(tau) s(lambda, tau)`` with its level, colour and weights.

    Raises
    ------
    InputError
        On spectral factors, times or a mode that :func:`split_level` and
        :func:`capture_weights` reject, or irradiance readings not one per capture and frame.

    Notes
    -----
    Per capture ``c``: ``S_c(lambda) = beta_c s_c(lambda)`` (:func:`split_level`). With the
    weights ``w`` of :func:`capture_weights`:

    - colour: ``s(lambda, tau) = sum_c w_c(tau) s_c(lambda)``;
    - level without irradiance: ``beta(tau) = sum_c w_c(tau) beta_c``;
    - level with irradiance readings: the captures anchor the scale,
      ``beta(tau) = E(tau) sum_c w_c(tau) beta_c / E_c``: the sensor's ratio carries the level
      between (and beyond) the captures. A frame without a reading (NaN), or any capture
      without one, falls back to the interpolated level.

    The decomposition is Eq. 11 of [1]_, ``J_lambda(x) = B(x) S(lambda)``, applied per capture.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    s_c = np.asarray(capture_spectral_factor, dtype=np.float64)
    if s_c.ndim == 1:
        s_c = s_c[None]
    beta_c, colour_c = split_level(s_c)
    w = capture_weights(capture_times, frame_times, mode)
    colour = w @ colour_c
    level = w @ beta_c
    used = np.zeros(w.shape[0], dtype=bool)
    if capture_irradiance is not None and frame_irradiance is not None:
        e_c = np.asarray(capture_irradiance, dtype=np.float64).ravel()
        e_f = np.asarray(frame_irradiance, dtype=np.float64).ravel()
        if e_c.size != s_c.shape[0] or e_f.size != w.shape[0]:
            raise InputError(
                f"irradiance readings: {e_c.size} for {s_c.shape[0]} captures and {e_f.size} for {w.shape[0]} frames"
            )
        if np.all(np.isfinite(e_c) & (e_c > 0)):
            used = np.isfinite(e_f) & (e_f > 0)
            scale = w @ (beta_c / e_c)
            level = np.where(used, np.where(used, e_f, 1.0) * scale, level)
    return FrameIllumination(
        spectral_factor=level[:, None] * colour, level=level, colour=colour, weights=w, irradiance_used=used
    )


def colour_change(capture_spectral_factor: np.ndarray) -> np.ndarray:
    """Return the largest relative change of the light's colour between consecutive captures.

    Parameters
    ----------
    capture_spectral_factor : numpy.ndarray
        (n_captures, n_bands) spectral factors.

    Returns
    -------
    numpy.ndarray
        (n_captures - 1,) ``max_lambda |s_{c+1}(lambda) / s_c(lambda) - 1|``, with ``s`` the
        colour of :func:`split_level` (the level removed, so a passing cloud does not count).

    Notes
    -----
    Eq. 11 of [1]_ takes the light's colour ``S(lambda)`` as one per dataset; this measures how
    much it changed between the captures of a flight.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    _, colour = split_level(np.atleast_2d(np.asarray(capture_spectral_factor, dtype=np.float64)))
    if colour.shape[0] < 2:
        return np.zeros(0)
    return np.max(np.abs(colour[1:] / colour[:-1] - 1.0), axis=1)


def centre_brightness(uv: np.ndarray, brightness: np.ndarray, *, reject: float = 0.1, iterations: int = 3) -> float:
    """Return the brightness at the reflector's centre from a plane fit ``B(u, v) = a + b u + c v``: ``a``.

    Parameters
    ----------
    uv : numpy.ndarray
        (n, 2) reflector-plane coordinates (metres, origin at the reflector's centre) of the
        pixels.
    brightness : numpy.ndarray
        (n,) their B (Eq. 14).
    reject : float
        Pixels more than this (relative) off the plane are left out of the refits: a shadow or
        a glint.
    iterations : int
        Refits after the first least squares.

    Returns
    -------
    float
        ``a``; NaN when fewer than 3 finite pixels remain.

    Notes
    -----
    The median-B gauge of :func:`fit_illumination` depends on which part of a non-uniformly lit
    reflector the camera sees (pose, crop); for a light that is linear over the reflector, ``a``
    does not, so captures under different light compare by it.
    """
    p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(brightness, dtype=np.float64).ravel()
    keep = np.all(np.isfinite(p), axis=1) & np.isfinite(b)
    a = float("nan")
    for _ in range(int(iterations) + 1):
        if np.count_nonzero(keep) < 3:
            return float("nan")
        design = np.column_stack([np.ones(np.count_nonzero(keep)), p[keep]])
        coef, *_ = np.linalg.lstsq(design, b[keep], rcond=None)
        a = float(coef[0])
        pred = coef[0] + p @ coef[1:]
        with np.errstate(invalid="ignore", divide="ignore"):
            new = np.isfinite(b) & np.all(np.isfinite(p), axis=1) & (np.abs(b / pred - 1.0) <= reject)
        if np.array_equal(new, keep):
            break
        keep = new
    return a


def shared_reflector_pixels(masks, owner, min_pixels: int = 1) -> tuple[list[np.ndarray], bool]:
    """Restrict each reflector image's pixels to sensor pixels shared by the captures.

    Parameters
    ----------
    masks : sequence of numpy.ndarray
        One (H, W) bool per reflector image: its reflector pixels.
    owner : sequence of int
        The capture index of each image.
    min_pixels : int
        Pixels every capture must keep.

    Returns
    -------
    masks : list of numpy.ndarray
        The first of these that leaves every capture at least ``min_pixels`` pixels:
        1. ``mask_k & C`` with ``C`` the pixels every image saw the reflector at;
        2. ``C`` the pixels every capture saw it at in some image: the intersection over the
        captures of the union of their images' masks;
        3. the masks unchanged (the captures barely overlap on the sensor).
    shared : bool
        True for 1. and 2., False for 3.

    Raises
    ------
    InputError
        When the number of masks and of capture indices differ.

    Notes
    -----
    With the radiance ``L = U(I) / (t V_hat)`` of Eq. 11 and a vignetting estimate
    ``V_hat = V (1 + e(lambda, x))``, Eq. 13 gives ``S(lambda)`` times a ``B^2``-weighted mean of
    ``1 / (1 + e(lambda, x))`` over the pixels the capture used, and Eq. 14's ``B(x)`` absorbs
    the band-common part of ``e`` (so does the level read from it, :func:`centre_brightness`).
    Captures that see the reflector at different pixels thus get different biases, which become
    an error of ``S(lambda, tau)`` between them; on the same pixels they share the bias, and its
    band-dependent part cancels in ``S_c / S_0`` (to first order, up to the different ``B``
    weights; exactly the same pixels in every image, 1., also the same weight per pixel). The
    band-common part enters the level read at the reflector centre (a gradient of ``e`` across
    the image looks like a light gradient in one image): it cancels as far as the captures have
    the reflector centre near the same pixel.
    """
    ms = [np.asarray(m, dtype=bool) for m in masks]
    own = np.asarray(owner, dtype=np.int64).ravel()
    if len(ms) != own.size:
        raise InputError(f"{len(ms)} reflector masks but {own.size} capture indices")
    if not ms:
        return ms, True
    every_image = np.logical_and.reduce(ms)
    every_capture = np.ones(ms[0].shape, dtype=bool)
    for c in np.unique(own):
        every_capture &= np.logical_or.reduce([m for m, o in zip(ms, own) if o == c])
    for common in (every_image, every_capture):
        out = [m & common for m in ms]
        if all(sum(int(np.count_nonzero(m)) for m, o in zip(out, own) if o == c) >= int(min_pixels)
               for c in np.unique(own)):
            return out, True
    return ms, False
