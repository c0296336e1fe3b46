"""What every camera maker's band files share: the :class:`CaptureMeta` of one band, the
:class:`TagContext` a maker's reader gets, and the tag helpers every reader uses (EXIF exposure
and ISO, XMP band name and wavelength, position, time, ids, black levels, the problems of
tags only one feature needs).

A tag the *radiance* needs that is missing or unusable raises :class:`FrameError` naming the
file and the tag (mscal never silently falls back to raw DN). A tag only one feature needs
(ReflectArea: the panel's area; Irradiance: the sun sensor; GPS; RigCameraIndex) that is
present but unusable is recorded in ``CaptureMeta.problems`` (file, tag, value, feature)
and disables that feature only. Each maker's own tags, radiance model and quirks are in
:mod:`pipeline.ingest.cameras`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.factory import upright

from pipeline.ingest.cameras.registry import (
    capture_id_tags,
    kept_out,
    maker_of,
    radiance_unit,
    sun_sensor_tag,
    time_tags,
)
from pipeline.ingest.exif import exposure_time, rational
from pipeline.ingest.gps import NoPosition
from pipeline.ingest.gps import exif_position as _gps
from pipeline.ingest.sun_scale import sun_scale
from pipeline.ingest.xmp import TagError, TagProblem, Xmp

FIRMWARE_HINT = "the camera firmware may be too old to write factory calibration; update it, or use a field calibration"
MAX_EXPOSURE_S = 1.0  # multispectral exposures are at most a few tens of ms
WAVELENGTH_RANGE_NM = (300.0, 1100.0)  # silicon sensors: anything else is a unit error


@dataclass(frozen=True)
class CaptureMeta:
    """Factory metadata of one band of a capture (units: s, nm, DN, degrees, metres)."""

    path: Path
    shape: tuple[int, int]  # (height, width) as stored
    bits_per_sample: int  # the file's BitsPerSample (16 for RedEdge's 12-bit data in 16-bit samples, 12 packed, 8 JPEG)
    band_name: str
    wavelength_nm: float
    fwhm_nm: float | None
    exposure_s: float
    gain: float  # ISO / 100 (MicaSense, Sentera); drone-dji:SensorGain (DJI)
    black_levels: tuple[float, ...]  # EXIF BlackLevel (per CFA position), drone-dji:BlackLevel
    irradiance: float | None  # sun sensor reading (unit: irradiance_unit)
    capture_id: str | None
    rig_camera_index: int | None
    reflect_area: tuple[float, ...] | None  # panel region written by the camera, if any
    lat: float | None
    lon: float | None
    alt_m: float | None
    time: str | None  # ISO 8601, with fraction of a second when SubsecTime is present
    radiometry: str  # a radiometry its maker registers (pipeline.ingest.cameras.registry)
    # the radiometric tags of the Pix4D camera schema (MicaSense; Parrot's 2-D vignetting): None
    # for a maker that writes none
    dark_row_values: tuple[float, ...] | None = None
    radiometric_calibration: tuple[float, float, float] | None = None  # a1, a2, a3
    vignetting_center: tuple[float, float] | None = None  # (x, y) pixels
    vignetting_polynomial: tuple[float, ...] | None = None  # k1..kn, lowest power first
    vignetting_polynomial_2d: tuple[float, ...] | None = None
    vignetting_polynomial_2d_exponents: tuple[float, ...] | None = None
    make: str | None = None
    model: str | None = None
    rig_name: str | None = None
    serial: str | None = None
    software: str | None = None
    orientation: int = 1  # EXIF Orientation (3: stored rotated 180 degrees)
    f_number: float | None = None
    iso: float | None = None
    channel: int | None = None  # channel of a multi-channel file (Sentera JPEG)
    irradiance_unit: str = "W m-2 nm-1"
    # MicaSense XMP Albedo: the reflectance of the panel in this band file, as the camera read
    # it from the panel's QR code (written in its panel captures with ReflectArea)
    panel_albedo: float | None = None
    calibration_picture: int | None = None  # XMP Camera:CalibrationPicture (Pix4D: 2, a valid panel capture)
    problems: tuple[TagProblem, ...] = ()
    # a maker's own per-band values its radiance or vignetting needs, as (name, value) pairs
    # (hashable values: numbers, text, tuples): a new maker needs no new field here (maker_tag)
    maker_tags: tuple[tuple[str, Any], ...] = ()
    # the file's XMP properties the sun-sensor model reads (camera_meta.sun_sensor_xmp_names; sun_sensor_xmp)
    sun_sensor_props: tuple[tuple[str, str, str | tuple[str, ...]], ...] | None = field(
        default=None, compare=False, repr=False)

    def maker_tag(self, name: str, default: Any = None) -> Any:
        """The value ``name`` of :attr:`maker_tags`, else ``default``."""
        return next((v for k, v in self.maker_tags if k == name), default)

    @property
    def black_level(self) -> float:
        """Black level in DN: the mean of EXIF BlackLevel, else of DarkRowValue (0 if none:
        JPEG cameras)."""
        levels = self.black_levels or self.dark_row_values or ()
        return float(sum(levels) / len(levels)) if levels else 0.0

    def clipped_from(self, camera_sat: int) -> int:
        """Stored value at and above which a pixel of this file is clipped: ``camera_sat``
        (the catalog camera's, the sensor's largest DN in the container's high bits: 65520 for
        a RedEdge's 12-bit data in 16-bit samples), at most the largest value the file's own
        BitsPerSample holds. A RedEdge set to save 12-bit TIFFs (MicaSense: "12-bit or 16-bit
        format ... divide the raw DN by 2^N") and a Sentera 6X store the sensor's DN as they
        are, packed in 12 bits: they clip at 4095."""
        return min(int(camera_sat), (1 << self.bits_per_sample) - 1)

    @property
    def radiance_unit(self) -> str:
        return radiance_unit(self.radiometry)

    @property
    def reflectance_band(self) -> bool:
        """True for a band that goes into reflectance (not one its maker keeps out: thermal,
        panchromatic; :attr:`pipeline.ingest.cameras.registry.Maker.kept_out`)."""
        return not kept_out(self.radiometry)

    def features(self) -> dict[str, bool]:
        """Which features this band file's metadata allows (radiance: always, or there would
        be no meta: the reader raises instead)."""
        bad = {p.feature for p in self.problems}
        return {
            "radiance": True,
            "sun_sensor_reading": self.irradiance is not None and self.irradiance > 0 and "sun_sensor" not in bad,
            "sun_sensor_reflectance": reflectance_factor(self) is not None and "sun_sensor" not in bad,
            "sun_sensor_absolute": sun_sensor_absolute(self) and reflectance_factor(self) is not None,
            "panel_area": self.reflect_area is not None and "panel_area" not in bad,
            "panel_albedo": self.panel_albedo is not None and self.calibration_picture == 2,
            "position": self.lat is not None and self.lon is not None,
            "rig_index": self.rig_camera_index is not None,
            "factory_band_alignment": _has_file_registration(self),
        }



def _has_file_registration(meta: CaptureMeta) -> bool:
    """Whether the band file carries its maker's own registration onto the camera's common
    image plane (:attr:`pipeline.ingest.cameras.registry.Maker.file_registration`)."""
    try:
        reg = maker_of(meta.radiometry).file_registration
    except KeyError:
        return False
    return reg is not None and reg.has(meta)


# --------------------------------------------------------------------------- EXIF


def int_tag(value: Any, default: int) -> int:
    """An integer tag (Orientation, ExifImageWidth) as int; ``default`` when it is missing or
    not one integer (another type, several values, text)."""
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return default
    return int(value)


def xmp_utc_time(xmp: Xmp) -> str | None:
    """The exposure's UTC time as a maker's XMP writes it (the first of every maker's
    :attr:`~pipeline.ingest.cameras.registry.Maker.time_tags` the file holds), else None."""
    return next((t for ns, name in time_tags() if (t := xmp.text(name, (ns,))) is not None), None)


def _time(exif: dict[str, Any], xmp: Xmp) -> str | None:
    """The exposure's time: :func:`pipeline.ingest.exif.exposure_time` of the file's tags."""
    return exposure_time(exif.get("DateTimeOriginal"), exif.get("SubsecTimeOriginal") or exif.get("SubsecTime"),
                         exif.get("OffsetTimeOriginal"), xmp_utc_time(xmp))


def exif_exposure(exif: dict[str, Any], path: Path) -> float:
    if "ExposureTime" not in exif:
        raise FrameError("no EXIF ExposureTime tag", path=path, hint=FIRMWARE_HINT)
    exposure = tag_number(exif["ExposureTime"], "EXIF ExposureTime", path)
    check_exposure(exposure, "EXIF ExposureTime", path)
    return exposure


def check_exposure(exposure: float, what: str, path: Path) -> None:
    if not (math.isfinite(exposure) and 0 < exposure <= MAX_EXPOSURE_S):
        raise FrameError(
            f"{what} {exposure!r} s is outside (0, {MAX_EXPOSURE_S:g}] s",
            path=path,
            hint="exposure must be in seconds; a value in ms or us means the file was rewritten with wrong units",
        )


def tag_number(value: Any, what: str, path: Path) -> float:
    """A RATIONAL or number tag as float (:func:`rational`; NaN for a zero denominator), a
    :class:`FrameError` naming the tag when it is text or another form that is no number."""
    try:
        return rational(value)
    except (TypeError, ValueError, ZeroDivisionError, IndexError, OverflowError):
        raise FrameError(f"{what} {str(value)[:40]!r} is not a number", path=path, hint=FIRMWARE_HINT) from None


def exif_iso(exif: dict[str, Any], path: Path) -> float:
    iso = exif.get("ISOSpeed") or exif.get("ISOSpeedRatings") or exif.get("PhotographicSensitivity")
    if isinstance(iso, (tuple, list)):
        iso = iso[0] if iso else None
    if not iso:
        raise FrameError("no EXIF ISOSpeed/ISOSpeedRatings tag (the gain)", path=path, hint=FIRMWARE_HINT)
    value = tag_number(iso, "EXIF ISO", path)
    if not (math.isfinite(value) and value > 0):
        raise FrameError(f"EXIF ISO {value!r} is not a positive number (the gain)", path=path, hint=FIRMWARE_HINT)
    return value


def exposure_and_gain(exif: dict[str, Any], path: Path) -> tuple[float, float]:
    return exif_exposure(exif, path), exif_iso(exif, path) / 100.0



@dataclass
class TagContext:
    """What a camera maker's reader gets: the file's tags and a list to record feature problems in."""

    path: Path
    xmp: Xmp
    exif: dict[str, Any]
    gps: dict[str, Any]
    shape: tuple[int, int]
    bits: int
    make: str | None
    model: str | None
    software: str | None
    serial: str | None
    orientation: int
    black_tag: Any
    problems: list[TagProblem] = field(default_factory=list)

    def optional(self, feature: str, read: Callable[[], Any]) -> Any:
        """``read()``, or None with a problem recorded when its tag is present but unusable."""
        try:
            return read()
        except TagError as exc:
            self.problems.append(exc.problem(feature))
            return None

    def required(self, tag: str, ns: Sequence[str] | None = None, count: int | None = None
                 ) -> tuple[float, ...]:
        try:
            v = self.xmp.numbers(tag, ns, count)
        except TagError as exc:
            raise FrameError(f"XMP {exc.reason}", path=self.path, hint=FIRMWARE_HINT) from None
        if v is None:
            raise FrameError(f"no XMP {tag} tag", path=self.path, hint=FIRMWARE_HINT)
        return v



def clean_text(value: Any) -> str | None:
    if value is None:
        return None
    text = value.decode("latin-1", errors="replace") if isinstance(value, bytes) else str(value)
    text = text.strip().strip("\x00").strip()
    return text or None



def band_of(ctx: TagContext, name_ns: Sequence[str] = ()) -> tuple[str, float, float | None]:
    """Band name, centre wavelength and FWHM (nm) of a single-band file, units checked; the
    band name in ``Camera:``/``MicaSense:``, else in a maker's own namespaces ``name_ns``."""
    x = ctx.xmp
    name = x.text("BandName") or (x.text("BandName", name_ns) if name_ns else None)
    if name is None:
        if x.has("BandName"):
            raise FrameError(f"XMP BandName is {x.raw('BandName')!r}, expected one name", path=ctx.path,
                             hint=FIRMWARE_HINT)
        raise FrameError("no XMP BandName tag", path=ctx.path, hint=FIRMWARE_HINT)
    wl = ctx.required("CentralWavelength", count=1)[0]
    check_wavelength(wl, ctx.path)
    fwhm = ctx.optional("bandwidth", lambda: x.numbers("WavelengthFWHM", count=1))
    return name, wl, fwhm[0] if fwhm else None


def check_wavelength(wl: float, path: Path) -> None:
    lo, hi = WAVELENGTH_RANGE_NM
    if not lo <= wl <= hi:
        raise FrameError(f"XMP CentralWavelength {wl:g} is outside {lo:g}-{hi:g} nm", path=path,
                         hint="the wavelength must be in nanometres")


#: The capture-id tags of the Pix4D camera schema, which several makers write: tried after
#: every maker's own (:attr:`pipeline.ingest.cameras.registry.Maker.capture_id_tags`).
SHARED_CAPTURE_ID_TAGS = (("Camera", "CaptureUUID"), ("Camera", "ImageUniqueID"))


def _common(ctx: TagContext) -> dict[str, Any]:
    """Fields every reader fills the same way: position, time, ids, feature problems."""
    x = ctx.xmp
    lat = lon = alt = None
    try:
        lat, lon, alt = _gps(ctx.gps)
    except NoPosition as exc:  # written, but no fix: named, left out (pipeline.ingest.gps)
        ctx.problems.append(TagProblem(str(ctx.path), exc.tag, exc.value, str(exc), "position"))
    except (TypeError, ValueError, ZeroDivisionError, IndexError) as exc:
        ctx.problems.append(TagProblem(str(ctx.path), "EXIF GPS", str(ctx.gps)[:160], str(exc), "position"))
    rig = ctx.optional("rig_index", lambda: x.number("RigCameraIndex"))
    area = ctx.optional("panel_area", lambda: x.numbers("ReflectArea", allowed=(4, 8)))
    if area is not None:
        h, w = ctx.shape
        pts = np.asarray(area).reshape(-1, 2) if len(area) == 8 else np.asarray(
            [[area[0], area[1]], [area[0] + area[2], area[1] + area[3]]])
        if len(area) == 4 and (area[2] <= 0 or area[3] <= 0):
            ctx.problems.append(TagProblem(str(ctx.path), "XMP ReflectArea", str(area), "non-positive width or height",
                                           "panel_area"))
            area = None
        elif pts.min() < 0 or pts[:, 0].max() > w - 1 or pts[:, 1].max() > h - 1:
            ctx.problems.append(TagProblem(str(ctx.path), "XMP ReflectArea", str(area),
                                           f"lies outside the {w} x {h} image", "panel_area"))
            area = None
    albedo = ctx.optional("panel_albedo", lambda: x.number("Albedo"))
    if albedo == 0:  # no panel measured (MicaSense's own reader takes an unreadable Albedo as 0 too)
        albedo = None
    elif albedo is not None and not 0 < albedo <= 1:
        ctx.problems.append(TagProblem(str(ctx.path), "XMP Albedo", repr(albedo), "a panel reflectance is in (0, 1]",
                                       "panel_albedo"))
        albedo = None
    picture = ctx.optional("panel_albedo", lambda: x.number("CalibrationPicture", ("Camera",)))
    capture_id = next((v for ns, name in (*capture_id_tags(), *SHARED_CAPTURE_ID_TAGS)
                       if (v := x.text(name, (ns,))) is not None), None)
    return dict(
        capture_id=capture_id, rig_camera_index=None if rig is None else int(rig), reflect_area=area,
        lat=lat, lon=lon, alt_m=alt, time=_time(ctx.exif, x), make=ctx.make, model=ctx.model,
        rig_name=x.text("RigName", ("Camera",)), serial=ctx.serial, software=ctx.software,
        orientation=ctx.orientation, panel_albedo=albedo,
        calibration_picture=None if picture is None else int(picture),
    )


def meta_fields(ctx: TagContext) -> dict[str, Any]:
    """:func:`_common` and then every problem recorded while reading (both as fields)."""
    common = _common(ctx)
    return {**common, "problems": tuple(ctx.problems)}


def black_levels(ctx: TagContext) -> tuple[float, ...]:
    black = ctx.black_tag
    if isinstance(black, (tuple, list)):
        return tuple(float(v) for v in black)
    return (float(black),) if black is not None else ()


def positive_irradiance(ctx: TagContext, tag: str, ns: Sequence[str]) -> float | None:
    def read() -> float | None:
        v = ctx.xmp.numbers(tag, ns)
        if v is None:
            return None
        if not v[0] > 0:
            raise TagError(f"XMP {tag}", ctx.xmp.raw(tag, ns), "not a positive number", ctx.path)
        return v[0]

    return ctx.optional("sun_sensor", read)



def radiance_tag(ctx: TagContext, tag: str, count: int | None = None) -> tuple[float, ...] | None:
    try:
        return ctx.xmp.numbers(tag, count=count)
    except TagError as exc:
        raise FrameError(f"XMP {exc.reason}", path=ctx.path, hint=FIRMWARE_HINT) from None



class VignettingTags(NamedTuple):
    """The tags a band's factory vignetting is computed from (hashable: the map is computed
    once per shape and tags, :func:`factory_vignetting`)."""

    center: tuple[float, float] | None
    poly: tuple[float, ...] | None
    poly_2d: tuple[float, ...] | None
    exponents_2d: tuple[float, ...] | None
    maker: tuple[tuple[str, Any], ...] = ()  # CaptureMeta.maker_tags: a maker's own vignetting values

    @classmethod
    def of(cls, meta: CaptureMeta) -> VignettingTags:
        return cls(meta.vignetting_center, meta.vignetting_polynomial,
                   meta.vignetting_polynomial_2d, meta.vignetting_polynomial_2d_exponents, meta.maker_tags)

    def maker_tag(self, name: str, default: Any = None) -> Any:
        """The value ``name`` of :attr:`maker` (as :meth:`CaptureMeta.maker_tag`), else ``default``."""
        return next((v for k, v in self.maker if k == name), default)


def sample_shift(dn_shift: int, bit_depth: int, stored_bits: int | None) -> int:
    """Right shift from one file's samples to sensor DN: ``dn_shift`` (the catalog's, for data
    in the high bits of a wider container), less for a file with fewer bits per sample than
    that container, 0 for one holding the ``bit_depth``-bit DN as they are; ``stored_bits``
    None (not known): ``dn_shift``."""
    if stored_bits is None:
        return dn_shift
    return min(dn_shift, max(0, int(stored_bits) - bit_depth))


@dataclass(frozen=True, eq=False)
class FieldParts:
    """Components of one band fitted in the field that replace the factory's (see
    :mod:`mscal_core.factory`): ``inverse_response`` U over the sensor DN (Eq. 5-7) and
    ``vignetting`` V ``(H, W)``, max 1 (Eq. 8-10); None keeps the factory's."""

    inverse_response: np.ndarray | None = None
    vignetting: np.ndarray | None = None
    dn_shift: int = 0  # the camera's: stored DN = sensor DN << dn_shift (4 for 12-bit data in 16-bit TIFFs)
    sensor_bits: int = 16  # the sensor's bits per DN: a file with fewer bits per sample is shifted less

    def shift_for(self, meta: "CaptureMeta") -> int:
        """The shift of ``meta``'s file to sensor DN (:func:`sample_shift`):
        :attr:`dn_shift`, less when the file stores fewer bits per sample (a RedEdge's packed
        12-bit TIFF: 0)."""
        return sample_shift(self.dn_shift, self.sensor_bits, meta.bits_per_sample)



def factory_vignetting(meta: CaptureMeta) -> np.ndarray:
    """The factory vignetting correction ``(H, W)`` of one band file (>= 1, multiplies DN).

    The map depends only on the band's shape and vignetting tags, which are the same in
    every capture of a camera: it is computed once per process and tags
    (:func:`_vignetting_of`; 0.1 s of a 1280 x 960 band, more than the rest of the band's
    radiance) and returned read-only. Tags whose map is not finite and positive everywhere
    (a corrupt polynomial: a denominator through zero or overflowing) raise :class:`FrameError`
    naming the file."""
    v, ok = _vignetting_of(meta.radiometry, meta.shape, VignettingTags.of(meta))
    if not ok:
        tags = maker_of(meta.radiometry).vignetting_tags or "the vignetting tags"
        raise FrameError(f"the vignetting tags give a correction that is not finite and positive over the image "
                         f"({tags} damaged)", path=meta.path,
                         hint="copy the band file again from the camera's card; a file with damaged calibration "
                              "tags cannot be used with --calibration factory")
    return v


@lru_cache(maxsize=16)  # a few bands of one or two cameras; 10 MB each at 1280 x 960
def _vignetting_of(radiometry: str, shape: tuple[int, int], tags: VignettingTags) -> tuple[np.ndarray, bool]:
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # judged below, once per tag set
        v = maker_of(radiometry).vignetting(radiometry, shape, tags)
    v.flags.writeable = False  # shared by every capture: a caller that wrote into it would change the next ones
    return v, bool(np.all(np.isfinite(v)) and np.all(v > 0))


def upright_meta(meta: CaptureMeta, image: np.ndarray) -> np.ndarray:
    """``image`` (stored orientation, last two axes) as meant to be seen (EXIF Orientation;
    Parrot Sequoia stores its frames rotated 180 degrees)."""
    try:
        return upright(image, meta.orientation)
    except ValueError as exc:
        raise FrameError(str(exc), path=meta.path) from None


def reflectance_factor(meta: CaptureMeta) -> float | None:
    """``k = c / E`` with reflectance ``R = k L`` from the band's own sun sensor, ``c`` the camera
    model's one fixed scale (:func:`pipeline.ingest.sun_scale.sun_sensor_scales`: MicaSense pi,
    DJI 1 as DJI's guides write it, Sequoia Parrot's K fixed at 5e-4), or None when it has no
    usable reading or its sensor gives no reflectance (Sentera's ILS counts: use a panel)."""
    e, scale = meta.irradiance, sun_scale(meta.radiometry)
    if e is None or not math.isfinite(e) or e <= 0 or scale is None:
        return None
    return scale.constant / e


def no_reflectance_reason(meta: CaptureMeta) -> str | None:
    """Why the band's own sun sensor gives no reflectance factor (:func:`reflectance_factor`
    is None), naming the tag: the problem recorded when a sun-sensor tag was present but
    unusable; for a band its maker keeps out of reflectance, that; the maker's own reason
    (:attr:`pipeline.ingest.cameras.registry.Maker.no_reflectance`: a sensor with no
    conversion to reflectance); else the tag that is missing. None when the band has a usable
    reading."""
    if reflectance_factor(meta) is not None:
        return None
    why = [p.message() for p in meta.problems if p.feature == "sun_sensor"]
    if why:
        return why[0]
    if kept_out(meta.radiometry):
        return f"a {meta.radiometry} band has no sun-sensor reflectance"
    try:
        own = maker_of(meta.radiometry).no_reflectance
    except KeyError:
        own = None
    reason = own(meta) if own is not None else None
    if reason:
        return reason
    tag = sun_sensor_tag(meta.radiometry) or "XMP Irradiance"
    return f"no sun-sensor reading: no {tag} in the file"


def sun_sensor_absolute(meta: CaptureMeta) -> bool:
    """Whether the sun-sensor route gives absolute reflectance (MicaSense) or relative: what
    the camera model's fixed scale says (:func:`pipeline.ingest.sun_scale.sun_sensor_scales`)."""
    scale = sun_scale(meta.radiometry)
    return scale is not None and scale.absolute

