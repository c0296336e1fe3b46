"""The apply worker server freezes what it imported (``gc.freeze``), and nothing else does."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pipeline.apply.execution import SERVER_MODULE, WORKER_MODULE, worker_context
from pipeline.apply.worker_server import SERVER_ENV

ROOT = Path(__file__).resolve().parents[3]
PROBE = ("import gc; n = gc.get_freeze_count(); import pipeline.apply.worker_server; "
         "print(n, gc.get_freeze_count())")


def _freeze_counts(env_value: str | None) -> tuple[int, int]:
    env = {k: v for k, v in os.environ.items() if k != SERVER_ENV}
    if env_value is not None:
        env[SERVER_ENV] = env_value
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    before, after = (int(x) for x in out.stdout.split())
    return before, after


def test_the_module_freezes_only_in_the_server() -> None:
    before, after = _freeze_counts("1")
    assert before == 0 and after > 1000  # every object of the imports so far, out of the collector's reach
    assert _freeze_counts(None) == (0, 0)
    assert _freeze_counts("0") == (0, 0)


def test_the_server_imports_the_worker_module_first_then_freezes(monkeypatch) -> None:
    from multiprocessing import forkserver

    started = []
    monkeypatch.setattr("pipeline.apply.execution.ensure_worker_server", lambda: started.append(1))
    worker_context()
    assert started == [1]
    assert forkserver._forkserver._preload_modules == [WORKER_MODULE, SERVER_MODULE]


def test_the_server_starts_with_the_variable_and_this_process_keeps_its_own(monkeypatch) -> None:
    from multiprocessing import forkserver

    from pipeline.apply.execution import ensure_worker_server

    seen = []
    monkeypatch.delenv(SERVER_ENV, raising=False)
    monkeypatch.setattr(forkserver, "ensure_running", lambda: seen.append(os.environ.get(SERVER_ENV)))
    ensure_worker_server()
    assert seen == ["1"] and SERVER_ENV not in os.environ  # set for the server's start only
