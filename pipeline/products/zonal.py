"""``mscal stats``: per-field statistics of index maps over many orthomosaics.

Inputs:

- fields: a GeoJSON file of Polygon / MultiPolygon features (:func:`read_fields`). Its CRS is
  the legacy ``crs`` member if present, else ``--fields-crs``, else WGS 84 longitude/latitude
  as RFC 7946 defines GeoJSON; coordinates that cannot be longitude/latitude with no CRS named
  are an :class:`InputError`. The field id is the property ``--id-property`` names, else the
  first of ``id``, ``field_id``, ``name``, ``fid`` in the properties, else the feature's
  ``id``, else ``field-<n>`` (1-based position); ids must be unique.
- mosaics (:class:`Mosaic`): reflectance orthomosaics (the index is evaluated tile by tile as
  ``mscal index`` does: same band matching, scaling and nodata rules, ``pipeline.products.indexmap``),
  or single-band index maps whose ``INDEX`` tag or band description is the index (the COGs
  ``mscal index`` writes), given as files (:func:`mosaics_from_files`) or found in an ``mscal
  catalog`` (:func:`mosaics_from_catalog`).

Each field is reprojected to the mosaic's CRS (its vertices, with GDAL; the raster is never
resampled) and rasterised on the mosaic's own grid, pixel centres inside
(:mod:`mscal_core.zonal` gives the statistics and their definitions).

Memory, per mosaic task: the mosaic is read in tiles (its internal blocks when it is tiled,
else 512 x 512 windows; ``tile=`` overrides) and a field's mask is rasterised tile by tile,
so no array is the size of the mosaic. The exact median and p10/p90 need all valid values of
a field at once: they are kept (float32, 4 bytes a pixel) until the field is finished, then
dropped. Peak memory of a task is therefore about ``max_cached_tiles`` index tiles (4 bytes
a pixel each, plus the reflectance bands of one tile while it is evaluated) plus the valid
pixels of the largest field times ~16 bytes (the float32 values, and float64 copies while
sorting). Fields are visited in tile order so that neighbouring fields reuse cached tiles.
Time grows with a field's area in the mosaic's pixels, including the part beyond the mosaic's
edge, which is rasterised too so that ``n_pixels`` (and so ``valid_fraction``) is exact.
Mosaics are processed in parallel, one Dask task each (threads; rasterio releases the GIL
while reading); peak memory is the sum over the tasks running at once (``workers``).

Nothing is dropped silently: every field gets at least one row. A row's ``status`` is

- ``ok``;
- ``no_valid_pixels``: the field is on the mosaic but every pixel of it is nodata;
- ``no_pixel_centre_inside``: the field touches the mosaic but is smaller than a pixel there;
- ``outside_all_mosaics``: no mosaic covers any of it (one row, statistics empty);
- ``invalid_geometry: <reason>`` (e.g. a self-intersection, with its location),
  ``not_a_polygon: <type>``, ``empty_geometry``, ``no_geometry``, ``reprojection_failed: ...``
  (one row, statistics empty; fix the geometry, e.g. ``shapely.make_valid``, and run again).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections import OrderedDict
from dataclasses import dataclass
from datetime import date, datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from mscal_core.errors import InputError
from mscal_core.zonal import zonal_statistics

from pipeline.ingest.catalog import Index, load_index
from pipeline.products.indexmap import alpha_bands, band_scales, evaluate_window, resolve_bands
from pipeline.storage.atomic import atomic_path

log = logging.getLogger(__name__)

__all__ = [
    "COLUMNS", "Field", "Fields", "Mosaic", "mosaic_stats", "mosaics_from_catalog", "mosaics_from_files",
    "read_fields", "write_table", "zonal_table",
]

#: Columns of the table, in order.
COLUMNS = ["field_id", "date", "flight", "collection", "index", "source", "n_pixels", "n_valid",
           "valid_fraction", "mean", "median", "std", "p10", "p90", "status"]
STAT_COLUMNS = ("valid_fraction", "mean", "median", "std", "p10", "p90")
ID_PROPERTIES = ("id", "field_id", "name", "fid")
WGS84 = "EPSG:4326"
DEFAULT_TILE = 512  # window side for mosaics stored in strips (tiled ones use their blocks)
DEFAULT_CACHED_TILES = 16  # 16 tiles of 512 x 512 float32 = 16 MB of index values per task


@dataclass(frozen=True)
class Field:
    """One field: its id, GeoJSON geometry (in the fields' CRS) and ``ok`` or why it is unusable."""

    id: str
    geometry: Mapping[str, Any] | None
    status: str = "ok"


@dataclass(frozen=True)
class Fields:
    path: str
    crs: str
    fields: tuple[Field, ...]


@dataclass(frozen=True)
class Mosaic:
    """One orthomosaic or index map and where it belongs in the table."""

    path: str
    flight: str
    date: date | None = None
    collection: str = ""


# --------------------------------------------------------------------------- fields


def _crs_member(doc: Mapping[str, Any]) -> str | None:
    crs = doc.get("crs")
    if not crs:
        return None
    if isinstance(crs, Mapping):
        props = crs.get("properties") or {}
        name = props.get("name") if isinstance(props, Mapping) else None
        if name:
            return str(name)
    return str(crs) if isinstance(crs, str) else None


def _coords(geom: Mapping[str, Any]) -> Iterable[Sequence[float]]:
    def walk(c: Any) -> Iterable[Sequence[float]]:
        if isinstance(c, (list, tuple)) and c and isinstance(c[0], (int, float)):
            yield c
        elif isinstance(c, (list, tuple)):
            for x in c:
                yield from walk(x)

    if geom.get("type") == "GeometryCollection":
        for g in geom.get("geometries") or []:
            yield from _coords(g)
    else:
        yield from walk(geom.get("coordinates"))


def _check_field(geom: Any) -> str:
    """``ok`` or why the geometry cannot be a field."""
    import shapely
    from shapely.geometry import shape

    if geom is None:
        return "no_geometry"
    if not isinstance(geom, Mapping) or "type" not in geom:
        return "invalid_geometry: not a GeoJSON geometry"
    if geom["type"] not in ("Polygon", "MultiPolygon"):
        return f"not_a_polygon: {geom['type']}"
    try:
        g = shape(geom)
    except Exception as exc:  # malformed coordinates of any kind
        return f"invalid_geometry: {exc}"
    if g.is_empty:
        return "empty_geometry"
    if not g.is_valid:
        return f"invalid_geometry: {shapely.is_valid_reason(g)}"
    return "ok"


def read_fields(path: str | Path, *, id_property: str | None = None, crs: str | None = None) -> Fields:
    """The fields of a GeoJSON FeatureCollection (or one Feature), each checked (module docstring)."""
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    path = Path(path)
    if not path.is_file():
        raise InputError("fields file not found", path=path, hint="give a GeoJSON FeatureCollection of polygons")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a GeoJSON file ({exc})", path=path) from None
    if not isinstance(doc, Mapping) or doc.get("type") not in ("FeatureCollection", "Feature"):
        raise InputError("not a GeoJSON FeatureCollection or Feature", path=path,
                         hint="the fields file must hold polygon features with an id property")
    features = doc.get("features") if doc["type"] == "FeatureCollection" else [doc]
    if not isinstance(features, list) or not features:
        raise InputError("holds no features", path=path, hint="add the fields as Polygon features")
    member = _crs_member(doc)
    if member and crs and CRS.from_user_input(member) != CRS.from_user_input(crs):
        raise InputError(f"names CRS {member} but --fields-crs is {crs}", path=path, hint="drop one of them")
    crs_text = crs or member
    if crs_text:
        try:
            CRS.from_user_input(crs_text)
        except CRSError as exc:
            raise InputError(f"CRS {crs_text!r} is not one PROJ knows ({exc})", path=path,
                             hint="give e.g. --fields-crs EPSG:32633") from None
    else:
        crs_text = WGS84
        far = [c for f in features if isinstance(f, Mapping) and isinstance(f.get("geometry"), Mapping)
               for c in _coords(f["geometry"]) if len(c) >= 2 and (abs(c[0]) > 180 or abs(c[1]) > 90)]
        if far:
            raise InputError(
                f"coordinates such as ({far[0][0]:g}, {far[0][1]:g}) are not longitude/latitude and the file "
                "names no CRS (GeoJSON without a crs member is WGS 84 longitude/latitude, RFC 7946)",
                path=path, hint="give the fields' CRS with --fields-crs EPSG:NNNN, or reproject them to WGS 84",
            )
    out: list[Field] = []
    for n, f in enumerate(features, start=1):
        if not isinstance(f, Mapping) or f.get("type") != "Feature":
            raise InputError(f"feature {n} is not a GeoJSON Feature", path=path)
        props = f.get("properties") or {}
        if id_property is not None:
            if id_property not in props or props[id_property] in (None, ""):
                raise InputError(f"feature {n} has no property {id_property!r}", path=path,
                                 hint=f"its properties: {', '.join(map(str, props)) or 'none'}")
            fid = props[id_property]
        else:
            fid = next((props[k] for k in ID_PROPERTIES if props.get(k) not in (None, "")), None)
            if fid is None:
                fid = f.get("id") if f.get("id") not in (None, "") else f"field-{n}"
        out.append(Field(str(fid), f.get("geometry"), _check_field(f.get("geometry"))))
    counts: dict[str, int] = {}
    for x in out:
        counts[x.id] = counts.get(x.id, 0) + 1
    dups = sorted(k for k, v in counts.items() if v > 1)
    if dups:
        raise InputError(f"field ids {', '.join(dups[:5])} occur more than once", path=path,
                         hint="each field needs its own id (choose the property with --id-property)")
    return Fields(str(path), crs_text, tuple(out))


# --------------------------------------------------------------------------- mosaics

_DATE_IN_PATH = re.compile(r"(?<!\d)(20\d\d|19\d\d)-?(0[1-9]|1[0-2])-?(0[1-9]|[12]\d|3[01])(?!\d)")


def _date_of_tif(src: Any, path: Path) -> date | None:
    """Acquisition date from the GeoTIFF's tags (TIFFTAG_DATETIME, ACQUISITIONDATETIME), else a
    YYYY-MM-DD / YYYYMMDD in its path, else None."""
    tags = {k.upper(): v for k, v in src.tags().items()}
    for key in ("ACQUISITIONDATETIME", "TIFFTAG_DATETIME", "DATETIME", "DATE"):
        m = re.match(r"^\s*(\d{4})[:\-](\d{2})[:\-](\d{2})", str(tags.get(key, "")))
        if m:
            try:
                return date(int(m.group(1)), int(m.group(2)), int(m.group(3)))
            except ValueError:
                pass
    for part in reversed(path.parts):
        m = _DATE_IN_PATH.search(part)
        if m:
            try:
                return date(int(m.group(1)), int(m.group(2)), int(m.group(3)))
            except ValueError:
                continue
    return None


def mosaics_from_files(paths: Sequence[str | Path]) -> list[Mosaic]:
    """:class:`Mosaic` of each file: ``flight`` is its path relative to the inputs' common
    folder without the suffix (the stem when there is one file); ``date`` as
    :func:`_date_of_tif` finds it."""
    import rasterio
    from rasterio.errors import RasterioIOError

    files = [Path(p) for p in paths]
    if not files:
        raise InputError("no orthomosaic given", hint="mscal stats --fields F.geojson ORTHO.tif [...], or --catalog")
    resolved = [f.resolve() for f in files]
    common = Path(os.path.commonpath([str(r.parent) for r in resolved]))
    out = []
    for f, r in zip(files, resolved):
        if not f.is_file():
            raise InputError("orthomosaic not found", path=f)
        try:
            with rasterio.open(f) as src:
                d = _date_of_tif(src, r)
        except RasterioIOError as exc:
            raise InputError(f"not a raster GDAL can read ({exc})", path=f) from None
        flight = str(r.relative_to(common).with_suffix("")) if len(files) > 1 else f.stem
        out.append(Mosaic(str(f), flight, d))
    return out


def mosaics_from_catalog(catalog: str | Path, index_name: str, skipped: list[str] | None = None) -> list[Mosaic]:
    """Every flight of an ``mscal catalog`` with an index map of ``index_name`` or an
    orthomosaic (the index map is preferred: no evaluation needed); flights with neither are
    appended to ``skipped`` as ``<collection>/<item>``.

    The date follows the same rule as for files (:func:`_date_of_tif`: the GeoTIFF's tags, then a
    date in its path), then the item's frame time; an item dated only by its processing time
    has no date."""
    import rasterio
    from rasterio.errors import RasterioIOError

    from pipeline.products.stac import catalog_rasters

    out = []
    for r in catalog_rasters(catalog, index_name, skipped):
        try:
            with rasterio.open(r["path"]) as src:
                day = _date_of_tif(src, Path(r["path"]))
        except RasterioIOError as exc:
            raise InputError(f"not a raster GDAL can read ({exc})", path=r["path"],
                             hint="rebuild the catalog with mscal catalog ROOT, or remove the file") from None
        out.append(Mosaic(r["path"], r["item"], day or r["date"], r["collection"]))
    return out


def _is_index_map(src: Any, index: Index) -> bool:
    alpha = alpha_bands(src)
    data = [b for b in range(1, src.count + 1) if b not in alpha]
    if len(data) != 1:
        return False
    tag = str(src.tags().get("INDEX", "")).strip().lower()
    desc = str(src.descriptions[data[0] - 1] or "").strip().lower()
    return index.name.lower() in (tag, desc)


def check_mosaic(path: str | Path, index: Index, bands: Mapping[str, int] | None = None) -> None:
    """Fail early, naming the file: unreadable, no CRS, or the index's bands not found."""
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        src = rasterio.open(path)
    except RasterioIOError as exc:
        raise InputError(f"not a raster GDAL can read ({exc})", path=path) from None
    with src:
        if src.crs is None:
            raise InputError(
                "has no CRS, so the fields cannot be placed on it",
                path=path, hint="set it, e.g. gdal_edit.py -a_srs EPSG:32633 FILE, or export the mosaic georeferenced",
            )
        if src.transform.is_identity:
            raise InputError("has no geotransform (pixel coordinates only)", path=path,
                             hint="export the mosaic georeferenced")
        if not _is_index_map(src, index):
            resolve_bands(src, tuple(index.inputs), bands, path=path)


class _IndexTiles:
    """Index values of a mosaic, tile by tile (float32, NaN = not valid), a few tiles cached."""

    def __init__(self, src: Any, index: Index, bands: Mapping[str, int] | None, tile: tuple[int, int] | None,
                 max_cached: int):
        self.src, self.index = src, index
        self.cache: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.max_cached = max(1, int(max_cached))
        self.reads = 0
        bh, bw = src.block_shapes[0]
        if tile is not None:
            self.th, self.tw = int(tile[0]), int(tile[1])
        elif bw < src.width:  # tiled: its own blocks
            self.th, self.tw = int(bh), int(bw)
        else:  # strips: square windows, whole strips
            self.tw = min(src.width, DEFAULT_TILE)
            self.th = int(bh) * max(1, DEFAULT_TILE // int(bh))
        self.direct = _is_index_map(src, index)
        if self.direct:
            alpha = alpha_bands(src)
            self.band = next(b for b in range(1, src.count + 1) if b not in alpha)
            self.alpha = alpha
        else:
            self.mapping = resolve_bands(src, tuple(index.inputs), bands, path=src.name)
            self.numbers = sorted(set(self.mapping.values()))
            self.scales = band_scales(src, self.numbers, None)
            self.alpha = alpha_bands(src)

    def tile(self, ti: int, tj: int) -> np.ndarray:
        """The index over tile (ti, tj) clipped to the mosaic."""
        key = (ti, tj)
        if key in self.cache:
            self.cache.move_to_end(key)
            return self.cache[key]
        from rasterio.windows import Window

        r0, c0 = ti * self.th, tj * self.tw
        win = Window(c0, r0, min(self.tw, self.src.width - c0), min(self.th, self.src.height - r0))
        if self.direct:
            arr = self.src.read(self.band, window=win, out_dtype="float32")
            bad = self.src.read_masks(self.band, window=win) == 0
            for a in self.alpha:
                bad |= self.src.read(a, window=win) == 0
            arr[bad] = np.nan
        else:
            arr = evaluate_window(self.src, self.index, self.mapping, self.numbers, self.scales, self.alpha, win)
        arr[~np.isfinite(arr)] = np.nan  # 0/0 or x/0 of an index is not a value
        self.reads += 1
        self.cache[key] = arr
        while len(self.cache) > self.max_cached:
            self.cache.popitem(last=False)
        return arr


def _pixel_bbox(bounds: tuple[float, float, float, float], transform: Any) -> tuple[int, int, int, int]:
    """Rows [r0, r1) and columns [c0, c1) of the grid whose pixel centres may lie in ``bounds``."""
    inv = ~transform
    xs, ys = [], []
    for x, y in ((bounds[0], bounds[1]), (bounds[0], bounds[3]), (bounds[2], bounds[1]), (bounds[2], bounds[3])):
        c, r = inv @ (x, y)
        xs.append(c)
        ys.append(r)
    return (math.floor(min(ys)), math.ceil(max(ys)) + 1, math.floor(min(xs)), math.ceil(max(xs)) + 1)


def _row(field_id: str, mosaic: Mosaic | None, index: str, status: str, stats: Any = None) -> dict[str, Any]:
    nan = float("nan")
    return {
        "field_id": field_id,
        "date": mosaic.date if mosaic else None,
        "flight": mosaic.flight if mosaic else "",
        "collection": mosaic.collection if mosaic else "",
        "index": index,
        "source": mosaic.path if mosaic else "",
        "n_pixels": stats.n_pixels if stats else 0,
        "n_valid": stats.n_valid if stats else 0,
        **{k: (getattr(stats, k) if stats else nan) for k in STAT_COLUMNS},
        "status": status,
    }


def mosaic_stats(mosaic: Mosaic, fields: Fields, index_name: str, *, bands: Mapping[str, int] | None = None,
                 tile: tuple[int, int] | None = None, max_cached_tiles: int = DEFAULT_CACHED_TILES) -> list[dict[str, Any]]:
    """Rows of the fields that touch ``mosaic`` (module docstring); fields it misses get none."""
    import rasterio
    from rasterio.features import rasterize
    from rasterio.warp import transform_geom
    from rasterio.windows import Window
    from rasterio.windows import transform as window_transform
    from shapely.geometry import box, shape

    index = load_index(index_name)
    rows: list[dict[str, Any]] = []
    with rasterio.open(mosaic.path) as src:
        tiles = _IndexTiles(src, index, bands, tile, max_cached_tiles)
        extent = box(*src.bounds)
        todo = []
        for f in fields.fields:
            if f.status != "ok":
                continue
            try:
                g = transform_geom(fields.crs, src.crs, f.geometry)
                sg = shape(g)
            except Exception as exc:  # GDAL/PROJ: outside the projection's domain
                rows.append(_row(f.id, mosaic, index.name, f"reprojection_failed: {exc}"))
                continue
            if sg.is_empty or not sg.intersects(extent):
                continue
            r0, r1, c0, c1 = _pixel_bbox(sg.bounds, src.transform)
            todo.append((r0 // tiles.th, c0 // tiles.tw, f, g, (r0, r1, c0, c1)))
        todo.sort(key=lambda t: (t[0], t[1]))  # tile order: neighbours share cached tiles
        for _, _, f, g, (r0, r1, c0, c1) in todo:
            n_pixels, n_inside, parts = 0, 0, []
            for ti in range(r0 // tiles.th, (r1 - 1) // tiles.th + 1):
                for tj in range(c0 // tiles.tw, (c1 - 1) // tiles.tw + 1):
                    # the part of tile (ti, tj) inside the field's box, on the (unbounded) grid
                    wr0, wr1 = max(r0, ti * tiles.th), min(r1, (ti + 1) * tiles.th)
                    wc0, wc1 = max(c0, tj * tiles.tw), min(c1, (tj + 1) * tiles.tw)
                    if wr1 <= wr0 or wc1 <= wc0:
                        continue
                    win = Window(wc0, wr0, wc1 - wc0, wr1 - wr0)
                    mask = rasterize([(g, 1)], out_shape=(wr1 - wr0, wc1 - wc0),
                                     transform=window_transform(win, src.transform), fill=0, dtype="uint8",
                                     all_touched=False).astype(bool)
                    n = int(mask.sum())
                    if n == 0:
                        continue
                    n_pixels += n
                    # clip to the mosaic
                    ir0, ir1 = max(wr0, 0), min(wr1, src.height)
                    ic0, ic1 = max(wc0, 0), min(wc1, src.width)
                    if ir1 <= ir0 or ic1 <= ic0:
                        continue
                    m = mask[ir0 - wr0:ir1 - wr0, ic0 - wc0:ic1 - wc0]
                    if not m.any():
                        continue
                    n_inside += int(m.sum())
                    t = tiles.tile(ti, tj)
                    v = t[ir0 - ti * tiles.th:ir1 - ti * tiles.th, ic0 - tj * tiles.tw:ic1 - tj * tiles.tw][m]
                    v = v[np.isfinite(v)]
                    if v.size:
                        parts.append(v)
            if n_inside == 0:
                status = "no_pixel_centre_inside" if n_pixels == 0 else None
                if status is None:  # its pixels are all beyond the mosaic's edge: it misses it
                    continue
                rows.append(_row(f.id, mosaic, index.name, status, zonal_statistics(np.empty(0), 0)))
                continue
            values = np.concatenate(parts) if parts else np.empty(0, np.float32)
            del parts
            st = zonal_statistics(values, n_pixels)
            rows.append(_row(f.id, mosaic, index.name, "ok" if st.n_valid else "no_valid_pixels", st))
        log.debug("%s: %d field rows, %d tile reads", mosaic.path, len(rows), tiles.reads)
    return rows


def zonal_table(fields: Fields, mosaics: Sequence[Mosaic], index_name: str, *, bands: Mapping[str, int] | None = None,
                workers: int | None = None, tile: tuple[int, int] | None = None,
                max_cached_tiles: int = DEFAULT_CACHED_TILES) -> "Any":
    """The tidy table (pandas DataFrame, :data:`COLUMNS`) of every field on every mosaic it
    touches, plus one row per field no mosaic covers or that is unusable. One Dask task per
    mosaic on ``workers`` threads (default: one per core)."""
    import dask
    import pandas as pd

    index = load_index(index_name)
    if not mosaics:
        raise InputError("no orthomosaic to compute statistics on",
                         hint="give orthomosaic files, or a catalog whose flights have orthomosaics or index maps")
    for m in mosaics:
        check_mosaic(m.path, index, bands)
    # arguments wrapped whole: dask would otherwise walk every dataclass field of every argument
    fd = dask.delayed(fields, traverse=False)
    bd = dask.delayed(dict(bands) if bands else None, traverse=False)
    tasks = [dask.delayed(mosaic_stats)(dask.delayed(m, traverse=False), fd, index.name, bands=bd, tile=tile,
                                        max_cached_tiles=max_cached_tiles) for m in mosaics]
    n = workers or os.cpu_count() or 1
    results = dask.compute(*tasks, scheduler="threads", num_workers=n) if n > 1 else [t.compute(scheduler="sync") for t in tasks]
    rows = [r for rs in results for r in rs]
    seen = {r["field_id"] for r in rows}
    for f in fields.fields:
        if f.status != "ok":
            rows.append(_row(f.id, None, index.name, f.status))
        elif f.id not in seen:
            rows.append(_row(f.id, None, index.name, "outside_all_mosaics"))
    order = {f.id: k for k, f in enumerate(fields.fields)}
    df = pd.DataFrame(rows, columns=COLUMNS)
    df["_o"] = df["field_id"].map(order)
    df["_d"] = pd.to_datetime(df["date"])
    df = df.sort_values(["_o", "_d", "flight"], kind="stable", na_position="last").drop(columns=["_o", "_d"])
    df = df.reset_index(drop=True)
    df["n_pixels"] = df["n_pixels"].astype("int64")
    df["n_valid"] = df["n_valid"].astype("int64")
    for c in STAT_COLUMNS:
        df[c] = df[c].astype("float64")
    return df


def write_table(df: Any, out: str | Path) -> tuple[Path, Path]:
    """``OUT.parquet`` and ``OUT.csv`` (``out`` with either suffix or none), each atomically.
    Parquet keeps ``date`` as a date; the CSV writes it ISO (YYYY-MM-DD), empty if unknown."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = Path(out)
    stem = out.with_suffix("") if out.suffix.lower() in (".parquet", ".csv") else out
    pq_path, csv_path = stem.with_name(stem.name + ".parquet"), stem.with_name(stem.name + ".csv")
    pq_path.parent.mkdir(parents=True, exist_ok=True)
    types = _arrow_types()
    table = pa.Table.from_pandas(df, preserve_index=False, schema=pa.schema([(c, types[c]) for c in COLUMNS]))
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), b"mscal": json.dumps(
        {"created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}).encode()})
    with atomic_path(pq_path) as tmp:
        pq.write_table(table, tmp)
    with atomic_path(csv_path) as tmp:
        df.assign(date=[d.isoformat() if isinstance(d, date) else "" for d in df["date"]]).to_csv(
            tmp, index=False, float_format="%.9g")
    return pq_path, csv_path


def _arrow_types() -> dict[str, Any]:
    import pyarrow as pa

    t = {c: pa.float64() for c in STAT_COLUMNS}
    t.update({"field_id": pa.string(), "date": pa.date32(), "flight": pa.string(), "collection": pa.string(),
              "index": pa.string(), "source": pa.string(), "n_pixels": pa.int64(), "n_valid": pa.int64(),
              "status": pa.string()})
    return t


def read_table(path: str | Path) -> Any:
    """The table written by :func:`write_table` (Parquet or CSV) as a DataFrame."""
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise InputError("statistics table not found", path=path, hint="write it with mscal stats -o TABLE")
    if path.suffix.lower() == ".csv":
        df = pd.read_csv(path, keep_default_na=True, dtype={"field_id": str, "flight": str, "collection": str})
        df["date"] = [date.fromisoformat(d) if isinstance(d, str) and d else None for d in df["date"]]
    else:
        df = pd.read_parquet(path)
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"is not an mscal stats table (no column {', '.join(missing)})", path=path)
    return df
