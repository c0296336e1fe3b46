"""Factory radiometric models of Parrot, DJI and Sentera cameras.

Parrot Sequoia, DJI multispectral (Phantom 4 Multispectral, Mavic 3M) and Sentera, from the
calibration their files carry.

Pure numpy (OpenCV for the DJI band alignment maps); the metadata is read by each maker's
module under ``pipeline.ingest.cameras``. MicaSense's model, the field components that may
replace a factory's, and the pieces every maker shares are in :mod:`mscal_core.factory`.
Each function's docstring cites the maker's document it follows.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from .factory import vignetting_2d


def sequoia_irradiance(
    dn: np.ndarray,
    *,
    f_number: float,
    exposure_s: float,
    iso: float,
    sensor_model: Sequence[float],
    vignetting: np.ndarray,
) -> np.ndarray:
    """Parrot Sequoia: irradiance on the sensor ``I = f^2 (p - B) / (A e g + C)`` [1]_.

    Parameters
    ----------
    dn : numpy.ndarray
        One band as stored.
    f_number : float
        ``f``, EXIF FNumber.
    exposure_s : float
        ``e``, EXIF ExposureTime in seconds.
    iso : float
        ``g``, the ISO value itself (EXIF ISOSpeedRatings, not ISO/100).
    sensor_model : sequence of float
        ``A, B, C`` = XMP ``Camera:SensorModel`` of the band (firmware >= 1.2.1).
    vignetting : numpy.ndarray
        ``1 / V``, which multiplies the stored value into ``p`` (``V`` the 2-D polynomial of
        :func:`vignetting_polynomial_2d`).

    Returns
    -------
    numpy.ndarray
        float64, the shape of ``dn``, floored at 0; "homogeneous to SI units but with an
        arbitrary scaling factor" (Parrot): a relative radiance.

    Raises
    ------
    ValueError
        On a non-positive exposure, ISO or f-number.

    References
    ----------
    .. [1] Parrot, application note SEQ AN 01, "Sequoia: pixel value to irradiance", quoted on
           Parrot's developer forum, "Details of Irradiance List tag for Sunshine sensor", 83-85.
    """
    a, b, c = (float(x) for x in sensor_model)
    if exposure_s <= 0 or iso <= 0 or f_number <= 0:
        raise ValueError(f"exposure ({exposure_s}), ISO ({iso}) and f-number ({f_number}) must be positive")
    p = np.asarray(dn, dtype=np.float64) * vignetting
    out = f_number**2 * (p - b) / (a * exposure_s * iso + c)
    return np.maximum(out, 0.0)


def vignetting_polynomial_2d(
    shape: tuple[int, int], coefficients: Sequence[float], exponents: Sequence[float]
) -> np.ndarray:
    """Return the 2-D polynomial ``P(x, y) = sum_i c_i (x/W)^ex_i (y/H)^ey_i`` itself.

    The relative illumination, Parrot's ``V`` [1]_; :func:`vignetting_2d` is its reciprocal, the
    correction.

    Parameters
    ----------
    shape, coefficients, exponents
        As in :func:`vignetting_2d`.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64.

    Raises
    ------
    ValueError
        When the exponents are not two per coefficient.

    References
    ----------
    .. [1] Parrot, application note SEQ AN 01, "Sequoia: pixel value to irradiance", quoted on
           Parrot's developer forum, "Details of Irradiance List tag for Sunshine sensor", 83-85.
    """
    return 1.0 / vignetting_2d(shape, coefficients, exponents)


def dji_vignetting_correction(shape: tuple[int, int], center: Sequence[float], k: Sequence[float]) -> np.ndarray:
    """Return the DJI P4 Multispectral / Mavic 3M vignetting correction, which *multiplies* the image.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the band.
    center : sequence of float
        ``(CenterX, CenterY)`` = ``drone-dji:CalibratedOpticalCenterX/Y`` in pixels.
    k : sequence of float
        XMP ``drone-dji:VignettingData`` (k[0]..k[5]).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float64 ``1 + k0 r + k1 r^2 + ... + k5 r^6`` ([1]_ Eq. 8-9, [2]_), ``r`` the
        distance in pixels of pixel (x, y) from ``center``.

    References
    ----------
    .. [1] DJI, "P4 Multispectral Image Processing Guide" v1.0 (2020.07).
    .. [2] DJI, "Mavic 3M Image Processing Guide" v1.0 (2023.08).
    """
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = np.hypot(x - float(center[0]), y - float(center[1]))
    out = np.ones_like(r)
    for power, kk in enumerate(k, start=1):
        out += float(kk) * r**power
    return out


def dji_camera_value(
    dn: np.ndarray,
    *,
    black_level: float,
    sensor_gain: float,
    exposure_us: float,
    vignetting: np.ndarray,
    gain_adjustment: float = 1.0,
    full_scale: float = 65535.0,
) -> np.ndarray:
    """DJI multispectral camera value ``X = pCam (p - p_BL) V / (g t)``.

    Parameters
    ----------
    dn : numpy.ndarray
        One band as stored.
    black_level : float
        ``BlackLevel`` in stored DN.
    sensor_gain : float
        ``g`` = ``drone-dji:SensorGain``.
    exposure_us : float
        ``t`` = ``drone-dji:ExposureTime`` in microseconds (converted to seconds).
    vignetting : numpy.ndarray
        ``V``, the correction (:func:`dji_vignetting_correction`).
    gain_adjustment : float
        ``pCam`` = ``drone-dji:SensorGainAdjustment`` ("individual difference correction").
    full_scale : float
        ``p = DN / full_scale``, ``p_BL = BlackLevel / full_scale`` ([1]_ Eq. 6-9, [2]_ Eq. 4-9:
        "divide the original number by 65535").

    Returns
    -------
    numpy.ndarray
        float64 camera value, the shape of ``dn``; floored at 0.

    Raises
    ------
    ValueError
        On a non-positive exposure or gain.

    Notes
    -----
    Reflectance is ``X / E`` with ``E`` = ``drone-dji:Irradiance`` up to one constant common to
    all bands (the guide's NDVI uses only ratios).

    References
    ----------
    .. [1] DJI, "P4 Multispectral Image Processing Guide" v1.0 (2020.07).
    .. [2] DJI, "Mavic 3M Image Processing Guide" v1.0 (2023.08).
    """
    if exposure_us <= 0 or sensor_gain <= 0:
        raise ValueError(f"exposure ({exposure_us} us) and gain ({sensor_gain}) must be positive")
    p = (np.asarray(dn, dtype=np.float64) - float(black_level)) / full_scale
    out = gain_adjustment * p * vignetting / (sensor_gain * exposure_us * 1e-6)
    return np.maximum(out, 0.0)


def dji_alignment_map(shape: tuple[int, int], center: Sequence[float], dewarp: Sequence[float] | None,
                      hmatrix: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Return the map that puts one DJI multispectral band on the designed ideal image plane.

    DJI "Mavic 3M Image Processing Guide" v1.0 (2023.08), section II steps 2-3 (the "P4
    Multispectral Image Processing Guide" v1.0 has the same two steps):

    - step 2, distortion correction: ``cv2.undistort`` with the camera matrix
      ``[[fx, 0, CenterX + cx], [0, fy, CenterY + cy], [0, 0, 1]]`` (``fx, fy, cx, cy, k1, k2,
      p1, p2, k3`` = ``drone-dji:DewarpData`` after its date, ``cx, cy`` offsets from
      ``CenterX, CenterY`` = ``drone-dji:CalibratedOpticalCenterX/Y``), the same matrix as the
      new camera matrix ("changing the camera matrix ... should be avoided");
    - step 3, ``cv2.warpPerspective`` with ``H`` = ``drone-dji:CalibratedHMatrix`` (row-major
      3 x 3, "from the individual physical image plane to the designed ideal image plane").

    Together the aligned band is ``A(x) = I(D(H^-1 x))`` with ``D`` OpenCV's distortion model
    (radial ``k1, k2, k3``, tangential ``p1, p2``) in that camera matrix. Step 4 (residual
    alignment of bands exposed at different times, by features) is left to ``mscal register``.

    Parameters
    ----------
    shape : tuple of int
        ``(height, width)`` of the band image (the output has the same size).
    center : sequence of float
        ``(CenterX, CenterY)`` in pixels.
    dewarp : sequence of float or None
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3``; None: no distortion correction (step 3 only).
    hmatrix : sequence of float
        The nine values of ``CalibratedHMatrix``, row-major.

    Returns
    -------
    map_x, map_y : numpy.ndarray
        float32 ``(height, width)`` source coordinates for ``cv2.remap``.
    """
    h, w = shape
    hm = np.asarray(hmatrix, dtype=np.float64).reshape(3, 3)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    src = np.linalg.solve(hm, np.stack([x.ravel(), y.ravel(), np.ones(x.size)]))
    u, v = src[0] / src[2], src[1] / src[2]
    if dewarp is not None:
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = (float(d) for d in dewarp)
        ox, oy = float(center[0]) + cx, float(center[1]) + cy
        xn, yn = (u - ox) / fx, (v - oy) / fy
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        u, v = xd * fx + ox, yd * fy + oy
    return u.reshape(h, w).astype(np.float32), v.reshape(h, w).astype(np.float32)


def remap_band(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Resample one band with ``cv2.remap`` maps (bilinear; NaN where the source lies outside).

    Parameters
    ----------
    image : numpy.ndarray
        ``(height, width)`` band.
    maps : tuple of numpy.ndarray
        ``(map_x, map_y)`` as from :func:`dji_alignment_map`.

    Returns
    -------
    numpy.ndarray
        float32 ``(height, width)``.
    """
    return cv2.remap(np.asarray(image, dtype=np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def color_transform(channels: np.ndarray, matrix: Sequence[float], rows: Sequence[int]) -> np.ndarray:
    """Sentera crosstalk removal: band ``i`` = ``sum_j M[i, j] DN_j`` over the image channels.

    Parameters
    ----------
    channels : numpy.ndarray
        ``(H, W, C)`` as stored (R, G, B for a JPEG).
    matrix : sequence of float
        The ``C x C`` row-major XMP ``Camera:ColorTransform`` (rows = output bands in
        ``Camera:BandName`` order, columns = channels: checked against [1]_).
    rows : sequence of int
        The output bands wanted.

    Returns
    -------
    numpy.ndarray
        ``(len(rows), H, W)`` float64.

    References
    ----------
    .. [1] Sentera, "Double 4K multispectral NDVI and NDRE calculations" (support.senterasensors.com).
    """
    ch = np.asarray(channels, dtype=np.float64)
    c = ch.shape[2]
    m = np.asarray(matrix, dtype=np.float64).reshape(c, c)
    return np.einsum("kc,hwc->khw", m[list(rows)], ch)


def sentera_relative_radiance(
    dn: np.ndarray,
    *,
    black_level: float,
    gain: float,
    exposure_s: float,
    bits_per_sample: int,
    channels: np.ndarray | None = None,
    matrix: Sequence[float] | None = None,
    channel: int | None = None,
) -> np.ndarray:
    """Relative radiance of one Sentera band (Double 4K, 6X).

    Parameters
    ----------
    dn : ndarray
        The band's stored DN ``(H, W)`` (its channel of a multi-channel file).
    black_level : float
        Black level in DN (0 for the Double 4K's JPEGs).
    gain : float
        ``ISO / 100``.
    exposure_s : float
        Exposure time in seconds.
    bits_per_sample : int
        The file's bits per sample: a DN of ``2**bits - 1`` is clipped.
    channels, matrix, channel : optional
        The whole ``(H, W, C)`` image, the ``C x C`` XMP ``Camera:ColorTransform`` and the
        band's row of it: with all three the band is first crosstalk-corrected
        (:func:`color_transform`).

    Returns
    -------
    ndarray
        ``(H, W)`` float64, relative (unit 1), NaN where a channel that enters the band is
        clipped.

    Notes
    -----
    Sentera's "autoexposure" normalisation::

        L = max((sum_j M[b, j] DN_j - p_BL) / (g t_e), 0)

    with ``M`` the colour transform (the identity when the file writes none: ``L`` from the
    band's own DN), ``g = ISO / 100`` and ``t_e`` the exposure. A pixel where any channel
    with a non-zero weight in row ``b`` (or the band's own DN) is at ``2**bits - 1`` is NaN:
    the band is unknown there (Sentera excludes saturated pixels).

    References
    ----------
    SenteraLLC, py-radiometric-corrections (autoexposure correction);
    Sentera, "Double 4K multispectral NDVI and NDRE calculations", support.senterasensors.com.
    """
    if matrix is not None and channel is not None and channels is not None:
        mixed = color_transform(channels, matrix, [channel])[0]
        n = channels.shape[2]
        used = [j for j in range(n) if matrix[n * channel + j] != 0]
        clipped = np.any(channels[:, :, used] >= 2**bits_per_sample - 1, axis=2)
    else:
        mixed = np.asarray(dn, dtype=np.float64)
        clipped = np.asarray(dn) >= 2**bits_per_sample - 1
    out = np.maximum((mixed - black_level) / (gain * exposure_s), 0.0)
    out[clipped] = np.nan
    return out


def sunshine_irradiance(ch0: Sequence[float], gain_index: Sequence[int], integration_ms: Sequence[float],
                        calibration: dict[int, float]) -> float:
    """Parrot Sequoia sunshine sensor: relative irradiance ``mean(CH0 / (g(i) t))`` [1]_.

    Parameters
    ----------
    ch0 : sequence of float
        The readings' ``CH0`` counts.
    gain_index : sequence of int
        Each reading's gain index ``i``.
    integration_ms : sequence of float
        Each reading's integration time ``t`` (ms).
    calibration : dict of int to float
        ``{i: CH0_i / t_i}`` from ``IrradianceCalibrationMeasurement`` (one light, each gain
        index): ``g(i) = calibration[i] / calibration[1]``, relative to gain index 1.

    Returns
    -------
    float
        The mean of ``CH0 / (g(i) t)`` (relative units: the sensor is linear with no black
        level, ``count ~ gain(i) t E``) over the readings whose gain index the table holds,
        with a positive time, not saturated (65535).

    Raises
    ------
    ValueError
        When no reading is usable.

    References
    ----------
    .. [1] Parrot, developer forum, "Details of Irradiance List tag for Sunshine sensor", post 2.
    """
    ref = calibration.get(1)
    values = []
    for c, i, t in zip(ch0, gain_index, integration_ms):
        g = calibration.get(int(i))
        if g is None or ref is None or not t > 0 or c >= 65535 or not g > 0:
            continue
        values.append(float(c) / ((g / ref) * float(t)))
    if not values:
        raise ValueError("no usable sunshine reading (unknown gain index or saturated)")
    return float(np.mean(values))
