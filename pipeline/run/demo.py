"""``mscal demo``: synthesize a complete session with known truth, run the post-flight flow on
it, and score its calibration against the truth."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

from pipeline.run.runner import CALIBRATION_STORE
from pipeline.sim.evaluate import evaluate_calibration
from pipeline.sim.synth import write_session
from pipeline.storage.store import open_calibration

#: The demo session's flights (SPEC: a small but complete session has two).
DEMO_FLIGHTS = ("field", "orchard")


def run_demo(out: str | Path, *, flow: Callable[..., dict[str, Any]], size: str = "small",
             seed: int = 0) -> dict[str, Any]:
    """Write ``out/session`` (synthetic: sweep, vignetting views, reflector images, two
    flights), run ``flow`` (the post-flight flow) on it into ``out`` (``calibration.zarr``,
    ``flights/<name>/``, ``run.json``), and write ``out/evaluation.json``."""
    out = Path(out)
    t0 = time.perf_counter()
    session = write_session(out / "session", seed=seed, size=size, flights=DEMO_FLIGHTS)
    t1 = time.perf_counter()
    record = flow(session=str(session), out=str(out))
    t2 = time.perf_counter()
    ds = open_calibration(out / CALIBRATION_STORE)
    report = out / "report.html"
    summary = {
        "session": str(session),
        "outputs": str(out),
        "run_json": str(out / "run.json"),
        "report": str(report) if report.is_file() else None,
        "calibration": str(out / CALIBRATION_STORE),
        "calibration_cached": record["calibration_cached"],
        "flights": {k: f"{out / 'flights' / k} ({v['frames_out']} frames)" for k, v in record["flights"].items()},
        "seconds": {"synthesize": round(t1 - t0, 1), "post_flight_flow": round(t2 - t1, 1)},
        "skipped": {k: (ds.attrs.get(k) or {}).get("skipped", []) for k in ("response", "vignetting", "illumination")},
        "errors_vs_truth": evaluate_calibration(session, ds),
    }
    (out / "evaluation.json").write_text(json.dumps(summary, indent=2))
    return summary
