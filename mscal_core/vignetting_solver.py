"""The sparse least squares behind the vignetting fit, Eq. 8-10 (no I/O).

:func:`mscal_core.vignetting.fit_vignetting` turns a band's reflector observations into the
unknowns V(x) per pixel and L(p) per plane cell; this module holds the parts that work on the
observations as a sparse pixel x cell incidence structure: which observations inform the fit
(:func:`informative`), the log-domain start (:func:`log_init`) and the alternation of the
paper's Eq. 9 and 10 (:func:`alternate`). Every observation joins one pixel to one cell, so the
unknowns form a bipartite graph: the sums over a pixel's or a cell's observations are one
sparse product each, and the cells can be eliminated exactly from any linear system in
(pixels, cells) because their block is diagonal.

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter
from scipy.sparse.csgraph import connected_components

from .errors import FitError, InputError

__all__ = [
    "ROBUST_LOSSES",
    "alternate",
    "compact",
    "csr",
    "incidence",
    "informative",
    "log_init",
    "has_outliers",
    "pixel_noise_variance",
    "reweighted",
    "robust_scale",
    "robust_weights",
    "shrink_detail",
    "view_offset_weights",
]

#: Tuning constants of the robust losses, in units of the residuals' MAD scale: each gives 95 %
#: of the least-squares efficiency when the residuals are Gaussian (Huber's k = 1.345, the
#: Cauchy loss's c = 2.385; Holland and Welsch 1977).
ROBUST_LOSSES = {"huber": 1.345, "cauchy": 2.3849}

#: Consistency factor of the MAD: ``1.4826 median |r|`` estimates the standard deviation of
#: Gaussian residuals.
MAD_TO_SIGMA = 1.4826

#: Floor of the robust scale (relative residual). The plane cells alone leave about 0.5 % of
#: light variation inside a cell (see :data:`mscal_core.vignetting.DEFAULT_CELLS_ALONG`), so a
#: residual below 0.1 % says nothing about an outlier; on noise-free data the floor keeps the
#: weights at 1 instead of dividing rounding errors by a zero scale.
MIN_ROBUST_SCALE = 1e-3

#: The robust alternation stops when this percentile of the relative change of V in a sweep is
#: below ``tol``, not its maximum: a few pixels seen a handful of times, whose observations'
#: weights keep trading places around the loss's corner, move by ~1e-4 for tens of sweeps
#: after the rest has settled to 1e-7 (measured on a 33-view band of a varied session).
ROBUST_STOP_PERCENTILE = 99.0

#: The observations' own robust weights apply only when more than this fraction of them miss
#: by more than :data:`OUTLIER_SCALES` robust scales in the least-squares fit. Measured
#: beyond 6 scales: clean bands of the varied sessions 0.00-0.04 % (their shot noise makes
#: the dim pixels' relative residuals heavy-tailed: 0.6-0.7 % beyond 4 scales on sessions 5
#: and 6, where the per-observation loss then cost 3-5 % of V error), a view of 40 off by
#: 15 % 2.1 %, a 25 % shadow over a third of one view 0.6 %. Gaussian noise: 2e-9.
ROBUST_MIN_OUTLIERS = 0.002

#: Misses beyond this many robust scales count as outliers for :data:`ROBUST_MIN_OUTLIERS`.
OUTLIER_SCALES = 6.0

Structure = tuple[np.ndarray, np.ndarray, np.ndarray]


def incidence(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int) -> Structure:
    """Return one sparse incidence structure for all the fit's sums.

    ``(order, indices, indptr)`` of the CSR matrix with one entry per observation (row = pixel,
    column = cell), the entries of a row in observation order (a stable sort).
    ``csr(data[order], indices, indptr)`` then sums ``data`` times a vector per pixel (``@``)
    or per cell (``.T @``), as ``np.bincount`` of the gathered products does, in one sparse
    product each, without the (observation,) temporaries.

    Parameters
    ----------
    rows : numpy.ndarray
        (n_obs,) integer row (pixel) index of each observation, in ``[0, n_rows)``.
    cols : numpy.ndarray
        (n_obs,) integer column (cell) index of each observation, in ``[0, n_cols)``.
    n_rows, n_cols : int
        Number of pixels and of cells.

    Returns
    -------
    tuple of numpy.ndarray
        ``(order, indices, indptr)``: the stable sort of the observations by row, their
        column indices in that order and the CSR row pointers (int32 where they fit).

    Notes
    -----
    The sums of Eq. 9 and 10 of [1]_ over a pixel's or a cell's observations are products
    with this matrix (pixels) or its transpose (cells).

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    order = np.argsort(rows, kind="stable")
    indptr = np.zeros(n_rows + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n_rows), out=indptr[1:])
    small = max(n_cols, int(indptr[-1])) < np.iinfo(np.int32).max
    idx_type = np.int32 if small else np.int64
    return order, cols[order].astype(idx_type), indptr.astype(idx_type)


def csr(data: np.ndarray, structure: Structure, shape: tuple[int, int]) -> sp.csr_matrix:
    """Return the CSR matrix of ``data`` (one value per observation) on an :func:`incidence` structure.

    Parameters
    ----------
    data : numpy.ndarray
        (n_obs,) value of each observation, in observation order.
    structure : tuple of numpy.ndarray
        ``(order, indices, indptr)`` from :func:`incidence`.
    shape : tuple of int
        ``(n_rows, n_cols)`` of the matrix.

    Returns
    -------
    scipy.sparse.csr_matrix
        Entry ``(row, col)`` is the sum of ``data`` over the observations joining them.
    """
    order, indices, indptr = structure
    return sp.csr_matrix((data[order], indices, indptr), shape=shape)


def compact(index: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(np.unique(index), position of each index in it)``.

    For indices in ``[0, size)``, by counting instead of sorting (O(n + size)).

    Parameters
    ----------
    index : numpy.ndarray
        (n,) non-negative integers below ``size``.
    size : int
        Upper bound (exclusive) of the indices.

    Returns
    -------
    active : numpy.ndarray
        The distinct indices in increasing order.
    rank : numpy.ndarray
        (n,) position of each element of ``index`` in ``active``.
    """
    seen = np.bincount(index, minlength=size) > 0
    active = np.flatnonzero(seen)
    rank = np.cumsum(seen) - 1
    return active, rank[index]


def informative(pix: np.ndarray, cell: np.ndarray, n_pix: int, n_cells: int) -> np.ndarray:
    """Step 1 of :func:`mscal_core.vignetting.fit_vignetting`.

    Mask of the observations in cells seen by >= 2 different pixels, within the largest
    connected part of the pixel/cell graph.

    Parameters
    ----------
    pix : numpy.ndarray
        (n_obs,) pixel index of each observation, in ``[0, n_pix)``.
    cell : numpy.ndarray
        (n_obs,) plane-cell index of each observation, in ``[0, n_cells)``.
    n_pix, n_cells : int
        Number of pixels and of plane cells.

    Returns
    -------
    numpy.ndarray
        (n_obs,) bool: the observations that constrain V.

    Raises
    ------
    FitError
        When no cell was seen by two different pixels (the views do not constrain V).

    Notes
    -----
    Eq. 8 of [1]_ determines ``V(x)`` and ``L(p)`` only up to one common scale on each
    connected part of the bipartite graph joining pixels to the cells they saw; a cell seen
    by one pixel only adds an unknown for each equation and constrains nothing.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    # exact integer test n * sum(p^2) - (sum p)^2 > 0 in float64: all terms are integers
    # below 2**53 here
    nc = np.bincount(cell, minlength=n_cells).astype(np.float64)
    s1 = np.bincount(cell, weights=pix.astype(np.float64), minlength=n_cells)
    s2 = np.bincount(cell, weights=pix.astype(np.float64) ** 2, minlength=n_cells)
    multi = nc * s2 - s1 * s1 > 0.5
    use = multi[cell]
    if not use.any():
        raise FitError(
            "no reflector point was seen by two different pixels: the views do not constrain "
            "the vignetting",
            hint="take reflector images from many viewpoints, moving the reflector across the "
            "image",
        )
    # largest connected part of the bipartite pixel/cell graph
    up, uc = pix[use], cell[use]
    graph = sp.coo_matrix(
        (np.ones(up.size, dtype=np.int8), (up, n_pix + uc)), shape=(n_pix + n_cells,) * 2
    ).tocsr()
    n_comp, labels = connected_components(graph, directed=False)
    if n_comp > 1:
        sizes = np.bincount(labels[up], minlength=n_comp)
        use[np.flatnonzero(use)[labels[up] != int(np.argmax(sizes))]] = False
    return use


def log_init(
    pix: np.ndarray, cell: np.ndarray, y: np.ndarray, n_pix: int, n_cell: int, max_iter: int,
    structure: Structure, weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Start V, L from ``log y = log V(x) + log L(p)`` by sparse linear least squares.

    Weights. Eq. 8 is a least-squares problem in ``y`` itself (weighted by ``w``: module
    docstring of :mod:`mscal_core.vignetting`); to first order its residual is
    ``y - V L = y (log y - log V - log L)``, so the log system weighted by ``w y^2`` has Eq. 8's
    minimum to first order in the noise, and the Eq. 9/10 alternation that follows starts next
    to it (the unweighted log fit gives every observation the same say, a dim cell in the
    shadow as much as a bright one, and leaves the alternation more to do where the light is
    uneven). ``weights`` are those ``w y^2`` (any common scale; default 1: unweighted).

    With ``A`` the weighted pixel x cell incidence matrix of the observations
    (:func:`incidence`) and ``D_p``, ``D_c`` the weight sums per pixel and per cell, the
    normal equations of ``a = log V``, ``b = log L`` are ``[[D_p, A], [A', D_c]] [a; b] =
    [r_p; r_c]`` (``r`` the weighted sums of ``log y`` per pixel and per cell). ``D_c`` is
    diagonal, so the cells are eliminated exactly: ``b = D_c^-1 (r_c - A' a)`` and ``a``
    solves the pixels' Schur complement

        ``(D_p - A D_c^-1 A') a = r_p - A D_c^-1 r_c``

    by conjugate gradients preconditioned with ``D_p`` (matrix-free: one product with ``A'``
    and one with ``A`` per iteration, no (observation,) temporaries, and no threaded-BLAS dot
    products, slow on a busy 2-core machine). On this bipartite structure CG on the Schur
    complement reaches a given accuracy in about half the iterations that the same CG on the
    whole system with its block-Jacobi preconditioner ``diag(D_p, D_c)`` needs (the iterates
    of the latter at even steps are those of the former; each iteration costs the same two
    products), so the start costs half as much. The consistent system's one-dimensional null
    space (``a + c``, ``b - c``) does not disturb CG from a zero start; the scale is fixed
    later (``max V = 1``). Stops when the preconditioned residual has fallen by 1e-7 (1e-14
    squared) or after ``max_iter`` iterations.

    Parameters
    ----------
    pix : numpy.ndarray
        (n_obs,) pixel index of each observation.
    cell : numpy.ndarray
        (n_obs,) plane-cell index of each observation.
    y : numpy.ndarray
        (n_obs,) positive observed values ``U(I) / t``.
    n_pix, n_cell : int
        Number of pixels and of cells.
    max_iter : int
        Most conjugate-gradient iterations.
    structure : tuple of numpy.ndarray
        :func:`incidence` of ``(pix, cell)``.
    weights : numpy.ndarray, optional
        (n_obs,) weights ``w y^2`` of the log system; ``None``: unweighted.

    Returns
    -------
    v : numpy.ndarray
        (n_pix,) start of V, maximum 1.
    lum : numpy.ndarray
        (n_cell,) start of L on the same scale.

    Notes
    -----
    Taking logarithms of Eq. 8 of [1]_, ``y = V(x) L(p)``, gives the linear system above.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    z = np.log(y)
    z0 = float(np.median(z))
    z = z - z0
    wt = np.ones(pix.size) if weights is None else np.asarray(weights, dtype=np.float64)
    deg_p = np.bincount(pix, weights=wt, minlength=n_pix)
    deg_c = np.bincount(cell, weights=wt, minlength=n_cell)
    inc = csr(wt, structure, (n_pix, n_cell))
    inc_t = inc.T
    rp = np.bincount(pix, weights=wt * z, minlength=n_pix)
    rc = np.bincount(cell, weights=wt * z, minlength=n_cell)

    def schur(d: np.ndarray) -> np.ndarray:
        return deg_p * d - inc @ ((inc_t @ d) / deg_c)

    a = np.zeros(n_pix)
    r = rp - inc @ (rc / deg_c)
    zr = r / deg_p
    d = zr.copy()
    rho = float(np.sum(r * zr))
    rho0 = rho
    for _ in range(max(0, int(max_iter))):
        if rho <= 1e-14 * rho0 or rho <= 0:
            break
        q = schur(d)
        alpha = rho / float(np.sum(d * q))
        a += alpha * d
        r -= alpha * q
        zr = r / deg_p
        rho_new = float(np.sum(r * zr))
        d = zr + (rho_new / rho) * d
        rho = rho_new
    b = (rc - inc_t @ a) / deg_c
    off = float(np.max(a))
    return np.exp(a - off), np.exp(b + off + z0)


def alternate(
    fy: np.ndarray, fw: np.ndarray, v: np.ndarray, nca: int, max_iter: int, tol: float,
    structure: Structure,
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Step 3 of :func:`mscal_core.vignetting.fit_vignetting`.

    Alternate Eq. 10' (L from V) and Eq. 9' (V from L) from ``v``; returns
    ``(V, L consistent with V, sweeps, converged)``. The sums over a cell's and a pixel's
    observations are sparse products with the incidence matrix weighted by ``w y`` and ``w``
    (:func:`incidence`): ``L = (W_y' V) / (W' V^2)``, ``V = (W_y L) / (W L^2)``.

    Parameters
    ----------
    fy : numpy.ndarray
        (n_obs,) observed values ``y``.
    fw : numpy.ndarray
        (n_obs,) weights ``w`` of Eq. 8's least squares.
    v : numpy.ndarray
        (n_pix,) start of V.
    nca : int
        Number of cells.
    max_iter : int
        Most sweeps.
    tol : float
        Converged when the largest relative change of V in a sweep is below it.
    structure : tuple of numpy.ndarray
        :func:`incidence` of the observations.

    Returns
    -------
    tuple
        ``(V, L, sweeps, converged)``: V per pixel, L per cell consistent with V, the
        number of sweeps done and whether ``tol`` was reached.

    Notes
    -----
    Eq. 9 of [1]_, ``V(x) = sum_p w y L(p) / sum_p w L(p)^2`` (over the cells ``x`` saw), and
    Eq. 10, ``L(p) = sum_x w y V(x) / sum_x w V(x)^2`` (over the pixels that saw ``p``), each
    the exact minimiser of Eq. 8 with the other factor held.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    npa = v.size
    wy_m = csr(fw * fy, structure, (npa, nca))
    w_m = csr(fw, structure, (npa, nca))
    wy_t, w_t = wy_m.T, w_m.T
    iterations = 0
    converged = False
    for iterations in range(1, max_iter + 1):
        lum = (wy_t @ v) / (w_t @ (v * v))
        v_new = (wy_m @ lum) / (w_m @ (lum * lum))
        change = float(np.max(np.abs(v_new - v) / v_new))
        v = v_new
        if change < tol:
            converged = True
            break
    # final L consistent with the final V
    lum = (wy_t @ v) / (w_t @ (v * v))
    return v, lum, iterations, converged


def robust_weights(resid: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """Return the IRLS weight of each observation for its relative residual.

    Parameters
    ----------
    resid : numpy.ndarray
        (n_obs,) relative residuals ``y / (V(x) L(p)) - 1``.
    loss : str
        ``"huber"`` or ``"cauchy"`` (:data:`ROBUST_LOSSES`).
    scale : float
        Robust scale of the residuals (``1.4826 median |r|``, floored at
        :data:`MIN_ROBUST_SCALE`).

    Returns
    -------
    numpy.ndarray
        (n_obs,) weights in (0, 1].

    Raises
    ------
    InputError
        On an unknown ``loss``.

    Notes
    -----
    With ``u = r / (c s)`` (``c`` the loss's constant, ``s`` the scale), the weight
    ``psi(u) / u`` of iteratively reweighted least squares is ``min(1, 1 / |u|)`` for Huber's
    loss and ``1 / (1 + u^2)`` for the Cauchy loss. Multiplying the weights ``w`` of Eq. 8 of
    [1]_ by it minimises ``sum w rho(r / s)`` instead of ``sum w r^2``: an observation that
    misses by many times the noise (a shadow, a glint, a view whose marker pose is wrong) has
    a bounded (Huber) or vanishing (Cauchy) say, one within the noise keeps its full say.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    if loss not in ROBUST_LOSSES:
        raise InputError(
            f"unknown robust loss {loss!r} of the vignetting fit; use one of "
            f"{', '.join(ROBUST_LOSSES)} (or None for plain least squares)"
        )
    u = np.abs(resid)
    u *= 1.0 / (ROBUST_LOSSES[loss] * scale)
    if loss == "huber":
        np.maximum(u, 1.0, out=u)
    else:
        np.square(u, out=u)
        u += 1.0
    return np.reciprocal(u, out=u)


def robust_scale(resid: np.ndarray, samples: int = 65536) -> float:
    """Return the MAD scale ``1.4826 median |r|`` of relative residuals, floored.

    Parameters
    ----------
    resid : numpy.ndarray
        (n_obs,) relative residuals ``y / (V(x) L(p)) - 1``.
    samples : int
        The median is taken over at most about this many residuals (every ``n // samples``-th;
        its relative standard error is then about ``1.1 / sqrt(samples)``, 0.5 %).

    Returns
    -------
    float
        The scale, at least :data:`MIN_ROBUST_SCALE`.

    Notes
    -----
    The residuals of Eq. 8 of [1]_ have median about 0 at the fit, so the MAD about 0 is
    their robust spread; ``1.4826`` makes it the standard deviation of Gaussian residuals.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    step = max(1, resid.size // max(1, int(samples)))
    if resid.size == 0:
        return MIN_ROBUST_SCALE
    return max(MAD_TO_SIGMA * float(np.median(np.abs(resid[::step]))), MIN_ROBUST_SCALE)


def view_offset_weights(
    resid: np.ndarray, view: np.ndarray, fw: np.ndarray, scale: float, n_views: int | None = None
) -> np.ndarray:
    """Return each view's Huber weight for its offset from the fit.

    Parameters
    ----------
    resid : numpy.ndarray
        (n_obs,) relative residuals ``y / (V(x) L(p)) - 1``.
    view : numpy.ndarray
        (n_obs,) non-negative integer view of each observation.
    fw : numpy.ndarray
        (n_obs,) Eq. 8 weights ``w``.
    scale : float
        Robust scale of the residuals (:func:`robust_scale`).
    n_views : int, optional
        Number of views (default ``view.max() + 1``).

    Returns
    -------
    numpy.ndarray
        (n_views,) weights in (0, 1]; 1 for a view without observations.

    Notes
    -----
    A view's offset ``m`` is the ``w``-weighted mean of its residuals clipped to
    ``+-3 s`` (a patch of outliers does not carry it; that is the per-observation loss's
    part). Its weight is Huber's ``min(1, k s / |m|)`` with ``k = 1.345`` and ``s`` the
    scale of the single residuals: a view whose intensities or pose are off by more than
    the noise of one pixel has all its pixels off together, which no single pixel shows
    (a view 7 % dark in a band with 2.5 % noise). A view that agrees with the fit of
    Eq. 8 of [1]_ to within the noise has weight exactly 1, whatever its noise.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    n = int(view.max()) + 1 if n_views is None and view.size else int(n_views or 0)
    clipped = np.clip(resid, -3.0 * scale, 3.0 * scale)
    den = np.bincount(view, weights=fw, minlength=n)
    num = np.bincount(view, weights=fw * clipped, minlength=n)
    offset = np.abs(num) / np.maximum(den, np.finfo(np.float64).tiny)
    return 1.0 / np.maximum(offset / (ROBUST_LOSSES["huber"] * scale), 1.0)


def reweighted(
    fy: np.ndarray, fw: np.ndarray, v: np.ndarray, cp: np.ndarray, cc: np.ndarray, nca: int,
    loss: str, max_iter: int, tol: float, structure: Structure,
    view: np.ndarray | None = None, per_observation: bool = True,
) -> tuple[np.ndarray, np.ndarray, int, bool, np.ndarray, float]:
    """Step 3 of :func:`mscal_core.vignetting.fit_vignetting` with a robust loss.

    Iteratively reweighted least squares of Eq. 8 inside the Eq. 9'/10' alternation, from the
    start ``v``: before each sweep the relative residuals ``r = y / (V L) - 1`` of the current
    V and L give their scale ``s`` (:func:`robust_scale`) and each observation's weight
    ``rho`` (:func:`robust_weights`), and the sweep (L from V, then V from L) runs with the
    weights ``w rho``. Reweighting every sweep instead of alternating to convergence between
    reweightings costs the residuals and the weighted matrices' data per sweep (written in
    place, the observations put in the matrices' order once) and about twice the sweeps of
    the least-squares alternation (9 against 4 on a 33-view band of a varied session).
    The scale follows the fit until it changes by less than 1 % in a sweep and is then held
    (a scale that moves with every sweep moves the weights, and V, by more than ``tol``).
    Stops when the :data:`ROBUST_STOP_PERCENTILE` percentile of the relative change of V in
    a sweep is below ``tol``. :func:`mscal_core.vignetting.fit_vignetting` runs it from the
    least-squares fit, and only when :func:`has_outliers` finds something that disagrees.

    Parameters
    ----------
    fy, fw : numpy.ndarray
        (n_obs,) observed values ``y`` and Eq. 8 weights ``w``.
    v : numpy.ndarray
        (n_pix,) start of V (:func:`log_init` or an earlier fit).
    cp, cc : numpy.ndarray
        (n_obs,) compact pixel and cell index of each observation.
    nca : int
        Number of cells.
    loss : str
        ``"huber"`` or ``"cauchy"``.
    max_iter : int
        Most sweeps.
    tol : float
        Converged when the largest relative change of V in a sweep is below it.
    structure : tuple of numpy.ndarray
        :func:`incidence` of the observations.
    view : numpy.ndarray, optional
        (n_obs,) view of each observation: each observation's weight is then also multiplied
        by its view's :func:`view_offset_weights`.
    per_observation : bool
        Whether each observation's own :func:`robust_weights` apply (False: only the views').

    Returns
    -------
    tuple
        ``(V, L, sweeps, converged, rho, scale)``: the robust V and L (L consistent with V
        under the last weights), the sweeps done, whether ``tol`` was reached, each
        observation's robust weight in the last sweep (observation order) and its scale.

    Notes
    -----
    The M-estimate of Eq. 8 of [1]_, ``min sum w rho(r / s)``, has the normal equations of a
    least-squares problem with weights ``w psi(u) / u``; Eq. 9 and 10 with those weights
    are its exact coordinate minimisers with the weights held, so each sweep does not
    increase the weighted-least-squares majoriser of the robust loss at the current fit
    (for Huber's convex loss this is the usual IRLS descent).

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    order = structure[0]
    y_s, w_s, p_s, c_s = fy[order], fw[order], cp[order], cc[order]
    view_s = None if view is None else view[order]
    n_views = int(view.max()) + 1 if view is not None and view.size else 0
    # the weighted matrices are made once; each sweep writes its weights into their data (the
    # transposes share it)
    wy_m = csr(fw * fy, structure, (v.size, nca))
    w_m = csr(fw, structure, (v.size, nca))
    wy_t, w_t = wy_m.T, w_m.T
    lum = (wy_t @ v) / (w_t @ (v * v))
    resid = np.empty_like(y_s)
    rho_s, scale, settled = np.ones_like(y_s), 0.0, False
    iterations, converged = 0, False
    stop_count = (1.0 - ROBUST_STOP_PERCENTILE / 100.0) * v.size
    for iterations in range(1, max(1, int(max_iter)) + 1):
        np.multiply(v[p_s], lum[c_s], out=resid)
        np.divide(y_s, resid, out=resid)
        resid -= 1.0
        if not settled:
            new_scale = robust_scale(resid)
            settled = abs(new_scale - scale) < 0.01 * new_scale
            scale = new_scale
        rho_s = robust_weights(resid, loss, scale) if per_observation else np.ones_like(resid)
        if view_s is not None:
            rho_s *= view_offset_weights(resid, view_s, w_s, scale, n_views)[view_s]
        np.multiply(w_s, rho_s, out=w_m.data)
        np.multiply(w_m.data, y_s, out=wy_m.data)
        lum = (wy_t @ v) / (w_t @ (v * v))
        v_new = (wy_m @ lum) / (w_m @ (lum * lum))
        moved = np.count_nonzero(np.abs(v_new - v) > tol * v_new)
        v = v_new
        if moved <= stop_count:
            converged = True
            break
    lum = (wy_t @ v) / (w_t @ (v * v))
    rho = np.empty_like(rho_s)
    rho[order] = rho_s
    return v, lum, iterations, converged, rho, scale


def has_outliers(resid: np.ndarray, scale: float) -> bool:
    """Return whether the residuals have more outliers than the noise explains.

    Parameters
    ----------
    resid : numpy.ndarray
        (n_obs,) relative residuals ``y / (V(x) L(p)) - 1`` of the least-squares fit.
    scale : float
        Their robust scale (:func:`robust_scale`).

    Returns
    -------
    bool
        True when more than :data:`ROBUST_MIN_OUTLIERS` of them are beyond
        :data:`OUTLIER_SCALES` scales.

    Notes
    -----
    Decides whether the robust refinement of Eq. 8 of [1]_ (:func:`reweighted`) runs: on
    residuals with Gaussian tails it would only cost efficiency and time.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    limit = OUTLIER_SCALES * scale
    return int(np.count_nonzero(np.abs(resid) > limit)) > ROBUST_MIN_OUTLIERS * resid.size


def pixel_noise_variance(resid: np.ndarray, pix: np.ndarray, weight: np.ndarray, shape: tuple[int, int],
                         n_unknowns: int, sigma: float = 6.0) -> np.ndarray:
    """Return the variance of each pixel's Eq. 9' estimate of V, relative to V, from the residuals.

    Parameters
    ----------
    resid : numpy.ndarray
        (n_obs,) relative residuals ``y / (V(x) L(p)) - 1`` of the fit.
    pix : numpy.ndarray
        (n_obs,) flat pixel of each observation in ``shape``.
    weight : numpy.ndarray
        (n_obs,) each observation's weight in Eq. 9', ``w L(p)^2``.
    shape : tuple of int
        ``(H, W)`` of the band grid.
    n_unknowns : int
        Unknowns the fit had (active pixels plus active plane cells).
    sigma : float
        Pixels: the observations' noise is pooled over a Gaussian of this width.

    Returns
    -------
    numpy.ndarray
        (H, W) ``c s2(x) sum a^2 / (sum a)^2`` over each pixel's observations (``a`` their
        weights, ``s2(x)`` the mean squared residual near the pixel, ``c = n_obs / (n_obs -
        n_unknowns)``); infinite where no observation is.

    Notes
    -----
    Eq. 9 of [1]_, ``V(x) = sum t L U / sum (t L)^2``, is a weighted mean of the ratios
    ``y / L`` of the pixel's observations; the variance of a weighted mean of independent
    errors of variance ``s2`` is ``s2 sum a^2 / (sum a)^2``. The few residuals of one pixel
    say little about ``s2``: it is pooled over the nearby pixels (the noise changes slowly
    across the image, with the falloff and the light). V and L were fitted to the same
    residuals, which makes them smaller than the noise by the degrees of freedom the fit
    took: ``c`` puts that back (1.6 with 12 views of a band grid, 1.1 with 40).

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    h, w = int(shape[0]), int(shape[1])
    n_pix = h * w
    n = np.bincount(pix, minlength=n_pix).astype(np.float64)
    sa = np.bincount(pix, weights=weight, minlength=n_pix)
    sa2 = np.bincount(pix, weights=weight * weight, minlength=n_pix)
    sr2 = np.bincount(pix, weights=resid * resid, minlength=n_pix)
    pooled_n = gaussian_filter(n.reshape(h, w), sigma, mode="reflect").ravel()
    pooled_r2 = gaussian_filter(sr2.reshape(h, w), sigma, mode="reflect").ravel()
    dof = float(pix.size) / max(float(pix.size - int(n_unknowns)), 1.0)
    out = np.full(n_pix, np.inf)
    ok = (n > 0) & (sa > 0) & (pooled_n > 0)
    out[ok] = dof * pooled_r2[ok] / pooled_n[ok] * sa2[ok] / (sa[ok] * sa[ok])
    return out.reshape(h, w)


def shrink_detail(detail: np.ndarray, noise_var: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, float]:
    """Shrink the pixel-scale detail of V by its signal-to-noise ratio (empirical Bayes).

    Parameters
    ----------
    detail : numpy.ndarray
        (H, W) V minus its smooth part (the radial model plus the residual smoothed over a
        few pixels), on the observed pixels.
    noise_var : numpy.ndarray
        (H, W) variance of each pixel's V estimate (:func:`pixel_noise_variance` times V^2).
    observed : numpy.ndarray
        (H, W) bool: the pixels the fit observed well; only they are used and changed.

    Returns
    -------
    tuple of (numpy.ndarray, float)
        The detail times ``s2 / (s2 + noise_var)`` on the observed pixels (unchanged
        elsewhere and where the noise is not finite), and ``s2``, the variance of the true
        detail: the detail's mean square less the mean noise variance (at least 0).

    Notes
    -----
    Eq. 9 of [1]_ gives V per pixel, so real pixel-to-pixel gain differences (PRNU, a speck
    of dust) are part of V; so is the noise of each pixel's estimate, about the observations'
    relative noise over the square root of the views that saw the pixel (2 % with dim views
    of a noisy sensor). Each pixel's detail is the true detail plus that noise; with the
    true detail's variance ``s2`` and the noise's ``n``, the estimate of least mean square
    error that is linear in the pixel's value keeps the share ``s2 / (s2 + n)``: all of a
    sensor's PRNU where it is well above the noise, nothing where there is none.

    References
    ----------
    .. [1] R. Khanna et al., "On Field Radiometric Calibration for Multispectral Cameras",
           ICRA 2017.
    """
    use = observed & np.isfinite(noise_var) & np.isfinite(detail)
    if not use.any():
        return detail, float("nan")
    s2 = max(0.0, float(np.mean(detail[use] ** 2)) - float(np.mean(noise_var[use])))
    out = detail.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = s2 / (s2 + noise_var[use])
    out[use] = detail[use] * np.where(np.isfinite(gain), gain, 1.0)
    return out, s2
