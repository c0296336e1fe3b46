"""Per-field statistics over synthetic orthomosaics with known per-pixel NDVI.

Mosaic A is in UTM 33N (EPSG:32633), mosaic B over the same ground in Web Mercator
(EPSG:3857); the fields are WGS 84 GeoJSON. The truth of each field on each mosaic is
computed here independently of the code under test: pixel centres of the mosaic's grid
inside the field's vertices (reprojected with PROJ, straight edges in the mosaic's CRS),
tested with matplotlib's point-in-polygon, and numpy statistics of the NDVI the mosaic was
written from (float64).
"""

from __future__ import annotations

import json
from datetime import date
from pathlib import Path

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from mscal_core.errors import InputError
from pipeline.products.zonal import (
    COLUMNS,
    Mosaic,
    mosaic_stats,
    mosaics_from_files,
    read_fields,
    read_table,
    write_table,
    zonal_table,
)
from pipeline.run.cli import main
from pipeline.sim.synth import write_orthomosaic

UTM = "EPSG:32633"
MERC = "EPSG:3857"
X0, Y0, PX = 500000.0, 5000130.0, 0.5  # mosaic A: top-left corner and pixel size (m)
HA, WA = 260, 300
TA = (PX, 0.0, X0, 0.0, -PX, Y0)
INVALID_A = (slice(100, 140), slice(150, 200))  # nodata block inside field "nodata"

# Fields in UTM metres (written to the GeoJSON as WGS 84 lon/lat). Vertices avoid pixel centres.
RECTS = {
    "north": (500010.13, 5000080.11, 500070.37, 5000125.29),  # crosses 64-px tile edges; also on B
    "nodata": (500072.2, 5000050.3, 500110.4, 5000085.6),
    "edge": (500130.3, 5000010.2, 500170.6, 5000040.7),  # half beyond A's right edge
    "away": (501000.1, 5000000.1, 501050.3, 5000050.3),  # on no mosaic
    "tiny": (500020.30, 5000020.30, 500020.40, 5000020.40),  # between pixel centres
}
TRIANGLE = [(500005.3, 5000005.2), (500060.7, 5000012.9), (500031.1, 5000066.6)]
BOWTIE = [(500020.1, 5000020.1), (500040.1, 5000040.1), (500040.1, 5000020.1), (500020.1, 5000040.1)]


def _lonlat(pts: list[tuple[float, float]], crs: str = UTM) -> list[list[float]]:
    from rasterio.warp import transform

    xs, ys = transform(crs, "EPSG:4326", [p[0] for p in pts], [p[1] for p in pts])
    return [[x, y] for x, y in zip(xs, ys)]


def _ring(rect: tuple[float, float, float, float]) -> list[tuple[float, float]]:
    x0, y0, x1, y1 = rect
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]


def _feature(fid: str, geometry: dict) -> dict:
    return {"type": "Feature", "properties": {"field_id": fid}, "geometry": geometry}


def _fields_doc() -> dict:
    feats = [_feature(k, {"type": "Polygon", "coordinates": [_lonlat(_ring(r))]}) for k, r in RECTS.items()]
    feats.append(_feature("triangle", {"type": "Polygon", "coordinates": [_lonlat(TRIANGLE + TRIANGLE[:1])]}))
    feats.append(_feature("bowtie", {"type": "Polygon", "coordinates": [_lonlat(BOWTIE + BOWTIE[:1])]}))
    feats.append(_feature("well", {"type": "Point", "coordinates": _lonlat([(500030.0, 5000030.0)])[0]}))
    return {"type": "FeatureCollection", "features": feats}


def _truth_mask(vertices_lonlat: list[list[float]], crs: str, transform: tuple, shape: tuple[int, int],
                pad: int) -> tuple[np.ndarray, int]:
    """(inside mask on the mosaic, number of centres inside on the grid extended by ``pad`` px)."""
    from rasterio.warp import transform as warp

    xs, ys = warp("EPSG:4326", crs, [v[0] for v in vertices_lonlat], [v[1] for v in vertices_lonlat])
    poly = MplPath(np.column_stack([xs, ys]))
    a, _, c, _, e, f = transform
    h, w = shape
    rows, cols = np.mgrid[-pad:h + pad, -pad:w + pad]
    centres = np.column_stack([(c + a * (cols + 0.5)).ravel(), (f + e * (rows + 0.5)).ravel()])
    inside = poly.contains_points(centres).reshape(rows.shape)
    return inside[pad:pad + h, pad:pad + w], int(inside.sum())


def _truth_stats(ndvi: np.ndarray, invalid: np.ndarray, mask: np.ndarray, n_pixels: int) -> dict:
    v = ndvi[mask & ~invalid]
    return {"n_pixels": n_pixels, "n_valid": v.size, "valid_fraction": v.size / n_pixels, "mean": v.mean(),
            "median": np.median(v), "std": v.std(), "p10": np.percentile(v, 10), "p90": np.percentile(v, 90)}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("zonal")
    rng = np.random.default_rng(7)
    ndvi_a = rng.uniform(-0.4, 0.85, size=(HA, WA))
    invalid_a = np.zeros((HA, WA), bool)
    invalid_a[INVALID_A] = True
    a = write_orthomosaic(root / "2026-06-01" / "ortho_a.tif", ndvi_a, crs=UTM, transform=TA, invalid=invalid_a,
                          seed=1, block=64, date="2026-06-01")
    # mosaic B: Web Mercator over field "north", 0.7 m pixels, strips (no tiles)
    from rasterio.warp import transform_bounds

    b0 = transform_bounds(UTM, MERC, 500000.0, 5000070.0, 500080.0, 5000130.0)
    tb = (0.7, 0.0, b0[0], 0.0, -0.7, b0[3])
    hb, wb = int((b0[3] - b0[1]) / 0.7), int((b0[2] - b0[0]) / 0.7)
    ndvi_b = rng.uniform(0.1, 0.8, size=(hb, wb))
    b = write_orthomosaic(root / "2026-06-08" / "ortho_b.tif", ndvi_b, crs=MERC, transform=tb, seed=2, block=None)
    fields = root / "fields.geojson"
    fields.write_text(json.dumps(_fields_doc()))
    return {"root": root, "a": a, "b": b, "fields": fields, "ndvi_a": ndvi_a, "invalid_a": invalid_a,
            "ndvi_b": ndvi_b, "tb": tb, "shape_b": (hb, wb)}


def _truth(scene: dict, fid: str, which: str) -> dict:
    doc = _fields_doc()
    ring = next(f for f in doc["features"] if f["properties"]["field_id"] == fid)["geometry"]["coordinates"][0]
    if which == "a":
        mask, n = _truth_mask(ring, UTM, TA, (HA, WA), pad=200)
        return _truth_stats(scene["ndvi_a"], scene["invalid_a"], mask, n)
    mask, n = _truth_mask(ring, MERC, scene["tb"], scene["shape_b"], pad=200)
    return _truth_stats(scene["ndvi_b"], np.zeros(scene["shape_b"], bool), mask, n)


def _check(row: dict, truth: dict) -> None:
    assert row["n_pixels"] == truth["n_pixels"]
    assert row["n_valid"] == truth["n_valid"]
    for k in ("valid_fraction", "mean", "median", "std", "p10", "p90"):
        assert row[k] == pytest.approx(truth[k], abs=1e-6), k


def test_statistics_exact_on_both_crs_across_tiles_and_nodata(scene: dict) -> None:
    fields = read_fields(scene["fields"])
    assert fields.crs == "EPSG:4326"
    mosaics = mosaics_from_files([scene["a"], scene["b"]])
    assert [m.date for m in mosaics] == [date(2026, 6, 1), date(2026, 6, 8)]  # tag, then folder name
    assert [m.flight for m in mosaics] == ["2026-06-01/ortho_a", "2026-06-08/ortho_b"]
    df = zonal_table(fields, mosaics, "ndvi", workers=2, tile=(64, 64))
    assert list(df.columns) == COLUMNS
    rows = {(r["field_id"], r["flight"]): r for r in df.to_dict("records")}
    for fid in ("north", "nodata", "edge", "triangle"):
        _check(rows[(fid, "2026-06-01/ortho_a")], _truth(scene, fid, "a"))
        assert rows[(fid, "2026-06-01/ortho_a")]["status"] == "ok"
    _check(rows[("north", "2026-06-08/ortho_b")], _truth(scene, "north", "b"))
    # the nodata block and the mosaic's edge show in the valid fraction
    assert rows[("nodata", "2026-06-01/ortho_a")]["valid_fraction"] < 0.8
    assert 0.4 < rows[("edge", "2026-06-01/ortho_a")]["valid_fraction"] < 0.6
    # nothing dropped: every bad or missing field has its row and reason
    status = {r["field_id"]: r["status"] for r in df.to_dict("records") if r["flight"] == ""}
    assert status["away"] == "outside_all_mosaics"
    assert status["bowtie"].startswith("invalid_geometry: Self-intersection")
    assert status["well"] == "not_a_polygon: Point"
    tiny = rows[("tiny", "2026-06-01/ortho_a")]
    assert tiny["status"] == "no_pixel_centre_inside" and tiny["n_pixels"] == 0
    assert set(df["field_id"]) == {"north", "nodata", "edge", "away", "tiny", "triangle", "bowtie", "well"}
    # tile size does not change a number: one window as large as the mosaic gives the same table
    whole = zonal_table(fields, mosaics, "ndvi", workers=1, tile=(4096, 4096))
    np.testing.assert_array_equal(df[["n_pixels", "n_valid"]].to_numpy(), whole[["n_pixels", "n_valid"]].to_numpy())
    np.testing.assert_allclose(df[["mean", "median", "p10", "p90"]].to_numpy(dtype=float),
                               whole[["mean", "median", "p10", "p90"]].to_numpy(dtype=float), rtol=0, atol=1e-12)


def test_index_map_input_and_fields_in_a_projected_crs(scene: dict, tmp_path: Path) -> None:
    """An NDVI COG from mscal index is used as is; fields given in UTM (legacy crs member)."""
    from pipeline.products.indexmap import index_map

    cog = index_map(scene["a"], "ndvi", tmp_path / "ndvi_a.tif")
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}},
           "features": [_feature("north", {"type": "Polygon", "coordinates": [[list(p) for p in _ring(RECTS["north"])]]})]}
    f = tmp_path / "utm.geojson"
    f.write_text(json.dumps(doc))
    fields = read_fields(f)
    rows = mosaic_stats(Mosaic(str(cog), "a"), fields, "ndvi")
    assert len(rows) == 1
    _check(rows[0], _truth(scene, "north", "a"))


def test_table_files_round_trip(scene: dict, tmp_path: Path) -> None:
    fields = read_fields(scene["fields"])
    df = zonal_table(fields, mosaics_from_files([scene["a"]]), "ndvi", workers=1)
    pq, csv = write_table(df, tmp_path / "stats")
    assert (pq.name, csv.name) == ("stats.parquet", "stats.csv")
    for p in (pq, csv):
        back = read_table(p)
        assert list(back.columns) == COLUMNS
        assert list(back["field_id"]) == list(df["field_id"])
        np.testing.assert_allclose(back["median"].to_numpy(float), df["median"].to_numpy(float), atol=1e-8)
        assert list(back["date"]) == list(df["date"])
    assert "2026-06-01" in csv.read_text()


def test_bad_inputs_are_named(scene: dict, tmp_path: Path) -> None:
    # fields in metres with no CRS named
    doc = {"type": "FeatureCollection",
           "features": [_feature("x", {"type": "Polygon", "coordinates": [[list(p) for p in _ring(RECTS["north"])]]})]}
    f = tmp_path / "nocrs.geojson"
    f.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="not longitude/latitude.*--fields-crs") as e:
        read_fields(f)
    assert "nocrs.geojson" in str(e.value)
    # a mosaic without a CRS
    import rasterio

    with rasterio.open(scene["a"]) as src:
        data, prof = src.read(), src.profile
    prof.pop("crs")
    bare = tmp_path / "bare.tif"
    with rasterio.open(bare, "w", **prof) as dst:
        dst.write(data)
        dst.descriptions = ("Red", "NIR")
    with pytest.raises(InputError, match="has no CRS") as e:
        zonal_table(read_fields(scene["fields"]), mosaics_from_files([bare]), "ndvi")
    assert "bare.tif" in str(e.value)
    # duplicate ids
    doc = _fields_doc()
    doc["features"][1]["properties"]["field_id"] = "north"
    f2 = tmp_path / "dup.geojson"
    f2.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="north occur more than once"):
        read_fields(f2)


def test_cli_writes_tables_and_season_plot(scene: dict, tmp_path: Path) -> None:
    out = tmp_path / "season"
    rc = main(["stats", "--fields", str(scene["fields"]), "--index", "ndvi", str(scene["a"]), str(scene["b"]),
               "-o", str(out), "--plot", str(tmp_path / "season.html"), "--workers", "1"])
    assert rc == 0
    df = read_table(tmp_path / "season.parquet")
    assert (tmp_path / "season.csv").is_file()
    assert df.loc[df["field_id"] == "north", "status"].tolist() == ["ok", "ok"]
    page = (tmp_path / "season.html").read_text()
    assert page.count("<img") >= 1 and "north" in page
    # a mosaic that is not there: one line naming it, exit 2
    assert main(["stats", "--fields", str(scene["fields"]), str(tmp_path / "missing.tif"), "-o", str(out)]) == 2


def test_memory_is_bounded_by_tiles_not_the_mosaic(tmp_path: Path) -> None:
    """A 2048 x 2048 mosaic (32 MB of reflectance) and a field of 1/16 of it: the task's
    numpy peak stays far below the mosaic's size (tracemalloc counts numpy's buffers)."""
    import tracemalloc

    n = 2048
    ndvi = np.full((n, n), 0.5)
    t = (PX, 0.0, X0, 0.0, -PX, Y0 + n * PX)
    ortho = write_orthomosaic(tmp_path / "big.tif", ndvi, crs=UTM, transform=t, block=256)
    rect = (X0 + 100.1, Y0 + n * PX - 400.1, X0 + 356.1, Y0 + n * PX - 144.1)  # 512 x 512 px
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": UTM}},
           "features": [_feature("f", {"type": "Polygon", "coordinates": [[list(p) for p in _ring(rect)]]})]}
    (tmp_path / "f.geojson").write_text(json.dumps(doc))
    fields = read_fields(tmp_path / "f.geojson")
    tracemalloc.start()
    rows = mosaic_stats(Mosaic(str(ortho), "big"), fields, "ndvi", max_cached_tiles=4)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert rows[0]["n_valid"] == 512 * 512 and rows[0]["median"] == pytest.approx(0.5, abs=1e-6)
    mosaic_bytes = 2 * n * n * 4
    assert peak < mosaic_bytes / 4, (peak, mosaic_bytes)


def test_season_plot_draws_the_table(tmp_path: Path) -> None:
    """The plotted medians, p10-p90 band and means are the table's rows of the field, by date;
    rows without numbers or a date are not drawn but counted in the report's table."""
    import pandas as pd
    from matplotlib.collections import PolyCollection

    from pipeline.products.report import plot_season, season_sections, write_report

    rows = []
    for k, d in enumerate([date(2026, 6, 15), date(2026, 6, 1), date(2026, 6, 8), None]):
        rows.append({"field_id": "f1", "date": d, "flight": f"fl{k}", "collection": "", "index": "ndvi", "source": "x",
                     "n_pixels": 10, "n_valid": 10, "valid_fraction": 1.0, "mean": 0.3 + 0.1 * k,
                     "median": 0.31 + 0.1 * k, "std": 0.05, "p10": 0.2 + 0.1 * k, "p90": 0.4 + 0.1 * k, "status": "ok"})
    rows.append({**rows[0], "field_id": "f2", "n_valid": 0, "median": float("nan"), "status": "no_valid_pixels"})
    df = pd.DataFrame(rows)
    fig = plot_season(df, "f1", "ndvi")
    ax = fig.axes[0]
    median_line, mean_line = ax.lines[0], ax.lines[1]
    np.testing.assert_allclose(median_line.get_ydata(), [0.41, 0.51, 0.31])  # 1, 8, 15 June
    np.testing.assert_allclose(mean_line.get_ydata(), [0.4, 0.5, 0.3])
    band = next(c for c in ax.collections if isinstance(c, PolyCollection))
    ys = band.get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(0.2) and ys.max() == pytest.approx(0.6)  # the undated row (0.5-0.7) is not drawn
    sec = season_sections(df)[0]
    assert sec.tables[0].rows == [["f1", 4, 1, ""], ["f2", 0, 0, "no_valid_pixels"]]
    assert len(sec.figures) == 1  # f2 has no numbers to draw
    df.to_csv(tmp_path / "t.csv", index=False)  # as the CSV mscal stats writes, dates ISO
    out = write_report(tmp_path / "r.html", stats=tmp_path / "t.csv")
    page = out.read_text()
    assert page.count("data:image/png;base64,") == 1 and "Season: ndvi" in page
