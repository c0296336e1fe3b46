#!/usr/bin/env python
"""A/B benchmark: ``mscal calibrate`` and ``mscal apply`` of an older commit against this checkout.

Usage::

    .venv/bin/python bench/bench_ab.py --old REV [--frames 300] [--repeat 4] [--out docs/benchmarks.md]

Answers "is this change slower?" on a shared machine whose load moves between runs: both
versions run in ONE process tree, on the same synthetic session and flight, alternately
(old, new, new, old, old, new, ...), so a load change hits both alike. The older commit is
checked out with ``git worktree add --detach`` into a temporary folder and run from there with
``PYTHONPATH`` (same venv, same packages); its CLI module is ``pipeline.run.cli`` or, before
the regrouping, ``pipeline.cli``. Each run gets a fresh output and calibration cache.

Figures per version: wall (min and median), CPU user+sys of the child (min and median: the
figure least moved by other work on the machine) and peak RSS, from ``os.wait4`` on a child
started by this small process. The flight's outputs are applied with the new version's
calibration store for both versions (the store format is a contract).

The markdown section replaces the text between ``<!-- bench_ab:start -->`` and
``<!-- bench_ab:end -->`` in ``--out`` (nothing is written without ``--out``).

``--factory N`` compares ``mscal apply --calibration factory --reference dls`` of
both versions on ``N`` MicaSense captures (``bench_factory.make_survey``), alternating with
``bench_factory``'s hand-written numpy loop of the manufacturer's model (old, new, loop, then
rotated). These runs go through ``bench_calibrate.run_measured``: CPU user+sys of the whole
process tree (worker processes included: a forkserver's workers are reaped by a subreaper),
peak summed PSS of the tree. Section key ``bench_ab_factory``.

Importing this module runs nothing.
"""

from __future__ import annotations

import argparse
import os
import shutil
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


def _cli_module(tree: Path) -> str:
    return "pipeline.run.cli" if (tree / "pipeline" / "run" / "cli.py").exists() else "pipeline.cli"


def _measure(cmd: list[str], tree: Path, cache: Path) -> tuple[float, float, float]:
    """Wall (s), CPU user+sys (s) and peak RSS (MiB) of one child run from ``tree``."""
    env = dict(os.environ, PYTHONPATH=str(tree), MSCAL_CACHE_DIR=str(cache))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=tempfile.gettempdir(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"bench_ab: {' '.join(cmd)} failed ({proc.returncode}):\n{err[-3000:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0


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


def run(old_rev: str, frames: int, repeat: int, work: Path, log=print) -> dict:
    old_tree = work / "old"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old_tree), old_rev],
                   check=True, capture_output=True)
    try:
        session, small, flight = work / "session", work / "small", work / "flight"
        log("synthesizing the session and the flight")
        subprocess.run([sys.executable, __file__, "--child-synth", str(session), str(small), str(flight),
                        str(frames)], check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        trees = {"old": old_tree, "new": ROOT}
        res: dict = {"calibrate": {"old": [], "new": []}, "apply": {"old": [], "new": []}}
        calib_new = None
        for i, which in enumerate(_order(repeat)):
            out = work / f"cal-{which}-{i}.zarr"
            cache = work / f"cache-{which}-{i}"
            cmd = [sys.executable, "-m", _cli_module(trees[which]), "calibrate", str(session), "-o", str(out)]
            res["calibrate"][which].append(_measure(cmd, trees[which], cache))
            log(f"calibrate {which}: {res['calibrate'][which][-1]}")
            shutil.rmtree(cache, ignore_errors=True)
            if which == "new":
                calib_new = out
        for i, which in enumerate(_order(repeat)):
            out = work / f"apply-{which}-{i}"
            cmd = [sys.executable, "-m", _cli_module(trees[which]), "apply", str(flight),
                   "--calibration", str(calib_new), "-o", str(out)]
            res["apply"][which].append(_measure(cmd, trees[which], work / f"cache-a-{which}-{i}"))
            log(f"apply {which}: {res['apply'][which][-1]}")
            shutil.rmtree(out, ignore_errors=True)
        return res
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old_tree)],
                       capture_output=True)


def run_factory(old_rev: str, captures: int, repeat: int, work: Path, log=print, settle_s: float = 0.0) -> dict:
    """Factory apply of the old and new versions and the hand loop, rotating (module docstring)."""
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_calibrate as bc
    import bench_factory as bf
    from bench_apply import settle

    old_tree = work / "old"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old_tree), old_rev],
                   check=True, capture_output=True)
    here, pythonpath = os.getcwd(), os.environ.get("PYTHONPATH")
    os.chdir(work)  # `python -m` puts the working directory first on sys.path: neither tree
    try:
        survey = bf.make_survey(work / "captures", captures, seed=1)
        log(f"{captures} captures written to {survey}")
        trees = {"old": old_tree, "new": ROOT}
        res: dict = {"old": [], "new": [], "loop": []}
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
                r = bc._check(bc.run_measured(cmd), f"{which} run")
                res[which].append((r.wall_s, r.cpu_s, r.maxrss_mib, r.user_s, r.sys_s))
                log(f"factory {which}: wall {r.wall_s:.1f} s, CPU {r.cpu_s:.1f} s, {r.maxrss_mib:.0f} MiB")
                shutil.rmtree(out, ignore_errors=True)
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
        "`bench_factory`'s hand-written numpy loop, rotating. CPU: user+sys of the whole process tree.",
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
        "for both). Runs alternate old/new so that a change of load hits both.",
        "",
        f"Load (`uptime`): at start `{load[0]}`; at end `{load[1]}`. Under load, wall time moves "
        "with the other work; CPU user+sys of the child is the steadier figure.",
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
    p.add_argument("--frames", type=int, default=300, help="flight length for apply (default 300)")
    p.add_argument("--repeat", type=int, default=3, help="runs per version and command (default 3)")
    p.add_argument("--out", type=Path, default=None, help="markdown file to update (default: none)")
    p.add_argument("--factory", type=int, default=0, metavar="N",
                   help="instead: factory apply on N MicaSense captures, old vs new vs the hand loop")
    p.add_argument("--settle", type=float, default=0.0, help="--factory: seconds of rest before each run")
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
            res = run_factory(args.old, args.factory, args.repeat, Path(tmp), settle_s=args.settle)
        else:
            res = run(args.old, args.frames, args.repeat, Path(tmp))
    if args.factory:
        md = render_factory(res, old_rev, new_rev, command, args.factory, (load0, uptime()))
    else:
        md = render(res, old_rev, new_rev, command, args.frames, (load0, uptime()))
    print(md)
    if args.out:
        _replace_section(args.out, md, "bench_ab_factory" if args.factory else SECTION_KEY)
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    print(f"done {stamp}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
