"""Two mscal processes on one output: one finishes with complete outputs, the
other refuses at once naming the holder (exit 75) or, with --wait, waits and then finds the
outputs up to date. No traceback, nothing half-written, every trial. And a run SIGKILLed at a
random (seeded) moment, then restarted by two processes at once: one completes, the other
refuses or waits, and the outputs equal an uninterrupted run's.

The kill comes from outside (``Popen.kill``): production code has no kill hook."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.pipeline.apply.test_apply import _assert_same_outputs, _outputs

ROOT = Path(__file__).resolve().parents[3]


def _start(flight: Path, calib: Path, out: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "pipeline.run.cli", "apply", str(flight), "--calibration", str(calib), "-o", str(out),
           *extra]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _pair(flight: Path, calib: Path, out: Path, wait: bool) -> list[int]:
    """Two applies started together on ``out``; checks what each said; their exit statuses."""
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
    return codes


def _assert_complete(out: Path, reference: dict | None) -> dict:
    """``out`` holds a complete flight (its marker matches its outputs), equal to ``reference``."""
    from pipeline.storage.atomic import outputs_manifest

    run = json.loads((out / "run.json").read_text())
    assert run["frames_out"] > 0
    assert run["outputs_manifest"] == outputs_manifest(out, run["outputs"].values())
    got = _outputs(out)
    reference = reference or got
    _assert_same_outputs(reference, got)
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name]
    return reference


def _trials(small, tmp_path: Path, n: int, wait: bool) -> None:
    session, calib = small
    flight = session / "flights" / "field"
    reference = None
    for k in range(n):
        out = tmp_path / f"out{k}"
        _pair(flight, calib, out, wait)
        reference = _assert_complete(out, reference)


def test_two_applies_on_one_out(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 3, wait=False)


def test_two_applies_on_one_out_the_second_waits(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 2, wait=True)


@pytest.mark.long  # ~3 min: make test-long
def test_twenty_trials_of_two_applies(small, tmp_path: Path) -> None:
    _trials(small, tmp_path, 20, wait=False)


def _entries(folder: Path) -> int:
    """Files and folders under ``folder`` (os.walk skips what is renamed away meanwhile)."""
    return sum(len(dirs) + len(files) for _, dirs, files in os.walk(folder))


def _kill_at(proc: subprocess.Popen, out: Path, k: int) -> None:
    """SIGKILL ``proc`` once ``out`` holds ``k`` files and folders (temporaries included): a
    point in its progress, not a time, so that the kill lands inside the run however busy
    the machine is. 0 kills it as it starts."""
    while proc.poll() is None:
        if _entries(out) >= k:
            proc.kill()  # SIGKILL
            break
        time.sleep(0.005)
    proc.communicate()


def _killed_then_two_restarts(small, tmp_path: Path, n: int, seed: int) -> dict[str, int]:
    """``n`` trials: an apply SIGKILLed at a random (seeded) point of its progress, once its OUT
    holds k files and folders, k drawn from 0 to one less than an uninterrupted run leaves;
    then two applies at once on its OUT (every other trial with --wait). Returns how the
    trials went."""
    session, calib = small
    flight = session / "flights" / "field"
    clean = tmp_path / "clean"
    assert _start(flight, calib, clean).wait(timeout=600) == 0
    reference = _assert_complete(clean, None)
    rng = random.Random(seed)
    tally = {"killed": 0, "finished_before_the_kill": 0, "refused": 0, "waited_or_after": 0}
    for k in range(n):
        out = tmp_path / f"killed{k}"
        victim = _start(flight, calib, out)
        _kill_at(victim, out, rng.randrange(_entries(clean)))
        tally["killed" if victim.returncode == -9 else "finished_before_the_kill"] += 1
        assert victim.returncode in (0, -9)
        codes = _pair(flight, calib, out, wait=bool(k % 2))
        tally["refused" if 75 in codes else "waited_or_after"] += 1
        _assert_complete(out, reference)
    return tally


def test_sigkill_then_two_restarts_at_once(small, tmp_path: Path) -> None:
    # two trials (one plain pair, one with --wait): the twenty-trial version is make test-long
    tally = _killed_then_two_restarts(small, tmp_path, 2, seed=23)
    print(f"2 SIGKILLs then two restarts: {tally}")
    assert tally["killed"] + tally["finished_before_the_kill"] == 2 and tally["killed"] >= 1, tally


@pytest.mark.long  # ~7 min: make test-long
def test_twenty_sigkills_then_two_restarts_at_once(small, tmp_path: Path) -> None:
    tally = _killed_then_two_restarts(small, tmp_path, 20, seed=2023)
    print(f"20 SIGKILLs then two restarts: {tally}")  # the README's numbers (pytest -s)
    assert tally["killed"] >= 10, tally  # the kill points lie inside the run
