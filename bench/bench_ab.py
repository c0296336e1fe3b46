#!/usr/bin/env python
"""A/B benchmark: ``mscal calibrate`` and ``mscal apply`` of an older commit against this checkout.

Usage::

    .venv/bin/python bench/bench_ab.py --old REV [--frames 600] [--repeat 3] [--settle 65] [--out docs/benchmarks.md]

Answers "is this change slower?" on a shared machine whose load moves between runs: both
versions run in ONE process tree, on the same synthetic session and flight, alternately
(old, new, new, old, old, new, ...), so a load change hits both alike. The older commit is
checked out with ``git worktree add --detach`` into a temporary folder and run from there with
``PYTHONPATH`` (same venv, same packages); its CLI module is ``pipeline.run.cli`` or, before
the regrouping, ``pipeline.cli``. Each run gets a fresh output and calibration cache. Before
each run, as in bench_apply.py: the previous run's outputs emptied and moved aside
(``bench_calibrate.discard``), ``sync``, ``--settle`` seconds of rest and the run's inputs read
once (``bench_apply.settle``).

Figures per version: wall (min and median), CPU user+sys (min and median: the figure least
moved by other work on the machine) of EVERY process the command starts (each command in its
own cgroup-v1 cpuacct group, entered before exec: a forkserver's workers count whoever reaps
them; :data:`LAUNCHER`; without a writable cgroup, ``wait4`` of a subreaper, and a note is
printed) and peak memory (summed PSS of the command's processes). The flight's outputs are
applied with the new version's calibration store for both versions (the store format is a
contract).

The markdown section replaces the text between ``<!-- bench_ab:start -->`` and
``<!-- bench_ab:end -->`` in ``--out`` (nothing is written without ``--out``).

``--factory N`` compares ``mscal apply --calibration factory --reference dls`` of
both versions on ``N`` MicaSense captures (``bench_factory.make_survey``), alternating with
``bench_factory``'s hand-written numpy loop of the manufacturer's model (old, new, loop, then
rotated), measured the same way. Section key ``bench_ab_factory``.

Importing this module runs nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

ROOT = Path(__file__).resolve().parents[1]
SECTION_KEY = "bench_ab"
CHILD_TIMEOUT_S = 3600.0


def _cli_module(tree: Path) -> str:
    return "pipeline.run.cli" if (tree / "pipeline" / "run" / "cli.py").exists() else "pipeline.cli"


#: Where each measured command gets its own cgroup-v1 CPU accounting group (see :data:`LAUNCHER`).
CPUACCT = Path("/sys/fs/cgroup/cpuacct")

#: A bare interpreter (``python -I -S -c``) started fresh for every measurement. It forks the
#: command; the child puts itself into a new cpuacct group before ``exec``, so every process
#: the command starts (a forkserver, its workers, their threads) is in that group whatever
#: becomes of its parent, and ``cpuacct.usage`` after the last of them ended is the CPU of the
#: whole command. The group is removed afterwards. Peak memory: the summed PSS (pages shared by
#: the processes counted once) of the group's processes, sampled every 0.25 s from ``/proc``,
#: or the command's own high-water mark when larger. The launcher is a child subreaper
#: (``PR_SET_CHILD_SUBREAPER``): processes the command leaves behind are reaped by it. Without a
#: writable cgroup (not Linux, not root, no cpuacct hierarchy), CPU is ``RUSAGE_CHILDREN`` of
#: the launcher (``wait4``): a process that was never reaped is missing from it.
LAUNCHER = r"""
import ctypes, json, os, resource, signal, sys, time
res, cg, err, timeout = sys.argv[1:5]
cmd = sys.argv[5:]
try:
    ctypes.CDLL(None).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
except (OSError, AttributeError):
    pass
note = ""
if cg:
    try:
        os.mkdir(cg)
        with open(os.path.join(cg, "cgroup.procs"), "w") as f:
            pass
    except OSError as exc:
        note, cg = f"no cpuacct group ({exc}): CPU from wait4 of the launcher's children", ""
page_kib = os.sysconf("SC_PAGE_SIZE") // 1024
def pids():
    if cg:
        with open(os.path.join(cg, "cgroup.procs")) as f:
            return [int(x) for x in f.read().split()]
    kids = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat", "rb") as f:
                    s = f.read()
            except OSError:
                continue
            kids.setdefault(int(s[s.rindex(b")") + 2:].split()[1]), []).append(int(d))
    out, todo = [], [os.getpid()]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out
def pss_kib():
    total = 0
    for pid in pids():
        try:
            with open(f"/proc/{pid}/smaps_rollup", "rb") as f:
                for line in f:
                    if line.startswith(b"Pss:"):
                        total += int(line.split()[1])
        except OSError:
            pass
    return total
fe = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
fo = os.open(os.devnull, os.O_WRONLY)
load = os.getloadavg()
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    try:
        if cg:
            with open(os.path.join(cg, "cgroup.procs"), "w") as f:
                f.write(str(os.getpid()))
        os.dup2(fo, 1)
        os.dup2(fe, 2)
        os.execvp(cmd[0], cmd)
    finally:
        os._exit(127)
signal.signal(signal.SIGALRM, lambda *a: os.kill(pid, signal.SIGKILL))
signal.alarm(max(1, int(float(timeout))))
peak = 0
while True:
    done, status, ru = os.wait4(pid, os.WNOHANG)
    if done:
        break
    peak = max(peak, pss_kib())
    time.sleep(0.25)
wall = time.perf_counter() - t0
signal.alarm(0)
deadline = time.monotonic() + 30  # the command's orphans, if any, exit when it has
while time.monotonic() < deadline:
    try:
        if os.waitpid(-1, os.WNOHANG)[0] == 0:
            time.sleep(0.05)
    except ChildProcessError:
        if not cg or not pids():
            break
        time.sleep(0.05)
tree = resource.getrusage(resource.RUSAGE_CHILDREN)
out = {"wall_s": wall, "user_s": tree.ru_utime, "sys_s": tree.ru_stime, "wait4_cpu_s": tree.ru_utime + tree.ru_stime,
       "maxrss_kib": max(ru.ru_maxrss, peak), "returncode": os.waitstatus_to_exitcode(status), "load_before": load,
       "method": "wait4", "note": note}
if cg:
    with open(os.path.join(cg, "cpuacct.usage")) as f:
        total = int(f.read()) / 1e9
    with open(os.path.join(cg, "cpuacct.stat")) as f:
        ticks = {k: int(v) for k, v in (line.split() for line in f)}
    share = ticks["user"] / max(1, ticks["user"] + ticks["system"])
    out.update(user_s=total * share, sys_s=total * (1 - share), method="cgroup")
    try:
        os.rmdir(cg)
    except OSError as exc:
        out["note"] = f"cpuacct group {cg} not removed: {exc}"
with open(res, "w") as fh:
    json.dump(out, fh)
"""


def _cgroup_dir() -> str:
    """A new cpuacct group's path for one command ("" when the hierarchy is not writable here)."""
    if not (CPUACCT / "cgroup.procs").exists() or not os.access(CPUACCT, os.W_OK):
        return ""
    return str(CPUACCT / f"mscal-bench-ab-{os.getpid()}-{time.monotonic_ns()}")


def _measure(cmd: list[str], tree: Path, cache: Path, log=print) -> tuple[float, float, float, float, float]:
    """Wall (s), CPU user+sys (s) of every process the command started, peak memory (MiB),
    CPU user and sys (s) of one child run from ``tree`` (:data:`LAUNCHER`)."""
    env = dict(os.environ, PYTHONPATH=str(tree), MSCAL_CACHE_DIR=str(cache))
    with tempfile.TemporaryDirectory(prefix="mscal-ab-run-") as tmp:
        res, err = Path(tmp) / "result.json", Path(tmp) / "stderr"
        subprocess.run([sys.executable, "-I", "-S", "-c", LAUNCHER, str(res), _cgroup_dir(), str(err),
                        str(CHILD_TIMEOUT_S), *cmd], check=True, env=env, cwd=tempfile.gettempdir(),
                       timeout=CHILD_TIMEOUT_S + 60)
        r = json.loads(res.read_text())
        if r["returncode"] != 0:
            raise SystemExit(f"bench_ab: {' '.join(cmd)} failed ({r['returncode']}):\n"
                             f"{err.read_text(errors='replace')[-3000:]}")
    if r["method"] != "cgroup" or r["note"]:
        log(f"note: {r['note'] or 'CPU from wait4'}")
    return r["wall_s"], r["user_s"] + r["sys_s"], r["maxrss_kib"] / 1024.0, r["user_s"], r["sys_s"]


def cpu_method() -> str:
    """How :func:`_measure` counts CPU on this machine (the report's wording)."""
    if _cgroup_dir():
        return ("CPU: user+sys of every process the command started (a cgroup-v1 cpuacct group per command, "
                "entered before exec)")
    return ("CPU: user+sys from wait4 of the launcher, a child subreaper (no writable cpuacct cgroup here: "
            "a worker process that was never reaped is not counted)")


def _order(repeat: int) -> list[str]:
    """old, new, new, old, old, new, ...: each version first equally often."""
    out: list[str] = []
    for i in range(repeat):
        out += ["old", "new"] if i % 2 == 0 else ["new", "old"]
    return out


def _child_synth(session: str, small: str, flight: str, frames: int) -> None:
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_apply

    from pipeline.sim.synth import write_session
    write_session(session, seed=0, size="full")
    write_session(small, seed=0, size="small")
    bench_apply.make_flight(Path(small) / "flights" / "field", Path(flight), frames, seed=1)


def run(old_rev: str, frames: int, repeat: int, work: Path, log=print, settle_s: float = 65.0) -> dict:
    """Calibrate, then apply, of both versions, alternating (:func:`_order`). Before each run:
    the previous run's outputs and cache emptied and moved aside (``bench_calibrate.discard``),
    ``sync``, ``settle_s`` seconds of rest and the run's inputs read once
    (``bench_apply.settle``), as bench_apply does: on this VM a command started sooner after
    another, or after a deletion, pays for that one (bench_apply's Method)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_apply import settle
    from bench_calibrate import discard

    old_tree = work / "old"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old_tree), old_rev],
                   check=True, capture_output=True)
    try:
        session, small, flight = work / "session", work / "small", work / "flight"
        log("synthesizing the session and the flight")
        subprocess.run([sys.executable, __file__, "--child-synth", str(session), str(small), str(flight),
                        str(frames)], check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        trees = {"old": old_tree, "new": ROOT}
        res: dict = {"calibrate": {"old": [], "new": []}, "apply": {"old": [], "new": []}, "settle_s": settle_s,
                     "cpu_method": cpu_method()}
        calib_new = None
        for i, which in enumerate(_order(repeat)):
            out = work / f"cal-{which}-{i}.zarr"
            cache = work / f"cache-{which}-{i}"
            cmd = [sys.executable, "-m", _cli_module(trees[which]), "calibrate", str(session), "-o", str(out)]
            settle(settle_s, warm=(session,))
            res["calibrate"][which].append(_measure(cmd, trees[which], cache, log))
            log(f"calibrate {which}: {res['calibrate'][which][-1]}")
            discard(cache)
            if which == "new":  # the store apply uses: the last one the new version made
                if calib_new is not None:
                    discard(calib_new)
                calib_new = out
            else:
                discard(out)
        for i, which in enumerate(_order(repeat)):
            out = work / f"apply-{which}-{i}"
            cache = work / f"cache-a-{which}-{i}"
            cmd = [sys.executable, "-m", _cli_module(trees[which]), "apply", str(flight),
                   "--calibration", str(calib_new), "-o", str(out)]
            settle(settle_s, warm=(flight, calib_new))
            res["apply"][which].append(_measure(cmd, trees[which], cache, log))
            log(f"apply {which}: {res['apply'][which][-1]}")
            discard(out)
            discard(cache)
        return res
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old_tree)],
                       capture_output=True)


def run_factory(old_rev: str, captures: int, repeat: int, work: Path, log=print, settle_s: float = 0.0) -> dict:
    """Factory apply of the old and new versions and the hand loop, rotating (module docstring)."""
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_factory as bf
    from bench_apply import settle
    from bench_calibrate import discard

    old_tree = work / "old"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old_tree), old_rev],
                   check=True, capture_output=True)
    here, pythonpath = os.getcwd(), os.environ.get("PYTHONPATH")
    os.chdir(work)  # `python -m` puts the working directory first on sys.path: neither tree
    try:
        survey = bf.make_survey(work / "captures", captures, seed=1)
        log(f"{captures} captures written to {survey}")
        trees = {"old": old_tree, "new": ROOT}
        res: dict = {"old": [], "new": [], "loop": [], "cpu_method": cpu_method()}
        order = ["old", "new", "loop"]
        for i in range(repeat):
            for which in order[i % 3:] + order[:i % 3]:
                out = work / f"out-{which}-{i}"
                if which == "loop":
                    os.environ["PYTHONPATH"] = str(ROOT)
                    cmd = [sys.executable, str(ROOT / "bench" / "bench_factory.py"), "--child", "loop", str(survey),
                           str(out)]
                else:
                    os.environ["PYTHONPATH"] = str(trees[which])
                    cmd = [sys.executable, "-m", _cli_module(trees[which]), "apply", str(survey), "--calibration",
                           "factory", "--reference", "dls", "-o", str(out), "-q"]
                settle(settle_s)
                r = _measure(cmd, ROOT if which == "loop" else trees[which], work / f"cache-{which}-{i}", log)
                res[which].append(r)
                log(f"factory {which}: wall {r[0]:.1f} s, CPU {r[1]:.1f} s, {r[2]:.0f} MiB")
                discard(out)
                discard(work / f"cache-{which}-{i}")
        return res
    finally:
        os.chdir(here)
        if pythonpath is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = pythonpath
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old_tree)],
                       capture_output=True)


def render_factory(res: dict, old_rev: str, new_rev: str, command: str, captures: int,
                   load: tuple[str, str]) -> str:
    med = statistics.median
    lines = [
        '<a id="bench-ab-factory"></a>',
        "",
        "## A/B: factory apply of this checkout against an older commit and the hand loop",
        "",
        "Produced by `bench/bench_ab.py --factory`; a later run replaces this section.",
        "",
        "```", command, "```", "",
        f"Old: git {old_rev}. New: git {new_rev}. {captures} MicaSense RedEdge captures "
        "(`bench_factory.make_survey`); `mscal apply --calibration factory --reference dls` of each version and "
        f"`bench_factory`'s hand-written numpy loop, rotating. {res.get('cpu_method', cpu_method())}.",
        "",
        f"Load (`uptime`): at start `{load[0]}`; at end `{load[1]}`.",
        "",
        "| command | runs | wall min (s) | wall median (s) | CPU median (s) | CPU / capture (ms) | user / sys (s) | "
        "captures/s (median wall) | CPU / wall | peak RSS max (MiB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    names = {"old": f"mscal apply, old ({old_rev})", "new": f"mscal apply, new ({new_rev})",
             "loop": "hand-written numpy loop"}
    for which in ("old", "new", "loop"):
        runs = res[which]
        w, c = med(r[0] for r in runs), med(r[1] for r in runs)
        lines.append(f"| {names[which]} | {len(runs)} | {min(r[0] for r in runs):.1f} | {w:.1f} | {c:.1f} | "
                     f"{1e3 * c / captures:.0f} | {med(r[3] for r in runs):.1f} / {med(r[4] for r in runs):.1f} | "
                     f"{captures / w:.1f} | {c / w:.2f} | {max(r[2] for r in runs):.0f} |")
    lw, ow, nw = (med(r[0] for r in res[k]) for k in ("loop", "old", "new"))
    lc, oc, nc = (med(r[1] for r in res[k]) for k in ("loop", "old", "new"))
    lines += ["", f"- new/old: CPU {nc / oc:.2f}x, wall {nw / ow:.2f}x. Loop wall / apply wall: old {lw / ow:.2f}x, "
                  f"new {lw / nw:.2f}x (target >= 2.0x). Loop CPU / apply CPU: old {lc / oc:.2f}x, new {lc / nc:.2f}x."]
    return "\n".join(lines) + "\n"


def render(res: dict, old_rev: str, new_rev: str, command: str, frames: int, load: tuple[str, str]) -> str:
    lines = [
        '<a id="bench-ab"></a>',
        "",
        "## A/B: this checkout against an older commit, alternating in one run",
        "",
        "Produced by `bench/bench_ab.py`; a later run replaces this section.",
        "",
        "```", command, "```", "",
        f"Old: git {old_rev}. New: git {new_rev}. Same venv; full synthetic session (seed 0) for "
        f"`calibrate`, a {frames}-frame full-resolution flight for `apply` (the new version's store "
        "for both). Runs alternate old/new so that a change of load hits both. Before each run: the previous "
        "run's outputs emptied and moved aside (`discard()` in bench_calibrate.py), `sync`, "
        f"{res.get('settle_s', 0):.0f} s of rest (`--settle`) and the inputs read once (`settle()` in "
        f"bench_apply.py). {res.get('cpu_method', cpu_method())}; peak memory: the summed PSS of its processes.",
        "",
        f"Load (`uptime`): at start `{load[0]}`; at end `{load[1]}`. Under load, wall time moves "
        "with the other work; CPU user+sys is the steadier figure.",
        "",
        "| command | version | runs | wall min (s) | wall median (s) | CPU min (s) | CPU median (s) | peak RSS max (MiB) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for cmd in ("calibrate", "apply"):
        for which in ("old", "new"):
            runs = res[cmd][which]
            walls = [r[0] for r in runs]
            cpus = [r[1] for r in runs]
            lines.append(f"| `mscal {cmd}` | {which} | {len(runs)} | {min(walls):.1f} | "
                         f"{statistics.median(walls):.1f} | {min(cpus):.1f} | {statistics.median(cpus):.1f} | "
                         f"{max(r[2] for r in runs):.0f} |")
    lines.append("")
    for cmd in ("calibrate", "apply"):
        o = statistics.median(r[1] for r in res[cmd]["old"])
        n = statistics.median(r[1] for r in res[cmd]["new"])
        ow = statistics.median(r[0] for r in res[cmd]["old"])
        nw = statistics.median(r[0] for r in res[cmd]["new"])
        lines.append(f"- `mscal {cmd}`: new/old CPU median {n / o:.2f}x, wall median {nw / ow:.2f}x.")
    return "\n".join(lines) + "\n"


def _replace_section(path: Path, text: str, key: str = SECTION_KEY) -> None:
    start, end = f"<!-- {key}:start -->", f"<!-- {key}:end -->"
    doc = path.read_text() if path.exists() else ""
    block = f"{start}\n{text}{end}"
    if start in doc and end in doc:
        doc = doc[: doc.index(start)] + block + doc[doc.index(end) + len(end):]
    else:
        doc = doc.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(doc)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--child-synth"]:
        _child_synth(argv[1], argv[2], argv[3], int(argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old", required=True, help="git revision to compare against (e.g. a tag or a commit)")
    p.add_argument("--frames", type=int, default=600, help="flight length for apply (default 600)")
    p.add_argument("--repeat", type=int, default=3, help="runs per version and command (default 3)")
    p.add_argument("--out", type=Path, default=None, help="markdown file to update (default: none)")
    p.add_argument("--factory", type=int, default=0, metavar="N",
                   help="instead: factory apply on N MicaSense captures, old vs new vs the hand loop")
    p.add_argument("--settle", type=float, default=None,
                   help="seconds of rest after sync before each run (default 65; --factory: 0)")
    p.add_argument("--section", default=None, metavar="KEY",
                   help="the section of --out to replace (default bench_ab, or bench_ab_factory with --factory): "
                        "another key keeps an A/B against a second commit beside the first")
    args = p.parse_args(argv)
    uptime = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    load0 = uptime()
    new_rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True).stdout.strip()
    old_rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.old], capture_output=True,
                             text=True, check=True).stdout.strip()
    command = ".venv/bin/python bench/bench_ab.py " + " ".join(argv)
    with tempfile.TemporaryDirectory(prefix="mscal-ab-") as tmp:
        if args.factory:
            res = run_factory(args.old, args.factory, args.repeat, Path(tmp),
                              settle_s=0.0 if args.settle is None else args.settle)
        else:
            res = run(args.old, args.frames, args.repeat, Path(tmp), settle_s=65.0 if args.settle is None else args.settle)
    if args.factory:
        md = render_factory(res, old_rev, new_rev, command, args.factory, (load0, uptime()))
    else:
        md = render(res, old_rev, new_rev, command, args.frames, (load0, uptime()))
    key = args.section or ("bench_ab_factory" if args.factory else SECTION_KEY)
    default_anchor = "bench-ab-factory" if args.factory else "bench-ab"
    md = md.replace(f'<a id="{default_anchor}"></a>', f'<a id="{key.replace("_", "-")}"></a>')
    print(md)
    if args.out:
        _replace_section(args.out, md, key)
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    print(f"done {stamp}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
