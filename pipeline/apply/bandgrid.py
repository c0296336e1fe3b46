"""A capture's bands on one pixel grid, and the check of it on the pixels.

:func:`one_grid` puts a capture's bands (stored orientation) on one grid: each band file's own
registration (DJI's DewarpData and CalibratedHMatrix, ``Plan.factory_alignment``), then the
image registration that refines it (``Plan.refine``: per band a transform from the reference
band, judged and estimated on each capture's own pixels, the flight's for a capture without
texture: :func:`pipeline.apply.coregistration.capture_transform`), then the band
transforms of a registration store or ``--centre-bands``
(:func:`pipeline.apply.stores.geometry_step`).

:func:`grid_residuals` measures, on a sampled capture's pixels, the shift of each band against
the reference band left after that grid and without it
(:func:`mscal_core.coregistration.stack_residuals`): run.json ``coregistration``.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from mscal_core.alignment import align_bands
from mscal_core.coregistration import stack_residuals

from pipeline.apply.coregistration import capture_transform
from pipeline.apply.stores import geometry_step
from pipeline.ingest.cameras.dispatch import align_by_files

if TYPE_CHECKING:
    from pipeline.apply.executor import Job, Plan


def one_grid(plan: Plan, job: Job, signal: np.ndarray
             ) -> tuple[np.ndarray, dict[str, Any] | None, Callable[[np.ndarray], np.ndarray] | None]:
    """A capture's bands (stored orientation) on one pixel grid (see the module docstring),
    unchanged when the plan has none of the steps; with ``plan.refine`` the capture's own
    alignment and where it came from (run.json ``coregistration.per_capture``), else None; and
    the warp applied, as a function of a stack on the capture's stored grid (None: no step
    moved it): the same steps with the same transforms, the capture's own image registration
    included, so that its quality mask follows its pixels exactly
    (:func:`pipeline.apply.quality.on_grid`)."""
    own = None
    steps: list[Callable[[np.ndarray], np.ndarray]] = []
    metas = job.capture.metas if job.capture is not None else None
    if plan.refine is not None and job.capture is not None:
        aligned = align_by_files(metas, signal) if plan.factory_alignment else signal
        on_meta, h, own = capture_transform(signal, aligned, plan.refine)
        base = aligned if on_meta else signal
        signal = base if h is None else align_bands(base, h)
        if on_meta and plan.factory_alignment:
            steps.append(lambda s: align_by_files(metas, s))
        if h is not None:
            steps.append(lambda s: align_bands(s, h))
    elif plan.factory_alignment and job.capture is not None:
        signal = align_by_files(metas, signal)
        steps.append(lambda s: align_by_files(metas, s))
    if plan.transforms is not None or plan.band_shift is not None:
        def geometry(s: np.ndarray) -> np.ndarray:
            return geometry_step(plan.transforms or Path(), plan.transforms is not None, plan.band_shift, job.name, s)

        signal = geometry(signal)
        steps.append(geometry)
    if not steps:
        return signal, own, None

    def warp(stack: np.ndarray) -> np.ndarray:
        for step in steps:
            stack = step(stack)
        return stack

    return signal, own, warp


def grid_and_residuals(plan: Plan, job: Job, signal: np.ndarray
                       ) -> tuple[np.ndarray, dict[str, Any] | None, Callable[[np.ndarray], np.ndarray] | None]:
    """:func:`one_grid`, the capture's entry of run.json ``coregistration`` (its residuals when
    measured, :func:`grid_residuals`; its own alignment under ``refinement``), or None, and the
    warp :func:`one_grid` applied (for the quality mask)."""
    after, own, warp = one_grid(plan, job, signal)
    residuals = grid_residuals(plan, job, signal, after)
    if own is not None:
        residuals = {**(residuals or {}), "refinement": own}
    return after, residuals, warp


def grid_residuals(plan: Plan, job: Job, before: np.ndarray, after: np.ndarray) -> dict[str, Any] | None:
    """For a capture the run measures (``job.measure``, reference band ``plan.coreg_reference``):
    per band the median residual shift (px) against the reference band and the tiles used, on
    the bands as written (``after``) and, when a step moved them, as stored (``before``).
    None for the other captures."""
    if not job.measure or plan.coreg_reference is None:
        return None
    names = [b.name for b in plan.camera.bands][: after.shape[0]]
    res = stack_residuals(after, plan.coreg_reference)
    out: dict[str, Any] = {"residual_px": {n: _px(r.median_px) for n, r in zip(names, res)},
                           "tiles": {n: r.n_tiles for n, r in zip(names, res)}}
    if before is not after:
        out["unaligned_px"] = {n: _px(r.median_px) for n, r in zip(names, stack_residuals(before, plan.coreg_reference))}
    return out


def _px(v: float) -> float | None:
    return round(float(v), 3) if np.isfinite(v) else None
