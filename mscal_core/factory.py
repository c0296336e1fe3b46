"""Factory radiometric model of MicaSense-style cameras, from the calibration their files carry.

MicaSense RedEdge/Altum files hold, per band, a radiometric calibration ``[a1, a2, a3]``, a
black level, and a vignetting model (a radial polynomial around a centre, or on newer
firmware a 2-D polynomial). MicaSense's published model turns a raw frame into radiance
(W m-2 sr-1 nm-1)::

    L(x, y) = V(x, y) * a1 / g * (p - p_BL) / (t_e + a2 * y - a3 * t_e * y)

with ``p = DN / 2**bits_per_sample`` the DN normalised by the *container* depth (2**16 for
the 12-bit RedEdge data stored in 16-bit TIFFs: a1 is scaled for that), ``p_BL`` the
normalised black level, ``g = ISO / 100`` the gain, ``t_e`` the exposure in seconds, ``y``
the pixel row (0 at the top), ``a2, a3`` the row-gradient (rolling shutter) terms, and
``V`` the vignetting correction (>= 1 away from the centre, so it *multiplies* the DN).
Negative radiance (noise around the black level) is floored at 0, as MicaSense does.

Components from the field fits may replace the factory's, one at a time:

- *field vignetting*: ``V(x, y)`` of the paper (Eq. 8-10, max 1, multiplies the scene) enters
  as the correction ``1 / V``;
- *field response*: the paper's inverse response ``U`` (Eq. 5-7, over the sensor's DN ``k``)
  replaces the linear ``p - p_BL``. ``U`` is relative (its scale is free in Eq. 5), so it is
  scaled by :func:`field_response_scale` to the factory's linear model over the lower half
  of the sensor range, where the sensor is linear by design: the radiance keeps its unit and
  only the *shape* (black level, shoulder) comes from the field.

Pure numpy (OpenCV for the polygon mask): the metadata is read by each camera maker's module,
``pipeline.ingest.cameras``.

References
----------
.. [1] MicaSense, ``micasense/imageprocessing`` (GitHub), ``micasense/image.py`` and
       ``micasense/metadata.py``: the RedEdge / Altum radiometric calibration model and its
       XMP tags.
.. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np


@dataclass(frozen=True)
class PanelStats:
    """Statistics of an image over a panel region.

    Attributes
    ----------
    mean, std : float
        Mean and standard deviation over the region.
    count : int
        Pixels in the region.
    saturated : int
        Of those, pixels above the saturation level.
    """

    mean: float
    std: float
    count: int
    saturated: int


def radial_vignetting(shape: tuple[int, int], center: Sequence[float], poly: Sequence[float]) -> np.ndarray:
    """Return the radial vignetting correction ``V = 1 / (1 + k1 r + k2 r^2 + ... + kn r^n)``.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the band.
    center : sequence of float
        ``(cx, cy)`` in pixels.
    poly : sequence of float
        ``[k1, ..., kn]`` in the order MicaSense's XMP ``VignettingPolynomial`` lists them
        (lowest power first, no constant term) [1]_.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64, 1 at the centre. ``r`` is the distance in pixels of the pixel centre
        grid point ``(x, y)`` (x = column, y = row, integer coordinates) from the centre.

    References
    ----------
    .. [1] MicaSense, ``micasense/imageprocessing`` (GitHub): ``image.py``, ``metadata.py``.
    """
    h, w = shape
    cx, cy = float(center[0]), float(center[1])
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = np.hypot(x - cx, y - cy)
    denom = np.ones_like(r)
    for power, k in enumerate(poly, start=1):
        denom += float(k) * r**power
    return 1.0 / denom


def vignetting_2d(
    shape: tuple[int, int], coefficients: Sequence[float], exponents: Sequence[float]
) -> np.ndarray:
    """Return the 2-D polynomial vignetting correction ``V = 1 / sum_i c_i u^ex_i v^ey_i``.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the band.
    coefficients : sequence of float
        ``c_i``.
    exponents : sequence of float
        The flat ``[ex_0, ey_0, ex_1, ey_1, ...]`` list of XMP ``VignettingPolynomial2DName``
        [1]_.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64; ``u = x / W`` and ``v = y / H`` are the normalised column and row.

    Raises
    ------
    ValueError
        When the exponents are not two per coefficient.

    References
    ----------
    .. [1] MicaSense, ``micasense/imageprocessing`` (GitHub): ``image.py``, ``metadata.py``.
    """
    if len(exponents) != 2 * len(coefficients):
        raise ValueError(
            f"2-D vignetting needs two exponents per coefficient, got {len(exponents)} for {len(coefficients)}"
        )
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u /= w
    v /= h
    poly = np.zeros((h, w), dtype=np.float64)
    for i, c in enumerate(coefficients):
        poly += float(c) * u ** float(exponents[2 * i]) * v ** float(exponents[2 * i + 1])
    return 1.0 / poly


def vignetting_map(
    shape: tuple[int, int],
    center: Sequence[float] | None = None,
    poly: Sequence[float] | None = None,
    *,
    poly_2d: Sequence[float] | None = None,
    exponents_2d: Sequence[float] | None = None,
) -> np.ndarray:
    """Return the factory vignetting correction of one band: the radial form if given, else the 2-D form.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the band.
    center, poly : sequence of float, optional
        The radial form (:func:`radial_vignetting`).
    poly_2d, exponents_2d : sequence of float, optional
        The 2-D form (:func:`vignetting_2d`).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64 correction map.

    Raises
    ------
    ValueError
        When neither form is given.

    Notes
    -----
    The convention differs from mscal's field ``V`` (max 1, divides the energy): the factory map
    is >= 1 off-centre and multiplies the DN; ``1 / map`` scaled to max 1 is the field-style
    vignetting.
    """
    if center is not None and poly is not None and len(poly) > 0:
        return radial_vignetting(shape, center, poly)
    if poly_2d is not None and exponents_2d is not None and len(poly_2d) > 0:
        return vignetting_2d(shape, poly_2d, exponents_2d)
    raise ValueError("no vignetting model: give center and poly, or poly_2d and exponents_2d")


def row_gradient(height: int, exposure_s: float, a2: float, a3: float) -> np.ndarray:
    """Return the row-gradient factor ``R(y) = t_e / (t_e + a2 y - a3 t_e y)`` per row.

    Parameters
    ----------
    height : int
        Rows of the band.
    exposure_s : float
        ``t_e`` in seconds.
    a2, a3 : float
        The row-gradient (rolling shutter) terms of the calibration [1]_.

    Returns
    -------
    numpy.ndarray
        Shape ``(H, 1)`` float64, ``y = 0`` the top row: ``1 / t_e`` times it is the rolling
        shutter's ``1 / (t_e + a2 y - a3 t_e y)`` of :func:`radiance`.

    References
    ----------
    .. [1] MicaSense, ``micasense/imageprocessing`` (GitHub): ``image.py``, ``metadata.py``.
    """
    y = np.arange(height, dtype=np.float64)[:, None]
    return exposure_s / (exposure_s + a2 * y - a3 * exposure_s * y)


def radiance(
    dn: np.ndarray,
    *,
    exposure_s: float,
    gain: float,
    black_level: float,
    calibration: Sequence[float],
    vignetting: np.ndarray,
    bits_per_sample: int = 16,
    signal: np.ndarray | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Compute the factory radiance ``L = V a1/g (p - p_BL) / (t_e + a2 y - a3 t_e y)``, W m-2 sr-1 nm-1.

    Parameters
    ----------
    dn : numpy.ndarray
        One band ``(H, W)`` as stored.
    exposure_s : float
        ``t_e`` in seconds.
    gain : float
        ``g = ISO / 100``.
    black_level : float
        In DN.
    calibration : sequence of float
        ``[a1, a2, a3]``.
    vignetting : numpy.ndarray
        The correction map (:func:`vignetting_map`, or ``1/V`` of a field fit).
    bits_per_sample : int
        The container depth the DN are normalised by.
    signal : numpy.ndarray, optional
        Replaces ``p - p_BL`` (a field response, see :func:`field_response_signal`).
    out : numpy.ndarray, optional
        ``(H, W)`` array (e.g. float32) that receives the result, rounded once from the float64
        computation.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64 radiance (``out`` if given); negative values are floored at 0.

    Raises
    ------
    ValueError
        On a non-positive exposure or gain, or a vignetting map or signal that does not match
        the image.

    Notes
    -----
    MicaSense's model [1]_, ``p = DN / 2**bits_per_sample``, ``p_BL = black_level / 2**bits_per_sample``.
    The paper's field parts [2]_ may replace the factory's: ``vignetting = 1 / V`` (Eq. 8-10),
    ``signal = c U(I)`` (Eq. 5-7, :func:`field_response_signal`); with both, the result is
    ``L = U(I) / (t V)`` (Eq. 2 and 4) times ``c a1 / g`` and the row gradient.

    References
    ----------
    .. [1] MicaSense, ``micasense/imageprocessing`` (GitHub): ``image.py``, ``metadata.py``.
    .. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration for
           Multispectral Cameras", ICRA 2017.
    """
    if exposure_s <= 0 or gain <= 0:
        raise ValueError(f"exposure ({exposure_s}) and gain ({gain}) must be positive")
    a1, a2, a3 = (float(c) for c in calibration)
    dn = np.asarray(dn)
    if vignetting.shape != dn.shape:
        raise ValueError(f"vignetting map {vignetting.shape} does not match the image {dn.shape}")
    # one float64 work array, every step in place (fewer passes and allocations than the
    # expression; each product in the same order, so the same values bit for bit)
    if signal is None:
        work = dn.astype(np.float64)  # (astype, then in place: numpy's casting loops are slower)
        work -= float(black_level)
        work *= 2.0**-bits_per_sample  # the quotient by 2**bits exactly (a power of two), for a third of its CPU
        np.multiply(vignetting, work, out=work)
    else:
        p = np.asarray(signal, dtype=np.float64)
        if p.shape != dn.shape:
            raise ValueError(f"signal {p.shape} does not match the image {dn.shape}")
        work = vignetting * p
    work *= row_gradient(dn.shape[0], exposure_s, a2, a3)
    work *= a1 / (gain * exposure_s)
    if out is None:
        np.maximum(work, 0.0, out=work)
        return work
    out[...] = work
    _floor_at_zero(out, work)
    return out


def _floor_at_zero(out: np.ndarray, work: np.ndarray) -> None:
    """Floor ``out``, which holds ``work`` cast already, at 0: ``out[...] = max(work, 0)``.

    OpenCV's threshold on the float32 values when all are finite (it gives ``max``'s value
    then: +0 for -0 and below, and the cast commutes with it), a third of ``np.maximum``'s CPU
    with the check; else ``np.maximum`` on ``work`` (which keeps NaN) and the cast again.
    """
    if out.dtype == np.float32 and out.ndim == 2 and out.flags.c_contiguous and np.isfinite(out).all():
        done = cv2.threshold(out, 0.0, 0.0, cv2.THRESH_TOZERO, dst=out)[1]
        if done.ctypes.data == out.ctypes.data and done.shape == out.shape:
            return
    np.maximum(work, 0.0, out=work)
    out[...] = work


def field_response_scale(
    inverse_response: np.ndarray, *, dn_shift: int, black_level: float, bits_per_sample: int = 16
) -> float:
    """Return the scale ``c`` that puts a field inverse response on the factory's linear scale.

    Parameters
    ----------
    inverse_response : numpy.ndarray
        ``U(k)`` for every sensor DN ``k`` (Eq. 5-7, relative units).
    dn_shift : int
        A stored value is ``k * 2**dn_shift``.
    black_level : float
        ``p_BL`` in stored DN.
    bits_per_sample : int
        The container depth.

    Returns
    -------
    float
        ``c = sum U f / sum U**2`` over the DN used.

    Raises
    ------
    ValueError
        When U is zero over the lower half of the DN range.

    Notes
    -----
    ``U`` is known only up to scale (Eq. 5 of [1]_). ``c`` minimises ``sum_k (c U(k) - f(k))**2``,
    ``f(k) = (k 2**dn_shift - p_BL) / 2**bits_per_sample`` the factory's ``p - p_BL``, over the
    finite ``U(k)`` whose stored value is above the black level, up to half of the sensor's
    range (where the factory model, linear, holds).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration for
           Multispectral Cameras", ICRA 2017.
    """
    u = np.asarray(inverse_response, dtype=np.float64)
    k = np.arange(u.size, dtype=np.float64)
    stored = k * 2.0**dn_shift
    f = (stored - float(black_level)) / 2.0**bits_per_sample
    use = (stored > black_level) & (k <= (u.size - 1) / 2) & np.isfinite(u)
    den = float(np.sum(u[use] ** 2))
    if not np.any(use) or den <= 0:
        raise ValueError("the inverse response is zero over the lower half of the DN range: no scale")
    return float(np.sum(u[use] * f[use]) / den)


def field_response_signal(dn: np.ndarray, inverse_response: np.ndarray, *, dn_shift: int, scale: float) -> np.ndarray:
    """Return ``c U(DN >> dn_shift)`` per pixel: the field response in the factory's units.

    Parameters
    ----------
    dn : numpy.ndarray
        One band as stored.
    inverse_response : numpy.ndarray
        ``U(k)`` for every sensor DN.
    dn_shift : int
        Stored DN are ``k * 2**dn_shift``.
    scale : float
        ``c`` from :func:`field_response_scale`.

    Returns
    -------
    numpy.ndarray
        float64, the shape of ``dn``: ``c U(I)``, ``I = DN >> dn_shift`` clipped to the table,
        with ``U(I(x)) = t E(x)`` of Eq. 4 of [1]_; it replaces ``p - p_BL`` in :func:`radiance`.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration for
           Multispectral Cameras", ICRA 2017.
    """
    k = np.right_shift(np.asarray(dn).astype(np.int64), dn_shift)
    k = np.clip(k, 0, inverse_response.size - 1)
    return scale * np.asarray(inverse_response, dtype=np.float64)[k]


def panel_stats(image: np.ndarray, mask: np.ndarray, saturation: float | None = None) -> PanelStats:
    """Return the mean, standard deviation, pixel count and saturated count of ``image`` over ``mask``.

    Parameters
    ----------
    image : numpy.ndarray
        One band.
    mask : numpy.ndarray
        Bool, the shape of ``image``.
    saturation : float, optional
        Pixels above it count as saturated (0 saturated when None).

    Returns
    -------
    PanelStats
        The statistics (population standard deviation).

    Raises
    ------
    ValueError
        When the mask does not match the image, or selects no pixel.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != image.shape:
        raise ValueError(f"mask {mask.shape} does not match the image {image.shape}")
    values = np.asarray(image, dtype=np.float64)[mask]
    if values.size == 0:
        raise ValueError("the panel region is empty")
    sat = 0 if saturation is None else int(np.count_nonzero(values > saturation))
    return PanelStats(mean=float(values.mean()), std=float(values.std()), count=int(values.size), saturated=sat)


def polygon_mask(shape: tuple[int, int], corners: Sequence[Sequence[float]]) -> np.ndarray:
    """Return the boolean ``(H, W)`` mask of the pixels inside (and on the edges of) a polygon.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)``.
    corners : sequence of (x, y)
        Pixel coordinates (x = column), e.g. a panel's four corners.

    Returns
    -------
    numpy.ndarray
        Bool ``(H, W)``.
    """
    pts = np.round(np.asarray(corners, dtype=np.float64)).astype(np.int32).reshape(-1, 1, 2)
    mask = np.zeros(shape, dtype=np.uint8)
    cv2.fillPoly(mask, [pts], 1)
    return mask.astype(bool)


def thermal_kelvin(dn: np.ndarray) -> np.ndarray:
    """Convert a MicaSense Altum / Altum-PT LWIR band to kelvin.

    Parameters
    ----------
    dn : numpy.ndarray
        The band as stored: centi-kelvin.

    Returns
    -------
    numpy.ndarray
        float64 ``T = DN / 100`` K ([1]_: ``(DN - 27315) * 0.01`` in degrees C).

    References
    ----------
    .. [1] MicaSense, ``micasense/imageprocessing`` (GitHub), ``micasense/image.py``.
    """
    return np.asarray(dn, dtype=np.float64) / 100.0


def upright(image: np.ndarray, orientation: int) -> np.ndarray:
    """Turn an image stored with EXIF ``orientation`` to how it is meant to be seen.

    Parameters
    ----------
    image : numpy.ndarray
        ``(..., H, W)``: the last two axes are rows and columns.
    orientation : int
        EXIF Orientation: 0 or 1 as stored, 3 rotated 180 degrees (as Parrot Sequoia writes),
        2 mirrored left-right, 4 mirrored top-bottom.

    Returns
    -------
    numpy.ndarray
        A view of ``image`` turned upright (``image`` itself for 0 and 1).

    Raises
    ------
    ValueError
        For orientations 5-8, which swap the axes (not supported), and any other value.
    """
    if orientation in (0, 1):
        return image
    if orientation == 3:
        return image[..., ::-1, ::-1]
    if orientation == 2:
        return image[..., :, ::-1]
    if orientation == 4:
        return image[..., ::-1, :]
    raise ValueError(f"EXIF orientation {orientation} (a 90 degree turn) is not supported")
