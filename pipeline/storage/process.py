"""Settings of a process that runs mscal's per-frame or per-band work (the apply executor's
and the calibration's worker pools, and the main process itself): one copy for both.

``die_with_parent``: a worker killed with its parent leaves no writer behind.
``reuse_freed_memory``: the large arrays freed by one frame or band are reused by the next
instead of being handed back to the kernel and zeroed again on the next touch.
"""

from __future__ import annotations

import signal

#: glibc ``mallopt`` parameters: ``M_TRIM_THRESHOLD``, ``M_MMAP_THRESHOLD``.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: ``prctl`` option ``PR_SET_PDEATHSIG`` (linux/prctl.h).
_PR_SET_PDEATHSIG = 1


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
    the outputs are the same."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024)
        libc.mallopt(_M_TRIM_THRESHOLD, 256 * 1024 * 1024)
    except (OSError, AttributeError):  # not glibc
        pass


__all__ = ["die_with_parent", "reuse_freed_memory"]
