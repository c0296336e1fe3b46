"""A written position that is no position: MicaSense's real RedEdge captures with the panel
capture's GPS rewritten to latitude 0, longitude 0 (taken on the ground before the fix), to
GPSStatus V, or a capture 10 km off the flight 2 s after the one before it. Such a capture has
no position in reflectance.zarr, the track plot, the STAC footprint or its TIFF's GPS tags,
and run.json's ``metadata_problems`` names its file."""

from __future__ import annotations

import json
import math
from pathlib import Path

import exifread
import numpy as np
import pytest
import xarray as xr

from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.gps import distance_m
from pipeline.products import report
from pipeline.products.stac import update_catalog
from pipeline.run.cli import main
from tests.gps_files import copy_capture, copy_sample, set_gps
from tests.micasense_data import require_data

# IMG_0001's position as its files carry it (36 deg 34' 33.8934" N, 119 deg 26' 6.93744" W)
LAT_0001 = 36 + 34 / 60 + 33.8934 / 3600
LON_0001 = -(119 + 26 / 60 + 6.93744 / 3600)


def _apply(folder: Path, out: Path) -> dict:
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--reference", "dls"]) == 0
    return json.loads((out / "run.json").read_text())


def _gps_tags(path: Path) -> dict[str, str]:
    with path.open("rb") as fh:
        return {k: str(v) for k, v in exifread.process_file(fh, details=False).items() if k.startswith("GPS")}


def _stac_bbox(out: Path) -> list[float]:
    update_catalog(out.parent)
    (item,) = [json.loads(p.read_text()) for p in (out.parent / "stac").rglob("*.json")
               if json.loads(p.read_text()).get("type") == "Feature"]
    return item["bbox"]


@pytest.fixture(scope="module")
def no_fix_run(tmp_path_factory) -> Path:
    require_data()
    folder = copy_sample(tmp_path_factory.mktemp("nofix") / "card")
    for b in range(1, 6):
        set_gps(folder / f"IMG_0000_{b}.tif", 0.0, 0.0, 0.0)
    out = tmp_path_factory.mktemp("nofix-out") / "flight"
    _apply(folder, out)
    return out


def test_gps_zero_zero_is_no_position(no_fix_run: Path) -> None:
    out = no_fix_run
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert list(ds["frame"].values) == ["IMG_0000", "IMG_0001"]
    assert math.isnan(float(ds["lat"][0])) and math.isnan(float(ds["lon"][0])) and math.isnan(float(ds["alt_m"][0]))
    assert float(ds["lat"][1]) == pytest.approx(LAT_0001, abs=1e-9)
    assert float(ds["lon"][1]) == pytest.approx(LON_0001, abs=1e-9)
    run = json.loads((out / "run.json").read_text())
    zero = [p for p in run["metadata_problems"] if p["feature"] == "position"]
    assert sorted(Path(p["file"]).name for p in zero) == [f"IMG_0000_{b}.tif" for b in range(1, 6)]
    assert {(p["tag"], p["value"]) for p in zero} == {("EXIF GPSLatitude/GPSLongitude", "0, 0")}
    assert "before the GPS had a fix" in zero[0]["reason"]
    # the panel capture's TIFFs carry no GPS at all; the flight capture's carry its own position
    panel_tifs = sorted((out / "panels").glob("IMG_0000_*.tif"))
    assert len(panel_tifs) == 5 and all(_gps_tags(p) == {} for p in panel_tifs)
    gps = _gps_tags(out / "photogrammetry" / "IMG_0001_Blue.tif")
    assert gps["GPS GPSLatitudeRef"] == "N" and gps["GPS GPSLongitudeRef"] == "W"
    assert gps["GPS GPSLatitude"] == "[36, 34, 169467/5000]"  # 33.8934"
    # track plot: the one positioned capture, not (0, 0)
    fig = report.plot_track(report.open_flight(out))
    offsets = fig.axes[0].collections[0].get_offsets()
    np.testing.assert_allclose(np.asarray(offsets), [[LON_0001, LAT_0001]], atol=1e-9)
    assert fig.axes[0].get_title() == "Track: 1 of 2 frames with GPS"
    # STAC: the footprint is the flight capture's point
    np.testing.assert_allclose(_stac_bbox(out), [LON_0001, LAT_0001, LON_0001, LAT_0001], atol=1e-9)


def test_gps_status_void_is_no_position(tmp_path: Path) -> None:
    require_data()
    folder = copy_sample(tmp_path / "card")
    path = set_gps(folder / "IMG_0001_2.tif", 36.5, -119.4, 120.0, status="V")
    meta = read_capture_meta(path)
    assert meta.lat is None and meta.lon is None and meta.alt_m is None
    (problem,) = [p for p in meta.problems if p.feature == "position"]
    assert (problem.tag, problem.value) == ("EXIF GPSStatus", "V")
    ok = read_capture_meta(set_gps(folder / "IMG_0001_3.tif", 36.5, -119.4, 120.0, status="A"))
    assert ok.lat == pytest.approx(36.5, abs=1e-9) and ok.lon == pytest.approx(-119.4, abs=1e-9)


def test_unreachable_position_is_no_position(tmp_path: Path) -> None:
    """IMG_0002: IMG_0001's files 2 s later and 10 km north. IMG_0000 and IMG_0001 are 91 s and
    a few metres apart; 10 km in 2 s is 5000 m/s: IMG_0002 has no position."""
    require_data()
    folder = copy_sample(tmp_path / "card")
    lat_far = LAT_0001 + 10_000 / (math.pi / 180 * 6_371_008.8)  # 10 km north
    assert distance_m(LAT_0001, LON_0001, lat_far, LON_0001) == pytest.approx(10_000, abs=0.01)
    copy_capture(folder, "0001", "0002", seconds_later=2, lat=lat_far, lon=LON_0001, alt_m=174.527)
    out = tmp_path / "out" / "flight"
    run = _apply(folder, out)
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert list(ds["frame"].values) == ["IMG_0000", "IMG_0001", "IMG_0002"]
    lat = ds["lat"].values
    assert np.isfinite(lat[:2]).all() and math.isnan(lat[2])
    assert float(ds["lat"][1]) == pytest.approx(LAT_0001, abs=1e-9)
    (problem,) = [p for p in run["metadata_problems"] if p["feature"] == "position"]
    assert Path(problem["file"]).name == "IMG_0002_1.tif"
    assert "10.00 km from the flight's median position and 5000 m/s from IMG_0001 (2.0 s apart)" in problem["reason"]
    assert _gps_tags(sorted((out / "photogrammetry").glob("IMG_0002*.tif"))[0]) == {}
    assert _gps_tags(sorted((out / "photogrammetry").glob("IMG_0001*.tif"))[0])["GPS GPSLatitudeRef"] == "N"


def test_snapshot_frames_without_a_fix_and_out_of_reach(small, tmp_path: Path) -> None:
    """The small session's 3-frame flight (2 s and 2 m apart) with IMG_0000 at 0/0 in
    frames.csv, IMG_0002 moved 10 km north and a fourth frame IMG_0003 (IMG_0001's pixels but
    one, 2 s after IMG_0002, at IMG_0001's position): IMG_0000 has no fix; IMG_0002 is 5000 m/s
    from its neighbours and 10 km from the median of the three positioned frames."""
    import shutil

    import tifffile

    session, calib = small
    flight = tmp_path / "field"
    shutil.copytree(session / "flights" / "field", flight)
    rows = (flight / "frames.csv").read_text().splitlines()
    head, r0, r1, r2 = rows
    f0 = r0.split(",")
    f0[4:6] = ["0", "0"]
    f2 = r2.split(",")
    lat2 = float(f2[4])
    f2[4] = f"{lat2 + 10_000 / (math.pi / 180 * 6_371_008.8):.8f}"
    img = tifffile.imread(flight / "IMG_0001.tif")
    img[0, 0] ^= 1  # not a duplicate of IMG_0001
    tifffile.imwrite(flight / "IMG_0003.tif", img)
    f3 = r1.split(",")
    f3[0], f3[3] = "IMG_0003.tif", "2017-06-14T09:50:06.000Z"
    (flight / "frames.csv").write_text("\n".join([head, ",".join(f0), r1, ",".join(f2), ",".join(f3)]) + "\n")
    out = tmp_path / "out"
    assert main(["apply", str(flight), "--calibration", str(calib), "-o", str(out)]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == ["IMG_0000", "IMG_0001", "IMG_0002", "IMG_0003"]
    problems = {p["file"]: p for p in run["metadata_problems"]}
    assert sorted(problems) == ["IMG_0000.tif", "IMG_0002.tif"]
    assert problems["IMG_0000.tif"]["value"] == "0, 0" and problems["IMG_0000.tif"]["feature"] == "position"
    assert problems["IMG_0002.tif"]["reason"].startswith("10.00 km from the flight's median position and 5001 m/s "
                                                         "from IMG_0001.tif (2.0 s apart)")
    ds = xr.open_zarr(out / "reflectance.zarr")
    lat = ds["lat"].values
    assert np.isnan(lat[0]) and np.isnan(lat[2]) and lat[1] == pytest.approx(47.45020045, abs=1e-9)
    assert _gps_tags(next((out / "photogrammetry").glob("IMG_0000_*.tif"))) == {}
    assert _gps_tags(next((out / "photogrammetry").glob("IMG_0002_*.tif"))) == {}
    assert _gps_tags(next((out / "photogrammetry").glob("IMG_0001_*.tif")))["GPS GPSLatitudeRef"] == "N"
