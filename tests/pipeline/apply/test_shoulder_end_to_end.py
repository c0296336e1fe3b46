"""End to end on a session drawn to be hard where the flight reads it (pipeline.sim.varied.harsh_params):
a harsh response shoulder, a sweep that ends near the top, a flight exposed so that the 0.9 panel
lies on the shoulder or above the sweep. ``mscal calibrate`` + ``mscal apply`` must flag those
pixels (bit 2 and/or 4), make them NaN (values kept with --keep-flagged), count them in run.json
per frame and band as in the array, warn naming frame and band, and leave the panels within 0.02
of the truth (their medians with the pixels flagged high counted as above them)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from mscal_core.quality import CENSOR_HIGH, FLAGS
from pipeline.run.cli import main
from pipeline.run.console import report_warnings
from pipeline.sim.evaluate import evaluate_calibration, evaluate_flight
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


def _band_counts(message: str) -> tuple[str, dict[str, int]]:
    """The frame and per band pixels a ``flagged_*`` warning names."""
    m = re.fullmatch(r"frame (\S+): [\d,]+ pixels .+ in \d+ bands? \((.+)\), (set to NaN|kept)", message)
    assert m is not None, message
    return m.group(1), {p.split(" ")[0]: int(p.split(" ")[1].replace(",", "")) for p in m.group(2).split(", ")}


def test_the_summary_warns_per_frame_naming_every_band(harsh) -> None:
    """One line per frame and flag names each band with its count, as run.json counts it, and
    every frame and band on the shoulder is named (3 frames x 3 flags: under the line limit)."""
    run = json.loads((harsh["default"] / "run.json").read_text())["quality"]
    lines = [w for w in report_warnings(flights=[harsh["default"]])
             if w["code"] in ("flagged_response_shoulder", "flagged_outside_sweep")]
    named: set[tuple[str, str, str]] = set()
    for w in lines:
        flag = w["code"].removeprefix("flagged_")
        frame, per_band = _band_counts(w["message"])
        assert per_band == {b: c[flag] for b, c in run["frames"][frame].items() if c.get(flag)}
        assert w["value"] == sum(per_band.values())
        assert w["message"].endswith("set to NaN")
        named |= {(frame, b, flag) for b in per_band}
    want = {(f, b, flag) for f, bands in run["frames"].items() for b, c in bands.items()
            for flag in ("response_shoulder", "outside_sweep") if c.get(flag)}
    assert named == want and len(want) >= 10


def test_the_panels_on_the_valid_pixels_are_within_0_02(harsh) -> None:
    """Scored with apply's quality mask: a panel's median counts its pixels flagged high as
    above it, a panel a tenth flagged or more in a band is not scored there. The error left is
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


def test_normalise_panel_counts_the_panels_flagged_pixels_above_their_own_bounds(harsh, tmp_path,
                                                                                 monkeypatch) -> None:
    """``--normalise panel`` on a gray panel where the shoulder flag cuts it (of the 0.9 and
    0.5 panels, the frame and panel with the most bands partly, under half, flagged): the
    scale is the panel's reflectance over its median with each pixel flagged high counted as
    above its own bound (:func:`mscal_core.quality.region_median`'s product-limit median),
    not over the median of its valid pixels alone, which read low. The bound is Eq. 15 of the
    highest trusted DN at the pixel: never above the value its own reading gives
    (``--keep-flagged``, U rises with DN), and close under it (the cut is just below)."""
    import pipeline.apply.options as options_module
    from mscal_core.quality import region_median

    seen = []

    def recording(values, quality, *args, **kwargs):
        seen.append((values, quality, kwargs))
        return region_median(values, quality, *args, **kwargs)

    monkeypatch.setattr(options_module, "region_median", recording)

    session = harsh["session"]
    ds = xr.open_zarr(harsh["default"] / "reflectance.zarr")
    q, refl = ds["quality"].values, ds["reflectance"].values
    truth = np.load(session / "truth.npz")
    names = [str(n) for n in truth["flight_field_material_names"]]
    cut = []
    for rho in (0.9, 0.5):
        mask = truth["flight_field_labels"] == names.index(f"panel_{rho:.2f}")
        share = np.array([[((q[f, b][mask[f]] & ON_SHOULDER) != 0).mean() for b in range(q.shape[1])]
                          for f in range(q.shape[0])])
        partly = ((share > 0) & (share < 0.5)).sum(axis=1)
        cut.append((int(partly.max()), rho, int(np.argmax(partly)), mask))
    n_cut, rho, f, mask = max(cut, key=lambda c: c[0])
    assert n_cut >= 3
    ys, xs = np.nonzero(mask[f])
    y0, y1, x0, x1 = ys.min() + 1, ys.max(), xs.min() + 1, xs.max()
    box = (slice(None), slice(y0, y1), slice(x0, x1))
    flat = refl[f][box].reshape(refl.shape[1], -1)
    censored = region_median(flat, q[f][box].reshape(flat.shape))
    valid_only = np.nanmedian(flat, axis=1)
    k_censored, k_valid = float(np.nanmedian(rho / censored)), float(np.nanmedian(rho / valid_only))
    assert abs(k_censored - k_valid) > 1e-4  # the session does tell the two apart
    frame = str(ds["frame"].values[f])
    out = tmp_path / "panel"
    assert main(["-q", "apply", str(session / "flights" / "field"), "--calibration", str(harsh["calib"]),
                 "-o", str(out), "--panel", f"{frame}:{x0},{y0},{x1},{y1}", "--panel-reflectance", str(rho)]) == 0
    scaled = xr.open_zarr(out / "reflectance.zarr")["reflectance"].values
    ok = np.isfinite(refl) & (refl > 0.05)
    (values, quality, kwargs), = seen
    bounds = kwargs["censor_at"]
    high = (quality & CENSOR_HIGH) != 0
    assert bounds.shape == flat.shape and high.sum() > 50
    kept = xr.open_zarr(harsh["keep"] / "reflectance.zarr")["reflectance"].values[f][box].reshape(flat.shape)
    assert np.isfinite(bounds[high]).mean() > 0.9
    both = high & np.isfinite(bounds) & np.isfinite(kept)
    ratio = bounds[both] / kept[both]
    assert ratio.max() <= 1.0 + 1e-5 and np.median(ratio) > 0.9
    k_bounded = float(np.nanmedian(rho / region_median(values, quality, censor_at=bounds)))
    np.testing.assert_allclose(np.median(scaled[ok] / refl[ok]), k_bounded, rtol=1e-5)
    print(f"scale: bounded {k_bounded:.5f}, counted above {k_censored:.5f}, valid alone {k_valid:.5f}; "
          f"bound / own value {np.median(ratio):.4f} (min {ratio.min():.4f})")


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


def _response_error_on_valid_dn(ds: xr.Dataset, truth) -> float:
    """U's error as the fits are scored (5-95 % of the DN range, a fraction of U(95 %), up to
    U's scale: :func:`mscal_core.metrics.response_error`) on the DN the quality mask leaves
    valid (:func:`mscal_core.quality.dn_flag_table` with the store's tables), worst band."""
    from mscal_core.quality import DEFAULT_BOUND, dn_flag_table

    U, Ut = ds["inverse_response"].values, truth["inverse_response"]
    flags = dn_flag_table(U.shape[0], U.shape[1], int(ds["saturation_dn"].values.min()),
                          ds["response_uncertainty"].values, DEFAULT_BOUND, ds["response_dn_range"].values)
    hi = int(np.floor(0.95 * (U.shape[1] - 1)))
    k = np.arange(int(np.ceil(0.05 * (U.shape[1] - 1))), hi + 1)
    worst = 0.0
    for b in range(U.shape[0]):
        s = float(U[b, k] @ Ut[b, k] / (U[b, k] @ U[b, k]))
        ok = k[flags[b, k] == 0]
        worst = max(worst, float(np.max(np.abs(s * U[b, ok] - Ut[b, ok]))) / float(Ut[b, hi]))
    return worst


@pytest.mark.long  # a full-size session written, calibrated and applied twice: ~2-3 min
def test_a_full_size_harsh_session_end_to_end(tmp_path) -> None:
    """Full-size harsh session 0 (25 bands, 14-frame sweep stopping at 0.883 of the range, 8
    flight frames exposed to 0.96-0.99) through ``mscal calibrate`` and ``mscal apply`` with
    the default options: every frame and band on the shoulder warned of, its pixels flagged and
    NaN, kept with --keep-flagged, and the fits and the flight on the valid pixels. Measured on
    full-size harsh sessions 0-4: U on the valid DN 0.0061-0.0092 (0.0065-0.035 over the whole
    5-95 %, i.e. where U is extrapolated above the sweep), V 0.0049-0.0098, S 0.0018-0.0053,
    panels 0.0044-0.0138 (session 3: the 0.9 panel at DN 953-973 in one band, where U is 1 %
    off, inside its stated uncertainty of ~2 %), NDVI <= 0.0005; session 0 here."""
    session = write_varied_session(tmp_path / "session", harsh_params(0, size="full"))
    calib = tmp_path / "calib.zarr"
    assert main(["-q", "calibrate", str(session), "-o", str(calib)]) == 0
    outs = {}
    for name, extra in (("default", []), ("keep", ["--keep-flagged"])):
        outs[name] = tmp_path / name
        assert main(["-q", "apply", str(session / "flights" / "field"), "--calibration", str(calib),
                     "-o", str(outs[name]), *extra]) == 0
    ds, truth = xr.open_zarr(calib).load(), np.load(session / "truth.npz")
    out = xr.open_zarr(outs["default"] / "reflectance.zarr")
    q, refl = out["quality"].values, out["reflectance"].values
    frames, bands = [str(f) for f in out["frame"].values], [str(b) for b in out["band_name"].values]
    run = json.loads((outs["default"] / "run.json").read_text())["quality"]
    # flagged, NaN, counted as in the array; every frame and band on the shoulder warned of
    on = (q & ON_SHOULDER) != 0
    assert on.any(axis=(2, 3)).sum() >= 40 and on.any(axis=(1, 2, 3)).all()  # 83 frame/bands, all 8 frames
    assert np.isnan(refl[q != 0]).all() and np.isfinite(refl[q == 0]).all()
    warned = set()
    for w in report_warnings(flights=[outs["default"]]):
        if w["code"] in ("flagged_response_shoulder", "flagged_outside_sweep"):
            frame, per_band = _band_counts(w["message"])
            flag = w["code"].removeprefix("flagged_")
            assert per_band == {b: c[flag] for b, c in run["frames"][frame].items() if c.get(flag)}
            warned |= {(frame, b) for b in per_band}
    assert warned == {(frames[f], bands[b]) for f, b in zip(*np.nonzero(on.any(axis=(2, 3))))}
    for f, frame in enumerate(frames):
        for b, band in enumerate(bands):
            want = {n: int(np.count_nonzero(q[f, b] & bit)) for n, bit in FLAGS.items() if np.count_nonzero(q[f, b] & bit)}
            assert run["frames"].get(frame, {}).get(band, {}) == want
    keep = xr.open_zarr(outs["keep"] / "reflectance.zarr")
    kq, kr = keep["quality"].values, keep["reflectance"].values
    np.testing.assert_array_equal(kq, q)
    assert np.isfinite(kr[(q != 0) & ((q & FLAGS["saturated"]) == 0)]).all()
    # the targets on the valid pixels (the panels: see the docstring)
    fits = evaluate_calibration(session, ds, flights=False)
    assert _response_error_on_valid_dn(ds, truth) < 0.02  # 0.0068
    assert fits["vignetting_rms_error"] < 0.015 and fits["spectral_factor_max_error"] < 0.01  # 0.0098, 0.0038
    flight = evaluate_flight(session, ds, truth, "field", reflectance=refl, quality=q)["eq15"]
    assert flight["panel_abs_error"] < 0.01 and flight["vegetation_ndvi_error"] < 0.01  # 0.0063, 0.0002
    # scored up to half flagged (the product-limit median, as --normalise panel keeps): the
    # panels the shoulder cuts by a tenth to a half read on the valid pixels just under the cut
    half = evaluate_flight(session, ds, truth, "field", reflectance=refl, quality=q, max_flagged_share=0.5)["eq15"]
    assert half["panels_flagged"] < flight["panels_flagged"] and half["panels_censored"] > flight["panels_censored"]
    assert half["panel_abs_error"] < 0.015  # 0.0103 (0.0037-0.0103 on full-size harsh sessions 0-4)
    kept = evaluate_flight(session, ds, truth, "field", reflectance=kr)["eq15"]
    assert kept["panel_abs_error"] > 0.02  # 0.029: what the flags kept out
