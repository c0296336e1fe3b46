"""pipeline.run.runner and pipeline.run.inbox without Prefect: cache keys, staging, inbox state."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import fsspec
import pytest

from mscal_core.errors import FitError, InputError, SessionError
from pipeline.ingest.session import load_session
from pipeline.run import inbox, runner

SESSION_YAML = """\
camera: ximea-mq022hg-sm5x5-nir
intrinsics: {fx: 436.0, fy: 436.0, cx: 204.0, cy: 108.0, dist: [-0.12, 0.05, 0.0012, -0.0008, 0.0]}
reflector: {reflectance: 0.5, size_m: [0.5, 0.5]}
marker: {dictionary: DICT_4X4_50, id: 3, size_m: 0.1}
"""


@pytest.fixture()
def session(tmp_path: Path) -> Path:
    """A session folder whose frames are stand-in bytes: cache keys only hash files."""
    root = tmp_path / "session"
    for folder in ("response", "vignetting", "reflector", "flights/a"):
        (root / folder).mkdir(parents=True)
        (root / folder / "frames.csv").write_text("file,exposure_ms\nf0.tif,1\n")
        (root / folder / "f0.tif").write_bytes(folder.encode())
    (root / "session.yaml").write_text(SESSION_YAML)
    return root


def _keys(session: Path, method: str = "forward") -> list[str]:
    return list(runner.stage_keys(load_session(session), method).values())


@pytest.mark.parametrize(
    "change, changed",
    [
        ("reflector/f0.tif", [False, False, True]),
        ("vignetting/f0.tif", [False, True, True]),
        ("response/f0.tif", [True, True, True]),
        ("flights/a/f0.tif", [False, False, False]),
    ],
)
def test_a_changed_input_changes_the_keys_of_exactly_the_stages_that_depend_on_it(
        session: Path, change: str, changed: list[bool]) -> None:
    before = _keys(session)
    (session / change).write_bytes(b"other content")
    after = _keys(session)
    assert [a != b for a, b in zip(before, after)] == changed


def test_session_yaml_and_method_enter_the_keys_where_they_matter(session: Path) -> None:
    before = _keys(session)
    (session / "session.yaml").write_text(SESSION_YAML.replace("id: 3", "id: 4"))
    assert [a != b for a, b in zip(before, _keys(session))] == [False, True, True]
    assert all(a != b for a, b in zip(_keys(session), _keys(session, "alternating")))


def test_products_in_session_yaml_change_no_key(session: Path) -> None:
    """What apply writes is no input of a fit: session.yaml's products key (or a comment)
    leaves every stage's key as it was."""
    before = _keys(session)
    (session / "session.yaml").write_text(SESSION_YAML + "# apply's choice\nproducts: {indices: [ndre], tiffs: false}\n")
    assert _keys(session) == before


def test_plan_finds_cached_stores_and_chains_partials(session: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    plan = runner.plan_calibration(session, cache)
    assert [s.name for s in plan.stages] == ["response", "vignetting", "illumination"]
    assert not plan.cached and [s.cached for s in plan.stages] == [False] * 3
    assert [s.partial for s in plan.stages] == [None, plan.stages[0].store, plan.stages[1].store]
    assert plan.final_store == plan.stages[2].store
    import numpy as np
    import xarray as xr

    from pipeline.storage.store import STORE_FORMAT, write_store

    store = xr.Dataset({"inverse_response": (("band", "dn"), np.zeros((1, 4), "float32"))},
                       attrs={"format": STORE_FORMAT, "camera": "x"})
    for s in plan.stages[:2]:  # as a finished write_store leaves them
        write_store(store, s.store)
    Path(plan.stages[2].store).mkdir(parents=True)  # a damaged store: its metadata and nothing else
    (Path(plan.stages[2].store) / "zarr.json").write_text("{}")
    again = runner.plan_calibration(session, cache)
    assert [s.cached for s in again.stages] == [True, True, False] and not again.cached


def test_a_missing_calibration_folder_is_named(session: Path, tmp_path: Path) -> None:
    (session / "vignetting" / "f0.tif").unlink()
    (session / "vignetting" / "frames.csv").unlink()
    (session / "vignetting").rmdir()
    with pytest.raises(SessionError, match="vignetting: calibration folder not found"):
        runner.plan_calibration(session, tmp_path / "cache")


def test_configure_prefect_keeps_what_is_set(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import sys

    monkeypatch.delitem(sys.modules, "prefect", raising=False)
    for k in ("PREFECT_HOME", "PREFECT_SERVER_ANALYTICS_ENABLED", "DO_NOT_TRACK",
              "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("MSCAL_CACHE_DIR", str(tmp_path / "c"))
    monkeypatch.setenv("DO_NOT_TRACK", "0")
    home = runner.configure_prefect()
    assert home == tmp_path / "c" / "prefect" and home.is_dir()
    assert os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] == "false"
    assert os.environ["DO_NOT_TRACK"] == "0"
    assert float(os.environ["PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"]) >= 60


def test_transient_errors_are_io_errors_only() -> None:
    assert runner.is_transient(ConnectionResetError("reset"))
    assert runner.is_transient(TimeoutError())
    assert not runner.is_transient(FileNotFoundError("x"))
    assert not runner.is_transient(InputError("bad"))
    assert not runner.is_transient(FitError("no fit"))
    assert not runner.is_transient(ValueError("bug"))


def test_remote_urls_are_staged_and_local_paths_are_not(tmp_path: Path) -> None:
    assert runner.is_remote("s3://b/p") and runner.is_remote("memory://x")
    assert not runner.is_remote("/data/s") and not runner.is_remote("file:///data/s")
    local = runner.run_paths("/data/s", "/data/o")
    assert (local.session, local.out, local.work) == ("/data/s", "/data/o", None)
    mixed = runner.run_paths("s3://b/s", "/data/o", str(tmp_path / "w"))
    assert (mixed.session, mixed.out) == (str(tmp_path / "w" / "session"), "/data/o")
    assert not mixed.work_is_temporary


def test_stage_in_and_upload_round_trip_with_run_json_last(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fs = fsspec.filesystem("memory")
    fs.pipe({"/src/session.yaml": b"camera: x\n", "/src/flights/a/f.tif": b"\x01\x02"})
    staged = runner.stage_in("memory://src", tmp_path / "staged")
    assert sorted(str(p.relative_to(staged)) for p in staged.rglob("*") if p.is_file()) == \
        ["flights/a/f.tif", "session.yaml"]
    assert (staged / "flights/a/f.tif").read_bytes() == b"\x01\x02"

    out = tmp_path / "out"
    (out / "flights/a").mkdir(parents=True)
    (out / "flights/a/r.bin").write_bytes(b"r")
    (out / "run.json").write_text('{"new": true}')
    fs.pipe("/dst/run.json", b'{"old": true}')
    calls: list[str] = []
    real_put_file = type(fs).put_file
    monkeypatch.setattr(type(fs), "put_file", lambda self, lp, rp, *a, **k: (calls.append(rp), real_put_file(self, lp, rp, *a, **k))[1])
    assert runner.upload(out, "memory://dst") == 2
    assert calls[-1].endswith("dst/run.json") and len(calls) == 2
    assert fs.cat("/dst/run.json") == b'{"new": true}' and fs.cat("/dst/flights/a/r.bin") == b"r"


def test_a_failed_upload_leaves_no_run_json_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fs = fsspec.filesystem("memory")
    fs.pipe("/dst2/run.json", b'{"old": true}')
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.bin").write_bytes(b"a")
    (out / "run.json").write_text("{}")

    def broken(self, *a, **k):
        raise ConnectionError("network down")

    monkeypatch.setattr(type(fs), "put", broken)
    with pytest.raises(ConnectionError):
        runner.upload(out, "memory://dst2")
    assert not fs.exists("/dst2/run.json")


def test_run_record_and_its_summary(session: Path, tmp_path: Path) -> None:
    plan = runner.plan_calibration(session, tmp_path / "cache")
    t = runner.Timings()
    with t.step("fit_response"):
        time.sleep(0.01)
    flights = {"a": {"frames_in": 4, "frames_out": 3, "quarantined": [{"file": "x.tif", "reason": "x.tif: truncated"}],
                     "saturated_pixels": 7, "up_to_date": False, "seconds": 1.5}}
    rec = runner.run_record(session="s3://b/s", out="/o", plan=plan, flights=flights, timings=t, dask_address=None)
    assert rec["calibration_cached"] is False and rec["fitted"] == ["response", "vignetting", "illumination"]
    assert rec["calibration_stages"]["response"]["seconds"] >= 0.01
    assert rec["flights"]["a"]["outputs"] == "flights/a/"
    assert rec["timings_s"]["total"] >= rec["timings_s"]["fit_response"]
    path = runner.write_run_json(tmp_path / "o", rec)
    assert json.loads(path.read_text()) == rec
    md = runner.summary_markdown(rec)
    assert "| a | 3 / 4 | 1 | 7 | 1.5 s |" in md and "calibration: fitted" in md


# --------------------------------------------------------------------------- inbox


def _session_folder(root: Path, name: str, ready: bool) -> Path:
    d = root / name
    (d / "response").mkdir(parents=True)
    (d / "session.yaml").write_text(SESSION_YAML)
    (d / "response" / "f.tif").write_bytes(b"f")
    if ready:
        (d / inbox.READY).write_text("")
    return d


def test_complete_means_ready_file_or_settled(tmp_path: Path) -> None:
    d = _session_folder(tmp_path, "s", ready=False)
    now = time.time()
    assert not inbox.is_complete(d, 600, now)
    assert inbox.is_complete(d, 600, now + 601)
    (d / inbox.READY).write_text("")
    assert inbox.is_complete(d, 600, now)
    (d / "session.yaml").unlink()  # a card folder needs none
    assert inbox.is_complete(d, 600, now)
    (d / "response" / "f.tif").unlink()
    assert not inbox.is_complete(d, 600, now + 10_000)  # nothing but READY
    assert inbox.incomplete_reason(d, 600, now) == "empty folder: nothing to process"


def test_what_is_not_processed_is_named_with_the_reason(tmp_path: Path) -> None:
    box = tmp_path / "inbox"
    _session_folder(box, "ready", ready=True)
    fresh = _session_folder(box, "copying", ready=False)
    (box / "empty").mkdir()
    (box / "stray.tif").write_bytes(b"x")
    (box / ".hidden").write_text("")
    now = time.time()
    for p in fresh.rglob("*"):
        os.utime(p, (now - 42, now - 42))
    assert inbox.waiting(box, 600, now) == {
        "copying": "still being copied: a file was modified 42 s ago and there is no READY file; processed once "
                   "nothing changed for 600 s (or once READY is written)",
        "empty": "empty folder: nothing to process",
        "stray.tif": "a file, not a folder: put each flight or session in a folder of its own in the inbox",
    }
    out = tmp_path / "out"
    inbox.record_waiting(out, inbox.waiting(box, 600, now))
    assert sorted(inbox.load_waiting(out)) == ["copying", "empty", "stray.tif"]
    inbox.record(out, "ready", listing="l", content="c", status="done")
    assert sorted(inbox.load_waiting(out)) == ["copying", "empty", "stray.tif"]  # kept beside the sessions
    assert inbox.load_state(out)["ready"]["status"] == "done"


def test_pending_sessions_and_the_state_file(tmp_path: Path) -> None:
    box, out = tmp_path / "inbox", tmp_path / "out"
    a = _session_folder(box, "a", ready=True)
    _session_folder(box, "b", ready=False)
    pending = inbox.pending_sessions(box, out, 600)
    assert [p.name for p in pending] == ["a"]
    p = pending[0]
    inbox.record(out, p.name, listing=p.listing, content=p.content, status="done")
    assert inbox.pending_sessions(box, out, 600) == []
    os.utime(a / "response" / "f.tif", (time.time() + 5, time.time() + 5))  # touched, same content
    assert inbox.pending_sessions(box, out, 600) == []
    assert inbox.load_state(out)["a"]["listing"] == inbox.listing_fingerprint(a)  # refreshed
    (a / "response" / "f.tif").write_bytes(b"changed")
    assert [p.name for p in inbox.pending_sessions(box, out, 600)] == ["a"]


def test_a_corrupt_state_file_is_named(tmp_path: Path) -> None:
    (tmp_path / inbox.STATE_FILE).write_text("{not json")
    with pytest.raises(InputError, match=r"\.mscal-serve\.json: cannot read the serve state"):
        inbox.load_state(tmp_path)


def test_next_time_follows_the_cron_expression() -> None:
    from datetime import datetime

    assert inbox.next_time("*/15 * * * *", datetime(2026, 5, 1, 10, 7)) == datetime(2026, 5, 1, 10, 15)
    assert inbox.next_time("0 6 * * *", datetime(2026, 5, 1, 10, 7)) == datetime(2026, 5, 2, 6, 0)
    with pytest.raises(InputError, match="not a cron expression"):
        inbox.next_time("sometimes", datetime(2026, 5, 1))
