"""Per-band work of the calibration, run on worker processes (issue 25).

The response (Eq. 5-7) and vignetting (Eq. 8-10) fits of one band do not depend on the other
bands. Run on threads they did not get faster on 2 cores (measured: response 6.8 s with one
thread, 6.9 s with two; vignetting 9.9 s and 10.9 s): the fits are many short numpy calls
and ``np.bincount`` steps that hold the GIL. :class:`BandPool` runs them on worker
processes instead. Each task gets its band's frames (a view of the stack, pickled when it is
sent, a few at a time) and returns the fit.

Workers are spawned (not forked from a forkserver): a spawned worker is a child of the main
process, joined when the pool closes, so its CPU time counts in the main process's
``RUSAGE_CHILDREN`` and in ``os.wait4`` of whoever started ``mscal`` (the benchmarks). A
forkserver's workers are its children, and the forkserver is never waited for: their CPU
time would vanish from every measurement. Spawning costs each worker the import of this
module (numpy, OpenCV, scipy, ``mscal_core``: about 0.5 s of CPU), made while the main
process reads the frames. Workers run single-threaded BLAS and OpenCV (the workers fill
the cores).

The numbers are the same whichever process fits a band: the worker runs exactly the code the
main process would (``tests/pipeline/calibrate/test_bands.py`` checks 1 worker against 2).

Only this module and ``mscal_core`` are imported here: a worker imports nothing else.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from mscal_core import geometry, response, vignetting

from pipeline.storage.process import die_with_parent, reuse_freed_memory

#: Environment variable: worker processes for the per-band fits (0 or unset: one per core;
#: 1: none, every band in the main process).
WORKERS_ENV = "MSCAL_CALIBRATE_WORKERS"


def band_workers(n_tasks: int) -> int:
    """Worker processes for ``n_tasks`` band fits: ``MSCAL_CALIBRATE_WORKERS`` if set (> 0),
    else the cores this process may run on; never more than the tasks."""
    raw = os.environ.get(WORKERS_ENV, "").strip()
    try:
        asked = int(raw) if raw else 0
    except ValueError:
        asked = 0
    if asked <= 0:
        try:
            asked = len(os.sched_getaffinity(0))
        except AttributeError:  # not Linux
            asked = os.cpu_count() or 1
    return max(1, min(asked, n_tasks))


#: Set for the workers when they start: one BLAS/OpenMP thread each.
_WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _worker_init() -> None:
    """A worker dies with the parent (a killed calibration leaves no process behind), reuses
    freed memory (a band's stacks are allocated again for every band) and runs OpenCV on one
    thread."""
    die_with_parent()
    reuse_freed_memory()
    import cv2

    cv2.setNumThreads(1)


class BandPool:
    """Runs per-band fits on worker processes (in the main process with one worker).

    Use as a context manager; the workers start when the pool is made, so they start while
    the main process reads the frames."""

    def __init__(self, workers: int | None = None):
        self.workers = band_workers(64) if workers is None else max(1, int(workers))
        self._pool: ProcessPoolExecutor | None = None
        reuse_freed_memory()  # this process reads every stack; with one worker it fits them too
        if self.workers >= 2:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_worker_init)
            saved = {k: os.environ.get(k) for k in _WORKER_ENV}
            os.environ.update({k: v for k, v in _WORKER_ENV.items() if saved[k] is None})
            try:
                for _ in range(self.workers):  # start them now (a spawned worker copies the environment)
                    self._pool.submit(int)
            finally:
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """``fn(*args)`` on a worker (or now, in this process, without workers)."""
        if self._pool is None:
            fut: Future = Future()
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller by .result()
                fut.set_exception(exc)
            return fut
        return self._pool.submit(fn, *args)

    def map(self, fn: Callable[..., Any], args: Sequence[tuple]) -> list[Any]:
        """``[fn(*a) for a in args]``, in order; the first error is raised."""
        return [f.result() for f in [self.submit(fn, *a) for a in args]]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> "BandPool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
    """One band's vignetting views: the band's DN of every frame ``(frame, H, W)`` (a view of
    the stack: pickled only when the task is sent), the frames used as views and, per view,
    its exposure time and marker pose; the band's U table, saturation and intrinsics, its
    offset on the band grid ``(dx, dy)`` and the reflector geometry (size, excluded centre,
    edge margin, cell grid)."""

    dn: np.ndarray
    frames: tuple[int, ...]
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

    def select(self, keep: Sequence[int]) -> "BandViews":
        """The same band with only views ``keep``."""
        from dataclasses import replace

        idx = list(keep)
        return replace(self, frames=tuple(self.frames[k] for k in idx),
                       exposures=tuple(self.exposures[k] for k in idx), poses=tuple(self.poses[k] for k in idx))


Observations = tuple[np.ndarray, np.ndarray, np.ndarray]


def energy(dn: np.ndarray, inverse_response: np.ndarray, t: float, saturation_dn: int) -> np.ndarray:
    """``U(I) / t`` for one band, NaN where saturated (Eq. 4)."""
    e = (inverse_response[dn] / t).astype(np.float32)
    e[dn >= saturation_dn] = np.nan
    return e


def band_observations(bv: BandViews) -> tuple[list[Observations], float]:
    """Eq. 8-10 observations of every view of one band, and the saturated fraction of its
    reflector pixels (QA report)."""
    shape = bv.dn.shape[1:]
    rays = geometry.pixel_rays(bv.intrinsics, shape, bv.offset)
    obs = []
    n_sat = n_pix = 0
    for k, pose in enumerate(bv.poses):
        dn = bv.dn[bv.frames[k]]
        e = energy(dn, bv.inverse_response, bv.exposures[k], bv.saturation_dn)
        uv = geometry.pixels_to_plane(pose, bv.intrinsics, shape, rays=rays)
        mask = geometry.reflector_mask(uv, bv.size_m, bv.exclude_half_m, bv.edge_margin_m)
        n_sat += int(np.count_nonzero(dn[mask] >= bv.saturation_dn))
        n_pix += int(np.count_nonzero(mask))
        obs.append(vignetting.view_observations(e, uv, mask, bv.size_m, grid=bv.grid))
    return obs, n_sat / max(n_pix, 1)


def fit_observations(obs: Sequence[Observations], shape: tuple[int, int], n_cells: int) -> vignetting.VignettingFit:
    """:func:`mscal_core.vignetting.fit_vignetting` of the views' observations together."""
    return vignetting.fit_vignetting(*(np.concatenate([o[k] for o in obs]) for k in range(3)), shape, n_cells)


def vignetting_band(bv: BandViews, screen: bool = False) -> tuple[vignetting.VignettingFit, float, np.ndarray | None]:
    """Eq. 8-10 of one band: the fit, the saturated fraction and, with ``screen``, each
    view's :func:`mscal_core.vignetting.view_inconsistency` with that fit."""
    obs, saturated = band_observations(bv)
    fit = fit_observations(obs, bv.dn.shape[1:], bv.grid[0] * bv.grid[1])
    frac = np.array([vignetting.view_inconsistency(fit, *o) for o in obs]) if screen else None
    return fit, saturated, frac


def lens_vignetting_band(bv: BandViews, min_views_to_screen: int) -> tuple[vignetting.VignettingFit, float, np.ndarray,
                                                                          list[int]]:
    """Eq. 8-10 of one lens of a multi-lens camera on its own views, screened on its own fit:
    views that disagree with it (:func:`mscal_core.vignetting.inconsistent_views`) are dropped
    and the lens fitted again when at least ``min_views_to_screen`` remain. Returns the fit,
    the saturated fraction (of all its views), each view's inconsistency and the views dropped."""
    obs, saturated = band_observations(bv)
    shape, n_cells = bv.dn.shape[1:], bv.grid[0] * bv.grid[1]
    fit = fit_observations(obs, shape, n_cells)
    frac = np.array([vignetting.view_inconsistency(fit, *o) for o in obs])
    bad = sorted(set(vignetting.inconsistent_views(frac).tolist()))
    if not bad or len(obs) - len(bad) < min_views_to_screen:
        return fit, saturated, frac, []
    return fit_observations([o for k, o in enumerate(obs) if k not in bad], shape, n_cells), saturated, frac, bad
