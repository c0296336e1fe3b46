"""``mscal run --dask-address``: a real ``dask scheduler`` and two ``dask worker`` processes
on loopback, started here; outputs must be identical to the local run's."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.run.cli import main

from .conftest import FLIGHTS, assert_same_flight_outputs

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("flows")]

DASK = str(Path(sys.executable).with_name("dask"))


def _wait_for(path: Path, procs: list[subprocess.Popen], timeout: float = 90) -> None:
    end = time.monotonic() + timeout
    while not path.is_file():
        dead = [p.args for p in procs if p.poll() is not None]
        assert not dead, f"exited early: {dead}"
        assert time.monotonic() < end, f"no {path} after {timeout} s"
        time.sleep(0.2)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``tcp://127.0.0.1:PORT`` of a scheduler with two single-threaded workers."""
    from distributed import Client

    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--scheduler-file", str(sched_file), *common],
                              stdout=subprocess.DEVNULL, stderr=(tmp / "scheduler.log").open("w"))]
    try:
        _wait_for(sched_file, procs)
        for i in range(2):
            procs.append(subprocess.Popen(
                [DASK, "worker", "--scheduler-file", str(sched_file), "--host", "127.0.0.1", "--nthreads", "1",
                 "--local-directory", str(tmp / f"w{i}"), *common],
                stdout=subprocess.DEVNULL, stderr=(tmp / f"worker{i}.log").open("w")))
        address = json.loads(sched_file.read_text())["address"]
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.fixture(scope="module")
def cluster_run(cluster: str, flow_session: Path, first_run: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dask-run") / "out"
    assert main(["run", str(flow_session), "-o", str(out), "--dask-address", cluster]) == 0
    return out


def _frame_compute_seconds(cluster: str) -> float:
    """Compute seconds of every ``process_frames`` task the scheduler has seen."""
    from distributed import Client

    def seconds(dask_scheduler) -> float:
        tp = dask_scheduler.task_prefixes.get("process_frames")
        return 0.0 if tp is None else tp.all_durations["compute"]

    with Client(cluster, timeout="30s") as client:
        return client.run_on_scheduler(seconds)


# The two `mscal run --dask-address` tests share a second full run (~40 s beyond the local one):
# make test-long. make test keeps the cluster through the factory apply test below (same
# executor: outputs identical to a local run, frames computed on the workers).
@pytest.mark.long
def test_cluster_run_outputs_are_identical_to_the_local_run(cluster_run: Path, first_run: Path, cluster: str) -> None:
    run = json.loads((cluster_run / "run.json").read_text())
    assert run["dask_address"] == cluster
    assert run["calibration_cached"] is True
    for name in FLIGHTS:
        assert run["flights"][name]["computed_on"] == f"dask scheduler {cluster}"
        assert run["flights"][name]["frames_out"] == 3
        assert_same_flight_outputs(first_run / "flights" / name, cluster_run / "flights" / name)


@pytest.mark.long
def test_cluster_run_computed_its_frames_on_the_cluster_workers(cluster_run: Path, cluster: str) -> None:
    """apply's per-frame tasks ran on the scheduler's workers (the default client's), not
    in the flow's process. Needs apply to use an active distributed client (lead's change)."""
    assert _frame_compute_seconds(cluster) > 0


@pytest.mark.long  # 27 s; the MicaSense factory apply on the cluster stays in make test
def test_cluster_run_of_a_multilens_session(cluster: str, multilens_session, tmp_path, monkeypatch) -> None:
    """--dask-address takes any camera: the one-file-per-band captures of a
    MicaSense session are computed on the cluster's workers, with the same outputs as a
    local ``mscal apply`` of the flight."""
    session, cache = multilens_session
    monkeypatch.setenv("MSCAL_CACHE_DIR", str(cache))
    out = tmp_path / "out"
    assert main(["run", str(session), "-o", str(out), "--dask-address", cluster]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["flights"]["field"]["computed_on"] == f"dask scheduler {cluster}"
    assert run["flights"]["field"]["frames_out"] == 2
    flight = json.loads((out / "flights" / "field" / "run.json").read_text())
    assert flight["scheduler"] == "distributed"
    alone = tmp_path / "alone"
    assert main(["apply", str(session / "flights" / "field"), "--calibration", str(out / "calibration.zarr"),
                 "-o", str(alone)]) == 0
    assert json.loads((alone / "run.json").read_text())["scheduler"] != "distributed"
    assert_same_flight_outputs(out / "flights" / "field", alone)


def test_factory_apply_runs_on_the_cluster(cluster: str, tmp_path) -> None:
    """The factory chain goes through the same executor, so under a distributed client its
    captures are computed on the cluster, with the outputs of a local run."""
    from distributed import Client

    from pipeline.apply.factory import FactoryOptions, apply_factory
    from tests.micasense_data import require_data

    opts = FactoryOptions(panel_reflectance="micasense-rp02-1603036-sc")
    before = _frame_compute_seconds(cluster)
    with Client(cluster, timeout="30s"):
        remote = apply_factory(require_data(), tmp_path / "remote", opts)
    assert _frame_compute_seconds(cluster) > before  # its captures were computed on the workers
    local = apply_factory(require_data(), tmp_path / "local", opts)
    assert remote.run["scheduler"] == "distributed" and local.run["scheduler"] != "distributed"
    assert remote.run["frames_out"] == local.run["frames_out"] == 2
    assert_same_flight_outputs(tmp_path / "remote", tmp_path / "local")


def test_a_card_session_runs_on_the_cluster(cluster: str, tmp_path) -> None:
    """``mscal run CARD --dask-address``: a flight folder off the card (no field session) is
    computed on the cluster's workers, with the outputs of a local factory apply."""
    import shutil

    from pipeline.apply.factory import FactoryOptions, apply_factory
    from tests.micasense_data import require_data

    card = tmp_path / "card" / "0000SET" / "000"
    card.mkdir(parents=True)
    for f in sorted(require_data().glob("IMG_000*_*.tif")):
        shutil.copy(f, card / f.name)
    before = _frame_compute_seconds(cluster)
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "card"), "-o", str(out), "--dask-address", cluster]) == 0
    assert _frame_compute_seconds(cluster) > before
    run = json.loads((out / "run.json").read_text())
    assert run["kind"] == "card" and run["dask_address"] == cluster
    assert run["flights"]["0000SET"]["computed_on"] == f"dask scheduler {cluster}"
    apply_factory(tmp_path / "card" / "0000SET", tmp_path / "local", FactoryOptions(camera="micasense-rededge"))
    assert_same_flight_outputs(out / "flights" / "0000SET", tmp_path / "local")
