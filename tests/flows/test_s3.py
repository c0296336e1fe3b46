"""``mscal run s3://... -o s3://...``: against moto's S3 server started here on loopback;
outputs identical to the local-disk run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import requests

from pipeline.run.cli import main

from .conftest import FLIGHTS, assert_same_flight_outputs

pytestmark = pytest.mark.xdist_group("flows")

BUCKET = "mscal-test"


@pytest.fixture()
def s3(monkeypatch: pytest.MonkeyPatch):
    """An S3 file system on a fresh moto server at 127.0.0.1, endpoint and dummy keys in the env."""
    import s3fs
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    for k, v in {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                 "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": f"http://{host}:{port}"}.items():
        monkeypatch.setenv(k, v)
    s3fs.S3FileSystem.clear_instance_cache()
    fs = s3fs.S3FileSystem()
    fs.mkdir(BUCKET)
    yield fs
    s3fs.S3FileSystem.clear_instance_cache()
    requests.post(f"http://{host}:{port}/moto-api/reset", timeout=30)  # moto's state is per process
    server.stop()


def test_s3_session_and_outputs_match_the_local_run(s3, flow_session: Path, first_run: Path, tmp_path: Path) -> None:
    files = sorted(p for p in flow_session.rglob("*") if p.is_file())
    s3.put([str(p) for p in files], [f"{BUCKET}/in/session/{p.relative_to(flow_session).as_posix()}" for p in files])
    work = tmp_path / "work"
    assert main(["run", f"s3://{BUCKET}/in/session", "-o", f"s3://{BUCKET}/out/run1", "--work-dir", str(work)]) == 0

    run = json.loads(s3.cat(f"{BUCKET}/out/run1/run.json"))
    assert run["session"] == f"s3://{BUCKET}/in/session" and run["out"] == f"s3://{BUCKET}/out/run1"
    assert run["calibration_cached"] is True  # same content as the local session: same keys
    assert run["timings_s"]["stage_in"] > 0
    local = tmp_path / "downloaded"
    remote = s3.find(f"{BUCKET}/out/run1")
    prefix = f"{BUCKET}/out/run1/"
    targets = [local / r[len(prefix):] for r in remote]
    for t in {t.parent for t in targets}:
        t.mkdir(parents=True, exist_ok=True)
    s3.get(remote, [str(t) for t in targets])
    assert (local / "calibration.zarr" / "zarr.json").is_file()
    for name in FLIGHTS:
        assert_same_flight_outputs(first_run / "flights" / name, local / "flights" / name)
        assert json.loads((local / "flights" / name / "run.json").read_text())["frames_out"] == 3


def test_a_missing_s3_session_is_one_line_and_exit_2(s3, tmp_path: Path, capsys) -> None:
    assert main(["run", f"s3://{BUCKET}/nothing-here", "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"mscal: error: s3://{BUCKET}/nothing-here: no files found "
                   "(check the URL and the storage credentials)"]
