"""Shared synthetic sessions: written and calibrated once per test process."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import pytest

from pipeline.run.cli import main
from pipeline.sim.synth import write_session


def _write_small(root: Path) -> tuple[Path, Path]:
    session = write_session(root / "session", seed=0, size="small")  # the demo session
    calib = root / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    return session, calib


@pytest.fixture(scope="session")
def small(tmp_path_factory) -> tuple[Path, Path]:
    """A small synthetic session (7-frame sweep, 8 views, 2 reflector images, a 3-frame
    flight) and its calibration store. Read-only for its users. Under pytest-xdist the test
    processes of one run share one copy (~30 s to write and calibrate): the first to get the
    lock writes it in the run's own base folder, the others wait for it."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return _write_small(tmp_path_factory.mktemp("small"))
    root = tmp_path_factory.getbasetemp().parent / "small-shared"  # this run's folder, not the workers'
    root.mkdir(exist_ok=True)
    with (root / "lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if (root / "done").is_file():
                return root / "session", root / "calib.zarr"
            paths = _write_small(root)
            (root / "done").write_text("written\n")
            return paths
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def full_session(tmp_path_factory) -> Path:
    """A full-size synthetic session (seed 11; ~60 s to write). Read-only for its users, which
    carry ``xdist_group("full_session")`` so that one test process writes it once."""
    return write_session(tmp_path_factory.mktemp("full") / "session", seed=11, size="full")
