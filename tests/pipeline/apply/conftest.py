"""Fixtures shared by the apply tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.run.cli import main


@pytest.fixture(scope="module")
def applied(small, tmp_path_factory) -> tuple[Path, Path, Path]:
    """(session, calibration store, OUT) of one ``mscal apply`` of the small session's field
    flight, per test module; tests that change OUT work on a copy."""
    session, calib = small
    out = tmp_path_factory.mktemp("apply") / "out"
    flight = session / "flights" / "field"
    assert main(["apply", str(flight), "--calibration", str(calib), "-o", str(out)]) == 0
    return session, calib, out
