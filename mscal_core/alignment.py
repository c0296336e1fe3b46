"""Putting the bands of one capture on the reference band's grid.

Multi-lens cameras: each band is resampled through its homography ``H_b`` (reference pixels
to band pixels, :mod:`mscal_core.homography`), ``aligned_b(x) = band_b(H_b x)``
(:func:`warp_to_reference`, :func:`align_bands`). Snapshot mosaics: the bands share one lens
but each samples the scene a fraction of a pixel away from the mosaic's centre position;
:func:`shift_bands` moves them there by separable cubic convolution
(:func:`mosaic_centre_offsets`, :func:`cubic_weights`).
"""

from __future__ import annotations

import cv2
import numpy as np

from .errors import InputError
from .homography import map_points


def warp_to_reference(band: np.ndarray, homography: np.ndarray, shape: tuple[int, int],
                      interpolation: int = cv2.INTER_LINEAR, fill: float = float("nan")) -> np.ndarray:
    """Resample a band onto the reference grid: ``aligned(x) = band(H x)``.

    Parameters
    ----------
    band : numpy.ndarray
        ``(h, w)`` band image.
    homography : numpy.ndarray
        (3, 3) reference pixels -> band pixels.
    shape : tuple of int
        ``(H, W)`` of the reference grid.
    interpolation : int
        OpenCV interpolation flag (bilinear by default).
    fill : float
        Value of the pixels whose source lies outside the band.

    Returns
    -------
    numpy.ndarray
        ``(H, W)``, float32 unless ``band`` is float64.

    Notes
    -----
    ``cv2.warpPerspective`` with ``WARP_INVERSE_MAP`` (``H`` maps the output grid to the band)
    and a constant border of ``fill``.
    """
    src = band if band.dtype in (np.float32, np.float64) else band.astype(np.float32)
    return cv2.warpPerspective(src, np.asarray(homography, dtype=np.float64), (shape[1], shape[0]),
                               flags=interpolation | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=fill)


def valid_mask(homography: np.ndarray, band_shape: tuple[int, int], shape: tuple[int, int],
               margin: float = 1.0) -> np.ndarray:
    """Mask the reference pixels whose band pixel lies inside the band.

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3) reference pixels -> band pixels.
    band_shape : tuple of int
        ``(h, w)`` of the band.
    shape : tuple of int
        ``(H, W)`` of the reference grid.
    margin : float
        How far (px) inside the band's outermost pixel centres ``H x`` must lie.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` bool: ``margin <= (H x)_x <= w - 1 - margin`` and the same for the rows.
    """
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    p = map_points(homography, np.stack([xs.ravel(), ys.ravel()], axis=1))
    bh, bw = band_shape
    ok = (p[:, 0] >= margin) & (p[:, 0] <= bw - 1 - margin) & (p[:, 1] >= margin) & (p[:, 1] <= bh - 1 - margin)
    return ok.reshape(h, w)


def align_bands(stack: np.ndarray, transforms: np.ndarray, *, interpolation: int = cv2.INTER_LINEAR,
                fill: float = float("nan")) -> np.ndarray:
    """Resample a band stack ``(band, H, W)`` onto the reference band's grid.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(band, H, W)``.
    transforms : numpy.ndarray
        (band, 3, 3) as stored by the registration.
    interpolation : int
        OpenCV interpolation flag (bilinear by default).
    fill : float
        Value of the pixels that no band b sample covers.

    Returns
    -------
    numpy.ndarray
        ``aligned_b(x) = stack_b(H_b x)``, float32 (float64 for a float64 stack). A NaN pixel
        makes NaN the aligned pixels it contributes to (weight above 1e-3); an aligned pixel
        needing any sample outside the band is ``fill``.

    Raises
    ------
    InputError
        When the number of transforms does not match the stack.
    """
    transforms = np.asarray(transforms, dtype=np.float64)
    if transforms.shape != (stack.shape[0], 3, 3):
        raise InputError(f"{transforms.shape[0]} band transforms for a {stack.shape[0]}-band stack",
                         hint="use a registration of this camera")
    dtype = np.float64 if stack.dtype == np.float64 else np.float32
    out = np.empty(stack.shape, dtype=dtype)
    shape = stack.shape[1:]
    for b in range(stack.shape[0]):
        if np.allclose(transforms[b], np.eye(3), atol=0.0, rtol=0.0):
            out[b] = stack[b]
            continue
        band = stack[b].astype(dtype, copy=False)
        bad = ~np.isfinite(band)
        # warped with zeros outside; coverage and NaN by warping masks: OpenCV multiplies a
        # NaN border or NaN pixel into its neighbours even where the weight is 0
        h = transforms[b]
        val = warp_to_reference(np.where(bad, 0, band).astype(dtype) if bad.any() else band, h, shape,
                                interpolation, 0.0)
        inside = warp_to_reference(np.ones(shape, np.float32), h, shape, interpolation, 0.0)
        if bad.any():
            good = warp_to_reference((~bad).astype(np.float32), h, shape, interpolation, 0.0)
            val[good < inside - 1e-3] = np.nan
        val[inside < 1.0 - 1e-3] = fill
        out[b] = val
    return out


def mosaic_centre_offsets(pattern_shape: tuple[int, int]) -> np.ndarray:
    """Return the offsets ``(dx, dy)`` (band-grid pixels) of each band's samples from the mosaic's centre position.

    Parameters
    ----------
    pattern_shape : tuple of int
        ``(R, C)`` of the filter pattern.

    Returns
    -------
    numpy.ndarray
        (R*C, 2) float64 ``((c - (C-1)/2)/C, (r - (R-1)/2)/R)``, i.e. ``((c-2)/5, (r-2)/5)`` for
        a 5 x 5 mosaic: band (r, c) pixel (i, j) samples band-grid point ``(j + c/C, i + r/R)``
        (docs/architecture.md), the centre band ``((R-1)/2, (C-1)/2)`` samples
        ``(j + ((C-1)/2)/C, ...)``.
    """
    rows, cols = pattern_shape
    rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return np.stack([(cc.ravel() - (cols - 1) / 2) / cols, (rr.ravel() - (rows - 1) / 2) / rows], axis=1)


def cubic_weights(t: float, a: float = -0.5) -> np.ndarray:
    """Return Keys' cubic convolution weights of four neighbouring samples.

    Parameters
    ----------
    t : float
        Position of the point, a fraction in [0, 1) past sample 0.
    a : float
        Keys' parameter; -0.5 makes the interpolation exact for quadratics.

    Returns
    -------
    numpy.ndarray
        (4,) float64 weights of the samples at offsets -1, 0, 1, 2.

    Notes
    -----
    With ``d`` the distance to a sample: ``(a + 2) d^3 - (a + 3) d^2 + 1`` for ``d <= 1``,
    ``a d^3 - 5 a d^2 + 8 a d - 4 a`` for ``1 < d < 2``, 0 beyond.

    References
    ----------
    Keys, R. G., "Cubic convolution interpolation for digital image processing", IEEE Trans.
    Acoustics, Speech, and Signal Processing 29(6), 1981.
    """
    d = np.abs(np.array([-1.0, 0.0, 1.0, 2.0]) - t)
    return np.where(d <= 1, (a + 2) * d**3 - (a + 3) * d**2 + 1,
                    np.where(d < 2, a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a, 0.0))


def _shift_axis(band: np.ndarray, shift: float, axis: int, fill: float) -> np.ndarray:
    """Shift bands along an axis by cubic convolution.

    ``out[..., j] = band(j - shift)`` along ``axis`` by cubic convolution (four shifted copies
    and scalar weights: no fixed-point rounding of the position as in cv2.remap); ``fill`` where
    a needed sample is outside.
    """
    if shift == 0:
        return band
    pos0 = -shift
    k0 = int(np.floor(pos0))
    w = cubic_weights(pos0 - k0)
    n = band.shape[axis]
    out = np.zeros_like(band)
    valid = np.ones(n, dtype=bool)
    for m, wm in zip(range(-1, 3), w):
        k = k0 + m  # out[j] uses band[j + k]
        lo, hi = max(0, -k), min(n, n - k)
        if wm != 0.0:
            dst = [slice(None)] * band.ndim
            src = [slice(None)] * band.ndim
            dst[axis], src[axis] = slice(lo, hi), slice(lo + k, hi + k)
            out[tuple(dst)] += wm * band[tuple(src)]
            valid[:lo] = False
            valid[hi:] = False
    shape = [1] * band.ndim
    shape[axis] = n
    return np.where(valid.reshape(shape), out, fill)


def shift_bands(stack: np.ndarray, offsets: np.ndarray, *, fill: float = float("nan")) -> np.ndarray:
    """Resample each band of ``stack`` (band, H, W) to the common centre position.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(band, H, W)``.
    offsets : numpy.ndarray
        (band, 2): band b's samples sit ``offsets[b] = (dx, dy)`` px from the centre position
        (:func:`mosaic_centre_offsets`).
    fill : float
        Value of the pixels that need a sample outside the band.

    Returns
    -------
    numpy.ndarray
        float32 (float64 for a float64 stack): the value at the centre position of pixel (i, j)
        is band b at ``(j - dx, i - dy)`` of its own grid, by separable cubic convolution
        (:func:`cubic_weights`), exact for quadratic images.

    Raises
    ------
    InputError
        When the number of offsets does not match the stack.

    References
    ----------
    Keys, R. G., "Cubic convolution interpolation for digital image processing", IEEE Trans.
    Acoustics, Speech, and Signal Processing 29(6), 1981.
    """
    offsets = np.asarray(offsets, dtype=np.float64)
    if offsets.shape != (stack.shape[0], 2):
        raise InputError(f"{len(offsets)} offsets for a {stack.shape[0]}-band stack")
    dtype = np.float64 if stack.dtype == np.float64 else np.float32
    out = np.empty(stack.shape, dtype=dtype)
    for b, (dx, dy) in enumerate(offsets):
        band = stack[b].astype(dtype, copy=False)
        out[b] = _shift_axis(_shift_axis(band, float(dx), 1, fill), float(dy), 0, fill)
    return out
