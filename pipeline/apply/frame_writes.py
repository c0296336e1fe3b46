"""A frame's file writes on writer threads while the frame goes on computing
(:class:`FrameWrites`; used by :func:`pipeline.apply.executor.process_frames`)."""
from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

_writer_of_thread = threading.local()

#: Writer threads of each computing thread (:class:`FrameWrites`). A frame hands over 15 files
#: (its chunks and, encoded on the computing thread, its 9 TIFFs); each direct write waits for
#: the device. One writer thread became the bottleneck once the TIFFs went to it; two kept
#: both cores busier: 600 full-resolution frames, 3 alternating runs each, median wall 16.7 s
#: against 17.9 s with the TIFFs written on the computing thread (docs/benchmarks.md).
WRITER_THREADS = 2


def _writer() -> ThreadPoolExecutor:
    """This thread's writer threads (made on first use, kept: their direct-I/O buffers are reused)."""
    ex = getattr(_writer_of_thread, "executor", None)
    if ex is None:
        ex = _writer_of_thread.executor = ThreadPoolExecutor(WRITER_THREADS, thread_name_prefix="mscal-writer")
    return ex


class FrameWrites:
    """A frame's file writes (chunks and TIFFs) on writer threads, while the frame goes on
    computing.

    A frame's outputs are made one after the other (reflectance, then the indices, then the
    TIFFs from them); each file write waits for the device (direct I/O), and the computing
    of the next product need not wait with it. Only arrays that nothing changes afterwards
    are handed over. :meth:`wait` returns once every write is on disk (the frame is reported
    done only then, as before) and raises the first write's error. ``nbytes``: the bytes of
    the arrays and parts handed over (what the frame holds in memory until written).
    """

    def __init__(self) -> None:
        self._pending: list[Future] = []
        self.nbytes = 0

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        self.nbytes += sum(_held_bytes(a) for a in args)
        self._pending.append(_writer().submit(fn, *args))

    def wait(self, raise_errors: bool = True) -> None:
        pending, self._pending = self._pending, []
        errors = [exc for f in pending if (exc := f.exception()) is not None]
        if errors and raise_errors:
            raise errors[0]


def _held_bytes(arg: Any) -> int:
    """Bytes of an array, a bytes-like object or a list of them (a TIFF's parts); 0 for others."""
    if isinstance(arg, np.ndarray):
        return int(arg.nbytes)
    if isinstance(arg, (bytes, bytearray, memoryview)):
        return memoryview(arg).nbytes
    if isinstance(arg, (list, tuple)):
        return sum(_held_bytes(a) for a in arg)
    return 0
