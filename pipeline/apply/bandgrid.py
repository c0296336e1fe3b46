"""A capture's bands on one pixel grid, and the check of it on the pixels.

:func:`one_grid` puts a capture's bands (stored orientation) on one grid: each band file's own
registration (DJI's DewarpData and CalibratedHMatrix, ``Plan.factory_alignment``), then the
image registration that refines it (``Plan.refine``: per band a transform from the reference
band, judged and estimated on each capture's own pixels, the flight's for a capture without
texture: :func:`pipeline.apply.coregistration.capture_alignment`), then the band
transforms of a registration store or ``--centre-bands``
(:func:`pipeline.apply.stores.geometry_step`).

:func:`grid_residuals` measures, on a sampled capture's pixels, the shift of each band against
the reference band left after that grid and without it
(:func:`mscal_core.coregistration.stack_residuals`): run.json ``coregistration``.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from mscal_core.coregistration import stack_residuals

from pipeline.apply.coregistration import capture_alignment
from pipeline.apply.stores import geometry_step
from pipeline.ingest.cameras.dispatch import align_by_files

if TYPE_CHECKING:
    from pipeline.apply.executor import Job, Plan


def one_grid(plan: Plan, job: Job, signal: np.ndarray) -> tuple[np.ndarray, dict[str, Any] | None]:
    """A capture's bands (stored orientation) on one pixel grid (see the module docstring);
    unchanged when the plan has none of the steps. With ``plan.refine`` the capture's own
    alignment and where it came from (run.json ``coregistration.per_capture``), else None."""
    own = None
    if plan.refine is not None and job.capture is not None:
        aligned = align_by_files(job.capture.metas, signal) if plan.factory_alignment else signal
        signal, own = capture_alignment(signal, aligned, plan.refine)
    elif plan.factory_alignment and job.capture is not None:
        signal = align_by_files(job.capture.metas, signal)
    if plan.transforms is not None or plan.band_shift is not None:
        signal = geometry_step(plan.transforms or Path(), plan.transforms is not None, plan.band_shift, job.name,
                               signal)
    return signal, own


def grid_and_residuals(plan: Plan, job: Job, signal: np.ndarray) -> tuple[np.ndarray, dict[str, Any] | None]:
    """:func:`one_grid`, and the capture's entry of run.json ``coregistration`` (its residuals
    when measured, :func:`grid_residuals`; its own alignment under ``refinement``), or None."""
    after, own = one_grid(plan, job, signal)
    residuals = grid_residuals(plan, job, signal, after)
    if own is not None:
        residuals = {**(residuals or {}), "refinement": own}
    return after, residuals


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
