"""Shared synthetic sessions: written and calibrated once per test process."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.run.cli import main
from pipeline.sim.synth import write_session


@pytest.fixture(scope="session")
def small(tmp_path_factory) -> tuple[Path, Path]:
    """A small synthetic session (7-frame sweep, 8 views, 2 reflector images, a 3-frame
    flight) and its calibration store."""
    root = tmp_path_factory.mktemp("small")
    session = write_session(root / "session", seed=0, size="small")  # the demo session
    calib = root / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    return session, calib


@pytest.fixture(scope="session")
def full_session(tmp_path_factory) -> Path:
    """A full-size synthetic session (seed 11; ~60 s to write). Read-only for its users, which
    carry ``xdist_group("full_session")`` so that one test process writes it once."""
    return write_session(tmp_path_factory.mktemp("full") / "session", seed=11, size="full")
