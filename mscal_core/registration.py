"""Band co-registration of multi-lens cameras: pure numpy + OpenCV, no I/O.

A camera with one lens per band (MicaSense, DJI P4 Multispectral / Mavic 3M, Parrot Sequoia)
sees each band from a slightly different point. For a flat scene (the ground seen from flight
altitude) band ``b`` is the reference band seen through a plane homography ``H_b``:

    x_b ~ H_b x_ref          (homogeneous pixel coordinates, x = column, y = row)

Convention used everywhere in mscal: ``H_b`` maps **reference-band pixels to band-b pixels**
(OpenCV's ECC warp from template to input), so the aligned band is
``aligned_b(x) = band_b(H_b x)``, i.e. ``cv2.warpPerspective(band_b, H_b, ...,
flags=WARP_INVERSE_MAP)``. ``H_ref`` is the identity. Pixel centres are at integer
coordinates.

Estimation (:func:`register_band`):

1. both images become gradient-magnitude images (:func:`gradient_image`): edges of vegetation
   are dark-on-bright in red and bright-on-dark in NIR; the gradient magnitude is the same
   for both, and ECC's correlation coefficient is invariant to the remaining gain and offset;
2. the translation at the coarsest pyramid level from phase correlation (``cv2.phaseCorrelate``)
   starts the search (lenses tens of pixels apart, beyond ECC's basin at full resolution);
3. enhanced correlation coefficient maximisation (Evangelidis & Psarakis 2008,
   ``cv2.findTransformECC``, ``MOTION_HOMOGRAPHY``) from the coarsest to the finest level;
4. if ECC fails or its quality is below the thresholds, feature matching on the gradient
   images (SIFT, ORB if SIFT finds too few) with a RANSAC homography is tried, and the
   better of the two kept (:func:`feature_homography`).

Quality figures of every estimate (:class:`BandRegistration`): ``ecc`` the correlation
coefficient of the gradient images after warping (full resolution, overlap only),
``n_inliers``/``inlier_ratio`` of feature matches that agree with the estimate within
:data:`INLIER_PX`, ``residual_px`` their rms reprojection error. :func:`accept` applies the
reject thresholds (:class:`Thresholds`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import cv2
import numpy as np

from .alignment import warp_to_reference
from .errors import FitError, InputError
from .homography import map_points, normalise_homography, scale_homography

INLIER_PX = 2.0  # a feature match agrees with a homography within this (px), see feature_homography
# Pyramid levels until the coarsest image is this small (px, shorter side): phase correlation
# there finds shifts up to about half of it, i.e. about a quarter of the frame at any size.
COARSEST_PX = 120
# ECC iterations at full resolution (each costs a warp of the whole image, ~60 ms at 1.2 MP);
# the coarser levels have converged by then (docs/registration.md: within 0.04 px of
# the 300-iteration result on the RedEdge sample)
FINE_ITERATIONS = 30
MAX_FEATURES = 3000  # keypoints per image: plenty for a homography, bounded cost on 1.2 MP bands


@dataclass(frozen=True)
class Thresholds:
    """Reject thresholds of one band's transform (:func:`accept`).

    A transform passes if its ECC correlation passes and, where feature matches were found at
    all, the inlier count and residual pass too (low texture gives few features but may still
    give a good ECC correlation).

    Attributes
    ----------
    min_ecc : float
        0.3 by default: the gradient correlation of aligned bands of the real RedEdge captures
        is 0.43-0.97 (NIR against red over vegetation the lowest) while a wrong or unrelated
        alignment leaves 0.04-0.2 (docs/registration.md).
    min_inliers : int
        12 by default: a homography has 8 degrees of freedom, 12 matches that agree within
        2 px leave a margin against chance agreements.
    max_residual_px : float
        1.0 by default: above the 0.3-0.7 px that agreeing SIFT matches on gradient images show
        on correctly aligned bands (synthetic and real), below the 2 px of :data:`INLIER_PX`.
    """

    min_ecc: float = 0.3
    min_inliers: int = 12
    max_residual_px: float = 1.0


@dataclass(frozen=True)
class BandRegistration:
    """Transform of one band to the reference band and its quality figures.

    Attributes
    ----------
    homography : numpy.ndarray
        (3, 3) float64, maps reference pixels to band pixels.
    method : str
        ``"identity"`` (the reference itself), ``"ecc"``, ``"features"``, ``"failed"`` (no
        estimate: the identity), or the methods of a composed transform joined by ``+``
        (:func:`register_stack`).
    ecc : float
        The gradient correlation after warping (nan if not computable).
    n_matches : int
        Feature matches found.
    n_inliers : int
        Those within :data:`INLIER_PX` of the transform.
    inlier_ratio : float
        ``n_inliers / n_matches`` (nan without matches).
    residual_px : float
        RMS reprojection error of the inliers (nan without inliers).
    path : tuple of int
        Bands the transform was composed along (:func:`register_stack`).
    """

    homography: np.ndarray
    method: str
    ecc: float
    n_matches: int
    n_inliers: int
    inlier_ratio: float
    residual_px: float
    path: tuple[int, ...] = ()  # bands from the reference to this band (register_stack)


# --------------------------------------------------------------------------- images


def normalise(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Image scaled to about [0, 1] by its 1st and 99th percentiles (float32).

    DN of any bit depth and exposure look alike to the next steps.

    Parameters
    ----------
    image : numpy.ndarray
        Image of any numeric dtype.
    mask : numpy.ndarray, optional
        Bool, the pixels used for the percentiles (every pixel by default); non-finite pixels
        are never used.

    Returns
    -------
    numpy.ndarray
        float32 of the image's shape, ``(I - p1) / (p99 - p1)`` (divided by 1 when the two
        percentiles are equal), NaN as 0 and +/-inf as 1/0; all zeros when no pixel is finite.
    """
    a = np.asarray(image, dtype=np.float32)
    vals = a[mask] if mask is not None else a
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return np.zeros_like(a)
    lo, hi = np.percentile(vals, (1.0, 99.0))
    scale = 1.0 / (hi - lo) if hi > lo else 1.0
    out = (a - np.float32(lo)) * np.float32(scale)
    return np.nan_to_num(out, nan=0.0, posinf=1.0, neginf=0.0)


def gradient_image(image: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Return the gradient magnitude of the normalised image.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` image of any numeric dtype.
    sigma : float
        Standard deviation (px) of the Gaussian applied before the gradient; 0 applies none.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 gradient magnitude.

    Notes
    -----
    ``|grad(G_sigma * I)|`` (3x3 Sobel after a Gaussian of ``sigma`` px) of the
    percentile-normalised image (:func:`normalise`). The magnitude is blind to the sign of an
    edge, so vegetation that is dark in red and bright in NIR gives the same edges in both bands.
    """
    a = normalise(image)
    if sigma > 0:
        a = cv2.GaussianBlur(a, (0, 0), sigma)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Pearson correlation coefficient of two images over ``mask`` (and finite pixels).

    Parameters
    ----------
    a, b : numpy.ndarray
        Images of the same shape.
    mask : numpy.ndarray, optional
        Bool, the pixels compared (besides the finite ones).

    Returns
    -------
    float
        The correlation in [-1, 1]; NaN with fewer than 100 pixels or a constant image.

    Notes
    -----
    ``sum(x' y') / sqrt(sum(x'^2) sum(y'^2))`` with ``x' = x - mean(x)``: ECC's criterion (the
    zero-mean normalised correlation) evaluated once.
    """
    ok = np.isfinite(a) & np.isfinite(b)
    if mask is not None:
        ok &= mask
    if ok.sum() < 100:
        return float("nan")
    x = a[ok].astype(np.float64)
    y = b[ok].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    d = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / d) if d > 0 else float("nan")


def gradient_correlation(ref: np.ndarray, band: np.ndarray, mask: np.ndarray | None = None,
                         sigma: float = 1.0) -> float:
    """Correlate the gradient magnitudes of two images.

    The figure used to judge band-to-band alignment: high where edges coincide.

    Parameters
    ----------
    ref, band : numpy.ndarray
        Images of the same grid.
    mask : numpy.ndarray, optional
        Bool, the pixels compared.
    sigma : float
        Gaussian of :func:`gradient_image`.

    Returns
    -------
    float
        :func:`correlation` of the two :func:`gradient_image`; NaN as there.
    """
    return correlation(gradient_image(ref, sigma), gradient_image(band, sigma), mask)


# --------------------------------------------------------------------------- estimation


def _pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [image]
    for _ in range(levels):
        out.append(cv2.pyrDown(out[-1]))
    return out


def pyramid_levels(shape: tuple[int, int], coarsest_px: int = COARSEST_PX) -> int:
    """Count the halvings until the shorter side is about ``coarsest_px``.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the full-resolution image.
    coarsest_px : int
        Wanted shorter side (px) of the coarsest level.

    Returns
    -------
    int
        ``max(0, floor(log2(min(H, W) / coarsest_px)))``.
    """
    return max(0, int(math.floor(math.log2(max(1.0, min(shape) / coarsest_px)))))


def phase_shift(ref: np.ndarray, band: np.ndarray) -> tuple[np.ndarray, float]:
    """Estimate a translation by phase correlation.

    Parameters
    ----------
    ref, band : numpy.ndarray
        Images of the same shape.

    Returns
    -------
    homography : numpy.ndarray
        ``[[1, 0, dx], [0, 1, dy], [0, 0, 1]]`` float64.
    response : float
        The phase correlation's peak response (0-1).

    Notes
    -----
    The translation ``d = (dx, dy)`` with ``band(x + d) ~ ref(x)`` from ``cv2.phaseCorrelate``
    with a Hanning window.
    """
    win = cv2.createHanningWindow((ref.shape[1], ref.shape[0]), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(ref.astype(np.float32), band.astype(np.float32), win)
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]), float(response)


def ecc_homography(ref_grad: np.ndarray, band_grad: np.ndarray, init: np.ndarray | None = None, *,
                   levels: int | None = None, iterations: int = 100, eps: float = 1e-6,
                   fine_iterations: int = FINE_ITERATIONS, min_cc: float | None = None) -> np.ndarray | None:
    """Estimate a homography by pyramid ECC (``cv2.findTransformECC``, ``MOTION_HOMOGRAPHY``) of two gradient images.

    Parameters
    ----------
    ref_grad, band_grad : numpy.ndarray
        Gradient images (:func:`gradient_image`) of the reference and the band.
    init : numpy.ndarray, optional
        Full-resolution starting homography; defaults to a phase-correlation shift at the
        coarsest level (:func:`phase_shift`).
    levels : int, optional
        Pyramid levels (default :func:`pyramid_levels`).
    iterations : int
        ECC's iterations per coarser level at most.
    eps : float
        ECC's convergence threshold.
    fine_iterations : int
        Iterations at full resolution.
    min_cc : float, optional
        Give up (None) as soon as a coarser level converges below it -- the correlation of
        smoothed coarse gradient images is higher than at full resolution, so such a pair would
        fail the threshold anyway, and the full-resolution iterations are the costly ones.

    Returns
    -------
    numpy.ndarray or None
        The homography mapping reference pixels to band pixels, or None if ECC fails to
        converge at the finest level.

    Notes
    -----
    ECC maximises the zero-mean normalised correlation of ``ref(x)`` and ``band(H x)`` over the
    8 parameters of ``H``. The pyramid halves the images ``levels`` times; the estimate of a
    level starts the next finer one as ``S H S^-1`` with ``S = diag(2, 2, 1)``
    (:func:`~mscal_core.homography.scale_homography`). A coarser level that fails keeps the
    previous estimate (unless ``min_cc`` is given).

    References
    ----------
    Evangelidis, G. D. and Psarakis, E. Z., "Parametric image alignment using enhanced
    correlation coefficient maximization", IEEE Trans. Pattern Analysis and Machine
    Intelligence 30(10), 2008.
    """
    if levels is None:
        levels = pyramid_levels(ref_grad.shape)
    ref_p = _pyramid(ref_grad, levels)
    band_p = _pyramid(band_grad, levels)
    factor = 0.5**levels
    if init is None:
        shift, _ = phase_shift(ref_p[-1], band_p[-1])
        h = shift
    else:
        h = scale_homography(init, factor)
    for level in range(levels, -1, -1):
        if level != levels:
            h = scale_homography(h, 2.0)
        warp = h.astype(np.float32)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations if level else fine_iterations, eps)
        try:
            cc, warp = cv2.findTransformECC(ref_p[level], band_p[level], warp, cv2.MOTION_HOMOGRAPHY, criteria, None, 1)
        except cv2.error:
            if level == 0 or min_cc is not None:
                return None
            continue  # keep the estimate and try the finer level
        if min_cc is not None and level > 0 and cc < min_cc:
            return None
        h = normalise_homography(warp.astype(np.float64))
    return h


@dataclass(frozen=True)
class Features:
    """Keypoints (N, 2) (x, y), their descriptors and the descriptor norm of one image."""

    points: np.ndarray
    descriptors: np.ndarray | None
    norm: int


def detect_features(grad: np.ndarray) -> Features:
    """Keypoints of a gradient image (scaled to 8 bits at its 99.5th percentile).

    Parameters
    ----------
    grad : numpy.ndarray
        Gradient image (:func:`gradient_image`).

    Returns
    -------
    Features
        Keypoints (N, 2) (x, y), their descriptors (None when none were found) and the norm
        that compares the descriptors.

    Notes
    -----
    SIFT (OpenCV 5's main modules have no AKAZE), at most :data:`MAX_FEATURES` keypoints; ORB
    when SIFT finds fewer than 50.

    References
    ----------
    Lowe, D. G., "Distinctive image features from scale-invariant keypoints",
    International Journal of Computer Vision 60(2), 2004.
    """
    hi = float(np.percentile(grad, 99.5)) or 1.0
    image8 = np.clip(grad * (255.0 / hi), 0, 255).astype(np.uint8)
    kp, des = cv2.SIFT_create(nfeatures=MAX_FEATURES).detectAndCompute(image8, None)
    norm = cv2.NORM_L2
    if des is None or len(kp) < 50:
        kp, des = cv2.ORB_create(nfeatures=MAX_FEATURES).detectAndCompute(image8, None)
        norm = cv2.NORM_HAMMING
    pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return Features(pts, des, norm)


def feature_matches(ref: Features, band: Features, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Match the keypoints of two images' :func:`detect_features`.

    Parameters
    ----------
    ref, band : Features
        Keypoints of the reference and of the band.
    ratio : float
        Lowe's ratio test: a match is kept if its descriptor distance is below ``ratio`` times
        that of the second best.

    Returns
    -------
    ref_xy, band_xy : numpy.ndarray
        (N, 2) float64 matched points (x, y); (0, 2) when either image has fewer than two
        keypoints, no descriptors, or the two use different descriptor norms.

    Notes
    -----
    Brute-force matching; only mutual best matches that pass the ratio test are kept.

    References
    ----------
    Lowe, D. G., "Distinctive image features from scale-invariant keypoints",
    International Journal of Computer Vision 60(2), 2004.
    """
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if (ref.descriptors is None or band.descriptors is None or len(ref.points) < 2 or len(band.points) < 2
            or ref.norm != band.norm):
        return empty
    matcher = cv2.BFMatcher(ref.norm)
    fwd = matcher.knnMatch(ref.descriptors, band.descriptors, k=2)
    back = {m.queryIdx: m.trainIdx for m in matcher.match(band.descriptors, ref.descriptors)}
    good = [m[0] for m in fwd if len(m) == 2 and m[0].distance < ratio * m[1].distance
            and back.get(m[0].trainIdx) == m[0].queryIdx]
    if not good:
        return empty
    return (ref.points[[m.queryIdx for m in good]], band.points[[m.trainIdx for m in good]])


def feature_homography(ref_xy: np.ndarray, band_xy: np.ndarray) -> np.ndarray | None:
    """Fit a RANSAC homography to matched points.

    Parameters
    ----------
    ref_xy, band_xy : numpy.ndarray
        (N, 2) matched points (x, y) of the reference and of the band (:func:`feature_matches`).

    Returns
    -------
    numpy.ndarray or None
        (3, 3) float64 homography mapping reference pixels to band pixels, scaled to
        ``H[2, 2] = 1``; None with fewer than 8 matches or no consensus.

    Notes
    -----
    ``cv2.findHomography`` with RANSAC (reprojection threshold :data:`INLIER_PX`, 5000
    iterations, confidence 0.999), refined on its inliers (Levenberg-Marquardt inside OpenCV).
    """
    if len(ref_xy) < 8:
        return None
    h, _ = cv2.findHomography(ref_xy, band_xy, cv2.RANSAC, INLIER_PX, maxIters=5000, confidence=0.999)
    return None if h is None else normalise_homography(h)


def match_quality(homography: np.ndarray, ref_xy: np.ndarray, band_xy: np.ndarray) -> tuple[int, float, float]:
    """Count and measure the matches that agree with a homography.

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3) reference pixels -> band pixels.
    ref_xy, band_xy : numpy.ndarray
        (N, 2) matched points (x, y).

    Returns
    -------
    n_inliers : int
        Matches with ``|H x_ref - x_band| <= INLIER_PX``.
    inlier_ratio : float
        ``n_inliers / N`` (NaN without matches).
    residual_px : float
        RMS distance of the inliers (NaN without inliers).
    """
    if len(ref_xy) == 0:
        return 0, float("nan"), float("nan")
    d = np.linalg.norm(map_points(homography, ref_xy) - band_xy, axis=1)
    inl = d <= INLIER_PX
    n = int(inl.sum())
    res = float(np.sqrt(np.mean(d[inl] ** 2))) if n else float("nan")
    return n, n / len(d), res


def evaluate(homography: np.ndarray, method: str, ref_grad: np.ndarray, band_grad: np.ndarray,
             matches: tuple[np.ndarray, np.ndarray]) -> BandRegistration:
    """Quality figures of one homography (see :class:`BandRegistration`).

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3) reference pixels -> band pixels.
    method : str
        How it was estimated (``"ecc"``, ``"features"``), kept in the result.
    ref_grad, band_grad : numpy.ndarray
        Gradient images of the reference and of the band.
    matches : tuple of numpy.ndarray
        ``(ref_xy, band_xy)`` from :func:`feature_matches`.

    Returns
    -------
    BandRegistration
        The homography (``H[2, 2] = 1``), ``ecc`` the :func:`correlation` of the reference's
        gradient image with the band's warped onto it (pixels the band covers), and the
        :func:`match_quality` of the matches.
    """
    warped = warp_to_reference(band_grad, homography, ref_grad.shape)
    ecc = correlation(ref_grad, warped)
    n_in, ratio, res = match_quality(homography, *matches)
    return BandRegistration(normalise_homography(homography), method, ecc, len(matches[0]), n_in, ratio, res)


def accept(reg: BandRegistration, thresholds: Thresholds = Thresholds()) -> bool:
    """Whether a band's transform passes the reject thresholds (:class:`Thresholds`).

    Parameters
    ----------
    reg : BandRegistration
        The transform and its quality figures.
    thresholds : Thresholds
        The reject thresholds.

    Returns
    -------
    bool
        True for the reference itself (``method == "identity"``); otherwise the ECC correlation
        must be finite and at least ``min_ecc`` and, when at least ``min_inliers`` matches were
        found at all, the inliers must number ``min_inliers`` and their residual be finite and at
        most ``max_residual_px``.
    """
    if reg.method == "identity":
        return True
    if not (np.isfinite(reg.ecc) and reg.ecc >= thresholds.min_ecc):
        return False
    if reg.n_matches >= thresholds.min_inliers:
        if reg.n_inliers < thresholds.min_inliers:
            return False
        if not (np.isfinite(reg.residual_px) and reg.residual_px <= thresholds.max_residual_px):
            return False
    return True


def _score(reg: BandRegistration) -> tuple[float, float]:
    return (reg.ecc if np.isfinite(reg.ecc) else -1.0, reg.n_inliers)


def register_band(ref_grad: np.ndarray, band_grad: np.ndarray, *, init: np.ndarray | None = None,
                  thresholds: Thresholds = Thresholds(), ref_features: Features | None = None,
                  band_features: Features | None = None) -> BandRegistration:
    """Register one band to the reference from their gradient images (:func:`gradient_image`).

    Parameters
    ----------
    ref_grad, band_grad : numpy.ndarray
        Gradient images of the same size.
    init : numpy.ndarray, optional
        Starting homography of ECC.
    thresholds : Thresholds
        Reject thresholds (:func:`accept`).
    ref_features, band_features : Features, optional
        Keypoints already detected (:func:`detect_features`).

    Returns
    -------
    BandRegistration
        The transform with its quality figures, returned even when it fails the thresholds
        (see :func:`accept`).

    Raises
    ------
    InputError
        When the two images differ in size.

    Notes
    -----
    Pyramid ECC; if ECC fails or does not pass ``thresholds``, features + RANSAC refined by
    ECC at full resolution, keeping the estimate with the higher gradient correlation (then
    more inliers). With no estimate at all, the identity with ``method="failed"``.
    """
    if ref_grad.shape != band_grad.shape:
        raise InputError(f"bands of one capture differ in size: {ref_grad.shape} vs {band_grad.shape}",
                         hint="every band of a multi-lens capture must have the same pixel grid")
    matches = feature_matches(ref_features or detect_features(ref_grad), band_features or detect_features(band_grad))
    candidates: list[BandRegistration] = []
    h_ecc = ecc_homography(ref_grad, band_grad, init, min_cc=thresholds.min_ecc)
    if h_ecc is not None:
        candidates.append(evaluate(h_ecc, "ecc", ref_grad, band_grad, matches))
    if not candidates or not accept(candidates[0], thresholds):
        h_feat = feature_homography(*matches)
        if h_feat is not None:
            feat = evaluate(h_feat, "features", ref_grad, band_grad, matches)
            # ECC from the feature estimate: features locate, ECC refines to sub-pixel
            h_ref = ecc_homography(ref_grad, band_grad, h_feat, levels=0)
            if h_ref is not None:
                refined = evaluate(h_ref, "features", ref_grad, band_grad, matches)
                feat = max(feat, refined, key=_score)
            candidates.append(feat)
    if not candidates:
        eye = np.eye(3)
        return BandRegistration(eye, "failed", float("nan"), len(matches[0]), 0, float("nan"), float("nan"))
    return max(candidates, key=_score)


def _pairs(n: int, reference: int, wavelengths: Sequence[float] | None, neighbours: int) -> list[tuple[int, int]]:
    if wavelengths is None or neighbours >= n - 1:
        return [(a, b) for a in range(n) for b in range(a + 1, n)]
    wl = np.asarray(wavelengths, dtype=np.float64)
    pairs = set()
    for a in range(n):
        order = [int(b) for b in np.argsort(np.abs(wl - wl[a]), kind="stable") if b != a]
        for b in order[:neighbours] + ([reference] if a != reference else []):
            pairs.add((min(a, b), max(a, b)))
    return sorted(pairs)


def _compose(edges: Sequence[BandRegistration], path: tuple[int, ...]) -> BandRegistration:
    """Compose a transform along a path of pairwise registrations.

    Its quality is the weakest edge's (NaN, i.e. failing, if any edge's figure is NaN).
    """
    h = np.eye(3)
    for e in edges:
        h = e.homography @ h
    if len(edges) == 1:
        return replace(edges[0], path=path)
    return BandRegistration(
        normalise_homography(h), "+".join(sorted({e.method for e in edges})),
        float(np.min([e.ecc for e in edges])), min(e.n_matches for e in edges), min(e.n_inliers for e in edges),
        float(np.min([e.inlier_ratio for e in edges])), float(np.max([e.residual_px for e in edges])), path,
    )


def register_stack(stack: np.ndarray, reference: int, *, wavelengths: Sequence[float] | None = None,
                   neighbours: int = 3, sigma: float = 1.0,
                   thresholds: Thresholds = Thresholds()) -> list[BandRegistration]:
    """Register every band of one capture to band ``reference``.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(band, H, W)`` capture.
    reference : int
        The reference band.
    wavelengths : sequence of float, optional
        Band wavelengths; None registers every pair.
    neighbours : int
        Each band is registered with its ``neighbours`` nearest bands in wavelength and with
        the reference.
    sigma : float
        Gaussian of :func:`gradient_image`.
    thresholds : Thresholds
        Reject thresholds (:func:`accept`).

    Returns
    -------
    list of BandRegistration
        One per band; the reference band's own entry is the identity.

    Raises
    ------
    InputError
        Unless ``stack`` is ``(band, H, W)`` and ``reference`` one of its bands.
    FitError
        When the bands cannot be linked by any registration.

    Notes
    -----
    Distant bands can look too different to register directly (blue against NIR over
    vegetation: gradient correlation ~0.1 on the real RedEdge flight capture, where blue against
    green is 0.84 and green against NIR 0.77). So pairs of bands are registered
    (:func:`register_band`), and each band's transform is composed along the maximum spanning
    tree of the pairs' gradient correlations (Prim's algorithm, pairs that fail ``thresholds``
    only when nothing else connects a band). A composed transform carries the weakest quality
    figures of its edges and its ``path``.
    """
    if stack.ndim != 3:
        raise InputError(f"a capture must be a (band, H, W) stack, got shape {stack.shape}")
    n = stack.shape[0]
    if not 0 <= reference < n:
        raise InputError(f"reference band {reference} is not one of the {n} bands")
    grads = [gradient_image(b, sigma) for b in stack]
    feats = [detect_features(g) for g in grads]
    edge: dict[tuple[int, int], BandRegistration] = {}
    for a, b in _pairs(n, reference, wavelengths, neighbours):
        reg = register_band(grads[a], grads[b], thresholds=thresholds, ref_features=feats[a], band_features=feats[b])
        edge[(a, b)] = reg  # a -> b
        inv = normalise_homography(np.linalg.inv(reg.homography))
        edge[(b, a)] = replace(reg, homography=inv)
    out: dict[int, BandRegistration] = {
        reference: BandRegistration(np.eye(3), "identity", 1.0, 0, 0, float("nan"), 0.0, (reference,))}
    chain: dict[int, list[BandRegistration]] = {reference: []}
    while len(out) < n:
        best = None
        for (a, b), reg in edge.items():
            if a in out and b not in out:
                key = (accept(reg, thresholds), _score(reg))
                if best is None or key > best[0]:
                    best = (key, a, b, reg)
        if best is None:  # unreachable: no pair at all (cannot happen with every pair tried)
            raise FitError("bands could not be linked by any registration", hint="check the capture's band files")
        _, a, b, reg = best
        chain[b] = chain[a] + [reg]
        out[b] = _compose(chain[b], out[a].path + (b,))
    return [out[b] for b in range(n)]
