"""reflectance.zarr's ``quality`` mask (pipeline.apply.quality): a flight whose pixels reach the
response's shoulder gets the bits, NaN by default and its values with --keep-flagged, per-frame
warnings naming the band, run.json counts equal to the array's; a store without the optional
variables applies as before and says which flags it checked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr

from mscal_core.quality import FLAGS
from pipeline.apply.quality import FACTORY_CHECKS
from pipeline.products.report.flight import MAX_FLAGGED_LINES
from pipeline.run.cli import main
from pipeline.run.console import report_warnings

SHOULDER_FROM = 400  # DN from which U's relative uncertainty passes 0.03 (0.01 + 1e-3 per DN above 400)
LOW = 50  # the sweep's lowest DN


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
    ds["response_dn_range"] = (("band", "end"), np.tile(np.array([[LOW, ndn - 2]], np.int32), (nb, 1)))
    ds = ds.assign_coords(end=["low", "high"])
    cov = np.full(ds["vignetting"].shape, 3, np.uint16)
    cov[:, :6, :10] = 0
    ds["vignetting_coverage"] = (("band", "y", "x"), cov)
    for v in ds.variables.values():
        v.encoding = {}
    ds.to_zarr(dst, mode="w", zarr_format=3, consolidated=True)
    return dst


@pytest.fixture(scope="module")
def flagged(small, tmp_path_factory) -> dict[str, Path]:
    """The small flight applied with the store of every variable (default and --keep-flagged)
    and with the store as calibrate writes it today."""
    session, calib = small
    root = tmp_path_factory.mktemp("quality")
    store = _with_quality_variables(calib, root / "calib_q.zarr")
    flight = session / "flights" / "field"
    outs = {"default": (store, []), "keep": (store, ["--keep-flagged"]), "plain": (calib, [])}
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
    assert ds["quality"].attrs["flag_masks"] == [1, 2, 4, 8, 16, 32]
    assert ds["quality"].attrs["flag_meanings"].split() == list(FLAGS)
    shoulder = (q & FLAGS["response_shoulder"]) != 0
    # the bit follows the DN: above the bound from DN 421 on, below the clip
    assert np.array_equal(shoulder, (raw > SHOULDER_FROM + 20) & (raw < 1023))
    assert 1e-4 < shoulder.mean() < 0.2  # the flight reaches the shoulder, not everywhere
    assert np.array_equal((q & FLAGS["outside_sweep"]) != 0, (raw < LOW) | (raw > 1022))
    unseen = (q & FLAGS["vignetting_unobserved"]) != 0
    assert unseen[:, :, :6, :10].all() and unseen.sum() == refl.shape[0] * refl.shape[1] * 60
    # NaN exactly where flagged (nothing else is NaN in this flight)
    assert np.array_equal(np.isnan(refl), q != 0)
    run = _run(flagged["default"])["quality"]
    assert run["checked"] == list(FLAGS) and run["bound"] == 0.03 and run["keep_flagged"] is False
    assert run["flags"] == FLAGS


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
    assert run["checked"] == ["saturated", "not_coregistered", "no_value"] == list(FACTORY_CHECKS)
    assert run["totals"] == {} and run["frames"] == {}


def test_warnings_name_frame_and_band(flagged) -> None:
    warnings = report_warnings(flights=[flagged["default"]])
    lines = [w["message"] for w in warnings if w["code"].startswith("flagged_")]
    run = _run(flagged["default"])["quality"]
    frame = next(iter(run["frames"]))
    band, flags = next(iter(run["frames"][frame].items()))
    n = flags.get("response_shoulder") or next(iter(flags.values()))
    assert len(lines) == MAX_FLAGGED_LINES + 1 and lines[-1].startswith("and ")
    shoulder = [m for m in lines if "on the response's shoulder, set to NaN" in m]
    assert shoulder and shoulder[0].startswith("frame IMG_")
    assert any(m.startswith(f"frame {frame}, band {band}: {n:,} pixels ") for m in lines)
    kept = [w["message"] for w in report_warnings(flights=[flagged["keep"]]) if w["code"].startswith("flagged_")]
    assert kept and all(m.endswith(", kept") for m in kept[:-1])
    assert not [w for w in report_warnings(flights=[flagged["plain"]]) if w["code"].startswith("flagged_")]


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
