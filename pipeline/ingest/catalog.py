"""Catalogs: cameras, reflectance targets and indices as YAML data.

Each file is read with ``yaml.safe_load`` and validated by a pydantic model (unknown keys
refused, :mod:`pipeline.ingest.schema`), then built into frozen dataclasses; a problem is one
line naming the file, the key and how to fix it (the keys that are allowed). The catalog folder
is the ``catalogs`` package (``catalogs/`` at the top of the project, installed with mscal as
package data and found with ``importlib.resources``), after the folders listed in
``MSCAL_CATALOG_PATH`` (``os.pathsep``-separated), which are searched first.

Parsed entries are cached on the file's path, modification time and size: a long-running
process (``mscal serve``) sees an edited or added catalog file at its next use.
"""

from __future__ import annotations

import ast
import importlib.resources
import os
import re
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from types import CodeType
from typing import Annotated, Any, Literal, Mapping

import numpy as np
import yaml
from mscal_core.errors import CatalogError, MscalError
from mscal_core.reflectance import keep_valid
from pydantic import AfterValidator, Field

from pipeline.ingest.meta import sample_shift
from pipeline.ingest.schema import (
    MAX_PIXELS,
    PositiveNumber,
    Problem,
    Strict,
    Text,
    check,
    finite_number,
    integer,
    is_int,
    is_number,
    items,
    one_of,
    pair,
    show_key,
    validate,
)

#: The catalogs shipped with mscal (the ``catalogs`` package's folder).
CATALOG_ROOT = Path(str(importlib.resources.files("catalogs")))


def catalog_dirs(kind: str, search_path: str | None = None) -> list[Path]:
    """Folders searched for entries of ``kind``: ``<folder>/<kind>`` for each folder of ``search_path`` (os.pathsep-
    separated; None: ``$MSCAL_CATALOG_PATH``, read at each search), then the shipped catalogs'."""
    path = os.environ.get("MSCAL_CATALOG_PATH", "") if search_path is None else search_path
    return [*(Path(p) / kind for p in path.split(os.pathsep) if p), CATALOG_ROOT / kind]


# --------------------------------------------------------------------------- reading YAML


def yaml_problem(exc: yaml.YAMLError) -> str:
    """One line saying where a YAML file is broken. The parser notices a problem where it can
    no longer go on (often the line after the mistake: an unclosed bracket is found at the next
    key), so the line where the construct it was reading began is named first."""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    pmark, cmark = getattr(exc, "problem_mark", None), getattr(exc, "context_mark", None)
    if cmark is not None and pmark is not None and (cmark.line, cmark.column) != (pmark.line, pmark.column):
        ctx = getattr(exc, "context", None) or "reading"
        return (f"not valid YAML at line {cmark.line + 1}, column {cmark.column + 1} ({ctx}): {problem} "
                f"at line {pmark.line + 1}, column {pmark.column + 1}")
    if pmark is not None:
        return f"not valid YAML at line {pmark.line + 1}, column {pmark.column + 1}: {problem}"
    return f"not valid YAML: {problem}"


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (PyYAML keeps the
    last one silently: which of two values was meant is anybody's guess)."""


def _map_without_duplicates(loader: _StrictLoader, node: yaml.MappingNode) -> Any:
    data: dict[Any, Any] = {}
    yield data
    seen: list[Any] = []
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in seen
        except TypeError:  # an unhashable key: construct_mapping says so below
            duplicate = False
        if duplicate:
            raise yaml.constructor.ConstructorError("while constructing a mapping", node.start_mark,
                                                    f"found the key {key!r} twice", key_node.start_mark)
        seen.append(key)
    data.update(loader.construct_mapping(node))


_StrictLoader.add_constructor("tag:yaml.org,2002:map", _map_without_duplicates)


def read_yaml(path: Path, error: type[MscalError] = CatalogError) -> Any:
    """``yaml.safe_load`` of ``path`` (a key given twice is an error); ``error`` naming the
    file and the line if it cannot be read or parsed (see :func:`yaml_problem`)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read: {getattr(exc, 'strerror', None) or exc}", path=path) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader
    except yaml.YAMLError as exc:
        raise error(yaml_problem(exc), path=path, hint="fix the YAML syntax") from None
    except RecursionError:
        raise error("not valid YAML: nested too deeply", path=path, hint="fix the YAML syntax") from None
    except (ValueError, OverflowError, TypeError) as exc:  # e.g. a date that does not exist: 2017-13-45
        raise error(f"not valid YAML: a value cannot be read ({exc})", path=path,
                    hint="quote a text that looks like a date or a number") from None


MAX_CHANNELS = 1024  # no sensor, mosaic or band grid is larger: a bigger number is a typo
Pair = pair()  # (row, column), (rows, columns): integers 0..MAX_PIXELS
_Strings = items(lambda v: isinstance(v, str), "a list of strings")


# --------------------------------------------------------------------------- cameras


@dataclass(frozen=True)
class Band:
    """One spectral band of a camera."""

    name: str
    wavelength_nm: float
    fwhm_nm: float | None = None
    mosaic: tuple[int, int] | None = None  # (row, column) in the filter mosaic
    channel: int | None = None  # channel index of a multi-channel image
    file_suffix: str | None = None  # band id in one-file-per-band captures


@dataclass(frozen=True)
class Layout:
    """How bands are laid out in the files a camera writes."""

    kind: str  # mosaic | multichannel | file_per_band | file_per_capture | folder_per_band
    pattern: tuple[int, int] | None = None
    origin: tuple[int, int] = (0, 0)
    grid: tuple[int, int] | None = None  # band grid (rows, columns)
    channels: int | None = None
    capture_pattern: str | None = None


@dataclass(frozen=True)
class SkipBand:
    """A band a camera writes that is read but kept out of reflectance (a panchromatic band at
    another resolution, a thermal band), and why."""

    name: str
    file_suffix: str | None  # None: a folder_per_band camera's band, known by its XMP BandName
    reason: str


@dataclass(frozen=True)
class Identify:
    """How a camera is recognised from its files (EXIF Make/Model, XMP Camera:RigName, the
    number of bands one capture holds). ``models``/``rig_names`` empty: any."""

    make: str
    models: tuple[str, ...] = ()
    rig_names: tuple[str, ...] = ()
    bands_per_capture: int | None = None  # every band file of one capture id, skipped ones included


@dataclass(frozen=True)
class CameraExif:
    """``exif: {make, model, pixel_um}``: the EXIF ``Make`` and ``Model`` of a camera whose
    frames carry no EXIF of their own (a snapshot mosaic camera's frames), and its sensor's
    pixel pitch in micrometres (the band grid's pitch is that times the mosaic pattern), from
    which per-frame TIFFs get their focal length in mm and focal plane resolution."""

    make: str
    model: str
    pixel_um: float | None = None


@dataclass(frozen=True)
class Camera:
    """A camera catalog entry (``catalogs/cameras/<name>.yaml``)."""

    name: str
    description: str
    bit_depth: int
    layout: Layout
    bands: tuple[Band, ...]
    sensor: tuple[int, int] | None = None  # (height, width) in sensor pixels
    index_bands: Mapping[str, float] = field(default_factory=dict)
    export_bands: tuple[str, ...] = ()
    source: str = ""
    container_bits: int | None = None  # bits per stored sample when the data sit in its high bits
    identify: Identify | None = None
    factory_model: str | None = None  # radiometric model of the files' own metadata (a camera maker's, pipeline.ingest.cameras)
    skip_bands: tuple[SkipBand, ...] = ()
    sources: tuple[str, ...] = ()  # the manufacturer's documents the entry is taken from
    exif: "CameraExif | None" = None  # what per-frame TIFFs say of a camera whose frames carry no EXIF

    @property
    def dn_max(self) -> int:
        return 2**self.bit_depth - 1

    @property
    def dn_shift(self) -> int:
        """Right shift from stored samples to sensor DN (4 for 12-bit data in 16-bit samples)."""
        return 0 if self.container_bits is None else self.container_bits - self.bit_depth

    def shift_for(self, stored_bits: int | None) -> int:
        """Right shift from one file's samples to sensor DN: :attr:`dn_shift` for a file in the
        catalog's container (a RedEdge's 16-bit TIFF: 4); less for a file with fewer bits per
        sample, 0 for one that holds the sensor's DN as they are (a RedEdge set to save 12-bit
        TIFFs). ``stored_bits`` None (not known): the catalog's :attr:`dn_shift`."""
        return sample_shift(self.dn_shift, self.bit_depth, stored_bits)

    @property
    def n_bands(self) -> int:
        return len(self.bands)

    @property
    def wavelengths(self) -> np.ndarray:
        return np.array([b.wavelength_nm for b in self.bands], dtype=np.float64)

    @property
    def band_names(self) -> list[str]:
        return [b.name for b in self.bands]

    def band_for_wavelength(self, wavelength_nm: float, tolerance_nm: float = 10.0) -> int:
        """Index of the band whose centre wavelength is nearest ``wavelength_nm``."""
        d = np.abs(self.wavelengths - wavelength_nm)
        i = int(np.argmin(d))
        if d[i] > tolerance_nm:
            raise CatalogError(
                f"camera {self.name} has no band within {tolerance_nm:g} nm of {wavelength_nm:g} nm",
                hint=f"bands: {', '.join(f'{w:g}' for w in self.wavelengths)}",
            )
        return i


_MAX_CH = MAX_CHANNELS - 1


class _BandModel(Strict):
    name: Text
    wavelength_nm: PositiveNumber
    fwhm_nm: PositiveNumber | None = None
    mosaic: Pair | None = None
    channel: integer(0, _MAX_CH) | None = None  # type: ignore[valid-type]
    file_suffix: Text | None = None


class _MosaicLayout(Strict):
    TAGS = ("mosaic",)
    kind: Literal["mosaic"]
    pattern: Pair
    grid: Pair
    origin: Pair = (0, 0)


class _ChannelLayout(Strict):
    TAGS = ("multichannel",)
    kind: Literal["multichannel"]
    channels: integer(1, MAX_CHANNELS, "a positive integer")  # type: ignore[valid-type]


class _FileLayout(Strict):
    # folder_per_band: one folder per band in a session folder, the band files of a capture
    # share one name (Sentera 6X: session/<band folder>/IMG_00001.tif); bands found by their XMP BandName
    TAGS = ("file_per_band", "file_per_capture", "folder_per_band")
    kind: Literal["file_per_band", "file_per_capture", "folder_per_band"]
    capture_pattern: Text


_Layout = Annotated[_MosaicLayout | _ChannelLayout | _FileLayout, Field(discriminator="kind")]


class _Sensor(Strict):
    width: integer(1, MAX_PIXELS, f"an integer 1..{MAX_PIXELS} (pixels)")  # type: ignore[valid-type]
    height: integer(1, MAX_PIXELS, f"an integer 1..{MAX_PIXELS} (pixels)")  # type: ignore[valid-type]


class _Identify(Strict):
    make: Text
    models: _Strings | None = None
    rig_names: _Strings | None = None
    bands_per_capture: integer(1, text="a positive integer") | None = None  # type: ignore[valid-type]


class _SkipBand(Strict):
    name: Text
    reason: Text
    file_suffix: Text | None = None


class _Exif(Strict):
    make: Text
    model: Text
    pixel_um: PositiveNumber | None = None


class _CameraModel(Strict):
    name: Text
    description: Text
    bit_depth: integer(1, 16)  # type: ignore[valid-type]
    container_bits: Any = None  # checked against bit_depth
    layout: _Layout
    bands: Annotated[tuple[_BandModel, ...], Field(min_length=1)]
    sensor: _Sensor | None = None
    index_bands: dict[Any, PositiveNumber] | None = None
    export_bands: items(lambda v: True, "a list of band names", str) | None = None  # type: ignore[valid-type]
    identify: _Identify | None = None
    factory_model: Any = None  # one of the registered makers' models
    skip_bands: tuple[_SkipBand, ...] | None = None
    sources: items(lambda v: isinstance(v, str) and bool(v.strip()),  # type: ignore[valid-type]
                   "a list of citations (text)") | None = None
    exif: _Exif | None = None


def parse_camera(data: Any, path: Path) -> Camera:
    """Validate a camera mapping into a :class:`Camera`: keys and values (:class:`_CameraModel`),
    then what ties them together: bit depths, the capture pattern, bands against the layout,
    the sensor, index, export and skipped bands, the factory model."""
    m = validate(_CameraModel, data, path, CatalogError, label="camera")
    container = m.container_bits
    if container is not None and not (is_int(container) and m.bit_depth <= container <= 16):
        raise CatalogError(f"container_bits must be an integer from bit_depth ({m.bit_depth}) to 16, got {container!r}",
                           path=path, hint="container_bits is the stored sample size when the DN sit in its high bits")
    layout = _layout(m.layout, path)
    bands = tuple(Band(**b.model_dump()) for b in m.bands)
    names = [b.name for b in bands]
    if len(set(names)) != len(names):
        raise CatalogError("band names must be unique", path=path)
    _check_bands_fit_layout(bands, layout, path)
    sensor = None if m.sensor is None else (m.sensor.height, m.sensor.width)
    _check_sensor(sensor, layout, path)
    unknown_export = [x for x in m.export_bands or () if x not in names]
    if unknown_export:
        raise CatalogError(f"export_bands names unknown band(s) {', '.join(map(show_key, unknown_export))}", path=path)
    skip = tuple(SkipBand(s.name, s.file_suffix, s.reason) for s in m.skip_bands or ())
    for k, s in enumerate(skip):
        if s.name in names:
            raise CatalogError(f"skip_bands[{k}] {s.name!r} is also in bands", path=path)
    if layout.kind == "file_per_band" and any(s.file_suffix is None for s in skip):
        raise CatalogError("skip_bands of a one-file-per-band camera need their file_suffix", path=path,
                           hint="add file_suffix: the band's number in the file name, as in bands")
    _check_factory_model(m.factory_model, m.sources, path)
    ident = m.identify
    camera = Camera(
        name=m.name, description=m.description, bit_depth=m.bit_depth, layout=layout, bands=bands, sensor=sensor,
        index_bands={str(k): v for k, v in (m.index_bands or {}).items()}, export_bands=m.export_bands or (),
        source=str(path), container_bits=container, factory_model=m.factory_model, skip_bands=skip,
        sources=m.sources or (), exif=None if m.exif is None else CameraExif(**m.exif.model_dump()),
        identify=None if ident is None else Identify(ident.make, ident.models or (), ident.rig_names or (),
                                                     ident.bands_per_capture),
    )
    for role, wl in camera.index_bands.items():
        try:
            camera.band_for_wavelength(wl)
        except CatalogError as exc:
            raise CatalogError(f"index_bands.{show_key(role)}: {exc.reason}", path=path) from None
    if camera.name != path.stem:
        raise CatalogError(f"name {camera.name!r} must match the file name {path.stem!r}", path=path)
    return camera


def _layout(lay: Any, path: Path) -> Layout:
    """The :class:`Layout` of a validated layout; a capture pattern must compile with its groups."""
    if not isinstance(lay, _FileLayout):
        return Layout(**lay.model_dump())
    try:
        with warnings.catch_warnings():  # "possible nested set": a warning on stderr would break the one line
            warnings.simplefilter("ignore", FutureWarning)
            rx = re.compile(lay.capture_pattern)
    except (re.error, OverflowError, RecursionError, ValueError) as exc:  # OverflowError: a{99999999999}
        raise CatalogError(f"layout.capture_pattern is not a valid regex: {exc}", path=path) from None
    need = {"capture", "band"} if lay.kind == "file_per_band" else {"capture"}  # others: one name
    if not need <= set(rx.groupindex):
        raise CatalogError(
            f"layout.capture_pattern needs named groups {', '.join(f'(?P<{g}>...)' for g in sorted(need))}",
            path=path,
        )
    return Layout(kind=lay.kind, capture_pattern=rx.pattern)


def _check_factory_model(model: Any, sources: tuple[str, ...] | None, path: Path) -> None:
    """``factory_model``: a registered maker's model, cited in ``sources``."""
    if model is None:
        return
    from pipeline.ingest.cameras.dispatch import factory_models  # the registered makers' models

    if model not in factory_models():
        raise CatalogError(f"factory_model must be one of {', '.join(factory_models())}, got {model!r}", path=path)
    if not sources:
        raise CatalogError("a camera with a factory_model must cite the manufacturer's documents in 'sources'",
                           path=path)


def _check_bands_fit_layout(bands: tuple[Band, ...], layout: Layout, path: Path) -> None:
    """Every mosaic position, channel or file suffix is given once, in the layout's order."""
    if layout.kind == "mosaic":
        assert layout.pattern is not None
        rows, cols = layout.pattern
        positions = [b.mosaic for b in bands]
        expected = [(r, c) for r in range(rows) for c in range(cols)]
        if positions != expected:
            raise CatalogError(
                f"a {rows}x{cols} mosaic needs {rows * cols} bands listed in row-major mosaic order "
                "with a 'mosaic: [row, column]' each",
                path=path,
            )
    elif layout.kind == "multichannel":
        chans = [b.channel for b in bands]
        if sorted(c for c in chans if isinstance(c, int)) != list(range(len(bands))) or len(bands) != layout.channels:
            raise CatalogError(
                f"a {layout.channels}-channel camera needs one band per channel with 'channel: 0..{len(bands) - 1}'",
                path=path,
            )
    elif layout.kind == "file_per_capture":
        chans = [b.channel for b in bands]
        if any(not isinstance(c, int) or c < 0 for c in chans) or len(set(chans)) != len(chans):
            raise CatalogError("one-file-per-capture cameras need a unique 'channel' (0, 1, ...) per band", path=path)
    elif layout.kind == "folder_per_band":
        return  # bands are recognised by their XMP BandName (unique names are checked already)
    else:
        sufs = [b.file_suffix for b in bands]
        if any(s is None for s in sufs) or len(set(sufs)) != len(sufs):
            raise CatalogError("one-file-per-band cameras need a unique 'file_suffix' per band", path=path)


def _check_sensor(sensor: tuple[int, int] | None, layout: Layout, path: Path) -> None:
    """A mosaic's band grid must fit the sensor ``(height, width)``."""
    if sensor is not None and layout.kind == "mosaic":
        assert layout.pattern and layout.grid
        need = (layout.origin[0] + layout.pattern[0] * layout.grid[0],
                layout.origin[1] + layout.pattern[1] * layout.grid[1])
        if need[0] > sensor[0] or need[1] > sensor[1]:
            raise CatalogError(
                f"layout.grid {list(layout.grid)} does not fit the {sensor[1]}x{sensor[0]} sensor",
                path=path,
            )


_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,127}")


def _find(kind: str, name: str) -> Path:
    if not _NAME.fullmatch(name):  # a path, an empty or a 300-character name is no catalog entry
        raise CatalogError(
            f"{kind[:-1]} name {name!r} is not a catalog name",
            hint=f"a name is the file name of catalogs/{kind}/NAME.yaml: letters, digits, '.', '_', '+', '-'; "
                 f"known {kind}: {', '.join(list_entries(kind)) or 'none'}",
        )
    for d in catalog_dirs(kind):
        p = d / f"{name}.yaml"
        try:
            if p.is_file():
                return p
        except OSError:  # e.g. a folder of MSCAL_CATALOG_PATH that cannot be read
            continue
    known = ", ".join(list_entries(kind)) or "none"
    raise CatalogError(
        f"unknown {kind[:-1]} {name!r}",
        hint=f"known {kind}: {known}; add catalogs/{kind}/{name}.yaml to describe it",
    )


def list_entries(kind: str) -> list[str]:
    """Names of the catalog entries of ``kind``."""
    names: set[str] = set()
    for d in catalog_dirs(kind):
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.yaml"))
    return sorted(names)


def load_camera(name: str) -> Camera:
    """The camera catalog entry ``name``; :class:`CatalogError` if unknown or invalid."""
    return _load("cameras", name)


def _load(kind: str, name: str) -> Any:
    """The parsed entry ``name`` of ``kind``, from the cache while its file is unchanged."""
    path = _find(kind, name)
    try:
        st = path.stat()
    except OSError as exc:
        raise CatalogError(f"cannot read catalog file: {exc.strerror}", path=path) from None
    return _parsed(kind, str(path), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=256)
def _parsed(kind: str, path: str, mtime_ns: int, size: int) -> Any:
    """Parse one catalog file; cached on (path, mtime, size), so an edit is a new key."""
    p = Path(path)
    return _PARSERS[kind](read_yaml(p), p)


def clear_cache() -> None:
    """Forget every parsed catalog entry (tests; edits are picked up without it)."""
    _parsed.cache_clear()


# --------------------------------------------------------------------------- reflectance targets


@dataclass(frozen=True)
class ReflectanceSpec:
    """Reflectance of a target: a scalar, or a table of (wavelength_nm, rho) rows."""

    table: tuple[tuple[float, float], ...] | None = None
    scalar: float | None = None
    name: str = ""

    def at(self, wavelengths_nm: np.ndarray) -> np.ndarray:
        """Reflectance at each wavelength (linear interpolation, flat beyond the table)."""
        wl = np.asarray(wavelengths_nm, dtype=np.float64)
        if self.scalar is not None:
            return np.full(wl.shape, self.scalar)
        assert self.table is not None
        t = np.array(self.table, dtype=np.float64)
        return np.interp(wl, t[:, 0], t[:, 1])


#: A row of a reflectance table.
_Row = Annotated[tuple[float, float], check(
    lambda r: isinstance(r, list) and len(r) == 2 and None not in map(finite_number, r) and r[0] > 0 and 0 < r[1] <= 1,
    "must be [wavelength_nm, reflectance]: finite numbers, nm > 0, 0 < reflectance <= 1", lambda r: (float(r[0]), float(r[1])))]


def _increasing(rows: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    wl = [r[0] for r in rows]
    if any(b <= a for a, b in zip(wl, wl[1:])):
        raise Problem("must list its wavelengths strictly increasing")
    return rows


#: A reflectance in (0, 1].
_Scalar = Annotated[float, check(lambda v: 0 < v <= 1, "must be in (0, 1]", float)]
#: A reflectance table: ``[[wavelength_nm, reflectance], ...]``, wavelengths increasing.
_Table = Annotated[tuple[_Row, ...], Field(min_length=1), AfterValidator(_increasing)]


def _reflectance_kind(value: Any) -> str | None:
    if is_number(value):
        return "number"
    if isinstance(value, list):
        return "table"
    return "name" if isinstance(value, str) else None


#: A reflectance as a file gives it: a number in (0, 1], a table or a reflectance target's name.
Reflectance = one_of(_reflectance_kind, "a number, a table of [wavelength_nm, reflectance] rows or a target name",
                     number=_Scalar, table=_Table, name=str)
#: A reflectance target's own reflectance: a number in (0, 1] or a table (no other target's name).
TargetReflectance = one_of(lambda v: None if isinstance(v, str) else _reflectance_kind(v),
                           "a number or a table of [wavelength_nm, reflectance] rows", number=_Scalar, table=_Table)


def reflectance_option(text: str, option: str = "--panel-reflectance") -> ReflectanceSpec:
    """A command-line reflectance: a number in (0, 1] or a reflectance target's name."""
    try:
        value: Any = float(text)
    except ValueError:
        value = text
    return parse_reflectance(value, option, option)


def parse_reflectance(value: Any, path: Path | str, where: str) -> ReflectanceSpec:
    """Validate a reflectance (:data:`Reflectance`: a number in (0, 1], a [[nm, rho], ...]
    table, or a target name) into a :class:`ReflectanceSpec`. An unknown or broken target is
    reported against ``path`` (the file that names it) too."""
    value = validate(Reflectance, value, path, CatalogError, prefix=where)
    return reflectance_spec(value, path, where)


def reflectance_spec(value: float | tuple[tuple[float, float], ...] | str, path: Path | str,
                     where: str) -> ReflectanceSpec:
    """The :class:`ReflectanceSpec` of a validated :data:`Reflectance` (a target's name: its
    catalog entry's, an unknown or broken one reported against ``path`` too)."""
    if isinstance(value, str):
        try:
            return load_target(value).reflectance
        except CatalogError as exc:
            at = f"its catalog entry {exc.path}: " if exc.path else ""
            raise CatalogError(f"{where} {value!r}: {at}{exc.reason}", path=path, hint=exc.hint) from None
    if isinstance(value, float):
        return ReflectanceSpec(scalar=value)
    return ReflectanceSpec(table=tuple(value))


@dataclass(frozen=True)
class Target:
    name: str
    description: str
    reflectance: ReflectanceSpec
    serials: tuple[str, ...] = ()  # of the panels it describes, as in their QR codes (pipeline.ingest.targets)


def load_target(name: str) -> Target:
    """A reflectance target from ``catalogs/targets/<name>.yaml``."""
    return _load("targets", name)


#: A panel's serial number: text, not empty (surrounding spaces dropped).
_Serial = Annotated[str, check(lambda v: isinstance(v, str) and bool(v.strip()), "must be text, not empty",
                               lambda v: v.strip(), hint="quote a serial YAML reads as a number")]


class _TargetModel(Strict):
    name: Text
    description: Text
    reflectance: TargetReflectance
    serial: _Serial | None = None
    serials: items(lambda v: isinstance(v, str) and bool(v.strip()),  # type: ignore[valid-type]
                   "a list of serial numbers (text, not empty)", lambda v: v.strip()) | None = None


def parse_target(data: Any, path: Path) -> Target:
    """Validate a target mapping into a :class:`Target` (:class:`_TargetModel`); a target listing
    serials is found by them and used by its file name, which its name must be."""
    m = validate(_TargetModel, data, path, CatalogError, label="target")
    spec = reflectance_spec(m.reflectance, path, "reflectance")
    seen: dict[str, str] = {}  # the first spelling of each serial: serial, then serials
    serials = tuple(seen.setdefault(v.casefold(), v) for v in ([m.serial] if m.serial else []) + list(m.serials or ())
                    if v.casefold() not in seen)
    if serials and m.name != path.stem:
        raise CatalogError(f"name {m.name!r} must match the file name {path.stem!r}", path=path)
    return Target(name=m.name, description=m.description, reflectance=spec, serials=serials)


# --------------------------------------------------------------------------- indices

_ALLOWED_NODES = (
    ast.Expression, ast.BinOp, ast.UnaryOp, ast.Name, ast.Load, ast.Constant,
    ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd,
)


@dataclass(frozen=True)
class Index:
    """A spectral index: an arithmetic expression of band roles (red, nir, ...)."""

    name: str
    description: str
    expression: str
    inputs: tuple[str, ...]
    valid_range: tuple[float, float] | None = None

    def evaluate(self, bands: Mapping[str, np.ndarray]) -> np.ndarray:
        """Evaluate on arrays keyed by role; NaN where the value is not finite (division by zero)
        or outside ``valid_range`` (:func:`mscal_core.reflectance.keep_valid`)."""
        code = _compiled(self.expression)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = eval(code, {"__builtins__": {}}, {k: bands[k] for k in self.inputs})  # validated AST
        return keep_valid(np.asarray(out, dtype=np.float32), self.valid_range)


@lru_cache(maxsize=64)
def _compiled(expression: str) -> CodeType:
    """The code of an index expression, compiled once per process: each frame evaluates it
    (compiling it each time took 0.02-0.07 ms a frame)."""
    return compile(ast.parse(expression, mode="eval"), "<index>", "eval")


class _IndexModel(Strict):
    name: Text
    description: Text
    expression: Text
    valid_range: Annotated[tuple[float, float], check(
        lambda v: isinstance(v, list) and len(v) == 2 and None not in map(finite_number, v) and v[0] < v[1],
        "must be [low, high] (finite numbers, low < high)", lambda v: (float(v[0]), float(v[1])))] | None = None


def parse_index(data: Any, path: Path) -> Index:
    """Validate an index mapping into an :class:`Index`: its expression is arithmetic of band roles."""
    m = validate(_IndexModel, data, path, CatalogError, label="index")
    expr = m.expression
    try:
        tree = ast.parse(expr, mode="eval")
        nodes = list(ast.walk(tree))
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise CatalogError(f"expression {expr!r} is not valid arithmetic", path=path) from None
    bad = [type(n).__name__ for n in nodes if not isinstance(n, _ALLOWED_NODES)]
    bad += [f"the constant {n.value!r}" for n in nodes if isinstance(n, ast.Constant)
            and finite_number(n.value) is None]
    bad += ["a power other than a number from -8 to 8" for n in nodes if isinstance(n, ast.BinOp)
            and isinstance(n.op, ast.Pow) and not (isinstance(n.right, ast.Constant)
                                                   and finite_number(n.right.value) is not None
                                                   and abs(n.right.value) <= 8)]
    if bad:
        raise CatalogError(
            f"expression {expr!r} uses {', '.join(sorted(set(bad)))}",
            path=path,
            hint="only band roles, numbers and + - * / are allowed, and ** with a number from -8 to 8",
        )
    inputs = tuple(sorted({n.id for n in nodes if isinstance(n, ast.Name)}))
    if m.name != path.stem:
        raise CatalogError(f"name {m.name!r} must match the file name {path.stem!r}", path=path)
    return Index(m.name, m.description, expr, inputs, m.valid_range)


def load_index(name: str) -> Index:
    """A spectral index from ``catalogs/indices/<name>.yaml``."""
    return _load("indices", name)


_PARSERS = {"cameras": parse_camera, "targets": parse_target, "indices": parse_index}