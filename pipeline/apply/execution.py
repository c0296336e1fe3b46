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

__all__ = ["SCHEDULERS", "Execution", "scheduler_for"]

#: Schedulers of the per-frame pass without a ``distributed`` client.
SCHEDULERS = ("threads", "processes")


@dataclass(frozen=True)
class Execution:
    """``scheduler``: threads or processes (:func:`scheduler_for`); ``workers``: how many (0:
    one per core); ``direct_io``: ``O_DIRECT`` writes on or off for this process and the
    worker processes it starts (None: leave the process's setting)."""

    scheduler: str = "threads"
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
    number of workers. Threads by default, one per core: the per-frame work is numpy, hashing
    and file writes, which release the GIL (two threads run a 120-frame flight 1.8x faster
    than one), and threads start at once where worker processes take 1-2 s. ``processes``
    chooses worker processes instead (a forkserver that imports the apply module once).
    """
    cpus = int(execution.workers) or os.cpu_count() or 1
    return execution.scheduler, max(1, min(cpus, n_frames))
