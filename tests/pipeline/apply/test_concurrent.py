"""Two mscal processes on one output (issue 23): one finishes with complete outputs, the
other refuses at once naming the holder (exit 75) or, with --wait, waits and then finds the
outputs up to date. No traceback, nothing half-written, every trial."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.pipeline.apply.test_apply import _assert_same_outputs, _outputs

ROOT = Path(__file__).resolve().parents[3]


def _start(flight: Path, calib: Path, out: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "pipeline.run.cli", "apply", str(flight), "--calibration", str(calib), "-o", str(out),
           *extra]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _trials(small, tmp_path: Path, n: int, wait: bool) -> None:
    session, calib = small
    flight = session / "flights" / "field"
    reference = None
    for k in range(n):
        out = tmp_path / f"out{k}"
        extra = ("--wait",) if wait else ()
        a, b = _start(flight, calib, out, *extra), _start(flight, calib, out, *extra)
        results = [(p.wait(timeout=600), *p.communicate()) for p in (a, b)]
        codes = sorted(r[0] for r in results)
        errs = [r[2] for r in results]
        assert not any("Traceback" in e for e in errs), errs
        if wait:
            assert codes == [0, 0], errs  # the second waited, then found the outputs up to date
        else:
            assert codes in ([0, 75], [0, 0]), errs  # 0, 0: the first finished before the second started
            if codes == [0, 75]:
                refused = next(e for (c, _, e) in results if c == 75).strip().splitlines()
                assert len(refused) == 1 and "is writing here: pid" in refused[0] and str(out) in refused[0]
        run = json.loads((out / "run.json").read_text())
        assert run["frames_out"] > 0
        got = _outputs(out)
        reference = reference or got
        _assert_same_outputs(reference, got)
        assert not [p for p in out.rglob("*") if ".tmp-" in p.name]


def test_two_applies_on_one_out(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 3, wait=False)


def test_two_applies_on_one_out_the_second_waits(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 2, wait=True)


@pytest.mark.long  # ~3 min: make test-long
def test_twenty_trials_of_two_applies(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 20, wait=False)
