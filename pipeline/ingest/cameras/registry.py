"""The camera makers mscal reads factory metadata of: each maker's module registers one
:class:`Maker` here (its tag reading, radiance model, vignetting, the units of its radiance and
its sun sensor: tag, fixed reflectance scale, attitude tags, measured direct/diffuse split,
self-compensated reading); :mod:`pipeline.ingest.cameras` picks one by a file's tags or by a
band's ``CaptureMeta.radiometry``, and the shared sun-sensor modules
(:mod:`pipeline.ingest.sun_scale`, :mod:`pipeline.ingest.sunsensor`) ask every maker here.

This module imports no other module of mscal at run time, so that the shared modules
(:mod:`pipeline.ingest.meta`) can look up what a maker registered without a cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from pathlib import Path
    from typing import Sequence

    import numpy as np
    from mscal_core.geometry import Intrinsics

    from pipeline.ingest.meta import CaptureMeta, FieldParts, TagContext, VignettingTags
    from pipeline.ingest.sun_scale import SunScale
    from pipeline.ingest.xmp import Xmp

#: ``radiance(meta, dn, parts, channels, out)``: a band's radiance from its stored DN
#: (:func:`pipeline.ingest.cameras.factory_radiance` checks the shapes and field parts first).
Radiance = Callable[["CaptureMeta", "np.ndarray", "FieldParts | None", "np.ndarray | None", "np.ndarray | None"],
                    "np.ndarray"]


@dataclass(frozen=True)
class AttitudeSource:
    """Where a maker's files keep the sun sensor's (or, failing that, the aircraft's) yaw,
    pitch and roll: ``read(xmp)`` gives them in radians, or None when the file has none.
    Every maker's sources are tried for every file, lowest ``rank`` first
    (:func:`attitude_sources`): a sensor's own angles before an aircraft's."""

    rank: int
    name: str  # what run.json's sun_sensor model says the orientation came from
    read: Callable[["Xmp"], "tuple[float, float, float] | None"]


@dataclass(frozen=True)
class SunSplit:
    """A sun sensor's own measured direct/scattered split (MicaSense DLS 2): ``direct``,
    ``scattered`` and ``horizontal`` (None: not written), in one unit (their scale cancels in
    the ratios used)."""

    direct: float
    scattered: float
    horizontal: float | None


@dataclass(frozen=True)
class FileRegistration:
    """A maker's own registration of each band file onto the camera's common image plane,
    written in the file (DJI: ``CalibratedHMatrix`` with ``DewarpData``): ``has(meta)`` whether
    a band file carries it, ``align(metas, stack)`` the bands ``(band, H, W)`` of one capture
    (stored orientation) on that plane (FrameError naming a band file without it), ``note`` what
    it is and where the maker documents it (run.json ``band_alignment``)."""

    has: Callable[["CaptureMeta"], bool]
    align: Callable[["Sequence[CaptureMeta]", "np.ndarray"], "np.ndarray"]
    note: str


@dataclass(frozen=True)
class Maker:
    """One camera maker's factory model.

    ``claims(ctx)`` says whether a file's tags are this maker's (tried in ``order``, lowest
    first; the ``fallback`` maker reads every file no other claims); ``read(ctx)`` gives the
    file's bands' :class:`~pipeline.ingest.meta.CaptureMeta`, each with a ``radiometry`` of
    ``units``; ``radiance`` computes a band's radiance for those radiometries and
    ``vignetting(radiometry, shape, tags)`` its factory vignetting correction (``(H, W)``, >= 1, multiplies DN).
    ``model`` is the catalog's ``factory_model`` name of the maker's cameras, ``sun_sensor_tag``
    the tag its sun-sensor reading comes from (named when a band has none), and
    ``companion_images`` the catalog cameras' images saved beside the band files that are no
    band files (camera name: (file-name pattern with group ``capture``, why it is left out)).

    The sun sensor (:mod:`pipeline.ingest.sun_scale`, :mod:`pipeline.ingest.sunsensor`):
    ``sun_scales`` the fixed reflectance scale ``c`` of ``R = c L / E`` per radiometry (none:
    its sensor gives no reflectance on its own); ``sun_factor(meta)`` the factor ``1 / E`` of a
    reading with no such scale that is still proportional to the light (a panel sets the
    scale); ``attitude`` the :class:`AttitudeSource` entries of its files' orientation tags;
    ``sun_split(xmp)`` a measured direct/scattered split (:class:`SunSplit`) and
    ``split_correction(xmp, split, elevation)`` the correction ``E_h / E_meas`` of a reading
    that is the split's own horizontal irradiance, recomputed with the sun's elevation
    (radians; None: the reading is the tilted total, for the tilt model with the measured
    ratio); ``compensated(xmp)`` whether the reading is already independent of the attitude (no tilt
    model on top), named ``compensated_model`` in run.json; ``sun_sensor_xmp`` the local names of
    the XMP properties these hooks read (kept on each band's metadata when its file is read, so
    the sun sensor reads no file twice: :func:`sun_sensor_xmp_names`); ``no_reflectance(meta)``
    the maker's own reason why a band's sun sensor gives no reflectance (None: the shared reason,
    :func:`pipeline.ingest.meta.no_reflectance_reason`); ``sun_unit_rules(xmp)`` the unit rules of
    an absolute sensor's reading, ``({rule: scale to W m-2 nm-1}, scale its reader applied)``, that
    :mod:`pipeline.apply.sun_check` chooses between against the clear sky (None: the reading is
    in W m-2 nm-1 as read, :data:`AS_READ_RULE`).

    Other tags: ``kept_out`` the radiometries of bands read but never part of reflectance
    (thermal, panchromatic); ``capture_id_tags`` the ``(namespace, name)`` XMP tags holding a
    capture's id, ``time_tags`` the ``(namespace, name)`` XMP tags holding the exposure's UTC
    time (every maker's are tried for every file, in maker order, before the shared ones);
    ``intrinsics(xmp, path)`` the lens of a file without the shared Pix4D perspective tags
    (None: it has none); ``vignetting_tags`` the tags its vignetting comes from (named when they
    give an unusable correction); ``field_parts`` whether its ``radiance`` takes a field
    calibration's response and/or vignetting (:class:`~pipeline.ingest.meta.FieldParts`) in
    place of the factory's; ``namespaces`` its own XMP namespaces (key: URIs, compared without a
    trailing slash), which files are parsed with once it is registered
    (:func:`pipeline.ingest.xmp.namespace_key`), and ``default_namespaces`` the keys of those that
    hold the shared Pix4D camera schema's tags as well (MicaSense's), looked up after ``Camera``
    whenever a reader names no namespace (:func:`pipeline.ingest.xmp.default_namespaces`); ``serial_tags`` the ``(namespace, name)`` XMP
    tags holding the camera body's serial number where EXIF has none (tried for every file, in
    maker order: :func:`pipeline.calibrate.library.file_serial`).

    Outputs: ``capture_id_output`` the XMP property ``(prefix, namespace URI, local name)`` the
    photogrammetry TIFFs of its captures carry the source's capture id in, for tools that look
    it up by that literal name (OpenDroneMap's ``MicaSense:CaptureId``); written when a capture's
    id is the files' own (not its file name): :func:`pipeline.apply.captures.capture_tags`.

    Geometry: ``file_registration`` the band files' own registration onto a common image plane
    (:class:`FileRegistration`; None: the maker writes none, the bands are aligned by
    ``mscal register`` or measured): :func:`pipeline.ingest.cameras.dispatch.has_file_registration`;
    ``sibling_position(folder, capture)`` ``(lat, lon, alt_m)`` of a capture whose band files
    have no position of their own, from a file the camera saves beside them (Parrot Sequoia's
    RGB JPEG), or None: :func:`pipeline.ingest.cameras.dispatch.sibling_position`.
    """

    name: str
    model: str
    units: dict[str, str]
    claims: Callable[["TagContext"], bool]
    read: Callable[["TagContext"], "list[CaptureMeta]"]
    radiance: Radiance
    vignetting: Callable[[str, tuple[int, int], "VignettingTags"], "np.ndarray"]
    order: int = 50
    fallback: bool = False
    sun_sensor_tag: str | None = None
    companion_images: dict[str, tuple[str, str]] = field(default_factory=dict)
    sun_scales: "dict[str, SunScale]" = field(default_factory=dict)
    sun_factor: "Callable[[CaptureMeta], float | None] | None" = None
    attitude: tuple[AttitudeSource, ...] = ()
    sun_split: "Callable[[Xmp], SunSplit | None] | None" = None
    split_correction: "Callable[[Xmp, SunSplit, float], float | None] | None" = None
    compensated: "Callable[[Xmp], bool] | None" = None
    compensated_model: str = ""
    sun_sensor_xmp: frozenset[str] = frozenset()
    no_reflectance: "Callable[[CaptureMeta], str | None] | None" = None
    sun_unit_rules: "Callable[[Xmp], tuple[dict[str, float], float]] | None" = None
    kept_out: frozenset[str] = frozenset()
    capture_id_tags: tuple[tuple[str, str], ...] = ()
    time_tags: tuple[tuple[str, str], ...] = ()
    intrinsics: "Callable[[Xmp, Path], Intrinsics | None] | None" = None
    vignetting_tags: str = ""
    field_parts: bool = False
    namespaces: dict[str, tuple[str, ...]] = field(default_factory=dict)
    default_namespaces: tuple[str, ...] = ()
    serial_tags: tuple[tuple[str, str], ...] = ()
    capture_id_output: tuple[str, str, str] | None = None
    file_registration: FileRegistration | None = None
    sibling_position: "Callable[[Path, str], tuple[float, float, float | None] | None] | None" = None


#: The unit rule of an absolute sun sensor's reading whose maker declares none
#: (:attr:`Maker.sun_unit_rules`): W m-2 nm-1 as its reader gives it.
AS_READ_RULE = "x 1: W m-2 nm-1 as read"

MAKERS: dict[str, Maker] = {}
#: The registered makers' own XMP namespaces: URI (no trailing slash) -> key (:attr:`Maker.namespaces`).
NAMESPACE_KEYS: dict[str, str] = {}
#: The registered makers' :attr:`Maker.default_namespaces`, in maker order (:func:`by_order`).
DEFAULT_NAMESPACE_KEYS: tuple[str, ...] = ()


def register(maker: Maker) -> Maker:
    """Add ``maker`` (called once by its module when imported); a second maker of one name,
    catalog model or radiometry is a programming error."""
    if maker.name in MAKERS:
        raise ValueError(f"camera maker {maker.name!r} registered twice")
    for other in MAKERS.values():
        if other.model == maker.model or set(other.units) & set(maker.units):
            raise ValueError(f"camera makers {other.name!r} and {maker.name!r} claim one model or radiometry")
        if other.fallback and maker.fallback:
            raise ValueError(f"camera makers {other.name!r} and {maker.name!r} are both the fallback")
    for key, uris in maker.namespaces.items():
        for uri in uris:
            if NAMESPACE_KEYS.get(uri.rstrip("/"), key) != key:
                raise ValueError(f"camera maker {maker.name!r}: XMP namespace {uri} is already "
                                 f"{NAMESPACE_KEYS[uri.rstrip('/')]!r}")
    if not set(maker.default_namespaces) <= set(maker.namespaces):
        raise ValueError(f"camera maker {maker.name!r}: default namespaces {maker.default_namespaces} are not "
                         "among its own namespaces")
    MAKERS[maker.name] = maker
    NAMESPACE_KEYS.update({uri.rstrip("/"): key for key, uris in maker.namespaces.items() for uri in uris})
    global DEFAULT_NAMESPACE_KEYS
    DEFAULT_NAMESPACE_KEYS = tuple(dict.fromkeys(k for m in by_order() for k in m.default_namespaces))
    return maker


def by_order() -> list[Maker]:
    """The registered makers in the order their ``claims`` are tried."""
    return sorted(MAKERS.values(), key=lambda m: (m.order, m.name))


def maker_of(radiometry: str) -> Maker:
    """The maker whose bands have ``radiometry`` (``CaptureMeta.radiometry``)."""
    for maker in MAKERS.values():
        if radiometry in maker.units:
            return maker
    raise KeyError(radiometry)


def radiance_unit(radiometry: str) -> str:
    """The unit of a band's radiance of ``radiometry``."""
    return maker_of(radiometry).units[radiometry]


def sun_sensor_tag(radiometry: str) -> str | None:
    """The sun-sensor tag the maker of ``radiometry`` reads, None if it names none."""
    try:
        return maker_of(radiometry).sun_sensor_tag
    except KeyError:
        return None


def fallback() -> Maker:
    """The maker that reads every file no other claims."""
    return next(m for m in by_order() if m.fallback)


def attitude_sources() -> list[AttitudeSource]:
    """Every maker's :class:`AttitudeSource`, in the order they are tried (rank, then name)."""
    return sorted((a for m in MAKERS.values() for a in m.attitude), key=lambda a: (a.rank, a.name))


def sun_sensor_xmp_names() -> frozenset[str]:
    """The local names of the XMP properties every maker's sun-sensor hooks read
    (:attr:`Maker.sun_sensor_xmp`)."""
    return frozenset(name for m in MAKERS.values() for name in m.sun_sensor_xmp)


def kept_out(radiometry: str) -> bool:
    """Whether bands of ``radiometry`` are read but never part of reflectance (:attr:`Maker.kept_out`)."""
    return any(radiometry in m.kept_out for m in MAKERS.values())


def capture_id_tags() -> list[tuple[str, str]]:
    """Every maker's ``(namespace, name)`` capture-id tags, in maker order (:func:`by_order`)."""
    return [t for m in by_order() for t in m.capture_id_tags]


def time_tags() -> list[tuple[str, str]]:
    """Every maker's ``(namespace, name)`` UTC exposure-time tags, in maker order."""
    return [t for m in by_order() for t in m.time_tags]


def serial_tags() -> list[tuple[str, str]]:
    """Every maker's ``(namespace, name)`` XMP tags of the camera's serial number, in maker order
    (:attr:`Maker.serial_tags`)."""
    return [t for m in by_order() for t in m.serial_tags]


def sun_unit_rules(radiometry: str, xmp: "Callable[[], Xmp]") -> tuple[dict[str, float], float]:
    """The unit rules of a band's absolute sun-sensor reading, ``({rule: scale to W m-2 nm-1},
    scale the reader applied)``: its maker's (:attr:`Maker.sun_unit_rules`, given the XMP
    ``xmp()`` returns), else the one rule :data:`AS_READ_RULE`."""
    try:
        rules = maker_of(radiometry).sun_unit_rules
    except KeyError:
        rules = None
    return ({AS_READ_RULE: 1.0}, 1.0) if rules is None else rules(xmp())


def capture_id_output(radiometry: str) -> tuple[str, str, str] | None:
    """The XMP property ``(prefix, namespace URI, local name)`` the photogrammetry TIFFs of a
    capture whose bands have ``radiometry`` carry its capture id in (:attr:`Maker.capture_id_output`),
    None when its maker names none."""
    try:
        return maker_of(radiometry).capture_id_output
    except KeyError:
        return None
