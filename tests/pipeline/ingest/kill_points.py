"""Test-only: make this process SIGKILL itself at a named step of an ingest.

Production code has no hook: :func:`arm` wraps the functions of :mod:`pipeline.ingest.raw`
and :mod:`pipeline.storage.atomic` that do each step, in the process that is to die (a
forked child, or ``python -c`` through :data:`KILL_CODE`). Points:

* ``create``: the cube is built under its temporary name, not yet renamed into place;
* ``frame:N``: the N-th new frame chunk of this run is written;
* ``coords:K``: the K-th commit wrote chunks and coordinates, not the consolidated metadata;
* ``consolidated:K``: ... and the consolidated metadata, not the ``frames_committed`` count;
* ``commit:K``: right after the K-th commit;
* ``recover``: uncommitted frames of a killed run were cut off, not yet re-consolidated.
"""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

from pipeline.ingest import raw
from pipeline.storage import atomic

#: Runs an ingest that dies at argv[5]: ``python -c KILL_CODE FLIGHT CAMERA OUT COMMIT_EVERY POINT``.
KILL_CODE = (
    "import sys\nfrom tests.pipeline.ingest.kill_points import arm\narm(sys.argv[5])\n"
    "from pipeline.ingest.raw import ingest_flight\n"
    "ingest_flight(sys.argv[1], sys.argv[2], sys.argv[3], commit_every=int(sys.argv[4]))\n"
)


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def arm(spec: str) -> None:
    """Wrap the step ``spec`` (``point`` or ``point:count``) so that this process dies there."""
    point, _, count = spec.partition(":")
    k = int(count) if count else None
    if point == "create":
        atomic.install_folder = lambda tmp, final, **kwargs: _die()  # atomic_folder looks it up at the rename
    elif point == "frame":
        _after_nth_chunk(k)
    elif point in ("coords", "consolidated", "commit", "recover"):
        _in_commit_or_recovery(point, k)
    else:
        raise ValueError(f"unknown kill point {spec!r}")


def _after_nth_chunk(n: int) -> None:
    write, lock, done = raw._write_chunk, threading.Lock(), [0]

    def write_then_die(*args: Any) -> None:
        write(*args)
        with lock:
            done[0] += 1
            if done[0] == n:
                _die()

    raw._write_chunk = write_then_die


def _in_commit_or_recovery(point: str, k: int | None) -> None:
    writer: list[Any] = [None]  # the CubeWriter inside its commit(), if any
    commit, consolidate, set_committed = raw.CubeWriter.commit, raw._consolidate, raw._set_committed

    def commit_tracked(self: Any) -> None:
        writer[0] = self
        try:
            commit(self)
        finally:
            writer[0] = None

    def at(kth: int | None) -> bool:
        return writer[0] is not None and writer[0].n_commits == kth

    def consolidate_or_die(path: Any) -> None:
        # outside a commit, _consolidate only runs in recovery (after cutting frames off)
        if (point == "coords" and at(k)) or (point == "recover" and writer[0] is None):
            _die()
        consolidate(path)

    def set_committed_or_die(path: Any, n: int) -> None:
        if point == "consolidated" and at(k):
            _die()
        set_committed(path, n)
        if point == "commit" and at(k):
            _die()

    raw.CubeWriter.commit = commit_tracked
    raw._consolidate = consolidate_or_die
    raw._set_committed = set_committed_or_die
