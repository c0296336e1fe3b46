"""Band co-registration measured on the pixels: pure numpy + OpenCV, no I/O.

Whatever put the bands of a multi-lens capture on one pixel grid (a camera's own metadata,
the transforms of ``mscal register``, or nothing), what is left is measured here, on the
pixels, per band against a reference band:

1. each band is decimated (``cv2.resize``, ``INTER_AREA``) to at most ``max_side`` pixels on
   its long side (:func:`decimate`; NaN pixels -- outside a warped band's cover, clipped --
   are filled with the band's median and remembered);
2. both become gradient-magnitude images (:func:`mscal_core.registration.gradient_image`): the
   edges of vegetation are the same in red and NIR although their contrast is reversed;
3. the frame, less a border of ``border`` (5 %) on each side, is cut into ``tiles`` (3 x 3);
   a tile is used only if it is covered by both bands (>= 95 % finite pixels), has texture in
   both (mean gradient >= :data:`MIN_TEXTURE` of the normalised image and >= a quarter of the
   frame's median tile) and the bands correlate there (ECC correlation >= ``min_cc``);
4. per tile the translation ``d`` with ``band(x + d) ~ ref(x)`` (the convention of
   :mod:`mscal_core.registration`: ``H = [[1, 0, dx], [0, 1, dy], [0, 0, 1]]`` maps reference
   pixels to band pixels) is found by phase correlation (``cv2.phaseCorrelate``, Hanning
   window) refined by ECC (Evangelidis & Psarakis 2008, ``cv2.findTransformECC``,
   ``MOTION_TRANSLATION``), and scaled back to full-resolution pixels;
5. per band the robust summary is the median over the tiles used of the shift magnitude
   ``|d|`` (px), with the median ``dx``, ``dy`` and the number of tiles (:class:`BandResidual`).

A translation pooled over several captures (the median of every tile's ``d``,
:func:`pooled_translations`) is the image registration that refines a metadata alignment
(DJI's Image Processing Guide, step 4): :func:`translation_transforms` gives it as the
(band, 3, 3) transforms of :func:`mscal_core.alignment.align_bands`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .errors import InputError
from .registration import gradient_image

MAX_SIDE = 640  # px on the long side of the measured images (cheap: a few ms per band)
TILES = (3, 3)  # rows, columns
BORDER = 0.05  # of each side left out: lens borders, warped bands' NaN edges
MIN_COVER = 0.95  # finite pixels of a tile in both bands
MIN_TEXTURE = 0.004  # mean gradient magnitude of a tile of the percentile-normalised image
MIN_CC = 0.2  # ECC correlation of the gradient tiles after the shift: the bands correlate there


@dataclass(frozen=True)
class BandResidual:
    """The residual shift of one band against the reference band.

    Attributes
    ----------
    median_px : float
        Median over the tiles used of the shift magnitude (full-resolution px); NaN when no
        tile could be used.
    dx, dy : float
        Median shift components (px): ``band(x + d) ~ ref(x)``.
    n_tiles : int
        Tiles used (texture, cover and correlation passed).
    shifts : tuple of (float, float)
        Each used tile's shift ``(dx, dy)`` (px), for pooling over captures.
    points : tuple of (float, float)
        Each used tile's centre ``(x, y)`` (full-resolution px), in the order of ``shifts``.
    """

    median_px: float
    dx: float
    dy: float
    n_tiles: int
    shifts: tuple[tuple[float, float], ...] = ()
    points: tuple[tuple[float, float], ...] = ()


def decimation(shape: tuple[int, int], max_side: int = MAX_SIDE) -> float:
    """Scale factor (<= 1) that brings the long side of ``shape`` to at most ``max_side``.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the image.
    max_side : int
        Largest long side (px) wanted.

    Returns
    -------
    float
        ``min(1, max_side / max(H, W))``.
    """
    return min(1.0, float(max_side) / float(max(shape)))


def decimate(image: np.ndarray, max_side: int = MAX_SIDE) -> tuple[np.ndarray, np.ndarray, float]:
    """Image decimated to at most ``max_side`` px on its long side (``INTER_AREA``).

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` image; NaN pixels allowed.
    max_side : int
        Largest long side (px) of the result.

    Returns
    -------
    image : numpy.ndarray
        float32, NaN filled with the median of the finite pixels (of every 4th row and column;
        0 if none) before decimating.
    cover : numpy.ndarray
        float32, the fraction of finite full-resolution pixels under each decimated pixel.
    scale : float
        The scale factor (:func:`decimation`); 1 when the image is small enough as it is.
    """
    a = np.asarray(image, dtype=np.float32)
    ok = np.isfinite(a)
    if not ok.all():
        sub = a[::4, ::4]
        fill = float(np.median(sub[np.isfinite(sub)])) if np.isfinite(sub).any() else 0.0
        a = np.where(ok, a, np.float32(fill))
    s = decimation(a.shape, max_side)
    if s >= 1.0:
        return a, ok.astype(np.float32), 1.0
    size = (max(1, round(a.shape[1] * s)), max(1, round(a.shape[0] * s)))
    return (cv2.resize(a, size, interpolation=cv2.INTER_AREA),
            cv2.resize(ok.astype(np.float32), size, interpolation=cv2.INTER_AREA), s)


def tile_boxes(shape: tuple[int, int], tiles: tuple[int, int] = TILES,
               border: float = BORDER) -> list[tuple[int, int, int, int]]:
    """Cut a grid of tiles over an image less a border.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the image.
    tiles : tuple of int
        ``(rows, columns)`` of tiles.
    border : float
        Fraction of each side left out.

    Returns
    -------
    list of tuple of int
        ``(y0, y1, x0, x1)`` (end exclusive) of each tile, row by row.
    """
    h, w = shape
    ys = np.linspace(border * h, (1 - border) * h, tiles[0] + 1).round().astype(int)
    xs = np.linspace(border * w, (1 - border) * w, tiles[1] + 1).round().astype(int)
    return [(int(ys[i]), int(ys[i + 1]), int(xs[j]), int(xs[j + 1]))
            for i in range(tiles[0]) for j in range(tiles[1])]


def tile_shift(ref_grad: np.ndarray, band_grad: np.ndarray) -> tuple[float, float, float]:
    """Measure the translation between two gradient tiles.

    Parameters
    ----------
    ref_grad, band_grad : numpy.ndarray
        Gradient tiles (:func:`mscal_core.registration.gradient_image`) of the same shape.

    Returns
    -------
    dx, dy : float
        The translation ``d`` with ``band(x + d) ~ ref(x)`` (tile px).
    cc : float
        The ECC correlation of the tiles after it.

    Notes
    -----
    Phase correlation (Hanning window) refined by ECC (``MOTION_TRANSLATION``); the phase
    estimate, with its own correlation, when ECC fails or moves further than a quarter of the
    tile's shorter side from it.

    References
    ----------
    Evangelidis, G. D. and Psarakis, E. Z., "Parametric image alignment using enhanced
    correlation coefficient maximization", IEEE Trans. Pattern Analysis and Machine
    Intelligence 30(10), 2008.
    """
    r = np.ascontiguousarray(ref_grad, dtype=np.float32)
    b = np.ascontiguousarray(band_grad, dtype=np.float32)
    win = cv2.createHanningWindow((r.shape[1], r.shape[0]), cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(r, b, win)
    warp = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-5)
    try:
        cc, warp = cv2.findTransformECC(r, b, warp, cv2.MOTION_TRANSLATION, crit, None, 1)
    except cv2.error:
        return float(dx), float(dy), _shifted_correlation(r, b, float(dx), float(dy))
    ex, ey = float(warp[0, 2]), float(warp[1, 2])
    if math.hypot(ex - dx, ey - dy) > 0.25 * min(r.shape):  # ECC ran away from the phase peak
        return float(dx), float(dy), _shifted_correlation(r, b, float(dx), float(dy))
    return ex, ey, float(cc)


def _shifted_correlation(ref: np.ndarray, band: np.ndarray, dx: float, dy: float) -> float:
    m = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float64)
    w = cv2.warpAffine(band, m, (ref.shape[1], ref.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REFLECT)
    x, y = ref.astype(np.float64).ravel(), w.astype(np.float64).ravel()
    x, y = x - x.mean(), y - y.mean()
    d = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / d) if d > 0 else float("nan")


def band_residual(ref: np.ndarray, band: np.ndarray, *, max_side: int = MAX_SIDE, tiles: tuple[int, int] = TILES,
                  border: float = BORDER, min_cc: float = MIN_CC) -> BandResidual:
    """Measure the residual shift of ``band`` against ``ref`` (two images of one grid).

    Parameters
    ----------
    ref, band : numpy.ndarray
        ``(H, W)`` images of the reference band and of the band; NaN pixels allowed.
    max_side : int
        Long side (px) the bands are decimated to (:func:`decimate`).
    tiles : tuple of int
        ``(rows, columns)`` of tiles (:func:`tile_boxes`).
    border : float
        Fraction of each side left out.
    min_cc : float
        ECC correlation a tile's gradients must reach after the shift to be used.

    Returns
    -------
    BandResidual
        Median shift magnitude and components over the tiles used (full-resolution px), and
        each used tile's shift and centre.

    Raises
    ------
    InputError
        When the two images differ in size.

    Notes
    -----
    Measured in tiles on decimated gradient images (the module docstring's steps 1-5).
    """
    if ref.shape != band.shape:
        raise InputError(f"bands of one capture differ in size: {ref.shape} vs {band.shape}")
    return _residual(_prepared(ref, max_side), _prepared(band, max_side), tiles, border, min_cc)


def _prepared(image: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Decimate an image and take its gradient magnitude (with the finite fraction and scale)."""
    a, ok, s = decimate(image, max_side)
    return gradient_image(a), ok, s


def _residual(ref: tuple[np.ndarray, np.ndarray, float], band: tuple[np.ndarray, np.ndarray, float],
              tiles: tuple[int, int], border: float, min_cc: float) -> BandResidual:
    (rg, r_ok, s), (bg, b_ok, _) = ref, band
    boxes = tile_boxes(rg.shape, tiles, border)
    texture = [min(float(rg[y0:y1, x0:x1].mean()), float(bg[y0:y1, x0:x1].mean())) for y0, y1, x0, x1 in boxes]
    floor = max(MIN_TEXTURE, 0.25 * float(np.median(texture)))
    shifts, points = [], []
    for (y0, y1, x0, x1), tex in zip(boxes, texture):
        cover = min(float(r_ok[y0:y1, x0:x1].mean()), float(b_ok[y0:y1, x0:x1].mean()))
        if cover < MIN_COVER or tex < floor or min(y1 - y0, x1 - x0) < 16:
            continue
        dx, dy, cc = tile_shift(rg[y0:y1, x0:x1], bg[y0:y1, x0:x1])
        if math.isfinite(cc) and cc >= min_cc:
            shifts.append((dx / s, dy / s))
            points.append(((x0 + (x1 - x0 - 1) / 2 + 0.5) / s - 0.5, (y0 + (y1 - y0 - 1) / 2 + 0.5) / s - 0.5))
    return summarise(shifts, points)


def summarise(shifts: Sequence[tuple[float, float]],
              points: Sequence[tuple[float, float]] = ()) -> BandResidual:
    """Summarise tile shifts (px): median magnitude, median components and count.

    Parameters
    ----------
    shifts : sequence of (float, float)
        Each tile's ``(dx, dy)``.
    points : sequence of (float, float)
        Each tile's centre ``(x, y)``, kept in the result.

    Returns
    -------
    BandResidual
        ``median(|d|)``, ``median(dx)``, ``median(dy)``, the count, the shifts and the points;
        NaN figures and no tiles when ``shifts`` is empty.
    """
    if not shifts:
        nan = float("nan")
        return BandResidual(nan, nan, nan, 0, ())
    d = np.asarray(shifts, dtype=np.float64)
    return BandResidual(float(np.median(np.hypot(d[:, 0], d[:, 1]))), float(np.median(d[:, 0])),
                        float(np.median(d[:, 1])), len(d), tuple((float(x), float(y)) for x, y in d),
                        tuple((float(x), float(y)) for x, y in points))


def stack_residuals(stack: np.ndarray, reference: int, *, max_side: int = MAX_SIDE, tiles: tuple[int, int] = TILES,
                    border: float = BORDER, min_cc: float = MIN_CC) -> list[BandResidual]:
    """Measure every band of a ``(band, H, W)`` capture against band ``reference``.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(band, H, W)`` capture, its bands on one grid.
    reference : int
        The reference band.
    max_side : int
        Long side (px) the bands are decimated to (:func:`decimate`).
    tiles : tuple of int
        ``(rows, columns)`` of tiles (:func:`tile_boxes`).
    border : float
        Fraction of each side left out.
    min_cc : float
        ECC correlation a tile's gradients must reach after the shift to be used.

    Returns
    -------
    list of BandResidual
        One per band (:func:`band_residual`); the reference band's own entry is zero, with no
        tiles.

    Raises
    ------
    InputError
        Unless ``stack`` is ``(band, H, W)`` and ``reference`` one of its bands.
    """
    if stack.ndim != 3 or not 0 <= reference < stack.shape[0]:
        raise InputError(f"reference band {reference} of a stack of shape {stack.shape}")
    ref = _prepared(stack[reference], max_side)  # once for every band
    return [BandResidual(0.0, 0.0, 0.0, 0, ()) if k == reference
            else _residual(ref, _prepared(stack[k], max_side), tiles, border, min_cc) for k in range(stack.shape[0])]


def pooled_translations(per_capture: Sequence[Sequence[BandResidual]]) -> np.ndarray:
    """Pool the tile shifts of several captures into one translation per band.

    Parameters
    ----------
    per_capture : sequence of sequence of BandResidual
        Per capture, per band (:func:`stack_residuals`).

    Returns
    -------
    numpy.ndarray
        (band, 2) float64: per band the median ``(dx, dy)`` over every used tile of every capture,
        NaN for a band no tile measured, 0 for the reference band; (0, 2) without captures.

    References
    ----------
    DJI, "P4 Multispectral Image Processing Guide" v1.0 (2020.07), step 4: image registration
    on top of the metadata's alignment.
    """
    if not per_capture:
        return np.zeros((0, 2))
    n = len(per_capture[0])
    out = np.full((n, 2), np.nan)
    for k in range(n):
        d = [s for cap in per_capture for s in cap[k].shifts]
        if d:
            out[k] = np.median(np.asarray(d, dtype=np.float64), axis=0)
        elif all(cap[k].n_tiles == 0 and cap[k].median_px == 0.0 for cap in per_capture):
            out[k] = 0.0  # the reference band
    return out


def translation_transforms(shifts: np.ndarray) -> np.ndarray:
    """Turn per-band shifts into (band, 3, 3) transforms ``[[1, 0, dx], [0, 1, dy], [0, 0, 1]]``.

    Parameters
    ----------
    shifts : numpy.ndarray
        (band, 2) ``(dx, dy)`` (:func:`pooled_translations`).

    Returns
    -------
    numpy.ndarray
        (band, 3, 3) float64 reference pixels -> band pixels, for
        :func:`mscal_core.alignment.align_bands`; NaN shifts become 0.
    """
    d = np.nan_to_num(np.asarray(shifts, dtype=np.float64).reshape(-1, 2))
    h = np.tile(np.eye(3), (len(d), 1, 1))
    h[:, 0, 2], h[:, 1, 2] = d[:, 0], d[:, 1]
    return h


def sample_every(n: int, limit: int) -> int:
    """Step ``N`` of an every-Nth sample of ``n`` captures that keeps at most ``limit``.

    Parameters
    ----------
    n : int
        Captures.
    limit : int
        Most captures wanted (below 1 counts as 1).

    Returns
    -------
    int
        ``max(1, ceil(n / limit))``.
    """
    return max(1, math.ceil(n / max(1, limit)))


MIN_AFFINE_TILES = 6  # tiles (pooled) below which a band's affine is not estimated


def pooled_affines(per_capture: Sequence[Sequence[BandResidual]]) -> np.ndarray | None:
    """Fit one affine transform per band to the tile shifts of several captures.

    Parameters
    ----------
    per_capture : sequence of sequence of BandResidual
        Per capture, per band (:func:`stack_residuals`).

    Returns
    -------
    numpy.ndarray or None
        (band, 3, 3) float64 transforms (reference pixels to band pixels, identity for the
        reference band, :func:`mscal_core.alignment.align_bands`); None without captures, when
        a band other than the reference has fewer than :data:`MIN_AFFINE_TILES` tiles, or when a
        fit fails.

    Notes
    -----
    Each used tile says that reference pixel ``p`` (its centre) is band pixel ``p + d``; the
    affine ``A`` with ``A p ~ p + d`` over every tile of every capture is fitted by least median
    of squares (``cv2.estimateAffine2D``, ``LMEDS``): rotation, scale and shear between lenses
    that one translation leaves.
    """
    if not per_capture:
        return None
    n = len(per_capture[0])
    out = np.tile(np.eye(3), (n, 1, 1))
    for k in range(n):
        pts = [p for cap in per_capture for p in cap[k].points]
        d = [s for cap in per_capture for s in cap[k].shifts]
        if not pts and all(cap[k].median_px == 0.0 for cap in per_capture):
            continue  # the reference band
        if len(pts) < MIN_AFFINE_TILES:
            return None
        src = np.asarray(pts, dtype=np.float64)
        a, _ = cv2.estimateAffine2D(src, src + np.asarray(d, dtype=np.float64), method=cv2.LMEDS)
        if a is None or not np.isfinite(a).all():
            return None
        out[k, :2] = a
    return out
