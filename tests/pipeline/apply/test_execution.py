"""How apply runs (``--scheduler``, ``--workers``, ``--direct-io``): command-line options that
default to their environment variables, recorded in run.json, never in the outputs or in the
fingerprint that decides whether a run is up to date."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from mscal_core.errors import InputError
from pipeline.apply.execution import AUTO_PROCESS_FRAMES, Execution, capture_pixels, scheduler_for, spare_workers
from pipeline.apply.factory import FactoryOptions
from pipeline.apply.options import ApplyOptions
from pipeline.run.cli import main
from pipeline.run.runner import apply_one
from pipeline.storage.directio import direct_io_enabled
from tests.micasense_data import require_data
from tests.no_processes import NoSemaphores


def test_scheduler_for_and_validation(monkeypatch) -> None:
    monkeypatch.setattr("os.cpu_count", lambda: 8)
    assert scheduler_for(100) == ("processes", 8)  # auto: a long flight on worker processes
    assert scheduler_for(AUTO_PROCESS_FRAMES - 1) == ("threads", 8)  # a short one on threads
    assert scheduler_for(AUTO_PROCESS_FRAMES, Execution(workers=1)) == ("threads", 1)  # one worker: no pool
    assert scheduler_for(100, Execution("threads")) == ("threads", 8)
    assert scheduler_for(3) == ("threads", 3)  # never more workers than frames
    assert scheduler_for(100, Execution("processes", 2)) == ("processes", 2)
    monkeypatch.setenv("MSCAL_APPLY_WORKERS", "1")  # read by the command line only
    assert scheduler_for(100) == ("processes", 8)
    with pytest.raises(InputError, match="--scheduler 'fork'"):
        Execution("fork")
    with pytest.raises(InputError, match="--workers -1"):
        Execution(workers=-1)


def test_a_spare_worker_only_where_its_memory_fits(monkeypatch) -> None:
    """One worker more than cores for worker processes writing with direct I/O, while every
    worker's memory (81 bytes a capture pixel) stays within 768 MiB: the snapshot camera's
    frames on 2 cores, not on 4, not a MicaSense capture; never with --workers given, on
    threads, without direct I/O, or beyond the frames."""
    from pipeline.ingest.catalog import load_camera

    snapshot, rededge = (capture_pixels(load_camera(n)) for n in ("ximea-mq022hg-sm5x5-nir", "micasense-rededge"))
    assert snapshot == 25 * 217 * 409 and rededge == 5 * 960 * 1280
    assert spare_workers(2, snapshot) == 1 and spare_workers(4, snapshot) == 0
    assert spare_workers(2, rededge) == 0 and spare_workers(1, snapshot) == 0 and spare_workers(2, 0) == 0
    assert spare_workers(2, 1_000_000) == 1 and spare_workers(8, 1_000_000) == 1 and spare_workers(9, 1_000_000) == 0
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    monkeypatch.setattr("pipeline.apply.execution.direct_io_enabled", lambda: True)
    assert scheduler_for(100, Execution(), snapshot) == ("processes", 3)
    assert scheduler_for(100, Execution(), rededge) == ("processes", 2)
    assert scheduler_for(100, Execution(workers=2), snapshot) == ("processes", 2)  # asked for: as given
    assert scheduler_for(100, Execution("threads"), snapshot) == ("threads", 2)
    assert scheduler_for(2, Execution("processes"), snapshot) == ("processes", 2)  # never more than frames
    assert scheduler_for(100, Execution(), 0) == ("processes", 2)  # size unknown
    monkeypatch.setattr("pipeline.apply.execution.direct_io_enabled", lambda: False)
    assert scheduler_for(100, Execution(), snapshot) == ("processes", 2)


def test_execution_is_not_in_the_fingerprint() -> None:
    other = Execution("processes", 3, False)
    assert ApplyOptions(execution=other).fingerprint() == ApplyOptions().fingerprint()
    assert "execution" not in ApplyOptions().fingerprint()
    assert FactoryOptions(execution=other).fingerprint() == FactoryOptions().fingerprint()


def _run(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def test_options_default_to_the_environment_and_are_recorded(tmp_path, monkeypatch, capsys) -> None:
    data = require_data()
    monkeypatch.setenv("MSCAL_APPLY_WORKERS", "1")
    monkeypatch.setenv("MSCAL_DIRECT_IO", "off")  # also restores the process's switch afterwards
    a = tmp_path / "a"
    assert main(["apply", str(data), "--calibration", "factory", "-o", str(a)]) == 0
    assert _run(a)["execution"] == {"scheduler": "threads", "workers": 1, "direct_io": False}
    # the options win over the environment; outputs are the same bytes, and a run with other
    # execution options over the same outputs is up to date
    b = tmp_path / "b"
    assert main(["apply", str(data), "--calibration", "factory", "-o", str(b), "--workers", "2", "--direct-io"]) == 0
    assert _run(b)["execution"] == {"scheduler": "threads", "workers": 2, "direct_io": direct_io_enabled()}
    files = sorted(p.relative_to(a) for sub in ("photogrammetry", "panels") for p in (a / sub).rglob("*.tif"))
    assert len(files) == 10  # IMG_0001's five in photogrammetry/, the panel capture IMG_0000's in panels/
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    capsys.readouterr()
    assert main(["apply", str(data), "--calibration", "factory", "-o", str(a), "--scheduler", "processes"]) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(["apply", str(data), "--calibration", "factory", "-o", str(a), "--workers", "-2"]) == 2


def test_run_records_execution_per_flight(small, tmp_path, monkeypatch) -> None:
    """What ``mscal run`` passes through the post-flight flow to each flight (no Prefect here)."""
    session, calib = small
    monkeypatch.setenv("MSCAL_DIRECT_IO", "1")  # restored afterwards
    summary = apply_one(str(session / "flights" / "field"), str(calib), str(tmp_path / "o"), workers=1,
                        direct_io=False)
    assert summary["execution"] == {"scheduler": "threads", "workers": 1, "direct_io": False}
    assert summary["frames_out"] == 3


def _arrays(out: Path) -> dict[str, np.ndarray]:
    import zarr

    found = {}
    for store in ("reflectance.zarr", "raw.zarr"):
        group = zarr.open_group(out / store, mode="r")
        found.update({f"{store}/{name}": np.asarray(group[name][...]) for name in group.array_keys()})
    return found


@pytest.mark.slow
def test_one_worker_and_two_worker_processes_write_the_same_bytes(tmp_path) -> None:
    """The factory pass over the MicaSense sample run by one thread and by two worker
    processes (each with its own vignetting maps, each writing whole chunks of its own frames):
    every array of reflectance.zarr and raw.zarr identical, every TIFF the same bytes, and
    run.json says how each ran."""
    data = require_data()
    one, two = tmp_path / "one", tmp_path / "two"
    args = ["apply", str(data), "--calibration", "factory", "--reference", "dls", "--products", "radiance"]
    assert main([*args, "-o", str(one), "--workers", "1"]) == 0
    assert main([*args, "-o", str(two), "--workers", "2", "--scheduler", "processes"]) == 0
    assert _run(one)["execution"]["scheduler"] == "threads" and _run(one)["execution"]["workers"] == 1
    assert _run(two)["execution"]["scheduler"] == "processes" and _run(two)["execution"]["workers"] == 2
    a, b = _arrays(one), _arrays(two)
    assert a.keys() == b.keys() and {"reflectance.zarr/reflectance", "reflectance.zarr/radiance", "raw.zarr/dn"} <= a.keys()
    for key in a:
        assert a[key].shape == b[key].shape, key
        if a[key].dtype.kind == "f":
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)  # NaN where NaN
        else:
            assert a[key].tolist() == b[key].tolist(), key
    refl = a["reflectance.zarr/reflectance"]
    assert refl.shape == (2, 5, 960, 1280) and 0.05 < float(np.nanmedian(refl)) < 1.0
    files = sorted(p.relative_to(one) for p in one.rglob("*.tif"))
    assert len(files) == 11  # the panel capture IMG_0000: 5 bands in panels/; IMG_0001: 5 bands + NDVI
    assert all((one / f).read_bytes() == (two / f).read_bytes() for f in files)


def test_runner_hands_the_jobs_over_a_window_at_a_time(monkeypatch) -> None:
    """The task graph of a long flight is built a window of frames at a time (its memory stays
    flat); results come back in job order, and a generator of jobs is drawn lazily."""
    from pipeline.apply import executor

    monkeypatch.setattr(executor, "RUN_WINDOW", 3)
    drawn: list[int] = []

    def jobs():
        for k in range(10):
            drawn.append(k)
            yield k

    seen_when: dict[int, int] = {}

    def fn(plan, job):
        seen_when[job] = len(drawn)
        return plan + job

    with executor.Runner(10, Execution("threads", 2)) as runner:
        assert runner.run(100, jobs(), fn=fn) == [100 + k for k in range(10)]
    # job k ran before any job past the end of its window was drawn
    assert all(seen_when[k] <= min(10, (k // 3 + 1) * 3) for k in range(10))
    assert max(seen_when.values()) == 10 and seen_when[0] == 3


def _slow_job(folder: str, job: int) -> int:
    import time

    time.sleep(0.05)
    (Path(folder) / str(job)).write_text("done")
    return job * 10


def test_stream_on_processes_gives_outcomes_in_order_and_closing_leaves_nothing_running(tmp_path) -> None:
    """Worker processes get their tasks straight from the pool, a few ahead; the caller takes
    the outcomes in job order as they come (apply's single pass commits raw.zarr meanwhile).
    Closing the stream early cancels what has not started and waits for what has."""
    import itertools
    import time

    from pipeline.apply.executor import TASKS_AHEAD, Runner

    with Runner(100, Execution("processes", 2, direct_io=False)) as runner:
        assert runner.run(str(tmp_path), range(12), fn=_slow_job) == [10 * k for k in range(12)]
        folder = tmp_path / "early"
        folder.mkdir()
        stream = runner.stream(str(folder), range(200), fn=_slow_job)
        assert list(itertools.islice(stream, 3)) == [0, 10, 20]
        stream.close()
        done = sorted(int(p.name) for p in folder.iterdir())
        time.sleep(0.5)  # a task still running would write its file meanwhile
        assert sorted(int(p.name) for p in folder.iterdir()) == done
        # the three taken, and at most the tasks that were given to the pool ahead of them
        assert done[:3] == [0, 1, 2] and 3 <= len(done) <= 3 + TASKS_AHEAD * 2 + 1


def test_flight_size_hint_counts_files_of_nested_folders_up_to_the_limit(tmp_path) -> None:
    from pipeline.apply.execution import flight_size_hint

    assert flight_size_hint(tmp_path / "missing") == 0
    for k in range(3):  # an SD-card tree: SET/000/IMG_0000_1.tif ...
        folder = tmp_path / "0001SET" / f"00{k}"
        folder.mkdir(parents=True)
        for b in range(5):
            (folder / f"IMG_{k:04d}_{b + 1}.tif").write_bytes(b"x")
    (tmp_path / "frames.csv").write_text("file\n")
    assert flight_size_hint(tmp_path, limit=100) == 16
    assert flight_size_hint(tmp_path, limit=7) == 7
    assert flight_size_hint(tmp_path) == 16  # below AUTO_PROCESS_FRAMES: counted whole


def test_worker_server_is_started_only_for_a_pass_on_processes(monkeypatch) -> None:
    from pipeline.apply.execution import start_worker_server

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    assert not start_worker_server(Execution(), AUTO_PROCESS_FRAMES - 1)  # a short flight: threads
    assert not start_worker_server(Execution("threads"), 500)
    assert not start_worker_server(Execution(workers=1), 500)
    assert start_worker_server(Execution(), AUTO_PROCESS_FRAMES)
    assert start_worker_server(Execution(), 500)  # running already: nothing more


def test_worker_server_that_cannot_start_is_left_to_the_pass(monkeypatch) -> None:
    """Where the system cannot start the server (no socket folder, no processes left), the
    early start gives up quietly: the pass then runs on threads or says why
    (``test_where_worker_processes_cannot_start_...``)."""
    from pipeline.apply.execution import start_worker_server

    def cannot(*args: object) -> None:
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    monkeypatch.setattr("multiprocessing.forkserver.ensure_running", cannot)
    assert not start_worker_server(Execution(), 500)
    monkeypatch.setattr("multiprocessing.forkserver.ensure_running", lambda: None)
    assert start_worker_server(Execution(), 500)  # the same call where the server starts


def _worker_environment(plan, job) -> dict[str, str | None]:
    import os

    return {k: os.environ.get(k) for k in ("MSCAL_DIRECT_IO", "MSCAL_TEST_KEPT", "MSCAL_TEST_GONE")}


def test_worker_processes_take_the_settings_of_the_pass_not_of_their_server(monkeypatch) -> None:
    """The workers are forked from a server started earlier (by the command line before its
    imports, or by an earlier pass of the process) with the environment of that moment; a
    pass's ``--no-direct-io`` (and any other ``MSCAL_*`` setting) must still reach them."""
    from pipeline.apply.execution import start_worker_server
    from pipeline.apply.executor import Runner

    monkeypatch.setenv("MSCAL_DIRECT_IO", "1")
    monkeypatch.setenv("MSCAL_TEST_GONE", "set when the server started")
    start_worker_server(Execution("processes", 2), 100)
    monkeypatch.delenv("MSCAL_TEST_GONE")
    monkeypatch.setenv("MSCAL_TEST_KEPT", "set after")
    with Runner(100, Execution("processes", 2, direct_io=False)) as runner:
        assert runner.scheduler == "processes"
        seen = runner.run(None, range(4), fn=_worker_environment)
    assert seen == [{"MSCAL_DIRECT_IO": "0", "MSCAL_TEST_KEPT": "set after", "MSCAL_TEST_GONE": None}] * 4


def _tables_held(plan, job) -> int:
    from pipeline.apply.stores import loaded_calibrations

    return loaded_calibrations()


def test_workers_load_the_calibration_tables_as_they_start(small, tmp_path) -> None:
    """``Runner(calibration=...)``: every worker holds the store's Eq. 15 tables before its
    first frame (loaded while the main process makes the stores and the plan); without it
    none does; a store that cannot be read does not stop the workers (nothing is held: the
    frames' own load then raises its error)."""
    from pipeline.apply.executor import Runner

    _, calib = small
    with Runner(100, Execution("processes", 2), calibration=calib) as runner:
        assert runner.scheduler == "processes"
        assert runner.run(None, range(4), fn=_tables_held) == [1] * 4
    with Runner(100, Execution("processes", 2)) as runner:
        assert runner.run(None, range(2), fn=_tables_held) == [0, 0]
    with Runner(100, Execution("processes", 2), calibration=tmp_path / "missing.zarr") as runner:
        assert runner.run(None, range(2), fn=_tables_held) == [0, 0]


def test_server_import_path_is_this_process_path_in_order_with_folders_made_absolute(tmp_path, monkeypatch) -> None:
    from pipeline.apply.execution import server_import_path

    monkeypatch.chdir(tmp_path)
    (tmp_path / "lib").mkdir()
    hook = "__editable__.mscal-0.1.0.finder.__path_hook__"  # not a folder: kept as it is
    assert server_import_path(["", "lib", hook, "/no/such", str(tmp_path), "/no/such", "/a:b"]) == [
        str(tmp_path), str(tmp_path / "lib"), hook, "/no/such"]  # once each, in order; "a:b" cannot be given


PROBE = '''
import json, sys
from pipeline.apply.execution import Execution
from pipeline.apply.executor import Runner
import probe_fns
if __name__ == "__main__":
    with Runner(100, Execution("processes", 1)) as runner:
        assert runner.scheduler == "processes"
        seen = runner.run(None, [0], fn=probe_fns.imported)
    print(json.dumps({"main": probe_fns.imported(None, 0), "worker": seen[0]}))
'''

PROBE_FNS = '''
import sys
def imported(plan, job):
    return {m: getattr(sys.modules.get(m), "__file__", None) for m in ("pipeline.apply.executor", "mscal_core")}
'''


def test_workers_import_what_the_main_process_imports_whatever_the_current_folder(tmp_path) -> None:
    """Run from a folder holding folders named ``pipeline`` and ``mscal_core`` (a user's own
    project, another checkout), the worker processes ran that code: their server is a new
    interpreter whose import path began with the current folder."""
    import subprocess
    import sys

    import pipeline

    here = tmp_path / "project"  # the current folder, with look-alike packages
    for pkg in ("pipeline", "pipeline/apply", "mscal_core"):
        (here / pkg).mkdir(parents=True)
        (here / pkg / "__init__.py").write_text("DECOY = True\n")
    (here / "pipeline" / "apply" / "executor.py").write_text("DECOY = True\n")
    tool = tmp_path / "tool"  # the script's folder (as the ``mscal`` entry point's)
    tool.mkdir()
    (tool / "probe.py").write_text(PROBE)
    (tool / "probe_fns.py").write_text(PROBE_FNS)
    env = {**os.environ, "PYTHONPATH": str(Path(pipeline.__file__).resolve().parents[1])}
    done = subprocess.run([sys.executable, str(tool / "probe.py")], cwd=here, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["worker"] == seen["main"]
    assert all(f is not None and not f.startswith(str(here)) for f in seen["main"].values()), seen


def _twice(plan, job) -> int:
    return 2 * job


def test_where_worker_processes_cannot_start_auto_runs_on_threads_and_processes_are_refused(monkeypatch,
                                                                                             caplog) -> None:
    from mscal_core.errors import ProcessesUnavailable
    from pipeline.apply.executor import Runner

    monkeypatch.setattr("pipeline.storage.process.ProcessPoolExecutor", NoSemaphores)
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    with caplog.at_level("WARNING"), Runner(100, Execution()) as runner:  # auto would take processes
        assert (runner.scheduler, runner.workers, runner.pool) == ("threads", 2, None)
        assert runner.execution["scheduler"] == "threads"  # run.json says what ran
        assert runner.run(None, range(4), fn=_twice) == [0, 2, 4, 6]
    assert "worker processes cannot start on this system (OSError: [Errno 38] Function not implemented): " \
           "running on 2 threads instead" in caplog.text
    with pytest.raises(ProcessesUnavailable) as refused:
        Runner(100, Execution("processes", 2))  # asked for: refused, saying what to do
    assert str(refused.value) == ("worker processes cannot start on this system (OSError: [Errno 38] Function not "
                                  "implemented) (run on threads: --scheduler threads, or MSCAL_APPLY_SCHEDULER=threads)")
