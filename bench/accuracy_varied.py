"""Accuracy over varied sessions, end to end through the product (``bench_accuracy.py --varied N``).

For each of ``N`` varied full-size sessions (``pipeline.sim.varied.write_varied_session(path,
k)``: light, noise, response shoulder, marker, views and exposures drawn per session from
random stream 1000 + k), in fresh processes: ``mscal calibrate SESSION`` and ``mscal apply
SESSION/flights/field --calibration CALIB`` with the default options. Then, against the
session's truth:

- the fits: U (5-95 % of the DN range, as the seeds are scored), V (RMS, worst band), S;
- the flight as apply wrote it (``OUT/reflectance.zarr``): gray panels after one scalar per
  frame, the same panel across frames (CV) and vegetation NDVI, on the pixels apply left a
  value (flagged pixels are NaN by default); a panel's value is the mean of its pixels, or,
  where some are flagged high, its median with each of those counted as above its own bound,
  and a panel a tenth flagged or more is not scored (:func:`pipeline.sim.evaluate.panel_value`): how many panels
  (per frame) were scored on such a censored median and how many were not scored are reported;
- beside it, the Eq. 16 baseline (divide by the reflector's DN) on the same frames, and the
  floor: Eq. 15 with the session's true U, V and S (what a perfect calibration scores; the
  panels' own pixel noise, e.g. of a 0.05 panel at ~30 DN above black, is in it), and the
  calibration's own share of the CV: the CV of mscal's (and Eq. 16's) reflectance over the
  floor's on the same pixels, where the pixel noise cancels
  (:func:`pipeline.sim.evaluate.calibration_cv`);
- the flags: pixels apply flagged (``quality`` != 0), the share of panel pixels flagged, and
  flagged pixels that still carry a value (must be 0 with the default options).

The markdown subsection goes between ``<!-- bench_accuracy_varied:start -->`` and
``<!-- bench_accuracy_varied:end -->`` of the output file.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import bench_calibrate as bc  # shared measurement and markdown helpers

SECTION_KEY = "bench_accuracy_varied"
FLIGHT = "field"
#: The flight's figures: key of :func:`pipeline.sim.evaluate.score_flight`, label, key of its
#: target in ``bench_calibrate.ACCURACY_TARGETS``.
FLIGHT_FIGURES = (("panel_abs_error", "gray panels, abs error", "panel"),
                  ("panel_cv_across_frames", "same panel across frames, CV", "cv"),
                  ("vegetation_ndvi_error", "vegetation NDVI, abs error", "ndvi"))
#: The floor (the true calibration's figure) is named in the reading when it comes within this
#: share of the target.
FLOOR_NOTE_SHARE = 0.8


@dataclass
class VariedAccuracy:
    """One varied session's figures."""

    index: int
    params: dict[str, Any]
    calibration: dict[str, Any]
    eq15: dict[str, float]
    eq16: dict[str, float]
    flags: dict[str, float] = field(default_factory=dict)
    truth: dict[str, float] = field(default_factory=dict)


def _child_synth(path: str, index: int) -> None:
    from pipeline.sim.varied import write_varied_session

    write_varied_session(path, int(index))


def product_reflectance(out: Path, flight_dir: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``reflectance`` and ``quality`` (None when apply wrote none) of an apply OUT, frames
    in the order of the flight's frames.csv."""
    import xarray as xr

    from pipeline.ingest.session import read_frame_table

    ds = xr.open_zarr(out / "reflectance.zarr")
    stems = [r.path.stem for r in read_frame_table(flight_dir)]
    ds = ds.sel(frame=stems)
    q = ds["quality"].values if "quality" in ds else None
    return ds["reflectance"].values, q


def flag_counts(refl: np.ndarray, quality: np.ndarray | None, labels: np.ndarray, panels: Sequence[int]) -> dict[str, float]:
    """Flagged pixels of the whole flight and of its gray panels, and flagged pixels left
    with a value (``quality`` != 0 and finite reflectance)."""
    if quality is None:
        return {"flagged_share": float("nan"), "panel_flagged_share": float("nan"), "flagged_with_value": float("nan"),
                "nan_share": float(np.mean(~np.isfinite(refl)))}
    flagged = quality != 0
    on_panel = np.isin(labels, list(panels))[:, None, :, :]
    on_panel = np.broadcast_to(on_panel, flagged.shape)
    return {
        "flagged_share": float(flagged.mean()),
        "panel_flagged_share": float(flagged[on_panel].mean()) if on_panel.any() else float("nan"),
        "flagged_with_value": float(np.count_nonzero(flagged & np.isfinite(refl))),
        "nan_share": float(np.mean(~np.isfinite(refl))),
    }


def run_session(index: int, workdir: Path, keep: bool = False, log: Callable[[str], None] = print) -> VariedAccuracy:
    """Synthesize, calibrate, apply and score varied session ``index``."""
    import xarray as xr

    from pipeline.sim.evaluate import evaluate_calibration, evaluate_flight, panel_labels

    sdir = workdir / f"accuracy{index}"
    session = sdir / "session"
    sdir.mkdir(parents=True, exist_ok=True)
    me = [sys.executable, str(Path(__file__).resolve()), "--child-synth"]
    try:
        bc._check(bc.run_measured([*me, str(session), str(index)]), "synthesis")
        params = json.loads((session / "params.json").read_text())
        calib, out = sdir / "calib.zarr", sdir / "out"
        bc._check(bc.run_measured([*bc.mscal_command(), "calibrate", str(session), "-o", str(calib)]), "mscal calibrate")
        flight_dir = session / "flights" / FLIGHT
        bc._check(bc.run_measured([*bc.mscal_command(), "apply", str(flight_dir), "--calibration", str(calib),
                                   "-o", str(out)]), "mscal apply")
        ds = xr.open_zarr(calib).load()
        truth = np.load(session / "truth.npz")
        fits = evaluate_calibration(session, ds, flights=False)  # the flight is scored on apply's output below
        refl, quality = product_reflectance(out, flight_dir)
        flight = evaluate_flight(session, ds, truth, FLIGHT, reflectance=refl, quality=quality,
                                 calibration_share=True)
        exact = xr.Dataset({"inverse_response": (("band", "dn"), truth["inverse_response"]),
                            "vignetting": (("band", "y", "x"), truth["vignetting"]),
                            "spectral_factor": (("band",), truth["spectral_factor"])})
        floor = evaluate_flight(session, exact, truth, FLIGHT)["eq15"]
        labels = truth[f"flight_{FLIGHT}_labels"]
        flags = flag_counts(refl, quality, labels, panel_labels(truth[f"flight_{FLIGHT}_material_names"]))
        log(f"[accuracy {index}] panel {flight['eq15']['panel_abs_error']:.4f}, CV "
            f"{flight['eq15']['panel_cv_across_frames']:.4f}, flagged {flags['flagged_share']:.4%}")
        return VariedAccuracy(index, params, fits, flight["eq15"], flight["eq16"], flags, floor)
    finally:
        if not keep:
            shutil.rmtree(sdir, ignore_errors=True)


def rows(results: Sequence[VariedAccuracy]) -> list[tuple[bc.Row, ...]]:
    """Each mscal row with its baseline rows after it (Eq. 16, the true calibration)."""
    T = bc.ACCURACY_TARGETS
    c = [r.calibration for r in results]
    pair = []
    pair.append((bc.Row("U: max abs error, 5-95 % DN / U(95 %)", [x["response_max_error"] for x in c], T["response"]),))
    pair.append((bc.Row("V: RMS of V/V_true - 1, worst band", [x.get("vignetting_rms_error", math.nan) for x in c],
                        T["vignetting"]),))
    pair.append((bc.Row("S: max relative error", [x.get("spectral_factor_max_error", math.nan) for x in c],
                        T["spectral"]),))
    for key, label, target in FLIGHT_FIGURES:
        pair.append((bc.Row(f"flight (apply's output): {label}", [r.eq15[key] for r in results], T[target]),
                     bc.Row(f"Eq. 16 baseline: {label}", [r.eq16[key] for r in results], None),
                     bc.Row(f"floor, Eq. 15 with the true U, V, S: {label}",
                            [r.truth.get(key, math.nan) for r in results], None)))
        if key == "panel_cv_across_frames":
            pair.append((bc.Row("flight (apply's output) over the floor, same pixels: CV (the calibration's share)",
                                [r.eq15.get("panel_cv_calibration", math.nan) for r in results], None),
                         bc.Row("Eq. 16 baseline over the floor, same pixels: CV",
                                [r.eq16.get("panel_cv_calibration", math.nan) for r in results], None)))
    for key, label, fmt in (("flagged_share", "pixels flagged", "{:.3%}"),
                            ("panel_flagged_share", "panel pixels flagged", "{:.3%}"),
                            ("nan_share", "pixels without a value (NaN)", "{:.3%}")):
        pair.append((bc.Row(label, [r.flags.get(key, math.nan) for r in results], None, fmt),))
    for key, label in (("panels_censored", "panels scored on a censored median (per frame)"),
                       ("panels_flagged", "panels a tenth flagged or more, not scored (per frame)")):
        pair.append((bc.Row(label, [r.eq15.get(key, math.nan) for r in results], None, "{:.0f}"),))
    pair.append((bc.Row("flagged pixels left with a value", [r.flags.get("flagged_with_value", math.nan) for r in results],
                        0.0, "{:.0f}"),))
    return pair


def render(results: Sequence[VariedAccuracy], command: str) -> str:
    """The markdown subsection: one column per session, the spread, the target and verdict;
    each flight figure with its Eq. 16 baseline and its floor on the next rows."""
    idx = [r.index for r in results]
    head = ["figure"] + [f"s{k}" for k in idx] + ["min", "median", "max", "target", "result"]
    lines = [
        "### Accuracy on varied sessions, end to end",
        "",
        f"`{command}`: sessions 0-{len(results) - 1} of `pipeline.sim.varied.write_varied_session(path, k)` "
        "(full size; what each draws: the calibrate section's parameter table), each through `mscal calibrate` and "
        "`mscal apply` with the default options, scored against the session's truth on the pixels apply left a "
        "value (flagged pixels are NaN by default). Each flight figure has the Eq. 16 baseline (divide by the "
        "reflector's DN) and the floor (Eq. 15 with the session's true U, V and S) on the next rows. A gray "
        "panel's value in a frame and band is the mean of its pixels (the median, with the pixels flagged high "
        "each counted as above its own bound, where some are: `pipeline.sim.evaluate.panel_value`; not scored "
        "a tenth flagged or more); the CV is the worst over the "
        "4 panels and 25 bands of that value over the frame's true light, across the frames. The CV rows "
        "\"over the floor, same pixels\" divide each pixel by the floor's on the same DN, so the pixel noise "
        "cancels and what is left is the calibration's share (`pipeline.sim.evaluate.calibration_cv`).",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(["---"] + ["---:"] * (len(idx) + 4) + [":---:"]) + "|",
    ]
    fails = []
    for group in rows(results):
        for r in group:
            tgt = ("<= " + bc._fmt(r.fmt, r.target)) if r.target is not None else ""
            verdict = r.verdict()
            if verdict.startswith("FAIL"):
                fails.append(f"{r.label} (worst {bc._fmt(r.fmt, r.worst)})")
            cells = [r.label] + [bc._fmt(r.fmt, v) for v in r.values] + bc.spread(r.values, r.fmt) + [tgt, verdict]
            lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(("Targets missed: " + "; ".join(fails) + ".") if fails else "Every target holds on every session.")
    near = [label for key, label, target in FLIGHT_FIGURES
            if any(r.truth.get(key, 0.0) > FLOOR_NOTE_SHARE * bc.ACCURACY_TARGETS[target] for r in results)]
    if near:
        lines.append("")
        lines.append(f"The true calibration itself comes within {1 - FLOOR_NOTE_SHARE:.0%} of the target on "
                     + "; ".join(near) + " on some sessions (floor rows): there the figure is mostly "
            "the panels' own pixel noise, not the calibration; read mscal's row beside its floor and "
            "beside its share over the floor on the same pixels.")
    lines.append("")
    return "\n".join(lines)


def run(n: int, workdir: Path, log: Callable[[str], None] = print) -> list[VariedAccuracy]:
    return [run_session(k, workdir, log=log) for k in range(n)]


if __name__ == "__main__" and len(sys.argv) == 4 and sys.argv[1] == "--child-synth":
    sys.path.insert(0, str(HERE.parent))
    _child_synth(sys.argv[2], int(sys.argv[3]))
