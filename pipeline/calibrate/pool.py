"""The worker processes of the per-band calibration fits.

The response (Eq. 5-7) and vignetting (Eq. 8-10) fits of one band do not depend on the other
bands (:mod:`pipeline.calibrate.bands`). Run on threads they did not get faster on 2 cores
(measured: response 6.8 s with one thread, 6.9 s with two; vignetting 9.9 s and 10.9 s): the
fits are many short numpy calls and ``np.bincount`` steps that hold the GIL.
:class:`BandPool` runs them on worker processes instead.

Workers are children of the main process, joined when the pool closes, so their CPU time
counts in the main process's ``RUSAGE_CHILDREN`` and in ``os.wait4`` of whoever started
``mscal`` (the benchmarks); not a forkserver's (its workers are its children, and it is never
waited for: their CPU time would vanish from every measurement). They are forked when this
process has a single thread (``mscal calibrate``: :func:`session_pool` imports the fits'
module first, so a forked worker starts with it imported and costs nothing), and spawned
otherwise (a fork copies only the calling thread, and a lock another thread held would stay
held in the child: a Prefect worker, a notebook). A spawned worker imports
:mod:`pipeline.calibrate.bands` (numpy, OpenCV, scipy, ``mscal_core``: about 1 s of CPU each)
as soon as the pool is made. Workers run single-threaded BLAS and OpenCV (the workers fill
the cores).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing
import os
import sys
import threading
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Callable, Iterator, Sequence

from mscal_core.errors import ProcessesUnavailable
from threadpoolctl import threadpool_limits

from pipeline.storage.process import die_with_parent, environment, reuse_freed_memory, start_pool

log = logging.getLogger(__name__)

#: What a worker imports when it starts: the module of the per-band fits.
FITS_MODULE = "pipeline.calibrate.bands"


#: Environment variable, the default of ``workers`` (:func:`band_workers`): worker processes
#: for the per-band fits (0 or unset: one per core; 1: none, every band in the main process).
#: docs/configuration.md lists it.
WORKERS_ENV = "MSCAL_CALIBRATE_WORKERS"


def band_workers(n_tasks: int, workers: int | None = None) -> int:
    """Worker processes for ``n_tasks`` band fits: ``workers`` if > 0; when None, the
    ``MSCAL_CALIBRATE_WORKERS`` environment variable if set (> 0); else (0, or an unset or
    unreadable variable) the cores this process may run on; never more than the tasks."""
    if workers is None:
        raw = os.environ.get(WORKERS_ENV, "").strip()
        try:
            workers = int(raw) if raw else 0
        except ValueError:
            workers = 0
    asked = workers
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
    freed memory (a band's stacks are allocated again for every band), runs BLAS and OpenCV
    on one thread (a forked worker inherits the parent's BLAS, loaded before the environment
    said so) and imports the fits' module now, not when its first band arrives."""
    die_with_parent()
    reuse_freed_memory()
    import cv2

    cv2.setNumThreads(1)
    threadpool_limits(limits=1, user_api="blas")
    importlib.import_module(FITS_MODULE)


@contextlib.contextmanager
def _opencv_pool_stopped() -> Iterator[None]:
    """OpenCV's worker threads stopped for the time of the block (``cv2.setNumThreads(1)``, its
    setting restored after). Forked while they run, a child that calls ``cv2.setNumThreads``
    waits forever in ``pthread_cond_destroy`` for waiters that were not copied into it: a
    second calibration in one process (a notebook, ``bench_accuracy.py``) hung so."""
    cv2 = sys.modules.get("cv2")  # not imported: its threads cannot have started
    if cv2 is None:
        yield
        return
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


@contextlib.contextmanager
def _starting_workers(method: str) -> Iterator[None]:
    """While the workers start: one BLAS/OpenMP thread each (:data:`_WORKER_ENV`, where this
    process does not set its own), and for forked workers OpenCV's threads stopped."""
    with environment({k: v for k, v in _WORKER_ENV.items() if k not in os.environ}), \
            _opencv_pool_stopped() if method == "fork" else contextlib.nullcontext():
        yield


def start_method() -> str:
    """``"fork"`` when this process has one thread (on Linux), else ``"spawn"``."""
    if sys.platform.startswith("linux") and threading.active_count() == 1:
        return "fork"
    return "spawn"


class BandPool:
    """Runs per-band fits on worker processes (in the main process with one worker).

    Use as a context manager; the workers start when the pool is made, so they start while
    the main process reads the frames."""

    def __init__(self, workers: int | None = None, method: str | None = None):
        """``workers`` (default: :func:`band_workers`'s, ``MSCAL_CALIBRATE_WORKERS`` or one per
        core); ``method``: the start method of the workers
        (default :func:`start_method`; ``"fork"`` from a process with other threads can leave a
        worker waiting forever on a lock one of them held: a pytest-xdist worker did)."""
        self.workers = band_workers(64) if workers is None else max(1, int(workers))
        self._pool: ProcessPoolExecutor | None = None
        reuse_freed_memory()  # this process reads every stack; with one worker it fits them too
        if self.workers >= 2:
            method = method or start_method()
            try:
                # started now (a worker copies the environment); a fork pool forks every
                # worker in the first submit
                self._pool = start_pool(self.workers, lambda: multiprocessing.get_context(method), _worker_init,
                                        starting=lambda: _starting_workers(method))
            except ProcessesUnavailable as exc:  # the same fits in this process, only slower
                log.warning("%s: fitting the bands in this process instead", exc.reason)
                self.workers = 1

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """``fn(*args)`` on a worker (or now, in this process, without workers)."""
        if self._pool is None:
            fut: Future = Future()
            try:
                # one BLAS thread, as in a worker: a threaded BLAS sums a matrix product in
                # another order, and the store would differ in its last bits with the workers
                with threadpool_limits(limits=1, user_api="blas"):
                    fut.set_result(fn(*args))
            except BaseException as exc:  # handed to the caller by .result()
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


def session_pool(session_dir: str | os.PathLike[str], workers: int | None = None) -> BandPool:
    """A :class:`BandPool` for a session folder's camera (``workers``, default
    :func:`band_workers`'s: ``MSCAL_CALIBRATE_WORKERS`` or a worker per core; at most one per
    band), started now, with the fits' module imported first (a forked worker then has it):
    ``mscal calibrate`` makes it before it imports the rest of the calibration. Raises what
    :func:`pipeline.ingest.session.load_session` raises for a bad session folder."""
    from pipeline.ingest.session import load_session

    n_bands = load_session(session_dir).camera.n_bands
    importlib.import_module(FITS_MODULE)
    return BandPool(band_workers(n_bands, workers))


@contextlib.contextmanager
def pool_or_own(pool: BandPool | None, n_tasks: int, workers: int | None = None) -> Iterator[BandPool]:
    """``pool``, or a pool of its own for ``n_tasks`` band fits (``workers``:
    :func:`band_workers`), closed on leaving."""
    if pool is not None:
        yield pool
        return
    with BandPool(band_workers(n_tasks, workers)) as own:
        yield own
