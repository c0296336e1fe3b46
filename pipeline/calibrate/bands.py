"""Per-band work of the calibration, run on the workers of :class:`pipeline.calibrate.pool.BandPool`.

The response (Eq. 5-7) and vignetting (Eq. 8-10) fits of one band do not depend on the other
bands. Each task gets its band's frames (views of the stack, pickled when it is sent, a few
at a time; of the vignetting views only the box of pixels that can see the reflector) and
returns the fit. The numbers are the same whichever process fits a band: the
worker runs exactly the code the main process would (``tests/pipeline/calibrate/test_bands.py``
checks 1 worker against 2).

Only this module and ``mscal_core`` are imported here: a worker imports nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from mscal_core import geometry, response, vignetting

# --------------------------------------------------------------------------- response (Eq. 5-7)


def response_band(dn: np.ndarray, exposures: np.ndarray, bit_depth: int,
                  method: str) -> tuple[list[int], response.ResponseFit | None]:
    """One band's sweep ``dn (frame, H, W)``: the frames whose brightness contradicts their
    exposure (then no fit), else the Eq. 5-7 fit."""
    flat = dn.reshape(dn.shape[0], -1)
    bad = response.check_exposure_consistency(flat, exposures, bit_depth)
    if bad:
        return list(bad), None
    return [], response.fit_response(flat, exposures, bit_depth, method=method)


# --------------------------------------------------------------------------- vignetting (Eq. 8-10)


@dataclass(frozen=True)
class BandViews:
    """One band's vignetting views: per view, the band's DN in the box of pixels that can see
    the reflector (``dn``: views of the stack, pickled only when the task is sent) and that box
    (``windows``: :func:`mscal_core.geometry.reflector_window`, found by the main process, which
    projects the reflector once per view for every band), its exposure time and marker pose;
    the band's shape, U table, saturation and intrinsics, its offset on the band grid
    ``(dx, dy)`` and the reflector geometry (size, excluded centre, edge margin, cell grid);
    ``robust``: the robust loss of the fit (``robust`` of :func:`mscal_core.vignetting.fit_vignetting`)."""

    dn: tuple[np.ndarray, ...]
    windows: tuple[tuple[slice, slice], ...]
    shape: tuple[int, int]
    exposures: tuple[float, ...]
    poses: tuple[geometry.Pose, ...]
    inverse_response: np.ndarray
    saturation_dn: int
    intrinsics: geometry.Intrinsics
    offset: tuple[float, float]
    size_m: tuple[float, float]
    exclude_half_m: float
    edge_margin_m: float
    grid: tuple[int, int]
    robust: str | None = None


Observations = tuple[np.ndarray, np.ndarray, np.ndarray]


def energy(dn: np.ndarray, inverse_response: np.ndarray, t: float, saturation_dn: int) -> np.ndarray:
    """``U(I) / t`` for one band, NaN where saturated (Eq. 4)."""
    e = (inverse_response[dn] / t).astype(np.float32)
    e[dn >= saturation_dn] = np.nan
    return e


def band_observations(bv: BandViews) -> tuple[list[Observations], float]:
    """Eq. 8-10 observations of every view of one band, and the saturated fraction of its
    reflector pixels (QA report)."""
    width = bv.shape[1]
    rays = geometry.pixel_rays(bv.intrinsics, bv.shape, bv.offset)
    obs = []
    n_sat = n_pix = 0
    for k, pose in enumerate(bv.poses):
        # only the box of pixels that can see the reflector: the same observations, in the
        # same order, as the whole band (geometry.reflector_window)
        rows, cols = bv.windows[k]
        dn = bv.dn[k]
        e = energy(dn, bv.inverse_response, bv.exposures[k], bv.saturation_dn)
        uv = geometry.pixels_to_plane(pose, bv.intrinsics, dn.shape, rays=rays[rows, cols])
        mask = geometry.reflector_mask(uv, bv.size_m, bv.exclude_half_m, bv.edge_margin_m)
        n_sat += int(np.count_nonzero(dn[mask] >= bv.saturation_dn))
        n_pix += int(np.count_nonzero(mask))
        pix, cell, val = vignetting.view_observations(e, uv, mask, bv.size_m, grid=bv.grid)
        sub_w = dn.shape[1]
        obs.append(((pix // sub_w + rows.start) * width + pix % sub_w + cols.start, cell, val))
    return obs, n_sat / max(n_pix, 1)


def fit_observations(obs: Sequence[Observations], shape: tuple[int, int], n_cells: int,
                     start: np.ndarray | None = None, robust: str | None = None) -> vignetting.VignettingFit:
    """:func:`mscal_core.vignetting.fit_vignetting` of the views' observations together
    (``start``: V of an earlier fit of the band to start from; ``robust``: its robust loss, the
    fit's ``view_weights`` then in the order of ``obs``)."""
    views = np.repeat(np.arange(len(obs)), [o[0].size for o in obs])
    return vignetting.fit_vignetting(*(np.concatenate([o[k] for o in obs]) for k in range(3)), shape, n_cells,
                                     start=start, robust=robust, view_index=views)


def view_coverage(obs: Sequence[Observations], shape: tuple[int, int]) -> np.ndarray:
    """How many of the views observed each pixel: ``(H, W)`` uint16 (saturating at 65535).

    A view observes a pixel when the pixel sees the reflector (inside its mask: off the marker
    and the edge margin) unsaturated, i.e. gives V an observation there
    (:func:`mscal_core.vignetting.view_observations`, one per pixel and view); 0 where no view
    did (V is extrapolated there)."""
    n_pix = int(shape[0]) * int(shape[1])
    count = np.zeros(n_pix, dtype=np.int64)
    for pix, _, _ in obs:  # one view at a time: no temporary the size of all observations
        count += np.bincount(pix, minlength=n_pix)
    return np.minimum(count, 65535).astype(np.uint16).reshape(shape)


def vignetting_band(bv: BandViews, screen: bool = False, start: np.ndarray | None = None
                    ) -> tuple[vignetting.VignettingFit, float, np.ndarray | None, np.ndarray]:
    """Eq. 8-10 of one band: the fit, the saturated fraction, with ``screen`` each view's
    :func:`mscal_core.vignetting.view_inconsistency` with that fit (else None), and the
    views' :func:`view_coverage`. ``start``: V of an earlier fit of the band (on more views)
    to start from."""
    obs, saturated = band_observations(bv)
    fit = fit_observations(obs, bv.shape, bv.grid[0] * bv.grid[1], start, bv.robust)
    frac = np.array([vignetting.view_inconsistency(fit, *o) for o in obs]) if screen else None
    return fit, saturated, frac, view_coverage(obs, bv.shape)


def lens_vignetting_band(bv: BandViews, min_views_to_screen: int
                         ) -> tuple[vignetting.VignettingFit, float, np.ndarray, list[int], np.ndarray]:
    """Eq. 8-10 of one lens of a multi-lens camera on its own views, screened on its own fit:
    views that disagree with it (:func:`mscal_core.vignetting.inconsistent_views`) are dropped
    and the lens fitted again when at least ``min_views_to_screen`` remain. Returns the fit,
    the saturated fraction (of all its views), each view's inconsistency, the views dropped
    and the :func:`view_coverage` of the views kept."""
    obs, saturated = band_observations(bv)
    shape, n_cells = bv.shape, bv.grid[0] * bv.grid[1]
    fit = fit_observations(obs, shape, n_cells, robust=bv.robust)
    frac = np.array([vignetting.view_inconsistency(fit, *o) for o in obs])
    bad = sorted(set(vignetting.inconsistent_views(frac).tolist()))
    if not bad or len(obs) - len(bad) < min_views_to_screen:
        return fit, saturated, frac, [], view_coverage(obs, shape)
    kept = [o for k, o in enumerate(obs) if k not in bad]
    return (fit_observations(kept, shape, n_cells, fit.vignetting, bv.robust), saturated, frac, bad,
            view_coverage(kept, shape))
