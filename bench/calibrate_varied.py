"""The varied sessions of ``bench/bench_calibrate.py --varied N``: ``mscal calibrate`` on N
full-size sessions of ``pipeline.sim.varied`` (light, noise, response shoulder, marker,
viewpoints, exposures and vignetting drawn per session), measured as the benchmark's seeds are.

Session ``k`` (k = 0 .. N-1) is ``write_varied_session(path, k)``: its parameters are
``draw_params(k)``, whose random stream is ``SEED_BASE + k`` (1000 + k), apart from the seeds of
``write_session``. Per session, each command in a fresh process under the benchmark's launcher
(``bench_calibrate.run_measured``): the synthesis (not part of the figures), the I/O floor
(read and demosaic every calibration frame), and ``mscal calibrate`` twice with the default
settings (the faster run is the speed figure, as for the seeds; the other's figures are kept
too). Accuracy is ``pipeline.sim.evaluate.evaluate_calibration`` of the first run's store.

Importing this module runs nothing; it is imported by ``bench_calibrate.py`` only with
``--varied``.
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import bench_calibrate as bc

#: Speed and memory targets on every varied session (all processes counted).
VARIED_WALL_TARGET_S = 10.0
VARIED_RSS_TARGET_MIB = 1024.0


@dataclass
class VariedResult:
    """One varied session: its parameters, the measured runs and the evaluation."""

    index: int
    params: dict[str, Any]
    synth: bc.Run
    floor: bc.Run
    runs: list[bc.Run]
    evaluation: dict[str, Any]
    stage_seconds: dict[str, float] = field(default_factory=dict)
    views_skipped: int = 0
    views_inconsistent: int = 0

    @property
    def fastest(self) -> bc.Run:
        return min(self.runs, key=lambda r: r.wall_s)

    @property
    def peak_rss_mib(self) -> float:
        return max(r.maxrss_mib for r in self.runs)


def child_synth(path: str, index: int) -> None:
    """The synthesis of varied session ``index`` (run in a child process)."""
    from pipeline.sim.varied import write_varied_session

    write_varied_session(path, int(index))


def run_varied_session(index: int, workdir: Path, keep: bool, log: Callable[[str], None] = print) -> VariedResult:
    import xarray as xr

    from pipeline.sim.evaluate import evaluate_calibration

    sdir = workdir / f"varied{index}"
    session = sdir / "session"
    sdir.mkdir(parents=True, exist_ok=True)
    me = [sys.executable, str(HERE / "bench_calibrate.py")]
    try:
        log(f"[varied {index}] synthesizing in {session}")
        synth = bc._check(bc.run_measured(me + ["--_child", "synth-varied", str(session), str(index)]), "synthesis")
        params = json.loads((session / "params.json").read_text())
        floor = bc._check(bc.run_measured(me + ["--_child", "io-floor", str(session)]), "I/O floor")
        runs = []
        for k in range(2):
            store = sdir / f"calib-{k}.zarr"
            runs.append(bc._check(bc.run_measured(bc.mscal_command() + ["calibrate", str(session), "-o", str(store)]),
                                  "mscal calibrate"))
            log(f"[varied {index}]   calibrate {runs[-1].wall_s:.1f} s, {runs[-1].cpu_s:.1f} s CPU, "
                f"{runs[-1].maxrss_mib:.0f} MiB")
        store = sdir / "calib-0.zarr"
        ev = evaluate_calibration(session, store)
        attrs = xr.open_zarr(store).attrs
        stages = {k: float((attrs.get(k) or {}).get("seconds", float("nan"))) for k in ("response", "vignetting", "illumination")}
        skipped = (attrs.get("vignetting") or {}).get("skipped", [])
        wrong = sum("marker pose likely wrong" in s.get("reason", "") for s in skipped)
        return VariedResult(index, params, synth, floor, runs, ev, stages, len(skipped), wrong)
    finally:
        if not keep:
            shutil.rmtree(sdir, ignore_errors=True)


def _rows(results: Sequence[VariedResult]) -> list[bc.Row]:
    T = bc.ACCURACY_TARGETS
    fl = [bc._flight(r.evaluation, "eq15") for r in results]
    ev = [r.evaluation for r in results]
    return [
        bc.Row("`mscal calibrate` wall, faster of two runs (s)", [r.fastest.wall_s for r in results],
               VARIED_WALL_TARGET_S, "{:.1f}", anchor="varied-wall"),
        bc.Row("`mscal calibrate` wall, other run (s)", [max(x.wall_s for x in r.runs) for r in results], None, "{:.1f}"),
        bc.Row("`mscal calibrate` CPU user+sys of the faster run (s)", [r.fastest.cpu_s for r in results], None, "{:.1f}"),
        bc.Row("`mscal calibrate` peak RSS, all processes, worst run (MiB)", [r.peak_rss_mib for r in results],
               VARIED_RSS_TARGET_MIB, "{:.0f}", anchor="varied-rss"),
        bc.Row("I/O floor wall (s)", [r.floor.wall_s for r in results], None, "{:.1f}"),
        bc.Row("wall / I/O floor", [r.fastest.wall_s / r.floor.wall_s for r in results], None, "{:.1f}x"),
        bc.Row("stage: response (s)", [r.stage_seconds.get("response", float("nan")) for r in results], None, "{:.1f}"),
        bc.Row("stage: vignetting (s)", [r.stage_seconds.get("vignetting", float("nan")) for r in results], None, "{:.1f}"),
        bc.Row("stage: illumination (s)", [r.stage_seconds.get("illumination", float("nan")) for r in results], None,
               "{:.1f}"),
        bc.Row("vignetting views skipped (of 40)", [float(r.views_skipped) for r in results], None, "{:.0f}"),
        bc.Row("of which: marker pose likely wrong", [float(r.views_inconsistent) for r in results], None, "{:.0f}"),
        bc.Row("1-min load average before `mscal calibrate`", [r.runs[0].load_before[0] for r in results], None, "{:.2f}"),
        bc.Row("response: max abs U error, 5-95 % DN / U(95 %)", [e["response_max_error"] for e in ev], T["response"],
               anchor="varied-response"),
        bc.Row("vignetting: RMS of V/V_true - 1 (all pixels, worst band)", [e["vignetting_rms_error"] for e in ev],
               T["vignetting"], anchor="varied-vignetting"),
        bc.Row("vignetting: same, observed pixels only", [e.get("vignetting_rms_error_observed", float("nan")) for e in ev],
               None),
        bc.Row("spectral factor S: max relative error", [e["spectral_factor_max_error"] for e in ev], T["spectral"],
               anchor="varied-spectral"),
        bc.Row("flight, Eq. 15: gray panel reflectance, abs error", [x["panel_abs_error"] for x in fl], T["panel"]),
        bc.Row("flight, Eq. 15: vegetation NDVI, abs error", [x["vegetation_ndvi_error"] for x in fl], T["ndvi"]),
        bc.Row("flight, Eq. 15: same panel across frames, CV", [x["panel_cv_across_frames"] for x in fl], T["cv"]),
    ]


def table(rows: Sequence[bc.Row], indices: Sequence[int]) -> str:
    """Per-session figures, their spread (min / median / max) and the verdict against the target."""
    head = ["figure"] + [f"session {k}" for k in indices] + ["min", "median", "max", "target", "result"]
    lines = ["| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] + ["---:"] * (len(indices) + 4) + [":---:"]) + "|"]
    for r in rows:
        tgt = ("<= " + bc._fmt(r.fmt, r.target)) if r.target is not None else ""
        label = (f'<a id="{r.anchor}"></a>' if r.anchor else "") + r.label
        cells = [label] + [bc._fmt(r.fmt, v) for v in r.values] + bc.spread(r.values, r.fmt) + [tgt, r.verdict()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


_PARAM_COLUMNS = (
    ("light a", "light_nonuniformity", "{:.2f}"), ("gradient (deg)", "light_gradient_deg", "{:.0f}"),
    ("read / shot noise (DN)", ("read_noise_dn", "shot_noise_dn_at_full"), "{:.1f}"),
    ("shoulder", "shoulder_start", "{:.2f}"), ("marker + border (m)", ("marker_size_m", "marker_border_m"), "{:.3f}"),
    ("distance (m)", "distance_m", "{:.2f}"), ("tilt (deg)", "max_tilt_deg", "{:.0f}"),
    ("views: missing / cut marker", ("n_missing", "n_partial"), "{:.0f}"), ("view exposure", "view_exposure", "{:.2f}"),
    ("sweep step", "sweep_step", "{:.2f}"), ("V falloff", "vignetting_falloff", "{:.2f}"),
)


def params_table(results: Sequence[VariedResult]) -> str:
    """What each session drew (``pipeline.sim.varied.draw_params``)."""
    head = ["session", "stream"] + [c[0] for c in _PARAM_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---:"] * len(head)) + "|"]
    for r in results:
        cells = [str(r.index), str(r.params.get("seed"))]
        for _, keys, fmt in _PARAM_COLUMNS:
            vals = [r.params[k] for k in keys] if isinstance(keys, tuple) else [r.params[keys]]
            flat = [x for v in vals for x in (v if isinstance(v, list) else [v])]
            cells.append(" / ".join(bc._fmt(fmt, float(x)) for x in flat))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render(results: Sequence[VariedResult]) -> str:
    """The markdown subsection of the varied sessions."""
    indices = [r.index for r in results]
    rows = _rows(results)
    fails = [r for r in rows if r.verdict().startswith("FAIL")]
    parts = [
        "### Varied sessions",
        "",
        f"`--varied {len(results)}`: sessions 0-{len(results) - 1} of `pipeline.sim.varied.write_varied_session(path, k)` "
        "(parameters `draw_params(k)`, random stream 1000 + k; full size: 14-frame sweep, 40 viewpoints, 3 reflector "
        "images, 8 flight frames). Each command in its own fresh process, as for the seeds; `mscal calibrate` twice "
        "per session, the faster run is the speed figure and the peak RSS is the worse of the two. Targets here: "
        f"<= {VARIED_WALL_TARGET_S:.0f} s wall and <= {VARIED_RSS_TARGET_MIB:.0f} MiB on every session, and the "
        "accuracy targets of the seeds.",
        "",
        params_table(results),
        "",
        table(rows, indices),
        "",
    ]
    if fails:
        parts.append("Targets missed on varied sessions: " + "; ".join(
            f"{r.label} (worst {bc._fmt(r.fmt, r.worst)}, target {bc._fmt(r.fmt, r.target)})" for r in fails) + ".")
    else:
        parts.append("Every target holds on every varied session.")
    parts.append("")
    return "\n".join(parts)
