"""``mscal apply CAPTURE_DIR --calibration factory`` on every camera mscal knows.

Real files: MicaSense RedEdge, Parrot Sequoia, Sentera Double 4K (../shared/data). Cameras
without files here are built from the real RedEdge files with their manufacturer's tag set
(tests/camera_files.py). Every capture must be processed, and the factory radiance must agree
with the manufacturer's published model -- evaluated here independently, pixel by pixel in
plain Python -- within 0.2 % on the panel and in the image corners.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
import xarray as xr

from pipeline.products.report import report_dict
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import PANEL_CORNERS, require_data

DATA_ROOT = Path(__file__).parents[3].parent / "shared" / "data"
TOL = 2e-3  # 0.2 %
CORNERS = ((0, 0), (1279, 0), (0, 959), (1279, 959), (3, 5), (1270, 950))  # (x, y)


def _apply(folder: Path, out: Path, *extra: str) -> dict:
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--products", "radiance", *extra]) == 0
    return json.loads((out / "run.json").read_text())


def _tags(path: Path) -> tuple[dict, str]:
    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
        return tags, tags[700].decode("utf-8")


def _floats(xmp: str, qname: str) -> list[float]:
    import re

    local = qname.split(":")[-1]  # any prefix: the test files use more than one
    body = re.search(rf"<([\w-]+):{local}>(.*?)</\1:{local}>", xmp, re.S)[2]
    return [float(v) for v in re.findall(r"[-+0-9.eE]+", re.sub(r"</?rdf:\w+>", " ", body))]


def micasense_expected(path: Path, x: int, y: int) -> float:
    """MicaSense's radiance model (support article 115000351194; image.py radiance()) at one
    pixel, from the file's own tags, in plain Python."""
    tags, xmp = _tags(path)
    dn = float(tifffile.imread(path)[y, x])
    exif = tags[34665]
    te = exif["ExposureTime"][0] / exif["ExposureTime"][1]
    g = exif["ISOSpeed"] / 100.0
    black = tags[50714]
    bl = sum(black) / len(black) if isinstance(black, tuple) else float(black)
    a1, a2, a3 = _floats(xmp, "MicaSense:RadiometricCalibration")
    if "VignettingPolynomial2D>" in xmp:
        c = _floats(xmp, "Camera:VignettingPolynomial2D")
        e = _floats(xmp, "Camera:VignettingPolynomial2DName")
        u, v = x / 1280.0, y / 960.0
        vig = 1.0 / sum(ci * u ** e[2 * i] * v ** e[2 * i + 1] for i, ci in enumerate(c))
    else:
        cx, cy = _floats(xmp, "Camera:VignettingCenter")
        k = _floats(xmp, "Camera:VignettingPolynomial")
        r = math.hypot(x - cx, y - cy)
        vig = 1.0 / (1.0 + sum(ki * r ** (i + 1) for i, ki in enumerate(k)))
    p, pbl = dn / 65536.0, bl / 65536.0
    return max(vig * a1 / g * (p - pbl) / (te + a2 * y - a3 * te * y), 0.0)


def _panel_mean_expected(path: Path, corners, expected_map) -> float:
    """Mean over the panel polygon of a model evaluated on the whole image (vectorised here,
    from the same plain formula)."""
    h, w = expected_map.shape
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.asarray(corners, np.int32).reshape(-1, 1, 2)], 1)
    return float(expected_map[mask.astype(bool)].mean())


def micasense_map(path: Path) -> np.ndarray:
    tags, xmp = _tags(path)
    dn = tifffile.imread(path).astype(np.float64)
    exif = tags[34665]
    te = exif["ExposureTime"][0] / exif["ExposureTime"][1]
    g = exif["ISOSpeed"] / 100.0
    black = tags[50714]
    bl = sum(black) / len(black) if isinstance(black, tuple) else float(black)
    a1, a2, a3 = _floats(xmp, "MicaSense:RadiometricCalibration")
    yy, xx = np.mgrid[0:960, 0:1280].astype(np.float64)
    if "VignettingPolynomial2D>" in xmp:
        c = _floats(xmp, "Camera:VignettingPolynomial2D")
        e = _floats(xmp, "Camera:VignettingPolynomial2DName")
        vig = 1.0 / sum(ci * (xx / 1280) ** e[2 * i] * (yy / 960) ** e[2 * i + 1] for i, ci in enumerate(c))
    else:
        cx, cy = _floats(xmp, "Camera:VignettingCenter")
        k = _floats(xmp, "Camera:VignettingPolynomial")
        r = np.hypot(xx - cx, yy - cy)
        vig = 1.0 / (1.0 + sum(ki * r ** (i + 1) for i, ki in enumerate(k)))
    return np.maximum(vig * a1 / g * (dn - bl) / 65536.0 / (te + a2 * yy - a3 * te * yy), 0.0)


def _check_radiance(ds: xr.Dataset, frame: int, band: int, path: Path, expected_at, panel=None, expected_map=None,
                    sat: int = 65520) -> None:
    rad = ds["radiance"].isel(frame=frame, band=band).values
    dn = tifffile.imread(path)
    for x, y in CORNERS:
        if dn[y, x] >= sat:
            continue
        assert rad[y, x] == pytest.approx(expected_at(path, x, y), rel=TOL), (path.name, x, y)
    if panel is not None:
        got = _panel_mean_expected(path, panel, np.nan_to_num(rad.astype(np.float64)))
        assert got == pytest.approx(_panel_mean_expected(path, panel, expected_map), rel=TOL)


# --------------------------------------------------------------------------- MicaSense variants


def test_rededge_mx_dual_is_ten_bands_one_capture(tmp_path) -> None:
    require_data()
    folder = cf.rededge_mx_dual(tmp_path / "dual")
    run = _apply(folder, tmp_path / "out", "--reference", "dls")
    assert run["camera"] == "micasense-rededge-mx-dual" and run["frames"] == ["IMG_0000", "IMG_0001"]
    assert run["quarantined"] == [] and "10 band(s) per capture" in run_value(run, "camera_identification")["evidence"]
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert ds.sizes["band"] == 10
    assert list(ds["wavelength"].values) == [475, 560, 668, 840, 717, 444, 531, 650, 705, 740]
    for f, cap in enumerate(cf.CAPTURES):
        for b in (0, 4, 5, 9):
            path = folder / f"IMG_{cap}_{b + 1}.tif"
            panel = PANEL_CORNERS[b % 5] if cap == "0000" else None
            _check_radiance(ds, f, b, path, micasense_expected, panel, micasense_map(path) if panel else None)


def test_rededge_p_pan_band_skipped_and_2d_vignetting(tmp_path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "p")
    run = _apply(folder, tmp_path / "out", "--reference", "dls")
    assert run["camera"] == "micasense-rededge-p" and run["frames"] == ["IMG_0000", "IMG_0001"]
    assert [s["band"] for s in run_value(run, "skipped_bands")] == ["Panchro", "Panchro"]
    assert "panchromatic" in run_value(run, "skipped_bands")[0]["reason"]
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert ds.sizes["band"] == 5
    for b in range(5):
        path = folder / f"IMG_0000_{b + 1}.tif"
        _check_radiance(ds, 0, b, path, micasense_expected, PANEL_CORNERS[b], micasense_map(path))


def test_altum_pt_thermal_never_in_reflectance(tmp_path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "apt", altum_pt=True)
    run = _apply(folder, tmp_path / "out", "--reference", "dls")
    assert run["camera"] == "micasense-altum-pt" and len(run["frames"]) == 2
    assert sorted({s["band"] for s in run_value(run, "skipped_bands")}) == ["LWIR", "Panchro"]
    lwir = [s for s in run_value(run, "skipped_bands") if s["band"] == "LWIR"][0]
    assert "thermal" in lwir["reason"] and "never mixed into reflectance" in lwir["reason"]
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert ds.sizes["band"] == 5 and 11000 not in list(ds["wavelength"].values)
    path = folder / "IMG_0001_3.tif"
    _check_radiance(ds, 1, 2, path, micasense_expected)
    path = folder / "IMG_0000_4.tif"
    _check_radiance(ds, 0, 3, path, micasense_expected, PANEL_CORNERS[3], micasense_map(path))


def test_reflect_area_as_one_li_and_other_prefix(tmp_path) -> None:
    """Firmware that writes ReflectArea as one rdf:li of comma-separated numbers: read as the
    panel region; the Camera namespace under another prefix and URI form is the same."""
    require_data()
    folder = cf.reflect_area_one_li(tmp_path / "fw", PANEL_CORNERS)
    run = _apply(folder, tmp_path / "out", "--panel-reflectance", "micasense-rp02-1603036-sc")
    assert run["frames"] == ["IMG_0000", "IMG_0001"] and run["metadata_problems"] == []
    # one region for all bands: band 1's area carried into each band by its detection
    assert run_value(run, "reference")["panels"][0]["region_source"] == ["xmp:Blue"] * 5
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    for b in range(5):
        path = folder / f"IMG_0000_{b + 1}.tif"
        _check_radiance(ds, 0, b, path, micasense_expected, PANEL_CORNERS[b], micasense_map(path))


def test_unreadable_reflect_area_disables_only_the_panel_area(tmp_path, capsys) -> None:
    require_data()
    folder = cf.reflect_area_one_li(tmp_path / "fw", PANEL_CORNERS, bad="622,371,574,abc")
    run = _apply(folder, tmp_path / "out", "--reference", "dls")
    assert run["frames"] == ["IMG_0000", "IMG_0001"] and run["quarantined"] == []
    (problem,) = run["metadata_problems"]
    assert problem["file"].endswith("IMG_0000_1.tif") and problem["tag"] == "ReflectArea"
    assert problem["value"] == "622,371,574,abc" and problem["feature"] == "panel_area"
    # the panel route still works: band 2's area, carried into every band by its detection of
    # the panel (one region for all bands; band 1 used to take its own detected inset)
    run = _apply(folder, tmp_path / "panel", "--panel-reflectance", "micasense-rp02-1603036-sc")
    assert run_value(run, "reference")["panels"][0]["region_source"] == ["xmp:Green"] * 5
    assert main(["cameras", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "tag problem: IMG_0000_1.tif: ReflectArea = '622,371,574,abc'" in out and "panel_area disabled" in out


def test_unreadable_sun_sensor_reading_keeps_the_radiance(tmp_path, capsys) -> None:
    """A capture whose Irradiance is unreadable still has radiance: processed, that band's
    reflectance NaN and named (run.json and a warning of the summary), the other bands'
    reflectance as before."""
    require_data()
    folder = tmp_path / "irr"
    folder.mkdir()
    for cap in cf.CAPTURES:
        for b in range(1, 6):
            edit = (lambda x: cf.set_element(x, "Camera:Irradiance", "n/a")) if (cap, b) == ("0001", 3) else None
            cf.rewrite(cf.band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", edit)
    capsys.readouterr()
    run = _apply(folder, tmp_path / "out", "--reference", "dls")  # auto: the panel's serial (its QR code)
    assert run["frames"] == ["IMG_0000", "IMG_0001"] and run["quarantined"] == [] and run_value(run, "reference")["route"] == "dls"
    (warn,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  warning reflectance_missing")]
    assert warn == ("  warning reflectance_missing: 1 band file(s) of 1 capture(s) have no usable sun-sensor reading: "
                    "their reflectance and the indices using them are NaN, radiance kept (run.json reflectance_missing; "
                    "first IMG_0001_3.tif: Irradiance = 'n/a': expected numbers (sun_sensor disabled)); a panel capture "
                    "with --panel-reflectance TARGET gives every band reflectance (value 1, threshold 0)")
    (missing,) = run_value(run, "reflectance_missing")
    assert (missing["capture"], missing["file"], missing["band"]) == ("IMG_0001", "IMG_0001_3.tif", "Red")
    assert "Irradiance = 'n/a'" in missing["reason"] and "sun_sensor disabled" in missing["reason"]
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    refl = ds["reflectance"].isel(frame=1).values
    assert np.isnan(refl[2]).all() and np.isfinite(refl[0]).mean() > 0.99
    assert np.isfinite(ds["radiance"].isel(frame=1, band=2).values).mean() > 0.99


def test_camera_override_everywhere(tmp_path) -> None:
    """--camera names the camera; a wrong one is reported per capture, not guessed around."""
    require_data()
    run = _apply(DATA_ROOT / "micasense-rededge", tmp_path / "o", "--camera", "micasense-rededge-mx")
    assert run["camera"] == "micasense-rededge-mx" and run_value(run, "camera_identification")["overridden"]
    assert main(["apply", str(DATA_ROOT / "micasense-rededge"), "--calibration", "factory", "-o",
                 str(tmp_path / "d"), "--camera", "micasense-rededge-mx-dual"]) == 2


# --------------------------------------------------------------------------- DJI


def dji_expected(path: Path, x: int, y: int) -> float:
    """DJI P4 Multispectral guide Eq. 6-9: X = pCam (DN/65535 - BL/65535) V / (g t_us 1e-6),
    V = 1 + sum k_i r^(i+1) about CalibratedOpticalCenterX/Y."""
    dn = float(tifffile.imread(path)[y, x])
    d = cf.DJI
    r = math.hypot(x - d["center"][0], y - d["center"][1])
    vig = 1.0 + sum(k * r ** (i + 1) for i, k in enumerate(d["k"]))
    return max(d["adjust"] * (dn / 65535 - d["black"] / 65535) * vig / (d["gain"] * d["exposure_us"] * 1e-6), 0.0)


def test_dji_p4_multispectral(tmp_path) -> None:
    require_data()
    folder = cf.dji_p4m(tmp_path / "p4m")
    # radiance on each stored pixel (registration: below); the sun sensor (auto: the QR code of the
    # MicaSense panel in the pixels these files were made of)
    run = _apply(folder, tmp_path / "out", "--no-align", "--reference", "dls")
    assert run["camera"] == "dji-p4-multispectral" and run["frames"] == ["001", "002"] and run["quarantined"] == []
    assert run_value(run, "band_alignment").startswith("none (--no-align")
    assert run_value(run, "reference")["route"] == "dls" and run_value(run, "reference")["scale"].startswith("fixed per camera model")
    # DJI's guides: R = X pCam / Irradiance, no further constant
    assert run_value(run, "reference")["sun_sensor_scale"]["constant"] == 1.0 and "relative_scale" not in run_value(run, "reference")
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert list(ds["wavelength"].values) == [450, 560, 650, 730, 840]  # NIR's from drone-dji:BandFreq
    for f in range(2):
        for b in range(5):
            path = folder / f"DJI_00{f + 1}{b + 1}.TIF"
            _check_radiance(ds, f, b, path, dji_expected)
            x, y = 3, 5
            refl = float(ds["reflectance"].isel(frame=f, band=b).values[y, x])
            # DJI's Irradiance is already compensated by the camera: divided by as written
            sun = run_value(run, "sun_sensor")[run["frames"][f]]
            assert sun["model"].startswith("DJI Irradiance as written")
            assert sun["correction"][ds["band_name"].values[b]] == 1.0
            assert refl == pytest.approx(dji_expected(path, x, y) / cf.DJI["irradiance"][b], rel=TOL)
    # the panel, as every other pixel, follows the guide's model
    path = folder / "DJI_0013.TIF"
    yy, xx = np.mgrid[0:960, 0:1280].astype(np.float64)
    r = np.hypot(xx - 640, yy - 480)
    vig = 1 + sum(k * r ** (i + 1) for i, k in enumerate(cf.DJI["k"]))
    full = np.maximum(1.002 * (tifffile.imread(path) - 4096.0) / 65535 * vig / 472.5e-6, 0)
    _check_radiance(ds, 0, 2, path, dji_expected, PANEL_CORNERS[2], full)


def test_dji_time_is_utc_at_exposure_not_the_local_clock(tmp_path) -> None:
    """A DJI band file's DateTimeOriginal is the aircraft's local clock; drone-dji:UTCAtExposure
    is UTC. Captures whose local clock reads 13:40 (UTC-7) and UTCAtExposure 20:40 UTC get the
    sun of 20:40 UTC (run.json), and their TIFFs say 20:40 UTC with GPS time stamps, as
    OpenDroneMap reads them. Taken as UTC, 13:40 put the sun 48 degrees lower, below the horizon."""
    import exifread

    from pipeline.ingest.solar import solar_position

    require_data()
    local = cf.dji_p4m(tmp_path / "local")
    folder = tmp_path / "utc"
    folder.mkdir()
    utc = {"1": "2017:10:19 20:40:39.200173", "2": "2017:10:19 20:42:10.200159"}
    for path in sorted(local.glob("*.TIF")):
        data = path.read_bytes()
        for a, b in ((b"2017:10:19 20:40:39", b"2017:10:19 13:40:39"), (b"2017:10:19 20:42:10", b"2017:10:19 13:42:10")):
            data = data.replace(a, b)  # every EXIF date of the file: the local clock, UTC-7
        path.write_bytes(data)
        stamp = utc[path.stem[-2]]
        cf.rewrite(path, folder / path.name,
                   lambda x, s=stamp: x.replace('drone-dji:SensorIndex=', f'drone-dji:UTCAtExposure="{s}" drone-dji:SensorIndex='))
    run = _apply(folder, tmp_path / "out", "--no-align")
    run_local = _apply(local, tmp_path / "out_local", "--no-align")
    for frame, when, lat, lon, alt in (("001", "2017-10-19T20:40:39.200173", 36.576096, -119.435269, 101.861),
                                       ("002", "2017-10-19T20:42:10.200159", 36.5760815, -119.4352604, 174.527)):
        el, _ = solar_position(np.array([when], "datetime64[ns]"), np.array([lat]), np.array([lon]), np.array([alt]))
        assert run_value(run, "sun_sensor")[frame]["sun_elevation_deg"] == pytest.approx(math.degrees(float(el[0])), abs=0.01)
        assert run_value(run, "sun_sensor")[frame]["sun_elevation_deg"] > run_value(run_local, "sun_sensor")[frame]["sun_elevation_deg"] + 40
    assert run_value(run, "capture_times") == {"utc": 2, "as_written": 0, "missing": 0, "first": {"utc": "001"}}
    assert run_value(run_local, "capture_times") == {"utc": 0, "as_written": 2, "missing": 0, "first": {"as_written": "001"}}
    codes = [w["code"] for s in report_dict(None, [tmp_path / "out"])["sections"] for w in s["warnings"]]
    assert "mixed_time_zones" not in codes
    # one capture with UTCAtExposure, one without: two clocks in one flight, warned of
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for path in sorted(folder.glob("DJI_001*.TIF")) + sorted(local.glob("DJI_002*.TIF")):
        (mixed / path.name).write_bytes(path.read_bytes())
    run_mixed = _apply(mixed, tmp_path / "out_mixed", "--no-align")
    assert run_value(run_mixed, "capture_times") == {"utc": 1, "as_written": 1, "missing": 0,
                                          "first": {"utc": "001", "as_written": "002"}}
    (warn,) = [w for s in report_dict(None, [tmp_path / "out_mixed"])["sections"] for w in s["warnings"]
               if w["code"] == "mixed_time_zones"]
    assert "1 capture(s) have their time in UTC (e.g. 001) and 1 as written" in warn["message"]
    with (tmp_path / "out" / "photogrammetry" / "002_Green.tif").open("rb") as fh:  # 001: the panel capture
        tags = exifread.process_file(fh, details=False)
    assert str(tags["EXIF DateTimeOriginal"]) == "2017:10:19 20:42:10"
    assert str(tags["EXIF OffsetTimeOriginal"]) == "+00:00"
    assert str(tags["GPS GPSDate"]) == "2017:10:19"
    assert [float(v.num) / v.den for v in tags["GPS GPSTimeStamp"].values] == pytest.approx([20, 42, 10.200159])


def _shift_px(a: np.ndarray, b: np.ndarray) -> float:
    """Displacement (px) between two 192 x 192 tiles by phase correlation (Hanning window)."""
    (dx, dy), _ = cv2.phaseCorrelate(a, b, cv2.createHanningWindow(a.shape[::-1], cv2.CV_64F))
    return float(np.hypot(dx, dy))


def test_dji_bands_registered_by_their_own_metadata(tmp_path) -> None:
    """DJI bands built through known lens distortions and planes (DewarpData, a different
    CalibratedHMatrix per band; tests/camera_files.dji_p4m_warped): the factory path puts them
    back on the scene's grid (the guide's steps 2-3) to < 0.5 px in the centre and the four
    corners of the image; with --no-align they are many pixels off."""
    require_data()
    folder = cf.dji_p4m_warped(tmp_path / "warped")
    run = _apply(folder, tmp_path / "out")
    assert run["frames"] == ["001", "002"] and run_value(run, "band_alignment").startswith("factory metadata: each band's")
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert ds.attrs["co_registered"] == 1 and ds.attrs["registration"] == "factory metadata"
    _apply(folder, tmp_path / "raw", "--no-align")
    raw = xr.open_zarr(tmp_path / "raw" / "reflectance.zarr")
    tiles = [(160, 200), (160, 1080), (800, 200), (800, 1080), (480, 640)]  # (y, x) centres
    worst, worst_raw = 0.0, 0.0
    for f, cap in enumerate(cf.CAPTURES):
        scene = tifffile.imread(cf.band_file(cap, 4)).astype(np.float64)
        for b in range(5):
            for y, x in tiles:
                sl = (slice(y - 96, y + 96), slice(x - 96, x + 96))
                ref = scene[sl] / scene[sl].mean()
                for store, out in ((ds, "aligned"), (raw, "raw")):
                    t = store["radiance"].isel(frame=f, band=b).values[sl].astype(np.float64)
                    assert np.isfinite(t).mean() > 0.99, (cap, b, y, x, out)
                    t = np.where(np.isfinite(t), t, np.nanmedian(t))
                    d = _shift_px(ref, t / t.mean())
                    if out == "aligned":
                        worst = max(worst, d)
                    else:
                        worst_raw = max(worst_raw, d)
    assert worst < 0.5  # measured 0.05 px
    assert worst_raw > 10  # measured 21.6 px: the test sees a misregistration


def test_dji_mavic_3m_black_level_from_xmp() -> None:
    """Mavic 3M writes the black level in drone-dji:BlackLevel, not EXIF."""
    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    tags, _ = _tags(cf.band_file("0000", 4))
    packet = cf.dji_xmp(4, "m3m").replace('drone-dji:SensorGain=', 'drone-dji:BlackLevel="3200" drone-dji:SensorGain=')
    tags[700] = packet.encode()
    del tags[50714]
    meta = meta_from_tags(cf.band_file("0000", 4), tags, (960, 1280), 16)
    assert meta.radiometry == "dji" and meta.black_level == 3200.0 and meta.band_name == "RedEdge"
    assert meta.exposure_s == pytest.approx(472.5e-6) and meta.maker_tag("dewarp")[:4] == (1949.45, 1939.77, 28.0, -17.0)
    assert meta.maker_tag("hmatrix")[2] == 2.5 and meta.features()["factory_band_alignment"]


# --------------------------------------------------------------------------- real: Sequoia, Sentera


def sequoia_expected(path: Path, x: int, y: int) -> float:
    """Parrot SEQ AN 01: I = f^2 (p/V - B) / (A e ISO + C), V = sum c (x/W)^ex (y/H)^ey, at a
    stored pixel (x, y)."""
    tags, xmp = _tags(path)
    exif = tags[34665]
    f = exif["FNumber"][0] / exif["FNumber"][1]
    e = exif["ExposureTime"][0] / exif["ExposureTime"][1]
    iso = exif["ISOSpeedRatings"]
    a, b, c = _floats(xmp, "Camera:SensorModel")
    coef = _floats(xmp, "Camera:VignettingPolynomial2D")
    ex = _floats(xmp, "Camera:VignettingPolynomial2DName")
    v = sum(ci * (x / 1280) ** ex[2 * i] * (y / 960) ** ex[2 * i + 1] for i, ci in enumerate(coef))
    p = float(tifffile.imread(path)[y, x])
    return max(f * f * (p / v - b) / (a * e * iso + c), 0.0)


def test_parrot_sequoia_real_capture(tmp_path) -> None:
    folder = DATA_ROOT / "parrot-sequoia"
    if not folder.is_dir():
        pytest.skip("no Sequoia sample")
    run = _apply(folder, tmp_path / "out")
    assert run["camera"] == "parrot-sequoia" and run["frames"] == ["IMG_180413_080658_0000"]
    assert run_value(run, "orientation").startswith("EXIF Orientation 3") and run_value(run, "reference")["scale"].startswith("fixed per")
    assert run_value(run, "reference")["sun_sensor_scale"]["constant"] == 5e-4  # Parrot's K, fixed for the camera model
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert list(ds["band_name"].values) == ["Green", "Red", "Red edge", "NIR"]
    for b, suffix in enumerate(("GRE", "RED", "REG", "NIR")):
        path = folder / f"IMG_180413_080658_0000_{suffix}.TIF"
        rad = ds["radiance"].isel(frame=0, band=b).values
        for x, y in CORNERS + ((640, 480),):
            # stored rotated 180 degrees: stored (x, y) is upright (W-1-x, H-1-y)
            assert rad[959 - y, 1279 - x] == pytest.approx(sequoia_expected(path, x, y), rel=TOL, abs=1e-6)
        raw = xr.open_zarr(tmp_path / "out" / "raw.zarr")["dn"].isel(frame=0, band=b).values
        np.testing.assert_array_equal(raw, tifffile.imread(path)[::-1, ::-1])
    # vegetation in the morning light: NIR above red in the median
    refl = np.nanmedian(ds["reflectance"].values, axis=(0, 2, 3))
    assert refl[3] > refl[1] and np.isfinite(ds["ndvi"].values).mean() > 0.9
    # Parrot's R = K I / E with K fixed at 5e-4 for the camera model (was: a run constant that
    # put the first capture's brightest median at 0.5): the band medians of this capture
    np.testing.assert_allclose(refl, [0.17848, 0.14583, 0.30822, 0.40934], rtol=1e-4)


def test_sequoia_on_an_sd_card_tree(tmp_path) -> None:
    """A Sequoia capture two folders down (as on the card) is recognised from the files below
    the folder and goes through the one executor as in its own folder: the same outputs."""
    folder = DATA_ROOT / "parrot-sequoia"
    if not folder.is_dir():
        pytest.skip("no Sequoia sample")
    card = tmp_path / "card" / "DCIM" / "0001"
    card.mkdir(parents=True)
    for p in folder.glob("*.TIF"):
        (card / p.name).write_bytes(p.read_bytes())
    run = _apply(tmp_path / "card", tmp_path / "out")
    ref = _apply(folder, tmp_path / "ref")
    assert run["camera"] == "parrot-sequoia" and run["frames"] == ref["frames"] and run["quarantined"] == []
    assert run_value(run, "orientation") == run_value(ref, "orientation") and run_value(run, "reference") == run_value(ref, "reference")
    a = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")["reflectance"].values
    b = xr.open_zarr(tmp_path / "ref" / "reflectance.zarr")["reflectance"].values
    np.testing.assert_array_equal(a, b)


def _without_sun_sensor(kind: str, folder: Path) -> Path:
    """A folder whose captures have no usable sun-sensor reflectance in any band."""
    if kind == "sequoia":  # older firmware: no Camera:IrradianceSensitivitiesGolden
        if not cf.SEQUOIA.is_dir():
            pytest.skip("no Sequoia sample")
        return cf.sequoia_without_golden(folder)
    if kind == "sentera":  # ILS counts: no published conversion
        if not (DATA_ROOT / "sentera-d4k" / "NDRE").is_dir():
            pytest.skip("no Sentera sample")
        return DATA_ROOT / "sentera-d4k" / "NDRE"
    require_data()  # MicaSense without its DLS tags
    folder.mkdir(parents=True)
    for cap in cf.CAPTURES:
        for b in range(1, 6):
            cf.rewrite(cf.band_file(cap, b), folder / f"IMG_{cap}_{b}.tif",
                       lambda x: cf.drop_element(cf.drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance"))
    return folder


@pytest.mark.parametrize(("kind", "file", "why"), [
    ("sequoia", "IMG_180413_080658_0000_GRE.TIF", "XMP IrradianceSensitivitiesGolden = '(missing)': not in the file"),
    ("micasense", "IMG_0000_1.tif",
     "no sun-sensor reading: no XMP Camera:Irradiance (DLS 1) or DLS:HorizontalIrradiance (DLS 2) in the file"),
    ("sentera", "IMG_00006.jpg", "Sentera's sun sensor (ILS) counts have no published conversion to reflectance"),
])
def test_reference_dls_without_any_sun_sensor_reading_exits_2(tmp_path, capsys, monkeypatch, kind, file, why) -> None:
    """--reference dls asks for the sun sensor: when no band of any capture has a usable
    reading it is refused before anything is written (one line naming a band file, the tag
    and the fixes), and an earlier run's outputs in OUT stay as they were. (The MicaSense
    panel's serial, read from its QR code, is kept out of the catalog here: auto would take
    the panel otherwise.)"""
    folder = _without_sun_sensor(kind, tmp_path / kind)
    (tmp_path / "catalog" / "targets").mkdir(parents=True)
    (tmp_path / "catalog" / "targets" / "micasense-rp02-1603036-sc.yaml").write_text(
        "name: micasense-rp02-1603036-sc\ndescription: without its serial\nreflectance: 0.5\n")
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path / "catalog"))
    dls = ["apply", str(folder), "--calibration", "factory", "--reference", "dls", "-o"]
    capsys.readouterr()
    assert main([*dls, str(tmp_path / "new")]) == 2
    err = capsys.readouterr().err.strip()
    n = 1 if kind == "sequoia" else 2
    assert len(err.splitlines()) == 1 and err.startswith(
        f"mscal: error: {folder / file}: --reference dls, but no band of the {n} capture(s) has a usable sun-sensor "
        f"reading; here: {why}"), err
    assert err.endswith("(give --panel-reflectance TARGET (a number, or a target of catalogs/targets) with a panel "
                        "capture in the folder (--panel IMG_XXXX names it); or leave out --reference dls for radiance "
                        "only (reflectance NaN))"), err
    assert not (tmp_path / "new").exists()
    if kind == "sentera":
        return  # its radiance-only run: test_sentera_d4k_real_captures
    out = tmp_path / "out"
    run = _apply(folder, out)  # auto: radiance only, and why
    assert run_value(run, "reference")["route"] == "none" and run_value(run, "reference")["reason"].startswith(f"{file}: {why}")
    assert run_value(run, "reflectance_missing") == []  # a band is named there only on the sun-sensor route
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert main([*dls, str(out)]) == 2
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert np.isnan(ds["reflectance"].values).all() and np.isnan(ds["ndvi"].values).all()
    if kind == "sequoia":  # the radiance is the factory model's, tag or no tag (stored rotated 180 degrees)
        rad = ds["radiance"].isel(frame=0, band=3).values
        assert rad[959 - 480, 1279 - 640] == pytest.approx(
            sequoia_expected(folder / "IMG_180413_080658_0000_NIR.TIF", 640, 480), rel=TOL)


def test_sentera_d4k_real_captures(tmp_path) -> None:
    root = DATA_ROOT / "sentera-d4k"
    if not root.is_dir():
        pytest.skip("no Sentera sample")
    for sensor, camera, rows in (("NDRE", "sentera-d4k-ndre", (0, 2)), ("nRGB", "sentera-d4k-nrgb", (0, 1, 2))):
        run = _apply(root / sensor, tmp_path / sensor)
        assert run["camera"] == camera and run["frames"] == ["IMG_00006", "IMG_00007"] and run["quarantined"] == []
        assert run_value(run, "reference")["route"] == "none"  # ILS counts: no published conversion, needs a panel
        ds = xr.open_zarr(tmp_path / sensor / "reflectance.zarr")
        for f, name in enumerate(run["frames"]):
            path = root / sensor / f"{name}.jpg"
            data = path.read_bytes()
            img = cv2.cvtColor(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
            i = data.index(b"<Camera:ColorTransform>")
            m = _floats(data[i: data.index(b"</Camera:ColorTransform>") + 24].decode(), "Camera:ColorTransform")
            import exifread

            ex = exifread.process_file(open(path, "rb"), details=False)
            iso = float(ex["EXIF ISOSpeedRatings"].values[0])
            t = float(ex["EXIF ExposureTime"].values[0].num) / ex["EXIF ExposureTime"].values[0].den
            checked = 0
            for b, row in enumerate(rows):
                rad = ds["radiance"].isel(frame=f, band=b).values
                for x, y in ((0, 0), (3999, 0), (0, 2999), (3999, 2999), (2000, 1500)):
                    mixed = sum(m[3 * row + j] * float(img[y, x, j]) for j in range(3))
                    if any(img[y, x, j] == 255 for j in range(3) if m[3 * row + j] != 0):
                        assert np.isnan(rad[y, x])  # a clipped channel in the mix
                        continue
                    assert rad[y, x] == pytest.approx(max(mixed, 0) / (iso / 100 * t), rel=TOL, abs=1e-3)
                    checked += 1
            assert checked >= 2 * len(rows)
        assert np.isnan(ds["reflectance"].values).all()


def test_sentera_panel_route(tmp_path) -> None:
    """A Sentera capture with a gray panel (painted into the real NDRE JPEG): reflectance from
    the panel through the colour transform; the panel reads its own reflectance back."""
    root = DATA_ROOT / "sentera-d4k" / "NDRE"
    if not root.is_dir():
        pytest.skip("no Sentera sample")
    folder = cf.sentera_with_panel(root, tmp_path / "ndre")
    run = _apply(folder, tmp_path / "out", "--panel-reflectance", "0.5", "--panel", "IMG_00006")
    # ILS counts: no reflectance alone, but they carry the light's change from the panel
    assert run["camera"] == "sentera-d4k-ndre" and run_value(run, "reference")["route"] == "panel-dls"
    assert run_value(run, "reference")["panels"][0]["region_source"] == ["detected", "detected"]
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    refl = ds["reflectance"].isel(frame=0).values[:, 1300:1600, 1800:2100]
    # RedEdge = 2.7 R - 2.581 B is 0.12 x 200 on the gray panel: JPEG's +-1 DN in R and B is
    # +-20 % per pixel there, so its median is held to 3 %, NIR (5.6 x 200) to 1 %
    med = np.nanmedian(refl, axis=(1, 2))
    assert med[0] == pytest.approx(0.5, rel=0.03) and med[1] == pytest.approx(0.5, rel=0.01)
    assert np.isfinite(ds["reflectance"].isel(frame=1).values).mean() > 0.9


def test_sentera_6x_session_built_from_d4k_files(tmp_path, capsys) -> None:
    """Sentera 6X (built: tests/camera_files.sentera_6x): one folder per band in a session
    folder, EXIF tags in IFD0, the capture id from ImageUniqueID. Recognised by ``mscal
    cameras``; ``apply --calibration factory``: radiance DN / (ISO/100 x exposure) pixel by
    pixel, no sun-sensor reflectance (route none), and a panel that reads 0.5 back."""
    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    session = cf.sentera_6x(tmp_path / "flight", panel=True)
    assert main(["cameras", str(tmp_path / "flight")]) == 0
    out = capsys.readouterr().out
    assert f"{session}:" in out and "camera: sentera-6x" in out and "captures: 2 complete, 0 quarantined" in out
    assert "bands: Blue 475 nm, Green 550 nm, Red 670 nm, RedEdge 715 nm, NIR 840 nm" in out
    assert "blue_475:" not in out  # the band folders are part of the session, not folders of their own
    run = _apply(tmp_path / "flight", tmp_path / "radiance")
    assert run["camera"] == "sentera-6x" and run["frames"] == ["IMG_00006", "IMG_00007"] and run["quarantined"] == []
    assert run_value(run, "reference")["route"] == "none"
    ds = xr.open_zarr(tmp_path / "radiance" / "reflectance.zarr")
    assert list(ds["band_name"].values) == ["Blue", "Green", "Red", "RedEdge", "NIR"]
    checked = 0
    for f, cap in enumerate(("IMG_00006", "IMG_00007")):
        for b, band in enumerate(ds["band_name"].values):
            path = session / cf.SENTERA_6X_BANDS[str(band)][0] / f"{cap}.tif"
            p = cf.PARAMS[str(path)]
            dn = tifffile.imread(path).astype(np.float64)
            rad = ds["radiance"].isel(frame=f, band=b).values
            for x, y in ((0, 0), (1903, 0), (0, 1427), (1903, 1427), (952, 714), (3, 5)):
                expected = dn[y, x] / (p["iso"] / 100 * p["exposure"][0] / p["exposure"][1])
                assert rad[y, x] == pytest.approx(expected, rel=TOL, abs=1e-6)
                checked += 1
    assert checked == 60
    (tmp_path / "flight" / "session.yaml").write_text("panel:\n  polygon: [[720, 520], [1080, 520], [1080, 780], [720, 780]]\n")
    run = _apply(tmp_path / "flight", tmp_path / "panel", "--panel-reflectance", "0.5", "--panel", "IMG_00006")
    # the built files carry ILS readings: the panel anchors them (panel + sun sensor, the default)
    assert run_value(run, "reference")["route"] == "panel-dls" and run["frames"] == ["IMG_00006", "IMG_00007"]
    refl = xr.open_zarr(tmp_path / "panel" / "reflectance.zarr")["reflectance"].isel(frame=0).values
    np.testing.assert_allclose(np.nanmedian(refl[:, 550:750, 750:1050], axis=(1, 2)), 0.5, rtol=0.03)


def test_altum_thermal_in_kelvin_in_its_own_files(tmp_path) -> None:
    """Altum (built): the LWIR band (centi-kelvin DN) is written as temperature in kelvin with
    the camera's own conversion, K = DN / 100, to thermal/<capture>_LWIR.tif on its own 160 x
    120 grid, and named in run.json; reflectance keeps the five reflectance bands only."""
    require_data()
    folder = cf.altum(tmp_path / "altum")
    grad = (27315 + 1000 + np.arange(120)[:, None] * 10 + np.arange(160)[None, :]).astype(np.uint16)  # 283.15 K +
    cf.extra_band(folder / "IMG_0001_6.tif", (120, 160), "LWIR", 11000, "0001", "Altum", grad)
    run = _apply(folder, tmp_path / "out", "--reference", "dls")
    assert run["camera"] == "micasense-altum" and run["frames"] == ["IMG_0000", "IMG_0001"]
    assert [s["band"] for s in run_value(run, "skipped_bands")] == ["LWIR", "LWIR"]
    assert run_value(run, "thermal")["unit"] == "K" and run["outputs"]["thermal"] == "thermal/"
    assert [(t["capture"], t["written"]) for t in run_value(run, "thermal")["files"]] == [
        ("IMG_0000", "thermal/IMG_0000_LWIR.tif"), ("IMG_0001", "thermal/IMG_0001_LWIR.tif")]
    k0 = tifffile.imread(tmp_path / "out" / "thermal" / "IMG_0000_LWIR.tif")
    assert k0.dtype == np.float32 and k0.shape == (120, 160)
    np.testing.assert_allclose(k0, 298.15, rtol=1e-7)  # the builder's 29815 centi-kelvin
    k1 = tifffile.imread(tmp_path / "out" / "thermal" / "IMG_0001_LWIR.tif")
    np.testing.assert_allclose(k1, grad / 100.0, rtol=1e-7)
    assert k1[0, 0] == pytest.approx(283.15) and k1[119, 159] == pytest.approx(283.15 + 11.9 + 1.59)
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert ds.sizes["band"] == 5 and 11000 not in list(ds["wavelength"].values)
    assert float(np.nanmax(ds["reflectance"].values)) < 5  # no kelvin in reflectance
