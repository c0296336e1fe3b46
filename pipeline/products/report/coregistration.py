"""Band co-registration of a flight as measured on its pixels (run.json ``coregistration``,
:mod:`pipeline.apply.coregistration`): a table per band and the ``band_misregistration``
warning."""

from __future__ import annotations

from typing import Any, Sequence

from pipeline.products.report.table import Table
from pipeline.products.report.thresholds import BAND_MISREGISTRATION_MAX_PX, QAWarning
from pipeline.storage.run_layout import run_value


def coregistration_tables(run: dict[str, Any], band_names: Sequence[str] = ()) -> list[Table]:
    """Per band: the residual shift against the reference band after the run's alignment
    (median and max over the measured captures), without it, and what was measured; with the
    metadata check's numbers when the band files' own registration was judged. [] for runs
    without a measurement (single-file cameras, earlier runs)."""
    rec = run_value(run, "coregistration")
    if not isinstance(rec, dict):
        return []
    flight = rec.get("flight") or {}
    order = [b for b in band_names if b in flight] + sorted(b for b in flight if b not in band_names)
    check = rec.get("metadata_check") or {}
    meta = check.get("metadata_px") or {}
    none = rec.get("alignment") == "none"  # then the residual is the unaligned one
    rows = [[b, flight[b].get("median_px"), flight[b].get("max_px"),
             flight[b].get("median_px" if none else "unaligned_median_px"), meta.get(b), flight[b].get("captures"),
             flight[b].get("tiles")] for b in order]
    sample = rec.get("sample") or {}
    note = (f"against band {rec.get('reference_band')} after: {rec.get('alignment')}; {sample.get('captures')} "
            f"survey capture(s) of {sample.get('of')} (every {sample.get('every')}), at {sample.get('max_side_px')} "
            f"px on the long side; {rec.get('method', '')}")
    if check.get("decision"):
        note += f". Metadata check on {', '.join(check.get('captures') or [])}: {check['decision']}"
    return [Table("Band co-registration (measured on the pixels, px)",
                  ["band", "residual median", "residual max", "without alignment", "metadata alone", "captures",
                   "tiles"], rows, note=note)]


def coregistration_warnings(run: dict[str, Any]) -> list[QAWarning]:
    """``band_misregistration``: a band whose median residual shift against the reference band
    is above :data:`BAND_MISREGISTRATION_MAX_PX` after the run's alignment."""
    rec = run_value(run, "coregistration")
    if not isinstance(rec, dict):
        return []
    flight = rec.get("flight") or {}
    bad = {b: r["median_px"] for b, r in flight.items() if (r.get("median_px") or 0.0) > BAND_MISREGISTRATION_MAX_PX}
    if not bad:
        return []
    worst = max(bad.values())
    alignment = rec.get("alignment", "none")
    hint = ("align them: mscal register CAPTURES -o REG.zarr, then apply with --registration REG.zarr"
            if alignment == "none" else "check the alignment; mscal register CAPTURES -o REG.zarr and "
            "--registration REG.zarr aligns by image registration")
    listed = ", ".join(f"{b} {v:.1f} px" for b, v in sorted(bad.items(), key=lambda kv: -kv[1]))
    return [QAWarning("band_misregistration",
                      f"bands are off band {rec.get('reference_band')} after alignment '{alignment}' by "
                      f"{listed} (median over {(rec.get('sample') or {}).get('captures')} measured capture(s), "
                      f"run.json coregistration): per-pixel indices mix neighbouring ground points; {hint}",
                      float(worst), BAND_MISREGISTRATION_MAX_PX)]
