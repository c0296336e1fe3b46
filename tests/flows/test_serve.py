"""``mscal serve --once``: complete sessions of an inbox processed once, restarts included."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import pytest

from pipeline.run.cli import main
from pipeline.run.inbox import READY, STATE_FILE

pytestmark = pytest.mark.xdist_group("flows")


def _serve(inbox: Path, root: Path) -> int:
    return main(["serve", "--inbox", str(inbox), "-o", str(root), "--once", "--settle-seconds", "600"])


def _state(root: Path) -> dict:
    return json.loads((root / STATE_FILE).read_text())["sessions"]


@pytest.mark.long  # ~52 s (a serve process, its own Prefect server, two sessions, restarts): make test-long
def test_serve_processes_complete_sessions_once_and_survives_restarts(
        flow_session: Path, first_run: Path, tmp_path: Path, capsys) -> None:
    inbox, root = tmp_path / "inbox", tmp_path / "processed"
    ready = inbox / "monday"
    shutil.copytree(flow_session, ready)
    (ready / READY).write_text("")
    uploading = inbox / "tuesday"  # just copied, no READY: still being uploaded
    shutil.copytree(flow_session, uploading)
    (inbox / "empty").mkdir()  # no session.yaml at all
    broken = inbox / "broken"  # complete, but its session.yaml names no camera
    broken.mkdir()
    (broken / "session.yaml").write_text("camera: no-such-camera\n")
    (broken / READY).write_text("")

    assert _serve(inbox, root) == 0  # a failed session does not stop the others
    out = capsys.readouterr().out
    assert "monday: done" in out and "broken: failed" in out
    state = _state(root)
    assert sorted(state) == ["broken", "monday"] and state["monday"]["status"] == "done"
    assert state["broken"]["status"] == "failed"
    assert len(state["monday"]["content_sha256"]) == 64
    run = json.loads((root / "monday" / "run.json").read_text())
    assert run["calibration_cached"] is True and sorted(run["flights"]) == ["field", "orchard"]
    assert not (root / "tuesday").exists()
    stamp = (root / "monday" / "run.json").stat().st_mtime_ns

    logs = sorted((root / "logs").iterdir())
    assert len(logs) == 1 and logs[0].name.endswith("-serve.log")  # the look that processed sessions

    # a restart: nothing new is complete, nothing is processed again, and no log is kept of it
    assert _serve(inbox, root) == 0
    assert capsys.readouterr().out == ""
    assert sorted((root / "logs").iterdir()) == logs
    assert (root / "monday" / "run.json").stat().st_mtime_ns == stamp

    # tuesday settles (nothing modified for longer than --settle-seconds); monday is copied
    # again with the same content (new modification times): only tuesday is processed
    old = time.time() - 3600
    for p in uploading.rglob("*"):
        os.utime(p, (old, old))
    for p in ready.rglob("*"):
        os.utime(p, None)
    assert _serve(inbox, root) == 0
    lines = capsys.readouterr().out.splitlines()  # the session, then its report's warnings
    assert lines[0] == f"tuesday: done -> {root / 'tuesday'}" and all(ln.startswith("  ") for ln in lines[1:])
    assert sorted(_state(root)) == ["broken", "monday", "tuesday"]
    assert (root / "monday" / "run.json").stat().st_mtime_ns == stamp
    assert (root / "tuesday" / "run.json").is_file()
    # OUT_ROOT's STAC catalog gained each session's flights as they were processed
    items = sorted(str(p.relative_to(root / "stac")) for p in (root / "stac").glob("*/items/*.json"))
    assert items == [f"processed/items/{d}__{f}.json" for d in ("monday", "tuesday") for f in ("field", "orchard")]


def test_serve_rejects_a_bad_cron_and_a_missing_inbox(tmp_path: Path, capsys) -> None:
    assert main(["serve", "--inbox", str(tmp_path), "-o", str(tmp_path / "o"), "--cron", "every hour"]) == 2
    assert "--cron 'every hour' is not a cron expression" in capsys.readouterr().err
    assert main(["serve", "--inbox", str(tmp_path / "nope"), "-o", str(tmp_path / "o"), "--once"]) == 2
    assert "inbox folder not found" in capsys.readouterr().err
