"""One pipeline for every camera: multi-lens (one-file-per-band) flights through the
one executor with a field calibration store or the factory model, on the real MicaSense
RedEdge captures; capture folders as the camera writes them; options refused where they do
not apply."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import pipeline.apply.executor as executor
from mscal_core.factory import row_gradient
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.tiff import read_raw
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests.micasense_data import BANDS, factory_store, require_data


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    require_data()
    return factory_store(tmp_path_factory.mktemp("ms-store") / "calib.zarr")


@pytest.fixture(scope="module")
def field_run(store, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ms-field") / "out"
    assert main(["apply", str(require_data()), "--calibration", str(store), "-o", str(out)]) == 0
    return out


def test_field_store_on_a_multilens_flight_is_eq15_per_band_file(field_run) -> None:
    """The store is the factory model (U linear, V the vignetting polynomial, S the factory
    scale): Eq. 15 per band file, with that file's own exposure and gain, must give the
    factory radiance without its row-gradient term, to float32 rounding, on a capture the
    store was not built from."""
    ds = xr.open_zarr(field_run / "reflectance.zarr")
    assert list(ds["frame"].values) == ["IMG_0000", "IMG_0001"]
    assert ds["reflectance"].shape == (2, 5, 960, 1280)
    assert list(ds["band_name"].values) == list(BANDS)
    refl = ds["reflectance"].values
    for b in range(5):
        meta = read_capture_meta(require_data() / f"IMG_0001_{b + 1}.tif")
        dn = read_raw(meta.path)
        expect = factory_radiance(meta, dn) / row_gradient(dn.shape[0], meta.exposure_s, *meta.radiometric_calibration[1:])
        ok = (dn < 65520) & (expect > 1e-3)
        assert ok.mean() > 0.9
        np.testing.assert_allclose(refl[1, b][ok], expect[ok], rtol=2e-5)
        assert np.all(np.isnan(refl[1, b][dn >= 65520]))  # saturated: NaN and counted
    run = json.loads((field_run / "run.json").read_text())
    assert run["saturated_pixels"]["total"] == sum(
        int(np.count_nonzero(read_raw(require_data() / f"IMG_000{c}_{b}.tif") >= 65520)) for c in (0, 1) for b in range(1, 6))
    # one layout for all cameras: the same outputs as a snapshot flight (the default products)
    assert set(ds.data_vars) == {"reflectance", "quality", "ndvi", "vegetation_mask"}
    assert sorted(p.name for p in (field_run / "photogrammetry").glob("IMG_0001_*.tif")) == sorted(
        f"IMG_0001_{b.replace(' e', 'E')}.tif" for b in BANDS)  # "Red edge" -> RedEdge: no spaces
    assert sorted(p.name for p in (field_run / "ndvi").glob("*.tif")) == ["IMG_0000.tif", "IMG_0001.tif"]
    assert run["calibration_sha256"] and run["frames_out"] == 2 and run["quarantined"] == []
    assert [s["file"] for s in run_value(run, "skipped")] == ["LICENSE", "README.md"]
    raw = xr.open_zarr(field_run / "raw.zarr")["dn"].values
    np.testing.assert_array_equal(raw[0, 3], read_raw(require_data() / "IMG_0000_4.tif"))


def test_factory_and_field_chains_run_in_the_same_executor(store, tmp_path, monkeypatch) -> None:
    """Both chains are one task function (executor.process_frames -> executor.radiometry)."""
    seen: list[tuple[str, str]] = []
    real = executor.radiometry

    def spy(camera, chain, job, dn, channels=None):
        seen.append((chain.kind, job.name))
        return real(camera, chain, job, dn, channels)

    monkeypatch.setattr(executor, "radiometry", spy)
    monkeypatch.setenv("MSCAL_APPLY_SCHEDULER", "threads")
    assert main(["apply", str(require_data()), "--calibration", str(store), "-o", str(tmp_path / "field")]) == 0
    assert main(["apply", str(require_data()), "--calibration", "factory", "-o", str(tmp_path / "factory"),
                 "--products", "radiance"]) == 0
    assert sorted(seen) == [("factory", "IMG_0000"), ("factory", "IMG_0001"), ("field", "IMG_0000"), ("field", "IMG_0001")]
    a = xr.open_zarr(tmp_path / "field" / "reflectance.zarr")
    f = xr.open_zarr(tmp_path / "factory" / "reflectance.zarr")
    assert set(a.data_vars) | {"radiance"} == set(f.data_vars)
    assert a["reflectance"].shape == f["reflectance"].shape


def test_field_store_on_12bit_band_files_is_the_16bit_result(field_run, store, tmp_path) -> None:
    """IMG_0001 with bands 3-5 as a RedEdge set to its 12-bit format writes them
    (tests.camera_files.rededge_12bit) and bands 1-2 as 16-bit files: the store's U is over the
    sensor DN, so the 12-bit files (sensor DN as they are) give the 16-bit run's reflectance and
    saturated pixels. Shifting them by the catalog's 4 as well gave a sixteenth of the DN:
    reflectance near zero and no pixel saturated."""
    from tests import camera_files as cf

    folder = tmp_path / "caps12"
    folder.mkdir()
    for b in range(1, 6):  # bands 1-2 as 16-bit files, 3-5 as 12-bit ones: each file by its own depth
        if b <= 2:
            shutil.copy(require_data() / f"IMG_0001_{b}.tif", folder / f"IMG_0001_{b}.tif")
        else:
            cf.rededge_12bit(require_data() / f"IMG_0001_{b}.tif", folder / f"IMG_0001_{b}.tif")
    out = tmp_path / "out"
    assert main(["apply", str(folder), "--calibration", str(store), "-o", str(out)]) == 0
    got = xr.open_zarr(out / "reflectance.zarr")["reflectance"].isel(frame=0).values
    ref = xr.open_zarr(field_run / "reflectance.zarr")["reflectance"].isel(frame=1).values
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-6, equal_nan=True)
    run, ref_run = (json.loads((o / "run.json").read_text()) for o in (out, field_run))
    assert run["saturated_pixels"]["total"] == ref_run["saturated_pixels"]["per_frame"]["IMG_0001"] == 7240


def test_rerun_is_up_to_date(field_run, store, capsys) -> None:
    assert main(["apply", str(require_data()), "--calibration", str(store), "-o", str(field_run)]) == 0
    assert "up to date" in capsys.readouterr().out


def test_sd_card_tree_with_other_files(store, tmp_path, capsys) -> None:
    """Captures in 0000SET/000/ and a second set restarting the numbering: names get their
    path; a copy of a capture (same CaptureId) is quarantined; other files are skipped, said."""
    card = tmp_path / "card"
    (card / "0000SET" / "000").mkdir(parents=True)
    (card / "0001SET" / "000").mkdir(parents=True)
    for p in require_data().glob("IMG_*.tif"):
        shutil.copy(p, card / "0000SET" / "000" / p.name)
    for b in range(1, 6):
        shutil.copy(require_data() / f"IMG_0001_{b}.tif", card / "0001SET" / "000" / f"IMG_0000_{b}.tif")
    (card / "0000SET" / "diag0.dat").write_bytes(b"\0" * 10)
    (card / "paramlog.txt").write_text("log")
    assert main(["apply", str(card), "--calibration", str(store), "-o", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "skipped 2 file(s) that are not captures: 0000SET/diag0.dat, paramlog.txt" in err
    assert "quarantined 0001SET/000/IMG_0000_1.tif: capture 0001SET_000_IMG_0000: same XMP CaptureId as " \
           "0000SET_000_IMG_0001" in err
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert list(ds["frame"].values) == ["0000SET_000_IMG_0000", "0000SET_000_IMG_0001"]


def test_store_of_other_bands_is_refused(store, tmp_path, capsys) -> None:
    ds = xr.open_zarr(store, chunks=None).load()
    ds = ds.assign_coords(band_name=("band", np.array(["B1", "B2", "B3", "B4", "B5"], dtype=object)))
    from pipeline.storage.store import write_store

    bad = write_store(ds, tmp_path / "bad.zarr")
    assert main(["apply", str(require_data()), "--calibration", str(bad), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "store bands B1, B2, B3, B4, B5 are not the bands of micasense-rededge" in err and "\n" not in err


@pytest.mark.parametrize("extra, expect", [
    (["--illumination", "linear", "--reference", "dls"], "--illumination is for the panel route"),
    (["--centre-bands"], "--centre-bands is for snapshot mosaic cameras"),
    (["--no-align", "--registration", "reg.zarr"], "--no-align and --registration contradict each other"),
    (["--normalise", "band:NIR"], "--normalise is for field calibrations"),
])
def test_factory_refuses_options_it_would_ignore(tmp_path, capsys, extra, expect) -> None:
    require_data()
    assert main(["apply", str(require_data()), "--calibration", "factory", "-o", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert expect in err and "\n" not in err
    assert not (tmp_path / "o" / "run.json").exists()


def test_factory_panel_light_follows_the_sun_sensor(tmp_path) -> None:
    """Default with a panel and sun-sensor readings (``panel-dls``): each capture's
    factor is the panel's times the sensor's change per band, E_h,b(panel) / E_h,b(capture)
    (tilt-corrected readings, run.json sun_sensor); ``--reference panel``: the panel's factor
    for every capture, as before."""
    args = ["apply", str(require_data()), "--calibration", "factory", "--panel-reflectance",
            "micasense-rp02-1603036-sc", "--panel", "IMG_0000"]
    assert main([*args, "-o", str(tmp_path / "lit"), "--products", "radiance"]) == 0
    assert main([*args, "-o", str(tmp_path / "flat"), "--reference", "panel"]) == 0
    lit = json.loads((tmp_path / "lit" / "run.json").read_text())
    flat = json.loads((tmp_path / "flat" / "run.json").read_text())
    k = run_value(flat, "reference")["factor"]
    assert flat["illumination"]["varies_in_time"] is False and "frame_irradiance" not in run_value(flat, "light")
    assert run_value(lit, "reference")["route"] == "panel-dls" and lit["illumination"]["mode"] == "linear"
    e = {c: run_value(lit, "sun_sensor")[c]["horizontal_irradiance"] for c in ("IMG_0000", "IMG_0001")}
    per = lit["illumination"]["per_frame"]
    for band in BANDS:
        assert per["IMG_0000"][band] == pytest.approx(k[band], rel=1e-9)
        assert per["IMG_0001"][band] == pytest.approx(k[band] * e["IMG_0000"][band] / e["IMG_0001"][band], rel=1e-5)
        assert run_value(lit, "light")["frame_irradiance"]["IMG_0001"][band] == pytest.approx(math.pi / per["IMG_0001"][band],
                                                                                   rel=1e-5)
    # the sensor's light fell 1-14 % per band between the two captures (Blue rose 1 %)
    change = {b: e["IMG_0001"][b] / e["IMG_0000"][b] for b in BANDS}
    assert change["Blue"] == pytest.approx(1.0128, abs=2e-3) and change["Red"] == pytest.approx(0.8556, abs=2e-3)
    a = xr.open_zarr(tmp_path / "lit" / "reflectance.zarr")
    ratio = np.nanmedian(a["reflectance"].values[1, 3] / a["radiance"].values[1, 3])
    assert ratio == pytest.approx(per["IMG_0001"]["NIR"], rel=1e-5)
    b = xr.open_zarr(tmp_path / "flat" / "reflectance.zarr")
    np.testing.assert_array_equal(a["reflectance"].values[0], b["reflectance"].values[0])


def test_field_store_light_follows_the_captures_sun_sensor(store, field_run, tmp_path) -> None:
    """A store whose reflector capture has a sun-sensor reading: each multi-lens
    capture's light is scaled by its own DLS reading (the mean of its bands' XMP Irradiance),
    so reflectance is Eq. 15 x E(reflector capture) / E(capture)."""
    from pipeline.storage.store import write_store

    e = {c: float(np.mean([read_capture_meta(require_data() / f"{c}_{b}.tif").irradiance for b in range(1, 6)]))
         for c in ("IMG_0000", "IMG_0001")}
    ds = xr.open_zarr(store, chunks=None).load()
    s = ds["spectral_factor"].values
    ds["capture_spectral_factor"] = (("capture", "band"), s[None])
    ds["capture_level"] = (("capture",), [float(np.exp(np.mean(np.log(s))))])
    ds["capture_irradiance"] = (("capture",), [e["IMG_0000"]])
    ds = ds.assign_coords(capture_name=("capture", np.array(["before"], dtype=object)),
                          capture_time=("capture", np.array(["2017-10-19T20:40:39"], dtype="datetime64[ns]")))
    lit_store = write_store(ds, tmp_path / "lit.zarr")
    out = tmp_path / "out"
    assert main(["apply", str(require_data()), "--calibration", str(lit_store), "-o", str(out)]) == 0
    lit = xr.open_zarr(out / "reflectance.zarr")["reflectance"].values
    plain = xr.open_zarr(field_run / "reflectance.zarr")["reflectance"].values
    for f, c in enumerate(("IMG_0000", "IMG_0001")):
        ratio = np.nanmedian(lit[f] / plain[f], axis=(1, 2))
        np.testing.assert_allclose(ratio, e["IMG_0000"] / e[c], rtol=1e-5)
    run = json.loads((out / "run.json").read_text())
    assert run["illumination"]["varies_in_time"] is True
    assert run["illumination"]["frames_with_irradiance"] == 2
    assert e["IMG_0000"] / e["IMG_0001"] != pytest.approx(1.0, abs=0.05)  # the readings differ enough to tell
