"""Per-band fits on worker processes: the same store whichever process fits a band."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

from pipeline.calibrate.pool import WORKERS_ENV, BandPool, band_workers
from pipeline.calibrate.views import detection_image
from tests.no_processes import NoSemaphores


def test_one_worker_and_two_give_the_same_store(small, tmp_path) -> None:
    """The shared small store was fitted in-process (tests/conftest.py sets one worker); the
    same session on two band workers, run as users run it (``mscal calibrate`` in a process
    of its own, single-threaded: forked workers), gives the same store, bit for bit."""
    session, calib = small
    assert os.environ.get(WORKERS_ENV) == "1"
    one = xr.open_zarr(calib).load()
    out = tmp_path / "cal-2.zarr"
    env = {**os.environ, WORKERS_ENV: "2"}
    run = subprocess.run([sys.executable, "-m", "pipeline.run.cli", "calibrate", str(session), "-o", str(out)],
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    two = xr.open_zarr(out).load()
    assert sorted(one.data_vars) == sorted(two.data_vars)
    for name in ("inverse_response", "vignetting", "vignetting_count", "spectral_factor", "reflector_brightness"):
        np.testing.assert_array_equal(one[name].values, two[name].values, err_msg=name)
    for stage in ("response", "vignetting", "illumination"):
        assert one.attrs[stage]["residuals"] == two.attrs[stage]["residuals"]
        assert one.attrs[stage]["skipped"] == two.attrs[stage]["skipped"]


def _fresh_interpreter(code: str, timeout: float) -> list[str]:
    """The words ``code`` prints, run by a fresh interpreter (single-threaded, as ``mscal
    calibrate`` starts; this test process has threads); its stderr if it fails."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.split()


def test_workers_fork_only_from_a_single_threaded_process() -> None:
    code = ("import threading, time\n"
            "from pipeline.calibrate.pool import start_method\n"
            "alone = start_method()\n"
            "threading.Thread(target=time.sleep, args=(0.5,)).start()\n"
            "print(alone, start_method())\n")
    assert _fresh_interpreter(code, timeout=60) == ["fork", "spawn"]


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_forked_and_spawned_workers_run_the_same_code(method: str) -> None:
    """In a fresh single-threaded interpreter, as ``mscal calibrate`` runs (this test process
    has threads: forking it could deadlock a child, which is why BandPool spawns then)."""
    code = ("import numpy as np\n"
            "from pipeline.calibrate.pool import BandPool\n"
            "if __name__ == '__main__':\n"
            "    x = np.linspace(0.0, 1.0, 1001)\n"
            f"    with BandPool(2, method={method!r}) as pool:\n"
            "        got = pool.map(np.dot, [(x, x), (2 * x, 2 * x)])\n"
            "        try:\n"
            "            pool.map(int, [('1',), ('not a number',)])\n"
            "        except ValueError as exc:\n"
            "            err = str(exc)\n"
            "    print(got == [float(x @ x), float((2 * x) @ (2 * x))], pool.workers, 'invalid literal' in err)\n")
    assert _fresh_interpreter(code, timeout=120) == ["True", "2", "True"]


def test_workers_fork_after_opencv_ran_its_own_threads() -> None:
    """A second calibration in one process (a notebook, ``bench_accuracy.py``): OpenCV's
    worker threads, started by the first, were running at the fork, and every forked worker
    hung in ``cv2.setNumThreads`` (``pthread_cond_destroy``). The pool stops them around the
    fork and gives OpenCV its setting back."""
    code = ("import cv2, numpy as np\n"
            "from pipeline.calibrate.pool import BandPool, start_method\n"
            "img = np.random.default_rng(0).random((1500, 1500), dtype=np.float32)\n"
            "for _ in range(3):\n"
            "    cv2.GaussianBlur(img, (31, 31), 5)\n"
            "before = cv2.getNumThreads()\n"
            "with BandPool(2) as pool:\n"
            "    got = pool.map(int, [('7',), ('8',)])\n"
            "print(start_method(), got == [7, 8], cv2.getNumThreads() == before)\n")
    assert _fresh_interpreter(code, timeout=120) == ["fork", "True", "True"]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_worker_error_reaches_the_caller(workers: int) -> None:
    with BandPool(workers) as pool:
        assert pool.map(int, [("7",), ("8",)]) == [7, 8]
        with pytest.raises(ValueError, match="invalid literal"):
            pool.map(int, [("1",), ("not a number",)])


@pytest.mark.parametrize(("env", "tasks", "expect"), [("3", 25, 3), ("3", 2, 2), ("1", 25, 1), ("", 1, 1)])
def test_band_workers(monkeypatch, env: str, tasks: int, expect: int) -> None:
    monkeypatch.setenv(WORKERS_ENV, env)
    assert band_workers(tasks) == expect


def test_band_workers_default_is_the_cores(monkeypatch) -> None:
    import os

    monkeypatch.setenv(WORKERS_ENV, "junk")
    assert band_workers(1000) == len(os.sched_getaffinity(0))


@pytest.mark.parametrize(("workers", "tasks", "expect"), [(3, 25, 3), (3, 2, 2), (1, 25, 1)])
def test_band_workers_parameter_wins_over_the_variable(monkeypatch, workers: int, tasks: int, expect: int) -> None:
    """``workers`` given: the variable (only its default) is not read; 0 is one per core."""
    import os

    monkeypatch.setenv(WORKERS_ENV, "7")
    assert band_workers(tasks, workers) == expect
    assert band_workers(1000, 0) == len(os.sched_getaffinity(0))


def test_detection_image_table_path_matches_the_plain_one() -> None:
    rng = np.random.default_rng(0)
    u = np.maximum.accumulate(rng.gamma(2.0, 1.0, (25, 1024)), axis=1)
    u[:, :40] = 0.0  # black level
    u[3] = 0.0  # a dark band: its median is 0 and it is not rescaled
    bands = rng.integers(0, 1024, (25, 60, 80)).astype(np.uint16)
    fast = detection_image(bands, u)  # monotone U, unsigned DN: table look-ups, median from counts
    plain = detection_image(bands.astype(np.int64), u)  # np.median of U(I), mean over bands
    assert fast.dtype == np.float32
    np.testing.assert_array_equal(fast, plain)
    odd = bands[:, :59, :79]  # an odd pixel count: the median is one DN's U
    np.testing.assert_array_equal(detection_image(odd, u), detection_image(odd.astype(np.int64), u))


def test_band_fits_run_in_this_process_where_worker_processes_cannot_start(monkeypatch, caplog) -> None:
    monkeypatch.setattr("pipeline.storage.process.ProcessPoolExecutor", NoSemaphores)
    with caplog.at_level("WARNING"), BandPool(2) as pool:
        assert pool.workers == 1
        assert pool.map(pow, [(2, 3), (3, 2)]) == [8, 9]
    assert "fitting the bands in this process instead" in caplog.text
