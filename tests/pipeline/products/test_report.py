"""The QA report: plots of stored results, warnings with numbers, one
self-contained HTML page, and (slow) that page rendered in headless Chromium.

The fast tests use a calibration store built from the synthetic camera truth (no fit: it
takes a second) and two short synthetic flights applied with it; the slow test uses the demo
session (``small``) end to end.
"""

from __future__ import annotations

import base64
import copy
import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import xarray as xr

from pipeline.ingest.catalog import load_camera
from pipeline.products import report
from pipeline.run.cli import main
from pipeline.sim.synth import write_frameset
from pipeline.sim.world.scene import flight_frames, make_truth
from pipeline.storage.atomic import TMP_MARK
from pipeline.storage.store import new_dataset, open_calibration, write_store

CAMERA = "ximea-mq022hg-sm5x5-nir"
N_BANDS = 25
QA_BAND = 7  # 803 nm, the camera's NIR index band
RHO = 0.5
IMG_PREFIX = '<img src="data:image/png;base64,'


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def truth():
    return make_truth(0)


def _reflector_images(truth, ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two reflector images at the QA band under opposite brightness ramps (B median 1),
    DN from the true response without noise; the reflector is a centred rectangle."""
    h, w = ds.sizes["y"], ds.sizes["x"]
    yy, xx = np.mgrid[0:h, 0:w]
    on = (np.abs(yy - h / 2) < 70) & (np.abs(xx - w / 2) < 150)
    ramp = (xx - w / 2) / w
    B = np.stack([1 + 0.8 * ramp, 1 - 0.8 * ramp]).astype(np.float32)
    B = np.where(on, B, np.nan)
    t = np.array([2.0, 2.5])
    U = ds["inverse_response"].values[QA_BAND]
    V, S = ds["vignetting"].values[QA_BAND], ds["spectral_factor"].values[QA_BAND]
    energy = t[:, None, None] * V * S * np.where(on, B, 1.0) * RHO
    energy *= U[500] / np.median(energy[:, on])  # U's units are the sensor's: bring the median to DN 500
    dn = np.clip(np.searchsorted(U, energy), 0, 1022).astype(np.uint16)
    return B, dn, t


def fake_calibration(truth) -> xr.Dataset:
    """A complete calibration store with the true U, V, S of the synthetic camera and the
    attributes 'mscal calibrate' writes, with sound numbers (no warning should fire)."""
    cam = load_camera(CAMERA)
    ds = new_dataset(cam)
    ds.coords["dn"] = np.arange(1024, dtype=np.int32)
    ds["inverse_response"] = (("band", "dn"), truth.inverse_response)
    ds["black_level"] = ("band", np.full(N_BANDS, truth.black_level))
    ds["saturation_dn"] = ("band", np.full(N_BANDS, 1023, dtype=np.int32))
    V = truth.vignetting.astype(np.float32)
    ds["vignetting"] = (("band", "y", "x"), V)
    count = np.zeros(V.shape, dtype=np.uint16)
    count[:, 20:200, 30:380] = 3
    count[:, 60:160, 100:300] = 6
    ds["vignetting_count"] = (("band", "y", "x"), count)
    ds["vignetting_observed"] = (("band", "y", "x"), count >= 3)
    ds["spectral_factor"] = ("band", truth.spectral_factor.astype(np.float64))
    B, dn, t = _reflector_images(truth, ds)
    ds = ds.assign_coords(reflector_image=[0, 1], reflector_file=("reflector_image", np.array(["r0.tif", "r1.tif"], dtype=object)),
                          reflector_exposure_ms=("reflector_image", t))
    ds["reflector_brightness"] = (("reflector_image", "y", "x"), B)
    ds["reflector_dn"] = (("reflector_image", "y", "x"), dn, {"band": QA_BAND})
    px = [int(np.isfinite(b).sum()) for b in B]
    ds.attrs.update({
        "response": {"inputs": {f"response/s{i}.tif": "0" * 64 for i in range(7)}, "skipped": [], "seconds": 1.0,
                     "residuals": {"method": "forward", "residual_rms_dn": [3.0] * N_BANDS,
                                   "black_level": [32.0] * N_BANDS, "observed_dn": [[26, 1022]] * N_BANDS}},
        "vignetting": {"inputs": {f"vignetting/v{i}.tif": "0" * 64 for i in range(8)}, "seconds": 1.0,
                       "skipped": [{"file": "v4.tif", "reason": "marker DICT_4X4_50 id 3 not found"}],
                       "residuals": {"views_used": 7, "views_total": 8, "residual_rms": [0.009] * N_BANDS,
                                     "observed_fraction": [float((count[0] >= 3).mean())] * N_BANDS,
                                     "saturated_fraction": [0.0] * N_BANDS}},
        "illumination": {"inputs": {"reflector/r0.tif": "0" * 64, "reflector/r1.tif": "0" * 64}, "skipped": [],
                         "seconds": 0.5,
                         "residuals": {"images_used": 2, "reflector_pixels": sum(px), "reflector_pixels_per_image": px,
                                       "residual_rms": 0.015, "image_brightness": [1.05, 0.95],
                                       "saturated_fraction": [0.0] * N_BANDS}},
        "fits": ["response", "vignetting", "illumination"], "mscal_version": "0.1.0",
    })
    return ds


@pytest.fixture(scope="module")
def calib(truth, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("calib") / "calib.zarr"
    write_store(fake_calibration(truth), path)
    return path


@pytest.fixture(scope="module")
def calib_ds(calib) -> xr.Dataset:
    return open_calibration(calib)


def _rewrite_csv(folder: Path, edit) -> None:
    rows = list(csv.DictReader((folder / "frames.csv").open()))
    edit(rows)
    with (folder / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)


@pytest.fixture(scope="module")
def flights(truth, calib, tmp_path_factory) -> dict[str, Path]:
    """Two applied flights of 4 synthetic frames: 'clean', and 'bad' with a truncated frame
    (quarantined) and IMG_0002's exposure_ms recorded 4x too long."""
    root = tmp_path_factory.mktemp("flights")
    fs = flight_frames(truth, n_frames=4, supersample=1)
    clean = root / "clean"
    write_frameset(clean, fs)
    bad = root / "bad"
    shutil.copytree(clean, bad)
    (bad / "IMG_0004.tif").write_bytes((bad / "IMG_0000.tif").read_bytes()[:5000])

    def edit(rows):
        rows[2]["exposure_ms"] = repr(float(rows[2]["exposure_ms"]) * 4)
        rows.append({**rows[0], "file": "IMG_0004.tif"})

    _rewrite_csv(bad, edit)
    out = {}
    for name, folder in (("clean", clean), ("bad", bad)):
        out[name] = root / f"out-{name}"
        assert main(["apply", str(folder), "--calibration", str(calib), "-o", str(out[name])]) == 0
    return out


def _panels(fig) -> list:
    """Axes of a figure other than colour bars."""
    return [ax for ax in fig.axes if ax.get_label() not in ("<colorbar>", "<twin>")]


# --------------------------------------------------------------------------- calibration plots


def test_calibration_plots_have_one_panel_per_band(calib_ds) -> None:
    ds = calib_ds
    fig = report.plot_inverse_response(ds)
    assert len(_panels(fig)) == N_BANDS
    # the first panel's solid line is U of band 0 inside the observed DN range, NaN outside
    y = np.asarray(_panels(fig)[0].lines[0].get_ydata(), dtype=float)
    np.testing.assert_allclose(y[26:1023], ds["inverse_response"].values[0, 26:1023])
    assert np.isnan(y[:26]).all() and np.isnan(y[1023:]).all()
    # with the fit's residual per DN bin stored, each panel gets it on a right-hand axis
    resid = np.linspace(0.5, 3.0, N_BANDS * 32).reshape(N_BANDS, 32)
    with_resid = ds.assign_coords(dn_bin=(np.arange(32) + 0.5) * 32).assign(
        response_residual=(("band", "dn_bin"), resid))
    fig = report.plot_inverse_response(with_resid)
    twins = [ax for ax in fig.axes if ax.get_label() == "<twin>"]
    assert len(_panels(fig)) == N_BANDS and len(twins) == N_BANDS
    np.testing.assert_allclose(twins[3].lines[0].get_ydata(), resid[3])
    for plot, var in ((report.plot_vignetting, "vignetting"), (report.plot_coverage, "vignetting_count")):
        fig = plot(ds)
        panels = _panels(fig)
        assert len(panels) == N_BANDS and all(len(ax.images) == 1 for ax in panels)
        assert len({ax.images[0].get_clim() for ax in panels}) == 1  # one shared colour scale
        assert len(fig.axes) == N_BANDS + 1  # and one colour bar
        data = np.ma.filled(np.asarray(panels[5].images[0].get_array(), dtype=float), np.nan)
        expect = ds[var].values[5].astype(float)
        if var == "vignetting_count":
            expect[expect == 0] = np.nan
        np.testing.assert_array_equal(data, expect)
    fig = report.plot_spectral_factor(ds)
    x, y = fig.axes[0].lines[0].get_data()
    order = np.argsort(ds["wavelength"].values)
    np.testing.assert_allclose(x, ds["wavelength"].values[order])
    np.testing.assert_allclose(y, ds["spectral_factor"].values[order])
    assert len(_panels(report.plot_brightness(ds))) == 2  # one per reflector image
    assert len(_panels(report.plot_reflector_correction(ds))) == 4  # Eq. 16 and Eq. 15 per image


def test_eq15_corrects_the_reflector_and_eq16_shows_the_light(calib_ds) -> None:
    rows = report.reflector_corrections(calib_ds)
    assert [(r["image"], r["reference"]) for r in rows] == [(0, 1), (1, 0)]
    for r in rows:
        # Eq. 15 with B recovers the uniform reflector to quantisation (< 1 %), at the same
        # level in both images ...
        assert r["eq15_spread"] < 0.01
        assert np.nanmedian(r["eq15"]) == pytest.approx(np.nanmedian(rows[0]["eq15"]), rel=0.005)
        # ... the baseline divides one ramp by the opposite one: (1+0.8a)/(1-0.8a) over the
        # reflector (|a| < 150/409) spans about 0.45 .. 2.2 of the median.
        assert r["eq16_spread"] > 1.0


# --------------------------------------------------------------------------- calibration warnings


def _edit(ds: xr.Dataset, stage: str, **residuals) -> xr.Dataset:
    out = ds.copy()
    out.attrs = copy.deepcopy(dict(ds.attrs))
    out.attrs[stage]["residuals"].update(residuals)
    return out


def test_sound_calibration_has_no_warning(calib_ds) -> None:
    assert report.calibration_warnings(calib_ds) == []


@pytest.mark.parametrize("stage, residuals, code, value, threshold", [
    ("response", {"observed_dn": [[26, 1022]] * 24 + [[40, 400]]}, "sweep_dn_range", (400 - 40) / (1022 - 32),
     report.SWEEP_COVERAGE_MIN),
    ("response", {"residual_rms_dn": [3.0] * 20 + [12.5] + [3.0] * 4}, "response_residual", 12.5,
     report.RESPONSE_RESIDUAL_RMS_DN_MAX),
    ("vignetting", {"saturated_fraction": [0.0] * 3 + [0.04] + [0.0] * 21}, "saturated_fraction", 0.04,
     report.SATURATED_FRACTION_MAX),
    ("vignetting", {"residual_rms": [0.05] + [0.009] * 24}, "vignetting_residual", 0.05, report.VIGNETTING_RESIDUAL_RMS_MAX),
    ("vignetting", {"observed_fraction": [0.3] * 25}, "vignetting_coverage", 0.3, report.VIGNETTING_OBSERVED_MIN),
    ("illumination", {"reflector_pixels": 4200}, "few_reflector_pixels", 4200, report.MIN_REFLECTOR_PIXELS),
    ("illumination", {"residual_rms": 0.08}, "illumination_residual", 0.08, report.ILLUMINATION_RESIDUAL_RMS_MAX),
    ("illumination", {"image_brightness": [1.2, 0.6]}, "exposure_inconsistent", 2.0, report.REFLECTOR_BRIGHTNESS_RATIO_MAX),
])
def test_each_warning_fires_with_its_number(calib_ds, stage, residuals, code, value, threshold) -> None:
    ws = report.calibration_warnings(_edit(calib_ds, stage, **residuals))
    assert [w.code for w in ws] == [code]
    assert ws[0].value == pytest.approx(value, rel=1e-6)
    assert ws[0].threshold == threshold


def test_the_response_residual_limit_scales_with_the_sensors_bits(calib_ds) -> None:
    """9 DN rms is set for the 10-bit sensor; a 12-bit store's DN count 4x as many for the same
    noise (12.9 DN on a sound RedEdge-style fit is no warning), a 16-bit store's 64x."""
    ds = _edit(calib_ds, "response", residual_rms_dn=[3.0] * 24 + [12.9])
    assert [w.code for w in report.calibration_warnings(ds)] == ["response_residual"]  # 10-bit: 12.9 > 9
    deep = ds.isel(dn=slice(0, 1)).reindex(dn=np.arange(4096))  # the same residuals on a 12-bit DN axis
    assert report.response_residual_limit(deep) == pytest.approx(36.0)
    assert [w.code for w in report.calibration_warnings(deep) if w.code == "response_residual"] == []
    assert report.response_residual_limit(ds.isel(dn=slice(0, 1)).reindex(dn=np.arange(65536))) == pytest.approx(576.0)


def test_marker_missing_in_three_of_eight_views(calib_ds) -> None:
    ds = calib_ds.copy()
    ds.attrs = copy.deepcopy(dict(calib_ds.attrs))
    ds.attrs["vignetting"]["skipped"] = [{"file": f"v{i}.tif", "reason": "marker DICT_4X4_50 id 3 not found"}
                                         for i in (1, 4, 6)]
    (w,) = report.calibration_warnings(ds)
    assert w.code == "marker_not_found" and w.value == pytest.approx(3 / 8)
    assert "3 of 8 views" in w.message


def test_narrow_sweep_names_the_band_and_range(calib_ds) -> None:
    ds = _edit(calib_ds, "response", observed_dn=[[26, 1022]] * 7 + [[30, 600]] + [[26, 1022]] * 17)
    (w,) = report.calibration_warnings(ds)
    assert "803 nm" in w.message and "30-600" in w.message


# --------------------------------------------------------------------------- flights


def test_flight_warnings_with_numbers(flights, calib_ds) -> None:
    assert report.flight_warnings(report.open_flight(flights["clean"]), calib_ds) == []
    ws = {w.code: w for w in report.flight_warnings(report.open_flight(flights["bad"]), calib_ds)}
    assert set(ws) == {"quarantined_frames", "exposure_inconsistent"}
    assert ws["quarantined_frames"].value == 1 and "IMG_0004.tif" in ws["quarantined_frames"].message
    # IMG_0002's exposure is recorded 4x too long: its level is 4x low (light varies a little per frame)
    assert 3.0 < ws["exposure_inconsistent"].value < 5.0
    assert "IMG_0002" in ws["exposure_inconsistent"].message and "IMG_0001" not in ws["exposure_inconsistent"].message


def test_flight_dn_beyond_a_narrow_sweep(flights, calib_ds) -> None:
    ds = _edit(calib_ds, "response", observed_dn=[[26, 300]] * N_BANDS)
    flight = report.open_flight(flights["clean"])
    (w,) = [w for w in report.flight_warnings(flight, ds) if w.code == "flight_dn_outside_sweep"]
    dn = xr.open_zarr(flights["clean"] / "raw.zarr")["dn"].values  # all frames, all pixels
    full = max(float(np.mean((dn[:, b] > 300) & (dn[:, b] < 1023))) for b in range(N_BANDS))
    assert full > 0.05 and w.value == pytest.approx(full, abs=0.01)  # the sample is close to the whole
    assert "300" in w.message


def test_frame_table_has_exposures_gps_and_quarantine_reasons(flights) -> None:
    flight = report.open_flight(flights["bad"])
    rows = report.frame_rows(flight)
    csv_rows = list(csv.DictReader((Path(flight.run["flight"]) / "frames.csv").open()))
    assert [r["frame"] for r in rows] == ["IMG_0000", "IMG_0001", "IMG_0002", "IMG_0003", "IMG_0004.tif"]
    for r, c in zip(rows[:4], csv_rows):
        assert r["exposure_ms"] == f"{float(c['exposure_ms']):g}"
        assert float(r["lat"]) == pytest.approx(float(c["lat"]), abs=1e-7)
        assert r["time"] == c["time"][:19] and r["status"] == "ok"
    assert rows[4]["status"] == "quarantined" and "IMG_0004.tif" in rows[4]["reason"]


def test_flight_plots(flights) -> None:
    flight = report.open_flight(flights["clean"])
    fig = report.plot_ndvi(flight)
    assert len(fig.axes) == 3 * 4  # 3 frames shown (first, middle, last): raw, calibrated, two Otsu masks
    (ax,) = [a for a in fig.axes if a.get_title() == "IMG_0000: NDVI calibrated"]
    calibrated = np.asarray(ax.images[0].get_array())
    np.testing.assert_allclose(calibrated, flight.reflectance["ndvi"].isel(frame=0).values, equal_nan=True)
    fig = report.plot_histograms(flight)
    assert len(_panels(fig)) == N_BANDS
    (stairs,) = _panels(fig)[0].patches
    counts = float(np.sum(stairs.get_data().values))
    # 4 frames x (every 3rd row and column of 217 x 409), minus values outside the shared range
    assert 0.98 * 4 * 73 * 137 <= counts <= 4 * 73 * 137
    fig = report.plot_track(flight)
    offsets = fig.axes[0].collections[0].get_offsets()
    np.testing.assert_allclose(offsets[:, 1], flight.reflectance["lat"].values)
    assert len(offsets) == 4


def test_histograms_stay_bounded_on_long_flights() -> None:
    idx = report.sample_indices(5000, report.HIST_MAX_FRAMES)
    assert len(idx) == report.HIST_MAX_FRAMES and idx[0] == 0 and idx[-1] == 4999
    assert report.flight._stride((5000, 25, 217, 409), report.HIST_MAX_PIXELS) == 3


# --------------------------------------------------------------------------- the page


def _pngs(page: str) -> list[np.ndarray]:
    out = []
    for b64 in re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page):
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_UNCHANGED)
        out.append(img)
    return out


def test_report_html_is_self_contained(calib, flights, tmp_path) -> None:
    out = tmp_path / "qa" / "report.html"
    assert report.write_report(out, calibration=calib, flights=[flights["bad"]]) == out
    page = out.read_text()
    n_plots = 6 + 3  # calibration: U, V, coverage, S, B, Eq. 15/16; flight: NDVI, track, histograms
    assert page.count(IMG_PREFIX) == n_plots == page.count("<img ")
    imgs = _pngs(page)
    assert len(imgs) == n_plots
    assert all(img is not None and img.shape[0] > 100 and img.shape[1] > 100 and img.std() > 0 for img in imgs)
    # nothing is loaded from anywhere: no external src/href, and the CSP forbids it anyway
    assert not re.search(r'(src|href)="(?!data:|#)', page)
    assert "default-src 'none'" in page
    # warnings with their numbers, the quarantined frame with its reason
    assert "quarantined_frames" in page and "exposure_inconsistent" in page and "IMG_0004.tif" in page
    summary = json.loads((tmp_path / "qa" / "calibration.json").read_text())
    assert summary["camera"] == CAMERA and len(summary["bands"]) == N_BANDS and summary["warnings"] == []
    assert summary["bands"][QA_BAND]["S"] == pytest.approx(float(open_calibration(calib)["spectral_factor"][QA_BAND]))
    assert not list((tmp_path / "qa").glob(f"*{TMP_MARK}*"))
    # no figure left in pyplot's registry (the report never uses pyplot)
    plt = sys.modules.get("matplotlib.pyplot")
    assert plt is None or plt.get_fignums() == []


def test_markdown_and_dict_carry_the_same_warnings(calib_ds, flights) -> None:
    md = report.report_markdown(calibration=calib_ds, flights=[flights["bad"]])
    d = report.report_dict(calibration=calib_ds, flights=[flights["bad"]])
    codes = [w["code"] for s in d["sections"] for w in s["warnings"]]
    assert sorted(codes) == ["exposure_inconsistent", "quarantined_frames"]
    for c in codes:
        assert f"| {c} |" in md
    assert "| IMG_0004.tif |" in md and "## Flight: bad" in md


def test_report_is_written_atomically(calib_ds, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(report.page, "_html_figure", lambda caption, build: f"<p>{caption}</p>")  # no rendering: fast
    out = tmp_path / "report.html"
    out.write_text("old report")
    seen = []
    real_replace = os.replace

    def failing_replace(src, dst):
        seen.append((Path(src), Path(dst)))
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError):
        report.write_report(out, calibration=calib_ds)
    # the temporary file sits beside the target, carries TMP_MARK, and is gone after the failure
    assert seen and seen[0][0].parent == tmp_path and TMP_MARK in seen[0][0].name
    assert out.read_text() == "old report"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.html"]
    monkeypatch.setattr(os, "replace", real_replace)
    report.write_report(out, calibration=calib_ds)
    assert out.read_text().startswith("<!DOCTYPE html>")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json", "report.html"]


def test_cli_report(calib, flights, tmp_path, capsys) -> None:
    out = tmp_path / "r.html"
    code = main(["report", "--flight", str(flights["clean"]), "--flight", str(flights["bad"]), "-o", str(out)])
    page = out.read_text()
    assert code == 0 and page.count(IMG_PREFIX) == 2 * 3 and "Flight: clean" in page and "Flight: bad" in page
    assert f"wrote {out}" in capsys.readouterr().out
    assert not (tmp_path / "calibration.json").exists()  # only beside a calibration's report
    code = main(["report", "--flight", str(tmp_path), "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no run.json" in err[0] and "mscal apply" in err[0]


# --------------------------------------------------------------------------- as a person sees it

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.mark.slow
@pytest.mark.long  # ~25 s (an apply, a report, a headless browser): make test-long
def test_demo_report_renders_in_chromium(small, tmp_path) -> None:
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} is not installed (Debian package 'chromium'; .ci/run installs it)")
    session, calib = small
    out = tmp_path / "out"
    assert main(["apply", str(session / "flights" / "field"), "--calibration", str(calib), "-o", str(out)]) == 0
    page = out / "report.html"
    assert main(["report", "--calibration", str(calib), "--flight", str(out), "-o", str(page)]) == 0
    common = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run([*common, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120)
    body = re.search(r"<body[^>]*>", dom.stdout)
    assert body, dom.stderr[-2000:]
    assert 'data-broken-images="0"' in body.group(0)
    assert dom.stdout.count("<img ") == 9
    shot = tmp_path / "page.png"
    subprocess.run([*common, f"--screenshot={shot}", "--window-size=1400,3000", page.as_uri()],
                   capture_output=True, timeout=120, check=True)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (3000, 1400)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # plots, not a blank page


def test_older_and_partial_stores_still_report(calib_ds) -> None:
    older = calib_ds.drop_vars(["reflector_brightness", "reflector_dn", "reflector_file", "reflector_exposure_ms"])
    (sec,) = report.build_sections(older)
    assert [c for c, _ in sec.figures] == ["Inverse response per band", "Vignetting per band",
                                           "Coverage of the vignetting fit", "Spectral factor"]
    partial = calib_ds[["inverse_response", "black_level", "saturation_dn"]]
    partial.attrs = {k: v for k, v in calib_ds.attrs.items() if k not in ("vignetting", "illumination")}
    (sec,) = report.build_sections(partial)
    assert [c for c, _ in sec.figures] == ["Inverse response per band"]
    assert report.calibration_warnings(partial) == []
    assert "| b803 | 803 |" in report.sections_markdown([sec])


def test_capture_level_table_says_how_the_sensor_level_was_obtained() -> None:
    """The calibration section lists each reflector capture's sun-sensor level and
    the store's ``sun_sensor_model`` (raw for a store written before it); none without levels."""
    import xarray as xr

    from pipeline.products.report.sections import capture_level_table

    times = np.array(["2026-06-01T10:00:00", "2026-06-01T10:34:00"], dtype="datetime64[ns]")
    ds = xr.Dataset({"capture_level": ("capture", [1.0, 0.87]),
                     "capture_irradiance": ("capture", [0.41, 0.356], {"sun_sensor_model": "horizontal"}),
                     "capture_time": ("capture", times)},
                    coords={"capture_name": ("capture", ["before", "after"])})
    t = capture_level_table(ds)
    assert t is not None and [r[0] for r in t.rows] == ["before", "after"]
    assert t.rows[1] == ["after", "2026-06-01T10:34:00", 0.87, 0.356]
    assert "horizontal" in t.note
    old = ds.assign(capture_irradiance=("capture", [0.41, 0.356]))
    assert "raw reading" in capture_level_table(old).note
    assert capture_level_table(ds.assign(capture_irradiance=("capture", [np.nan, np.nan]))) is None


def test_report_warnings_do_not_import_matplotlib(calib, flights) -> None:
    """Every command's summary asks the report for its warnings; matplotlib (0.6 s to import)
    is loaded only where a figure is drawn."""
    import subprocess

    code = ("import sys; from pipeline.run.console import report_warnings; "
            f"w = report_warnings({str(calib)!r}, [{str(flights['bad'])!r}]); "
            "print(len(w), sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    n, mods = out.stdout.split(" ", 1)
    assert int(n) >= 2 and mods.strip() == "[]"  # the bad flight's warnings, without matplotlib
