"""How an apply pass runs: scheduler, worker count, direct I/O (never what it computes).

These are the options ``--scheduler``, ``--workers`` and ``--direct-io/--no-direct-io`` of
``mscal apply`` and ``mscal run``, whose defaults come from ``MSCAL_APPLY_SCHEDULER``,
``MSCAL_APPLY_WORKERS`` and ``MSCAL_DIRECT_IO`` (read by the command line only). They change
neither the outputs nor the fingerprint that decides whether a run is up to date; run.json
records them.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from dataclasses import dataclass
from multiprocessing.context import ForkServerContext
from pathlib import Path
from typing import Any, Sequence

from mscal_core.errors import InputError

from pipeline.storage.atomic import iter_files
from pipeline.storage.directio import direct_io_enabled, set_direct_io
from pipeline.storage.process import POOL_ERRORS, environment

__all__ = ["AUTO_PROCESS_FRAMES", "SCHEDULERS", "SERVER_MODULE", "WORKER_BYTES_PER_PIXEL", "WORKER_MEMORY",
           "WORKER_MODULE", "Execution", "capture_pixels", "distributed_client", "ensure_worker_server",
           "flight_size_hint", "scheduler_for", "server_import_path", "spare_workers", "start_worker_server",
           "take_worker_environment", "worker_context", "worker_environment"]

#: Schedulers of the per-frame pass without a ``distributed`` client (``auto``: see
#: :func:`scheduler_for`).
SCHEDULERS = ("auto", "threads", "processes")

#: ``auto`` uses worker processes from this many frames on (with two workers or more). Starting
#: them costs 1-2 s of CPU (a forkserver that imports the apply module, then one fork per
#: worker); a full-resolution frame costs 0.1-0.2 s, a third to a half of it in Python under
#: the GIL (TIFF headers, tag parsing, per-frame bookkeeping), which threads cannot overlap.
AUTO_PROCESS_FRAMES = 32

#: A worker process's memory per output pixel of the capture it computes (bytes): the
#: snapshot camera's frames (25 bands of 217 x 409, 2.2 Mpx) cost 172 MiB a worker (600
#: frames, peak of every process: 636 MiB with 2 workers, 808 MiB with 3).
WORKER_BYTES_PER_PIXEL = 81

#: The worker processes' share of apply's 1 GiB memory target (the main process, ~250 MiB,
#: keeps the rest): a spare worker (:func:`spare_workers`) only within it.
WORKER_MEMORY = 768 * 1024 * 1024


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


def capture_pixels(camera: Any) -> int:
    """Output pixels of one capture of ``camera`` (a catalog entry): its bands times its band
    grid (a mosaic's) or its sensor; 0 when the catalog gives neither."""
    shape = camera.layout.grid or camera.sensor
    return int(camera.n_bands) * int(shape[0]) * int(shape[1]) if shape else 0


def spare_workers(workers: int, pixels: int) -> int:
    """Worker processes beyond one per core (0 or 1) for captures of ``pixels`` output pixels.

    A worker writes its frames' files with direct I/O and waits on the device when they take
    longer than computing the next frame; one more worker than cores computes meanwhile. On
    the snapshot camera (2 cores, 600 frames): the machine's busy cores during apply 1.76 ->
    1.85, the CPU of apply's own processes over wall 1.67 -> 1.74-1.75, peak memory 636-648 ->
    793-808 MiB (4 workers: 980 MiB). The wall moved within the machine's run-to-run spread:
    10.37 -> 9.67 s (medians of 3 alternating runs each), 9.4 s (one run) against 10.0 s
    (median of 3) in docs/benchmarks.md. Only while every worker's memory
    (:data:`WORKER_BYTES_PER_PIXEL`) stays within :data:`WORKER_MEMORY`: a 5-band MicaSense
    capture (6.1 Mpx) keeps one worker per core."""
    if workers < 2 or pixels <= 0:
        return 0
    return int((workers + 1) * pixels * WORKER_BYTES_PER_PIXEL <= WORKER_MEMORY)


def scheduler_for(n_frames: int, execution: Execution = Execution(), pixels: int = 0) -> tuple[str, int]:
    """Dask scheduler of the per-frame pass when no ``distributed`` client is active, and its
    number of workers (``execution.workers``, else one per core, plus :func:`spare_workers`
    for worker processes writing with direct I/O on captures of ``pixels`` output pixels;
    never more than frames).
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
    if scheduler == "processes" and not int(execution.workers) and direct_io_enabled():
        workers = min(n_frames, workers + spare_workers(workers, pixels))
    return scheduler, workers


#: The module the worker processes run, imported once by their server (the forkserver) before
#: any worker is forked from it.
WORKER_MODULE = "pipeline.apply.executor"

#: Imported by the server after :data:`WORKER_MODULE`: freezes what the server holds
#: (:mod:`pipeline.apply.worker_server`).
SERVER_MODULE = "pipeline.apply.worker_server"

#: Environment variables a worker process reads (direct I/O, catalog path): given to each
#: worker as the main process has them when the pass starts (:func:`worker_environment`), not
#: as they were when the server was started.
WORKER_ENV_PREFIX = "MSCAL_"


def worker_context() -> ForkServerContext:
    """The worker processes' multiprocessing context: a forkserver that has imported
    :data:`WORKER_MODULE` (one import for every worker of the process's passes), started
    (:func:`ensure_worker_server`) if it is not running."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([WORKER_MODULE, SERVER_MODULE])
    ensure_worker_server()
    return ctx


def ensure_worker_server() -> None:
    """Start the forkserver (if it is not running) so that it imports what this process
    imports: :func:`server_import_path` as its ``PYTHONPATH``, and no current folder first
    (``PYTHONSAFEPATH``), both for the server's start only, and
    :data:`pipeline.apply.worker_server.SERVER_ENV` (the server freezes what it imported).

    Why: the server is a new interpreter (``python -c``), so its import path begins with the
    current folder, and Python 3.11's forkserver imports its preload before it takes the
    parent's ``sys.path``. Run from a folder that held a ``pipeline`` or ``mscal_core``
    folder (a user's own project, another checkout of mscal), the workers ran that code,
    not the installed one: an error at best (``module 'mscal_core' has no attribute
    '__version__'``), at worst another version's outputs. An interpreter started with ``-I``
    or ``-E`` gives its server neither variable; its own import path has no current folder
    either, so both then import from the same places."""
    from multiprocessing import forkserver

    from pipeline.apply.worker_server import SERVER_ENV

    with environment({"PYTHONPATH": os.pathsep.join(server_import_path()), "PYTHONSAFEPATH": "1", SERVER_ENV: "1"}):
        forkserver.ensure_running()


def server_import_path(path: Sequence[str] | None = None) -> list[str]:
    """This process's import path (``path``, default ``sys.path``) as the worker server's
    ``PYTHONPATH``, in order: folders and archives made absolute (``''``, the current folder,
    made explicit), other entries as they are (a path hook's name, e.g. an editable
    install's); entries that hold the path separator cannot be given and are left out."""
    out = []
    for entry in sys.path if path is None else path:
        full = os.path.abspath(entry or os.curdir) if os.path.exists(entry or os.curdir) else entry
        if os.pathsep not in full and full not in out:
            out.append(full)
    return out


def worker_environment() -> dict[str, str]:
    """This process's ``MSCAL_*`` variables, for a worker to take over when it starts: the
    forkserver keeps the environment of the moment it was started (possibly an earlier pass,
    or before ``--no-direct-io`` was applied), and its workers inherit the server's."""
    return {k: v for k, v in os.environ.items() if k.startswith(WORKER_ENV_PREFIX)}


def take_worker_environment(environment: dict[str, str]) -> None:
    """In a worker process: its ``MSCAL_*`` variables become ``environment`` (those of
    :func:`worker_environment` in the main process), others of that prefix are removed."""
    for key in [k for k in os.environ if k.startswith(WORKER_ENV_PREFIX) and k not in environment]:
        del os.environ[key]
    os.environ.update(environment)


def distributed_client():
    """The active ``distributed`` client (the caller's ``with Client(...)``), if any. A caller
    with a client has imported ``distributed``; without one it is not imported here (0.2 s of
    every run's start)."""
    if "distributed" not in sys.modules:
        return None
    try:
        from distributed import default_client
    except ImportError:
        return None
    try:
        return default_client()
    except ValueError:
        return None


def flight_size_hint(folder: str | Path, limit: int = AUTO_PROCESS_FRAMES) -> int:
    """Files in ``folder`` and its subfolders, counted up to ``limit`` (cheap: no file is
    opened; a folder that cannot be read ends the count). An upper bound of the frames of a
    flight (a capture can be several files)."""
    n = 0
    try:
        for _ in iter_files(folder):
            n += 1
            if n >= limit:
                break
    except OSError:
        pass
    return n


def start_worker_server(execution: Execution, frames_hint: int) -> bool:
    """Start the worker processes' server now, if a pass of about ``frames_hint`` frames would
    run on worker processes (:func:`scheduler_for`): its import of :data:`WORKER_MODULE` (about
    a second) then runs while this process imports and reads the flight, instead of before
    the first frame. Returns whether it was started. Harmless when the guess is wrong: the
    pass starts the server itself if needed, and an unused server ends with this process."""
    if distributed_client() is not None or scheduler_for(frames_hint, execution)[0] != "processes":
        return False
    try:
        worker_context()
    except POOL_ERRORS:  # the pass says why (pipeline.storage.process.start_pool)
        return False
    return True
