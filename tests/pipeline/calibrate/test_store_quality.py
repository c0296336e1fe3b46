"""What the calibration store says about how far U and V can be trusted: the response's
per-DN uncertainty and fitted DN range, the vignetting views' coverage of each pixel; and a
store without them (written by another tool or an older mscal) still opens."""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.calibrate import bands
from pipeline.calibrate import vignetting_stage as vstage
from pipeline.calibrate.intrinsics import with_intrinsics
from pipeline.calibrate.stage import StageReport
from pipeline.calibrate.views import load_marker_frames
from pipeline.ingest.session import load_session
from pipeline.storage.store import open_calibration, write_store


def test_store_carries_the_response_uncertainty_and_range(small) -> None:
    _, calib = small
    ds = xr.open_zarr(calib).load()
    unc, rng = ds["response_uncertainty"], ds["response_dn_range"]
    assert unc.dims == ("band", "dn") and unc.dtype == np.float32 and unc.shape == (25, 1024)
    assert rng.dims == ("band", "end") and rng.dtype == np.int32 and list(ds["end"].values) == ["low", "high"]
    assert len(unc.attrs["noise_variance"]) == 25 and "sigma_I" in unc.attrs["description"]
    lo, hi = rng.sel(end="low").values, rng.sel(end="high").values
    assert np.all(lo < 40) and np.all(hi > 1000)  # the small sweep reaches from near black to the clip
    U = ds["inverse_response"].values
    for b in range(25):
        u = unc.values[b]
        assert np.all(np.isnan(u[:lo[b]])) and np.all(np.isnan(u[hi[b] + 1:]))
        inside = u[lo[b]:hi[b] + 1]
        assert np.all(np.isinf(inside[U[b, lo[b]:hi[b] + 1] == 0]))
        # mid-range: a reading's noise through U's slope, 1-2 % (read 1.5 DN, shot 9 DN at full scale)
        assert 0.008 < float(np.median(u[300:700])) < 0.02
        assert float(np.median(u[990:1011])) > float(np.median(u[300:700]))


def test_coverage_counts_the_views_that_observed_each_pixel(small) -> None:
    session_dir, calib = small
    ds = xr.open_zarr(calib).load()
    cov = ds["vignetting_coverage"]
    assert cov.dims == ("band", "y", "x") and cov.dtype == np.uint16 and cov.shape == ds["vignetting"].shape
    # by hand: each view's observations of the band (7 views: below the screening minimum, all kept)
    U, sat = ds["inverse_response"].values, ds["saturation_dn"].values
    session, _ = with_intrinsics(load_session(session_dir))
    _, stack, views = load_marker_frames(session, session.vignetting_dir, U, StageReport("vignetting"))
    b = session.camera.n_bands // 2
    obs, _ = bands.band_observations(vstage._band_views(session, stack, b, views, U, sat, {}))
    hand = np.zeros(cov.shape[1:], dtype=np.int64)
    for pix, _, _ in obs:
        np.add.at(hand.reshape(-1), pix, 1)
    np.testing.assert_array_equal(cov.values[b], hand)
    c = cov.values[b]
    assert 0 < np.mean(c == 0) < 1 and c.max() <= len(views)  # some pixels never saw the reflector
    assert not np.any(ds["vignetting_observed"].values[b][c == 0])  # V is filled there
    assert np.all(cov.values >= ds["vignetting_count"].values)  # the fit's informative ones are a subset


def test_view_coverage_of_hand_made_observations() -> None:
    empty = np.zeros(0, dtype=np.int64)
    obs = [(np.array([0, 1, 5]), empty, empty), (np.array([1, 5, 7]), empty, empty), (np.array([5]), empty, empty)]
    cov = bands.view_coverage(obs, (2, 4))
    assert cov.dtype == np.uint16
    np.testing.assert_array_equal(cov, [[1, 2, 0, 0], [0, 3, 0, 1]])


def test_store_without_the_quality_variables_still_opens(small, tmp_path) -> None:
    session_dir, calib = small
    camera = load_session(session_dir).camera
    ds = open_calibration(calib, camera)
    bare = ds.drop_vars(["response_uncertainty", "response_dn_range", "vignetting_coverage", "end"])
    path = write_store(bare, tmp_path / "bare.zarr")
    out = open_calibration(path, camera, need="apply")
    assert "response_uncertainty" not in out and "vignetting_coverage" not in out
    np.testing.assert_array_equal(out["inverse_response"].values, ds["inverse_response"].values)
