"""Process settings of mscal's workers and main process (pipeline.storage.process)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.no_processes import NoSemaphores

#: In a fresh process: whether transparent huge pages are off for it (``PR_GET_THP_DISABLE``)
#: before and after the workers' memory settings, whether a process it starts after has them
#: off too, and the huge pages behind 64 MB of new, touched arrays. The probe first clears the
#: setting: the test's own process may hold it from an earlier test (children inherit it).
PROBE = (
    "import ctypes, subprocess, sys\n"
    "import numpy as np\n"
    "from pipeline.storage.process import reuse_freed_memory\n"
    "get = 'import ctypes; print(ctypes.CDLL(\"libc.so.6\").prctl(42, 0, 0, 0, 0))'\n"
    "ctypes.CDLL('libc.so.6').prctl(41, 0, 0, 0, 0)\n"  # PR_SET_THP_DISABLE 0: not inherited from this test's process
    "before = ctypes.CDLL('libc.so.6').prctl(42, 0, 0, 0, 0)\n"
    "reuse_freed_memory()\n"
    "after = ctypes.CDLL('libc.so.6').prctl(42, 0, 0, 0, 0)\n"
    "child = subprocess.run([sys.executable, '-c', get], capture_output=True, text=True).stdout.strip()\n"
    "keep = [np.ones(2 ** 20) for _ in range(8)]\n"
    "huge = [int(line.split()[1]) for line in open('/proc/self/smaps_rollup') if line.startswith('AnonHugePages')]\n"
    "print(before, after, child, huge[0] if huge else 0)\n"
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="huge pages are a Linux setting")
@pytest.mark.parametrize(("env", "want"), [(None, "0 1 1"), ("1", "0 0 0"), ("0", "0 0 0")])
def test_new_arrays_use_small_pages_unless_numpy_is_told_otherwise(env: str | None, want: str) -> None:
    """A worker's memory settings keep new arrays out of huge pages (slow first touches on a VM
    whose memory goes back to the host), in the processes it starts too, after numpy was
    imported; NUMPY_MADVISE_HUGEPAGE, when set, decides instead (numpy reads it itself)."""
    environ = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if env is not None:
        environ["NUMPY_MADVISE_HUGEPAGE"] = env
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=environ, timeout=120,
                         check=True)
    *flags, huge_kb = out.stdout.split()
    assert " ".join(flags) == want
    if env != "1":  # off, by mscal or by numpy: not one 2 MB page behind the 64 MB
        assert huge_kb == "0"


class _Pool:
    """A process pool whose workers cannot start (the system refuses a fork)."""

    made: list["_Pool"] = []

    def __init__(self, workers, mp_context=None, initializer=None, initargs=()):
        self.shut = False
        _Pool.made.append(self)

    def submit(self, fn, *args):
        raise OSError(11, "Resource temporarily unavailable")

    def shutdown(self, wait=True, cancel_futures=False):
        self.shut = True


def test_a_pool_the_system_cannot_run_is_refused_with_its_reason_and_nothing_left_running(monkeypatch) -> None:
    import multiprocessing

    from mscal_core.errors import ProcessesUnavailable
    from pipeline.storage.process import start_pool

    entered = []

    def starting():
        entered.append(True)
        return open(os.devnull)  # any context manager

    monkeypatch.setattr("pipeline.storage.process.ProcessPoolExecutor", _Pool)
    with pytest.raises(ProcessesUnavailable, match=r"cannot start on this system \(BlockingIOError: \[Errno 11\] Resource temporarily unavailable\)$"):
        start_pool(2, lambda: multiprocessing.get_context("spawn"), print, starting=starting)
    assert entered == [True] and _Pool.made[-1].shut  # started inside starting(); shut down after
    monkeypatch.setattr("pipeline.storage.process.ProcessPoolExecutor", NoSemaphores)
    with pytest.raises(ProcessesUnavailable, match=r"\(OSError: \[Errno 38\] Function not implemented\)"):
        start_pool(2, lambda: multiprocessing.get_context("spawn"), print)


def test_environment_is_set_for_the_block_and_restored_after(monkeypatch) -> None:
    from pipeline.storage.process import environment

    monkeypatch.setenv("MSCAL_TEST_HAD", "before")
    monkeypatch.delenv("MSCAL_TEST_NEW", raising=False)
    with pytest.raises(RuntimeError), environment({"MSCAL_TEST_HAD": "in", "MSCAL_TEST_NEW": "in"}):
        assert (os.environ["MSCAL_TEST_HAD"], os.environ["MSCAL_TEST_NEW"]) == ("in", "in")
        raise RuntimeError("restored on an error too")
    assert os.environ["MSCAL_TEST_HAD"] == "before" and "MSCAL_TEST_NEW" not in os.environ


#: In a fresh process: two rounds of a forkserver pool (as the apply executor's) shut down and
#: stop_process_servers called; the live and dead children left after each round, and each
#: round's result (the second pool starts the servers again).
ROUNDS = (
    "import json, multiprocessing, psutil\n"
    "from pipeline.storage.process import start_pool, stop_process_servers\n"
    "def kids():\n"
    "    return sorted(c.status() for c in psutil.Process().children(recursive=True))\n"
    "if __name__ == '__main__':\n"
    "    out = []\n"
    "    for k in (1, 2):\n"
    "        pool = start_pool(2, lambda: multiprocessing.get_context('forkserver'), int)\n"
    "        during = len(psutil.Process().children(recursive=True))\n"
    "        got = sum(pool.map(abs, range(-k * 10, 0)))\n"
    "        pool.shutdown(wait=True)\n"
    "        stop_process_servers()\n"
    "        out.append({'during': during, 'result': got, 'after': kids()})\n"
    "    print(json.dumps(out))\n"
)


def test_stopped_servers_leave_no_process_and_start_again(tmp_path) -> None:
    """After a forkserver pool is shut down, stop_process_servers ends the forkserver and the
    resource tracker and reaps them (no live or dead child left); a later pool in the same
    process starts them again and runs. (Two workers, a server and a tracker while it runs.)"""
    import json

    import pipeline

    (tmp_path / "rounds.py").write_text(ROUNDS)
    env = {**os.environ, "PYTHONPATH": os.path.dirname(os.path.dirname(pipeline.__file__))}
    done = subprocess.run([sys.executable, str(tmp_path / "rounds.py")], capture_output=True, text=True,
                          timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    rounds = json.loads(done.stdout.strip().splitlines()[-1])
    assert [r["result"] for r in rounds] == [55, 210]
    assert [r["during"] for r in rounds] == [4, 4]
    assert [r["after"] for r in rounds] == [[], []]
    assert "leaked" not in done.stderr and "relaunching" not in done.stderr
