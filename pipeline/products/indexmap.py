"""``mscal index ORTHO.tif --index ndvi -o ndvi.tif``: index maps of reflectance orthomosaics.

Reads a multi-band reflectance orthomosaic (a GeoTIFF from OpenDroneMap, Pix4D, Metashape or
``mscal``'s own per-frame TIFFs mosaicked: float32 reflectance, or integers holding
reflectance x 32768), finds the bands of the index's roles (``red``, ``nir``, ``rededge``, ...),
evaluates the index block by block (memory does not grow with the mosaic) and writes a Cloud
Optimized GeoTIFF: float32, NaN where any input is nodata, CRS and transform of the input,
band description = index name, overviews, DEFLATE.

Which band is which role, in this order:

1. ``bands={"red": 3, "nir": 5}`` (``--bands red=3,nir=5``), 1-based band numbers;
2. a band description naming the role (case, spaces, ``_`` and ``-`` ignored): ``Red``,
   ``NIR``, ``Near infrared``, ``Red edge`` / ``RedEdge`` / ``RE``, ``Green``, ``Blue``, ``R``/``G``/``B``;
   OpenDroneMap's ``odm_orthophoto`` writes the photos' band names (``Camera:BandName`` made
   alphanumeric, e.g. ``Rededge``, or ``b670`` for ``mscal``'s TIFFs) as band descriptions,
   then one alpha band;
3. a wavelength, from the description (``670``, ``b670``, ``670nm``, ``NIR 840``) or from band
   metadata (``CENTRAL_WAVELENGTH_UM`` in GDAL's ``IMAGERY`` domain, or a ``wavelength`` /
   ``central_wavelength`` item, in nm, or in micrometres when below 10 or marked so): the band
   closest to the role's nominal wavelength inside the role's window (:data:`ROLE_WAVELENGTHS`),
   e.g. red 670 nm and NIR 803 nm on the paper's 25-band Ximea camera.

A role that cannot be matched is an :class:`InputError` naming the file and listing its band
descriptions. An alpha band (ODM orthophotos end with one) is never a role; its zeros, the
file's nodata value, its internal mask and NaN all make the output NaN.

Scaling: with ``scale=None`` (default) each band's GDAL scale/offset is applied when set;
otherwise integer data is divided by 32768 (``mscal``'s uint16 convention, see
``pipeline.products.writers``) and float data is taken as reflectance. Normalised differences such as
NDVI do not depend on the scale; indices with constants do.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
from mscal_core.errors import InputError

from pipeline.ingest.catalog import Index, load_index
from pipeline.products.writers import REFLECTANCE_SCALE
from pipeline.storage.atomic import atomic_path

__all__ = [
    "ROLE_ALIASES", "ROLE_WAVELENGTHS", "alpha_bands", "band_scales", "evaluate_window", "index_map", "parse_bands_option",
    "resolve_bands",
]

# role -> (window low nm, window high nm, nominal nm); windows do not overlap.
ROLE_WAVELENGTHS: dict[str, tuple[float, float, float]] = {
    "blue": (400.0, 500.0, 475.0),
    "green": (500.0, 600.0, 560.0),
    "red": (600.0, 690.0, 668.0),
    "rededge": (690.0, 760.0, 717.0),
    "nir": (760.0, 1000.0, 800.0),
}
# role -> band descriptions that name it, normalised (lower case, letters and digits only).
ROLE_ALIASES: dict[str, frozenset[str]] = {
    "blue": frozenset({"blue", "blu", "b"}),  # r, g, b: as odm_orthophoto's -bands reads them
    "green": frozenset({"green", "grn", "g"}),
    "red": frozenset({"red", "r"}),
    "rededge": frozenset({"rededge", "re", "edge"}),
    "nir": frozenset({"nir", "nearinfrared", "nearir", "infrared"}),
}

_WAVELENGTH_IN_TEXT = re.compile(
    r"^\s*(?:[A-Za-z][A-Za-z ]*?)?\s*[_\- ]?\s*(\d{3,4}(?:\.\d+)?)\s*(?:nm)?\s*$", re.IGNORECASE
)
_WAVELENGTH_KEYS = ("central_wavelength", "centralwavelength", "center_wavelength", "wavelength", "wavelength_nm")
_MICRON_UNITS = {"um", "µm", "micrometer", "micrometers", "micrometre", "micrometres", "micron", "microns"}
_BLOCK_BIG = 512
_BLOCK_SMALL = 256
_WINDOW_H = 1024  # pixels per processing window (rounded to whole blocks): ~2 Mpixel, memory flat
_WINDOW_W = 2048


def _norm(text: str) -> str:
    return re.sub(r"[^a-z0-9]", "", text.lower())


def parse_bands_option(text: str) -> dict[str, int]:
    """``"red=3,nir=5"`` -> ``{"red": 3, "nir": 5}``; :class:`InputError` if malformed."""
    out: dict[str, int] = {}
    for item in text.split(","):
        if not item.strip():
            continue
        role, sep, num = item.partition("=")
        try:
            if not sep or not role.strip():
                raise ValueError
            out[role.strip().lower()] = int(num)
        except ValueError:
            raise InputError(f"--bands {text!r} is not ROLE=NUMBER,...", hint="e.g. --bands red=3,nir=5") from None
    return out


def _band_wavelength(ds, b: int) -> float | None:
    """Centre wavelength (nm) of band ``b`` from its metadata or description, if any."""
    tags_img = {k.upper(): v for k, v in ds.tags(b, ns="IMAGERY").items()}
    if "CENTRAL_WAVELENGTH_UM" in tags_img:
        try:
            return float(tags_img["CENTRAL_WAVELENGTH_UM"]) * 1000.0
        except ValueError:
            pass
    tags = {k.lower(): v for k, v in ds.tags(b).items()}
    units = str(tags.get("wavelength_units", tags.get("wavelength_unit", ""))).strip().lower()
    for key in _WAVELENGTH_KEYS:
        if key in tags:
            m = re.match(r"^\s*([0-9]*\.?[0-9]+)\s*([a-zµ]*)\s*$", str(tags[key]), re.IGNORECASE)
            if not m:
                continue
            v = float(m.group(1))
            unit = (m.group(2) or units).lower()
            if unit in _MICRON_UNITS or (not unit and v < 10):
                v *= 1000.0
            if v > 0:
                return v
    desc = ds.descriptions[b - 1] or ""
    m = _WAVELENGTH_IN_TEXT.match(desc)
    if m:
        return float(m.group(1))
    return None


def alpha_bands(ds) -> list[int]:
    """1-based numbers of the alpha (mask) bands of the open rasterio dataset ``ds``."""
    from rasterio.enums import ColorInterp

    return [i + 1 for i, ci in enumerate(ds.colorinterp) if ci == ColorInterp.alpha]


def _describe_bands(ds) -> str:
    parts = []
    for b in range(1, ds.count + 1):
        desc = ds.descriptions[b - 1]
        wl = _band_wavelength(ds, b)
        extra = f" ({wl:g} nm)" if wl is not None and not (desc and re.search(r"\d", desc)) else ""
        alpha = " (alpha)" if b in alpha_bands(ds) else ""
        parts.append(f"{b}={desc!r}{extra}{alpha}" if desc else f"{b}=(none){extra}{alpha}")
    return ", ".join(parts)


def resolve_bands(ds, roles: tuple[str, ...] | list[str], bands: Mapping[str, int] | None = None,
                  *, path: str | Path | None = None) -> dict[str, int]:
    """Map each role to a 1-based band number of the open rasterio dataset ``ds``."""
    path = path if path is not None else ds.name
    given = {str(k).strip().lower(): v for k, v in (bands or {}).items()}
    unknown = sorted(set(given) - set(roles))
    if unknown:
        raise InputError(
            f"--bands names {', '.join(unknown)}, which the index does not use",
            path=path, hint=f"the index uses {', '.join(roles)}",
        )
    alpha = set(alpha_bands(ds))
    candidates = [b for b in range(1, ds.count + 1) if b not in alpha]
    out: dict[str, int] = {}
    for role in roles:
        if role in given:
            b = given[role]
            if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 1 <= int(b) <= ds.count:
                raise InputError(
                    f"--bands {role}={b!r}: the file has bands 1..{ds.count}",
                    path=path, hint=f"its bands: {_describe_bands(ds)}",
                )
            out[role] = int(b)
            continue
        aliases = ROLE_ALIASES.get(role, frozenset()) | {_norm(role)}
        named = [b for b in candidates if _norm(ds.descriptions[b - 1] or "") in aliases]
        if len(named) > 1:
            raise InputError(
                f"bands {', '.join(map(str, named))} all look like {role!r}",
                path=path, hint=f"choose one with --bands {role}=N; its bands: {_describe_bands(ds)}",
            )
        if named:
            out[role] = named[0]
            continue
        if role in ROLE_WAVELENGTHS:
            lo, hi, nominal = ROLE_WAVELENGTHS[role]
            best: tuple[float, int] | None = None
            for b in candidates:
                wl = _band_wavelength(ds, b)
                if wl is not None and lo <= wl < hi and (best is None or abs(wl - nominal) < best[0]):
                    best = (abs(wl - nominal), b)
            if best is not None:
                out[role] = best[1]
                continue
        window = ""
        if role in ROLE_WAVELENGTHS:
            lo, hi, _ = ROLE_WAVELENGTHS[role]
            window = f" or a wavelength in {lo:g}-{hi:g} nm"
        raise InputError(
            f"cannot tell which band is {role!r}: no band description names it{window}; "
            f"band descriptions: {_describe_bands(ds)}",
            path=path,
            hint=f"give the band numbers, e.g. --bands {','.join(f'{r}=N' for r in roles)}",
        )
    auto = [r for r in roles if r not in given]
    seen: dict[int, str] = {}
    for r in auto:
        if out[r] in seen:
            raise InputError(
                f"roles {seen[out[r]]!r} and {r!r} both matched band {out[r]}",
                path=path, hint=f"give the band numbers with --bands; its bands: {_describe_bands(ds)}",
            )
        seen[out[r]] = r
    return out


def band_scales(ds, numbers: list[int], scale: float | None) -> dict[int, tuple[float, float]]:
    """``{band: (scale, offset)}`` that turn stored values of ``numbers`` into reflectance
    (``scale`` given: that scale, offset 0)."""
    out = {}
    for b in numbers:
        if scale is not None:
            out[b] = (float(scale), 0.0)
            continue
        s, o = ds.scales[b - 1], ds.offsets[b - 1]
        if (s is not None and s != 1.0) or (o is not None and o != 0.0):
            out[b] = (float(s if s is not None else 1.0), float(o or 0.0))
        elif np.issubdtype(np.dtype(ds.dtypes[b - 1]), np.integer):
            out[b] = (1.0 / REFLECTANCE_SCALE, 0.0)
        else:
            out[b] = (1.0, 0.0)
    return out


def _windows(height: int, width: int, block: int):
    """Block-aligned windows of at most ~2 Mpixel, row-major."""
    from rasterio.windows import Window

    win_h = block * max(1, _WINDOW_H // block)
    win_w = block * max(1, _WINDOW_W // block)
    for r in range(0, height, win_h):
        for c in range(0, width, win_w):
            yield Window(c, r, min(win_w, width - c), min(win_h, height - r))


def _no_georeferencing_warning(f: Callable[..., Any]) -> Callable[..., Any]:
    """Run ``f`` without rasterio's NotGeoreferencedWarning: an orthomosaic without a
    geotransform gives an index map without one, which :func:`georeferenced` tells the caller
    (``mscal index`` says it once, in its summary)."""
    import functools

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from rasterio.errors import NotGeoreferencedWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return f(*args, **kwargs)

    return wrapper


@_no_georeferencing_warning
def georeferenced(path: str | Path) -> bool:
    """Whether a raster has a CRS and a geotransform (or GCPs)."""
    import rasterio

    with rasterio.open(path) as src:
        return src.crs is not None and (not src.transform.is_identity or bool(src.gcps[0]))


@_no_georeferencing_warning
def index_map(
    ortho_path: str | Path, index_name: str, out_path: str | Path, *, bands: Mapping[str, int] | None = None,
    scale: float | None = None,
) -> Path:
    """Write the index ``index_name`` of the orthomosaic ``ortho_path`` as a COG at ``out_path``.

    ``bands`` maps roles to 1-based band numbers (the rest are found from the file's band
    descriptions / wavelengths). ``scale`` multiplies every input band (default: GDAL scale
    metadata, else 1/32768 for integer data, 1 for float data). Returns ``out_path``.
    """
    import rasterio
    import rasterio.shutil
    from rasterio.errors import RasterioIOError

    ortho_path, out_path = Path(ortho_path), Path(out_path)
    index: Index = load_index(index_name)
    if not ortho_path.is_file():
        raise InputError("orthomosaic not found", path=ortho_path)
    if out_path.resolve() == ortho_path.resolve():
        raise InputError("the output would overwrite the orthomosaic", path=out_path, hint="choose another -o")
    try:
        src = rasterio.open(ortho_path)
    except RasterioIOError as exc:
        raise InputError(f"not a raster GDAL can read ({exc})", path=ortho_path) from None
    with src:
        roles = tuple(index.inputs)
        mapping = resolve_bands(src, roles, bands, path=ortho_path)
        numbers = sorted(set(mapping.values()))
        scales = band_scales(src, numbers, scale)
        alpha = alpha_bands(src)
        h, w = src.height, src.width
        block = _BLOCK_BIG if max(h, w) >= 4096 else _BLOCK_SMALL
        profile = {
            "driver": "GTiff", "height": h, "width": w, "count": 1, "dtype": "float32",
            "nodata": float("nan"), "tiled": True, "blockxsize": block, "blockysize": block,
            "compress": "deflate", "zlevel": 1, "predictor": 3, "bigtiff": "if_safer",
        }
        if src.crs is not None:
            profile["crs"] = src.crs
        if src.transform is not None and not src.transform.is_identity:
            profile["transform"] = src.transform
        elif src.gcps[0]:
            profile["gcps"], profile["crs"] = src.gcps[0], src.gcps[1]
        tags = {
            "INDEX": index.name,
            "INDEX_DESCRIPTION": index.description,
            "EXPRESSION": index.expression,
            "BANDS": ",".join(f"{r}={mapping[r]}" for r in roles),
            "SOURCE": ortho_path.name,
        }
        with atomic_path(out_path, durable=True) as tmp_cog:
            stage = tmp_cog.with_name(tmp_cog.name + ".stage.tif")
            try:
                with rasterio.open(stage, "w", **profile) as dst:
                    dst.set_band_description(1, index.name)
                    dst.update_tags(**tags)
                    for win in _windows(h, w, block):
                        dst.write(evaluate_window(src, index, mapping, numbers, scales, alpha, win), 1, window=win)
                rasterio.shutil.copy(
                    stage, tmp_cog, driver="COG", BLOCKSIZE=block, COMPRESS="DEFLATE", PREDICTOR="YES",
                    OVERVIEWS="AUTO", RESAMPLING="AVERAGE", BIGTIFF="IF_SAFER",
                )
            finally:
                for f in (stage, stage.with_name(stage.name + ".aux.xml"), stage.with_name(stage.name + ".ovr")):
                    f.unlink(missing_ok=True)
    return out_path


def evaluate_window(src, index: Index, mapping: dict[str, int], numbers: list[int],
                     scales: dict[int, tuple[float, float]], alpha: list[int], win) -> np.ndarray:
    """The index over one window of ``src`` (float32), NaN where a band is masked or an
    alpha band is 0 (what ``mscal index`` writes and ``mscal stats`` reads)."""
    data = src.read(numbers, window=win, out_dtype="float32", masked=False)
    valid = np.ones(data.shape[1:], dtype=bool)
    arrays: dict[int, np.ndarray] = {}
    for k, b in enumerate(numbers):
        valid &= src.read_masks(b, window=win) > 0
        s, o = scales[b]
        arr = data[k]
        if s != 1.0 or o != 0.0:
            arr = arr * np.float32(s) + np.float32(o)
        arrays[b] = arr
    for a in alpha:
        valid &= src.read(a, window=win) != 0
    out = index.evaluate({r: arrays[mapping[r]] for r in mapping})
    out = np.asarray(out, dtype=np.float32)
    out[~valid] = np.nan
    return out
