"""``mscal demo``: synthesize a session with known truth, calibrate it, score the fits."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from .calibrate import calibrate_session
from .evaluate import evaluate_calibration
from .synth import write_session


def run_demo(out: str | Path, *, size: str = "small", seed: int = 0) -> dict[str, Any]:
    """Write ``out/session`` (synthetic), ``out/calibration.zarr`` and ``out/evaluation.json``."""
    out = Path(out)
    t0 = time.perf_counter()
    session = write_session(out / "session", seed=seed, size=size)
    t1 = time.perf_counter()
    calib = out / "calibration.zarr"
    ds = calibrate_session(session, calib)
    t2 = time.perf_counter()
    errors = evaluate_calibration(session, ds)
    summary = {
        "session": str(session),
        "calibration": str(calib),
        "seconds": {"synthesize": round(t1 - t0, 1), "calibrate": round(t2 - t1, 1)},
        "skipped": {k: (ds.attrs.get(k) or {}).get("skipped", []) for k in ("response", "vignetting", "illumination")},
        "errors_vs_truth": errors,
    }
    (out / "evaluation.json").write_text(json.dumps(summary, indent=2))
    return summary
