"""``mscal run`` as a user sees it in a terminal, each case in its own process:

* two runs started together on one OUT: one completes, the other refuses at once in one line
  (exit 75) or, with --wait (every other trial of the long version), waits and then finds
  every flight up to date;
* a flight that cannot be processed (an empty folder) beside good ones: exit 3, a few lines on
  stderr, no Prefect record or traceback there; they are in ``OUT/logs/<time>-run.log``;
* a run that fails entirely (unreadable reflector images): one line on stderr, the reason and
  the log file, which holds the traceback.

The processes share a Prefect home of their own (not the test process's, whose embedded server
may be running) and the calibration cache of the test process (filled by ``first_run``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.flows.conftest import FLIGHTS, assert_same_flight_outputs

pytestmark = pytest.mark.xdist_group("flows")  # one worker: one calibration cache

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run_env(first_run, tmp_path_factory) -> dict[str, str]:
    env = dict(os.environ)
    env["PREFECT_HOME"] = str(tmp_path_factory.mktemp("prefect-subprocess"))
    return env


@pytest.fixture(scope="module")
def bad_session(flow_session, tmp_path_factory) -> Path:
    """The flow session with an empty flight folder beside its two good flights."""
    session = tmp_path_factory.mktemp("bad") / "session"
    shutil.copytree(flow_session, session)
    (session / "flights" / "empty").mkdir()
    return session


def _start(env: dict[str, str], session: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipeline.run.cli", "run", str(session), "-o", str(out), *extra],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(p: subprocess.Popen) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=900)
    return p.returncode, out, err


def _assert_quiet(err: str) -> None:
    """Nothing of Prefect's or Dask's on the terminal: no traceback, no log record."""
    assert "Traceback" not in err and not re.search(r"\| (INFO|WARNING|ERROR) ", err), err
    assert "distributed." not in err, err


def _assert_bad_flight_run(code: int, err: str, out: Path) -> None:
    """A run of ``bad_session`` that completed: exit 3, the empty flight named, the log named."""
    assert code == 3, err
    lines = err.strip().splitlines()
    assert len(lines) <= 3, err
    _assert_quiet(err)
    assert lines[0].startswith("flight empty was not processed:") and "no frames found" in lines[0]
    log = Path(lines[-1].rsplit(": ", 1)[1])
    assert log.parent == out / "logs" and log.name.endswith("-run.log") and log.is_file()
    text = log.read_text()
    assert "Traceback" in text and "SessionError" in text and "[apply-empty]" in text


def _trials(env: dict[str, str], session: Path, first_run: Path, tmp_path: Path, n: int) -> dict[str, int]:
    """``n`` trials of two runs at once on a new OUT (every other trial with --wait)."""
    tally = {"refused": 0, "waited": 0, "one_after_the_other": 0}
    started = time.monotonic()
    for k in range(n):
        out = tmp_path / f"out{k}"
        wait = ("--wait",) if k % 2 else ()
        results = [_finish(p) for p in (_start(env, session, out, *wait), _start(env, session, out, *wait))]
        codes = sorted(r[0] for r in results)
        if 75 in codes:
            assert not wait and codes == [3, 75], results
            refused = next(r[2] for r in results if r[0] == 75).strip().splitlines()
            assert len(refused) == 1 and "is writing here: pid" in refused[0] and str(out) in refused[0], refused
            tally["refused"] += 1
        else:
            assert codes == [3, 3], results
            tally["waited" if wait else "one_after_the_other"] += 1
        for code, _, err in results:
            if code == 3:
                _assert_bad_flight_run(code, err, out)
        run = json.loads((out / "run.json").read_text())
        assert run["status"] == "partial" and run["flights"]["empty"]["status"] == "failed"
        for name in FLIGHTS:
            assert run["flights"][name]["status"] == "done"
            assert_same_flight_outputs(first_run / "flights" / name, out / "flights" / name)
        assert not [p for p in out.rglob("*") if ".tmp-" in p.name]
    # a record for the README's reliability section (pytest -s shows it), never asserted on
    print(f"\n{n} trial(s) of two `mscal run` on one OUT: {tally}, {time.monotonic() - started:.0f} s")
    return tally


# ~50 s (two trials of two `mscal run` subprocesses, each with its own Prefect server): make
# test-long, beside its 20-trial twin. make test keeps the same lock through two applies at once
# on one OUT (tests/pipeline/apply/test_concurrent.py).
@pytest.mark.long
def test_two_runs_on_one_out_one_completes_the_other_refuses_or_waits(run_env, bad_session, first_run,
                                                                       tmp_path: Path) -> None:
    tally = _trials(run_env, bad_session, first_run, tmp_path, 1)  # --wait: the long test and the apply tests
    assert sum(tally.values()) == 1


@pytest.mark.long  # ~20 min: make test-long
def test_twenty_trials_of_two_runs_on_one_out(run_env, bad_session, first_run, tmp_path: Path) -> None:
    tally = _trials(run_env, bad_session, first_run, tmp_path, 20)
    assert tally["refused"] + tally["one_after_the_other"] == 10 and tally["waited"] == 10


def test_a_failed_run_says_one_line_naming_its_log(run_env, flow_session, tmp_path: Path) -> None:
    session = tmp_path / "session"
    shutil.copytree(flow_session, session)
    for p in (session / "reflector").glob("*.tif"):
        p.write_bytes(b"junk")
    out = tmp_path / "out"
    code, _, err = _finish(_start(run_env, session, out))
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    _assert_quiet(err)
    assert lines[0].startswith("mscal: error: ") and "reflector_0.tif: unreadable or truncated image" in lines[0]
    log = Path(re.search(r"\(log: (.+)\)$", lines[0]).group(1))
    assert log.parent == out / "logs" and log.is_file()
    text = log.read_text()
    assert "Traceback" in text and "FrameError" in text and "Starting temporary server" in text
