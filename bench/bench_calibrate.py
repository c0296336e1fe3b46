#!/usr/bin/env python
"""Calibration benchmark: ``mscal calibrate`` on full-size synthetic sessions.

Usage::

    .venv/bin/python bench/bench_calibrate.py [--quick] [--seeds 0 1 2] [--varied 5] [--out docs/benchmarks.md]

Per seed:

1. synthesize a session (``pipeline.sim.synth.write_session``) into a temporary folder, in its own
   process (timed separately; not part of the calibrate figure);
2. baseline measured in the same run, the I/O floor: a fresh process that reads and demosaics
   every frame of ``response/``, ``vignetting/`` and ``reflector/`` (``read_frame_table`` +
   ``read_bands``, one frame at a time, nothing kept) and nothing else;
3. ``mscal calibrate SESSION -o CALIB.zarr`` (default response estimator) in a fresh process;
4. ``mscal calibrate ... --response-method alternating`` (the paper's plain Eq. 6/7) as an
   accuracy baseline;
5. ``pipeline.sim.evaluate.evaluate_calibration`` on both stores (in this process, not timed).

``--varied N`` adds N sessions of ``pipeline.sim.varied``, measured the same way and tabled per
session with their spread (``bench/calibrate_varied.py``, which says how they are drawn).

Wall time and peak RSS are those of each child alone: every measured command is started by a
tiny fresh launcher process (:data:`LAUNCHER`) that reaps it with ``os.wait4`` and reports that
one child's rusage, so ``ru_maxrss`` is polluted neither by other children nor by this
process's own memory (see the note at :data:`LAUNCHER`).

The markdown section (machine, command, tables, a plain reading) replaces the text between
``<!-- bench_calibrate:start -->`` and ``<!-- bench_calibrate:end -->`` in ``--out`` and
leaves the rest of the file alone. ``--quick`` runs the small session with one seed; it writes
nothing unless ``--out`` is given, and then under its own markers (``bench_calibrate_quick``)
so it never replaces the full-size figures.

Importing this module runs nothing.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import shlex
import shutil
import stat
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "docs" / "benchmarks.md"
SECTION_KEY = "bench_calibrate"
QUICK_SECTION_KEY = "bench_calibrate_quick"
CHILD_TIMEOUT_S = 1800.0

#: The calibration's targets. ``upper`` means the figure must be <= the target.
WALL_TARGET_S = 60.0
#: ``mscal calibrate`` of a full session within this wall time on 2 cores (the faster
#: of two runs of the default command: the machine is shared and its load moves).
FAST_WALL_TARGET_S = 10.0
#: The band workers' setting (pipeline.calibrate.pool.WORKERS_ENV; not imported: importing this
#: module must stay light).
WORKERS_ENV = "MSCAL_CALIBRATE_WORKERS"
RSS_TARGET_MIB = 4096.0  # "4 GB" read as 4 GiB
ACCURACY_TARGETS = {
    "response": 0.02,       # max |U error| over 5-95 % of DN range / U(95 %)
    "vignetting": 0.015,    # RMS of V_est / V_true - 1
    "spectral": 0.01,       # max relative error of S after scale alignment
    "panel": 0.01,          # white-panel-normalised gray panel reflectance, absolute
    "ndvi": 0.01,           # vegetation NDVI, absolute
    "cv": 0.01,             # same panel across frames, coefficient of variation
}


# --------------------------------------------------------------------------- markdown section


def markers(key: str = SECTION_KEY) -> tuple[str, str]:
    return f"<!-- {key}:start -->", f"<!-- {key}:end -->"


def replace_section(text: str, body: str, key: str = SECTION_KEY) -> str:
    """``text`` with the section between ``key``'s markers replaced by ``body`` (markers kept).

    If the markers are absent the section is appended at the end. Text outside the markers,
    including other marked sections, is kept byte for byte.
    """
    start, end = markers(key)
    block = f"{start}\n{body.strip()}\n{end}"
    i = text.find(start)
    j = text.find(end, i + len(start)) if i >= 0 else -1
    if i >= 0 and j >= 0:
        return text[:i] + block + text[j + len(end):]
    if i >= 0 or text.find(end) >= 0:
        raise ValueError(f"unbalanced {key} markers: found only one of {start!r} / {end!r}")
    if not text.strip():
        text = "# Benchmarks\n"
    sep = "" if text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")
    return text + sep + block + "\n"


def write_section(path: Path, body: str, key: str = SECTION_KEY) -> None:
    path = Path(path)
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(replace_section(old, body, key), encoding="utf-8")
    os.replace(tmp, path)


# --------------------------------------------------------------------------- child measurement


@dataclass
class Run:
    """One command: wall time, CPU time of its process tree (it and its worker processes) and
    peak RSS (its own high-water mark, or its tree's summed PSS when larger)."""

    cmd: list[str]
    wall_s: float
    user_s: float
    sys_s: float
    maxrss_mib: float
    returncode: int
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float] = (float("nan"),) * 3
    stdout: str = ""
    stderr: str = ""
    #: CPU time the whole machine spent busy while the command ran (:func:`machine_busy_s`):
    #: its processes and the kernel's threads that work for it (block I/O completion, the
    #: file system's journal), and anything else running
    machine_cpu_s: float = float("nan")
    #: cores busy on average over a moment of rest just before (:func:`machine_busy_rate`;
    #: nan: not measured)
    machine_idle_cores: float = float("nan")

    @property
    def cpu_s(self) -> float:
        return self.user_s + self.sys_s


#: A tiny launcher, started fresh for every measurement: it spawns the command, reaps it with
#: ``os.wait4`` and reports that child's rusage. On Linux a child's ``ru_maxrss`` also counts
#: the memory of the process it was spawned from (fork/vfork + exec keep the old image's
#: high-water mark), so spawning the measured command straight from this (large) process would
#: inflate its peak RSS; the launcher is a bare interpreter of ~10 MiB.
#:
#: A command may run worker processes (``mscal apply``'s forkserver pool): their CPU
#: counts too. The launcher is a child subreaper (Linux ``PR_SET_CHILD_SUBREAPER``): the
#: processes the command leaves behind (a forkserver that outlives the command by a moment,
#: with the workers it reaped) come to it and are reaped too, so the CPU reported is that of
#: the whole process tree (``RUSAGE_CHILDREN``). The peak RSS is the larger of the command's
#: own high-water mark and the tree's summed memory (PSS: pages shared by the processes counted
#: once), sampled every 0.25 s from ``/proc``.
LAUNCHER = r"""
import ctypes, json, os, resource, signal, sys, time
res, out, err, timeout = sys.argv[1:5]
cmd = sys.argv[5:]
fo = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
fe = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
try:
    ctypes.CDLL(None).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
except (OSError, AttributeError):
    pass
page_kib = os.sysconf("SC_PAGE_SIZE") // 1024
def tree_kib():
    kids, rss = {}, {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return 0
    for d in names:
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", "rb") as f:
                s = f.read()
        except OSError:
            continue
        fields = s[s.rindex(b")") + 2:].split()
        kids.setdefault(int(fields[1]), []).append(int(d))
        rss[int(d)] = int(fields[21]) * page_kib
    total, todo = 0, [os.getpid()]
    while todo:
        for c in kids.get(todo.pop(), []):
            total += pss_kib(c, rss[c])
            todo.append(c)
    return total
def pss_kib(pid, rss):  # shared pages (a forkserver's imports in its workers) counted once
    try:
        with open(f"/proc/{pid}/smaps_rollup", "rb") as f:
            for line in f:
                if line.startswith(b"Pss:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return rss
load = os.getloadavg()
t0 = time.perf_counter()
pid = os.posix_spawnp(cmd[0], cmd, dict(os.environ),
                      file_actions=[(os.POSIX_SPAWN_DUP2, fo, 1), (os.POSIX_SPAWN_DUP2, fe, 2)])
signal.signal(signal.SIGALRM, lambda *a: os.kill(pid, signal.SIGKILL))
signal.alarm(max(1, int(float(timeout))))
peak = 0
while True:
    done, status, ru = os.wait4(pid, os.WNOHANG)
    if done:
        break
    peak = max(peak, tree_kib())
    time.sleep(0.25)
wall = time.perf_counter() - t0
signal.alarm(0)
deadline = time.monotonic() + 30  # the command's orphans, if any, exit when it has
while time.monotonic() < deadline:
    try:
        if os.waitpid(-1, os.WNOHANG)[0] == 0:
            time.sleep(0.05)
    except ChildProcessError:
        break
tree = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(res, "w") as fh:
    json.dump({"wall_s": wall, "user_s": tree.ru_utime, "sys_s": tree.ru_stime,
               "maxrss_kib": max(ru.ru_maxrss, peak), "own_user_s": ru.ru_utime, "own_sys_s": ru.ru_stime,
               "returncode": os.waitstatus_to_exitcode(status), "load_before": load,
               "load_after": os.getloadavg()}, fh)
"""


def machine_busy_s() -> float:
    """CPU seconds the whole machine has spent busy since it started: the first line of
    ``/proc/stat`` (every CPU) less idle and I/O wait; nan where there is no ``/proc/stat``."""
    try:
        with open("/proc/stat") as fh:
            ticks = [int(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return float("nan")
    busy = sum(ticks[:8]) - ticks[3] - ticks[4]  # user..steal, less idle and iowait (guest counted in user)
    return busy / os.sysconf("SC_CLK_TCK")


def machine_busy_rate(seconds: float) -> float:
    """Cores busy on average over the next ``seconds`` (:func:`machine_busy_s`)."""
    b0, t0 = machine_busy_s(), time.perf_counter()
    time.sleep(seconds)
    return (machine_busy_s() - b0) / (time.perf_counter() - t0)


def run_measured(cmd: Sequence[str], timeout: float = CHILD_TIMEOUT_S) -> Run:
    """Run ``cmd`` under :data:`LAUNCHER` in a fresh process; its figures are the child's alone.

    Dirty pages of earlier steps (e.g. the flight just written) are flushed first (``os.sync``):
    otherwise the first command measured pays for their writeback (seen: the I/O floor slower
    than the loop that does the same writes and more)."""
    os.sync()
    with tempfile.TemporaryDirectory(prefix="mscal-bench-run-") as tmp:
        res, out, err = (str(Path(tmp) / n) for n in ("result.json", "stdout", "stderr"))
        busy0 = machine_busy_s()
        subprocess.run([sys.executable, "-I", "-S", "-c", LAUNCHER, res, out, err, str(timeout), *cmd],
                       check=True, timeout=timeout + 60)
        busy = machine_busy_s() - busy0
        r = json.loads(Path(res).read_text())
        so = Path(out).read_text(errors="replace")
        se = Path(err).read_text(errors="replace")
    # Linux: ru_maxrss in KiB (macOS: bytes).
    rss = r["maxrss_kib"] / 1024.0 if sys.platform != "darwin" else r["maxrss_kib"] / 2**20
    return Run(list(cmd), r["wall_s"], r["user_s"], r["sys_s"], rss, r["returncode"],
               tuple(r["load_before"]), tuple(r["load_after"]), so, se, machine_cpu_s=busy)


def _check(run: Run, what: str) -> Run:
    if run.returncode != 0:
        raise RuntimeError(f"{what} failed (exit {run.returncode}): {shlex.join(run.cmd)}\n{run.stderr[-4000:]}")
    return run


TRASH = ".discarded"


def discard(path: Path) -> None:
    """Take a finished command's outputs out of the way without deleting them: every file
    emptied (its blocks freed), the tree moved into ``TRASH`` beside it. The work folder's
    removal at the end of the benchmark deletes it.

    Deleting instead makes the next measured command pay for it on ext4: for 60 s after a
    deletion (360 s while the inode table block is dirty) ``recently_deleted`` makes every
    inode allocation scan past the freed inodes, which in perf profiles of ``mscal apply`` on
    this VM was ~12 % of all CPU samples even 65 s after deleting the previous OUT, and a
    300-frame apply took 13.6 s after ``rm -rf`` against 11.1 s after emptying the files
    (docs/benchmarks.md). Files with other hard links (inputs linked from a source tree) are
    left whole.
    """
    if not path.exists():
        return
    for root, _dirs, files in os.walk(path):
        for name in files:
            p = os.path.join(root, name)
            st = os.lstat(p)
            if stat.S_ISREG(st.st_mode) and st.st_nlink == 1 and st.st_size:
                os.truncate(p, 0)
    trash = path.parent / TRASH
    trash.mkdir(exist_ok=True)
    k = sum(1 for _ in trash.iterdir())
    path.rename(trash / f"{path.name}.{k}")


def mscal_command() -> list[str]:
    exe = Path(sys.executable).parent / "mscal"
    found = str(exe) if exe.exists() else shutil.which("mscal")
    return [found] if found else [sys.executable, "-m", "pipeline.run.cli"]


# --------------------------------------------------------------------------- child modes


def _child_synth(path: str, seed: int, size: str) -> None:
    from pipeline.sim.synth import write_session

    write_session(path, seed=seed, size=size)


def _child_io_floor(session_dir: str) -> None:
    """Read + demosaic every calibration frame, one at a time, keep nothing."""
    from pipeline.ingest.session import load_session, read_bands, read_frame_table

    session = load_session(session_dir)
    n = 0
    checksum = 0
    for folder in (session.response_dir, session.vignetting_dir, session.reflector_dir):
        for rec in read_frame_table(folder):
            bands = read_bands(rec, session.camera)
            checksum += int(bands[:, 0, 0].sum())  # touch the result
            n += 1
    print(json.dumps({"frames": n, "checksum": checksum}))


# --------------------------------------------------------------------------- one seed


@dataclass
class SeedResult:
    seed: int
    size: str
    synth: Run
    floor: Run
    floor_frames: int
    forward: Run
    alternating: Run
    eval_forward: dict[str, Any]
    eval_alternating: dict[str, Any]
    stage_seconds: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    worst_band: dict[str, str] = field(default_factory=dict)
    forward_again: Run | None = None  # the default command a second time (after the 1-worker run)
    one_worker: Run | None = None  # the default command with one band worker (no worker processes)

    @property
    def fastest(self) -> Run:
        """The faster of the two runs of the default command."""
        runs = [r for r in (self.forward, self.forward_again) if r is not None]
        return min(runs, key=lambda r: r.wall_s)


def _per_band_detail(session: Path, calib: Path) -> dict[str, str]:
    """Which band is worst for each fit (for the diagnosis, not the targets)."""
    import numpy as np
    import xarray as xr

    from mscal_core import metrics

    truth = np.load(session / "truth.npz")
    ds = xr.open_zarr(calib).load()
    wl = truth["wavelength_nm"]
    U, Ut = ds["inverse_response"].values, truth["inverse_response"]
    r = [metrics.response_error(U[b], Ut[b]) for b in range(U.shape[0])]
    V, Vt = ds["vignetting"].values, truth["vignetting"]
    v = [metrics.vignetting_rms(V[b], Vt[b]) for b in range(V.shape[0])]
    S, St = ds["spectral_factor"].values, truth["spectral_factor"]
    s = float(S @ St / (S @ S))
    se = np.abs(s * S / St - 1.0)
    out = {}
    for name, errs in (("response", r), ("vignetting", v), ("spectral", list(se))):
        b = int(np.argmax(errs))
        out[name] = f"band {b} ({wl[b]:.0f} nm): {errs[b]:.4f}"
    return out


def run_seed(seed: int, size: str, workdir: Path, keep: bool, log=print) -> SeedResult:
    from pipeline.sim.evaluate import evaluate_calibration

    sdir = workdir / f"seed{seed}"
    session = sdir / "session"
    sdir.mkdir(parents=True, exist_ok=True)
    me = [sys.executable, str(Path(__file__).resolve())]
    try:
        log(f"[seed {seed}] synthesizing {size} session in {session}")
        synth = _check(run_measured(me + ["--_child", "synth", str(session), str(seed), size]), "synthesis")
        log(f"[seed {seed}]   synth {synth.wall_s:.1f} s; I/O floor ...")
        floor = _check(run_measured(me + ["--_child", "io-floor", str(session)]), "I/O floor")
        floor_frames = int(json.loads(floor.stdout.strip().splitlines()[-1])["frames"])
        log(f"[seed {seed}]   floor {floor.wall_s:.1f} s, {floor.maxrss_mib:.0f} MiB; calibrate (forward) ...")
        cal_f = sdir / "calib-forward.zarr"
        fwd = _check(run_measured(mscal_command() + ["calibrate", str(session), "-o", str(cal_f)]), "mscal calibrate")
        log(f"[seed {seed}]   forward {fwd.wall_s:.1f} s, {fwd.maxrss_mib:.0f} MiB; calibrate (alternating) ...")
        cal_a = sdir / "calib-alternating.zarr"
        alt = _check(
            run_measured(mscal_command() + ["calibrate", str(session), "-o", str(cal_a),
                                            "--response-method", "alternating"]),
            "mscal calibrate --response-method alternating",
        )
        log(f"[seed {seed}]   alternating {alt.wall_s:.1f} s, {alt.maxrss_mib:.0f} MiB; one band worker ...")
        one = _check(run_measured(["env", f"{WORKERS_ENV}=1", *mscal_command(), "calibrate", str(session), "-o",
                                   str(sdir / "calib-1-worker.zarr")]), "mscal calibrate with 1 band worker")
        log(f"[seed {seed}]   1 worker {one.wall_s:.1f} s; calibrate (forward) again ...")
        again = _check(run_measured(mscal_command() + ["calibrate", str(session), "-o", str(sdir / "calib-again.zarr")]),
                       "mscal calibrate (second run)")
        log(f"[seed {seed}]   again {again.wall_s:.1f} s; evaluating ...")
        ev_f = evaluate_calibration(session, cal_f)
        ev_a = evaluate_calibration(session, cal_a)
        import xarray as xr

        attrs = xr.open_zarr(cal_f).attrs
        stage_seconds = {k: float((attrs.get(k) or {}).get("seconds", float("nan")))
                         for k in ("response", "vignetting", "illumination")}
        skipped = {k: len((attrs.get(k) or {}).get("skipped", [])) for k in ("response", "vignetting", "illumination")}
        detail = _per_band_detail(session, cal_f)
        return SeedResult(seed, size, synth, floor, floor_frames, fwd, alt, ev_f, ev_a,
                          stage_seconds, skipped, detail, again, one)
    finally:
        if not keep:
            shutil.rmtree(sdir, ignore_errors=True)


# --------------------------------------------------------------------------- tables


@dataclass
class Row:
    label: str
    values: list[float]
    target: float | None = None  # upper bound
    fmt: str = "{:.4f}"
    note: str = ""
    anchor: str = ""  # HTML id of the row (README figures link to it), stable across runs

    @property
    def worst(self) -> float:
        finite = [v for v in self.values if v is not None and math.isfinite(v)]
        if len(finite) < len(self.values):
            return float("nan")
        return max(finite)

    def verdict(self) -> str:
        if self.target is None:
            return ""
        w = self.worst
        if not math.isfinite(w):
            return "FAIL (nan)"
        return "PASS" if w <= self.target else "FAIL"


def _flight(ev: dict[str, Any], which: str) -> dict[str, float]:
    fl = [v for k, v in ev.items() if k.startswith("flight_") and isinstance(v, dict)]
    if not fl:
        return {"panel_abs_error": float("nan"), "vegetation_ndvi_error": float("nan"),
                "panel_cv_across_frames": float("nan")}
    keys = ("panel_abs_error", "vegetation_ndvi_error", "panel_cv_across_frames")
    return {k: max(f[which][k] for f in fl) for k in keys}


def performance_rows(results: Sequence[SeedResult]) -> list[Row]:
    f = lambda attr: [getattr(r, attr) for r in results]
    fwd, alt, floor = f("forward"), f("alternating"), f("floor")
    return [
        Row("`mscal calibrate` wall (s)", [r.wall_s for r in fwd], WALL_TARGET_S, "{:.1f}", anchor="cal-wall"),
        Row("`mscal calibrate` peak RSS (MiB)", [r.maxrss_mib for r in fwd], RSS_TARGET_MIB, "{:.0f}", anchor="cal-rss"),
        Row("`mscal calibrate` CPU user+sys (s)", [r.cpu_s for r in fwd], None, "{:.1f}"),
        Row("I/O floor wall (s)", [r.wall_s for r in floor], None, "{:.1f}"),
        Row("I/O floor peak RSS (MiB)", [r.maxrss_mib for r in floor], None, "{:.0f}"),
        Row("wall / I/O floor", [a.wall_s / b.wall_s for a, b in zip(fwd, floor)], None, "{:.1f}x", anchor="cal-wall-floor"),
        Row("peak RSS / I/O floor", [a.maxrss_mib / b.maxrss_mib for a, b in zip(fwd, floor)], None, "{:.1f}x"),
        Row("stage: response (s)", [r.stage_seconds.get("response", float("nan")) for r in results], None, "{:.1f}"),
        Row("stage: vignetting (s)", [r.stage_seconds.get("vignetting", float("nan")) for r in results], None, "{:.1f}"),
        Row("stage: illumination (s)", [r.stage_seconds.get("illumination", float("nan")) for r in results], None, "{:.1f}"),
        Row("`mscal calibrate` wall, faster of two runs (s)", [r.fastest.wall_s for r in results],
            FAST_WALL_TARGET_S, "{:.1f}", anchor="cal-wall-fast"),
        Row("`mscal calibrate` CPU user+sys of that run (s)", [r.fastest.cpu_s for r in results], None, "{:.1f}"),
        Row(f"`{WORKERS_ENV}=1` (no band workers) wall (s)",
            [r.one_worker.wall_s if r.one_worker else float("nan") for r in results], None, "{:.1f}"),
        Row("speed-up, 2 band workers vs 1", [r.one_worker.wall_s / r.fastest.wall_s if r.one_worker else float("nan")
                                              for r in results], None, "{:.2f}x", anchor="cal-workers"),
        Row("`--response-method alternating` wall (s)", [r.wall_s for r in alt], None, "{:.1f}"),
        Row("`--response-method alternating` peak RSS (MiB)", [r.maxrss_mib for r in alt], None, "{:.0f}"),
        Row("synthesis wall (s, not part of the figure)", [r.synth.wall_s for r in results], None, "{:.1f}"),
        Row("1-min load average before `mscal calibrate`", [r.load_before[0] for r in fwd], None, "{:.2f}"),
        Row("1-min load average after `mscal calibrate`", [r.load_after[0] for r in fwd], None, "{:.2f}"),
    ]


def accuracy_rows(results: Sequence[SeedResult]) -> list[tuple[str, list[Row]]]:
    T = ACCURACY_TARGETS
    groups: list[tuple[str, list[Row]]] = []
    for name, key, a in (("default (`forward`)", "eval_forward", "cal-forward"),
                         ("`alternating` (paper Eq. 6/7, baseline)", "eval_alternating", "cal-alternating")):
        evs = [getattr(r, key) for r in results]
        groups.append((f"Calibration fits, response estimator {name}", [
            Row("response: max abs U error, 5-95 % DN / U(95 %)", [e["response_max_error"] for e in evs], T["response"],
                anchor=f"{a}-response"),
            Row("response: median over bands", [e["response_median_error"] for e in evs], None,
                anchor=f"{a}-response-median"),
            Row("vignetting: RMS of V/V_true - 1 (all pixels, worst band)", [e["vignetting_rms_error"] for e in evs],
                T["vignetting"], anchor=f"{a}-vignetting"),
            Row("vignetting: same, observed pixels only", [e.get("vignetting_rms_error_observed", float("nan")) for e in evs],
                None, anchor=f"{a}-vignetting-observed"),
            Row("spectral factor S: max relative error", [e["spectral_factor_max_error"] for e in evs], T["spectral"],
                anchor=f"{a}-spectral"),
        ]))
    for name, key, which, a in (
        ("Flight, Eq. 15 with the default calibration", "eval_forward", "eq15", "cal-eq15"),
        ("Flight, Eq. 15 with the `alternating` calibration (baseline)", "eval_alternating", "eq15", "cal-eq15-alternating"),
        ("Flight, Eq. 16 (divide by reflector DN; baseline, independent of the calibration)", "eval_forward", "eq16",
         "cal-eq16"),
    ):
        fl = [_flight(getattr(r, key), which) for r in results]
        groups.append((name, [
            Row("gray panel reflectance, abs error (white-panel normalised)", [x["panel_abs_error"] for x in fl], T["panel"],
                anchor=f"{a}-panel"),
            Row("vegetation NDVI, abs error", [x["vegetation_ndvi_error"] for x in fl], T["ndvi"], anchor=f"{a}-ndvi"),
            Row("same panel across frames, CV", [x["panel_cv_across_frames"] for x in fl], T["cv"], anchor=f"{a}-cv"),
        ]))
    return groups


def _fmt(fmt: str, v: float) -> str:
    if v is None or not math.isfinite(v):
        return "nan"
    return fmt.format(v)


def spread(values: Sequence[float], fmt: str) -> list[str]:
    """Min, median and max of the finite ``values``, formatted (``nan`` when none is finite)."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return ["nan"] * 3
    return [_fmt(fmt, min(finite)), _fmt(fmt, statistics.median(finite)), _fmt(fmt, max(finite))]


def table(rows: Sequence[Row], seeds: Sequence[int]) -> str:
    head = ["figure"] + [f"seed {s}" for s in seeds] + ["worst", "target", "result"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * (len(seeds) + 2) + [":---:"]) + "|"]
    for r in rows:
        tgt = ("<= " + _fmt(r.fmt, r.target)) if r.target is not None else ""
        label = (f'<a id="{r.anchor}"></a>' if r.anchor else "") + r.label
        cells = [label] + [_fmt(r.fmt, v) for v in r.values] + [_fmt(r.fmt, r.worst), tgt, r.verdict()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- report


def _cmd(args: Sequence[str]) -> str:
    try:
        return subprocess.run(list(args), capture_output=True, text=True, cwd=ROOT, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _proc_field(path: str, key: str) -> str:
    """The value after ``key:`` on the first such line of a /proc file ("" if none)."""
    try:
        return next((line.split(":", 1)[1].strip() for line in Path(path).read_text().splitlines()
                     if line.startswith(key)), "")
    except OSError:
        return ""


def machine_info() -> dict[str, str]:
    import cv2
    import numpy

    mem_kib = _proc_field("/proc/meminfo", "MemTotal").split()
    sha = _cmd(["git", "rev-parse", "--short", "HEAD"])
    changed = [line.strip().split(None, 1)[-1]
               for line in _cmd(["git", "status", "--porcelain", "--untracked-files=no"]).splitlines() if line.strip()]
    return {
        "nproc": str(os.cpu_count()),
        "memory": f"{int(mem_kib[0]) / 2**20:.1f} GiB" if mem_kib else "",
        "cpu": _proc_field("/proc/cpuinfo", "model name"),
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "opencv": cv2.__version__,
        "git": sha + (f" with uncommitted changes to {', '.join(f'`{c}`' for c in changed)}" if changed else ""),
    }


def failures(perf: Sequence[Row], acc: Sequence[tuple[str, list[Row]]], seeds: Sequence[int],
             target_groups: Sequence[str]) -> list[str]:
    out = []
    groups = [("Speed and memory", list(perf))] + [(g, rows) for g, rows in acc if g in target_groups]
    for g, rows in groups:
        for r in rows:
            if r.verdict().startswith("FAIL"):
                bad = [(s, v) for s, v in zip(seeds, r.values) if not (math.isfinite(v) and v <= r.target)]
                where = ", ".join(f"seed {s}: {_fmt(r.fmt, v)}" for s, v in bad)
                over = (r.worst / r.target) if r.target else float("nan")
                out.append(f"{g} / {r.label}: worst {_fmt(r.fmt, r.worst)} vs target {_fmt(r.fmt, r.target)} "
                           f"({over:.2f}x the target; {where})")
    return out


def _scaling_lines(results: Sequence[SeedResult]) -> list[str]:
    """The 10 s wall target and the expected scaling with cores, from the 1- and 2-worker runs."""
    ones = [(r.one_worker.wall_s, r.fastest.wall_s) for r in results if r.one_worker is not None]
    if not ones:
        return []
    fast = [r.fastest.wall_s for r in results]
    verdict = "PASS" if max(fast) <= FAST_WALL_TARGET_S else "FAIL"
    # Amdahl from the two points: T1 = serial + par, T2 = serial + par / 2
    par = [2.0 * (t1 - t2) for t1, t2 in ones]
    serial = [t1 - p for (t1, _), p in zip(ones, par)]
    proj = lambda n: [s_ + p / n for s_, p in zip(serial, par)]
    return [
        f"- The faster of two runs took {min(fast):.1f}-{max(fast):.1f} s wall (target "
        f"{FAST_WALL_TARGET_S:.0f} s on 2 cores: {verdict}). With one band worker (every band fitted in the main "
        f"process) {min(t for t, _ in ones):.1f}-{max(t for t, _ in ones):.1f} s: 2 workers are "
        f"{min(a / b for a, b in ones):.2f}-{max(a / b for a, b in ones):.2f}x faster. Read as Amdahl's law, "
        f"{min(serial):.1f}-{max(serial):.1f} s do not spread over workers (start-up, reading, the marker search, "
        f"the illumination fit, writing the store) and {min(par):.1f}-{max(par):.1f} s do (the band fits): "
        f"expected {min(proj(4)):.1f}-{max(proj(4)):.1f} s on 4 cores and {min(proj(8)):.1f}-{max(proj(8)):.1f} s "
        f"on 8 (projected, not measured; at most one worker per band).",
    ]


def reading(results: Sequence[SeedResult], perf: list[Row], acc: list[tuple[str, list[Row]]],
            seeds: Sequence[int]) -> str:
    by = {r.label: r for r in perf}
    wall = by["`mscal calibrate` wall (s)"]
    rss = by["`mscal calibrate` peak RSS (MiB)"]
    ratio = by["wall / I/O floor"]
    cpu = by["`mscal calibrate` CPU user+sys (s)"]
    lo, hi = min(wall.values), max(wall.values)
    lines = [
        f"- `mscal calibrate` took {lo:.1f}-{hi:.1f} s wall over {len(seeds)} seed(s) "
        f"(target {WALL_TARGET_S:.0f} s: {wall.verdict()}), {min(ratio.values):.1f}-{max(ratio.values):.1f}x the "
        f"I/O floor measured in the same run; CPU time {min(cpu.values):.1f}-{max(cpu.values):.1f} s, i.e. "
        f"{min(c / w for c, w in zip(cpu.values, wall.values)):.2f}-{max(c / w for c, w in zip(cpu.values, wall.values)):.2f} "
        f"cores busy on average. Peak RSS {min(rss.values):.0f}-{max(rss.values):.0f} MiB "
        f"(target {RSS_TARGET_MIB:.0f} MiB: {rss.verdict()}).",
    ]
    loads = [x for r in results for x in (r.forward.load_before[0], r.forward.load_after[0]) if math.isfinite(x)]
    ncpu = os.cpu_count() or 1
    if loads and max(loads) > ncpu:
        lines.append(
            f"- The machine was contended: the 1-min load average around `mscal calibrate` was "
            f"{min(loads):.1f}-{max(loads):.1f} on {ncpu} CPUs, so the wall times include time spent waiting "
            f"for a CPU; the CPU time (user+sys) is the less load-sensitive figure."
        )
    lines += _scaling_lines(results)
    st = [(k, max(r.stage_seconds.get(k, float('nan')) for r in results)) for k in ("response", "vignetting", "illumination")]
    lines.append("- Worst stage times: " + ", ".join(f"{k} {v:.1f} s" for k, v in st)
                 + " (from the store's provenance); the rest is start-up, reading and writing the store.")
    skipped = {k: max(r.skipped.get(k, 0) for r in results) for k in ("response", "vignetting", "illumination")}
    if any(skipped.values()):
        lines.append("- Frames skipped (most over seeds): " + ", ".join(f"{k} {v}" for k, v in skipped.items())
                     + " (the synthetic sessions include views with the marker out of frame).")
    target_groups = [acc[0][0], acc[2][0]]
    fails = failures(perf, acc, seeds, target_groups)
    if fails:
        lines.append("- Targets FAILED (default calibration):")
        lines += [f"  - {f}" for f in fails]
    else:
        lines.append("- Every target passes with the default calibration, on every seed.")
    alt_resp = acc[1][1][0]
    lines.append(f"- The paper's plain alternation (`--response-method alternating`) gives a worst response error "
                 f"of {alt_resp.worst:.4f} against {acc[0][1][0].worst:.4f} for the default (worst vignetting RMS "
                 f"{acc[1][1][2].worst:.4f}, S error {acc[1][1][4].worst:.4f}, Eq. 15 panel error "
                 f"{acc[3][1][0].worst:.4f}).")
    e15 = acc[2][1]
    e16 = acc[4][1]
    lines.append(
        f"- Flight, worst over seeds: Eq. 15 panel error {e15[0].worst:.4f}, NDVI error {e15[1].worst:.4f}, "
        f"panel CV {e15[2].worst:.4f}; Eq. 16 baseline {e16[0].worst:.4f}, {e16[1].worst:.4f}, {e16[2].worst:.4f}."
    )
    for r in results:
        lines.append(f"- Worst band, seed {r.seed} (default): " + "; ".join(f"{k} {v}" for k, v in r.worst_band.items()))
    return "\n".join(lines)


def render(results: Sequence[SeedResult], command: str, info: dict[str, str], loads: dict[str, str],
           quick: bool, started: str, launcher_floor_mib: float = float("nan")) -> str:
    seeds = [r.seed for r in results]
    perf = performance_rows(results)
    acc = accuracy_rows(results)
    size = results[0].size
    title = "Calibration benchmark" + (" (quick smoke run, small session)" if quick else "")
    parts = [
        f"## {title}",
        "",
        f"Produced by `bench/bench_calibrate.py`; a later run replaces this section. Run started {started}.",
        "",
        "```",
        command,
        "```",
        "",
        "Machine: " + "; ".join([
            f"{info['nproc']} CPUs ({info['cpu']})", f"{info['memory']} RAM", info["os"],
            f"Python {info['python']}", f"numpy {info['numpy']}", f"OpenCV {info['opencv']}",
        ]) + f". Code: git {info['git']}.",
        "",
        f"Load (`uptime`): at start `{loads['start']}`; at end `{loads['end']}`. The machine is shared: "
        "other work may have run during the measurements (the 1-min load before each calibrate run is in "
        "the first table).",
        "",
        f"Session: `pipeline.sim.synth.write_session(size=\"{size}\", seed=...)`"
        + (" (10-bit, 14-frame sweep, 40 viewpoints of which 2 without the marker, 3 reflector images, "
           "8 flight frames)." if size == "full" else " (7-frame sweep, 8 viewpoints, 2 reflector images, 3 flight "
                                                       "frames). The targets are defined for the full session; "
                                                       "here they are indicative only.")
        + " Each measured command runs in its own fresh process, started by a bare launcher "
        "interpreter that reaps it with `os.wait4`; wall time and peak RSS (`ru_maxrss`) are that "
        f"child's alone (the launcher itself sets a floor of {launcher_floor_mib:.0f} MiB, measured on `true`). "
        "The I/O floor is a process that reads and "
        "demosaics every frame of `response/`, `vignetting/` and `reflector/` (one frame at a time, "
        f"{results[0].floor_frames} frames) and does nothing else. The frames are in the page cache "
        "for both (the session was just written). Accuracy is `pipeline.sim.evaluate.evaluate_calibration` "
        "against the session's `truth.npz`; \"worst\" is the maximum over seeds.",
        "",
        "### Speed and memory",
        "",
        table(perf, seeds),
        "",
    ]
    for name, rows in acc:
        parts += [f"### {name}", "", table(rows, seeds), ""]
    parts += ["### Reading", "", reading(results, perf, acc, seeds), ""]
    return "\n".join(parts)


def _uptime() -> str:
    out = _cmd(["uptime"])
    if out:
        return out.strip()
    return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small session, one seed (smoke run)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="seeds (default 0 1 2; --quick: 0)")
    p.add_argument("--out", type=Path, default=None,
                   help=f"markdown file to update (default {DEFAULT_OUT.relative_to(ROOT)}; --quick: none)")
    p.add_argument("--workdir", type=Path, default=None, help="where sessions are written (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the sessions and stores")
    p.add_argument("--varied", type=int, default=0, metavar="N",
                   help="also N varied full-size sessions (pipeline.sim.varied, sessions 0..N-1)")
    p.add_argument("--json", type=Path, default=None, help="also write the raw figures as JSON")
    p.add_argument("--_child", nargs="+", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _varied():
    return importlib.import_module("calibrate_varied")


def _run_child(mode: str, rest: Sequence[str]) -> None:
    """One measured child's work (``--_child MODE ...``)."""
    if mode == "synth":
        _child_synth(rest[0], int(rest[1]), rest[2])
    elif mode == "io-floor":
        _child_io_floor(rest[0])
    elif mode == "synth-varied":
        _varied().child_synth(rest[0], int(rest[1]))
    else:
        raise SystemExit(f"unknown child mode {mode}")


def main(argv: Sequence[str] | None = None) -> int:
    raw_argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(raw_argv)
    if args._child:
        _run_child(args._child[0], args._child[1:])
        return 0

    sys.path.insert(0, str(ROOT))
    size = "small" if args.quick else "full"
    seeds = args.seeds if args.seeds is not None else ([0] if args.quick else [0, 1, 2])
    out = args.out if args.out is not None else (None if args.quick else DEFAULT_OUT)
    key = QUICK_SECTION_KEY if args.quick else SECTION_KEY
    try:
        py = Path(sys.executable).relative_to(ROOT)
    except ValueError:
        py = Path(sys.executable)
    command = shlex.join([str(py), "bench/bench_calibrate.py", *raw_argv])

    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    loads = {"start": _uptime()}
    info = machine_info()  # the code as it was when the run started
    print(f"load at start: {loads['start']}", flush=True)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="mscal-bench-"))
    results = []
    try:
        for s in seeds:
            results.append(run_seed(s, size, workdir, args.keep, log=lambda m: print(m, flush=True)))
        varied = [_varied().run_varied_session(k, workdir, args.keep, log=lambda m: print(m, flush=True))
                  for k in range(args.varied)]
    finally:
        if args.workdir is None and not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
    loads["end"] = _uptime()
    launcher_floor = run_measured(["true"]).maxrss_mib
    git_end = machine_info()["git"]
    if git_end != info["git"]:
        info["git"] += f" at the start; {git_end} at the end (the tree changed during the run)"
    md = render(results, command, info, loads, args.quick, started, launcher_floor)
    md += ("\n" + _varied().render(varied)) if varied else ""
    print()
    print(md)
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in results], indent=2, default=str))
    if out is not None:
        write_section(out, md, key)
        print(f"\nwrote section {key} of {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
