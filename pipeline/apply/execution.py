"""How an apply pass runs: scheduler, worker count, direct I/O (never what it computes).

These are the options ``--scheduler``, ``--workers`` and ``--direct-io/--no-direct-io`` of
``mscal apply`` and ``mscal run``, whose defaults come from ``MSCAL_APPLY_SCHEDULER``,
``MSCAL_APPLY_WORKERS`` and ``MSCAL_DIRECT_IO`` (read by the command line only). They change
neither the outputs nor the fingerprint that decides whether a run is up to date; run.json
records them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from mscal_core.errors import InputError

from pipeline.storage.directio import direct_io_enabled, set_direct_io

__all__ = ["AUTO_PROCESS_FRAMES", "SCHEDULERS", "Execution", "scheduler_for"]

#: Schedulers of the per-frame pass without a ``distributed`` client (``auto``: see
#: :func:`scheduler_for`).
SCHEDULERS = ("auto", "threads", "processes")

#: ``auto`` uses worker processes from this many frames on (with two workers or more). Starting
#: them costs 1-2 s of CPU (a forkserver that imports the apply module, then one fork per
#: worker); a full-resolution frame costs 0.1-0.2 s, a third to a half of it in Python under
#: the GIL (TIFF headers, tag parsing, per-frame bookkeeping), which threads cannot overlap.
AUTO_PROCESS_FRAMES = 32


@dataclass(frozen=True)
class Execution:
    """``scheduler``: auto, threads or processes (:func:`scheduler_for`); ``workers``: how many
    (0: one per core); ``direct_io``: ``O_DIRECT`` writes on or off for this process and the
    worker processes it starts (None: leave the process's setting)."""

    scheduler: str = "auto"
    workers: int = 0
    direct_io: bool | None = None

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise InputError(f"--scheduler {self.scheduler!r}: use {' or '.join(SCHEDULERS)}")
        if int(self.workers) < 0:
            raise InputError(f"--workers {self.workers}: use a positive number, or 0 for one per core")

    def install(self) -> None:
        """Apply the process-wide part (direct I/O) before any worker starts."""
        if self.direct_io is not None:
            set_direct_io(self.direct_io)

    def record(self, scheduler: str, workers: int) -> dict[str, Any]:
        """What run.json says about it: the scheduler and workers actually used, direct I/O."""
        return {"scheduler": scheduler, "workers": workers, "direct_io": direct_io_enabled()}


def scheduler_for(n_frames: int, execution: Execution = Execution()) -> tuple[str, int]:
    """Dask scheduler of the per-frame pass when no ``distributed`` client is active, and its
    number of workers (``execution.workers``, else one per core; never more than frames).
    ``threads``: the numpy, hashing and file writes of a frame release the GIL, and threads
    start at once, but the Python part of each frame (a third to a half of its CPU: TIFF
    headers, tags, bookkeeping) runs one thread at a time. ``processes``: worker processes (a
    forkserver that imports the apply module once; each worker keeps its own read-only tables,
    e.g. the factory vignetting maps, for the whole pass), every core busy. ``auto`` (the
    default): processes for a flight of :data:`AUTO_PROCESS_FRAMES` frames or more with two
    workers or more, else threads. The outputs are the same bytes whichever runs them.
    """
    cpus = int(execution.workers) or os.cpu_count() or 1
    workers = max(1, min(cpus, n_frames))
    scheduler = execution.scheduler
    if scheduler == "auto":
        scheduler = "processes" if workers >= 2 and n_frames >= AUTO_PROCESS_FRAMES else "threads"
    return scheduler, workers
