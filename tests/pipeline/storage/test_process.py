"""Process settings of mscal's workers and main process (pipeline.storage.process)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.no_processes import NoSemaphores

PROBE = (
    "from numpy._core.multiarray import _set_madvise_hugepage as hp\n"
    "from pipeline.storage.process import reuse_freed_memory\n"
    "before = hp(True); hp(before)\n"
    "reuse_freed_memory()\n"
    "print(before, hp(True))\n"
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="huge pages are a Linux setting")
@pytest.mark.parametrize(("env", "want"), [(None, "True False"), ("1", "True True"), ("0", "False False")])
def test_new_arrays_use_small_pages_unless_numpy_is_told_otherwise(env: str | None, want: str) -> None:
    """A worker's memory settings turn NumPy's huge-page advice off (slow first touches on a VM
    whose memory goes back to the host), but NUMPY_MADVISE_HUGEPAGE, when set, decides."""
    environ = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if env is not None:
        environ["NUMPY_MADVISE_HUGEPAGE"] = env
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=environ, timeout=120,
                         check=True)
    assert out.stdout.strip() == want


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
