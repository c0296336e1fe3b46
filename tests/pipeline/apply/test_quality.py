"""reflectance.zarr's ``quality`` mask (pipeline.apply.quality): a flight whose pixels reach the
response's shoulder gets the bits, NaN by default and its values with --keep-flagged, per-frame
warnings naming the band, run.json counts equal to the array's; a store without the optional
variables applies as before and says which flags it checked."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tifffile
import xarray as xr

from mscal_core.quality import FLAGS
from pipeline.apply.bandgrid import one_grid
from pipeline.apply.coregistration import RESIDUAL_MAX_PX
from pipeline.apply.quality import (
    FACTORY_CHECKS,
    Flagging,
    checked,
    counts,
    finish,
    finish_counted,
    not_coregistered,
    on_grid,
    quality_record,
)
from pipeline.apply.stores import geometry_step
from pipeline.products.report.flight import MAX_FLAGGED_LINES, flagged_pixels
from pipeline.run.cli import main
from pipeline.run.console import report_warnings

SHOULDER_FROM = 400  # DN from which U's relative uncertainty passes 0.03 (0.01 + 1e-3 per DN above 400)
LOW = 50  # the sweep's lowest DN
FIT_SHARE = 0.002  # the fit's own share of U's uncertainty in that store (its bound: 0.0033)


def _with_quality_variables(calib: Path, dst: Path) -> Path:
    """The calibration store with ``response_uncertainty``, ``response_dn_range`` and
    ``vignetting_coverage`` (as a calibration that writes them would: NaN outside the fit)."""
    ds = xr.open_zarr(calib).load()
    nb, ndn = ds.sizes["band"], ds.sizes["dn"]
    dn = np.arange(ndn)
    unc = np.where(dn < SHOULDER_FROM, 0.01, 0.01 + (dn - SHOULDER_FROM) * 1e-3)
    unc = np.broadcast_to(unc, (nb, ndn)).astype(np.float32).copy()
    unc[:, :LOW] = np.nan
    ds["response_uncertainty"] = (("band", "dn"), unc)
    fit = np.where(np.isnan(unc), np.nan, FIT_SHARE).astype(np.float32)  # under the fit bound: the total decides
    ds["response_fit_uncertainty"] = (("band", "dn"), fit)
    ds["response_dn_range"] = (("band", "end"), np.tile(np.array([[LOW, ndn - 2]], np.int32), (nb, 1)))
    ds = ds.assign_coords(end=["low", "high"])
    cov = np.full(ds["vignetting"].shape, 3, np.uint16)
    cov[:, :6, :10] = 0
    ds["vignetting_coverage"] = (("band", "y", "x"), cov)
    for v in ds.variables.values():
        v.encoding = {}
    ds.to_zarr(dst, mode="w", zarr_format=3, consolidated=True)
    return dst


def _without_quality_variables(calib: Path, dst: Path) -> Path:
    """The calibration store without the optional variables (as another tool, or an mscal
    before them, writes it)."""
    ds = xr.open_zarr(calib).load().drop_vars(["response_uncertainty", "response_fit_uncertainty", "response_dn_range",
                                                "vignetting_coverage"], errors="ignore")
    ds = ds.drop_dims([d for d in ("end",) if d in ds.dims])
    for v in ds.variables.values():
        v.encoding = {}
    ds.to_zarr(dst, mode="w", zarr_format=3, consolidated=True)
    return dst


@pytest.fixture(scope="module")
def flagged(small, tmp_path_factory) -> dict[str, Path]:
    """The small flight applied with the store of every variable (default and --keep-flagged)
    and with a store without the optional variables."""
    session, calib = small
    root = tmp_path_factory.mktemp("quality")
    store = _with_quality_variables(calib, root / "calib_q.zarr")
    plain = _without_quality_variables(calib, root / "calib_plain.zarr")
    flight = session / "flights" / "field"
    outs = {"default": (store, []), "keep": (store, ["--keep-flagged"]), "plain": (plain, [])}
    for name, (c, extra) in outs.items():
        assert main(["-q", "apply", str(flight), "--calibration", str(c), "-o", str(root / name), *extra]) == 0
    return {**{name: root / name for name in outs}, "store": store}


def _run(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def _counts(q: np.ndarray) -> dict[str, int]:
    return {name: int(np.count_nonzero(q & bit)) for name, bit in FLAGS.items() if np.count_nonzero(q & bit)}


def test_shoulder_pixels_get_their_bit_and_are_nan(flagged) -> None:
    ds = xr.open_zarr(flagged["default"] / "reflectance.zarr")
    raw = xr.open_zarr(flagged["default"] / "raw.zarr")["dn"].values
    q, refl = ds["quality"].values, ds["reflectance"].values
    assert q.dtype == np.uint8 and q.shape == refl.shape
    assert ds["quality"].attrs["flag_masks"] == [1, 2, 4, 8, 16, 32, 64]
    assert ds["quality"].attrs["flag_meanings"].split() == list(FLAGS)
    shoulder = (q & FLAGS["response_shoulder"]) != 0
    # the bit follows the DN: above the bound from DN 421 on, below the clip
    assert np.array_equal(shoulder, (raw > SHOULDER_FROM + 20) & (raw < 1023))
    assert 1e-4 < shoulder.mean() < 0.2  # the flight reaches the shoulder, not everywhere
    assert np.array_equal((q & FLAGS["outside_sweep"]) != 0, (raw < LOW) | (raw > 1022))
    assert np.array_equal((q & FLAGS["below_sweep"]) != 0, raw < LOW)
    unseen = (q & FLAGS["vignetting_unobserved"]) != 0
    assert unseen[:, :, :6, :10].all() and unseen.sum() == refl.shape[0] * refl.shape[1] * 60
    # NaN exactly where flagged (nothing else is NaN in this flight)
    assert np.array_equal(np.isnan(refl), q != 0)
    run = _run(flagged["default"])["quality"]
    # a snapshot camera's bands are not measured for co-registration: that flag is not checked
    assert run["checked"] == [f for f in FLAGS if f != "not_coregistered"]
    assert run["bound"] == 0.03 and run["keep_flagged"] is False
    assert run["flags"] == FLAGS


def test_the_fits_own_share_over_its_bound_is_the_shoulder_too(flagged, tmp_path) -> None:
    """A store whose fit share of U's uncertainty passes 0.0033 from DN 380 on (the total stays
    under 0.03 up to DN 420): the shoulder bit from DN 380 on, as the store's table says; the
    same share under the bound leaves it from DN 421 on; run.json states the bound."""
    from pipeline.apply.stores import quality_tables

    ds = xr.open_zarr(flagged["store"]).load()
    fit = ds["response_fit_uncertainty"].values
    fit[:, 380:] = 0.006
    ds["response_fit_uncertainty"] = (("band", "dn"), fit)
    for v in ds.variables.values():
        v.encoding = {}
    ds.to_zarr(tmp_path / "calib_fit.zarr", mode="w", zarr_format=3, consolidated=True)
    sat = int(ds["saturation_dn"].min())
    for store, first in ((tmp_path / "calib_fit.zarr", 380), (flagged["store"], SHOULDER_FROM + 21)):
        dn_flags, _, checked = quality_tables(str(store), sat, 0.03)
        shoulder = (dn_flags & FLAGS["response_shoulder"]) != 0
        assert "response_shoulder" in checked
        assert not shoulder[:, :first].any() and shoulder[:, first:sat].all(), store
    assert _run(flagged["default"])["quality"]["fit_bound"] == pytest.approx(0.01 / 3)


def test_run_json_counts_equal_the_array(flagged) -> None:
    ds = xr.open_zarr(flagged["default"] / "reflectance.zarr")
    q = ds["quality"].values
    run = _run(flagged["default"])["quality"]
    names = [str(b) for b in ds["band_name"].values]
    for f, frame in enumerate(str(x) for x in ds["frame"].values):
        want = {names[b]: c for b in range(q.shape[1]) if (c := _counts(q[f, b]))}
        assert run["frames"][frame] == want
    assert run["totals"] == {names[b]: _counts(q[:, b]) for b in range(q.shape[1]) if _counts(q[:, b])}


def test_keep_flagged_keeps_the_values_and_redoes_the_flight(flagged) -> None:
    keep = xr.open_zarr(flagged["keep"] / "reflectance.zarr")
    plain = xr.open_zarr(flagged["plain"] / "reflectance.zarr")["reflectance"].values
    q = keep["quality"].values
    assert np.array_equal(q, xr.open_zarr(flagged["default"] / "reflectance.zarr")["quality"].values)
    refl = keep["reflectance"].values
    assert np.isfinite(refl[q != 0]).all()  # nothing saturated in this flight: every flagged value kept
    np.testing.assert_array_equal(refl, plain)  # what the store without the flags gives
    run = _run(flagged["keep"])
    assert run["quality"]["keep_flagged"] is True and run["products"]["keep_flagged"] is True
    assert run["fingerprint"] != _run(flagged["default"])["fingerprint"]
    assert run["fingerprint"]["options"]["products"]["keep_flagged"] is True


def test_a_store_without_the_optional_variables_applies_as_before(flagged) -> None:
    plain = xr.open_zarr(flagged["plain"] / "reflectance.zarr")
    default = xr.open_zarr(flagged["default"] / "reflectance.zarr")
    q = default["quality"].values
    a, b = plain["reflectance"].values, default["reflectance"].values
    np.testing.assert_array_equal(a[q == 0], b[q == 0])  # unflagged pixels: the same reflectance
    assert not np.isnan(a).any()
    assert not plain["quality"].values.any()
    run = _run(flagged["plain"])["quality"]
    assert run["checked"] == ["saturated", "no_value"]
    assert run["totals"] == {} and run["frames"] == {}


def test_warnings_name_frame_and_band(flagged) -> None:
    warnings = report_warnings(flights=[flagged["default"]])
    lines = [w["message"] for w in warnings if w["code"].startswith("flagged_")]
    run = _run(flagged["default"])["quality"]
    frame = next(iter(run["frames"]))
    band, flags = next(iter(run["frames"][frame].items()))
    n = flags.get("response_shoulder") or next(iter(flags.values()))
    shoulder = [m for m in lines if "on the response's shoulder in " in m]
    assert shoulder and shoulder[0].startswith("frame IMG_") and shoulder[0].endswith("set to NaN")
    assert any(m.startswith(f"frame {frame}: ") and (f"({band} {n:,}" in m or f", {band} {n:,}" in m)
               for m in lines)
    kept = [w["message"] for w in report_warnings(flights=[flagged["keep"]]) if w["code"].startswith("flagged_")]
    assert kept and all(m.endswith(", kept") for m in kept if not m.startswith("and "))
    assert not [w for w in report_warnings(flights=[flagged["plain"]]) if w["code"].startswith("flagged_")]


def test_flagged_pixels_one_line_per_frame_and_flag_then_the_frames_left() -> None:
    frames = {f"IMG_{f:04d}": {"b670": {"response_shoulder": 10 + f, "saturated": 3},
                               "b678": {"response_shoulder": 1000 * f, "outside_sweep": 7}}
              for f in range(MAX_FLAGGED_LINES)}
    frames["IMG_0000"]["b678"] = {"outside_sweep": 7}  # no shoulder pixel in b678 of the first frame
    lines = flagged_pixels({"quality": {"keep_flagged": False, "frames": frames}})
    assert len(lines) == MAX_FLAGGED_LINES + 1
    assert lines[0].message == "frame IMG_0000: 10 pixels on the response's shoulder in 1 band (b670 10), set to NaN"
    assert lines[1].message == ("frame IMG_0000: 7 pixels outside the response sweep's DN range in 1 band (b678 7), "
                                "set to NaN")
    assert lines[2].message == ("frame IMG_0001: 1,011 pixels on the response's shoulder in 2 bands "
                                "(b670 11, b678 1,000), set to NaN")
    assert (lines[2].code, lines[2].value) == ("flagged_response_shoulder", 1011.0)
    # 40 frame/flag counts: 20 lines, then one naming the 10 frames left (IMG_0010-0019)
    assert lines[-1].code == "flagged_more"
    assert lines[-1].message.startswith("and 20 more frame/flag counts of flagged pixels in 10 frame(s): IMG_0010, ")
    assert lines[-1].value == sum(10 + f + 1000 * f + 7 for f in range(10, 20))
    assert not any("saturated" in w.message for w in lines)  # saturation has its own warning


def test_tiffs_carry_the_nan(flagged) -> None:
    ds = xr.open_zarr(flagged["default"] / "reflectance.zarr")
    q = ds["quality"].values
    names = [str(b) for b in ds["band_name"].values]
    tiffs = sorted((flagged["default"] / "photogrammetry").glob("IMG_0000_*.tif"))
    assert tiffs
    for path in tiffs:
        b = names.index(path.stem.split("_", 2)[2])
        data = tifffile.imread(path)
        assert np.array_equal(data == 65535, q[0, b] != 0)  # uint16 TIFFs: NaN is 65535


def _plan(**kw) -> SimpleNamespace:
    bands = [SimpleNamespace(name=n) for n in ("blue", "green", "red")]
    return SimpleNamespace(**{"camera": SimpleNamespace(bands=bands), "factory_alignment": False, "transforms": None,
                              "band_shift": None, "refine": None, "coreg_reference": None, **kw})


def test_coregistration_is_checked_on_the_sample_and_on_captures_judged_on_their_own_pixels() -> None:
    refine = SimpleNamespace(reference=0)
    plan = _plan(coreg_reference=0, factory_alignment=True, refine=refine)
    bad = RESIDUAL_MAX_PX + 0.5
    own = {"refinement": {"from": "own pixels", "alignment": "factory metadata", "metadata_px": {"red": bad}}}
    refined = {"refinement": {"from": "own pixels", "alignment": "factory metadata + image registration",
                              "metadata_px": {"red": 9.0, "green": 9.0}, "refined_px": {"red": 0.2, "green": bad}}}
    flight = {"refinement": {"from": "flight (fewest textured tiles in a band: 1 < 3)", "alignment": "factory metadata"}}
    measured = {"residual_px": {"green": bad}, **own}
    assert not_coregistered(plan, own) == [2]
    assert not_coregistered(plan, refined) == [1]  # the refinement's residuals, not the metadata's
    assert not_coregistered(plan, flight) == []  # not judged on its pixels: not checked
    assert not_coregistered(plan, measured) == [1]  # the sample's measurement of the bands as written first
    # a band shift after the refinement moves the bands: the judgement no longer describes them
    assert not_coregistered(_plan(coreg_reference=0, factory_alignment=True, refine=refine, band_shift=(1, 1)),
                            own) == []
    flagging = checked(Flagging(checked=FACTORY_CHECKS), plan)
    assert flagging.own_pixels
    run = quality_record(flagging, {}, {"A": measured, "B": refined, "C": flight, "D": None})
    checks = run["coregistration"]
    assert (checks["measured"], checks["own_pixels"], checks["not_checked"]) == (["A"], ["B"], ["C", "D"])
    assert "not passed" in checks["rule"]
    # a pass that does not check the flag says nothing of captures
    assert "coregistration" not in quality_record(checked(Flagging(checked=FACTORY_CHECKS), _plan()), {}, {"A": None})


def test_a_band_that_failed_coregistration_is_flagged_whole_and_nan() -> None:
    plan = _plan(coreg_reference=0, factory_alignment=True)  # aligned by the files' registration, measured
    residuals = {"residual_px": {"blue": 0.4, "green": None, "red": RESIDUAL_MAX_PX + 0.5}}
    assert not_coregistered(plan, residuals) == [2]
    assert not_coregistered(plan, None) == []
    # bands left on their own grids (no alignment), or not measured: nothing to fail
    assert not_coregistered(_plan(coreg_reference=0), residuals) == []
    assert checked(Flagging(checked=FACTORY_CHECKS), _plan(coreg_reference=0)).checked == ("saturated", "no_value")
    assert checked(Flagging(checked=FACTORY_CHECKS), plan).checked == FACTORY_CHECKS
    refl = np.ones((3, 4, 5), np.float32)
    refl[0, 0, 0] = np.nan
    q = np.zeros((3, 4, 5), np.uint8)
    q[1, 1, 1] = FLAGS["response_shoulder"]  # kept: its value stays
    out = finish(Flagging(keep_flagged=False), q.copy(), refl.copy(), [2], moved=False)
    assert (out[2] == FLAGS["not_coregistered"]).all() and out[0, 0, 0] == FLAGS["no_value"]
    assert out[1, 1, 1] == FLAGS["response_shoulder"] and np.count_nonzero(out) == 20 + 2
    r = refl.copy()
    finish(Flagging(keep_flagged=False), q.copy(), r, [2], moved=False)
    assert np.isnan(r[2]).all() and np.isfinite(r[1]).all()  # the field tables made the shoulder NaN already
    r = refl.copy()
    finish(Flagging(keep_flagged=True), q.copy(), r, [2], moved=True)
    assert np.isfinite(r[1:]).all()  # kept
    r = refl.copy()
    finish(Flagging(keep_flagged=False), q.copy(), r, [], moved=True)
    assert np.isnan(r[1, 1, 1]) and np.count_nonzero(np.isnan(r)) == 2  # moved by the grid: NaN made here


@pytest.mark.parametrize("share", [0.01, 0.3])  # the gathered way, and (dense NaN) the two passes
def test_finish_counted_is_finish_then_counts(share) -> None:
    rng = np.random.default_rng(5)
    names = ["a", "b", "c", "d"]
    refl = rng.uniform(0, 1, (4, 30, 40)).astype(np.float32)
    q = np.zeros(refl.shape, np.uint8)
    hit = rng.random(refl.shape) < share
    q[hit] = rng.choice([1, 2, 4, 8, 6, 9], size=int(hit.sum())).astype(np.uint8)
    q[3] = 0  # a band with nothing flagged
    refl[q != 0] = np.nan  # the field tables make flagged pixels NaN
    refl[0, 0, :3] = np.nan  # NaN for no flagged reason: no_value
    cases = [(Flagging(), [], False), (Flagging(), [2], False), (Flagging(keep_flagged=True), [1], True)]
    for flagging, bad, moved in cases:
        r1, r2 = refl.copy(), refl.copy()
        want = finish(flagging, q.copy(), r1, bad, moved)
        got, got_counts = finish_counted(flagging, q.copy(), r2, bad, moved, names)
        assert got.tobytes() == want.tobytes() and r2.tobytes() == r1.tobytes()
        assert got_counts == counts(want, names) and list(got_counts) == list(counts(want, names))
    got, c = finish_counted(Flagging(), q.copy(), refl.copy(), [], False, names)
    assert c["a"]["no_value"] == 3 and "d" not in c
    assert sum(c["b"].values()) >= np.count_nonzero(q[1])  # a pixel with two bits counts under both
    stray = q.copy()
    stray[3, 5, 5] = FLAGS["response_shoulder"]  # flagged but not NaN (kept): counted all the same
    got, c = finish_counted(Flagging(), stray.copy(), refl.copy(), [], False, names)
    assert c["d"] == {"response_shoulder": 1} and got.tobytes() == finish(Flagging(), stray.copy(), refl.copy(), [],
                                                                           False).tobytes()


def test_sensor_flags_is_frame_flags(monkeypatch) -> None:
    """The pixel table's flagged positions found once: the same mask as frame_flags, band by
    band, whether a band's NaN pixels are exactly the pixel table's or not (a saturated pixel,
    a flagged DN elsewhere), and with flagged values kept."""
    import pipeline.apply.quality as quality
    from mscal_core.quality import frame_flags, mask_tables
    from mscal_core.reflectance import eq15_fast, eq15_tables
    from pipeline.apply.stores import flag_positions

    rng = np.random.default_rng(7)
    n, h, w, n_dn = 4, 20, 30, 256
    dn_flags = np.zeros((n, n_dn), np.uint8)
    dn_flags[:, 250:] = FLAGS["response_shoulder"]
    pixel = np.zeros((n, h, w), np.uint8)
    pixel[:, :3, :] = FLAGS["vignetting_unobserved"]
    pixel[2] = 0  # a band without flagged pixels
    lut, inv_v = eq15_tables(np.tile(np.linspace(0, 1, n_dn), (n, 1)), np.ones((n, h, w)), np.ones(n))
    lut, inv_v = mask_tables(lut, inv_v, dn_flags, pixel)
    monkeypatch.setattr(quality, "quality_tables", lambda *a: (dn_flags, pixel, ()))
    monkeypatch.setattr(quality, "pixel_flag_sets", lambda *a: flag_positions(pixel))
    dn = rng.integers(0, 240, (n, h, w)).astype(np.uint16)
    dn[1, 10, 10] = 252  # a flagged DN outside the pixel table's pixels: band 1 the general way
    dn[3, 0, 0] = 255  # a flagged DN on a flagged pixel: both bits
    refl = eq15_fast(dn[None], lut, inv_v, 1.0, n_dn)[0]
    got = quality.sensor_flags(Flagging(), Path("calib"), n_dn, dn, refl)
    want = frame_flags(dn, dn_flags, pixel, reflectance=refl)
    assert got.tobytes() == want.tobytes()
    assert got[3, 0, 0] == FLAGS["response_shoulder"] | FLAGS["vignetting_unobserved"] and got[1, 10, 10] == 2
    assert np.count_nonzero(got[2]) == 0 and np.count_nonzero(got[0]) == 3 * w
    kept = quality.sensor_flags(Flagging(keep_flagged=True), Path("calib"), n_dn, dn, refl)
    assert kept.tobytes() == frame_flags(dn, dn_flags, pixel).tobytes()


def test_the_mask_moves_with_the_bands(tmp_path) -> None:
    """--centre-bands: each bit goes where the band's pixels go, flagged where a flagged pixel
    contributes (as NaN spreads through the resampling)."""
    plan = _plan(band_shift=((0.0, 0.0), (2.0, 0.0), (0.0, -1.0)))
    job = SimpleNamespace(capture=None, name="IMG_0000")
    q = np.zeros((3, 12, 12), np.uint8)
    q[:, 6, 6] = FLAGS["response_shoulder"] | FLAGS["vignetting_unobserved"]
    refl = np.where(q != 0, np.nan, 1.0).astype(np.float32)
    moved = geometry_step(Path(), False, plan.band_shift, job.name, refl)
    after, _, warp = one_grid(plan, job, refl)
    assert np.array_equal(after, moved, equal_nan=True)  # the warp the reflectance took
    out = on_grid(q, warp)
    assert set(np.unique(out)) == {0, FLAGS["response_shoulder"] | FLAGS["vignetting_unobserved"]}
    assert out[0, 6, 6] and np.count_nonzero(out[0]) == 1  # not moved
    assert np.array_equal(out != 0, np.isnan(moved) & (np.abs(np.arange(12) - 6)[None, :, None] < 4)
                          & (np.abs(np.arange(12) - 6)[None, None, :] < 4))
    assert out[1, 6, 8] and out[2, 5, 6] and not out[1, 6, 6]


def test_the_mask_follows_a_captures_own_image_registration(monkeypatch) -> None:
    """A DJI capture whose bands the metadata leaves 3-5 px apart is refined on its own pixels
    (:func:`pipeline.apply.bandgrid.one_grid`); the quality bits of its stored grid take the
    same warp, so each lands where its pixel's value (NaN, as the field tables make it) did."""
    import cv2

    import pipeline.apply.bandgrid as bandgrid
    from pipeline.apply.coregistration import REFINED, Refinement
    from pipeline.ingest.catalog import load_camera

    # the metadata alignment: no move
    monkeypatch.setattr(bandgrid, "align_by_files", lambda metas, stack: stack.copy())
    bands = tuple(load_camera("dji-p4-multispectral").band_names)
    rng = np.random.default_rng(3)
    scene = sum(w * cv2.GaussianBlur(rng.random((560, 720)).astype(np.float32), (0, 0), s)
                for s, w in ((2.0, 1.0), (6.0, 2.0)))
    offsets = [(4.0, -2.0), (-3.0, 3.0), (0.0, 0.0), (2.5, 4.0), (-4.0, -1.0)]
    yy, xx = np.mgrid[0:480, 0:640].astype(np.float32)
    stack = np.stack([cv2.remap(scene, xx + 40 + dx, yy + 40 + dy, cv2.INTER_CUBIC) for dx, dy in offsets])
    q = np.zeros(stack.shape, np.uint8)
    q[0, 200:210, 300:320] = FLAGS["response_shoulder"]
    q[3, 100:104, 50:53] = FLAGS["saturated"]
    clean = stack.copy()
    stack[q != 0] = np.nan  # flagged pixels are NaN out of the field tables
    plan = _plan(coreg_reference=2, factory_alignment=True, refine=Refinement(2, bands, True, None, REFINED))
    job = SimpleNamespace(capture=SimpleNamespace(metas=[None] * 5), name="001")
    after, own, warp = bandgrid.one_grid(plan, job, stack)
    assert own["alignment"] == REFINED and max(own["refined_px"].values()) < 0.3
    moved = on_grid(q, warp)
    nan = np.isnan(after) & ~np.isnan(warp(clean))  # the flagged pixels' NaN, not the warp's borders
    for b, bit in ((0, FLAGS["response_shoulder"]), (3, FLAGS["saturated"])):
        got = (moved[b] & bit) != 0
        assert np.array_equal(got, nan[b]), b  # exactly where the NaN went, no more, no fewer
        assert not np.array_equal(got, q[b] != 0)  # 2.5-4.5 px away from the stored grid's pixels
    assert not moved[[1, 2, 4]].any()
