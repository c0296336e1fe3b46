"""The marker's pose when two poses fit its corners: both IPPE solutions and the choice (no I/O).

A square marker seen in perspective is a plane homography of its 4 corners; when the marker
is small in the image or seen nearly face-on the homography is close to affine, and two poses
reproject the corners almost equally well: the true one and its mirror about the line of
sight (the planar pose ambiguity, [1]_). ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` returns the one
with the smaller reprojection error, which corner noise of a few tenths of a pixel can make the
wrong one; the wrong one tilts the plane the other way, and the reflector around the marker
(Eq. 8-10 of [2]_ map its pixels through the pose) lands on the wrong pixels, more so the
further from the marker.

Here both solutions are kept (:func:`ippe_candidates`, ``cv2.solvePnPGeneric``) and one is
chosen (:func:`choose_pose`):

1. by reprojection error when it separates them clearly (:func:`reprojection_decides`);
2. else by the image: the candidate whose outlines of the marker's white paper and of the
   reflector around it fall on the image's edges (:func:`outline_contrast`), the reflector
   being rigidly attached to the marker;
3. else the smaller reprojection error (what ``solvePnP`` gives).

:class:`PoseChoice` records which solution was taken, why, and both reprojection errors.

Before that, the corners themselves: :func:`refine_corners_by_edges` replaces each of the
detector's corners (``cornerSubPix``, biased inward at a convex corner) by the intersection of
lines fitted to the marker's edges; :func:`pose_in_image` chains the two.

References
----------
.. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
       International Journal of Computer Vision, 109(3), 252-286, 2014.
.. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import FitError, InputError
from .geometry import Intrinsics, Pose, aruco_dictionary, marker_object_points, project_to_pixels

__all__ = [
    "EDGE_RATIO",
    "REPROJECTION_MARGIN_PX",
    "REPROJECTION_RATIO",
    "PoseCandidate",
    "PoseChoice",
    "choose_pose",
    "estimate_marker_pose",
    "ippe_candidates",
    "marker_modules",
    "outline_contrast",
    "pose_in_image",
    "refine_corners_by_edges",
    "reprojection_decides",
]

#: The second solution's reprojection error must be at least this multiple of the first's ...
REPROJECTION_RATIO = 3.0
#: ... and exceed it by at least this many pixels (about twice the corner noise left after
#: sub-pixel refinement) for the reprojection error alone to choose.
REPROJECTION_MARGIN_PX = 0.3
#: The image chooses when one candidate's outline contrast is at least this multiple of the
#: other's. On 80 rendered small oblique markers (16-27 px, read noise up to 20 DN) the solution
#: nearer the truth had the higher contrast every time; where the two differed by more than
#: 3 deg, by a factor of 1.05 at least (median 2).
EDGE_RATIO = 1.02
#: Half the step across an outline at which the image is compared, in pixels.
EDGE_STEP_PX = 1.0
#: Common shifts of the outlines tried (pixels; :func:`outline_contrast`).
EDGE_SHIFTS_PX = tuple(np.linspace(-2.0, 2.0, 9))
#: Samples per side of an outline.
EDGE_SAMPLES = 24
#: A candidate's outline contrast needs at least this many samples inside the image.
MIN_EDGE_SAMPLES = 16


@dataclass(frozen=True)
class PoseCandidate:
    """One solution of the marker pose and its RMS reprojection error of the 4 corners (pixels)."""

    pose: Pose
    reprojection_px: float


@dataclass(frozen=True)
class PoseChoice:
    """The pose taken for a marker and why.

    Attributes
    ----------
    pose : Pose
        The pose taken.
    alternative : Pose or None
        The other IPPE solution (None when only one lies in front of the camera).
    solution : int
        Which solution was taken: 0 is the one of smaller reprojection error (what
        ``solvePnP`` returns), 1 the other.
    reprojection_px : tuple of float
        RMS corner reprojection errors of solutions 0 and 1 (NaN for a missing one).
    by : str
        ``"reprojection"`` (it separates them clearly), ``"outline"`` (the image's edges at the
        paper and reflector outlines), ``"single"`` (one solution) or ``"undecided"`` (neither
        separates them: solution 0); a caller that chose again on other evidence says which
        (:meth:`swapped`, e.g. ``"consistency"`` with the other views' vignetting fit).
    contrast : tuple of float
        :func:`outline_contrast` of solutions 0 and 1 (NaN where not measured).
    """

    pose: Pose
    alternative: Pose | None
    solution: int
    reprojection_px: tuple[float, float]
    by: str
    contrast: tuple[float, float] = (float("nan"), float("nan"))

    def swapped(self, by: str) -> PoseChoice:
        """Take the other solution instead, for the reason ``by`` (e.g. ``"consistency"``)."""
        if self.alternative is None:
            raise InputError("a pose with a single solution has no other to take")
        return PoseChoice(self.alternative, self.pose, 1 - self.solution, self.reprojection_px, by, self.contrast)

    def as_record(self) -> dict[str, object]:
        """Plain numbers for a report: ``solution``, ``by``, ``reprojection_px``, ``contrast``."""
        def r(x: float, n: int) -> float | None:
            return round(float(x), n) if np.isfinite(x) else None

        return {
            "solution": int(self.solution),
            "by": self.by,
            "reprojection_px": [r(e, 4) for e in self.reprojection_px],
            "contrast": [r(c, 4) for c in self.contrast],
        }


def ippe_candidates(corners: np.ndarray, marker_size_m: float, intrinsics: Intrinsics) -> list[PoseCandidate]:
    """Both IPPE solutions of a square marker's pose, smaller reprojection error first.

    Parameters
    ----------
    corners : numpy.ndarray
        (4, 2) pixels TL, TR, BR, BL (:func:`mscal_core.geometry.detect_marker`).
    marker_size_m : float
        Side of the marker in metres.
    intrinsics : Intrinsics
        The band grid's (or lens's) intrinsics.

    Returns
    -------
    list of PoseCandidate
        One or two candidates, each with the whole marker in front of the camera, ordered by
        their RMS reprojection error ``sqrt(mean_k |x_k - pi(X_k)|^2)`` over the 4 corners.

    Raises
    ------
    InputError
        On bad arguments.
    FitError
        If no solution puts the marker in front of the camera.

    Notes
    -----
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)``: IPPE [1]_ solves the plane's pose from
    the homography's first-order expansion at the marker centre, which has exactly two
    solutions ``R_1, R_2 = R_v R_{1,2}`` mirroring the plane's normal about the line of sight;
    each is refined by OpenCV and scored by its reprojection error.

    References
    ----------
    .. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
           International Journal of Computer Vision, 109(3), 252-286, 2014.
    """
    pts = np.asarray(corners, dtype=np.float64)
    if pts.shape != (4, 2) or not np.all(np.isfinite(pts)):
        raise InputError(f"marker corners must be (4, 2) finite pixels, got shape {pts.shape}")
    size = float(marker_size_m)
    if not np.isfinite(size) or size <= 0:
        raise InputError(
            f"marker size must be a positive length in metres, got {marker_size_m!r}",
            hint="check marker_size_m of the reflector target",
        )
    obj = marker_object_points(size)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, pts.reshape(4, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs,
            flags=cv2.SOLVEPNP_IPPE_SQUARE,
        )
    except cv2.error as exc:  # degenerate corners (e.g. all on a line)
        raise FitError(f"no marker pose found from the detected corners ({exc.err})") from None
    out = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        pose = Pose(np.ravel(rvec), np.ravel(tvec))
        if np.any((obj @ pose.rotation.T + pose.tvec)[:, 2] <= 0):
            continue
        err = project_to_pixels(obj[:, :2], pose, intrinsics) - pts
        out.append(PoseCandidate(pose, float(np.sqrt(np.mean(np.sum(err**2, axis=1))))))
    if not out:
        raise FitError(
            "no marker pose found from the detected corners, or it puts the marker behind the camera",
            hint="check the intrinsics and the marker size",
        )
    return sorted(out, key=lambda c: c.reprojection_px)


def reprojection_decides(errors: Sequence[float], ratio: float = REPROJECTION_RATIO,
                         margin_px: float = REPROJECTION_MARGIN_PX) -> bool:
    """Whether the reprojection errors ``(e0, e1)``, ``e0 <= e1``, separate two solutions clearly.

    Parameters
    ----------
    errors : sequence of float
        RMS reprojection errors of solutions 0 and 1 (pixels).
    ratio, margin_px : float
        :data:`REPROJECTION_RATIO`, :data:`REPROJECTION_MARGIN_PX`.

    Returns
    -------
    bool
        ``e1 >= ratio e0`` and ``e1 - e0 >= margin_px``.

    Notes
    -----
    The 4 corners give 8 numbers for 6 pose parameters: a true pose leaves residuals of the
    order of the corner noise, its mirror adds a systematic residual that grows with the
    marker's tilt from the line of sight and its size in the image [1]_. Below the margin the
    wrong solution can come first (corner noise of 0.2-0.3 px is enough for near-frontal views).

    References
    ----------
    .. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
           International Journal of Computer Vision, 109(3), 252-286, 2014.
    """
    e0, e1 = float(errors[0]), float(errors[1])
    return bool(e1 >= ratio * e0 and e1 - e0 >= margin_px)


def _outline_samples(half_wh: tuple[float, float], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points on the 4 sides of a centred rectangle (corners left out) and their outward normals."""
    hw, hh = half_wh
    t = np.linspace(-0.8, 0.8, n)
    pts, nrm = [], []
    for side_pt, side_n, along in (
        ((hw, 0.0), (1.0, 0.0), (0.0, hh)), ((-hw, 0.0), (-1.0, 0.0), (0.0, hh)),
        ((0.0, hh), (0.0, 1.0), (hw, 0.0)), ((0.0, -hh), (0.0, -1.0), (hw, 0.0)),
    ):
        pts.append(np.asarray(side_pt) + t[:, None] * np.asarray(along))
        nrm.append(np.broadcast_to(np.asarray(side_n), (n, 2)))
    return np.concatenate(pts), np.concatenate(nrm)


def outline_contrast(
    image: np.ndarray,
    pose: Pose,
    intrinsics: Intrinsics,
    outlines_m: Sequence[tuple[float, float]],
    offset: tuple[float, float] = (0.0, 0.0),
    step_px: float = EDGE_STEP_PX,
    n_per_side: int = EDGE_SAMPLES,
    shifts_px: Sequence[float] = EDGE_SHIFTS_PX,
) -> tuple[float, int]:
    """How well a pose's outlines on the marker plane fall on edges of the image.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) image (any real dtype) whose pixel ``(i, j)`` sees image point
        ``(j + dx, i + dy)``.
    pose : Pose
        Candidate pose of the marker.
    intrinsics : Intrinsics
        The intrinsics the pose was found with.
    outlines_m : sequence of (float, float)
        Half width and half height (metres) of rectangles centred on the marker whose sides
        are edges in the scene: the marker's white paper, the reflector.
    offset : tuple of float
        ``(dx, dy)``.
    step_px : float
        Half the step across a side at which the image is compared (pixels, at the side).
    n_per_side : int
        Samples per side.
    shifts_px : sequence of float
        Common shifts of all the outlines along their normals (pixels), see Notes.

    Returns
    -------
    tuple
        ``(contrast, n)``: ``max_s mean_p |I(pi(p + (s - d) n)) - I(pi(p + (s + d) n))|`` over
        the shifts ``s`` and the ``n`` samples ``p`` on the sides (outward normal ``n``) that
        fall inside the image at every shift, divided by the image's robust range (99th - 1st
        percentile); NaN when ``n`` is 0.

    Notes
    -----
    ``d`` and ``s`` are in pixels at the depth ``z`` of ``p`` (``x z / f`` metres on the
    plane, ``f`` the mean focal length), ``pi`` the pose's projection
    (:func:`mscal_core.geometry.project_to_pixels`) and ``I`` bilinear. The reflector is
    rigidly attached to the marker, so the true pose puts its outlines on the image's step
    edges (full contrast) while the mirrored IPPE solution [1]_ tilts them: pixels off, inward
    on one side and outward on the other. A shift common to every side (the best ``s``) absorbs
    an error of the pose's scale, which both solutions share (a marker whose corners came out a
    little inside looks a little farther), without aligning a tilted outline. Samples near the
    sides' ends are left out (corners blur).

    References
    ----------
    .. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
           International Journal of Computer Vision, 109(3), 252-286, 2014.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise InputError(f"outline contrast needs a single-band image (H, W), got shape {img.shape}")
    pts, nrm = [], []
    for half in outlines_m:
        p, n = _outline_samples((float(half[0]), float(half[1])), int(n_per_side))
        pts.append(p)
        nrm.append(n)
    if not pts:
        return float("nan"), 0
    p, n = np.concatenate(pts), np.concatenate(nrm)
    rot = pose.rotation
    depth = p @ rot[2, :2] + pose.tvec[2]
    front = depth > 0
    p, n, depth = p[front], n[front], depth[front]
    px = (depth / (0.5 * (intrinsics.fx + intrinsics.fy)))[:, None]  # metres per pixel at p
    shifts = np.asarray(shifts_px, dtype=np.float64).reshape(-1)
    m = p.shape[0]
    h, w = img.shape
    # every shift's inner and outer points in one projection: (shift, in/out, sample)
    at = np.concatenate([p + (sh + sign * float(step_px)) * px * n for sh in shifts for sign in (-1.0, 1.0)])
    xy = project_to_pixels(at, pose, intrinsics) - np.asarray(offset, dtype=np.float64)
    inside = np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1)
    inside &= (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    inside = inside.reshape(shifts.size * 2, m).all(axis=0)  # samples in the image at every shift
    if not inside.any():
        return float("nan"), 0
    xy = np.where(np.isfinite(xy), xy, 0.0).astype(np.float32)
    vals = cv2.remap(img, xy[:, :1], xy[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    vals = vals.reshape(shifts.size, 2, m)[..., inside]
    diff = np.abs(vals[:, 0] - vals[:, 1])  # (shift, sample)
    ok = np.all(np.isfinite(diff), axis=0)
    if not ok.any():
        return float("nan"), 0
    finite = np.isfinite(img)
    lo, hi = np.percentile(img[finite], [1, 99])
    scale = float(hi - lo) if hi > lo else 1.0
    return float(np.max(np.mean(diff[:, ok], axis=1)) / scale), int(np.count_nonzero(ok))


def choose_pose(
    candidates: Sequence[PoseCandidate],
    image: np.ndarray | None = None,
    intrinsics: Intrinsics | None = None,
    outlines_m: Sequence[tuple[float, float]] = (),
    offset: tuple[float, float] = (0.0, 0.0),
) -> PoseChoice:
    """Choose between the IPPE solutions of :func:`ippe_candidates`.

    Parameters
    ----------
    candidates : sequence of PoseCandidate
        One or two, smaller reprojection error first.
    image : numpy.ndarray, optional
        The image the corners were found in (see :func:`outline_contrast`); without it only
        the reprojection error chooses.
    intrinsics : Intrinsics, optional
        Needed with ``image``.
    outlines_m : sequence of (float, float)
        Half sizes of the rectangles around the marker whose sides are edges (its paper, the
        reflector).
    offset : tuple of float
        The image's ``(dx, dy)`` (:func:`outline_contrast`).

    Returns
    -------
    PoseChoice
        Solution 1 only when the reprojection error does not separate the two
        (:func:`reprojection_decides`) and solution 1's outline contrast ``c1`` is at least
        :data:`EDGE_RATIO` times solution 0's ``c0`` (both measured on at least
        :data:`MIN_EDGE_SAMPLES` samples); solution 0 otherwise.

    Notes
    -----
    The two solutions of the planar pose ambiguity [1]_ reproject the 4 corners about equally
    well when the marker is near-frontal or small in the image; they differ most far from the
    marker, where the reflector's edges are: the paper's pose map ``pi_i`` of [2]_ is only as
    good as the solution taken there.

    References
    ----------
    .. [1] T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation",
           International Journal of Computer Vision, 109(3), 252-286, 2014.
    .. [2] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    if not candidates:
        raise InputError("choose_pose needs at least one pose candidate")
    first = candidates[0]
    if len(candidates) == 1:
        return PoseChoice(first.pose, None, 0, (first.reprojection_px, float("nan")), "single")
    second = candidates[1]
    errors = (first.reprojection_px, second.reprojection_px)
    if reprojection_decides(errors):
        return PoseChoice(first.pose, second.pose, 0, errors, "reprojection")
    if image is None or intrinsics is None or not outlines_m:
        return PoseChoice(first.pose, second.pose, 0, errors, "undecided")
    measured = [outline_contrast(image, c.pose, intrinsics, outlines_m, offset) for c in (first, second)]
    contrast = (measured[0][0], measured[1][0])
    enough = all(k >= MIN_EDGE_SAMPLES for _, k in measured) and all(np.isfinite(contrast))
    if enough and contrast[1] >= EDGE_RATIO * contrast[0]:
        return PoseChoice(second.pose, first.pose, 1, errors, "outline", contrast)
    if enough and contrast[0] >= EDGE_RATIO * contrast[1]:
        return PoseChoice(first.pose, second.pose, 0, errors, "outline", contrast)
    return PoseChoice(first.pose, second.pose, 0, errors, "undecided", contrast)


def estimate_marker_pose(
    corners: np.ndarray,
    marker_size_m: float,
    intrinsics: Intrinsics,
    image: np.ndarray | None = None,
    outlines_m: Sequence[tuple[float, float]] = (),
    offset: tuple[float, float] = (0.0, 0.0),
) -> PoseChoice:
    """Estimate the marker's pose from its corners, the planar ambiguity resolved.

    Parameters
    ----------
    corners : numpy.ndarray
        (4, 2) pixels TL, TR, BR, BL, on the image grid plus ``offset`` (the points the
        intrinsics apply to).
    marker_size_m : float
        Side of the marker in metres.
    intrinsics : Intrinsics
        The band grid's (or lens's) intrinsics.
    image, outlines_m, offset
        As in :func:`choose_pose`.

    Returns
    -------
    PoseChoice
        :func:`choose_pose` of :func:`ippe_candidates`.

    Raises
    ------
    InputError
        On bad arguments.
    FitError
        If no pose puts the marker in front of the camera.
    """
    return choose_pose(ippe_candidates(corners, marker_size_m, intrinsics), image, intrinsics, outlines_m, offset)


#: Where along each side of the marker the edge is measured (fractions of the side; the
#: corners, where the two sides' blur meet, are left out).
EDGE_SPAN = (0.2, 0.8)
#: Profiles measured across each side.
EDGE_PROFILES = 15
#: Reach of a profile on either side of the side, in modules (the black border is one module
#: wide, the white paper beyond it wider), at most :data:`EDGE_REACH_MAX_PX` pixels.
EDGE_REACH_MODULES = 0.6
EDGE_REACH_MAX_PX = 3.0


def _side_edge_points(img: np.ndarray, a: np.ndarray, b: np.ndarray, outward: np.ndarray,
                      reach: float) -> np.ndarray:
    """Sub-pixel points of the dark-to-bright edge along the side ``a -> b`` (image grid)."""
    t = np.linspace(*EDGE_SPAN, EDGE_PROFILES)
    s = np.arange(-reach, reach + 1e-9, 0.1)
    base = a[None, :] + t[:, None] * (b - a)[None, :]
    pts = base[:, None, :] + s[None, :, None] * outward[None, None, :]
    vals = cv2.remap(img, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    out = []
    for k in range(t.size):
        v = vals[k]
        dark, bright = float(np.mean(v[:3])), float(np.mean(v[-3:]))
        if not bright - dark > 0.2 * (float(v.max()) - float(v.min()) + 1e-12) or bright <= dark:
            continue
        level = 0.5 * (dark + bright)
        above = np.flatnonzero(v >= level)
        if above.size == 0 or above[0] == 0:
            continue
        j = int(above[0])
        f = (level - v[j - 1]) / (v[j] - v[j - 1]) if v[j] != v[j - 1] else 0.5
        out.append(base[k] + (s[j - 1] + f * (s[j] - s[j - 1])) * outward)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def refine_corners_by_edges(
    image: np.ndarray,
    corners: np.ndarray,
    modules: int,
    intrinsics: Intrinsics | None = None,
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Refine a marker's 4 corners as the intersections of lines fitted to its 4 edges.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) image the corners were found in (any real dtype).
    corners : numpy.ndarray
        (4, 2) corners TL, TR, BR, BL on the image grid (:func:`mscal_core.geometry.detect_marker`).
    modules : int
        Cells across the marker, its black border included (6 for a 4 x 4 dictionary).
    intrinsics : Intrinsics, optional
        With them the edges are fitted as straight lines of the undistorted image (the
        marker's sides are straight on the plane), else of the image itself.
    offset : tuple of float
        ``(dx, dy)``: pixel ``(i, j)`` sees image point ``(j + dx, i + dy)`` (for the intrinsics).

    Returns
    -------
    numpy.ndarray
        (4, 2) corners on the image grid; ``corners`` unchanged where a side gives fewer than 5
        edge points or the lines do not meet near the corner (within one module).

    Notes
    -----
    ``cornerSubPix`` puts a corner where the image gradients around it are orthogonal to the
    lines joining them to it; at the convex corner of a blurred dark square those lines lean
    inward, so every corner comes out inside the marker (0.17 px on the synthetic band-grid
    markers: a marker that looks smaller and a pose that is a little far). The middle of a
    straight blurred step edge, where the profile across it passes half-way from the black
    border to the white paper, is unbiased for a symmetric blur: each side is located there by
    :data:`EDGE_PROFILES` profiles over :data:`EDGE_SPAN` of its length, fitted with a total
    least-squares line, and each corner is the intersection of its two sides' lines.
    """
    img = np.asarray(image, dtype=np.float32)
    quad = np.asarray(corners, dtype=np.float64)
    if img.ndim != 2 or quad.shape != (4, 2) or not np.all(np.isfinite(quad)):
        raise InputError(f"edge refinement needs a single-band image and (4, 2) finite corners, got image shape "
                         f"{img.shape} and corners shape {quad.shape}")
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
    module = side / max(int(modules), 1)
    reach = min(EDGE_REACH_MODULES * module, EDGE_REACH_MAX_PX)
    centre = quad.mean(axis=0)
    off = np.asarray(offset, dtype=np.float64)
    lines = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([d[1], -d[0]])
        if n @ (0.5 * (a + b) - centre) < 0:
            n = -n
        pts = _side_edge_points(img, a, b, n, reach)
        if pts.shape[0] < 5:
            return quad.copy()
        if intrinsics is not None:
            pts = cv2.undistortPoints((pts + off).reshape(-1, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs,
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
                                      ).reshape(-1, 2)
        mean = pts.mean(axis=0)
        normal = np.linalg.svd(pts - mean)[2][1]  # total least squares: n . x = n . mean
        lines.append(np.append(normal, -normal @ mean))
    out = np.empty((4, 2))
    for k in range(4):  # corner k joins side k-1 (into it) and side k (out of it)
        p = np.cross(lines[k - 1], lines[k])
        if abs(p[2]) < 1e-12:
            return quad.copy()
        out[k] = p[:2] / p[2]
    if intrinsics is not None:
        pts3 = np.concatenate([out, np.ones((4, 1))], axis=1).reshape(-1, 1, 3)
        out = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), intrinsics.matrix,
                                intrinsics.dist_coeffs)[0].reshape(4, 2) - off
    if np.any(np.linalg.norm(out - quad, axis=1) > module):
        return quad.copy()
    return out


def marker_modules(dictionary: str) -> int:
    """Cells across a marker of an OpenCV ArUco dictionary, its black border included.

    Parameters
    ----------
    dictionary : str
        OpenCV name, e.g. ``"DICT_4X4_50"``.

    Returns
    -------
    int
        ``markerSize + 2`` (6 for a 4 x 4 dictionary).

    Raises
    ------
    InputError
        For an unknown name.
    """
    return int(aruco_dictionary(dictionary).markerSize) + 2


def pose_in_image(
    image: np.ndarray,
    corners: np.ndarray,
    dictionary: str,
    marker_size_m: float,
    intrinsics: Intrinsics,
    outlines_m: Sequence[tuple[float, float]] = (),
    offset: tuple[float, float] = (0.0, 0.0),
) -> PoseChoice:
    """Estimate the marker's pose in an image from its detected corners, edge-refined, ambiguity resolved.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) image the corners were found in.
    corners : numpy.ndarray
        (4, 2) corners TL, TR, BR, BL on the image grid (:func:`mscal_core.geometry.detect_marker`).
    dictionary : str
        The marker's ArUco dictionary (for its cells across, :func:`marker_modules`).
    marker_size_m : float
        Side of the marker in metres.
    intrinsics : Intrinsics
        The intrinsics of the image points ``(j + dx, i + dy)``.
    outlines_m : sequence of (float, float)
        As in :func:`choose_pose`.
    offset : tuple of float
        ``(dx, dy)``.

    Returns
    -------
    PoseChoice
        :func:`estimate_marker_pose` of :func:`refine_corners_by_edges` (plus ``offset``).
    """
    refined = refine_corners_by_edges(image, corners, marker_modules(dictionary), intrinsics, offset)
    return estimate_marker_pose(refined + np.asarray(offset, dtype=np.float64), marker_size_m, intrinsics, image,
                                outlines_m, offset)
