"""End to end on a session drawn to be hard where the flight reads it (pipeline.sim.varied.harsh_params):
a harsh response shoulder, a sweep that ends near the top, a flight exposed so that the 0.9 panel
lies on the shoulder or above the sweep. ``mscal calibrate`` + ``mscal apply`` must flag those
pixels (bit 2 and/or 4), make them NaN (values kept with --keep-flagged), count them in run.json
per frame and band as in the array, warn naming frame and band, and leave the panels within 0.02
of the truth (their medians with the pixels flagged high counted as above them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from mscal_core.quality import FLAGS
from pipeline.run.cli import main
from pipeline.run.console import report_warnings
from pipeline.sim.evaluate import evaluate_flight
from pipeline.sim.varied import harsh_params, write_varied_session

pytestmark = pytest.mark.slow

ON_SHOULDER = FLAGS["response_shoulder"] | FLAGS["outside_sweep"]


@pytest.fixture(scope="module")
def harsh(tmp_path_factory) -> dict[str, Path]:
    """Harsh small session 0 (shoulder from 0.908 of the range, headroom 1.034: U at the clip
    1.4 x U at the knee; the sweep's 99.5 % energy at 0.883 of the range in its longest frame),
    calibrated and applied (default and --keep-flagged)."""
    root = tmp_path_factory.mktemp("harsh")
    session = write_varied_session(root / "session", harsh_params(0), n_flight_frames=3)
    calib = root / "calib.zarr"
    assert main(["-q", "calibrate", str(session), "-o", str(calib)]) == 0
    out = {"session": session, "calib": calib}
    for name, extra in (("default", []), ("keep", ["--keep-flagged"])):
        out[name] = root / name
        assert main(["-q", "apply", str(session / "flights" / "field"), "--calibration", str(calib),
                     "-o", str(out[name]), *extra]) == 0
    return out


def _white(session: Path) -> np.ndarray:
    """(frame, y, x) pure pixels of the 0.9 panel."""
    truth = np.load(session / "truth.npz")
    names = [str(n) for n in truth["flight_field_material_names"]]
    return truth["flight_field_labels"] == names.index("panel_0.90")


def test_the_bright_panel_on_the_shoulder_is_flagged_and_nan(harsh) -> None:
    ds = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    q, refl = ds["quality"].values, ds["reflectance"].values
    raw = xr.open_zarr(harsh["default"] / "raw.zarr")["dn"].values
    white = _white(harsh["session"])
    qw = q.transpose(1, 0, 2, 3)[:, white]  # (band, pixels of the panel in every frame)
    flagged = (qw & ON_SHOULDER) != 0
    # the flight put the panel on the shoulder: a good share of it is flagged, in many bands
    assert flagged.mean() > 0.2
    assert (flagged.mean(axis=1) > 0.05).sum() >= 10
    # the flags follow the DN: every flagged panel pixel reads above the bulk of the unflagged ones
    rw = raw.transpose(1, 0, 2, 3)[:, white]
    for b in np.flatnonzero(flagged.any(axis=1) & (~flagged).any(axis=1)):
        assert rw[b][flagged[b] & (rw[b] < 1023)].min() > np.percentile(rw[b][~flagged[b]], 50)
    # NaN by default wherever flagged, finite on the valid panel pixels
    rwv = refl.transpose(1, 0, 2, 3)[:, white]
    assert np.isnan(rwv[qw != 0]).all() and np.isfinite(rwv[qw == 0]).all()
    # ... and kept with --keep-flagged (except saturated pixels, which have no value)
    keep = xr.open_zarr(harsh["keep"] / "reflectance.zarr")
    np.testing.assert_array_equal(keep["quality"].values, q)
    kw = keep["reflectance"].values.transpose(1, 0, 2, 3)[:, white]
    sat = (qw & FLAGS["saturated"]) != 0
    assert np.isfinite(kw[flagged & ~sat]).all()
    np.testing.assert_array_equal(kw[qw == 0], rwv[qw == 0])


def test_run_json_counts_the_flags_per_frame_and_band_as_the_array(harsh) -> None:
    ds = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    q = ds["quality"].values
    names = [str(b) for b in ds["band_name"].values]
    run = json.loads((harsh["default"] / "run.json").read_text())["quality"]
    assert "response_shoulder" in run["checked"] and "outside_sweep" in run["checked"]
    seen_shoulder = 0
    for f, frame in enumerate(str(x) for x in ds["frame"].values):
        for b, band in enumerate(names):
            want = {name: int(np.count_nonzero(q[f, b] & bit)) for name, bit in FLAGS.items()
                    if np.count_nonzero(q[f, b] & bit)}
            assert run["frames"].get(frame, {}).get(band, {}) == want
            seen_shoulder += want.get("response_shoulder", 0) + want.get("outside_sweep", 0)
    assert seen_shoulder > 1000


def test_the_summary_warns_naming_frame_and_band(harsh) -> None:
    run = json.loads((harsh["default"] / "run.json").read_text())["quality"]
    lines = [w["message"] for w in report_warnings(flights=[harsh["default"]]) if w["code"].startswith("flagged_")]
    on_shoulder = [m for m in lines if "on the response's shoulder" in m or "outside the response sweep" in m]
    assert on_shoulder
    for m in on_shoulder:
        frame, band = m.split(":")[0].removeprefix("frame ").split(", band ")
        n = int(m.split(": ")[1].split(" pixels")[0].replace(",", ""))
        flag = "response_shoulder" if "shoulder" in m else "outside_sweep"
        assert run["frames"][frame][band][flag] == n
        assert m.endswith("set to NaN")


def test_the_panels_on_the_valid_pixels_are_within_0_02(harsh) -> None:
    """Scored with apply's quality mask: a panel's median counts its pixels flagged high as
    above it, a panel half flagged or more in a band is not scored there. The error left is
    U's own where the panel's median reads, just below the shoulder flag's cut (within its
    bound, 0.03 of U): 0.0135 here, 0.009-0.019 on small harsh sessions 0-4."""
    session = harsh["session"]
    ds = xr.open_zarr(harsh["calib"]).load()
    truth = np.load(session / "truth.npz")
    out = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    valid = evaluate_flight(session, ds, truth, "field", reflectance=out["reflectance"].values,
                            quality=out["quality"].values)
    kept = evaluate_flight(session, ds, truth, "field",
                           reflectance=xr.open_zarr(harsh["keep"] / "reflectance.zarr")["reflectance"].values)
    assert valid["eq15"]["panel_abs_error"] < 0.02
    assert valid["eq15"]["panels_censored"] + valid["eq15"]["panels_flagged"] > 0  # the mask was read
    assert kept["eq15"]["panel_abs_error"] > 0.02  # what the flags kept out


def test_normalise_panel_counts_the_panels_flagged_pixels_as_above_it(harsh, tmp_path) -> None:
    """``--normalise panel`` on the 0.9 panel where the shoulder flag cuts it: the scale is
    0.9 over the panel's median with its pixels flagged high counted as above it
    (:func:`mscal_core.quality.region_median`), not over the median of its valid pixels alone,
    which read low."""
    from mscal_core.quality import region_median

    session = harsh["session"]
    ds = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    q, refl = ds["quality"].values, ds["reflectance"].values
    white = _white(session)
    # the frame where most bands have the panel partly (under half) flagged
    share = np.array([[((q[f, b][white[f]] & ON_SHOULDER) != 0).mean() for b in range(q.shape[1])]
                      for f in range(q.shape[0])])
    f = int(np.argmax(((share > 0) & (share < 0.5)).sum(axis=1)))
    ys, xs = np.nonzero(white[f])
    y0, y1, x0, x1 = ys.min() + 1, ys.max(), xs.min() + 1, xs.max()
    box = (slice(None), slice(y0, y1), slice(x0, x1))
    flat = refl[f][box].reshape(refl.shape[1], -1)
    censored = region_median(flat, q[f][box].reshape(flat.shape))
    valid_only = np.nanmedian(flat, axis=1)
    k_censored, k_valid = float(np.nanmedian(0.9 / censored)), float(np.nanmedian(0.9 / valid_only))
    assert abs(k_censored - k_valid) > 1e-4  # the session does tell the two apart
    frame = str(ds["frame"].values[f])
    out = tmp_path / "panel"
    assert main(["-q", "apply", str(session / "flights" / "field"), "--calibration", str(harsh["calib"]),
                 "-o", str(out), "--panel", f"{frame}:{x0},{y0},{x1},{y1}", "--panel-reflectance", "0.9"]) == 0
    scaled = xr.open_zarr(out / "reflectance.zarr")["reflectance"].values
    ok = np.isfinite(refl) & (refl > 0.05)
    np.testing.assert_allclose(np.median(scaled[ok] / refl[ok]), k_censored, rtol=1e-5)


def test_normalise_band_counts_the_bands_flagged_pixels_as_above_its_median(harsh, tmp_path) -> None:
    """``--normalise band:NAME`` divides each frame by the band's median with its pixels
    flagged high counted as above it (its valid pixels alone read low)."""
    from mscal_core.quality import CENSOR_HIGH, region_median

    ds = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    q, refl = ds["quality"].values, ds["reflectance"].values
    high = np.bitwise_and(q, CENSOR_HIGH) != 0
    b = int(np.argmax(high.sum(axis=(0, 2, 3))))  # the band flagged high most often
    name = str(ds["band_name"].values[b])
    want = np.array([1.0 / float(region_median(refl[f, b].ravel(), q[f, b].ravel())) for f in range(len(refl))])
    plain = np.array([1.0 / np.nanmedian(refl[f, b]) for f in range(len(refl))])
    assert np.abs(want / plain - 1).max() > 1e-3  # the flags move this band's median
    out = tmp_path / "band"
    assert main(["-q", "apply", str(harsh["session"] / "flights" / "field"), "--calibration", str(harsh["calib"]),
                 "-o", str(out), "--normalise", f"band:{name}"]) == 0
    scaled = xr.open_zarr(out / "reflectance.zarr")["reflectance"].values
    for f in range(len(refl)):
        ok = np.isfinite(refl[f]) & (refl[f] > 0.05)
        np.testing.assert_allclose(np.median(scaled[f][ok] / refl[f][ok]), want[f], rtol=1e-5)
