"""Optical attenuation (vignetting) from many views of a gray reflector: Eq. 8-10 (no I/O).

Model (Eq. 2, 4): a pixel ``x`` of view ``i`` that sees the reflector point ``p`` records
``U(I_i(x)) = t_i V(x) L(p)``. ``L(p)``, the radiance leaving the reflector at ``p``, is the
same in every view but free from point to point: the light on the reflector is NOT assumed
uniform anywhere. The paper fits

- (8)  ``M(L, V) = sum_{i,p} (t_i V(pi_i(p)) L(p) - U(I_i(pi_i(p))))^2``
- (9)  ``V(x) = sum t_i L(p) U(I_i(x)) / sum (t_i L(p))^2`` over all (i, p) with pi_i(p) = x
- (10) ``L(p) = sum_i t_i V(pi_i(p)) U(I_i(pi_i(p))) / sum_i (t_i V(pi_i(p)))^2``

alternately, and normalises ``max V = 1`` per band.

Discretisation. The paper discretises the reflector into points ``p`` (1000 x 1000 on
full-resolution images) and projects each into the image (``pi_i(p) = x``). Here the plane
is cut into ``nu x nv`` cells and every observed pixel is mapped once, through the inverse
map (:func:`mscal_core.geometry.pixels_to_plane`), to the cell containing the plane point
its centre sees (:func:`view_observations`). This is the same least-squares problem with the
roles of "sample" and "bin" swapped: each pixel of each view is used exactly once, none is
dropped or counted twice. Default cell size: see :data:`DEFAULT_CELLS_ALONG`.

Exposure. The observations passed to :func:`fit_vignetting` are energies per unit time
``y = U(I)/t`` (the t's are already divided in), so with ``y`` Eq. 9 and 10 read

- (9')  ``V(x) = sum w L(p) y / sum w L(p)^2``
- (10') ``L(p) = sum w V(x) y / sum w V(x)^2``

with per-observation weights ``w``: ``w = 1`` (default) weights every observation alike,
which is right for a relative (multiplicative) noise of the same size in every view;
``w = t_i^2`` reproduces the paper's Eq. 9 / 10 literally (``t L U = t^2 L y``,
``(t L)^2 = t^2 L^2``).

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from .errors import FitError, InputError
from .geometry import size_wh
from .vignetting_solver import (
    alternate,
    compact,
    has_outliers,
    incidence,
    informative,
    log_init,
    pixel_noise_variance,
    reweighted,
    robust_scale,
    robust_weights,
    shrink_detail,
    view_offset_weights,
)

#: The solver's helper under its former private name (kept for the callers that import it).
_compact = compact

__all__ = [
    "DEFAULT_CELLS_ALONG",
    "VignettingFit",
    "cell_centres",
    "cell_grid",
    "fit_vignetting",
    "view_observations",
]

#: Default number of plane cells along the longer side of the reflector. On the 217 x 409
#: band grid the reflector spans ~100-250 pixels per view, so 128 cells make a cell about
#: one pixel footprint (between 0.5 and 1.3 footprints): fine enough that the light varies
#: little inside a cell (a 2:1 gradient across the reflector changes by ~0.5 % per cell) and
#: coarse enough that a cell is seen by several pixels of several views, which is what ties
#: V(x) at different pixels together. The paper's 1000 x 1000 points suit full-resolution
#: images (5x finer): on the band grid they would leave most cells with one observation
#: per view and add unknowns without adding information.
DEFAULT_CELLS_ALONG = 128

#: Percentile of the well-observed V that is set to 1 (the robust "max V = 1" gauge).
ROBUST_MAX_PERCENTILE = 99.9

# Gaussian width (pixels) and certainty floor of the normalised convolution that carries the
# local residual (V - radial model) of the observed pixels into the filled pixels.
_FILL_SIGMA = 6.0
_FILL_CERTAINTY = 0.25
# At most this many observed pixels enter the radial model fit (random, seeded subsample).
_MODEL_SAMPLES = 20000
# Below this many observed pixels the "model" is a constant (weighted mean V).
_MODEL_MIN_PIXELS = 50
# Gaussian width (pixels) of the denoising used only to set the gauge.
_GAUGE_SIGMA = 2.0


@dataclass(frozen=True, eq=False)
class VignettingFit:
    """Result of :func:`fit_vignetting` for one band.

    Attributes
    ----------
    vignetting : numpy.ndarray
        (H, W) float64, V(x), ``max V = 1`` (gauge: the 99.9th percentile of the denoised
        well-observed V is 1, the few values above are clipped to 1); filled where not observed.
    count : numpy.ndarray
        (H, W) int64: informative observations per pixel (in cells seen by at least two
        different pixels, in the main connected part of the pixel/cell graph).
    observed : numpy.ndarray
        (H, W) bool: ``count >= min_count``; False pixels are filled smoothly.
    radiance : numpy.ndarray
        (n_cells,) float64: L(p) per plane cell in the same gauge (``V L = y``); NaN for cells
        never observed.
    residual_rms : float
        Relative rms of ``y / (V L) - 1`` over the informative observations.
    iterations : int
        Eq. 9/10 alternations done.
    converged : bool
        Whether ``tol`` was reached.
    view_weights : numpy.ndarray or None
        (n_views,) with ``robust`` and ``view_index``: each view's mean robust weight over its
        informative observations, relative to the median view (1: trusted as much as a typical
        view; a view that disagrees is well below 1); NaN for a view with no informative
        observation. None otherwise.
    robust_scale : float
        The robust scale ``1.4826 median |r|`` of the relative residuals in the last
        reweighting round (NaN without ``robust``).
    """

    vignetting: np.ndarray
    count: np.ndarray
    observed: np.ndarray
    radiance: np.ndarray
    residual_rms: float
    iterations: int
    converged: bool
    view_weights: np.ndarray | None = None
    robust_scale: float = float("nan")


# --------------------------------------------------------------------------- plane cells


def cell_grid(
    size_m: float | Sequence[float],
    *,
    cells_per_m: float | None = None,
    grid: tuple[int, int] | None = None,
) -> tuple[int, int]:
    """Return the number of plane cells ``(nu, nv)`` across the reflector.

    Parameters
    ----------
    size_m : float or sequence of float
        Reflector size ``[w, h]`` in metres (one value: a square).
    cells_per_m : float, optional
        Cell density: ``nu = ceil(w * cells_per_m)``, same for ``nv``.
    grid : tuple of int, optional
        ``(nu, nv)`` given directly; wins over ``cells_per_m``.

    Returns
    -------
    tuple of int
        ``(nu, nv)``; ``n_cells = nu * nv``. Without ``grid`` or ``cells_per_m``: square cells
        with :data:`DEFAULT_CELLS_ALONG` along the longer side.

    Raises
    ------
    InputError
        On a grid that is not two positive integers or a non-positive density.
    """
    w, h = size_wh(size_m)
    if grid is not None:
        try:
            nu, nv = (int(grid[0]), int(grid[1]))
        except (TypeError, ValueError, IndexError):
            raise InputError(
                f"cell grid must be two positive integers (nu, nv), got {grid!r}"
            ) from None
        if nu <= 0 or nv <= 0:
            raise InputError(f"cell grid must be two positive integers (nu, nv), got {grid!r}")
        return nu, nv
    if cells_per_m is not None:
        density = float(cells_per_m)
        if not np.isfinite(density) or density <= 0:
            raise InputError(f"cells_per_m must be a positive number, got {cells_per_m!r}")
        return max(1, int(np.ceil(w * density - 1e-9))), max(1, int(np.ceil(h * density - 1e-9)))
    cell = max(w, h) / DEFAULT_CELLS_ALONG
    return max(1, int(round(w / cell))), max(1, int(round(h / cell)))


def cell_centres(size_m: float | Sequence[float], grid: tuple[int, int]) -> np.ndarray:
    """Return the plane points (u, v) of the cell centres in cell-index order.

    Parameters
    ----------
    size_m : float or sequence of float
        Reflector size ``[w, h]`` in metres.
    grid : tuple of int
        ``(nu, nv)`` from :func:`cell_grid`.

    Returns
    -------
    numpy.ndarray
        ``(nu * nv, 2)`` metres. Cell ``iv * nu + iu`` spans
        ``u in [-w/2 + iu w/nu, -w/2 + (iu+1) w/nu)`` and likewise in ``v`` (``v`` up, as in the
        marker frame).
    """
    w, h = size_wh(size_m)
    nu, nv = cell_grid(size_m, grid=grid)
    uc = -0.5 * w + (np.arange(nu) + 0.5) * (w / nu)
    vc = -0.5 * h + (np.arange(nv) + 0.5) * (h / nv)
    uu, vv = np.meshgrid(uc, vc)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def view_observations(
    energy: np.ndarray,
    uv: np.ndarray,
    mask: np.ndarray,
    size_m: float | Sequence[float],
    *,
    cells_per_m: float | None = None,
    grid: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Collect the observations of ONE band in ONE view of the reflector for :func:`fit_vignetting`.

    Every pixel with ``mask`` True, finite positive energy and its plane point inside the
    reflector gives one observation: its flat pixel index ``i * W + j``, the flat index of the
    cell containing its plane point (see :func:`cell_centres`; grid from :func:`cell_grid`) and
    its energy.

    Parameters
    ----------
    energy : numpy.ndarray
        (H, W) ``U(I)/t`` (saturated pixels passed as NaN).
    uv : numpy.ndarray
        (H, W, 2) plane points from :func:`mscal_core.geometry.pixels_to_plane`.
    mask : numpy.ndarray
        (H, W) bool from :func:`mscal_core.geometry.reflector_mask`.
    size_m : float or sequence of float
        Reflector size ``[w, h]`` in metres.
    cells_per_m, grid
        The cell grid, as :func:`cell_grid`.

    Returns
    -------
    pixel_index, cell_index : numpy.ndarray
        int64, of the same length.
    values : numpy.ndarray
        float64 energies ``y = U(I)/t``.

    Raises
    ------
    InputError
        When the shapes of ``energy``, ``uv`` and ``mask`` do not match.

    Notes
    -----
    This is the inverse of the paper's ``pi_i(p) = x`` [1]_: each pixel is mapped once to the
    plane instead of each plane point projected into the image.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    e = np.asarray(energy, dtype=np.float64)
    pts = np.asarray(uv, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if e.ndim != 2 or pts.shape != e.shape + (2,) or m.shape != e.shape:
        raise InputError(
            f"energy (H, W), uv (H, W, 2) and mask (H, W) must match, got {e.shape}, "
            f"{pts.shape}, {m.shape}"
        )
    w, h = size_wh(size_m)
    nu, nv = cell_grid(size_m, cells_per_m=cells_per_m, grid=grid)
    flat = np.flatnonzero(m.ravel())
    vals = e.ravel()[flat]
    u = pts[..., 0].ravel()[flat]
    v = pts[..., 1].ravel()[flat]
    with np.errstate(invalid="ignore"):
        fu = (u + 0.5 * w) / w
        fv = (v + 0.5 * h) / h
        keep = (np.isfinite(vals) & (vals > 0) & (fu >= 0) & (fu <= 1) & (fv >= 0) & (fv <= 1))
    iu = np.minimum((fu[keep] * nu).astype(np.int64), nu - 1)
    iv = np.minimum((fv[keep] * nv).astype(np.int64), nv - 1)
    return flat[keep].astype(np.int64), iv * nu + iu, vals[keep]


# --------------------------------------------------------------------------- the fit


def _radial_design(x: np.ndarray, y: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    r2 = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (scale * scale)
    return np.stack([np.ones_like(r2), r2, r2 * r2, r2 * r2 * r2], axis=1)


def _radial_model(v: np.ndarray, weight: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Smooth radial model ``V = a0 + a1 r^2 + a2 r^4 + a3 r^6`` with a free centre.

    ``r`` is the distance to the centre (cx, cy) over the half diagonal; the centre is found
    by nonlinear least squares (variable projection: the a's are solved linearly for each
    centre), weighted by the observation count, on a seeded subsample of the observed pixels.
    Returns the model evaluated on the whole (H, W) grid.
    """
    h, w = v.shape
    ii, jj = np.nonzero(observed)
    if ii.size < _MODEL_MIN_PIXELS:  # too few pixels for a radial fit: weighted mean
        wsum = float(np.sum(weight[ii, jj]))
        if wsum > 0:
            mean = float(np.sum(v[ii, jj] * weight[ii, jj]) / wsum)
        else:
            mean = float(np.mean(v[ii, jj]))
        return np.full((h, w), mean)
    if ii.size > _MODEL_SAMPLES:
        pick = np.random.default_rng(0).choice(ii.size, _MODEL_SAMPLES, replace=False)
        ii, jj = ii[pick], jj[pick]
    xs, ys = jj.astype(np.float64), ii.astype(np.float64)
    target = v[ii, jj]
    sw = np.sqrt(weight[ii, jj])
    scale = 0.5 * float(np.hypot(h, w))

    def solve(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        design = _radial_design(xs, ys, centre, scale)
        coef = np.linalg.lstsq(design * sw[:, None], target * sw, rcond=None)[0]
        return coef, (design @ coef - target) * sw

    start = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    try:
        res = least_squares(
            lambda c: solve(c)[1], start, method="trf",
            bounds=([-0.5 * w, -0.5 * h], [1.5 * w, 1.5 * h]), x_scale=scale, max_nfev=60,
        )
        centre = res.x
    except (ValueError, np.linalg.LinAlgError):
        centre = start
    coef = solve(centre)[0]
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
    return (_radial_design(gx.ravel(), gy.ravel(), centre, scale) @ coef).reshape(h, w)


def _normalised_blur(
    values: np.ndarray, certainty: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised convolution: Gaussian blur of ``certainty * values`` and of ``certainty``."""
    num = cv2.GaussianBlur(values * certainty, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(certainty, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return num, den


def fit_vignetting(
    pixel_index: np.ndarray,
    cell_index: np.ndarray,
    values: np.ndarray,
    shape: tuple[int, int],
    n_cells: int,
    *,
    weights: np.ndarray | None = None,
    max_iter: int = 100,
    tol: float = 1e-5,
    min_count: int = 3,
    smooth_sigma: float = 0.0,
    init_iter: int = 200,
    start: np.ndarray | None = None,
    robust: str | None = None,
    view_index: np.ndarray | None = None,
    denoise: bool = True,
) -> VignettingFit:
    """Fit V(x) and L(p) of one band from all its reflector observations (Eq. 8-10).

    Parameters
    ----------
    pixel_index : numpy.ndarray
        Flat index into ``shape = (H, W)`` of every observation (the concatenated outputs of
        :func:`view_observations` over all views).
    cell_index : numpy.ndarray
        Flat plane cell of every observation, ``< n_cells``.
    values : numpy.ndarray
        ``y = U(I)/t``; non-finite or non-positive values are ignored.
    shape : tuple of int
        ``(H, W)`` of the band grid.
    n_cells : int
        Number of plane cells.
    weights : numpy.ndarray, optional
        Per observation weights of Eq. 9'/10' (module docstring); ``w = t^2`` is the paper's
        literal weighting; default 1.
    max_iter : int
        Eq. 9'/10' sweeps at most.
    tol : float
        Stop when the largest relative change of V is below this.
    min_count : int
        Pixels with fewer informative observations are filled (``observed = False``).
    smooth_sigma : float
        Pixels; > 0 smooths the residual ``V - model`` of the well-observed V (default 0: off).
    init_iter : int
        Iterations of the log-domain initialisation at most (0: start from V = 1).
    start : numpy.ndarray, optional
        (H, W) V of an earlier fit of the same band (e.g. on more views) to start the Eq.
        9'/10' alternation from instead of the log-domain initialisation; the fit converges to
        the same V (within ``tol``) without the cost of that start (a few more sweeps, fewer
        sparse products in all). Ignored where not finite and positive on the fit's pixels.
    robust : {None, "huber", "cauchy"}
        Robust loss of the iteratively reweighted refinement (step 3b); None: plain least
        squares (Eq. 8 as in the paper).
    view_index : numpy.ndarray, optional
        (n_obs,) non-negative integer view of each observation; with ``robust`` the fit
        reports each view's robust weight (``VignettingFit.view_weights``).
    denoise : bool
        Shrink the pixel-scale detail of the well-observed V by its signal-to-noise ratio
        (step 6); False keeps Eq. 9's V per pixel. Ignored with ``smooth_sigma > 0``.

    Returns
    -------
    VignettingFit
        V (``max V = 1``), the counts and the observed mask, L per cell, the residual and the
        iterations.

    Raises
    ------
    InputError
        On inconsistent inputs or an unknown ``robust`` loss.
    FitError
        When no informative observation is left (e.g. every view saw the reflector at the same
        place), no pixel has ``min_count`` of them, or the fitted V is not positive.

    Notes
    -----
    The paper fits Eq. 8, ``M(L, V) = sum_{i,p} (t_i V(pi_i(p)) L(p) - U(I_i(pi_i(p))))^2``, by
    alternating Eq. 9, ``V(x) = sum t_i L(p) U(I_i(x)) / sum (t_i L(p))^2``, and Eq. 10,
    ``L(p) = sum_i t_i V(pi_i(p)) U(I_i(pi_i(p))) / sum_i (t_i V(pi_i(p)))^2`` [1]_. With
    ``y = U(I)/t`` they read ``V(x) = sum w L(p) y / sum w L(p)^2`` (9') and
    ``L(p) = sum w V(x) y / sum w V(x)^2`` (10'). Steps:

    1. Only informative observations are used: those in cells seen by at least two different
       pixels (a cell seen by one pixel only fixes its own L and says nothing about V), in the
       largest connected part of the pixel/cell graph (a separate part would have its own
       unknown scale).
    2. Initialisation: log-domain sparse least squares ``log y = log V(x) + log L(p)``,
       weighted by ``w y^2`` so that its minimum is Eq. 8's to first order in the noise
       (preconditioned CGLS, the method of ``scipy.sparse.linalg.lsqr``, matrix-free; at most
       ``init_iter`` iterations, 0 = start from V = 1; the plane cells are eliminated
       exactly, see :func:`mscal_core.vignetting_solver.log_init`). It solves the slow, smooth
       modes that the plain alternation takes many sweeps to move. With ``start``, the
       alternation starts from that V instead.
    3. Alternate Eq. 10' (L from V) and Eq. 9' (V from L), vectorised with ``np.bincount``,
       until the largest relative change of V is below ``tol`` or ``max_iter`` sweeps.
       3b. With ``robust``, iteratively reweighted least squares from that fit
       (:func:`mscal_core.vignetting_solver.reweighted`): with ``r = y / (V L) - 1`` the
       relative residual of an observation and ``s = 1.4826 median |r|`` their scale (the
       MAD), each sweep multiplies ``w`` by ``rho = min(1, k s / |r|)`` (Huber,
       ``k = 1.345``) or ``rho = 1 / (1 + (r / (c s))^2)`` (Cauchy, ``c = 2.385``) of the
       current fit. A patch of pixels or a whole view that disagrees with the others (a
       shadow, a glint, a wrong marker pose) then counts less, instead of pulling L, and
       through L the V of every pixel that saw those cells. The observations' own weights
       apply only when more than 0.2 % of the residuals are beyond 6 scales
       (:func:`mscal_core.vignetting_solver.has_outliers`). With ``view_index`` each
       observation's weight is also multiplied by its view's Huber weight for the view's
       mean offset ``m`` (clipped residuals), ``min(1, k s / |m|)``
       (:func:`mscal_core.vignetting_solver.view_offset_weights`): a view dark by more than
       one pixel's noise counts less although none of its pixels is an outlier. Nothing to
       down-weight (no tails, no view offset beyond ``k s``): the least-squares fit is kept
       and every weight is 1.
    4. Gauge (V is known up to scale, paper: max V = 1): the 99.9th percentile over the
       well-observed pixels (``count >= min_count``) of a denoised V (the radial model of step
       5 plus the residual smoothed over 2 px) is set to 1 and L scaled inversely. A single
       noisy pixel does not set the scale, and the per-pixel noise does not push the
       percentile up (with 1 % noise a plain percentile puts the gauge ~0.5 % too high). The
       few V above 1 are clipped to 1.
    5. Pixels with ``count < min_count`` are filled with a smooth radial model
       ``a0 + a1 r^2 + a2 r^4 + a3 r^6`` around a fitted centre (the paper finds radially
       symmetric vignetting) plus the local residual of nearby observed pixels (normalised
       convolution, sigma 6 px, fading to the pure model farther away); flagged
       ``observed = False``.
    6. ``smooth_sigma > 0`` (pixels, default 0 = off) smooths the well-observed V to beat
       per-pixel noise: only the residual ``V - model`` is smoothed (normalised convolution
       over the observed pixels) and added back to the model, so the falloff itself, which the
       model carries, is not flattened. Off by default because per-pixel gain differences
       (PRNU, dust) are real parts of V. Instead, with ``denoise`` (default), the detail
       ``V - (model + residual smoothed over 2 px)`` is shrunk by its signal-to-noise ratio
       (:func:`mscal_core.vignetting_solver.shrink_detail`, each pixel's noise from its
       observations' residuals, :func:`mscal_core.vignetting_solver.pixel_noise_variance`):
       a sensor's PRNU above the noise stays, the noise of dim or few views goes.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    h, w = int(shape[0]), int(shape[1])
    n_pix = h * w
    n_cells = int(n_cells)
    if robust is not None:
        robust_weights(np.zeros(0), robust, 1.0)  # an unknown loss fails here, before the work
    pix, cell, y, wt, view = _checked_observations(
        pixel_index, cell_index, values, shape, n_cells, weights, min_count, view_index
    )
    # 1. informative observations, 2. log-domain start, 3. Eq. 10' / Eq. 9' alternation
    use = informative(pix, cell, n_pix, n_cells)
    fp, fc, fy, fw = pix[use], cell[use], y[use], wt[use]
    # compact indices of the active unknowns
    act_p, cp = compact(fp, n_pix)
    act_c, cc = compact(fc, n_cells)
    structure = incidence(cp, cc, act_p.size, act_c.size)
    v = _start_values(start, act_p, n_pix)
    if v is None:
        # weighted w y^2: the log fit with Eq. 8's minimum to first order (see log_init)
        v, lum = log_init(cp, cc, fy, act_p.size, act_c.size, int(init_iter), structure,
                          fw * (fy / float(np.median(fy))) ** 2)
    v, lum, iterations, converged = alternate(fy, fw, v, act_c.size, int(max_iter), tol, structure)
    resid = fy / (v[cp] * lum[cc]) - 1.0
    view_weights, rscale = None, float("nan")
    if robust is not None:
        # 3b. reweighted from the least-squares fit, when something disagrees
        rscale, rho = robust_scale(resid), np.ones_like(fy)
        fv = None if view is None else view[use]
        tails = has_outliers(resid, rscale)
        if tails or (fv is not None and bool(np.any(view_offset_weights(resid, fv, fw, rscale) < 1.0))):
            v, lum, sweeps, converged, rho, rscale = reweighted(
                fy, fw, v, cp, cc, act_c.size, robust, int(max_iter), tol, structure, fv, tails
            )
            iterations += sweeps
            resid = fy / (v[cp] * lum[cc]) - 1.0
        if view is not None:
            view_weights = _view_weights(fv, fw, rho)
    residual_rms = float(np.sqrt(np.mean(resid * resid)))
    noise_rel = None
    if denoise and not (smooth_sigma and float(smooth_sigma) > 0):  # step 6's shrinkage: each pixel's noise
        eff = fw * lum[cc] ** 2 * (rho if robust is not None else 1.0)
        noise_rel = pixel_noise_variance(resid, fp, eff, (h, w), act_p.size + act_c.size)

    count = np.bincount(fp, minlength=n_pix).astype(np.int64).reshape(h, w)
    observed = count >= int(min_count)
    if not observed.any():
        raise FitError(
            f"no pixel has {min_count} or more informative reflector observations",
            hint="take more reflector images, or lower min_count",
        )
    v_full = np.full(n_pix, np.nan)
    v_full[act_p] = v
    # 4. gauge, 5./6. optional smoothing of the residual, fill
    scale, v_img, model, resid_img = _gauge(v_full.reshape(h, w), count, observed)
    lum = lum * scale
    out = _smooth_and_fill(v_img, model, resid_img, count, observed, smooth_sigma, noise_rel)
    radiance = _cell_radiance(out, pix, cell, y, wt, n_cells)
    radiance[act_c] = lum

    out.flags.writeable = False
    count.flags.writeable = False
    observed.flags.writeable = False
    radiance.flags.writeable = False
    return VignettingFit(
        vignetting=out,
        count=count,
        observed=observed,
        radiance=radiance,
        residual_rms=residual_rms,
        iterations=iterations,
        converged=converged,
        view_weights=view_weights,
        robust_scale=rscale,
    )


def _view_weights(view: np.ndarray, fw: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Each view's ``w``-weighted mean robust weight, relative to the median view."""
    n_views = int(view.max()) + 1 if view.size else 0
    den = np.bincount(view, weights=fw, minlength=n_views)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(view, weights=fw * rho, minlength=n_views) / den
    mean[den <= 0] = np.nan
    typical = float(np.nanmedian(mean)) if np.isfinite(mean).any() else 1.0
    return mean / typical


def _start_values(start: np.ndarray | None, active: np.ndarray, n_pix: int) -> np.ndarray | None:
    """Return V of ``start`` on the active pixels.

    None without a start or where one of its values there is not finite and positive.
    """
    if start is None:
        return None
    flat = np.asarray(start, dtype=np.float64).ravel()
    if flat.size != n_pix:
        raise InputError(f"start must have the band's {n_pix} pixels, got {flat.size}")
    v = flat[active]
    return v.copy() if bool(np.all(np.isfinite(v) & (v > 0))) else None


def _checked_observations(
    pixel_index: np.ndarray, cell_index: np.ndarray, values: np.ndarray, shape: tuple[int, int],
    n_cells: int, weights: np.ndarray | None, min_count: int, view_index: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Check the inputs of :func:`fit_vignetting`.

    Return ``(pixel, cell, y, weight, view)`` of the usable observations (finite, positive
    value and weight), indices as int64 (``view`` None without ``view_index``).
    """
    h, w = int(shape[0]), int(shape[1])
    n_pix = h * w
    pix = np.asarray(pixel_index).ravel()
    cell = np.asarray(cell_index).ravel()
    y = np.asarray(values, dtype=np.float64).ravel()
    if h <= 0 or w <= 0 or n_cells <= 0:
        raise InputError(f"shape and n_cells must be positive, got {shape!r}, {n_cells}")
    if not (pix.size == cell.size == y.size):
        raise InputError(
            f"pixel_index, cell_index and values must have the same length, got {pix.size}, "
            f"{cell.size}, {y.size}"
        )
    integral = np.issubdtype(pix.dtype, np.integer) and np.issubdtype(cell.dtype, np.integer)
    if pix.size and not integral:
        raise InputError("pixel_index and cell_index must be integer arrays")
    pix = pix.astype(np.int64)
    cell = cell.astype(np.int64)
    out_of_range = pix.size and (
        pix.min() < 0 or pix.max() >= n_pix or cell.min() < 0 or cell.max() >= n_cells
    )
    if out_of_range:
        raise InputError(
            f"pixel_index must be in [0, {n_pix}) and cell_index in [0, {n_cells}); got pixel "
            f"{pix.min()}..{pix.max()}, cell {cell.min()}..{cell.max()}"
        )
    if weights is None:
        wt = np.ones_like(y)
    else:
        wt = np.asarray(weights, dtype=np.float64).ravel()
        if wt.size != y.size:
            raise InputError(
                f"weights must have one value per observation, got {wt.size} for {y.size}"
            )
    if int(min_count) < 1:
        raise InputError(f"min_count must be at least 1, got {min_count}")
    view = None if view_index is None else _checked_views(view_index, y.size)
    with np.errstate(invalid="ignore"):
        good = np.isfinite(y) & (y > 0) & np.isfinite(wt) & (wt > 0)
    return pix[good], cell[good], y[good], wt[good], None if view is None else view[good]


def _checked_views(view_index: np.ndarray, n_obs: int) -> np.ndarray:
    """``view_index`` of :func:`fit_vignetting` as int64, checked."""
    view = np.asarray(view_index).ravel()
    if view.size != n_obs or (view.size and not np.issubdtype(view.dtype, np.integer)):
        raise InputError(
            f"view_index must be one integer per observation, got {view.size} {view.dtype} "
            f"values for {n_obs}"
        )
    if view.size and view.min() < 0:
        raise InputError(f"view_index must be non-negative, got {view.min()}")
    return view.astype(np.int64)


def _gauge(
    v_img: np.ndarray, count: np.ndarray, observed: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Step 4 of :func:`fit_vignetting`.

    The scale that sets the ``ROBUST_MAX_PERCENTILE`` of a denoised V (radial model + residual
    smoothed over ``_GAUGE_SIGMA`` px, so per-pixel noise does not push the percentile up) to 1.
    Returns ``(scale, V, model, V - model)``, the last three divided by the scale (the residual
    0 where not observed).
    """
    cert = observed.astype(np.float64)
    model = _radial_model(v_img, count.astype(np.float64), observed)
    resid_img = np.where(observed, v_img - model, 0.0)
    num, den = _normalised_blur(resid_img, cert * count, _GAUGE_SIGMA)
    with np.errstate(invalid="ignore", divide="ignore"):
        denoised = model + num / den
    scale = float(np.percentile(denoised[observed], ROBUST_MAX_PERCENTILE))
    if not np.isfinite(scale) or scale <= 0:
        raise FitError("the fitted vignetting is not positive: the reflector data are inconsistent")
    return scale, v_img / scale, model / scale, resid_img / scale


def _smooth_and_fill(
    v_img: np.ndarray, model: np.ndarray, resid_img: np.ndarray, count: np.ndarray,
    observed: np.ndarray, smooth_sigma: float, noise_rel: np.ndarray | None = None,
) -> np.ndarray:
    """Smooth and fill V: steps 5 and 6 of :func:`fit_vignetting`.

    The optional smoothing of the residual over the observed pixels, and the fill (radial model
    plus nearby residual) of the others; without smoothing, with ``noise_rel`` (each pixel's
    relative noise variance), the detail shrunk by its signal-to-noise ratio.
    """
    cert = observed.astype(np.float64)
    out = v_img.copy()
    smoothing = bool(smooth_sigma) and float(smooth_sigma) > 0
    if smoothing or noise_rel is not None:
        num, den = _normalised_blur(resid_img, cert * count, float(smooth_sigma) if smoothing else _GAUGE_SIGMA)
        with np.errstate(invalid="ignore", divide="ignore"):
            part = num / den
        smoothed = model + part
        if not smoothing:
            detail, _ = shrink_detail(np.where(observed, resid_img - part, np.nan), noise_rel * v_img * v_img, observed)
            smoothed = smoothed + detail
        out = np.where(observed, smoothed, out)
    num, den = _normalised_blur(resid_img, cert, _FILL_SIGMA)
    fill = model + num / np.maximum(den, _FILL_CERTAINTY)
    # filled values stay within (half the smallest observed V, 1]: a radial polynomial
    # extrapolated far into a never-seen corner must not go to 0 or negative
    low = 0.5 * float(np.min(out[observed]))
    return np.where(observed, np.minimum(out, 1.0), np.clip(fill, low, 1.0))


def _cell_radiance(
    v: np.ndarray, pix: np.ndarray, cell: np.ndarray, y: np.ndarray, wt: np.ndarray, n_cells: int
) -> np.ndarray:
    """Eq. 10' radiance of every observed cell (also cells seen by one pixel only) for the final V.

    NaN for cells never seen.
    """
    vv = v.ravel()[pix]
    num_l = np.bincount(cell, weights=wt * y * vv, minlength=n_cells)
    den_l = np.bincount(cell, weights=wt * vv * vv, minlength=n_cells)
    radiance = np.full(n_cells, np.nan)
    seen = den_l > 0
    radiance[seen] = num_l[seen] / den_l[seen]
    return radiance


def view_inconsistency(
    fit: VignettingFit, pixel_index: np.ndarray, cell_index: np.ndarray, values: np.ndarray, tol: float = 0.1
) -> float:
    """Return the fraction of one view's observations the fitted model misses.

    Parameters
    ----------
    fit : VignettingFit
        The band's fit.
    pixel_index, cell_index, values : numpy.ndarray
        One view's observations (:func:`view_observations`).
    tol : float
        Relative miss counted as inconsistent.

    Returns
    -------
    float
        Fraction of the comparable observations with ``|y / (V(x) L(p)) - 1| > tol`` (Eq. 8
        model ``y = V(x) L(p)``); NaN when nothing is comparable. Observations in cells the fit
        never saw are ignored.

    Notes
    -----
    A good view scatters by its noise only (about 1 %); a view whose marker pose is wrong (e.g.
    the wrong one of the two planar-pose solutions) maps lawn or the marker's paper onto
    reflector cells and misses by tens of percent on a large part of its pixels.
    """
    v = fit.vignetting.ravel()[pixel_index]
    lp = fit.radiance[cell_index]
    ok = np.isfinite(lp) & (lp > 0) & (v > 0) & np.isfinite(values)
    if not ok.any():
        return float("nan")
    rel = values[ok] / (v[ok] * lp[ok]) - 1.0
    return float(np.mean(np.abs(rel) > tol))


def inconsistent_views(fractions: np.ndarray, floor: float = 0.05, factor: float = 5.0) -> np.ndarray:
    """Find the views to drop before the per-band fits.

    Parameters
    ----------
    fractions : numpy.ndarray
        :func:`view_inconsistency` of every view (NaN allowed).
    floor : float
        Fractions up to this are always kept.
    factor : float
        Multiple of the median fraction over views above which a view is dropped.

    Returns
    -------
    numpy.ndarray
        int64 indices of the views whose fraction is above ``max(floor, factor x the median
        over views)``.
    """
    f = np.asarray(fractions, dtype=np.float64)
    finite = f[np.isfinite(f)]
    if finite.size == 0:
        return np.array([], dtype=np.int64)
    limit = max(floor, factor * float(np.median(finite)))
    return np.nonzero(np.isfinite(f) & (f > limit))[0]
