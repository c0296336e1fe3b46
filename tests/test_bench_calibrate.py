"""bench/bench_calibrate.py's markdown section writer (no benchmark is run here)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "bench_calibrate.py"


def _load():
    spec = importlib.util.spec_from_file_location("bench_calibrate_under_test", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


bench = _load()


def test_import_has_no_side_effects() -> None:
    code = (
        "import importlib.util, sys\n"
        f"spec = importlib.util.spec_from_file_location('b', {str(SCRIPT)!r})\n"
        "m = importlib.util.module_from_spec(spec); sys.modules['b'] = m; spec.loader.exec_module(m)\n"
        "heavy = [k for k in ('pipeline.sim.synth', 'pipeline.calibrate.fit', 'xarray', 'cv2') if k in sys.modules]\n"
        "print(heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.strip() == "[]"
    assert out.stderr == ""


def test_replace_section_replaces_only_its_section() -> None:
    start, end = bench.markers()
    qs, qe = bench.markers(bench.QUICK_SECTION_KEY)
    before = "# Benchmarks\n\nIntro text.\n\n## Other benchmark\n\n| a | b |\n|---|---|\n| 1 | 2 |\n\n"
    middle = f"\n\n{qs}\nquick figures\n{qe}\n\n## Yet another\n\nkept.\n"
    text = before + f"{start}\nold figures\nmore old lines\n{end}" + middle
    new = bench.replace_section(text, "## Calibration benchmark\n\nnew figures\n")
    assert new == before + f"{start}\n## Calibration benchmark\n\nnew figures\n{end}" + middle
    assert "old figures" not in new
    # Running again with the same body is a fixed point; the other marked section is untouched.
    assert bench.replace_section(new, "## Calibration benchmark\n\nnew figures\n") == new
    assert bench.replace_section(new, "quick 2", bench.QUICK_SECTION_KEY).count("new figures") == 1


def test_replace_section_appends_when_absent_and_creates_header() -> None:
    start, end = bench.markers()
    assert bench.replace_section("", "body") == f"# Benchmarks\n\n{start}\nbody\n{end}\n"
    assert bench.replace_section("# B\n\nother\n", "body") == f"# B\n\nother\n\n{start}\nbody\n{end}\n"


def test_replace_section_refuses_unbalanced_markers() -> None:
    start, _ = bench.markers()
    with pytest.raises(ValueError, match="unbalanced"):
        bench.replace_section(f"# B\n{start}\nhalf a section\n", "body")


def test_write_section_keeps_other_sections(tmp_path: Path) -> None:
    path = tmp_path / "docs" / "benchmarks.md"
    bench.write_section(path, "first run")
    path.write_text(path.read_text() + "\n## Hand-written notes\n\nkeep me\n")
    bench.write_section(path, "second run")
    text = path.read_text()
    assert "second run" in text and "first run" not in text
    assert text.endswith("## Hand-written notes\n\nkeep me\n")
    assert not list(path.parent.glob("*.tmp"))


def test_run_measured_counts_the_worker_processes_a_command_leaves_behind() -> None:
    """A command whose worker process outlives it (as ``mscal apply``'s forkserver pool can):
    the worker's CPU is in the figures (the launcher is a subreaper and reaps it) and
    its memory is in the peak (the tree's summed PSS, sampled while the command runs)."""
    worker = ("import time, numpy as np\n"
              "a = np.ones(200 * 2**20, np.uint8)\n"  # 200 MiB, touched
              "print('ready', flush=True)\n"
              "t = time.process_time()\n"
              "while time.process_time() - t < 0.6: pass\n")
    command = ("import subprocess, sys, time\n"
               f"p = subprocess.Popen([sys.executable, '-c', {worker!r}], stdout=subprocess.PIPE)\n"
               "p.stdout.readline()\n"
               "time.sleep(0.8)\n"
               "sys.exit(0)\n")  # without waiting for the worker: it is left to the launcher
    run = bench.run_measured([sys.executable, "-c", command], timeout=120)
    assert run.returncode == 0
    assert run.cpu_s >= 0.6  # the command itself uses < 0.2 s
    assert run.maxrss_mib >= 200


def test_scaling_lines_read_the_two_worker_counts_as_amdahl() -> None:
    """1 worker 20 s, 2 workers 11 s: 18 s spread over workers, 2 s do not; 4 cores 6.5 s."""
    from types import SimpleNamespace

    def seed(one: float, two: float) -> SimpleNamespace:
        return SimpleNamespace(one_worker=SimpleNamespace(wall_s=one), fastest=SimpleNamespace(wall_s=two))

    (line,) = bench._scaling_lines([seed(20.0, 11.0), seed(18.0, 9.5)])
    assert "took 9.5-11.0 s wall (target 10 s on 2 cores: FAIL)" in line
    assert "2 workers are 1.82-1.89x faster" in line
    assert "1.0-2.0 s do not spread" in line and "17.0-18.0 s do (the band fits)" in line
    assert "expected 5.2-6.5 s on 4 cores" in line
    (ok,) = bench._scaling_lines([seed(18.0, 9.5)])
    assert "target 10 s on 2 cores: PASS" in ok
    assert bench._scaling_lines([SimpleNamespace(one_worker=None, fastest=SimpleNamespace(wall_s=9.0))]) == []


def test_varied_table_gives_each_session_and_the_spread() -> None:
    """``--varied``: one column per session, then min / median / max over them, and the verdict
    against the target on the worst."""
    spec = importlib.util.spec_from_file_location("calibrate_varied_under_test", SCRIPT.parent / "calibrate_varied.py")
    varied = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = varied
    spec.loader.exec_module(varied)
    rows = [varied.bc.Row("wall (s)", [9.1, 12.0, 8.0], 10.0, "{:.1f}"),
            varied.bc.Row("CPU (s)", [14.0, float("nan"), 13.0], None, "{:.1f}")]
    lines = varied.table(rows, [0, 1, 2]).splitlines()
    assert lines[0] == "| figure | session 0 | session 1 | session 2 | min | median | max | target | result |"
    assert lines[2] == "| wall (s) | 9.1 | 12.0 | 8.0 | 8.0 | 9.1 | 12.0 | <= 10.0 | FAIL |"
    assert lines[3] == "| CPU (s) | 14.0 | nan | 13.0 | 13.0 | 13.5 | 14.0 |  |  |"
