"""``mscal apply CAPTURE_DIR --calibration factory -o OUT`` on MicaSense's real RedEdge
captures (IMG_0000: panel, IMG_0001: flight): radiance and reflectance from the files' own
factory metadata, panel found without help, sun-sensor route, photogrammetry tags, re-runs,
and captures that are incomplete or truncated."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import exifread
import numpy as np
import pytest
import tifffile
import xarray as xr

from mscal_core.factory import polygon_mask
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.catalog import load_target
from pipeline.ingest.tiff import read_raw
from pipeline.products.writers import file_band_name
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import BANDS, MARKER_PANEL, PANEL_CORNERS, paint_marker, require_data

PANEL_TARGET = "micasense-rp02-1603036-sc"
SERIAL_SOURCE = f"panel serial RP02-1603036-SC (QR code of IMG_0000) -> target {PANEL_TARGET}"


def _apply(folder: Path, out: Path, *extra: str) -> int:
    return main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--products", "radiance", *extra])


@pytest.fixture(scope="module")
def panel_run(tmp_path_factory) -> Path:
    data = require_data()
    out = tmp_path_factory.mktemp("factory") / "panel"
    assert _apply(data, out, "--panel-reflectance", PANEL_TARGET) == 0
    return out


@pytest.fixture(scope="module")
def dls_run(tmp_path_factory) -> Path:
    data = require_data()
    out = tmp_path_factory.mktemp("factory") / "dls"
    assert _apply(data, out, "--reference", "dls") == 0  # auto reads the panel's serial: the panel route
    return out


def test_radiance_is_the_factory_model_and_dls_reflectance_is_pi_l_over_e(dls_run) -> None:
    """DLS route: R = pi L / E_h with E_h the reading turned horizontal (sun position,
    tilt, direct/diffuse split; the correction E_h / E per capture is in run.json sun_sensor)."""
    data = require_data()
    ds = xr.open_zarr(dls_run / "reflectance.zarr")
    run = json.loads((dls_run / "run.json").read_text())
    assert run_value(run, "reference")["route"] == "dls" and run["frames"] == ["IMG_0000", "IMG_0001"]
    # the panel capture was held 10.8 deg off level, the flight capture 1.6 deg: the model
    # (MicaSense's DLS 1, clear sky 1/6) lowers the tilted reading by 11 %, the level one barely
    corr = {c: run_value(run, "sun_sensor")[c]["correction"] for c in ("IMG_0000", "IMG_0001")}
    assert run_value(run, "sun_sensor")["IMG_0000"]["sensor_tilt_deg"] == pytest.approx(10.806, abs=0.01)
    assert run_value(run, "sun_sensor")["IMG_0000"]["sun_elevation_deg"] == pytest.approx(41.22, abs=0.02)
    assert corr["IMG_0000"]["Blue"] == pytest.approx(0.8862, abs=2e-3)
    assert corr["IMG_0001"]["Blue"] == pytest.approx(1.0170, abs=2e-3)
    assert list(ds["band_name"].values) == list(BANDS)
    for f, cap in enumerate(("IMG_0000", "IMG_0001")):
        for b in range(5):
            meta = read_capture_meta(data / f"{cap}_{b + 1}.tif")
            dn = read_raw(meta.path)
            expect = factory_radiance(meta, dn).astype(np.float32)
            expect[dn >= 65520] = np.nan
            got = ds["radiance"].isel(frame=f, band=b).values
            np.testing.assert_allclose(got, expect, rtol=1e-6, equal_nan=True)
            refl = ds["reflectance"].isel(frame=f, band=b).values
            k = math.pi / (meta.irradiance * corr[cap][BANDS[b]])
            np.testing.assert_allclose(refl, expect * np.float32(k), rtol=1e-5, equal_nan=True)
            assert float(ds["irradiance"].isel(frame=f, band=b)) == pytest.approx(meta.irradiance)
    raw = xr.open_zarr(dls_run / "raw.zarr")
    np.testing.assert_array_equal(raw["dn"].isel(frame=1, band=3).values, read_raw(data / "IMG_0001_4.tif"))


def test_panel_route_finds_the_panel_and_gives_its_reflectance_back(panel_run) -> None:
    run = json.loads((panel_run / "run.json").read_text())
    ref = run_value(run, "reference")
    assert ref["route"] == "panel-dls"  # the default with a panel and sun-sensor readings
    (panel,) = ref["panels"]
    assert panel["capture"] == "IMG_0000" and panel["region_source"] == ["detected"] * 5
    # the panel is evenly lit in this capture: the Eq. 11-14 split and the plain mean agree
    for band in BANDS:
        assert panel["factor_split"][band] == pytest.approx(panel["factor_mean"][band], rel=5e-3)
    lo, hi = panel["brightness_p10_p90"]
    assert 0.95 < lo <= 1.0 <= hi < 1.05
    # reflectance over the published panel corners is the panel's own reflectance
    ds = xr.open_zarr(panel_run / "reflectance.zarr")
    rho = load_target(PANEL_TARGET).reflectance.at(ds["wavelength"].values)
    for b in range(5):
        img = ds["reflectance"].isel(frame=0, band=b).values
        inner = polygon_mask(img.shape, np.mean(PANEL_CORNERS[b], axis=0) + 0.7 * (np.array(PANEL_CORNERS[b]) - np.mean(PANEL_CORNERS[b], axis=0)))
        assert float(np.nanmean(img[inner])) == pytest.approx(rho[b], rel=0.01)
    # the flight capture: vegetation, a plausible NDVI (the published tutorial's scene)
    ndvi = ds["ndvi"].isel(frame=1).values
    assert 0.5 < float(np.nanmedian(ndvi)) < 0.75
    assert np.isfinite(ds["reflectance"].values).mean() > 0.99


def test_panel_reflectance_from_the_cameras_albedo(panel_run, tmp_path) -> None:
    """A panel capture whose band files carry XMP Albedo (MicaSense: the panel's reflectance as
    the camera read it from its QR code) gives reflectance without --panel-reflectance: the
    panel comes back at its Albedo and run.json says where rho came from. --panel-reflectance
    still wins; an Albedo that is not a reflectance in one band is named and not used (0: none
    measured; the panel's serial, read from its QR code, gives the reflectance then)."""
    from pipeline.apply.factory_reference import ALBEDO_SOURCE

    folder = cf.rededge_auto_panel(tmp_path / "auto", ["0.25"] * 5)
    assert _apply(folder, tmp_path / "albedo") == 0
    run = json.loads((tmp_path / "albedo" / "run.json").read_text())
    ref = run_value(run, "reference")
    assert ref["route"] == "panel-dls" and ref["panel_reflectance"] == ALBEDO_SOURCE and "panels_seen" not in ref
    (panel,) = ref["panels"]
    assert panel["capture"] == "IMG_0000" and panel["reflectance"] == dict.fromkeys(BANDS, 0.25)
    ds = xr.open_zarr(tmp_path / "albedo" / "reflectance.zarr")
    for b in range(5):
        img = ds["reflectance"].isel(frame=0, band=b).values
        corners = np.array(PANEL_CORNERS[b], dtype=np.float64)
        inner = polygon_mask(img.shape, corners.mean(axis=0) + 0.7 * (corners - corners.mean(axis=0)))
        assert float(np.nanmean(img[inner])) == pytest.approx(0.25, rel=0.01)
    # the same panel, its reflectance given: the published one wins, outputs as the plain run's
    assert _apply(folder, tmp_path / "given", "--panel-reflectance", PANEL_TARGET) == 0
    given = run_value(json.loads((tmp_path / "given" / "run.json").read_text()), "reference")
    assert given["panel_reflectance"] == f"--panel-reflectance {PANEL_TARGET}"
    np.testing.assert_allclose(xr.open_zarr(tmp_path / "given" / "reflectance.zarr")["reflectance"].values,
                               xr.open_zarr(panel_run / "reflectance.zarr")["reflectance"].values, rtol=1e-6, equal_nan=True)
    bad = cf.rededge_auto_panel(tmp_path / "bad", ["0.25", "0", "1.7", "0.25", "0.25"])  # 0: not measured
    assert _apply(bad, tmp_path / "bad_out") == 0
    bad_run = json.loads((tmp_path / "bad_out" / "run.json").read_text())
    assert run_value(bad_run, "reference")["route"] == "panel-dls" and "panels_seen" not in run_value(bad_run, "reference")
    assert run_value(bad_run, "reference")["panel_reflectance"] == SERIAL_SOURCE
    (problem,) = [p for p in bad_run["metadata_problems"] if p["feature"] == "panel_albedo"]
    assert problem["file"].endswith("IMG_0000_3.tif") and problem["value"] == "1.7"


def test_albedo_only_of_a_valid_panel_capture_and_auto_falls_back_without_a_panel(tmp_path, capsys) -> None:
    """Albedo counts only with CalibrationPicture 2 (MicaSense's automatic panel capture; Pix4D
    1: an invalid one): with 1 it is ignored (the panel's serial, from its QR code, is used
    instead). With 2 on a capture where no panel can be found (the flight capture),
    --reference auto takes the sun sensor as without it and run.json says why; --reference
    panel, asked for, stops with the reason; --panel naming a capture without Albedo takes the
    panel's serial, or stops naming the capture(s) without Albedo."""
    invalid = cf.rededge_auto_panel(tmp_path / "invalid", ["0.25"] * 5, picture=1)
    assert _apply(invalid, tmp_path / "invalid_out") == 0
    ref = run_value(json.loads((tmp_path / "invalid_out" / "run.json").read_text()), "reference")
    assert ref["route"] == "panel-dls" and "albedo_panel_unusable" not in ref and "panels_seen" not in ref
    assert ref["panel_reflectance"] == SERIAL_SOURCE and ref["panels"][0]["reflectance"]["Red"] == 0.68
    flight = cf.rededge_auto_panel(tmp_path / "flight", ["0.25"] * 5, capture="0001")
    assert _apply(flight, tmp_path / "flight_out") == 0
    ref = run_value(json.loads((tmp_path / "flight_out" / "run.json").read_text()), "reference")
    assert ref["route"] == "dls" and "panel_reflectance" not in ref
    assert ref["albedo_panel_unusable"].startswith(
        "IMG_0001_1.tif: no usable panel among the 1 capture(s) with the camera's XMP Albedo: no reflectance panel found")
    from pipeline.products.report import report_dict

    warns = {w["code"]: w for s in report_dict(None, [tmp_path / "flight_out"])["sections"] for w in s["warnings"]}
    assert "reflectance comes from the dls route instead" in warns["albedo_panel_unusable"]["message"]
    capsys.readouterr()
    assert _apply(flight, tmp_path / "asked", "--reference", "panel") == 2
    assert "no usable panel among the 1 capture(s)" in capsys.readouterr().err
    assert _apply(flight, tmp_path / "serial", "--reference", "panel", "--panel", "IMG_0000") == 0
    ref = run_value(json.loads((tmp_path / "serial" / "run.json").read_text()), "reference")
    assert ref["route"] == "panel" and ref["panel_reflectance"] == SERIAL_SOURCE
    assert _apply(flight, tmp_path / "named", "--reference", "panel", "--panel", "IMG_0000,IMG_0001") == 2
    assert "--panel capture(s) IMG_0000: not in the folder, or a band file has no XMP Albedo" in capsys.readouterr().err
    assert not (tmp_path / "asked").exists() and not (tmp_path / "named").exists()


def test_panel_and_dls_are_compared_in_run_json(panel_run) -> None:
    panel = run_value(json.loads((panel_run / "run.json").read_text()), "reference")["panels"][0]
    for band in BANDS:
        ratio = panel["panel_over_dls"][band]
        assert ratio == pytest.approx(panel["factor_split"][band] / panel["factor_dls"][band])
        assert 0.5 < ratio < 2.0  # same light, two references: of the same order, not equal (DLS tilt)


def test_report_compares_panel_and_dls(panel_run, dls_run, tmp_path) -> None:
    from pipeline.products.report import PANEL_DLS_COLOUR_SPREAD_MAX, report_dict, write_report

    sec = report_dict(flights=[panel_run])["sections"][0]
    table = next(t for t in sec["tables"] if t["title"].startswith("Reflectance reference: panel vs sun sensor"))
    ratio = run_value(json.loads((panel_run / "run.json").read_text()), "reference")["panels"][0]["panel_over_dls"]
    assert [r[1] for r in table["rows"]] == list(BANDS) and all(r[0] == "IMG_0000" for r in table["rows"])
    assert [float(r[5]) for r in table["rows"]] == pytest.approx([ratio[b] for b in BANDS], rel=1e-3)
    # this RedEdge's DLS (no tilt correction) and its panel disagree in colour by tens of per cent
    spread = max(ratio.values()) / min(ratio.values()) - 1
    warned = [w for w in sec["warnings"] if w["code"] == "panel_dls_colour"]
    assert spread > PANEL_DLS_COLOUR_SPREAD_MAX and len(warned) == 1
    assert warned[0]["value"] == pytest.approx(spread) and "NIR" in warned[0]["message"]
    dls = report_dict(flights=[dls_run])["sections"][0]
    assert [t["rows"][0][0] for t in dls["tables"] if t["title"] == "Reflectance reference"] == ["dls"]
    assert not [w for w in dls["warnings"] if w["code"] == "panel_dls_colour"]
    html = write_report(tmp_path / "r.html", flights=[panel_run]).read_text()
    assert "panel vs sun sensor" in html and "panel_dls_colour" in html


def test_photogrammetry_tiffs_of_a_capture_share_its_uuid(panel_run) -> None:
    uuids = set()
    for rig, band in enumerate(BANDS):
        p = panel_run / "photogrammetry" / f"IMG_0001_{file_band_name(band)}.tif"
        with p.open("rb") as fh:
            tags = exifread.process_file(fh, details=False)
        assert str(tags["GPS GPSLongitudeRef"]) == "W" and str(tags["GPS GPSLatitudeRef"]) == "N"
        lat = sum(float(v.num) / float(v.den) / 60**i for i, v in enumerate(tags["GPS GPSLatitude"].values))
        assert lat == pytest.approx(36.576, abs=1e-3)
        xmp = tifffile.TiffFile(p).pages[0].tags[700].value
        xmp = xmp.decode() if isinstance(xmp, bytes) else xmp
        assert band in xmp and f'RigCameraIndex="{rig}"' in xmp
        uuids.add(xmp.split("CaptureUUID=")[1][:38])
        assert tifffile.imread(p).shape == (960, 1280)
    assert len(uuids) == 1
    assert (panel_run / "ndvi" / "IMG_0001.tif").is_file()


def test_rerun_is_up_to_date(panel_run, capsys) -> None:
    before = (panel_run / "run.json").read_bytes()
    assert _apply(require_data(), panel_run, "--panel-reflectance", PANEL_TARGET) == 0
    assert "up to date" in capsys.readouterr().out
    assert (panel_run / "run.json").read_bytes() == before


def test_up_to_date_is_decided_by_the_files_content(tmp_path, capsys) -> None:
    """A copy of the folder with new modification times is up to date; a band file rewritten
    with its size and time kept (one DN changed) is not: the content decides, as for a
    snapshot flight."""
    import os

    data = require_data()
    folder = tmp_path / "caps"
    folder.mkdir()
    for p in sorted(data.glob("IMG_000[01]_*.tif")):
        shutil.copy(p, folder / p.name)  # new modification times
    out = tmp_path / "out"
    assert _apply(folder, out, "--reference", "dls", "--no-tiffs") == 0
    run = json.loads((out / "run.json").read_text())
    assert run["frames_out"] == 2 and len(run["fingerprint"]["frames_sha256"]) == 64
    assert set(run["frames_sha256"]) == {"IMG_0000", "IMG_0001"}
    for p in folder.iterdir():
        os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    capsys.readouterr()
    assert _apply(folder, out, "--reference", "dls", "--no-tiffs") == 0
    assert "up to date" in capsys.readouterr().out
    band = folder / "IMG_0001_3.tif"
    st = band.stat()
    raw = bytearray(band.read_bytes())
    raw[len(raw) // 2] ^= 0x01  # a pixel in the middle of the image: same size, other content
    band.write_bytes(bytes(raw))
    os.utime(band, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert band.stat().st_size == st.st_size and band.stat().st_mtime_ns == st.st_mtime_ns
    assert _apply(folder, out, "--reference", "dls", "--no-tiffs") == 0
    assert "up to date" not in capsys.readouterr().out
    again = json.loads((out / "run.json").read_text())
    assert again["frames_sha256"]["IMG_0000"] == run["frames_sha256"]["IMG_0000"]
    assert again["frames_sha256"]["IMG_0001"] != run["frames_sha256"]["IMG_0001"]


def test_incomplete_and_truncated_captures_are_quarantined(tmp_path, capsys) -> None:
    data = require_data()
    folder = tmp_path / "caps"
    folder.mkdir()
    for p in data.glob("IMG_000[01]_*.tif"):
        shutil.copy(p, folder / p.name)
        shutil.copy(p, folder / p.name.replace("IMG_0001", "IMG_0002").replace("IMG_0000", "IMG_0003"))
    (folder / "IMG_0002_5.tif").unlink()  # capture IMG_0002 misses a band
    blob = (folder / "IMG_0003_3.tif").read_bytes()
    (folder / "IMG_0003_3.tif").write_bytes(blob[: len(blob) // 2])  # truncated
    out = tmp_path / "out"
    assert _apply(folder, out) == 0
    run = json.loads((out / "run.json").read_text())
    reasons = {q["file"]: q["reason"] for q in run["quarantined"]}
    assert run["frames"] == ["IMG_0000", "IMG_0001"] and run["frames_in"] == 4
    assert any("IMG_0002" in f for f in reasons) and "missing band file(s) 5" in " ".join(reasons.values())
    assert any("IMG_0003" in f for f in reasons)
    assert not list((out / "photogrammetry").glob("IMG_0003_*")) and not list(out.rglob("*.tmp*"))
    assert xr.open_zarr(out / "reflectance.zarr").sizes["frame"] == 2
    assert _apply(folder, tmp_path / "strict", "--strict") == 3


def test_12bit_band_files_give_the_16bit_radiance_and_their_clipped_pixels(dls_run, tmp_path) -> None:
    """IMG_0001 saved as packed 12-bit TIFFs (tests.camera_files.rededge_12bit): applied, not
    quarantined; radiance and reflectance as from the 16-bit files; its pixels at 4095 are
    saturated (NaN and counted, as the 16-bit files' at 65520); raw.zarr keeps the DN as stored."""
    from tests import camera_files as cf

    data = require_data()
    folder = tmp_path / "caps12"
    folder.mkdir()
    for b in range(1, 6):
        cf.rededge_12bit(data / f"IMG_0001_{b}.tif", folder / f"IMG_0001_{b}.tif")
    out = tmp_path / "out12"
    assert _apply(folder, out) == 0
    run = json.loads((out / "run.json").read_text())
    ref = json.loads((dls_run / "run.json").read_text())
    assert run["frames"] == ["IMG_0001"] and run["quarantined"] == []
    assert run["saturated_pixels"]["per_frame"]["IMG_0001"] == ref["saturated_pixels"]["per_frame"]["IMG_0001"] == 7240
    ds, ds16 = xr.open_zarr(out / "reflectance.zarr"), xr.open_zarr(dls_run / "reflectance.zarr")
    raw = xr.open_zarr(out / "raw.zarr")
    for b in range(5):
        dn16 = read_raw(data / f"IMG_0001_{b + 1}.tif")
        dn = raw["dn"].isel(frame=0, band=b).values
        np.testing.assert_array_equal(dn, dn16 >> 4)
        rad = ds["radiance"].isel(frame=0, band=b).values
        assert np.isnan(rad[dn == 4095]).all() and np.isfinite(rad[dn < 4095]).all()
        for var in ("radiance", "reflectance"):
            np.testing.assert_allclose(ds[var].isel(frame=0, band=b).values, ds16[var].isel(frame=1, band=b).values,
                                       rtol=1e-6, equal_nan=True)


def test_panel_marker_from_session_yaml(panel_run, tmp_path) -> None:
    """A session.yaml beside the captures says where the panel is from a marker in its plane;
    the factors agree with the ones from the detected panel (same panel, 0.75-inset regions)."""
    import yaml

    data = require_data()
    session = tmp_path / "session"
    folder = session / "flights" / "f1"
    folder.mkdir(parents=True)
    for p in data.glob("IMG_000[01]_*.tif"):
        shutil.copy(p, folder / p.name)
    for b in range(1, 6):
        dn = tifffile.memmap(folder / f"IMG_0000_{b}.tif", mode="r+")
        paint_marker(dn, b)
        dn.flush()
        del dn
    (session / "session.yaml").write_text(yaml.safe_dump({"panel": MARKER_PANEL}))
    assert _apply(folder, tmp_path / "out", "--panel-reflectance", PANEL_TARGET) == 0
    (panel,) = run_value(json.loads((tmp_path / "out" / "run.json").read_text()), "reference")["panels"]
    assert panel["region_source"] == ["marker"] * 5
    (detected,) = run_value(json.loads((panel_run / "run.json").read_text()), "reference")["panels"]
    for band in BANDS:
        assert panel["factor_split"][band] == pytest.approx(detected["factor_split"][band], rel=0.01), band
    # a marker config the images do not show: the detection is used, as without session.yaml
    (session / "session.yaml").write_text(yaml.safe_dump({"panel": {**MARKER_PANEL,
                                                                    "marker": {**MARKER_PANEL["marker"], "id": 8}}}))
    assert _apply(folder, tmp_path / "out8", "--panel-reflectance", PANEL_TARGET) == 0
    (panel8,) = run_value(json.loads((tmp_path / "out8" / "run.json").read_text()), "reference")["panels"]
    assert panel8["region_source"] == ["detected"] * 5


def _field_store(path: Path, capture: str, *, response: str, vignetting: str) -> Path:
    """A field calibration store for the RedEdge: ``response`` 'factory' (U linear with the
    capture's black level, arbitrary scale) or 'square'; ``vignetting`` 'factory' (V = 1 /
    the factory correction) or 'flat'."""
    from pipeline.ingest.catalog import load_camera
    from pipeline.ingest.meta import factory_vignetting
    from pipeline.storage.store import new_dataset, write_store

    data = require_data()
    metas = [read_capture_meta(data / f"{capture}_{b + 1}.tif") for b in range(5)]
    k = np.arange(4096, dtype=np.float64)
    lut = np.stack([3.0 * (k * 16 - m.black_level) if response == "factory" else k**2 for m in metas])
    vig = np.stack([1 / factory_vignetting(m) if vignetting == "factory" else np.ones(m.shape) for m in metas])
    ds = new_dataset(load_camera("micasense-rededge"))
    ds["inverse_response"] = (("band", "dn"), lut)
    ds["vignetting"] = (("band", "y", "x"), vig)
    return write_store(ds, path)


def test_field_components_replace_the_factory_ones(tmp_path) -> None:
    data = require_data()
    folder = tmp_path / "caps"
    folder.mkdir()
    for p in data.glob("IMG_0001_*.tif"):
        shutil.copy(p, folder / p.name)
    same = _field_store(tmp_path / "same.zarr", "IMG_0001", response="factory", vignetting="factory")
    flat = _field_store(tmp_path / "flat.zarr", "IMG_0001", response="square", vignetting="flat")
    outs = {}
    for name, extra in {
        "factory": [],
        "both": ["--field-calibration", str(same)],  # the factory model re-expressed as field fits
        "vignetting": ["--field-calibration", str(flat), "--field-components", "vignetting"],
        "response": ["--field-calibration", str(flat), "--field-components", "response"],
    }.items():
        assert _apply(folder, tmp_path / name, *extra) == 0, name
        outs[name] = xr.open_zarr(tmp_path / name / "reflectance.zarr")["radiance"].isel(frame=0).values
    np.testing.assert_allclose(outs["both"], outs["factory"], rtol=2e-6, equal_nan=True)
    run = json.loads((tmp_path / "vignetting" / "run.json").read_text())
    assert run_value(run, "components") == {"response": "factory", "vignetting": f"field:{flat.resolve()}"}
    assert run_value(json.loads((tmp_path / "factory" / "run.json").read_text()), "components") == {
        "response": "factory", "vignetting": "factory"}
    for b in range(5):
        meta = read_capture_meta(folder / f"IMG_0001_{b + 1}.tif")
        from pipeline.ingest.meta import factory_vignetting

        corr = factory_vignetting(meta)
        # flat field V: the factory radiance without its vignetting correction
        np.testing.assert_allclose(outs["vignetting"][b], outs["factory"][b] / corr, rtol=2e-6, equal_nan=True)
        # a squared U: radiance grows with the square of (DN - 0), scaled to the factory at the low end
        dn = read_raw(meta.path).astype(np.float64)
        lit = (dn > 8 * meta.black_level) & (dn < 65520)
        ratio = outs["response"][b][lit] / outs["factory"][b][lit]
        slope = np.polyfit(dn[lit], ratio, 1)[0]
        assert slope > 0 and np.corrcoef(dn[lit], ratio)[0, 1] > 0.99, b


def test_field_components_on_12bit_band_files(tmp_path) -> None:
    """The field response over sensor DN on IMG_0001 as packed 12-bit files: the same radiance
    as on the 16-bit files (U is indexed by the sensor DN, which the 12-bit file stores as it
    is, and scaled with the file's own black level and depth). Indexing it with the catalog's
    shift of 4 as well read U at a sixteenth of the DN."""
    from tests import camera_files as cf

    data = require_data()
    f16, f12 = tmp_path / "caps16", tmp_path / "caps12"
    f16.mkdir()
    f12.mkdir()
    for b in range(1, 6):
        shutil.copy(data / f"IMG_0001_{b}.tif", f16 / f"IMG_0001_{b}.tif")
        cf.rededge_12bit(data / f"IMG_0001_{b}.tif", f12 / f"IMG_0001_{b}.tif")
    square = _field_store(tmp_path / "square.zarr", "IMG_0001", response="square", vignetting="factory")
    rad = {}
    for name, folder in (("16", f16), ("12", f12)):
        assert _apply(folder, tmp_path / name, "--field-calibration", str(square)) == 0, name
        rad[name] = xr.open_zarr(tmp_path / name / "reflectance.zarr")["radiance"].isel(frame=0).values
    lit = np.isfinite(rad["16"]) & (rad["16"] > 0)
    assert lit.mean() > 0.9
    np.testing.assert_array_equal(np.isnan(rad["12"]), np.isnan(rad["16"]))
    np.testing.assert_allclose(rad["12"][lit], rad["16"][lit], rtol=1e-5)


@pytest.mark.parametrize(
    ("extra", "expect"),
    [
        (["--field-components", "vignetting"], "needs --field-calibration"),
        (["--field-calibration", "STORE", "--field-components", "spectral_factor"], "not one of response, vignetting"),
        (["--field-calibration", "NOSTORE"], "calibration store not found"),
    ],
)
def test_bad_field_components_exit_2(tmp_path, capsys, extra, expect) -> None:
    store = _field_store(tmp_path / "s.zarr", "IMG_0001", response="factory", vignetting="factory")
    extra = [str(store) if e == "STORE" else str(tmp_path / "none.zarr") if e == "NOSTORE" else e for e in extra]
    assert _apply(require_data(), tmp_path / "o", *extra) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err, err


@pytest.mark.parametrize(
    ("extra", "expect"),
    [
        (["--panel", "IMG_0042", "--panel-reflectance", "0.5"], "IMG_0042 that are not in the folder"),
        (["--panel", "IMG_0001", "--panel-reflectance", "0.5"], "panel capture IMG_0001"),
        (["--normalise", "band:Red"], "use --reference"),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, extra, expect) -> None:
    assert _apply(require_data(), tmp_path / "o", *extra) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err, err
    assert not (tmp_path / "o" / "reflectance.zarr").exists()


def test_folder_without_factory_metadata_is_named(tmp_path, capsys) -> None:
    folder = tmp_path / "plain"
    folder.mkdir()
    tifffile.imwrite(folder / "IMG_0000_1.tif", np.zeros((8, 8), np.uint16))
    assert _apply(folder, tmp_path / "o") == 2
    err = capsys.readouterr().err
    assert "no TIFF with factory radiometric metadata" in err and str(folder) in err


def test_a_panel_capture_on_the_sun_sensor_route_is_kept_out_of_photogrammetry(dls_run) -> None:
    """IMG_0000 shows the panel in every band: without --panel-reflectance it is still a
    capture of reflectance.zarr, but its TIFFs go to OUT/panels/, not among the survey frames."""
    run = json.loads((dls_run / "run.json").read_text())
    assert run_value(run, "panels") == [{"capture": "IMG_0000",
                              "reason": "a reflectance panel (camera's panel flag, --panel, or detected); not used: "
                                        "no --panel-reflectance"}]
    assert sorted(p.name for p in (dls_run / "panels").iterdir()) == sorted(
        f"IMG_0000_{file_band_name(b)}.tif" for b in BANDS)
    assert sorted(p.name for p in (dls_run / "photogrammetry").iterdir()) == sorted(
        f"IMG_0001_{file_band_name(b)}.tif" for b in BANDS)
    assert [p.name for p in (dls_run / "ndvi").iterdir()] == ["IMG_0001.tif"]
    assert list(xr.open_zarr(dls_run / "reflectance.zarr")["frame"].values) == ["IMG_0000", "IMG_0001"]
