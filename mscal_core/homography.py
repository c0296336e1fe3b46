"""Plane homographies between band grids: mapping points, comparing, combining, re-basing.

For a flat scene, band ``b`` of a multi-lens camera is the reference band seen through a
plane homography ``H_b`` mapping **reference-band pixels to band-b pixels** (homogeneous
coordinates, x = column, y = row, pixel centres at integers):

    x_b ~ H_b x_ref

:mod:`mscal_core.registration` estimates them, :mod:`mscal_core.alignment` resamples bands
with them; this module holds the geometry both use: mapping points (:func:`map_points`),
the misalignment between two transforms (:func:`transform_distance`), the robust
combination of several estimates (:func:`combine_homographies`) and the choice of and change
to another reference band (:func:`centre_reference`, :func:`rebase`).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from .errors import FitError


def map_points(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points through a homography.

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3).
    points : numpy.ndarray
        Points (x, y), any shape that reshapes to (N, 2).

    Returns
    -------
    numpy.ndarray
        (N, 2) float64 ``H x`` dehomogenised: ``(u / w, v / w)`` for ``(u, v, w) = H (x, y, 1)``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    q = np.c_[p, np.ones(len(p))] @ np.asarray(homography, dtype=np.float64).T
    return q[:, :2] / q[:, 2:3]


def local_motion(homography: np.ndarray, point: tuple[float, float]) -> tuple[float, float, float, float]:
    """Describe what ``H`` does near ``point`` (x, y) of the reference image, for people to read.

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3) reference pixels -> band pixels; its overall scale does not matter.
    point : tuple of float
        ``(x, y)`` in reference pixels.

    Returns
    -------
    dx, dy : float
        The shift ``H x - x`` (px).
    rotation : float
        Degrees, counter-clockwise in image coordinates.
    scale : float
        The local scale factor.

    Notes
    -----
    With the Jacobian ``J = d(H x)/dx`` at ``point``: rotation = ``atan2(J10 - J01, J00 + J11)``
    and scale = ``sqrt(|det J|)``.
    """
    h = normalise_homography(homography)
    x, y = float(point[0]), float(point[1])
    w = h[2, 0] * x + h[2, 1] * y + 1.0
    u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    j = np.array([[h[0, 0] - u * h[2, 0], h[0, 1] - u * h[2, 1]],
                  [h[1, 0] - v * h[2, 0], h[1, 1] - v * h[2, 1]]]) / w
    rotation = float(np.degrees(np.arctan2(j[1, 0] - j[0, 1], j[0, 0] + j[1, 1])))
    return u - x, v - y, rotation, float(np.sqrt(abs(np.linalg.det(j))))


def grid_points(shape: tuple[int, int], n: tuple[int, int] = (9, 12), margin: float = 0.05) -> np.ndarray:
    """Return an evenly spaced grid of points over an image.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the image.
    n : tuple of int
        ``(rows, cols)`` of the grid.
    margin : float
        Inset on each side, as a fraction of the image's size.

    Returns
    -------
    numpy.ndarray
        (rows * cols, 2) float64 points (x, y), row by row.
    """
    h, w = shape
    ys = np.linspace(margin * (h - 1), (1 - margin) * (h - 1), n[0])
    xs = np.linspace(margin * (w - 1), (1 - margin) * (w - 1), n[1])
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def transform_distance(h_a: np.ndarray, h_b: np.ndarray, shape: tuple[int, int],
                       n: tuple[int, int] = (9, 12)) -> np.ndarray:
    """Distances (px) between ``H_a x`` and ``H_b x`` over :func:`grid_points` of ``shape``.

    The misalignment one transform leaves against the other.

    Parameters
    ----------
    h_a, h_b : numpy.ndarray
        (3, 3) transforms of the same reference grid.
    shape : tuple of int
        ``(H, W)`` of the reference grid.
    n : tuple of int
        ``(rows, cols)`` of the grid of points.

    Returns
    -------
    numpy.ndarray
        (rows * cols,) float64 distances.
    """
    pts = grid_points(shape, n)
    return np.linalg.norm(map_points(h_a, pts) - map_points(h_b, pts), axis=1)


def scale_homography(homography: np.ndarray, factor: float) -> np.ndarray:
    """Return the same mapping on images scaled by ``factor`` (coordinates ``x' = factor x``).

    Parameters
    ----------
    homography : numpy.ndarray
        (3, 3) on the unscaled images.
    factor : float
        Scale of the images (0.5: one pyramid level down).

    Returns
    -------
    numpy.ndarray
        (3, 3) float64 ``S H S^-1`` with ``S = diag(factor, factor, 1)``.
    """
    s = np.diag([factor, factor, 1.0])
    return s @ np.asarray(homography, dtype=np.float64) @ np.diag([1.0 / factor, 1.0 / factor, 1.0])



def normalise_homography(h: np.ndarray) -> np.ndarray:
    """Scale a homography so that ``H[2, 2] = 1``.

    Parameters
    ----------
    h : numpy.ndarray
        (3, 3) homography (any overall scale, ``H[2, 2]`` not 0).

    Returns
    -------
    numpy.ndarray
        (3, 3) float64 ``H / H[2, 2]``: the same mapping.
    """
    h = np.asarray(h, dtype=np.float64)
    return h / h[2, 2]


def combine_homographies(homographies: Sequence[np.ndarray], shape: tuple[int, int],
                         n: tuple[int, int] = (9, 12)) -> tuple[np.ndarray, float]:
    """Robust combination of several estimates of one transform.

    Parameters
    ----------
    homographies : sequence of numpy.ndarray
        (3, 3) estimates of the same transform (e.g. one per capture).
    shape : tuple of int
        ``(H, W)`` of the reference grid.
    n : tuple of int
        ``(rows, cols)`` of the grid of points (:func:`grid_points`).

    Returns
    -------
    homography : numpy.ndarray
        (3, 3) float64 combined transform (``H[2, 2] = 1``); the estimate itself when there is
        one.
    spread : float
        The median over grid points of the median distance of the estimates to it (px); 0 for
        one estimate.

    Raises
    ------
    FitError
        With no estimates, or when the median points admit no homography.

    Notes
    -----
    Every estimate maps the :func:`grid_points` of ``shape``; the coordinate-wise median of the
    mapped points is fitted by a least-squares homography (``cv2.findHomography``, method 0).
    Half of the estimates may be arbitrarily wrong (breakdown point of the median).
    """
    hs = [np.asarray(h, dtype=np.float64) for h in homographies]
    if not hs:
        raise FitError("no transform estimates to combine", hint="register at least one capture")
    if len(hs) == 1:
        return normalise_homography(hs[0]), 0.0
    pts = grid_points(shape, n)
    mapped = np.stack([map_points(h, pts) for h in hs])  # (k, N, 2)
    med = np.median(mapped, axis=0)
    h, _ = cv2.findHomography(pts, med, 0)
    if h is None:
        raise FitError("the median of the transforms is degenerate", hint="check the captures' registrations")
    spread = float(np.median(np.median(np.linalg.norm(mapped - med[None], axis=2), axis=0)))
    return normalise_homography(h), spread



def centre_reference(homographies: np.ndarray, shape: tuple[int, int]) -> int:
    """Choose the reference band whose warps to the others are smallest.

    Parameters
    ----------
    homographies : numpy.ndarray
        (band, 3, 3) transforms from the pixels of any one band to each band's.
    shape : tuple of int
        ``(H, W)`` of the bands.

    Returns
    -------
    int
        The band whose transforms to all other bands move the grid least (sum over bands of the
        median grid displacement), i.e. the lens in the middle of the rig: aligning to it keeps
        the warps and the lost border smallest.
    """
    n = len(homographies)
    pts = grid_points(shape)
    cost = np.zeros(n)
    for c in range(n):
        inv_c = np.linalg.inv(homographies[c])
        for b in range(n):
            h = homographies[b] @ inv_c
            cost[c] += float(np.median(np.linalg.norm(map_points(h, pts) - pts, axis=1)))
    return int(np.argmin(cost))


def rebase(homographies: np.ndarray, reference: int) -> np.ndarray:
    """Re-express the transforms relative to another reference band.

    Parameters
    ----------
    homographies : numpy.ndarray
        (band, 3, 3) transforms from the old reference's pixels to each band's.
    reference : int
        The new reference band.

    Returns
    -------
    numpy.ndarray
        ``H'_b = H_b H_ref^-1`` (band ``reference``'s pixels -> old reference pixels -> band b
        pixels), each scaled to ``H[2, 2] = 1``; ``H'_reference`` is the identity.
    """
    inv = np.linalg.inv(homographies[reference])
    return np.stack([normalise_homography(h @ inv) for h in homographies])
