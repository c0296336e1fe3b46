"""The STAC catalog of an output root: layout, items, incremental updates, offline
validation. Flight folders are laid out as mscal apply / mscal run write them (run.json,
reflectance.zarr with its frame coordinates; the reflectance itself is not read)."""

from __future__ import annotations

import json
import os
import socket
import warnings
from datetime import date
from pathlib import Path

import numpy as np
import pytest

from mscal_core.errors import InputError
from pipeline.products.stac import find_flights, update_catalog, validate_catalog
from pipeline.run.cli import main
from pipeline.sim.synth import write_orthomosaic

UTM = "EPSG:32633"


def _flight(out: Path, *, lat0: float, lon0: float, day: str, n: int = 4, seed: int = 0, gps: bool = True,
            times: bool = True) -> Path:
    """A flight folder: reflectance.zarr with the frame coordinates of mscal apply, run.json."""
    import xarray as xr

    rng = np.random.default_rng(seed)
    lat = lat0 + rng.uniform(0, 0.001, n) if gps else np.full(n, np.nan)
    lon = lon0 + rng.uniform(0, 0.001, n) if gps else np.full(n, np.nan)
    t = (np.datetime64(f"{day}T10:00:00") + np.arange(n) * np.timedelta64(30, "s")) if times else \
        np.full(n, np.datetime64("NaT"), "datetime64[ns]")
    ds = xr.Dataset({"ndvi": (("frame", "y", "x"), np.zeros((n, 2, 2), np.float32))},
                    coords={"frame": [f"IMG_{i:04d}" for i in range(n)], "lat": ("frame", lat), "lon": ("frame", lon),
                            "alt_m": ("frame", np.full(n, 40.0)), "time": ("frame", t.astype("datetime64[ns]"))},
                    attrs={"camera": "ximea-mq022hg-sm5x5-nir", "calibration_sha256": "ab" * 32})
    out.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():  # zarr: fixed-width strings have no v3 spec yet (test data only)
        warnings.simplefilter("ignore")
        ds.to_zarr(out / "reflectance.zarr", mode="w", consolidated=False)
    (out / "photogrammetry").mkdir(exist_ok=True)
    (out / "ndvi").mkdir(exist_ok=True)
    run = {"calibration": "/cache/illumination-1.zarr", "calibration_sha256": "ab" * 32, "frames_in": n,
           "frames_out": n, "quarantined": [], "versions": {"mscal": "0.1.0"}}
    (out / "run.json").write_text(json.dumps(run))
    return out


def _session(out: Path, flights: dict[str, dict]) -> Path:
    for name, kw in flights.items():
        _flight(out / "flights" / name, **kw)
    (out / "calibration.zarr").mkdir(parents=True, exist_ok=True)
    (out / "report.html").write_text("<html></html>")
    (out / "run.json").write_text(json.dumps({"session": "s", "calibration_cached": True,
                                              "calibration_stages": {"response": {"key": "k1"}}}))
    return out


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    r = tmp_path / "out"
    (r / "farm-a").mkdir(parents=True)
    (r / "farm-a" / "mscal-project.yaml").write_text("id: farm-north\ntitle: North farm\nlicense: CC-BY-4.0\n")
    _session(r / "farm-a" / "2026-06-01", {"field": dict(lat0=45.1, lon0=15.0, day="2026-06-01")})
    s2 = _session(r / "farm-a" / "2026-06-08", {"field": dict(lat0=45.1, lon0=15.0, day="2026-06-08", seed=1)})
    # an orthomosaic and its NDVI map beside the second flight (what ODM + mscal index give)
    t = (0.5, 0.0, 500000.0, 0.0, -0.5, 5000100.0)
    ortho = write_orthomosaic(s2 / "flights" / "field" / "odm_orthophoto" / "odm_orthophoto.tif",
                              np.full((200, 160), 0.4), crs=UTM, transform=t)
    from pipeline.products.indexmap import index_map

    index_map(ortho, "ndvi", s2 / "flights" / "field" / "ndvi_map.tif")
    # another farm, no project file: a plain mscal apply OUT without GPS nor times
    _flight(r / "farm-b" / "2026-06-02" / "plot7", lat0=0, lon0=0, day="2026-06-02", gps=False, times=False)
    return r


def _no_network(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*a, **k):
        raise OSError("network disabled by the test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    import pystac

    monkeypatch.setattr(pystac.StacIO, "read_text", lambda self, *a, **k: refuse())


def test_catalog_layout_items_and_offline_validation(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _no_network(monkeypatch)
    assert len(find_flights(root)) == 3
    s = update_catalog(root, project_level=1)
    assert s["collections"] == ["farm-b", "farm-north"] and s["items"] == 3 and len(s["added"]) == 3
    cat = json.loads((root / "catalog.json").read_text())
    assert cat["type"] == "Catalog" and cat["mscal:project_level"] == 1
    assert all(not link["href"].startswith("/") for link in cat["links"])  # relative links only
    coll = json.loads((root / "stac" / "farm-north" / "collection.json").read_text())
    assert coll["title"] == "North farm" and coll["license"] == "CC-BY-4.0"
    items = root / "stac" / "farm-north" / "items"
    assert sorted(p.name for p in items.iterdir()) == ["2026-06-01__field.json", "2026-06-08__field.json"]
    it = json.loads((items / "2026-06-01__field.json").read_text())
    # footprint from the frames' GPS: the hull of the positions, time range of the frames
    import xarray as xr

    ds = xr.open_zarr(root / "farm-a" / "2026-06-01" / "flights" / "field" / "reflectance.zarr", consolidated=False)
    np.testing.assert_allclose(it["bbox"], [ds.lon.min(), ds.lat.min(), ds.lon.max(), ds.lat.max()], atol=1e-12)
    assert it["properties"]["start_datetime"] == "2026-06-01T10:00:00Z"
    assert it["properties"]["end_datetime"] == "2026-06-01T10:01:30Z"
    assert it["properties"]["mscal:footprint_source"] == "frame_gps"
    assert it["properties"]["instruments"] == ["ximea-mq022hg-sm5x5-nir"]
    assert it["properties"]["mscal:calibration_sha256"] == "ab" * 32
    assert it["properties"]["mscal:calibration_cached"] is True
    # every asset resolves to what it names
    for key in ("reflectance", "run", "photogrammetry", "ndvi_frames", "report", "calibration"):
        assert (items / it["assets"][key]["href"]).resolve().exists(), key
    assert (items / it["assets"]["report"]["href"]).resolve() == root / "farm-a" / "2026-06-01" / "report.html"
    # the flight with an orthomosaic: footprint from it, NDVI map as an index asset
    it2 = json.loads((items / "2026-06-08__field.json").read_text())
    assert it2["properties"]["mscal:footprint_source"] == "orthomosaic"
    from rasterio.warp import transform_bounds

    np.testing.assert_allclose(it2["bbox"], transform_bounds(UTM, "EPSG:4326", 500000, 5000000, 500080, 5000100),
                               atol=2e-6)
    assert it2["assets"]["index_ndvi"]["mscal:index"] == "ndvi"
    assert it2["assets"]["orthomosaic"]["mscal:kind"] == "orthomosaic"
    # no GPS, no frame times: no geometry, processing time, said so
    it3 = json.loads((root / "stac" / "farm-b" / "items" / "2026-06-02__plot7.json").read_text())
    assert it3["geometry"] is None and it3["properties"]["mscal:time_source"] == "processing"
    assert validate_catalog(root) == 1 + 2 + 3


def test_incremental_update(root: Path) -> None:
    update_catalog(root, project_level=1)
    item = root / "stac" / "farm-north" / "items" / "2026-06-01__field.json"
    before = item.stat().st_mtime_ns
    s = update_catalog(root)  # the project level is kept from the catalog
    assert (s["unchanged"], s["added"], s["updated"], s["removed"]) == (3, [], [], [])
    assert s["project_level"] == 1 and item.read_text() and item.stat().st_mtime_ns >= before
    run = root / "farm-a" / "2026-06-01" / "flights" / "field" / "run.json"
    run.write_text(run.read_text().replace('"frames_out": 4', '"frames_out": 3'))
    s = update_catalog(root)
    assert s["updated"] == ["farm-north/2026-06-01__field"] and s["unchanged"] == 2
    assert json.loads(item.read_text())["properties"]["mscal:frames_out"] == 3
    import shutil

    shutil.rmtree(root / "farm-b")
    s = update_catalog(root)
    assert sorted(s["removed"]) == ["farm-b/2026-06-02__plot7", "farm-b/collection"]
    assert not (root / "stac" / "farm-b").exists()
    assert validate_catalog(root / "catalog.json") == 1 + 1 + 2


def _signed_area(ring: list[list[float]]) -> float:
    x, y = np.asarray(ring, float).T
    return 0.5 * float(np.sum(x[:-1] * y[1:] - x[1:] * y[:-1]))


def test_second_update_rewrites_nothing_and_extents_hold_every_item(root: Path) -> None:
    """Nothing changed: no file is rewritten. A collection's temporal extent covers items with a
    single datetime too (farm-b's only flight has one instant, its processing time)."""
    update_catalog(root, project_level=1)
    files = sorted((root / "stac").rglob("*.json")) + [root / "catalog.json"]
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in files}
    update_catalog(root)
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in files} == before
    coll = json.loads((root / "stac" / "farm-b" / "collection.json").read_text())
    item = json.loads((root / "stac" / "farm-b" / "items" / "2026-06-02__plot7.json").read_text())
    when = item["properties"]["datetime"]
    assert when is not None and coll["extent"]["temporal"]["interval"] == [[when, when]]
    north = json.loads((root / "stac" / "farm-north" / "collection.json").read_text())
    assert north["extent"]["temporal"]["interval"] == [["2026-06-01T10:00:00Z", "2026-06-08T10:01:30Z"]]


def test_footprints_counterclockwise_and_no_host_paths(root: Path) -> None:
    """RFC 7946: outer rings counterclockwise. Properties hold no host paths: the calibration
    cache outside the root is left out (its sha256 names it), the session folder is relative."""
    update_catalog(root, project_level=1)
    items = sorted((root / "stac").rglob("items/*.json"))
    rings = 0
    for p in items:
        d = json.loads(p.read_text())
        g = d["geometry"]
        polys = [] if g is None else [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
        for poly in polys:
            assert _signed_area(poly[0]) > 0, p.name  # exterior counterclockwise
            rings += 1
        for k, v in d["properties"].items():
            assert not (isinstance(v, str) and (v.startswith("/") or "://" in v)), (p.name, k, v)
    assert rings == 2
    it = json.loads((root / "stac" / "farm-north" / "items" / "2026-06-01__field.json").read_text())
    assert "mscal:calibration" not in it["properties"]  # /cache/... lies outside the catalog
    # a session recorded by its absolute path under the root: relative to the item file
    srun = root / "farm-a" / "2026-06-01" / "run.json"
    srun.write_text(json.dumps({**json.loads(srun.read_text()), "session": str(root / "farm-a" / "in")}))
    run = root / "farm-a" / "2026-06-01" / "flights" / "field" / "run.json"
    run.write_text(json.dumps({**json.loads(run.read_text()),
                               "calibration": str(root / "farm-a" / "2026-06-01" / "calibration.zarr")}))
    update_catalog(root)
    it = json.loads((root / "stac" / "farm-north" / "items" / "2026-06-01__field.json").read_text())
    items_dir = root / "stac" / "farm-north" / "items"
    assert (items_dir / it["properties"]["mscal:session"]).resolve() == root / "farm-a" / "in"
    assert (items_dir / it["properties"]["mscal:calibration"]).resolve() == \
        root / "farm-a" / "2026-06-01" / "calibration.zarr"


def test_broken_item_fails_validation_offline(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    update_catalog(root, project_level=1)
    _no_network(monkeypatch)
    item = root / "stac" / "farm-north" / "items" / "2026-06-01__field.json"
    d = json.loads(item.read_text())
    d["properties"]["start_datetime"] = "the first of June"
    item.write_text(json.dumps(d))
    with pytest.raises(InputError, match="not valid STAC") as e:
        validate_catalog(root)
    assert "2026-06-01__field.json" in str(e.value)
    d["properties"]["start_datetime"] = "2026-06-01T10:00:00Z"
    del d["geometry"]
    item.write_text(json.dumps(d))
    with pytest.raises(InputError, match="not valid STAC"):
        validate_catalog(root)
    # an extension whose schema is not shipped: an error, not a download
    d["geometry"] = None
    del d["bbox"]
    d["stac_extensions"] = ["https://stac-extensions.github.io/eo/v2.0.0/schema.json"]
    item.write_text(json.dumps(d))
    with pytest.raises(InputError, match="cannot be validated offline"):
        validate_catalog(root)


def test_bad_project_file_and_cli(root: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["catalog", str(root), "--project-level", "1"]) == 0
    assert "3 item(s) in 2 collection(s): 3 added" in capsys.readouterr().out
    assert main(["catalog", str(root), "--validate-only"]) == 0
    assert "6 STAC object(s) valid" in capsys.readouterr().out
    (root / "farm-a" / "mscal-project.yaml").write_text("id: farm-north\nowner: me\n")
    assert main(["catalog", str(root)]) == 2
    err = capsys.readouterr().err
    assert "mscal-project.yaml" in err and "unknown key(s) owner" in err
    assert main(["catalog", str(tmp_path / "nowhere")]) == 2


def test_stats_over_the_catalog(root: Path, tmp_path: Path) -> None:
    from pipeline.products.zonal import mosaics_from_catalog, read_fields, zonal_table

    update_catalog(root, project_level=1)
    ms = mosaics_from_catalog(root, "ndvi")
    assert len(ms) == 1 and ms[0].path.endswith("ndvi_map.tif")  # the index map is preferred
    assert (ms[0].flight, ms[0].collection, ms[0].date) == ("2026-06-08__field", "farm-north", date(2026, 6, 8))
    ring = [[500010.1, 5000010.1], [500030.1, 5000010.1], [500030.1, 5000030.1], [500010.1, 5000030.1],
            [500010.1, 5000010.1]]
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"id": "p1"}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}
    (tmp_path / "f.geojson").write_text(json.dumps(doc))
    df = zonal_table(read_fields(tmp_path / "f.geojson", crs=UTM), ms, "ndvi", workers=1)
    row = df.iloc[0]
    assert row["status"] == "ok" and row["n_valid"] == 40 * 40
    assert row["median"] == pytest.approx(0.4, abs=1e-6) and row["std"] == pytest.approx(0.0, abs=1e-6)
    assert os.path.basename(row["source"]) == "ndvi_map.tif"


def test_stats_dates_mosaics_by_their_own_tags_first(root: Path) -> None:
    """The documented date rule: TIFFTAG_DATETIME, then a date in the path, then the item's
    frame time; an item dated only by its processing time gives no date."""
    import rasterio

    from pipeline.products.zonal import mosaics_from_catalog

    flight = root / "farm-a" / "2026-06-08" / "flights" / "field"
    with rasterio.open(flight / "ndvi_map.tif", "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
        dst.update_tags(TIFFTAG_DATETIME="2026:06:07 18:30:00")
    update_catalog(root, project_level=1)
    assert [m.date for m in mosaics_from_catalog(root, "ndvi")] == [date(2026, 6, 7)]
    # no tag, no date in the path, and no frame times: no date (not the processing day)
    moved = root / "farm-c" / "late" / "field"
    moved.parent.mkdir(parents=True)
    _flight(moved, lat0=45.1, lon0=15.0, day="2026-06-09", times=False)
    write_orthomosaic(moved / "odm_orthophoto.tif", np.full((20, 16), 0.4), crs=UTM,
                      transform=(0.5, 0.0, 500000.0, 0.0, -0.5, 5000100.0))
    update_catalog(root, project_level=1)
    got = {m.flight: m.date for m in mosaics_from_catalog(root, "ndvi")}
    assert got == {"2026-06-08__field": date(2026, 6, 7), "late__field": None}


def test_stats_command_over_the_catalog(root: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    update_catalog(root, project_level=1)
    ring = [[500010.1, 5000010.1], [500030.1, 5000010.1], [500030.1, 5000030.1], [500010.1, 5000030.1],
            [500010.1, 5000010.1]]
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"id": "p1"}, "geometry": {"type": "Polygon", "coordinates": [ring]}},
        {"type": "Feature", "properties": {"id": "p2"}, "geometry": {"type": "Polygon", "coordinates": [
            [[p[0] + 5000, p[1]] for p in ring]]}}]}
    (tmp_path / "f.geojson").write_text(json.dumps(doc))
    assert main(["stats", "--fields", str(tmp_path / "f.geojson"), "--fields-crs", UTM, "--catalog", str(root),
                 "-o", str(tmp_path / "t.csv"), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "2 flight(s) of the catalog have no orthomosaic or ndvi map" in err and "farm-b/2026-06-02__plot7" in err
    assert "field p2: outside_all_mosaics" in err
    import pandas as pd

    t = pd.read_csv(tmp_path / "t.csv")
    assert list(zip(t["field_id"], t["flight"].fillna(""), t["status"])) == [
        ("p1", "2026-06-08__field", "ok"), ("p2", "", "outside_all_mosaics")]
    assert t.loc[0, "date"] == "2026-06-08" and t.loc[0, "collection"] == "farm-north"


def test_the_flow_step_reports_a_broken_root_instead_of_failing(root: Path) -> None:
    """runner.update_catalog (the flow's task): a typo elsewhere under the root is returned as
    an error, the run whose outputs are complete is not failed; a staged remote OUT is named
    after its URL."""
    from pipeline.run import runner

    (root / "farm-a" / "mscal-project.yaml").write_text("id: [not, a, string]\n")
    res = runner.update_catalog(root)
    assert "mscal-project.yaml" in res["error"] and "id" in res["error"]
    (root / "farm-a" / "mscal-project.yaml").unlink()
    res = runner.update_catalog(root, "s3://bucket/farms/north-2026/")
    assert res["collections"] == ["north-2026"]
    assert json.loads((root / "catalog.json").read_text())["title"] == "mscal: north-2026"
