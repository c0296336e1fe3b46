"""Find a reflectance panel in one band image without manual help, and compare polygons.

A calibrated panel (e.g. MicaSense RP02) shows up as the largest bright, *uniform*, convex
quadrilateral in the frame: its QR sticker and instruction card are bright too but
textured, vegetation and soil are neither quadrilateral nor uniform. :func:`detect_panel`

1. normalises the image to 8 bits between its 1st and 99.9th percentile and smooths it;
2. thresholds it at several levels from Otsu's up to near white, and keeps every outer
   contour whose polygon approximation (``cv2.approxPolyDP``) has 4 convex corners, covers at
   least ``min_area_frac`` of the frame, fills its polygon (a contour with holes or bites is
   not a panel) and has a near-square minimum-area rectangle (``max_aspect``);
3. keeps the candidates whose interior (eroded by 10 % of the side) has a coefficient of
   variation below ``max_cv``, and takes the largest;
4. refines its outline by thresholding a window around it at the mid level between the
   panel's interior median and the surround's median (the 50 % point of a blurred edge).

The outline is the whole bright surface. The region used for statistics is that outline
shrunk about its centroid (:func:`shrink_polygon`): the panel's edges are blurred, shadowed
by the panel's frame and shift between bands; MicaSense's published panel corners for its
sample panel capture are the inner ~75 % (linear) of the bright surface.

Pure numpy + OpenCV: no I/O. Returns None when no panel is found; the caller names the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .factory import polygon_mask

__all__ = [
    "PanelDetection",
    "QR_UPSCALE",
    "detect_panel",
    "order_corners",
    "panel_from_marker",
    "polygon_iou",
    "qr_serial",
    "sample_quad",
    "shrink_polygon",
]

# Linear fraction of the bright surface used for statistics: the panel's edges are blurred
# by the lens and soiled by handling, so only its centre is sampled (as MicaSense's published
# corners do). 0.75 reproduces those corners on the one real capture we have (IoU 0.91-0.93);
# a different panel or camera may want another value: it is a parameter of detect_panel.
DEFAULT_INSET = 0.75


@dataclass(frozen=True)
class PanelDetection:
    """A detected panel.

    Attributes
    ----------
    outline : numpy.ndarray
        (4, 2) float64 (x, y) corners of the bright surface in :func:`order_corners` order.
    cv : float
        Coefficient of variation (std / mean) of its interior.
    area : float
        Its area in pixels.
    """

    outline: np.ndarray
    cv: float
    area: float


def order_corners(corners: Sequence[Sequence[float]]) -> np.ndarray:
    """Order four corners clockwise on screen, as MicaSense lists them.

    Parameters
    ----------
    corners : sequence of (x, y)
        Four corners in any order.

    Returns
    -------
    numpy.ndarray
        (4, 2) float64 ordered clockwise on screen (bottom-right, bottom-left, top-left,
        top-right) from the one with the largest x + y -- the order MicaSense lists its panel
        corners in.

    Raises
    ------
    ValueError
        Unless there are four corners.
    """
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if pts.shape != (4, 2):
        raise ValueError(f"expected 4 corners, got {pts.shape[0]}")
    c = pts.mean(axis=0)
    # image y points down: increasing atan2 angle runs clockwise on screen
    ang = np.arctan2(pts[:, 1] - c[1], pts[:, 0] - c[0])
    pts = pts[np.argsort(ang)]
    start = int(np.argmax(pts.sum(axis=1)))
    return np.roll(pts, -start, axis=0)


def shrink_polygon(corners: Sequence[Sequence[float]], factor: float) -> np.ndarray:
    """Scale the polygon by ``factor`` about its vertex centroid.

    Parameters
    ----------
    corners : sequence of (x, y)
        The polygon's vertices.
    factor : float
        Linear scale, ``0 < factor <= 1``.

    Returns
    -------
    numpy.ndarray
        The scaled vertices, float64, in the same order.

    Raises
    ------
    ValueError
        For a factor outside ``(0, 1]``.
    """
    if not 0 < factor <= 1:
        raise ValueError(f"shrink factor must be in (0, 1], got {factor!r}")
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    c = pts.mean(axis=0)
    return c + (pts - c) * float(factor)


def polygon_iou(shape: tuple[int, int], a: Sequence[Sequence[float]], b: Sequence[Sequence[float]]) -> float:
    """Return the intersection over union of two polygons rasterised on a pixel grid.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the grid.
    a, b : sequence of (x, y)
        The polygons' vertices in pixels.

    Returns
    -------
    float
        Intersection over union of the two rasterised polygons.
    """
    ma, mb = polygon_mask(shape, a), polygon_mask(shape, b)
    union = np.count_nonzero(ma | mb)
    return float(np.count_nonzero(ma & mb) / union) if union else 0.0


def _to_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(img, [1.0, 99.9])
    if not hi > lo:
        return np.zeros(img.shape, dtype=np.uint8)
    u8 = np.clip((img - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)
    return cv2.GaussianBlur(u8, (5, 5), 0)


def _interior(shape: tuple[int, int], quad: np.ndarray) -> np.ndarray:
    """Pixels of the quadrilateral away from its edges (eroded by 10 % of its side)."""
    mask = polygon_mask(shape, quad).astype(np.uint8)
    side = np.sqrt(max(cv2.contourArea(quad.astype(np.float32)), 1.0))
    k = max(3, int(round(0.1 * side)) | 1)
    return cv2.erode(mask, np.ones((k, k), np.uint8)).astype(bool)


def _quad(contour: np.ndarray, min_area: float, max_aspect: float) -> np.ndarray | None:
    """Return the contour's 4-corner convex approximation if it looks like a panel, else None."""
    area = cv2.contourArea(contour)
    if area < min_area:
        return None
    approx = cv2.approxPolyDP(contour, 0.04 * cv2.arcLength(contour, True), True)
    if len(approx) != 4 or not cv2.isContourConvex(approx):
        return None
    if not 0.9 <= area / max(cv2.contourArea(approx), 1.0) <= 1.1:
        return None
    (_, _), (w, h), _ = cv2.minAreaRect(approx)
    if min(w, h) <= 0 or max(w, h) / min(w, h) > max_aspect:
        return None
    return approx.reshape(4, 2).astype(np.float64)


def _cv(image: np.ndarray, quad: np.ndarray) -> float:
    inner = _interior(image.shape, quad)
    values = image[inner]
    if values.size < 16 or values.mean() <= 0:
        return float("inf")
    return float(values.std() / values.mean())


def _refine(image: np.ndarray, quad: np.ndarray, min_area: float, max_aspect: float) -> np.ndarray:
    """Outline at the 50 % level between the panel and its surround (coarse outline if that fails)."""
    h, w = image.shape
    side = np.sqrt(cv2.contourArea(quad.astype(np.float32)))
    margin = int(round(0.25 * side))
    x0, y0 = (np.floor(quad.min(axis=0)) - margin).astype(int)
    x1, y1 = (np.ceil(quad.max(axis=0)) + margin).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    win = image[y0 : y1 + 1, x0 : x1 + 1]
    local = quad - [x0, y0]
    inside = polygon_mask(win.shape, local)
    k = max(3, int(round(0.05 * side)) | 1)
    ring = ~cv2.dilate(inside.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    if not ring.any():
        return quad
    level = 0.5 * (np.median(win[_interior(win.shape, local)]) + np.median(win[ring]))
    binary = (cv2.GaussianBlur(win, (3, 3), 0) > level).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    centre = local.mean(axis=0)
    for c in contours:
        if cv2.pointPolygonTest(c, (float(centre[0]), float(centre[1])), False) > 0:
            refined = _quad(c, min_area, max_aspect)
            if refined is not None:
                return refined + [x0, y0]
    return quad


def detect_panel(
    image: np.ndarray,
    *,
    min_area_frac: float = 0.003,
    max_cv: float = 0.05,
    max_aspect: float = 2.0,
    levels: int = 8,
) -> PanelDetection | None:
    """Find the largest bright, uniform, convex quadrilateral in one band.

    Parameters
    ----------
    image : numpy.ndarray
        One band ``(H, W)``.
    min_area_frac : float
        The smallest panel as a fraction of the frame.
    max_cv : float
        The largest std/mean of the panel's interior (a panel is uniform to a few %, its QR
        sticker is not).
    max_aspect : float
        The largest side ratio of its minimum-area rectangle (a square panel seen at an angle).
    levels : int
        The number of thresholds from Otsu's to near white.

    Returns
    -------
    PanelDetection or None
        The panel, or None when nothing qualifies.

    Raises
    ------
    ValueError
        Unless ``image`` is 2-D.

    Notes
    -----
    The steps are in the module docstring.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"detect_panel needs one band (H, W), got shape {img.shape}")
    u8 = _to_u8(img)
    otsu, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    min_area = min_area_frac * img.size
    best: PanelDetection | None = None
    for level in np.linspace(otsu, 250.0, levels):
        contours, _ = cv2.findContours((u8 > level).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        for c in contours:
            quad = _quad(c, min_area, max_aspect)
            if quad is None:
                continue
            cv = _cv(img, quad)
            area = float(cv2.contourArea(quad.astype(np.float32)))
            if cv <= max_cv and (best is None or area > best.area):
                best = PanelDetection(outline=quad, cv=cv, area=area)
    if best is None:
        return None
    outline = order_corners(_refine(img, best.outline, min_area, max_aspect))
    area = float(cv2.contourArea(outline.astype(np.float32)))
    return PanelDetection(outline=outline, cv=_cv(img, outline), area=area)


def sample_quad(image: np.ndarray, corners: Sequence[Sequence[float]], n: int = 32) -> np.ndarray:
    """Resample an image on an ``n x n`` grid spanning a quadrilateral.

    Bilinear, via the homography from the unit square to ``corners`` in :func:`order_corners`
    order. Maps the same physical points of a panel in bands that are not co-registered: grid
    cell (i, j) of every band's panel quadrilateral is the same spot on the panel.

    Parameters
    ----------
    image : numpy.ndarray
        One band ``(H, W)``.
    corners : sequence of (x, y)
        The quadrilateral's corners.
    n : int
        Samples along each side.

    Returns
    -------
    numpy.ndarray
        ``(n, n)`` float64, row 0 along the top edge (top-left to top-right).
    """
    quad = order_corners(corners)  # BR, BL, TL, TR
    dst = np.array([[n - 1, n - 1], [0, n - 1], [0, 0], [n - 1, 0]], dtype=np.float32)
    h = cv2.getPerspectiveTransform(quad.astype(np.float32), dst)
    return cv2.warpPerspective(
        np.asarray(image, dtype=np.float64), h, (n, n), flags=cv2.INTER_LINEAR, borderValue=float("nan")
    )


def panel_from_marker(
    marker_corners: Sequence[Sequence[float]],
    marker_size_m: float,
    panel_size_m: tuple[float, float],
    panel_offset_m: tuple[float, float],
) -> np.ndarray:
    """Return the image corners of a rectangular panel lying in the plane of an ArUco/AprilTag marker.

    Parameters
    ----------
    marker_corners : sequence of (x, y)
        TL, TR, BR, BL in image pixels as :func:`mscal_core.geometry.detect_marker` returns
        them.
    marker_size_m : float
        Side of the marker in metres.
    panel_size_m : tuple of float
        ``(w, h)`` of the panel in metres.
    panel_offset_m : tuple of float
        ``(du, dv)``, the panel's centre in the marker frame.

    Returns
    -------
    numpy.ndarray
        (4, 2) float64 panel corners in :func:`order_corners` order.

    Raises
    ------
    ValueError
        When the marker corners do not define a plane-to-image map.

    Notes
    -----
    The marker frame is that of :mod:`mscal_core.geometry` (centre at the origin, ``u`` right,
    ``v`` up as printed). The plane-to-image map of a pinhole camera is the homography ``H``
    with ``H (u_k, v_k, 1) ~ (x_k, y_k, 1)`` for the four marker corners ``k`` (solved exactly
    from the 4 correspondences); the panel corners are ``H`` applied to theirs. Lens distortion
    is not modelled: keep the panel near the marker.
    """
    h = 0.5 * float(marker_size_m)
    src = np.array([[-h, h], [h, h], [h, -h], [-h, -h]], dtype=np.float64)
    dst = np.asarray(marker_corners, dtype=np.float64).reshape(4, 2)
    # exact 4-point solve with h33 = 1: x (h31 u + h32 v + 1) = h11 u + h12 v + h13, same for y
    A = np.zeros((8, 8))
    for k, ((u, v), (x, y)) in enumerate(zip(src, dst)):
        A[2 * k] = [u, v, 1, 0, 0, 0, -x * u, -x * v]
        A[2 * k + 1] = [0, 0, 0, u, v, 1, -y * u, -y * v]
    try:
        H = np.append(np.linalg.solve(A, dst.ravel()), 1.0).reshape(3, 3)
    except np.linalg.LinAlgError:
        raise ValueError(f"marker corners {dst.tolist()} do not define a plane-to-image map") from None
    w, hh = 0.5 * float(panel_size_m[0]), 0.5 * float(panel_size_m[1])
    du, dv = (float(v) for v in panel_offset_m)
    panel = np.array([[du - w, dv + hh], [du + w, dv + hh], [du + w, dv - hh], [du - w, dv - hh]], dtype=np.float64)
    out = cv2.perspectiveTransform(panel.reshape(-1, 1, 2), H).reshape(4, 2)
    return order_corners(out)


_UNIT = np.array([[1.0, 1.0], [0.0, 1.0], [0.0, 0.0], [1.0, 0.0]], dtype=np.float32)  # BR, BL, TL, TR


def to_panel_coords(quad: Sequence[Sequence[float]], points: Sequence[Sequence[float]]) -> np.ndarray:
    """Map image points into the unit square of a panel quadrilateral.

    Parameters
    ----------
    quad : sequence of (x, y)
        The panel's four corners (any order; :func:`order_corners`).
    points : sequence of (x, y)
        Image points.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` panel coordinates ``(u, v)``: (0, 0) the top-left corner, (1, 1) the
        bottom-right, through the homography of the quadrilateral onto the unit square. The same
        ``(u, v)`` in two bands' quadrilaterals is the same spot of the panel.
    """
    h = cv2.getPerspectiveTransform(order_corners(quad).astype(np.float32), _UNIT)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.perspectiveTransform(pts, h).reshape(-1, 2)


def from_panel_coords(quad: Sequence[Sequence[float]], uv: Sequence[Sequence[float]]) -> np.ndarray:
    """Map panel coordinates ``(u, v)`` (:func:`to_panel_coords`) back into an image.

    Parameters
    ----------
    quad : sequence of (x, y)
        The panel's four corners in this image.
    uv : sequence of (u, v)
        Points in the panel's unit square.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` image points ``(x, y)``.
    """
    h = cv2.getPerspectiveTransform(_UNIT, order_corners(quad).astype(np.float32))
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.perspectiveTransform(pts, h).reshape(-1, 2)


def inset_square(inset: float = DEFAULT_INSET) -> np.ndarray:
    """Return the centred square of side ``inset`` in panel coordinates, BR, BL, TL, TR.

    Parameters
    ----------
    inset : float
        Linear fraction of the panel kept, ``0 < inset <= 1``.

    Returns
    -------
    numpy.ndarray
        ``(4, 2)`` panel coordinates.
    """
    return shrink_polygon(_UNIT.astype(np.float64), inset)


# --------------------------------------------------------------------------- the panel's QR code

#: Percentiles between which a band is stretched to 8 bits for QR decoding: robust to a few
#: hot or clipped pixels and to the 12-bit-in-16 storage of the band files.
QR_STRETCH_PERCENTILES = (0.5, 99.5)
#: Second try of a band whose QR code was located but not read: the image enlarged this much.
QR_UPSCALE = 2


def _qr_u8(image: np.ndarray) -> np.ndarray:
    """Stretch a band linearly to uint8 between its :data:`QR_STRETCH_PERCENTILES`.

    The percentiles are taken on every other pixel of every other row (the same values, a
    quarter of the work).
    """
    img = np.asarray(image)
    lo, hi = (float(v) for v in np.percentile(img[::2, ::2], QR_STRETCH_PERCENTILES))
    if not hi > lo:
        return np.zeros(img.shape, dtype=np.uint8)
    scaled = (img.astype(np.float32) - np.float32(lo)) * np.float32(255.0 / (hi - lo))
    return np.clip(scaled, 0.0, 255.0).astype(np.uint8)


def _qr_read(detector: cv2.QRCodeDetector, u8: np.ndarray) -> tuple[str, bool]:
    """Read a QR code: its text ('' when none is read) and whether one was located at all."""
    try:
        text, points, _ = detector.detectAndDecode(u8)
    except cv2.error:
        return "", False
    return (text or "").strip(), points is not None


def qr_serial(bands: Sequence[np.ndarray], give_up_after: int | None = 3) -> str | None:
    """Return the text of the QR code seen in a capture's band images, or None.

    On a calibrated reflectance panel it is the panel's serial number (``RP02-1603036-SC`` on
    MicaSense's sample panel), which names its reflectance (a catalog target).

    Method, per band in order: the image is stretched linearly to uint8 between its 0.5th
    and 99.5th percentiles, ``u8 = clip(255 (I - p0.5) / (p99.5 - p0.5), 0, 255)`` (12-bit
    data in 16-bit samples and a dark scene around a bright panel both fill the 8 bits), and
    OpenCV's ``QRCodeDetector.detectAndDecode`` reads it. A band whose code is located but not
    read is tried again enlarged :data:`QR_UPSCALE` times (bilinear), which reads codes only a
    few pixels per module across. The answer is the text read in most bands (a majority vote:
    QR codes carry error correction, so a wrong text is rare, but two texts read equally often
    give None). Reading stops once one text holds a majority of all the bands.

    Cost: about 25 ms per 1280 x 960 band. A capture without a code (a flight capture) stops
    after ``give_up_after`` bands in a row in which no code was even located (None: every
    band is tried).

    Parameters
    ----------
    bands : sequence of 2-D arrays
        The capture's band images (any numeric type: stored DN are fine).
    give_up_after : int or None
        Bands in a row without a located code after which a capture with nothing read yet is
        taken to show no code.

    Returns
    -------
    str or None
        The decoded text, stripped of surrounding whitespace, or None.
    """
    detector = cv2.QRCodeDetector()
    votes: dict[str, int] = {}
    misses = 0
    for image in bands:
        img = np.asarray(image)
        if img.ndim != 2 or min(img.shape) < 21:  # a QR code is at least 21 modules a side
            continue
        u8 = _qr_u8(img)
        text, located = _qr_read(detector, u8)
        if not text and located:
            big = cv2.resize(u8, None, fx=QR_UPSCALE, fy=QR_UPSCALE, interpolation=cv2.INTER_LINEAR)
            text, _ = _qr_read(detector, big)
        if text:
            votes[text] = votes.get(text, 0) + 1
            if 2 * votes[text] > len(bands):
                break
        misses = 0 if (text or located) else misses + 1
        if not votes and give_up_after is not None and misses >= give_up_after:
            break
    if not votes:
        return None
    ranked = sorted(votes.items(), key=lambda kv: kv[1], reverse=True)
    if len(ranked) > 1 and ranked[0][1] == ranked[1][1]:
        return None
    return ranked[0][0]
