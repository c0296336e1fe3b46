"""When ``mscal apply`` returns, no process it started is alive: the worker processes, their
server (the forkserver) and multiprocessing's resource tracker are ended and waited for, not
left to notice the command's end when its process exits."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.micasense_data import require_data

# Run in a process of its own: what the command leaves behind is what that process's children are.
SCRIPT = """
import json, sys
import psutil
from pipeline.run.cli import main

def children():
    return [" ".join(c.cmdline())[:120] for c in psutil.Process().children(recursive=True)]

if __name__ == "__main__":
    rc = main(["apply", sys.argv[1], "--calibration", "factory", "-o", sys.argv[2], "--scheduler", "processes",
               "--workers", "2", "--no-direct-io"])
    after = children()
    from multiprocessing import forkserver, resource_tracker
    print(json.dumps({"rc": rc, "after": after, "server": forkserver._forkserver._forkserver_pid,
                      "tracker": resource_tracker._resource_tracker._pid}))
"""


def test_apply_on_worker_processes_leaves_no_process_behind(tmp_path: Path) -> None:
    import pipeline

    data = require_data()
    (tmp_path / "probe.py").write_text(SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(Path(pipeline.__file__).resolve().parents[1])}  # this checkout's code
    done = subprocess.run([sys.executable, str(tmp_path / "probe.py"), str(data), str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert seen["rc"] == 0 and run["frames_out"] == 2
    assert run["scheduler"] == "processes" and run["execution"]["workers"] == 2  # the pass ran on worker processes
    assert seen["after"] == [] and seen["server"] is None and seen["tracker"] is None
    assert "leaked" not in done.stderr  # the tracker had no semaphore left to clean up
