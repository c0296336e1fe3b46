"""``mscal catalog ROOT``: a static STAC catalog of everything mscal produced under ROOT.

Layout (static JSON, every link relative, so the tree can be moved or served as files)::

    ROOT/catalog.json                              the root Catalog
    ROOT/stac/<project>/collection.json            one Collection per farm / project
    ROOT/stac/<project>/items/<item>.json          one Item per flight

**Flights.** Every folder under ROOT that holds ``run.json`` and ``reflectance.zarr`` (an
``mscal apply`` OUT, or ``OUT/flights/<name>/`` of ``mscal run`` / ``mscal serve``). The walk
does not enter ``*.zarr``, hidden folders, ``ROOT/stac/`` or a flight's ``photogrammetry/`` and
``ndvi/``.

**Projects** (Collections), for each flight, in this order:

1. the nearest folder between the flight and ROOT (both included) holding ``mscal-project.yaml``
   (:class:`Project`: ``id`` required; ``title``, ``description``, ``license``, ``keywords``
   optional; unknown keys rejected): e.g. one per farm folder;
2. else the folder ``project_level`` levels below ROOT on the flight's path
   (``--project-level``; 0 = ROOT itself, the default: everything in one collection named after
   ROOT's folder; 1 = ``ROOT/<farm>/...``). The level is kept in ``catalog.json``
   (``mscal:project_level``) so that later updates (the flow's) keep it.

**Items.** id = the flight's path below its project folder, without ``flights`` components,
joined with ``__`` (``2026-06-01__field``). Geometry and bbox: the union of the footprints of
the flight's orthomosaics / index maps when it has any (their raster bounds reprojected to WGS
84, 21 points per edge), else the convex hull of the frames' GPS positions (the camera's track:
the imaged ground extends about half an image footprint beyond it), else none
(``mscal:footprint_source`` says which). Time: first and last frame time (``time``
coordinate); a flight without frame times gets its ``run.json`` modification time, marked
``mscal:time_source: processing``. Properties: ``instruments`` = [camera], ``mscal:camera``,
``mscal:camera_make``, ``mscal:camera_model`` and ``mscal:camera_serial`` (as the files say,
for cameras recognised from them; a card session's flights also ``mscal:radiometry`` and
``mscal:light_reference``), frame counts, calibration provenance (``mscal:calibration``,
``mscal:calibration_sha256``, and
from the session's ``run.json`` when there is one ``mscal:calibration_cached`` and
``mscal:calibration_stages``), ``mscal:version``. Assets (hrefs relative to the item file):
``reflectance`` (zarr), ``run`` (run.json), ``photogrammetry`` and ``ndvi_frames`` (folders),
``report`` (``report.html`` of the flight or of its session), ``calibration`` (the session's
``calibration.zarr``), and every GeoTIFF with a CRS at the top of the flight folder or one
folder down (outside the per-frame folders): single-band index maps (``INDEX`` tag or band
description naming a catalog index, as ``mscal index`` writes) as ``index_<name>``
(``mscal:kind: index``), others as ``orthomosaic`` (``mscal:kind: orthomosaic``).

**Incremental.** Each item keeps ``mscal:fingerprint`` (sha256 of the flight's ``run.json``,
the session's ``run.json``, the names, sizes and modification times of the rasters and report
it catalogues, its project and :data:`ITEM_FORMAT`); an update re-reads only flights whose
fingerprint changed, keeps the others' JSON as it was, removes items of flights that are gone.
Updates hold ``ROOT/.mscal-catalog.lock`` (:class:`pipeline.storage.lock.FolderLock`, waiting), so concurrent
runs do not interleave.

**Validation.** Every object written is validated against the STAC 1.1.0 JSON schemas
(:class:`OfflineValidator`): the schemas are the copies pystac ships as package data (STAC
spec and GeoJSON schemas, Apache-2.0 / MIT); a schema that is not there is an error, never a
download. Items use core fields only (no extension schemas needed); mscal's own fields carry
the ``mscal:`` prefix.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from mscal_core.errors import InputError

from pipeline.ingest.catalog import read_yaml
from pipeline.ingest.exif import parse_iso
from pipeline.storage.atomic import write_text_atomic
from pipeline.storage.lock import FolderLock
from pipeline.storage.run_layout import run_value

log = logging.getLogger(__name__)

__all__ = [
    "ITEM_FORMAT", "OfflineValidator", "Project", "catalog_rasters", "find_flights", "load_project",
    "update_catalog", "validate_catalog",
]

CATALOG_FILE = "catalog.json"
STAC_DIR = "stac"
PROJECT_FILE = "mscal-project.yaml"
LOCK_FILE = ".mscal-catalog.lock"
ITEM_FORMAT = 2  # bump when items gain or change fields: every item is rebuilt once
SKIP_DIRS = {"photogrammetry", "panels", "ndvi"}  # per-frame folders of a flight: never walked
MEDIA_ZARR = "application/vnd+zarr"
MEDIA_GEOTIFF = "image/tiff; application=geotiff"
MEDIA_COG = "image/tiff; application=geotiff; profile=cloud-optimized"
_ID_OK = re.compile(r"[^A-Za-z0-9._-]+")


# --------------------------------------------------------------------------- projects


@dataclass(frozen=True)
class Project:
    """A Collection: ``id`` names it (letters, digits, ``.``, ``_``, ``-``)."""

    id: str
    title: str | None = None
    description: str | None = None
    license: str = "other"
    keywords: tuple[str, ...] = field(default_factory=tuple)


_PROJECT_KEYS = {"id", "title", "description", "license", "keywords"}


def _clean_id(text: str) -> str:
    out = _ID_OK.sub("-", text).strip("-")
    return out or "mscal"


def load_project(path: str | Path) -> Project:
    """``mscal-project.yaml`` -> :class:`Project`; :class:`InputError` naming the file if invalid."""
    path = Path(path)
    doc = read_yaml(path, InputError)
    if not isinstance(doc, dict):
        raise InputError("must be a mapping with at least 'id'", path=path, hint="e.g. id: farm-north")
    unknown = sorted(set(map(str, doc)) - _PROJECT_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}", path=path,
                         hint=f"allowed: {', '.join(sorted(_PROJECT_KEYS))}")
    pid = doc.get("id")
    if not isinstance(pid, str) or not pid.strip() or _ID_OK.search(pid):
        raise InputError(f"id {pid!r} must be a non-empty string of letters, digits, '.', '_' or '-'", path=path,
                         hint="e.g. id: farm-north")
    for k in ("title", "description", "license"):
        if k in doc and not isinstance(doc[k], str):
            raise InputError(f"{k} must be a string, not {type(doc[k]).__name__}", path=path)
    kw = doc.get("keywords", [])
    if not isinstance(kw, list) or not all(isinstance(k, str) for k in kw):
        raise InputError("keywords must be a list of strings", path=path)
    return Project(pid, doc.get("title"), doc.get("description"), doc.get("license", "other"), tuple(kw))


def find_flights(root: str | Path) -> list[Path]:
    """Flight folders (``run.json`` + ``reflectance.zarr``) under ``root``, sorted."""
    root = Path(root)
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        skip = {n for n in dirnames if n.startswith(".") or n.endswith(".zarr")}
        if d == root:
            skip.add(STAC_DIR)  # the catalog's own folder
        if "run.json" in filenames and (d / "reflectance.zarr").is_dir():
            out.append(d)
            skip |= SKIP_DIRS  # a flight's per-frame folders
        dirnames[:] = sorted(set(dirnames) - skip)
    return sorted(out)


def project_for(root: Path, flight: Path, level: int, root_name: str | None = None) -> tuple[Project, Path]:
    """The project of ``flight`` and its folder (module docstring); ``root_name`` names ROOT's
    own project instead of its folder name (a staged copy of a remote OUT)."""
    rel = flight.relative_to(root)
    for k in range(len(rel.parts), -1, -1):
        d = root.joinpath(*rel.parts[:k])
        if (d / PROJECT_FILE).is_file():
            return load_project(d / PROJECT_FILE), d
    k = min(level, len(rel.parts))
    d = root.joinpath(*rel.parts[:k])
    return Project(_clean_id(root_name if k == 0 and root_name else d.resolve().name)), d


def _item_id(project_dir: Path, flight: Path) -> str:
    parts = [p for p in flight.relative_to(project_dir).parts if p != "flights"]
    return "__".join(_clean_id(p) for p in parts) if parts else _clean_id(flight.resolve().name)


# --------------------------------------------------------------------------- one flight


def _session_out(flight: Path) -> Path | None:
    """The ``mscal run`` OUT of a flight at ``OUT/flights/<name>``, if it is one."""
    if flight.parent.name == "flights" and (flight.parent.parent / "run.json").is_file():
        return flight.parent.parent
    return None


def _tifs(flight: Path) -> list[Path]:
    out = []
    for p in sorted(flight.iterdir()):
        if p.is_file() and p.suffix.lower() in (".tif", ".tiff") and not p.name.startswith("."):
            out.append(p)
        elif p.is_dir() and p.name not in SKIP_DIRS and not p.name.endswith(".zarr") and not p.name.startswith("."):
            out += sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in (".tif", ".tiff")
                          and not q.name.startswith("."))
    return out


def _report(flight: Path) -> Path | None:
    for d in (flight, _session_out(flight)):
        if d is not None and (d / "report.html").is_file():
            return d / "report.html"
    return None


def _stat_key(p: Path) -> list[Any]:
    st = p.stat()
    return [p.name, st.st_size, st.st_mtime_ns]


def flight_fingerprint(flight: Path, project: Project) -> str:
    h = hashlib.sha256()
    session = _session_out(flight)
    parts: dict[str, Any] = {
        "format": ITEM_FORMAT, "project": [project.id, project.title, project.description, project.license],
        "run": hashlib.sha256((flight / "run.json").read_bytes()).hexdigest(),
        "session_run": hashlib.sha256((session / "run.json").read_bytes()).hexdigest() if session else None,
        "tifs": [[str(p.relative_to(flight)), *_stat_key(p)[1:]] for p in _tifs(flight)],
        "report": _stat_key(_report(flight)) if _report(flight) else None,
    }
    h.update(json.dumps(parts, sort_keys=True).encode())
    return h.hexdigest()


def _raster_info(path: Path) -> dict[str, Any] | None:
    """Kind, index name and WGS 84 footprint of a GeoTIFF; None if it has no CRS or cannot be read."""
    import rasterio
    from rasterio.errors import RasterioIOError
    from rasterio.warp import transform_geom

    from pipeline.ingest.catalog import list_entries

    try:
        with rasterio.open(path) as src:
            if src.crs is None or src.transform.is_identity:
                log.warning("%s: no CRS or geotransform; not catalogued as a raster", path)
                return None
            from pipeline.products.indexmap import alpha_bands

            alpha = alpha_bands(src)
            data = [b for b in range(1, src.count + 1) if b not in alpha]
            names = {n.lower() for n in list_entries("indices")}
            tag = str(src.tags().get("INDEX", "")).strip().lower()
            desc = str(src.descriptions[data[0] - 1] or "").strip().lower() if data else ""
            index = (tag if tag in names else desc if desc in names else None) if len(data) == 1 else None
            x0, y0, x1, y1 = src.bounds
            n = 21
            ring = ([(x0 + (x1 - x0) * i / (n - 1), y0) for i in range(n)]
                    + [(x1, y0 + (y1 - y0) * i / (n - 1)) for i in range(1, n)]
                    + [(x1 - (x1 - x0) * i / (n - 1), y1) for i in range(1, n)]
                    + [(x0, y1 - (y1 - y0) * i / (n - 1)) for i in range(1, n)])
            geom = transform_geom(src.crs, "EPSG:4326", {"type": "Polygon", "coordinates": [ring]})
            return {"kind": "index" if index else "orthomosaic", "index": index, "geometry": geom,
                    "cog": src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT", "").upper() == "COG" or bool(index)}
    except RasterioIOError as exc:
        log.warning("%s: not readable (%s); not catalogued", path, exc)
        return None


def _frame_coords(flight: Path, panels: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray, str | None]:
    """Latitude, longitude and time of the flight's frames and its camera. A position that is
    none is NaN: latitude and longitude 0 (no GPS fix, :mod:`pipeline.ingest.gps`), and the
    frames of ``panels`` (panel captures, taken on the ground before or after the flight: they
    do not widen its footprint) when any other frame has a position."""
    import xarray as xr

    try:
        ds = xr.open_zarr(flight / "reflectance.zarr", consolidated=False)
    except Exception as exc:  # zarr raises many kinds
        raise InputError(f"cannot open reflectance.zarr ({exc})", path=flight / "reflectance.zarr",
                         hint="re-run mscal apply on the flight, or remove the folder") from None
    with ds:
        lat = np.asarray(ds["lat"].values, float) if "lat" in ds.coords else np.empty(0)
        lon = np.asarray(ds["lon"].values, float) if "lon" in ds.coords else np.empty(0)
        t = np.asarray(ds["time"].values) if "time" in ds.coords else np.empty(0, "datetime64[ns]")
        names = [str(f) for f in ds["frame"].values] if "frame" in ds.coords else []
        camera = ds.attrs.get("camera")
    if lat.shape != lon.shape:  # one without the other: no positions
        return np.full(len(names), np.nan), np.full(len(names), np.nan), t, camera
    none = (lat == 0) & (lon == 0)
    lat, lon = np.where(none, np.nan, lat), np.where(none, np.nan, lon)
    if panels and len(names) == lat.size:
        panel = np.isin(names, list(panels))
        if (np.isfinite(lat) & np.isfinite(lon) & ~panel).any():
            lat, lon = np.where(panel, np.nan, lat), np.where(panel, np.nan, lon)
    return lat, lon, t, camera


def _rel(target: Path, item_file: Path) -> str:
    rel = os.path.relpath(target, item_file.parent).replace(os.sep, "/")
    return rel + "/" if target.is_dir() else rel


def _rel_inside(target: str | Path | None, root: Path | None, item_file: Path) -> str | None:
    """``target`` relative to ``item_file`` when it lies inside the catalog ``root``, else None:
    a catalog holds no host paths (a copied catalog would point nowhere)."""
    if not target or root is None:
        return None
    t = Path(str(target))
    if not t.is_absolute() or "://" in str(target):
        return None
    try:
        t.resolve().relative_to(root.resolve())
    except ValueError:
        return None
    return _rel(t, item_file)


def _camera_props(run: dict[str, Any], srun: dict[str, Any], name: str) -> dict[str, Any]:
    """``mscal:camera_make``/``_model``/``_serial`` as the files say (the flight's
    ``camera_identification``, else a card session's ``card``), and for a card session's flight
    the radiometry and light reference it got."""
    ident = dict(run_value(run, "camera_identification") or {})
    for key, value in (srun.get("card") or {}).items():
        if key in ("make", "model", "serial") and value and not ident.get(key):
            ident[key] = value
    props = {"mscal:camera_make": ident.get("make"), "mscal:camera_model": ident.get("model"),
             "mscal:camera_serial": ident.get("serial")}
    flight_rec = (srun.get("flights") or {}).get(name) or {}
    if flight_rec.get("calibration"):
        props["mscal:radiometry"] = flight_rec["calibration"]
        props["mscal:light_reference"] = (flight_rec.get("reference") or {}).get("route")
    return props


def flight_item(flight: Path, project: Project, project_dir: Path, item_file: Path, fingerprint: str,
                root: Path | None = None) -> Any:
    """The pystac Item of one flight folder (module docstring); asset hrefs relative to ``item_file``.

    Paths in properties (``mscal:calibration``, ``mscal:session``) are relative to the item
    file when they lie under the catalog ``root``, and left out otherwise (a calibration in a
    cache elsewhere is identified by ``mscal:calibration_sha256``). The footprint's outer rings
    run counterclockwise (RFC 7946)."""
    import pystac
    import shapely
    from shapely.geometry import MultiPoint, mapping, shape

    run = json.loads((flight / "run.json").read_text())
    session = _session_out(flight)
    srun = json.loads((session / "run.json").read_text()) if session else {}
    lat, lon, t, camera = _frame_coords(flight, [str(p.get("capture")) for p in run_value(run, "panels") or () if isinstance(p, dict)])
    rasters = {p: _raster_info(p) for p in _tifs(flight)}
    rasters = {p: r for p, r in rasters.items() if r is not None}
    if rasters:
        geom = shapely.unary_union([shape(r["geometry"]) for r in rasters.values()])
        source = "orthomosaic"
    else:
        ok = np.isfinite(lat) & np.isfinite(lon)
        geom = MultiPoint(np.column_stack([lon[ok], lat[ok]])).convex_hull if ok.any() else None
        source = "frame_gps" if geom is not None else "none"
    if geom is not None:
        geom = shapely.orient_polygons(geom, exterior_cw=False)
    tt = t[~np.isnat(t)] if t.size else t
    props: dict[str, Any] = {}
    if tt.size:
        t0 = datetime.fromisoformat(np.datetime_as_string(tt.min(), unit="s")).replace(tzinfo=timezone.utc)
        t1 = datetime.fromisoformat(np.datetime_as_string(tt.max(), unit="s")).replace(tzinfo=timezone.utc)
        time_source = "frames"
    else:
        t0 = t1 = datetime.fromtimestamp((flight / "run.json").stat().st_mtime, tz=timezone.utc).replace(microsecond=0)
        time_source = "processing"
    props["start_datetime"], props["end_datetime"] = pystac.utils.datetime_to_str(t0), pystac.utils.datetime_to_str(t1)
    camera = camera or run.get("camera")
    if camera:
        props["instruments"] = [str(camera)]
    props.update({
        "mscal:camera": camera, "mscal:time_source": time_source, "mscal:footprint_source": source,
        "mscal:frames_in": run.get("frames_in"), "mscal:frames_out": run.get("frames_out"),
        "mscal:frames_quarantined": len(run.get("quarantined") or []),
        "mscal:calibration": _rel_inside(run.get("calibration"), root, item_file),
        "mscal:calibration_sha256": run.get("calibration_sha256"),
        "mscal:version": (run.get("versions") or {}).get("mscal"), "mscal:fingerprint": fingerprint,
        "mscal:flight_dir": _rel(flight, item_file),
    })
    props.update(_camera_props(run, srun, flight.name))
    if srun:
        props["mscal:calibration_cached"] = srun.get("calibration_cached")
        props["mscal:calibration_stages"] = {k: (v or {}).get("key") for k, v in (srun.get("calibration_stages") or {}).items()}
        props["mscal:session"] = _rel_inside(srun.get("session"), root, item_file)
    props = {k: v for k, v in props.items() if v is not None}
    item = pystac.Item(
        id=_item_id(project_dir, flight),
        geometry=mapping(geom) if geom is not None else None,
        bbox=list(geom.bounds) if geom is not None else None,
        datetime=t0 if t0 == t1 else None,
        start_datetime=t0 if t0 != t1 else None, end_datetime=t1 if t0 != t1 else None,
        properties=props,
    )
    if t0 == t1:  # one instant: datetime carries it, start/end would only repeat it
        item.properties.pop("start_datetime", None)
        item.properties.pop("end_datetime", None)
    item.set_self_href(str(item_file))

    def add(key: str, target: Path, media: str | None, roles: list[str], title: str, **extra: Any) -> None:
        item.add_asset(key, pystac.Asset(_rel(target, item_file), title=title, media_type=media, roles=roles,
                                         extra_fields=extra))

    add("reflectance", flight / "reflectance.zarr", MEDIA_ZARR, ["data"], "reflectance, NDVI, NDRE per frame (Eq. 15)")
    add("run", flight / "run.json", "application/json", ["metadata"], "run record of the flight")
    if (flight / "photogrammetry").is_dir():
        add("photogrammetry", flight / "photogrammetry", None, ["data"],
            "per-frame reflectance TIFFs for photogrammetry (folder)")
    if (flight / "ndvi").is_dir():
        add("ndvi_frames", flight / "ndvi", None, ["data"], "per-frame NDVI TIFFs (folder)")
    rep = _report(flight)
    if rep is not None:
        add("report", rep, "text/html", ["overview"], "QA report")
    if session is not None and (session / "calibration.zarr").is_dir():
        add("calibration", session / "calibration.zarr", MEDIA_ZARR, ["metadata"], "calibration store of the session")
    for p, r in rasters.items():
        base = f"index_{r['index']}" if r["index"] else "orthomosaic"
        key, n = base, 2
        while key in item.assets:
            key, n = f"{base}_{n}", n + 1
        extra = {"mscal:kind": r["kind"]}
        if r["index"]:
            extra["mscal:index"] = r["index"]
        add(key, p, MEDIA_COG if r["cog"] else MEDIA_GEOTIFF, ["data"],
            f"{r['index'].upper()} map" if r["index"] else "reflectance orthomosaic", **extra)
    return item


# --------------------------------------------------------------------------- validation


def _offline_validator_class() -> type:
    import jsonschema
    import pystac.utils
    from pystac.errors import STACValidationError
    from pystac.validation import GetSchemaError, STACValidator
    from pystac.validation.local_validator import get_local_schema_cache
    from pystac.validation.schema_uri_map import DefaultSchemaUriMap
    from referencing import Registry, Resource
    from referencing.exceptions import Unresolvable

    def refuse(uri: str) -> Any:
        raise GetSchemaError(uri, LookupError(f"schema {uri} is not shipped with pystac and mscal never downloads one"))

    class _Offline(STACValidator):
        """pystac's validator interface (:class:`pystac.validation.STACValidator`) over the
        schemas pystac ships (``get_local_schema_cache``), looked up by pystac's own
        ``DefaultSchemaUriMap``: a schema that is not among them, or that one of them refers
        to, raises :class:`pystac.validation.GetSchemaError` instead of being read from its
        URL. Nothing reads a URL here (no ``StacIO``)."""

        def __init__(self) -> None:
            self.schema_uri_map = DefaultSchemaUriMap()
            self.schemas = get_local_schema_cache()
            self.registry = Registry(retrieve=refuse).with_resources(  # type: ignore[call-arg]
                (uri, Resource.from_contents(schema)) for uri, schema in self.schemas.items())

        def _check(self, stac_dict: dict[str, Any], object_type: Any, uri: str, href: str | None) -> str:
            schema = self.schemas.get(uri) or refuse(uri)
            check = jsonschema.validators.validator_for(schema)(schema, registry=self.registry)
            try:
                errors = list(check.iter_errors(stac_dict))
            except Unresolvable as exc:  # a $ref to a schema that is not shipped
                raise GetSchemaError(getattr(exc, "ref", uri), exc) from None
            if errors:
                best = jsonschema.exceptions.best_match(errors)
                raise STACValidationError(f"Validation failed for {object_type} at {href} against schema at {uri}"
                                          f"\n{best}", source=errors) from best
            return uri

        def validate_core(self, stac_dict: dict[str, Any], stac_object_type: Any, stac_version: str,
                          href: str | None = None) -> str | None:
            uri = self.schema_uri_map.get_object_schema_uri(stac_object_type, stac_version)
            return None if uri is None else self._check(stac_dict, stac_object_type, uri, href)

        def validate_extension(self, stac_dict: dict[str, Any], stac_object_type: Any, stac_version: str,
                               extension_id: str, href: str | None = None) -> str:
            uri = pystac.utils.make_absolute_href(extension_id, href)
            return self._check(stac_dict, stac_object_type, uri, href)

    return _Offline


def OfflineValidator() -> Any:  # a factory named as the class it returns
    """A pystac ``STACValidator`` that never touches the network (module docstring)."""
    return _offline_validator_class()()


def _validate(d: dict[str, Any], href: Path, validator: Any) -> None:
    import pystac.validation
    from pystac.errors import STACValidationError
    from pystac.validation import GetSchemaError

    try:
        pystac.validation.validate_dict(d, href=str(href), validator=validator)
    except STACValidationError as exc:
        first = str(exc).splitlines()
        raise InputError(f"not valid STAC: {' '.join(first[1:2] or first[:1])}", path=href,
                         hint="rebuild it with mscal catalog ROOT") from None
    except GetSchemaError as exc:
        raise InputError(f"cannot be validated offline ({exc})", path=href,
                         hint="use core STAC fields only, or ship the extension's schema") from None


def validate_catalog(catalog: str | Path) -> int:
    """Validate ``catalog.json`` and every child and item it links to (relative links), offline.
    Returns the number of objects validated; :class:`InputError` naming the first invalid file."""
    catalog = Path(catalog)
    if catalog.is_dir():
        catalog = catalog / CATALOG_FILE
    validator = OfflineValidator()
    todo, seen = [catalog], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read a STAC object ({exc})", path=p) from None
        _validate(d, p, validator)
        for link in d.get("links", []):
            if link.get("rel") in ("child", "item"):
                todo.append((p.parent / link["href"]).resolve())
    return len(seen)


# --------------------------------------------------------------------------- the catalog


def _locked(root: Path) -> FolderLock:
    """The catalog's lock: updates of one ROOT wait for each other (however long), apart from
    the output folders' own locks (a run updates the catalog of the OUT it holds)."""
    return FolderLock(root, name=LOCK_FILE, wait=True, what="another mscal process updating the catalog")


def _write_json(path: Path, d: dict[str, Any]) -> bool:
    """Write ``d`` atomically unless ``path`` already holds exactly it (an update with nothing
    changed leaves every file, and its mtime, as it was). True when written."""
    text = json.dumps(d, indent=2, sort_keys=False) + "\n"
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return False
    write_text_atomic(path, text)
    return True


def update_catalog(root: str | Path, *, project_level: int | None = None, validate: bool = True,
                   root_name: str | None = None) -> dict[str, Any]:
    """Build or update ``ROOT/catalog.json`` and its collections and items (module docstring).
    ``root_name``: the name of ROOT's own project and of the catalog, when ROOT's folder name
    is not it (the flow's staged copy of a remote OUT).

    Returns ``{"catalog": path, "items": n, "added": [...], "updated": [...], "unchanged": n,
    "removed": [...], "collections": [...]}`` (item ids as ``<collection>/<item>``)."""
    import pystac

    root = Path(root)
    if not root.is_dir():
        raise InputError("output root not found", path=root, hint="give the folder that holds mscal's outputs")
    with _locked(root):
        cat_path = root / CATALOG_FILE
        old_cat = json.loads(cat_path.read_text()) if cat_path.is_file() else {}
        if project_level is None:
            project_level = int(old_cat.get("mscal:project_level", 0))
        if project_level < 0:
            raise InputError(f"--project-level {project_level} must be 0 or more")
        stac_dir = root / STAC_DIR
        flights = find_flights(root)
        groups: dict[str, tuple[Project, list[Any]]] = {}
        summary: dict[str, Any] = {"added": [], "updated": [], "unchanged": 0, "removed": []}
        written: set[Path] = set()
        item_ids: dict[tuple[str, str], Path] = {}
        for flight in flights:
            project, pdir = project_for(root, flight, project_level, root_name)
            iid = _item_id(pdir, flight)
            if (project.id, iid) in item_ids:
                raise InputError(f"flights {item_ids[(project.id, iid)]} and {flight} would both be item {iid!r} "
                                 f"of collection {project.id!r}", path=flight,
                                 hint="rename one of the folders, or give its project an mscal-project.yaml")
            item_ids[(project.id, iid)] = flight
            item_file = stac_dir / project.id / "items" / f"{iid}.json"
            fp = flight_fingerprint(flight, project)
            old = json.loads(item_file.read_text()) if item_file.is_file() else None
            key = f"{project.id}/{iid}"
            if old is not None and old.get("properties", {}).get("mscal:fingerprint") == fp:
                item = pystac.Item.from_dict(old, preserve_dict=False)
                item.set_self_href(str(item_file))
                summary["unchanged"] += 1
            else:
                item = flight_item(flight, project, pdir, item_file, fp, root)
                summary["updated" if old is not None else "added"].append(key)
            if groups.get(project.id, (project,))[0] != project:
                raise InputError(f"two different projects are both named {project.id!r}", path=flight,
                                 hint=f"give each its own id in {PROJECT_FILE}")
            groups.setdefault(project.id, (project, []))[1].append(item)
        name = root_name or root.resolve().name
        catalog = pystac.Catalog(id="mscal", description=f"Calibrated products of mscal under {name}",
                                 title=f"mscal: {name}",
                                 extra_fields={"mscal:project_level": project_level},
                                 catalog_type=pystac.CatalogType.SELF_CONTAINED)
        catalog.set_self_href(str(cat_path))
        for pid, (project, items) in sorted(groups.items()):
            coll = pystac.Collection(
                id=pid, description=project.description or f"Flights of {pid} calibrated by mscal",
                title=project.title, license=project.license, keywords=list(project.keywords) or None,
                extent=_extent(items),
            )
            catalog.add_child(coll)
            coll.set_self_href(str(stac_dir / pid / "collection.json"))
            for item in sorted(items, key=lambda i: i.id):
                href = item.get_self_href()
                coll.add_item(item)
                item.set_self_href(href)
        validator = OfflineValidator() if validate else None
        objs = [catalog, *catalog.get_children(), *catalog.get_items(recursive=True)]
        for obj in objs:
            p = Path(obj.get_self_href())
            d = obj.to_dict(include_self_link=False, transform_hrefs=True)
            if validator is not None:
                _validate(d, p, validator)
            _write_json(p, d)
            written.add(p.resolve())
        if stac_dir.is_dir():  # items of flights that are gone, collections left empty
            for p in sorted(stac_dir.rglob("*.json")):
                if p.resolve() not in written:
                    summary["removed"].append(str(p.relative_to(stac_dir).with_suffix("")).replace("/items/", "/"))
                    p.unlink()
            for d in sorted((q for q in stac_dir.rglob("*") if q.is_dir()), key=lambda q: -len(q.parts)):
                if not any(d.iterdir()):
                    d.rmdir()
        summary.update({"catalog": str(cat_path), "items": sum(len(v[1]) for v in groups.values()),
                        "collections": sorted(groups), "project_level": project_level})
        return summary


def _extent(items: list[Any]) -> Any:
    import pystac

    boxes = [i.bbox for i in items if i.bbox]
    if boxes:
        b = np.array(boxes, float)
        bbox = [float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())]
    else:
        bbox = [-180.0, -90.0, 180.0, 90.0]
    times = []
    for i in items:  # a fresh Item keeps a single datetime as .datetime, outside its properties
        times += [t for t in (i.datetime, i.common_metadata.start_datetime, i.common_metadata.end_datetime) if t]
    span = [min(times), max(times)] if times else [None, None]
    return pystac.Extent(pystac.SpatialExtent([bbox]), pystac.TemporalExtent([span]))


def catalog_rasters(catalog: str | Path, index_name: str, skipped: list[str] | None = None) -> list[dict[str, Any]]:
    """Per item of ``catalog`` (a catalog.json or its folder): the index map of ``index_name``
    if it has one, else its orthomosaic; ``{"path", "item", "collection", "date"}``. Items
    with neither are left out, their ``<collection>/<item>`` appended to ``skipped``."""
    catalog = Path(catalog)
    if catalog.is_dir():
        catalog = catalog / CATALOG_FILE
    if not catalog.is_file():
        raise InputError("STAC catalog not found", path=catalog, hint="build it with mscal catalog ROOT")
    out = []
    todo = [catalog]
    while todo:
        p = todo.pop(0)
        d = json.loads(p.read_text(encoding="utf-8"))
        for link in d.get("links", []):
            if link.get("rel") in ("child", "item"):
                todo.append((p.parent / link["href"]).resolve())
        if d.get("type") != "Feature":
            continue
        assets = d.get("assets", {})
        pick = next((a for a in assets.values() if a.get("mscal:kind") == "index"
                     and str(a.get("mscal:index", "")).lower() == index_name.lower()), None)
        pick = pick or next((a for a in assets.values() if a.get("mscal:kind") == "orthomosaic"), None)
        if pick is None:
            log.info("%s: item %s has no orthomosaic or %s map", p, d.get("id"), index_name)
            if skipped is not None:
                skipped.append(f"{d.get('collection', '')}/{d.get('id')}")
            continue
        props = d.get("properties", {})
        when = props.get("datetime") or props.get("start_datetime")
        if props.get("mscal:time_source") == "processing":
            when = None  # the day it was processed is not the day it was flown
        day = parse_iso(when).date() if when else None
        out.append({"path": str((p.parent / pick["href"]).resolve()), "item": d.get("id"),
                    "collection": d.get("collection", ""), "date": day})
    return out
