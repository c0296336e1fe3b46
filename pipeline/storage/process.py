"""Settings of a process that runs mscal's per-frame or per-band work (the apply executor's
and the calibration's worker pools, and the main process itself): one copy for both.

``start_pool``: a pool of worker processes, started now, or :class:`ProcessesUnavailable`
where the system cannot run one; ``environment``: variables set for a block (what a process
started in it inherits), restored after.
``die_with_parent``: a worker killed with its parent leaves no writer behind.
``reuse_freed_memory``: the large arrays freed by one frame or band are reused by the next
instead of being handed back to the kernel and zeroed again on the next touch, and new
arrays are touched in small pages (``small_pages``).
"""

from __future__ import annotations

import contextlib
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.context import BaseContext
from typing import Any, Callable, ContextManager, Iterator, Mapping

from mscal_core.errors import ProcessesUnavailable

#: glibc ``mallopt`` parameters: ``M_TRIM_THRESHOLD``, ``M_MMAP_THRESHOLD``.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: ``prctl`` options ``PR_SET_PDEATHSIG``, ``PR_SET_THP_DISABLE`` (linux/prctl.h).
_PR_SET_PDEATHSIG, _PR_SET_THP_DISABLE = 1, 41


#: What making or starting a process pool raises on a system that cannot run one: ``OSError``
#: from ``sem_open`` (AWS Lambda: ENOSYS; a sandbox: EACCES), from a fork (EAGAIN, ENOMEM) or
#: from the forkserver's socket; ``NotImplementedError`` or ``ImportError`` where Python has
#: no semaphores at all (``concurrent.futures`` checks for them).
POOL_ERRORS = (OSError, NotImplementedError, ImportError)


def start_pool(workers: int, context: Callable[[], BaseContext], initializer: Callable[..., Any],
               initargs: tuple = (), starting: Callable[[], ContextManager[Any]] = contextlib.nullcontext
               ) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes of the multiprocessing ``context()`` (called here: a
    forkserver starts in it), each started now, inside ``starting()``.

    Raises :class:`ProcessesUnavailable` (saying why) when the system cannot run them, with
    nothing left running; the caller decides whether to run on threads or in its own process
    instead, or to stop, and gives its own users' fix."""
    pool = None
    try:
        pool = ProcessPoolExecutor(workers, mp_context=context(), initializer=initializer, initargs=initargs)
        with starting():
            for _ in range(workers):
                pool.submit(int)
        return pool
    except POOL_ERRORS as exc:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        raise ProcessesUnavailable(
            f"worker processes cannot start on this system ({type(exc).__name__}: {exc})") from exc


@contextlib.contextmanager
def environment(values: Mapping[str, str]) -> Iterator[None]:
    """``values`` set in ``os.environ`` for the block (a process started in it inherits them),
    each variable restored after: to its earlier value, or removed if it had none."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def stop_process_servers() -> None:
    """End the helper processes multiprocessing started for this process's pools -- the
    forkserver (the apply executor's worker server) and the resource tracker -- and wait for
    them, so that a command leaves no process of its own behind when it returns (they would
    otherwise see this process's end only when it exits, up to a second later). The pools
    must be shut down first; a later pool starts them again. Objects of a shut-down pool that
    still hold semaphores are collected first (:mod:`gc`), so that the tracker has none left
    to clean up."""
    import gc
    from multiprocessing import forkserver, resource_tracker

    server = forkserver._forkserver  # multiprocessing has no public stop
    if getattr(server, "_forkserver_pid", None) is not None:
        with contextlib.suppress(ChildProcessError):  # already reaped (a SIGCHLD handler)
            server._stop()
    tracker = resource_tracker._resource_tracker
    if getattr(tracker, "_pid", None) is not None:
        gc.collect()  # a pool's queues and locks: their semaphores unregistered now, not at exit
        with contextlib.suppress(ChildProcessError):
            tracker._stop()


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; elsewhere nothing)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux
        pass


def reuse_freed_memory() -> None:
    """Keep the memory of one frame's (or band's) arrays for the next (glibc only; elsewhere
    nothing).

    Each frame allocates and frees the same large arrays (the bands' bytes, DN, float64 work
    arrays, radiance and reflectance cubes, a band's stack of views: up to 25 MB each). glibc
    serves such arrays with a fresh ``mmap`` and unmaps them when freed, so every frame
    touches new pages, and the kernel zeroes each of them on a page fault: a tenth of the
    apply pass's CPU and 3.4 of calibrate's 35 s (1.15 million minor faults), as system time.
    With ``M_MMAP_THRESHOLD`` at glibc's maximum (32 MB) they come from the heap and are
    reused, and ``M_TRIM_THRESHOLD`` keeps up to 256 MB freed at the heap's top instead of
    handing it back. The peak memory is about the same (one frame's working set per worker);
    the outputs are the same. New arrays are touched in small pages (:func:`small_pages`)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024)
        libc.mallopt(_M_TRIM_THRESHOLD, 256 * 1024 * 1024)
    except (OSError, AttributeError):  # not glibc
        pass
    small_pages()


#: NumPy's own switch for huge pages, read when numpy is imported: when it is set, numpy's
#: choice stands and :func:`small_pages` does nothing.
NUMPY_HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"


def small_pages() -> None:
    """Keep this process's new large arrays in small pages, and those of the processes it
    starts after: no transparent huge pages (Linux; elsewhere nothing), unless
    ``NUMPY_MADVISE_HUGEPAGE`` is set.

    NumPy asks the kernel (``madvise``) for 2 MB pages for every array of 4 MB or more, so
    the first touch of such an array zeroes 2 MB per page fault. On a virtual machine whose
    idle memory goes back to the host (Firecracker, ballooned or free-page-reporting clouds:
    this project's CI machine) such a fault is slow: measured there, touching 540 MB of new
    arrays took 2.0-3.1 s of system time with huge pages and 0.41-0.49 s without, and
    ``mscal calibrate`` on the full synthetic session 4.1-5.4 s of system time against
    1.3-1.8 s (wall 13.3-16.1 s against 11.2-13.1 s, runs interleaved). On a machine whose
    memory is all its own the two differ by hundredths of a second; huge pages would still
    save TLB misses, which mscal's band-sized arrays hardly have. Set
    ``NUMPY_MADVISE_HUGEPAGE=1`` to keep NumPy's default.

    How: Linux's ``prctl(PR_SET_THP_DISABLE)``, which a forked child inherits and ``execve``
    keeps. ``NUMPY_MADVISE_HUGEPAGE=0`` alone would not do: NumPy reads it only when it is
    imported, and the processes this runs in (mscal's main process, the calibration's forked
    workers) imported numpy before; NumPy has no public setter after import. With the
    kernel's default mode (``madvise``: huge pages only where a program asks for them) the
    two are the same: numpy's large arrays in small pages (measured: 512 MB of new arrays,
    no huge page and the same page faults either way); in mode ``always`` the rest of the
    process's memory stays in small pages too.
    """
    if os.environ.get(NUMPY_HUGEPAGE_ENV) is not None:
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_THP_DISABLE, 1, 0, 0, 0)  # -1 on a kernel < 3.15
    except (OSError, AttributeError):  # not Linux
        pass


__all__ = ["NUMPY_HUGEPAGE_ENV", "POOL_ERRORS", "die_with_parent", "environment", "reuse_freed_memory", "small_pages",
           "start_pool", "stop_process_servers"]
