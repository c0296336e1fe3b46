"""mscal calibrate / fit end to end on synthetic sessions with known truth, and bad input."""

from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.run.cli import main
from pipeline.sim.evaluate import evaluate_calibration


def _run(args: list[str], capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


# --------------------------------------------------------------------------- round trip


def test_small_session_round_trip(small) -> None:
    session, calib = small
    err = evaluate_calibration(session, calib)
    assert err["response_max_error"] < 0.02
    assert err["vignetting_rms_error_observed"] < 0.02
    assert err["spectral_factor_max_error"] < 0.02
    flight = err["flight_field"]
    assert flight["eq15"]["panel_abs_error"] < 0.015
    assert flight["eq15"]["vegetation_ndvi_error"] < 0.01
    # the Eq. 16 baseline is visibly worse under the reflector's non-uniform light
    assert flight["eq16"]["panel_abs_error"] > 3 * flight["eq15"]["panel_abs_error"]
    assert flight["eq16"]["vegetation_ndvi_error"] > 0.05


def test_store_contract_and_provenance(small) -> None:
    session, calib = small
    ds = xr.open_zarr(calib)
    assert ds["inverse_response"].dims == ("band", "dn") and ds.sizes["dn"] == 1024
    assert ds["vignetting"].dims == ("band", "y", "x") and ds["vignetting"].shape == (25, 217, 409)
    assert ds["spectral_factor"].dims == ("band",)
    assert float(ds["wavelength"].sel(band=24)) == 670.0
    U = ds["inverse_response"].values
    assert np.all(np.diff(U, axis=1) >= 0)
    assert np.all(U[:, :20] == 0)  # at and below the black level (32 DN in the synthetic sensor)
    V = ds["vignetting"].values
    np.testing.assert_allclose(V.reshape(25, -1).max(axis=1), 1.0, atol=1e-6)
    assert np.all(V > 0)
    S = ds["spectral_factor"].values
    assert np.all(S > 0)
    assert ds.attrs["camera"] == "ximea-mq022hg-sm5x5-nir"
    assert ds.attrs["fits"] == ["response", "vignetting", "illumination"]
    n_views = len(list((session / "vignetting").glob("*.tif")))
    assert len(ds.attrs["vignetting"]["inputs"]) == n_views
    assert all(len(h) == 64 for h in ds.attrs["response"]["inputs"].values())
    truth = np.load(session / "truth.npz")
    missing = [f"{n}.tif" for n, ok in zip(truth["vignetting_names"], truth["vignetting_marker_in_frame"]) if not ok]
    skipped = [s["file"] for s in ds.attrs["vignetting"]["skipped"]]
    assert missing and set(missing) <= set(skipped)
    assert all("not found" in s["reason"] for s in ds.attrs["vignetting"]["skipped"])


def test_store_records_how_each_marker_pose_was_chosen(small) -> None:
    session, calib = small
    ds = xr.open_zarr(calib)
    skipped = {s["file"] for s in ds.attrs["vignetting"]["skipped"]}
    views = sorted(p.name for p in (session / "vignetting").glob("*.tif") if p.name not in skipped)
    for stage in ("vignetting", "illumination"):
        poses = ds.attrs[stage]["residuals"]["marker_poses"]
        assert all(p["solution"] in (0, 1) and p["by"] in ("reprojection", "outline", "single", "undecided")
                   for p in poses)
        # both IPPE solutions' reprojection errors, the one taken first unless the outline chose
        for p in poses:
            e0, e1 = p["reprojection_px"]
            assert 0 <= e0 < 0.5 and (e1 is None or e1 >= e0)
    assert sorted(p["file"] for p in ds.attrs["vignetting"]["residuals"]["marker_poses"]) == views


def test_store_keeps_what_the_qa_report_needs(small) -> None:
    """B(x) per reflector image, one band of its DN, exposures and saturated fractions."""
    session, calib = small
    ds = xr.open_zarr(calib).load()
    truth = np.load(session / "truth.npz")
    n_img = len(list((session / "reflector").glob("*.tif")))
    B = ds["reflector_brightness"].values
    assert B.shape == (n_img, 217, 409)
    res = ds.attrs["illumination"]["residuals"]
    # B is set exactly on the reflector pixels the fit used, with median 1 over all of them
    assert [int(np.isfinite(b).sum()) for b in B] == res["reflector_pixels_per_image"]
    assert sum(res["reflector_pixels_per_image"]) == res["reflector_pixels"]
    assert abs(float(np.nanmedian(B)) - 1.0) < 1e-6
    # and it is the true brightness up to the gauge: the ratio is constant to noise (1.4 %)
    ok = np.isfinite(B)
    ratio = B[ok] / truth["reflector_B"][ok]
    assert np.std(ratio) / np.median(ratio) < 0.03
    band = ds["reflector_dn"].attrs["band"]
    assert float(ds["wavelength"].values[band]) == 803.0  # the camera's NIR index band
    assert ds["reflector_dn"].dtype == np.uint16 and ds["reflector_dn"].shape == B.shape
    assert list(ds["reflector_file"].values) == [f"{n}.tif" for n in truth["reflector_names"]][:n_img]
    np.testing.assert_allclose(ds["reflector_exposure_ms"].values, truth["reflector_exposure_ms"][:n_img])
    assert len(res["image_brightness"]) == n_img
    for stage in ("vignetting", "illumination"):
        frac = ds.attrs[stage]["residuals"]["saturated_fraction"]
        assert len(frac) == 25 and all(0.0 <= f < 0.01 for f in frac)
    # the response fit's residual per DN bin: defined over the DN the sweep observed, and its
    # sample-weighted mean square is the stored overall rms (within the bins' rounding)
    prof = ds["response_residual"].values
    assert prof.shape == (25, 32) and ds["dn_bin"].values[0] == 16.0
    obs = ds.attrs["response"]["residuals"]["observed_dn"]
    rms = ds.attrs["response"]["residuals"]["residual_rms_dn"]
    for b in (0, 12, 24):
        inside = (ds["dn_bin"].values > obs[b][0] + 32) & (ds["dn_bin"].values < obs[b][1] - 32)
        assert np.isfinite(prof[b][inside]).all()
        assert np.nanmin(prof[b]) <= rms[b] <= np.nanmax(prof[b])


def test_fit_stages_one_at_a_time_match_calibrate(small, tmp_path, capsys) -> None:
    session, calib = small
    u = tmp_path / "u.zarr"
    v = tmp_path / "v.zarr"
    full = tmp_path / "full.zarr"
    assert _run(["fit", "response", session, "-o", u], capsys)[0] == 0
    assert _run(["fit", "vignetting", session, "-o", v, "--calibration", u], capsys)[0] == 0
    assert _run(["fit", "illumination", session, "-o", full, "--calibration", v], capsys)[0] == 0
    a, b = xr.open_zarr(full), xr.open_zarr(calib)
    assert "vignetting" not in xr.open_zarr(u)
    for name in ("inverse_response", "vignetting", "spectral_factor"):
        np.testing.assert_allclose(a[name].values, b[name].values, rtol=1e-6)
    # what says how far U and V can be trusted survives the stores in between
    for name in ("response_uncertainty", "response_dn_range", "vignetting_coverage"):
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)


def test_fit_response_on_a_plain_folder_needs_a_camera(small, tmp_path, capsys) -> None:
    session, _ = small
    code, _, err = _run(["fit", "response", session / "response", "-o", tmp_path / "u.zarr"], capsys)
    assert code == 2 and "--camera NAME is required" in err
    code, out, _ = _run(
        ["fit", "response", session / "response", "--camera", "ximea-mq022hg-sm5x5-nir", "-o", tmp_path / "u.zarr"], capsys
    )
    assert code == 0 and "wrote" in out


@pytest.mark.parametrize("argv", [[], ["calibrate"], ["fit"], ["fit", "response"], ["fit", "vignetting"], ["fit", "illumination"], ["demo"]])
def test_help(argv, capsys) -> None:
    code, out, _ = _run([*argv, "--help"], capsys)
    assert code == 0 and "Usage: mscal" in out


# --------------------------------------------------------------------------- bad input


def _clone(session: Path, dst: Path, copy: tuple[str, ...] = ()) -> Path:
    """A session folder whose sub-folders link to ``session``'s, except those in ``copy``."""
    dst.mkdir()
    shutil.copy(session / "session.yaml", dst / "session.yaml")
    for sub in ("response", "vignetting", "reflector"):
        if sub in copy:
            shutil.copytree(session / sub, dst / sub)
        else:
            os.symlink(session / sub, dst / sub)
    return dst


def _edit_csv(path: Path, edit) -> None:
    rows = list(csv.DictReader(path.open()))
    edit(rows)
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)


def _one_line_error(code: int, err: str) -> str:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mscal: error: ")
    assert "Traceback" not in err
    return lines[0]


def _set(rows, i, key, value):
    rows[i][key] = value


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize(
    "case, expect",
    [
        ("frame_missing", "sweep_02.tif is listed but the file does not exist"),
        ("truncated", "sweep_01.tif: unreadable or truncated image"),
        ("not_image", "sweep_01.tif: unreadable or truncated image"),
        ("no_exposure", "frame sweep_03.tif has no exposure_ms"),
        ("zero_exposure", "frame sweep_03.tif has exposure_ms 0; it must be positive"),
        ("negative_exposure", "frame sweep_03.tif has exposure_ms -2"),
        ("one_exposure", "the sweep has 1 distinct exposure(s); the response fit needs at least 2"),
        ("inconsistent", "brightness contradicts exposure for"),
    ],
)
def test_bad_sweep_gives_one_line_naming_the_file(small, tmp_path, capsys, case, expect) -> None:
    session, calib = small
    bad = _clone(session, tmp_path / "bad", copy=("response",))
    resp = bad / "response"
    csv_path = resp / "frames.csv"
    if case == "frame_missing":
        (resp / "sweep_02.tif").unlink()
    elif case == "truncated":
        _truncate(resp / "sweep_01.tif")
    elif case == "not_image":
        (resp / "sweep_01.tif").write_text("hello")
    elif case == "no_exposure":
        _edit_csv(csv_path, lambda r: _set(r, 3, "exposure_ms", ""))
    elif case == "zero_exposure":
        _edit_csv(csv_path, lambda r: _set(r, 3, "exposure_ms", "0"))
    elif case == "negative_exposure":
        _edit_csv(csv_path, lambda r: _set(r, 3, "exposure_ms", "-2"))
    elif case == "one_exposure":
        _edit_csv(csv_path, lambda r: [row.update(exposure_ms="5") for row in r])
    elif case == "inconsistent":
        def swap(rows):
            rows[1]["exposure_ms"], rows[5]["exposure_ms"] = rows[5]["exposure_ms"], rows[1]["exposure_ms"]
        _edit_csv(csv_path, swap)
    # an existing store at the output path must survive the failed run untouched
    out = tmp_path / "out.zarr"
    shutil.copytree(calib, out)
    before = xr.open_zarr(out)["spectral_factor"].values.copy()
    line = _one_line_error(*_run(["calibrate", bad, "-o", out], capsys)[::2])
    assert expect in line
    if case in ("frame_missing", "no_exposure", "zero_exposure", "negative_exposure", "one_exposure", "inconsistent"):
        assert "frames.csv" in line
    np.testing.assert_array_equal(xr.open_zarr(out)["spectral_factor"].values, before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad", "out.zarr"]


@pytest.mark.parametrize(
    "edit, expect",
    [
        (lambda t: t.replace("id: 3", "id: 7"), "marker DICT_4X4_50 id 7 was not found in any of the 8 frames"),
        (lambda t: t.replace("DICT_4X4_50", "DICT_5X5_50"), "was not found in any"),
        (lambda t: t.replace("DICT_4X4_50", "DICT_NOPE"), "marker.dictionary 'DICT_NOPE' is not an OpenCV ArUco/AprilTag dictionary"),
        (lambda t: t.replace("camera: ximea-mq022hg-sm5x5-nir", "camera: ximea-typo"), "unknown camera 'ximea-typo'"),
        (lambda t: t.replace("camera:", "camera_name:"), "missing key(s) camera"),
        (lambda t: t + "\n  - ]\n", "not valid YAML"),
    ],
)
def test_bad_session_yaml_or_marker(small, tmp_path, capsys, edit, expect) -> None:
    session, calib = small
    bad = _clone(session, tmp_path / "bad")
    (bad / "session.yaml").write_text(edit((bad / "session.yaml").read_text()))
    code, _, err = _run(["fit", "vignetting", bad, "-o", tmp_path / "v.zarr", "--calibration", calib], capsys)
    line = _one_line_error(code, err)
    assert expect in line
    assert not (tmp_path / "v.zarr").exists()


def test_missing_session_folder_and_yaml(tmp_path, capsys) -> None:
    line = _one_line_error(*_run(["calibrate", tmp_path / "nope", "-o", tmp_path / "c.zarr"], capsys)[::2])
    assert "nope: session folder not found" in line
    (tmp_path / "empty").mkdir()
    line = _one_line_error(*_run(["calibrate", tmp_path / "empty", "-o", tmp_path / "c.zarr"], capsys)[::2])
    assert "empty/session.yaml: session.yaml is missing" in line


def test_partial_store_of_another_kind_is_named(small, tmp_path, capsys) -> None:
    session, _ = small
    u = tmp_path / "u.zarr"
    assert _run(["fit", "response", session, "-o", u], capsys)[0] == 0
    line = _one_line_error(*_run(["fit", "illumination", session, "-o", tmp_path / "x.zarr", "--calibration", u], capsys)[::2])
    assert "u.zarr: store lacks vignetting needed for illumination" in line


# --------------------------------------------------------------------------- full size (the accuracy targets)


@pytest.mark.slow
@pytest.mark.xdist_group("full_session")
def test_full_size_session_meets_the_targets(full_session, tmp_path) -> None:
    session = full_session
    calib = tmp_path / "calib.zarr"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    err = evaluate_calibration(session, calib)
    assert err["response_max_error"] <= 0.02
    assert err["vignetting_rms_error"] <= 0.015
    assert err["spectral_factor_max_error"] <= 0.01
    f = err["flight_field"]
    assert f["eq15"]["panel_abs_error"] <= 0.01
    assert f["eq15"]["vegetation_ndvi_error"] <= 0.01
    assert f["eq15"]["panel_cv_across_frames"] <= 0.01
    assert f["eq16"]["panel_abs_error"] > f["eq15"]["panel_abs_error"]
