"""The vignetting stage's view screening (Eq. 8-10 per band): a dropped view costs one band
fit more, not every band twice, and the band refitted from its first fit's V is the fit of
the views kept."""

from __future__ import annotations

import numpy as np
import xarray as xr

from mscal_core import vignetting
from pipeline.calibrate import bands
from pipeline.calibrate import vignetting_stage as vstage
from pipeline.calibrate.intrinsics import with_intrinsics
from pipeline.calibrate.pool import BandPool
from pipeline.calibrate.stage import StageReport
from pipeline.calibrate.views import load_marker_frames
from pipeline.ingest.session import load_session


def test_a_dropped_view_refits_one_band_not_all(small, monkeypatch) -> None:
    session_dir, calib = small
    store = xr.open_zarr(calib).load()
    U, sat = store["inverse_response"].values, store["saturation_dn"].values
    session, _ = with_intrinsics(load_session(session_dir))
    report = StageReport("vignetting")
    _, stack, views = load_marker_frames(session, session.vignetting_dir, U, report)
    assert len(views) == 7
    # the screening finds view 2 wrong (the small session has 7 views, below the default
    # minimum for screening)
    monkeypatch.setattr(vstage, "MIN_VIEWS_TO_SCREEN", 3)
    monkeypatch.setattr(vignetting, "inconsistent_views", lambda frac, *a, **k: np.array([2]))
    calls: list[bool] = []
    fit_vignetting = vignetting.fit_vignetting

    def counted(*args, **kwargs):
        calls.append(kwargs.get("start") is not None)
        return fit_vignetting(*args, **kwargs)

    monkeypatch.setattr(vignetting, "fit_vignetting", counted)
    with BandPool(1) as pool:
        fits, _, kept = vstage._fit_band_vignetting(session, stack, views, U, sat, report, pool, lambda: None)
    n_bands = session.camera.n_bands
    # one worker: the reference band on all views, then again from its V, then the others once
    assert len(calls) == n_bands + 1 and calls[1] and sum(calls) == 1
    assert len(kept) == 6 and views[2] not in kept
    assert report.skipped[-1]["file"] == views[2][1].record.path.name == "view_02.tif"
    assert "marker pose likely wrong" in report.skipped[-1]["reason"]
    # the warm-started refit is the fit of the kept views from the log-domain start, within
    # the alternation's stopping tolerance
    ref = n_bands // 2
    monkeypatch.setattr(vignetting, "fit_vignetting", fit_vignetting)
    scratch = bands.vignetting_band(vstage._band_views(session, stack, ref, kept, U, sat, {}))[0]
    np.testing.assert_array_equal(fits[ref].observed, scratch.observed)
    assert np.max(np.abs(fits[ref].vignetting - scratch.vignetting)) < 2e-4


def test_each_views_robust_weight_is_recorded(small) -> None:
    """The band fits' robust weights land in the views' ``marker_poses`` records, one per
    band: ~1 for the clean views, less for a view made 20 % darker in DN (7 views: too few
    to screen, so only the robust loss keeps it from pulling V; with 7 views it also pulls
    the fit, so its own residual, and weight, is not as far off as with 40)."""
    session_dir, calib = small
    store = xr.open_zarr(calib).load()
    U, sat = store["inverse_response"].values, store["saturation_dn"].values
    session, _ = with_intrinsics(load_session(session_dir))
    report = StageReport("vignetting")
    _, stack, views = load_marker_frames(session, session.vignetting_dir, U, report)
    dark = views[4][0]
    stack = stack.copy()
    stack[dark] = np.round(stack[dark] * 0.8).astype(stack.dtype)
    with BandPool(1) as pool:
        fits, _, kept = vstage._fit_band_vignetting(session, stack, views, U, sat, report, pool, lambda: None)
    assert len(kept) == len(views) == 7
    assert not any("likely wrong" in s["reason"] for s in report.skipped)
    records = {r["file"]: r["robust_weight"] for r in report.residuals["marker_poses"]}
    n_bands = session.camera.n_bands
    assert set(records) == {v.record.path.name for _, v in views}
    assert all(len(w) == n_bands for w in records.values())
    bad = records.pop(views[4][1].record.path.name)
    assert max(bad) < 0.7  # measured 0.64-0.66
    assert min(min(w) for w in records.values()) > 0.95  # measured 1.0 (no view offset, no tails)
    assert max(max(w) for w in records.values()) < 1.1
