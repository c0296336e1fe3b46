"""Factory radiometric metadata of one band file, pure Python (no exiftool), for every vendor
mscal knows: MicaSense (RedEdge, RedEdge-M/-MX, MX Dual, RedEdge-P, Altum, Altum-PT), Parrot
Sequoia, DJI Phantom 4 Multispectral / Mavic 3M, Sentera Double 4K / 6X.

A TIFF's EXIF (Make, Model, ExposureTime, ISO, FNumber, BlackLevel, Orientation, GPS,
DateTimeOriginal + SubsecTime) is read with tifffile, a JPEG's with exifread; the XMP packet
with :mod:`pipeline.ingest.xmp` (attributes, elements, rdf:Seq/Bag/Alt, numbers in one
``rdf:li``, namespaces by URI). Which radiometric model a file gets (``CaptureMeta.radiometry``)
follows from its tags: ``drone-dji:`` calibration tags -> ``dji``; ``Camera:SensorModel`` ->
``sequoia``; ``Camera:ColorTransform`` -> ``sentera``; ``MicaSense:RadiometricCalibration`` ->
``micasense``; a ``LWIR`` band -> ``thermal``; a ``Panchro`` band is read but marked.

A tag the *radiance* needs that is missing or unusable raises :class:`FrameError` naming the
file and the tag (mscal never silently falls back to raw DN). A tag only one feature needs
(ReflectArea: the panel's area; Irradiance: the sun sensor; GPS; RigCameraIndex) that is
present but unreadable is recorded in ``CaptureMeta.problems`` (file, tag, value, feature)
and disables that feature only.
"""

from __future__ import annotations

import base64
import itertools
import math
import re
import struct
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.factory import (
    color_transform,
    dji_alignment_map,
    dji_camera_value,
    dji_vignetting_correction,
    field_response_scale,
    field_response_signal,
    radiance,
    remap_band,
    sequoia_irradiance,
    sunshine_irradiance,
    thermal_kelvin,
    upright,
    vignetting_2d,
    vignetting_map,
)

from pipeline.ingest.catalog import sample_shift
from pipeline.ingest.exif import EXIF_CODES, exifread_tags, exposure_time, rational
from pipeline.ingest.gps import NoPosition
from pipeline.ingest.gps import exif_position as _gps
from pipeline.ingest.sun_scale import sun_scale
from pipeline.ingest.xmp import TagError, TagProblem, Xmp, jpeg_xmp_packet, legacy_properties, parse_numbers

if TYPE_CHECKING:
    from pipeline.ingest.catalog import Camera

FIRMWARE_HINT = "the camera firmware may be too old to write factory calibration; update it, or use a field calibration"
MAX_EXPOSURE_S = 1.0  # multispectral exposures are at most a few tens of ms
WAVELENGTH_RANGE_NM = (300.0, 1100.0)  # silicon sensors: anything else is a unit error
RADIANCE_UNITS = {
    "micasense": "W m-2 sr-1 nm-1",
    "sequoia": "1 (Parrot SEQ AN 01 irradiance on the sensor, SI-homogeneous with an arbitrary scale)",
    "dji": "1 (DJI camera value pCam (p - p_BL) V / (g t), relative)",
    "sentera": "1 (DN, crosstalk-corrected by Camera:ColorTransform where written, / (ISO/100 * exposure s), relative)",
    "thermal": "K",
    "panchro": "W m-2 sr-1 nm-1",
}


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
    dark_row_values: tuple[float, ...] | None
    radiometric_calibration: tuple[float, float, float] | None  # MicaSense a1, a2, a3
    vignetting_center: tuple[float, float] | None  # (x, y) pixels
    vignetting_polynomial: tuple[float, ...] | None  # k1..kn, lowest power first
    vignetting_polynomial_2d: tuple[float, ...] | None
    vignetting_polynomial_2d_exponents: tuple[float, ...] | None
    irradiance: float | None  # sun sensor reading (unit: irradiance_unit)
    capture_id: str | None
    rig_camera_index: int | None
    reflect_area: tuple[float, ...] | None  # panel region written by the camera, if any
    lat: float | None
    lon: float | None
    alt_m: float | None
    time: str | None  # ISO 8601, with fraction of a second when SubsecTime is present
    radiometry: str = "micasense"  # a key of RADIANCE_UNITS
    make: str | None = None
    model: str | None = None
    rig_name: str | None = None
    serial: str | None = None
    software: str | None = None
    orientation: int = 1  # EXIF Orientation (3: stored rotated 180 degrees)
    f_number: float | None = None
    iso: float | None = None
    sensor_model: tuple[float, float, float] | None = None  # Parrot A, B, C
    gain_adjustment: float | None = None  # drone-dji:SensorGainAdjustment
    dji_vignetting: tuple[float, ...] | None = None  # drone-dji:VignettingData k0..k5
    dji_center: tuple[float, float] | None = None  # drone-dji:CalibratedOpticalCenterX/Y
    dji_dewarp: tuple[float, ...] | None = None  # fx, fy, cx, cy, k1, k2, p1, p2, k3
    dji_hmatrix: tuple[float, ...] | None = None  # CalibratedHMatrix, 9 row-major values
    channel: int | None = None  # channel of a multi-channel file (Sentera JPEG)
    channel_mix: tuple[float, ...] | None = None  # Camera:ColorTransform, whole matrix
    irradiance_unit: str = "W m-2 nm-1"
    # MicaSense XMP Albedo: the reflectance of the panel in this band file, as the camera read
    # it from the panel's QR code (written in its panel captures with ReflectArea)
    panel_albedo: float | None = None
    calibration_picture: int | None = None  # XMP Camera:CalibrationPicture (Pix4D: 2, a valid panel capture)
    problems: tuple[TagProblem, ...] = ()
    # the file's XMP properties the sun-sensor model reads (SUN_SENSOR_XMP; sun_sensor_xmp)
    sun_sensor_props: tuple[tuple[str, str, str | tuple[str, ...]], ...] | None = field(
        default=None, compare=False, repr=False)

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
        return RADIANCE_UNITS[self.radiometry]

    @property
    def reflectance_band(self) -> bool:
        """True for a band that goes into reflectance (not thermal, not panchromatic)."""
        return self.radiometry not in ("thermal", "panchro")

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
            "factory_band_alignment": self.dji_hmatrix is not None,
        }


# --------------------------------------------------------------------------- XMP


def xmp_properties(packet: bytes | str, path: Path | str) -> dict[str, Any]:
    """Properties of an XMP packet in the Camera and MicaSense namespaces, by local name
    (kept for its callers; new code uses :class:`pipeline.ingest.xmp.Xmp`)."""
    return legacy_properties(packet, path)


# --------------------------------------------------------------------------- EXIF


def _int_tag(value: Any, default: int) -> int:
    """An integer tag (Orientation, ExifImageWidth) as int; ``default`` when it is missing or
    not one integer (another type, several values, text)."""
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return default
    return int(value)


def _time(exif: dict[str, Any], xmp: Xmp) -> str | None:
    """The exposure's time: :func:`pipeline.ingest.exif.exposure_time` of the file's tags."""
    return exposure_time(exif.get("DateTimeOriginal"), exif.get("SubsecTimeOriginal") or exif.get("SubsecTime"),
                         exif.get("OffsetTimeOriginal"), xmp.text("UTCAtExposure", ("drone-dji",)))


def _exposure(exif: dict[str, Any], path: Path) -> float:
    if "ExposureTime" not in exif:
        raise FrameError("no EXIF ExposureTime tag", path=path, hint=FIRMWARE_HINT)
    exposure = _number(exif["ExposureTime"], "EXIF ExposureTime", path)
    _check_exposure(exposure, "EXIF ExposureTime", path)
    return exposure


def _check_exposure(exposure: float, what: str, path: Path) -> None:
    if not (math.isfinite(exposure) and 0 < exposure <= MAX_EXPOSURE_S):
        raise FrameError(
            f"{what} {exposure!r} s is outside (0, {MAX_EXPOSURE_S:g}] s",
            path=path,
            hint="exposure must be in seconds; a value in ms or us means the file was rewritten with wrong units",
        )


def _number(value: Any, what: str, path: Path) -> float:
    """A RATIONAL or number tag as float (:func:`rational`; NaN for a zero denominator), a
    :class:`FrameError` naming the tag when it is text or another form that is no number."""
    try:
        return rational(value)
    except (TypeError, ValueError, ZeroDivisionError, IndexError, OverflowError):
        raise FrameError(f"{what} {str(value)[:40]!r} is not a number", path=path, hint=FIRMWARE_HINT) from None


def _iso(exif: dict[str, Any], path: Path) -> float:
    iso = exif.get("ISOSpeed") or exif.get("ISOSpeedRatings") or exif.get("PhotographicSensitivity")
    if isinstance(iso, (tuple, list)):
        iso = iso[0] if iso else None
    if not iso:
        raise FrameError("no EXIF ISOSpeed/ISOSpeedRatings tag (the gain)", path=path, hint=FIRMWARE_HINT)
    value = _number(iso, "EXIF ISO", path)
    if not (math.isfinite(value) and value > 0):
        raise FrameError(f"EXIF ISO {value!r} is not a positive number (the gain)", path=path, hint=FIRMWARE_HINT)
    return value


def _exposure_and_gain(exif: dict[str, Any], path: Path) -> tuple[float, float]:
    return _exposure(exif, path), _iso(exif, path) / 100.0


# --------------------------------------------------------------------------- the reader


@dataclass
class _Ctx:
    """What a vendor reader gets: the file's tags and a list to record feature problems in."""

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

    def required(self, tag: str, ns: Sequence[str] = ("Camera", "MicaSense"), count: int | None = None
                 ) -> tuple[float, ...]:
        try:
            v = self.xmp.numbers(tag, ns, count)
        except TagError as exc:
            raise FrameError(f"XMP {exc.reason}", path=self.path, hint=FIRMWARE_HINT) from None
        if v is None:
            raise FrameError(f"no XMP {tag} tag", path=self.path, hint=FIRMWARE_HINT)
        return v


def read_capture_meta(path: str | Path) -> CaptureMeta:
    """Factory metadata of one single-band file; :class:`FrameError` naming the file and tag
    if its radiance cannot be computed. (Multi-channel files: :func:`read_file_metas`.)"""
    metas = read_file_metas(path)
    return metas[0]


def read_file_metas(path: str | Path) -> list[CaptureMeta]:
    """Factory metadata of every band a file holds (one for TIFF band files, one per kept
    channel of a Sentera JPEG)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError("file does not exist", path=path)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return _read_jpeg(path)
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) == 0:  # header read, but the first IFD lies past the end of the file
                raise FrameError("TIFF has no readable image directory (file truncated?)", path=path,
                                 hint="copy the file again from the camera's card")
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}
            shape = (int(page.imagelength), int(page.imagewidth))
            bits = int(page.bitspersample)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise FrameError(f"not a readable TIFF ({type(exc).__name__}: {exc})", path=path,
                         hint="copy the file again from the camera's card") from None
    if 700 not in tags:
        raise FrameError("no XMP packet (TIFF tag 700)", path=path, hint=FIRMWARE_HINT)
    return [meta_from_tags(path, tags, shape, bits)]


def meta_from_tags(path: Path, tags: dict[int, Any], shape: tuple[int, int], bits: int) -> CaptureMeta:
    """Build and check a :class:`CaptureMeta` from a TIFF's tag values keyed by tag code."""
    xmp = Xmp.parse(tags[700], path)
    exif = dict(tags[34665]) if isinstance(tags.get(34665), dict) else {}  # an EXIF IFD tifffile could not follow: none
    for name, code in EXIF_CODES.items():  # EXIF tags a camera wrote into IFD0 (Sentera 6X)
        if name not in exif and code in tags:
            exif[name] = tags[code]
    ctx = _Ctx(
        path=path, xmp=xmp, exif=exif, gps=dict(tags[34853]) if isinstance(tags.get(34853), dict) else {},
        shape=shape, bits=bits, make=_clean(tags.get(271)), model=_clean(tags.get(272)), software=_clean(tags.get(305)),
        serial=_clean(exif.get("BodySerialNumber") or tags.get(50735)), orientation=_int_tag(tags.get(274), 1),
        black_tag=tags.get(50714),
    )
    metas = _with_sun_sensor_props(ctx, _dispatch(ctx))
    return metas[0]


#: Local names of the XMP properties read by the sun-sensor model
#: (:mod:`pipeline.apply.sunlight`: orientation, DLS 2 split, Sequoia's IrradianceList): kept
#: on each band's metadata, so the sun sensor reads no file a second time.
SUN_SENSOR_XMP = frozenset({
    "Yaw", "Pitch", "Roll", "IrradianceYaw", "IrradiancePitch", "IrradianceRoll", "Irradiance",
    "DirectIrradiance", "ScatteredIrradiance", "HorizontalIrradiance", "IrradianceList", "IrradianceScaleToSIUnits",
    "FlightYawDegree", "FlightPitchDegree", "FlightRollDegree",  # DJI: the aircraft's, when no sensor's own
})


def _with_sun_sensor_props(ctx: _Ctx, metas: list[CaptureMeta]) -> list[CaptureMeta]:
    props = tuple((ns, name, tuple(v) if isinstance(v, list) else v)
                  for (ns, name), v in ctx.xmp.props.items() if name in SUN_SENSOR_XMP)
    return [replace(m, sun_sensor_props=props) for m in metas]


def sun_sensor_xmp(meta: CaptureMeta) -> Xmp | None:
    """The XMP properties of ``meta``'s file that the sun-sensor model reads
    (:data:`SUN_SENSOR_XMP`), as kept when the file was read; None for metadata made
    otherwise (read the file's XMP then)."""
    if meta.sun_sensor_props is None:
        return None
    return Xmp({(ns, name): list(v) if isinstance(v, tuple) else v for ns, name, v in meta.sun_sensor_props},
               meta.path)


def _clean(value: Any) -> str | None:
    if value is None:
        return None
    text = value.decode("latin-1", errors="replace") if isinstance(value, bytes) else str(value)
    text = text.strip().strip("\x00").strip()
    return text or None


def _dispatch(ctx: _Ctx) -> list[CaptureMeta]:
    x = ctx.xmp
    band = x.text("BandName") or x.text("BandName", ("drone-dji",))
    if band is not None and band.upper() == "LWIR":
        return [_minimal(ctx, band, "thermal")]
    if band is not None and band.casefold().startswith("panchro"):
        try:
            return [_micasense(ctx, panchro=True)]
        except FrameError:  # a band kept out of reflectance need not carry a full radiometric model
            return [_minimal(ctx, band, "panchro")]
    if x.has("SensorGain", ("drone-dji",)) or x.has("VignettingData", ("drone-dji",)):
        return [_dji(ctx)]
    if x.has("SensorModel", ("Camera",)) or (ctx.make or "").lower() == "parrot":
        return [_sequoia(ctx)]
    if x.has("ColorTransform", ("Camera",)) or (ctx.make or "").lower() == "sentera":
        return _sentera(ctx)
    return [_micasense(ctx)]


def _band(ctx: _Ctx) -> tuple[str, float, float | None]:
    """Band name, centre wavelength and FWHM (nm) of a single-band file, units checked."""
    x = ctx.xmp
    name = x.text("BandName") or x.text("BandName", ("drone-dji",))
    if name is None:
        if x.has("BandName"):
            raise FrameError(f"XMP BandName is {x.raw('BandName')!r}, expected one name", path=ctx.path,
                             hint=FIRMWARE_HINT)
        raise FrameError("no XMP BandName tag", path=ctx.path, hint=FIRMWARE_HINT)
    wl = ctx.required("CentralWavelength", count=1)[0]
    _check_wavelength(wl, ctx.path)
    fwhm = ctx.optional("bandwidth", lambda: x.numbers("WavelengthFWHM", count=1))
    return name, wl, fwhm[0] if fwhm else None


def _check_wavelength(wl: float, path: Path) -> None:
    lo, hi = WAVELENGTH_RANGE_NM
    if not lo <= wl <= hi:
        raise FrameError(f"XMP CentralWavelength {wl:g} is outside {lo:g}-{hi:g} nm", path=path,
                         hint="the wavelength must be in nanometres")


def _common(ctx: _Ctx) -> dict[str, Any]:
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
    capture_id = (x.text("CaptureId", ("MicaSense",)) or x.text("CaptureUUID", ("drone-dji",))
                  or x.text("CaptureUUID", ("Camera",)) or x.text("ImageUniqueID", ("Camera",)))
    return dict(
        capture_id=capture_id, rig_camera_index=None if rig is None else int(rig), reflect_area=area,
        lat=lat, lon=lon, alt_m=alt, time=_time(ctx.exif, x), make=ctx.make, model=ctx.model,
        rig_name=x.text("RigName", ("Camera",)), serial=ctx.serial, software=ctx.software,
        orientation=ctx.orientation, panel_albedo=albedo,
        calibration_picture=None if picture is None else int(picture),
    )


def _finish(ctx: _Ctx) -> dict[str, Any]:
    """:func:`_common` and then every problem recorded while reading (both as fields)."""
    common = _common(ctx)
    return {**common, "problems": tuple(ctx.problems)}


def _black_levels(ctx: _Ctx) -> tuple[float, ...]:
    black = ctx.black_tag
    if isinstance(black, (tuple, list)):
        return tuple(float(v) for v in black)
    return (float(black),) if black is not None else ()


def _positive_irradiance(ctx: _Ctx, tag: str, ns: Sequence[str]) -> float | None:
    def read() -> float | None:
        v = ctx.xmp.numbers(tag, ns)
        if v is None:
            return None
        if not v[0] > 0:
            raise TagError(f"XMP {tag}", ctx.xmp.raw(tag, ns), "not a positive number", ctx.path)
        return v[0]

    return ctx.optional("sun_sensor", read)


def _micasense(ctx: _Ctx, panchro: bool = False) -> CaptureMeta:
    """MicaSense: micasense/imageprocessing ``image.py`` ``radiance()`` (cameras.md §1.3)."""
    x, path = ctx.xmp, ctx.path
    exposure, gain = _exposure_and_gain(ctx.exif, path)
    exposure = micasense_exposure(exposure, ctx.model)
    name, wl, fwhm = _band(ctx)
    black = _black_levels(ctx)
    dark = ctx.optional(None, lambda: x.numbers("DarkRowValue"))
    if not black and not dark:
        raise FrameError("no EXIF BlackLevel and no XMP DarkRowValue tag", path=path, hint=FIRMWARE_HINT)
    cal = ctx.required("RadiometricCalibration", count=3)
    if cal[0] <= 0:
        raise FrameError(f"XMP RadiometricCalibration a1 = {cal[0]!r} must be positive", path=path, hint=FIRMWARE_HINT)
    center = _radiance_tag(ctx, "VignettingCenter", 2)
    poly = _radiance_tag(ctx, "VignettingPolynomial")
    poly2d = _radiance_tag(ctx, "VignettingPolynomial2D")
    exps2d = _radiance_tag(ctx, "VignettingPolynomial2DName")
    if poly2d and exps2d and len(exps2d) != 2 * len(poly2d):
        raise FrameError(f"XMP VignettingPolynomial2DName has {len(exps2d)} exponents for {len(poly2d)} "
                         "coefficients of VignettingPolynomial2D (two per coefficient)", path=path, hint=FIRMWARE_HINT)
    if not ((center and poly) or (poly2d and exps2d)):
        raise FrameError(
            "no vignetting model: needs XMP VignettingCenter + VignettingPolynomial "
            "or VignettingPolynomial2D + VignettingPolynomial2DName",
            path=path,
            hint=FIRMWARE_HINT,
        )
    irr = _micasense_irradiance(ctx)
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=gain, black_levels=black, dark_row_values=dark,
        radiometric_calibration=(cal[0], cal[1], cal[2]),
        vignetting_center=(center[0], center[1]) if center else None, vignetting_polynomial=poly,
        vignetting_polynomial_2d=poly2d, vignetting_polynomial_2d_exponents=exps2d, irradiance=irr,
        radiometry="panchro" if panchro else "micasense", iso=gain * 100.0,
        **_finish(ctx),
    )


#: The ExposureTime some legacy RedEdge firmware wrote for its shortest exposure, and the
#: exposure it really used (micasense/imageprocessing ``metadata.py`` ``exposure()``: "correct
#: for incorrect exposure in some legacy RedEdge firmware versions"; every model but Altum).
LEGACY_REDEDGE_EXPOSURE = (1.0 / 6329.0, 0.000274)


def micasense_exposure(exposure_s: float, model: str | None) -> float:
    """A MicaSense file's EXIF ExposureTime in seconds, with the legacy RedEdge firmware's
    wrong 1/6329 s replaced by the 0.274 ms it used (:data:`LEGACY_REDEDGE_EXPOSURE`)."""
    wrong, used = LEGACY_REDEDGE_EXPOSURE
    if (model or "").strip().lower() != "altum" and abs(exposure_s - wrong) < 1e-6:
        return used
    return exposure_s


def _micasense_irradiance(ctx: _Ctx) -> float | None:
    """Spectral irradiance on the DLS, W m-2 nm-1: ``Camera:Irradiance`` (the reading on the
    sensor's own plane), else DLS 2's ``HorizontalIrradiance``; either times the file's
    irradiance scale (:func:`_micasense_irradiance_scale`). DLS 2 firmware still writes the
    legacy ``Irradiance`` tag beside ``HorizontalIrradiance``, in the same uW cm-2 nm-1 as its
    other irradiance tags ("DLS2 irradiance units",
    https://github.com/micasense/imageprocessing/issues/47): read
    unscaled it gave reflectance 100x too low."""
    ns = ("Camera", "MicaSense", "DLS")
    irr = _positive_irradiance(ctx, "Irradiance", ("Camera", "MicaSense"))
    if irr is None:
        irr = _positive_irradiance(ctx, "HorizontalIrradiance", ns)
    if irr is None:
        return None
    scale = _micasense_irradiance_scale(ctx)
    return None if scale is None else irr * scale


def _micasense_irradiance_scale(ctx: _Ctx) -> float | None:
    """The factor to W m-2 nm-1 of a MicaSense file's irradiance tags, as micasense/imageprocessing
    ``metadata.py`` ``irradiance_scale_factor()`` takes it: ``IrradianceScaleToSIUnits`` when the
    file has it; else 0.01 when it has DLS 2's ``HorizontalIrradiance`` (uW cm-2 nm-1); else 1
    (DLS 1). None, with the problem recorded, when the scale tag is there but not a positive number."""
    ns = ("Camera", "MicaSense", "DLS")

    def read() -> float | None:
        v = ctx.xmp.numbers("IrradianceScaleToSIUnits", ns)
        if v is None:
            return 0.01 if ctx.xmp.has("HorizontalIrradiance", ns) else 1.0
        if not (math.isfinite(v[0]) and v[0] > 0):
            raise TagError("XMP IrradianceScaleToSIUnits", ctx.xmp.raw("IrradianceScaleToSIUnits", ns),
                           "not a positive number", ctx.path)
        return v[0]

    return ctx.optional("sun_sensor", read)


def _radiance_tag(ctx: _Ctx, tag: str, count: int | None = None) -> tuple[float, ...] | None:
    try:
        return ctx.xmp.numbers(tag, count=count)
    except TagError as exc:
        raise FrameError(f"XMP {exc.reason}", path=ctx.path, hint=FIRMWARE_HINT) from None


def _minimal(ctx: _Ctx, band: str, radiometry: str) -> CaptureMeta:
    """A band read for what it is but never part of reflectance: LWIR (Altum, Altum-PT;
    centi-kelvin DN) or a panchromatic band without a full radiometric model."""
    x = ctx.xmp
    wl = ctx.optional(None, lambda: x.number("CentralWavelength")) or 11000.0
    exposure = _number(ctx.exif["ExposureTime"], "EXIF ExposureTime", ctx.path) if "ExposureTime" in ctx.exif else 0.0
    return CaptureMeta(
        path=ctx.path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=band, wavelength_nm=wl, fwhm_nm=None,
        exposure_s=exposure, gain=1.0, black_levels=(), dark_row_values=None, radiometric_calibration=None,
        vignetting_center=None, vignetting_polynomial=None, vignetting_polynomial_2d=None,
        vignetting_polynomial_2d_exponents=None, irradiance=None, radiometry=radiometry,
        **_finish(ctx),
    )


def _sequoia(ctx: _Ctx) -> CaptureMeta:
    """Parrot Sequoia: SensorModel (A, B, C), VignettingPolynomial2D, IrradianceList."""
    x, path = ctx.xmp, ctx.path
    exposure = _exposure(ctx.exif, path)
    iso = _iso(ctx.exif, path)
    name, wl, fwhm = _band(ctx)
    model = ctx.required("SensorModel", ("Camera",), 3)
    if "FNumber" not in ctx.exif:
        raise FrameError("no EXIF FNumber tag (Parrot's sensor model needs it)", path=path, hint=FIRMWARE_HINT)
    f_number = _number(ctx.exif["FNumber"], "EXIF FNumber", path)
    if not (math.isfinite(f_number) and 0.5 < f_number < 64):
        raise FrameError(f"EXIF FNumber {f_number!r} is not an f-number", path=path)
    poly2d = _radiance_tag(ctx, "VignettingPolynomial2D")
    exps2d = _radiance_tag(ctx, "VignettingPolynomial2DName")
    if not (poly2d and exps2d) or len(exps2d) != 2 * len(poly2d):
        raise FrameError("no usable vignetting model: needs XMP VignettingPolynomial2D and "
                         "VignettingPolynomial2DName (two exponents per coefficient)", path=path, hint=FIRMWARE_HINT)
    irr = ctx.optional("sun_sensor", lambda: _sequoia_sunshine(x, path))
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=iso / 100.0, black_levels=_black_levels(ctx), dark_row_values=None,
        radiometric_calibration=None, vignetting_center=None, vignetting_polynomial=None,
        vignetting_polynomial_2d=poly2d, vignetting_polynomial_2d_exponents=exps2d, irradiance=irr,
        radiometry="sequoia", f_number=f_number, iso=iso, sensor_model=(model[0], model[1], model[2]),
        irradiance_unit="1 (sunshine CH0 / (gain x ms x golden sensitivity), relative)", **_finish(ctx),
    )


#: How band files' metadata are read, in the fingerprints of runs on them: a change here gives
#: the same files and options other results, so an earlier run is not reused as up to date.
METADATA_READING = ("2026-12-05: exposure times in UTC when the file says so; XMP Albedo panels; 12-bit files by their "
                    "depth; EXIF values that are none (zero denominators, empty fields) left out; GPS 0/0, void or "
                    "unreachable: no position")


SUNSHINE_RECORD = struct.Struct("<QHHHHfff")  # timestamp us, CH0, CH1, gain index, integration ms, yaw, pitch, roll


def sunshine_records(x: Xmp, path: Path | None = None) -> list[tuple] | None:
    """The records of a Sequoia's ``Camera:IrradianceList`` (base64 of :data:`SUNSHINE_RECORD`
    structs: timestamp, CH0, CH1, gain index, integration ms, yaw, pitch, roll), or None when
    the tag is absent; :class:`TagError` when it cannot be decoded."""
    raw = x.text("IrradianceList", ("Camera",))
    if raw is None:
        return None
    try:
        blob = base64.b64decode("".join(raw.split()), validate=True)
    except (ValueError, TypeError):
        raise TagError("XMP IrradianceList", raw, "not base64", path) from None
    if len(blob) == 0 or len(blob) % SUNSHINE_RECORD.size:
        raise TagError("XMP IrradianceList", raw, f"{len(blob)} bytes is not a whole number of "
                       f"{SUNSHINE_RECORD.size}-byte records (firmware before 1.1.0?)", path)
    return list(SUNSHINE_RECORD.iter_unpack(blob))


def _sequoia_sunshine(x: Xmp, path: Path) -> float | None:
    """Relative irradiance of the band's sunshine sensor from ``Camera:IrradianceList``
    (base64 of 28-byte records) and ``IrradianceCalibrationMeasurement`` (gain index,
    exposure ms, CH0, CH1 rows); :func:`mscal_core.factory.sunshine_irradiance`, divided by
    the band's CH0 sensitivity ``IrradianceSensitivitiesGolden[0]`` so that the four bands'
    readings share one scale. That division is inferred from the tag's name (no Parrot text
    found): on the real capture in ../shared/data it turns an implausible spectrum (red edge
    4x the others) into a vegetation-like one (NIR > red edge > green > red). Without the tag
    the band has no reading (a sun_sensor problem naming it): every band shares Parrot's one
    constant K (:mod:`pipeline.ingest.sun_scale`), so a per-band sensitivity left out would
    not cancel but change every index."""
    recs = sunshine_records(x, path)
    if recs is None:
        return None
    raw = x.text("IrradianceList", ("Camera",))
    table = x.numbers("IrradianceCalibrationMeasurement", ("Camera",))
    if table is None or len(table) % 4:
        raise TagError("XMP IrradianceCalibrationMeasurement", x.raw("IrradianceCalibrationMeasurement", ("Camera",)),
                       "expected rows of (gain index, exposure ms, CH0, CH1)", path)
    cal = {int(table[i]): table[i + 2] / table[i + 1] for i in range(0, len(table), 4)
           if table[i + 1] > 0 and table[i + 2] < 65535}
    try:
        counts = sunshine_irradiance([r[1] for r in recs], [r[3] for r in recs], [r[4] for r in recs], cal)
    except ValueError as exc:
        raise TagError("XMP IrradianceList", raw, str(exc), path) from None
    sens = x.numbers("IrradianceSensitivitiesGolden", ("Camera",))
    if sens is None:
        raise TagError("XMP IrradianceSensitivitiesGolden", "(missing)", "not in the file (older firmware?): the "
                       "bands' sunshine readings cannot be put on one scale without it", path)
    if not sens[0] > 0:
        raise TagError("XMP IrradianceSensitivitiesGolden", x.raw("IrradianceSensitivitiesGolden", ("Camera",)),
                       "expected the CH0 and CH1 sensitivities (positive): the bands' sunshine readings cannot be "
                       "compared without them", path)
    return counts / sens[0]


def _dji(ctx: _Ctx) -> CaptureMeta:
    """DJI P4 Multispectral / Mavic 3M (drone-dji namespace, attributes)."""
    x, path = ctx.xmp, ctx.path
    dj = ("drone-dji",)
    name, wl, fwhm = _dji_band(ctx)
    black = _black_levels(ctx) or (ctx.required("BlackLevel", dj, 1) if x.has("BlackLevel", dj) or not x.has(
        "BlackCurrent", dj) else ctx.required("BlackCurrent", dj, 1))  # BlackCurrent: the Mavic 3M manual's name
    gain = ctx.required("SensorGain", dj, 1)[0]
    if not gain > 0:
        raise FrameError(f"XMP drone-dji:SensorGain {gain!r} must be positive", path=path)
    exposure_us = ctx.required("ExposureTime", dj, 1)[0]
    exposure = exposure_us * 1e-6
    _check_exposure(exposure, f"XMP drone-dji:ExposureTime {exposure_us:g} us =", path)
    adj = ctx.required("SensorGainAdjustment", dj, 1)[0]
    k = ctx.required("VignettingData", dj, 6)
    cx = ctx.required("CalibratedOpticalCenterX", dj, 1)[0]
    cy = ctx.required("CalibratedOpticalCenterY", dj, 1)[0]
    h, w = ctx.shape
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise FrameError(f"XMP drone-dji:CalibratedOpticalCenterX/Y ({cx:g}, {cy:g}) lies outside the {w} x {h} "
                         "image (it must be in pixels)", path=path)
    irr = _positive_irradiance(ctx, "Irradiance", dj)
    dewarp = ctx.optional("dewarp", lambda: _dji_dewarp(x, path))
    hmat = ctx.optional("band_alignment", lambda: x.numbers("CalibratedHMatrix", dj, 9) or x.numbers(
        "DewarpHMatrix", dj, 9))
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=gain, black_levels=tuple(black), dark_row_values=None, radiometric_calibration=None,
        vignetting_center=None, vignetting_polynomial=None, vignetting_polynomial_2d=None,
        vignetting_polynomial_2d_exponents=None, irradiance=irr, radiometry="dji", gain_adjustment=adj,
        dji_vignetting=k, dji_center=(cx, cy), dji_dewarp=dewarp, dji_hmatrix=hmat,
        irradiance_unit="1 (DJI calibrated sunlight sensor value)", **_finish(ctx),
    )


def _dji_band(ctx: _Ctx) -> tuple[str, float, float | None]:
    """Band of a DJI file: Camera:BandName/CentralWavelength if written, else drone-dji:BandName
    and BandFreq ``840(+/-26)nm``."""
    x = ctx.xmp
    if x.has("CentralWavelength"):
        return _band(ctx)
    name = x.text("BandName", ("drone-dji",)) or x.text("BandName")
    freq = x.text("BandFreq", ("drone-dji",))
    m = _DJI_BAND_FREQ.match(freq or "")
    own = ctx.optional(None, lambda: x.numbers("CentralWavelength", ("drone-dji",), 1))
    if name is None or (m is None and own is None):
        raise FrameError("no band name and centre wavelength (XMP Camera:CentralWavelength, drone-dji:"
                         f"CentralWavelength or drone-dji:BandFreq like 840(+/-26)nm; got {freq!r})",
                         path=ctx.path, hint=FIRMWARE_HINT)
    wl = own[0] if own is not None else float(m[1])  # type: ignore[index]
    _check_wavelength(wl, ctx.path)
    return name, wl, (2 * float(m[2])) if m is not None and m[2] else None


#: drone-dji:BandFreq: ``840(+/-26)nm`` (P4 Multispectral Image Processing Guide), ``560(±16)nm``
#: (Mavic 3M User Manual, "Photo File"), spaces allowed.
_DJI_BAND_FREQ = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*(?:\(\s*(?:\+/-|\+-|±)\s*([0-9]+(?:\.[0-9]*)?)\s*\))?\s*nm\s*$")


def _dji_dewarp(x: Xmp, path: Path) -> tuple[float, ...] | None:
    raw = x.text("DewarpData", ("drone-dji",))
    if raw is None:
        return None
    nums = parse_numbers(raw.split(";", 1)[-1]) or ()
    if len(nums) != 9:
        raise TagError("XMP drone-dji:DewarpData", raw, "expected 'date;fx,fy,cx,cy,k1,k2,p1,p2,k3'", path)
    return tuple(nums)


def _read_jpeg(path: Path) -> list[CaptureMeta]:
    """A JPEG of a multi-channel camera (Sentera Double 4K): EXIF with exifread, XMP from APP1."""
    data = path.read_bytes()
    if data[:2] != b"\xff\xd8":
        raise FrameError("not a JPEG file", path=path)
    packet = jpeg_xmp_packet(data)
    if packet is None:
        raise FrameError("no XMP packet (JPEG APP1 http://ns.adobe.com/xap/1.0/)", path=path, hint=FIRMWARE_HINT)
    exif, gps = _jpeg_exif(data, path)
    width = _int_tag(exif.get("ExifImageWidth"), 0)
    height = _int_tag(exif.get("ExifImageLength"), 0)
    if not (0 < width <= 1 << 16 and 0 < height <= 1 << 16):  # a JPEG is at most 65535 pixels a side
        width = height = 0
    if not (width and height):
        import cv2

        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FrameError("JPEG could not be decoded", path=path)
        height, width = img.shape[:2]
    ctx = _Ctx(
        path=path, xmp=Xmp.parse(packet, path), exif=exif, gps=gps, shape=(height, width), bits=8,
        make=_clean(exif.get("Make")), model=_clean(exif.get("Model")), software=_clean(exif.get("Software")),
        serial=_clean(exif.get("BodySerialNumber")), orientation=_int_tag(exif.get("Orientation"), 1), black_tag=None,
    )
    return _with_sun_sensor_props(ctx, _dispatch(ctx))


def _jpeg_exif(data: bytes, path: Path | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """A JPEG's EXIF and GPS tags, named and shaped as tifffile gives a TIFF's
    (:func:`pipeline.ingest.exif.exifread_tags`: what is not a value -- the thumbnail, a maker
    note, an empty field, a zero denominator -- is left out). IFD0 and the EXIF IFD make one
    dict (the EXIF IFD's tag wins), the GPS IFD the other. EXIF that exifread cannot parse
    raises :class:`FrameError`; a JPEG without EXIF gives two empty dicts."""
    import io

    try:
        tags = exifread_tags(io.BytesIO(data))
    except Exception as exc:  # exifread raises a zoo of errors on corrupt EXIF
        raise FrameError(f"EXIF unreadable ({type(exc).__name__}: {str(exc)[:80]})", path=path,
                         hint="copy the file again from the camera's card") from None
    exif: dict[str, Any] = {}
    gps: dict[str, Any] = {}
    for key, value in tags.items():  # IFD0's, then the EXIF IFD's, then the GPS IFD's
        group, _, name = key.partition(" ")
        name = name.replace("SubSecTime", "SubsecTime")  # exifread's spelling -> tifffile's
        (gps if group == "GPS" else exif)[name] = value
    return exif, gps


#: The JPEG beside a capture's band files that holds its position when they do not: Parrot
#: Sequoia's ``<capture>_RGB.JPG`` (OpenDroneMap contrib/sequoia: the camera "captures five
#: images per shot, an RGB JPG and four single band TIFs, but only the JPG contains GPS Exif
#: tags").
RGB_SIBLING_SUFFIX = "_RGB"


def sibling_position(folder: Path, capture: str) -> tuple[float, float, float | None] | None:
    """``(lat, lon, alt_m)`` from the EXIF GPS of ``folder/<capture>_RGB.JPG`` (or ``.jpg``), or
    None when there is no such file or it has no usable position."""
    for suffix, ext in itertools.product((RGB_SIBLING_SUFFIX, RGB_SIBLING_SUFFIX.lower()), (".JPG", ".jpg", ".jpeg")):
        path = folder / f"{capture}{suffix}{ext}"
        if not path.is_file():
            continue
        try:
            _, gps = _jpeg_exif(path.read_bytes(), path)
            lat, lon, alt = _gps(gps)
        except (OSError, FrameError, TypeError, ValueError, ZeroDivisionError, IndexError, KeyError):
            return None
        if lat is None or lon is None or not (math.isfinite(lat) and math.isfinite(lon)) or (lat, lon) == (0.0, 0.0):
            return None
        return lat, lon, alt
    return None


#: Images a camera saves beside its band files that are not band files, by catalog camera:
#: the file-name pattern (group ``capture``: the capture the image belongs to, as the camera's
#: ``capture_pattern`` names it in its band files) and why the image is left out. The P4
#: Multispectral numbers the six files of a capture as one: its RGB camera's ``DJI_XXX0.JPG``,
#: then the band files ``DJI_XXX1.TIF`` .. ``DJI_XXX5.TIF``.
COMPANION_IMAGES: dict[str, tuple[str, str]] = {
    "dji-p4-multispectral": (r"(?i)^DJI_(?P<capture>[0-9]+)0\.jpe?g$",
                             "RGB camera image of the DJI P4 Multispectral (not a band file)"),
}


def companion_images(files: Sequence[Path], camera: Camera) -> dict[Path, str]:
    """Of ``files``, the images ``camera`` saves with its band files (:data:`COMPANION_IMAGES`)
    whose capture has band files among ``files`` in the same folder, with why each is left
    out of the captures. A file only named like one (no band file of its capture beside it)
    is not one."""
    entry = COMPANION_IMAGES.get(camera.name)
    if entry is None:
        return {}
    companion, reason = re.compile(entry[0]), entry[1]
    bands = capture_pattern(camera)
    captures = {(p.parent, m["capture"]) for p in files if (m := bands.match(p.name)) is not None}
    out = {}
    for p in files:
        m = companion.match(p.name)
        if m is not None and not bands.match(p.name) and (p.parent, m["capture"]) in captures:
            out[p] = reason
    return out


def _sentera(ctx: _Ctx) -> list[CaptureMeta]:
    """Sentera Double 4K (JPEG, three channels, Camera:ColorTransform) and 6X (one TIFF per
    band). Radiance is relative: crosstalk-corrected DN / (ISO/100 x exposure), Sentera's
    "autoexposure" normalisation (SenteraLLC py-radiometric-corrections); the ILS
    (``Camera:SunSensor``) is kept as the band's sun-sensor reading, in counts."""
    x, path = ctx.xmp, ctx.path
    exposure, gain = _exposure_and_gain(ctx.exif, path)
    names = x.texts("BandName") or []
    wls = ctx.required("CentralWavelength")
    fwhms = ctx.optional(None, lambda: x.numbers("WavelengthFWHM")) or ()
    if len(names) != len(wls):
        raise FrameError(f"XMP BandName has {len(names)} names, CentralWavelength {len(wls)} values", path=path)
    matrix = None
    if x.has("ColorTransform", ("Camera",)):
        matrix = ctx.required("ColorTransform", ("Camera",))
        if len(matrix) != len(names) ** 2:
            raise FrameError(f"XMP Camera:ColorTransform has {len(matrix)} values, expected {len(names)}x{len(names)} "
                             "(one row per band)", path=path)
    sun = ctx.optional("sun_sensor", lambda: x.numbers("SunSensor", ("Camera",), len(names)))
    common = _finish(ctx)
    if common["capture_id"] is None:  # 6X: EXIF ImageUniqueID "<session>_<capture number>", one per capture
        common["capture_id"] = _clean(ctx.exif.get("ImageUniqueID"))
    out = []
    for i, (name, wl) in enumerate(zip(names, wls)):
        if wl <= 0 or name.lower() == "garbage":  # a channel Sentera writes for crosstalk only
            continue
        _check_wavelength(wl, path)
        out.append(CaptureMeta(
            path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl,
            fwhm_nm=fwhms[i] if i < len(fwhms) and fwhms[i] > 0 else None, exposure_s=exposure, gain=gain,
            black_levels=_black_levels(ctx), dark_row_values=None, radiometric_calibration=None,
            vignetting_center=None, vignetting_polynomial=None, vignetting_polynomial_2d=None,
            vignetting_polynomial_2d_exponents=None,
            irradiance=sun[i] if sun is not None and sun[i] > 0 else None, radiometry="sentera",
            channel=i if len(names) > 1 else None, channel_mix=matrix, iso=gain * 100.0,
            irradiance_unit="1 (Sentera ILS counts)", **common,
        ))
    if not out:
        raise FrameError("no usable band (every CentralWavelength is 0)", path=path)
    return out


# --------------------------------------------------------------------------- factory model


def factory_vignetting(meta: CaptureMeta) -> np.ndarray:
    """The factory vignetting correction ``(H, W)`` of one band file (>= 1, multiplies DN).

    The map depends only on the band's shape and vignetting tags, which are the same in
    every capture of a camera: it is computed once per process and tags
    (:func:`_vignetting_of`; 0.1 s of a 1280 x 960 band, more than the rest of the band's
    radiance) and returned read-only. Tags whose map is not finite and positive everywhere
    (a corrupt polynomial: a denominator through zero or overflowing) raise :class:`FrameError`
    naming the file."""
    v, ok = _vignetting_of(meta.radiometry, meta.shape, meta.dji_center, meta.dji_vignetting, meta.vignetting_center,
                           meta.vignetting_polynomial, meta.vignetting_polynomial_2d,
                           meta.vignetting_polynomial_2d_exponents)
    if not ok:
        raise FrameError("the vignetting tags give a correction that is not finite and positive over the image "
                         "(XMP VignettingCenter/VignettingPolynomial, VignettingPolynomial2D or DJI "
                         "VignettingData damaged)", path=meta.path,
                         hint="copy the band file again from the camera's card; a file with damaged calibration "
                              "tags cannot be used with --calibration factory")
    return v


@lru_cache(maxsize=16)  # a few bands of one or two cameras; 10 MB each at 1280 x 960
def _vignetting_of(radiometry: str, shape: tuple[int, int], dji_center: tuple[float, float] | None,
                   dji_vignetting: tuple[float, ...] | None, center: tuple[float, float] | None,
                   poly: tuple[float, ...] | None, poly_2d: tuple[float, ...] | None,
                   exponents_2d: tuple[float, ...] | None) -> tuple[np.ndarray, bool]:
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # judged below, once per tag set
        v = _vignetting_map(radiometry, shape, dji_center, dji_vignetting, center, poly, poly_2d, exponents_2d)
    v.flags.writeable = False  # shared by every capture: a caller that wrote into it would change the next ones
    return v, bool(np.all(np.isfinite(v)) and np.all(v > 0))


def _vignetting_map(radiometry: str, shape: tuple[int, int], dji_center: tuple[float, float] | None,
                    dji_vignetting: tuple[float, ...] | None, center: tuple[float, float] | None,
                    poly: tuple[float, ...] | None, poly_2d: tuple[float, ...] | None,
                    exponents_2d: tuple[float, ...] | None) -> np.ndarray:
    if radiometry == "dji":
        assert dji_center is not None and dji_vignetting is not None
        v = dji_vignetting_correction(shape, dji_center, dji_vignetting)
    elif radiometry in ("sentera", "thermal"):
        v = np.ones(shape)
    elif radiometry == "sequoia":
        assert poly_2d is not None and exponents_2d is not None
        v = vignetting_2d(shape, poly_2d, exponents_2d)
    else:
        v = vignetting_map(shape, center, poly, poly_2d=poly_2d, exponents_2d=exponents_2d)
    return v


FACTORY_ALIGNMENT_NOTE = ("each band's drone-dji:DewarpData (distortion, camera matrix about CalibratedOpticalCenterX/Y) "
                          "and CalibratedHMatrix (onto the designed ideal image plane): DJI Image Processing Guide "
                          "steps 2-3; NaN where a band does not cover")


def has_factory_alignment(meta: CaptureMeta) -> bool:
    """Whether the band file carries its own registration to the camera's common image plane
    (DJI: ``CalibratedHMatrix``, with ``DewarpData`` when written)."""
    return meta.radiometry == "dji" and meta.dji_hmatrix is not None and meta.dji_center is not None


@lru_cache(maxsize=32)
def _alignment_map(shape: tuple[int, int], center: tuple[float, float], dewarp: tuple[float, ...] | None,
                   hmatrix: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    return dji_alignment_map(shape, center, dewarp, hmatrix)  # the same for every capture of a flight


def factory_align(metas: Sequence[CaptureMeta], stack: np.ndarray) -> np.ndarray:
    """Bands ``(band, H, W)`` of one capture (stored orientation) on the camera's common image
    plane with each band file's own registration (:func:`has_factory_alignment`;
    :func:`mscal_core.factory.dji_alignment_map`); FrameError naming a band file without it."""
    out = np.empty(stack.shape, np.float32)
    for b, meta in enumerate(metas):
        if not has_factory_alignment(meta):
            raise FrameError("no band registration in the file's metadata (drone-dji:CalibratedHMatrix)", path=meta.path,
                             hint="align the bands with 'mscal register' and --registration, or apply with --no-align")
        assert meta.dji_center is not None and meta.dji_hmatrix is not None
        out[b] = remap_band(stack[b], _alignment_map(meta.shape, meta.dji_center, meta.dji_dewarp, meta.dji_hmatrix))
    return out


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
        """The shift of ``meta``'s file to sensor DN (:func:`pipeline.ingest.catalog.sample_shift`):
        :attr:`dn_shift`, less when the file stores fewer bits per sample (a RedEdge's packed
        12-bit TIFF: 0)."""
        return sample_shift(self.dn_shift, self.sensor_bits, meta.bits_per_sample)


def factory_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None = None,
                     channels: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Radiance of one band's DN with its own factory model (unit: ``meta.radiance_unit``;
    kelvin for a thermal band), or with the field-fitted ``parts`` in place of the factory's
    response and/or vignetting (MicaSense model only). ``channels``: the whole ``(H, W, C)``
    image of a multi-channel file (Sentera), which the colour transform needs. The result is
    in the stored orientation (see :func:`upright_meta`); with ``out`` (e.g. a float32 band of
    the capture's cube) it is written there and ``out`` returned."""
    rad = _factory_radiance(meta, dn, parts, channels, out)
    if out is not None and rad is not out:
        out[...] = rad
        return out
    return rad


def _factory_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None, channels: np.ndarray | None,
                      out: np.ndarray | None) -> np.ndarray:
    if dn.shape != meta.shape:
        raise FrameError(f"image {dn.shape} does not match its metadata {meta.shape}", path=meta.path)
    if parts is not None and (parts.vignetting is not None or parts.inverse_response is not None) and \
            meta.radiometry != "micasense":
        raise FrameError(f"field components replace parts of MicaSense's model only, not {meta.radiometry}'s",
                         path=meta.path, hint="leave out --field-calibration for this camera")
    if meta.radiometry == "thermal":
        return thermal_kelvin(dn)
    if meta.radiometry == "dji":
        return dji_camera_value(dn, black_level=meta.black_level, sensor_gain=meta.gain,
                                exposure_us=meta.exposure_s * 1e6, vignetting=factory_vignetting(meta),
                                gain_adjustment=meta.gain_adjustment or 1.0)
    if meta.radiometry == "sequoia":
        assert meta.sensor_model is not None and meta.f_number is not None and meta.iso is not None
        return sequoia_irradiance(dn, f_number=meta.f_number, exposure_s=meta.exposure_s, iso=meta.iso,
                                  sensor_model=meta.sensor_model, vignetting=factory_vignetting(meta))
    if meta.radiometry == "sentera":
        if meta.channel_mix is not None and meta.channel is not None:
            if channels is None:
                raise FrameError("the colour transform needs every channel of the file", path=meta.path)
            mixed = color_transform(channels, meta.channel_mix, [meta.channel])[0]
            n = channels.shape[2]
            used = [j for j in range(n) if meta.channel_mix[n * meta.channel + j] != 0]
            clipped = np.any(channels[:, :, used] >= 2**meta.bits_per_sample - 1, axis=2)
        else:
            mixed = np.asarray(dn, dtype=np.float64)
            clipped = np.asarray(dn) >= 2**meta.bits_per_sample - 1
        out = np.maximum((mixed - meta.black_level) / (meta.gain * meta.exposure_s), 0.0)
        out[clipped] = np.nan  # a clipped channel in the mix: the band is unknown there (Sentera excludes them)
        return out
    vignetting = factory_vignetting(meta)
    signal = None
    if parts is not None and parts.vignetting is not None:
        if parts.vignetting.shape != dn.shape:
            raise FrameError(f"field vignetting {parts.vignetting.shape} does not match the image {dn.shape}",
                             path=meta.path)
        v = np.asarray(parts.vignetting, dtype=np.float64)
        vignetting = np.divide(1.0, v, out=np.full(v.shape, np.nan), where=v > 0)
    if parts is not None and parts.inverse_response is not None:
        shift = parts.shift_for(meta)
        c = field_response_scale(parts.inverse_response, dn_shift=shift, black_level=meta.black_level,
                                 bits_per_sample=meta.bits_per_sample)
        signal = field_response_signal(dn, parts.inverse_response, dn_shift=shift, scale=c)
    assert meta.radiometric_calibration is not None
    return radiance(
        dn,
        exposure_s=meta.exposure_s,
        gain=meta.gain,
        black_level=meta.black_level,
        calibration=meta.radiometric_calibration,
        vignetting=vignetting,
        bits_per_sample=meta.bits_per_sample,
        signal=signal,
        out=out,
    )


def upright_meta(meta: CaptureMeta, image: np.ndarray) -> np.ndarray:
    """``image`` (stored orientation, last two axes) as meant to be seen (EXIF Orientation;
    Parrot Sequoia stores its frames rotated 180 degrees)."""
    try:
        return upright(image, meta.orientation)
    except ValueError as exc:
        raise FrameError(str(exc), path=meta.path) from None


def reflectance_factor(meta: CaptureMeta) -> float | None:
    """``k = c / E`` with reflectance ``R = k L`` from the band's own sun sensor, ``c`` the camera
    model's one fixed scale (:data:`pipeline.ingest.sun_scale.SUN_SENSOR_SCALES`: MicaSense pi,
    DJI 1 as DJI's guides write it, Sequoia Parrot's K fixed at 5e-4), or None when it has no
    usable reading or its sensor gives no reflectance (Sentera's ILS counts: use a panel)."""
    e, scale = meta.irradiance, sun_scale(meta.radiometry)
    if e is None or not math.isfinite(e) or e <= 0 or scale is None:
        return None
    return scale.constant / e


#: The sun-sensor tags each radiance model reads (named when a band has no reading at all).
SUN_SENSOR_TAGS = {
    "micasense": "XMP Camera:Irradiance (DLS 1) or DLS:HorizontalIrradiance (DLS 2)",
    "sequoia": "XMP Camera:IrradianceList (sunshine sensor)",
    "dji": "XMP drone-dji:Irradiance",
}


def no_reflectance_reason(meta: CaptureMeta) -> str | None:
    """Why the band's own sun sensor gives no reflectance factor (:func:`reflectance_factor`
    is None), naming the tag: the problem recorded when a sun-sensor tag was present but
    unusable, else the tag that is missing; None when the band has a usable reading."""
    if reflectance_factor(meta) is not None:
        return None
    why = [p.message() for p in meta.problems if p.feature == "sun_sensor"]
    if why:
        return why[0]
    if meta.radiometry == "sentera":
        return "Sentera's sun sensor (ILS) counts have no published conversion to reflectance"
    if meta.radiometry in ("thermal", "panchro"):
        return f"a {meta.radiometry} band has no sun-sensor reflectance"
    tag = SUN_SENSOR_TAGS.get(meta.radiometry, "XMP Irradiance")
    return f"no sun-sensor reading: no {tag} in the file"


def sun_sensor_absolute(meta: CaptureMeta) -> bool:
    """Whether the sun-sensor route gives absolute reflectance (MicaSense) or relative: what
    the camera model's fixed scale says (:data:`pipeline.ingest.sun_scale.SUN_SENSOR_SCALES`)."""
    scale = sun_scale(meta.radiometry)
    return scale is not None and scale.absolute


# --------------------------------------------------------------------------- irradiance


def xmp_irradiance(path: str | Path) -> float | None:
    """The XMP ``Irradiance`` (downwelling light sensor) of a TIFF frame, else None.

    Reads only the first page's tags (no pixels); a file that is not a TIFF or has no XMP
    packet, or whose packet has no Irradiance, gives None (most cameras do not write one).
    A present but unusable value (not a number, not positive) raises :class:`FrameError`
    naming the file.
    """
    import tifffile

    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(700)
            packet = None if tag is None else tag.value
    except (tifffile.TiffFileError, ValueError, OSError, IndexError):  # IndexError: truncated, no IFD
        return None
    if packet is None:
        return None
    try:
        x = Xmp.parse(packet, path)
    except FrameError:
        return None
    try:
        values = x.numbers("Irradiance")
    except TagError as exc:
        raise FrameError(f"XMP {exc.reason}", path=path,
                         hint="the sun sensor reading is unusable; remove the frame or give an irradiance column in frames.csv") from None
    if not values:
        return None
    if not (math.isfinite(values[0]) and values[0] > 0):
        raise FrameError(f"XMP Irradiance {values[0]!r} is not a positive number", path=path,
                         hint="the sun sensor reading is unusable; remove the frame or give an irradiance column in frames.csv")
    return float(values[0])


def capture_irradiance(capture: "Capture") -> float | None:
    """One raw irradiance level of a one-file-per-band capture: the mean of its bands' XMP
    Irradiance (each band's sensor reading), None unless every band has one. Only ratios of
    these levels are used (:func:`mscal_core.illumination.frame_illumination`). Kept for
    calibration stores from before horizontal levels (raw ``capture_irradiance``); newer stores use the
    horizontal level of :func:`pipeline.ingest.sunsensor.capture_levels`."""
    values = [m.irradiance for m in capture.metas]
    if not values or any(v is None or not v > 0 for v in values):
        return None
    return float(sum(values) / len(values))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- captures

DEFAULT_CAPTURE_PATTERN = r"^(?P<capture>.+)_(?P<band>[0-9]+)\.tif$"


@dataclass(frozen=True)
class Capture:
    """One capture: its bands' metadata in band (catalog) order, and the files of bands that
    are read but not part of reflectance (``skipped``: ``{file, band, reason}``)."""

    name: str  # file name stem without the band suffix, e.g. IMG_0000
    capture_id: str
    metas: tuple[CaptureMeta, ...]  # ordered by band (catalog order, else by suffix)
    skipped: tuple[dict[str, str], ...] = ()

    @property
    def files(self) -> tuple[Path, ...]:
        out: list[Path] = []
        for m in self.metas:
            if m.path not in out:
                out.append(m.path)
        return tuple(out)

    @property
    def problems(self) -> list[TagProblem]:
        seen: list[TagProblem] = []
        for m in self.metas:
            for p in m.problems:
                if p not in seen:
                    seen.append(p)
        return seen


def capture_pattern(camera: Camera | None) -> re.Pattern[str]:
    """The file-name pattern of a camera's captures (named groups ``capture`` and ``band``)."""
    text = (camera.layout.capture_pattern if camera is not None else None) or DEFAULT_CAPTURE_PATTERN
    return re.compile(text)


def group_captures(
    folder: str | Path, camera: Camera | None = None
) -> tuple[list[Capture], list[dict[str, str]]]:
    """Group a folder's band files into captures by their name and check them.

    With ``camera`` its ``capture_pattern`` and band list are used: every band's file must be
    present and its XMP BandName must be the catalog's (case aside); files of the camera's
    ``skip_bands`` (a panchromatic or thermal band) are named in ``Capture.skipped``. Without
    it, the band suffixes seen in the folder are expected in every capture. The band files of
    one capture must carry one XMP capture id, and no two captures may share one (the later
    name is a copy). One file holding several bands (a Sentera JPEG) is one capture. A
    ``folder_per_band`` camera (Sentera 6X) is given its session folder: the files of one name
    in its band folders are one capture, each band known by its XMP BandName.

    Returns the complete captures (sorted by name) and one problem per incomplete or unusable
    capture as ``[{file, reason}]`` (``file`` the offending band file, else the capture's first
    file), for the run's quarantine list.
    """
    folder = Path(folder)
    pattern = capture_pattern(camera)
    per_file = camera is not None and camera.layout.kind == "file_per_capture"
    per_folder = camera is not None and camera.layout.kind == "folder_per_band"
    skip = {s.name.casefold(): s for s in (camera.skip_bands if camera is not None else ())}
    by_name: dict[str, dict[str, CaptureMeta]] = {}
    unusable: dict[str, list[tuple[Path, str]]] = {}
    skipped: dict[str, list[dict[str, str]]] = {}
    for path in band_files(folder, per_folder):
        m = pattern.match(path.name)
        if m is None or not path.is_file():
            continue
        bands = by_name.setdefault(m["capture"], {})
        try:
            metas = read_file_metas(path)
        except FrameError as exc:
            s = next((s for s in skip.values() if not (per_file or per_folder) and s.file_suffix == m["band"]), None)
            if s is not None:  # the file of a band kept out of reflectance anyway: named, not fatal
                skipped.setdefault(m["capture"], []).append(
                    {"file": str(path), "band": s.name, "reason": f"{s.reason}; unreadable: {exc.reason}"})
            else:
                unusable.setdefault(m["capture"], []).append((path, exc.reason))
            continue
        if per_file:
            for meta in metas:
                bands[str(meta.channel)] = meta
        elif per_folder:  # a band folder's file: the band is its XMP BandName
            key = metas[0].band_name.casefold()
            if key in bands:
                unusable.setdefault(m["capture"], []).append(
                    (path, f"band {metas[0].band_name} also in {bands[key].path.parent.name}/ (two folders of one band?)"))
            bands[key] = metas[0]
        else:
            bands[m["band"]] = metas[0]
    for name, bands in by_name.items():  # bands kept out of reflectance, recognised by their XMP BandName
        for key in [k for k, meta in bands.items() if meta.band_name.casefold() in skip]:
            s = skip[bands[key].band_name.casefold()]
            skipped.setdefault(name, []).append({"file": str(bands[key].path), "band": s.name, "reason": s.reason})
            del bands[key]
    problems: list[dict[str, str]] = []
    captures: list[Capture] = []
    owner: dict[str, str] = {}  # capture id -> the first capture name that carries it
    for name in sorted(by_name):
        bands = by_name[name]
        files = [m.path for m in bands.values()] + [p for p, _ in unusable.get(name, [])]
        files += [Path(s["file"]) for s in skipped.get(name, [])]
        first = min(files)
        if name in unusable:
            (path, why), more = unusable[name][0], len(unusable[name]) - 1
            problems.append({"file": str(path), "reason": f"capture {name}: band file {path.name}: {why}"
                             + (f" (and {more} more unusable band file(s))" if more else "")})
            continue
        expected = _by_band_name(bands, camera) or _expected_suffixes(camera, by_name)
        reason = _capture_problem(bands, expected, name, camera)
        ids = sorted({m.capture_id for m in bands.values() if m.capture_id})
        if reason is None and len(ids) > 1:
            reason = f"capture {name}: its band files carry {len(ids)} different XMP CaptureIds (files of other captures renamed?)"
        cid = ids[0] if ids else name
        if reason is None and cid in owner:
            reason = f"capture {name}: same XMP CaptureId as {owner[cid]} (a copy of that capture?)"
        if reason:
            problems.append({"file": str(first), "reason": reason})
            continue
        owner[cid] = name
        metas = tuple(bands[s] for s in expected)
        captures.append(Capture(name=name, capture_id=cid, metas=metas if per_folder else _placed(name, metas),
                                skipped=tuple(skipped.get(name, []))))
    return captures, problems


def _placed(name: str, metas: tuple[CaptureMeta, ...]) -> tuple[CaptureMeta, ...]:
    """The band files' metadata, positioned from the capture's RGB JPEG
    (:func:`sibling_position`) when none of them has a position of its own."""
    if any(m.lat is not None for m in metas):
        return metas
    pos = sibling_position(metas[0].path.parent, name)
    return metas if pos is None else tuple(replace(m, lat=pos[0], lon=pos[1], alt_m=pos[2]) for m in metas)


def band_files(folder: Path, per_folder: bool = False) -> list[Path]:
    """The files of a capture folder, sorted; with ``per_folder`` (layout ``folder_per_band``:
    a session folder holding one folder per band) the files of its sub-folders."""
    if not per_folder:
        return sorted(folder.iterdir())
    return sorted((p for d in folder.iterdir() if d.is_dir() and not d.name.startswith(".") for p in d.iterdir()),
                  key=lambda p: (p.name, p.parent.name))


def capture_folder_of(path: Path, camera: Camera) -> Path:
    """The folder :func:`group_captures` takes for a band file of ``camera``: its own, or for
    a ``folder_per_band`` camera the session folder above its band folder."""
    return path.parent.parent if camera.layout.kind == "folder_per_band" else path.parent


def _by_band_name(bands: dict[str, CaptureMeta], camera: Camera | None) -> list[str] | None:
    """The file keys in catalog band order when every catalog band is found, once, by its XMP
    BandName (case aside) and no other band is left: the manufacturer's file numbering then
    does not matter. None otherwise (the suffix check names what is wrong)."""
    if camera is None or len(bands) != camera.n_bands:
        return None
    by = {}
    for key, meta in bands.items():
        by.setdefault(meta.band_name.casefold(), []).append(key)
    keys = []
    for b in camera.bands:
        found = by.get(b.name.casefold(), [])
        if len(found) != 1:
            return None
        keys.append(found[0])
    return keys


def _expected_suffixes(camera: Camera | None, by_id: dict[str, dict[str, CaptureMeta]]) -> list[str]:
    if camera is not None:
        if camera.layout.kind == "file_per_capture":
            return [str(b.channel) for b in camera.bands]
        if camera.layout.kind == "folder_per_band":
            return [b.name.casefold() for b in camera.bands]
        return [str(b.file_suffix) for b in camera.bands]
    seen = {s for bands in by_id.values() for s in bands}
    return sorted(seen, key=lambda s: (len(s), s))


def _capture_problem(
    bands: dict[str, CaptureMeta], expected: list[str], name: str, camera: Camera | None
) -> str | None:
    """Why a capture's files do not make one complete capture, or None."""
    missing = [s for s in expected if s not in bands]
    extra = sorted(set(bands) - set(expected))
    if camera is not None and camera.layout.kind == "file_per_capture":
        extra = []  # channels the catalog does not use (e.g. Sentera's Garbage) are not an error
    if missing or extra:
        named = {str(b.file_suffix): f"{b.file_suffix} ({b.name})" for b in (camera.bands if camera else ())}
        parts = ([f"missing band file(s) {', '.join(named.get(s, s) for s in missing)}"] if missing else []) + (
            [f"unexpected band file(s) {', '.join(extra)}"] if extra else []
        )
        return f"capture {name}: {'; '.join(parts)}"
    if camera is not None:
        wrong = [
            f"_{k} is {bands[k].band_name!r}, catalog says {b.name!r}"
            for k, b in zip(expected, camera.bands)
            if bands[k].band_name.casefold() != b.name.casefold()
        ]
        if wrong:
            return f"capture {name}: band names differ from camera {camera.name}: {'; '.join(wrong)}"
    return None


# --------------------------------------------------------------------------- pixels


def read_capture_pixels(capture: Capture, out: np.ndarray | None = None
                        ) -> tuple[str, list[np.ndarray], dict[Path, np.ndarray]]:
    """Content hash (over the capture's files, in band order), the stored DN of each band
    (its channel, for a multi-channel file) and the whole ``(H, W, C)`` image of every
    multi-channel file (for :func:`factory_radiance`'s colour transform). ``out``: a uint16
    ``(band, H, W)`` cube into which a one-band file of that shape is decoded where it can be
    (its DN are then ``out[b]``; the caller copies the others)."""
    from hashlib import sha256

    from pipeline.ingest.raw import read_whole
    from pipeline.ingest.session import decode_raw

    h = sha256()
    decoded: dict[Path, np.ndarray] = {}
    into = _band_slots(capture, out)
    for path in capture.files:  # each read into the thread's buffer, decoded before the next
        data = read_whole(path, path.stat().st_size, "wait for the copy to finish, or re-copy the file")
        h.update(data)
        try:
            decoded[path] = np.asarray(decode_raw(data, path, into.get(path)))
        except FrameError:
            raise
        except Exception as exc:  # tifffile raises IndexError/ValueError on truncated files
            raise FrameError(f"unreadable band file ({type(exc).__name__}: {exc})", path=path) from None
    dns = []
    stacks: dict[Path, np.ndarray] = {}
    for meta in capture.metas:
        img = decoded[meta.path]
        if meta.channel is not None:
            if img.ndim != 3 or img.shape[2] <= meta.channel:
                raise FrameError(f"image {img.shape} has no channel {meta.channel} (band {meta.band_name})",
                                 path=meta.path)
            stacks[meta.path] = img
            img = img[:, :, meta.channel]
        if img.shape != meta.shape:
            raise FrameError(f"image {img.shape} does not match its metadata {meta.shape}", path=meta.path)
        dns.append(np.asarray(img).astype(np.uint16, copy=False))
    return h.hexdigest(), dns, stacks


def _band_slots(capture: Capture, out: np.ndarray | None) -> dict[Path, np.ndarray]:
    """``out[b]`` of each one-band file whose shape it has (:func:`read_capture_pixels`)."""
    if out is None or out.ndim != 3 or out.dtype != np.uint16 or len(capture.metas) != out.shape[0]:
        return {}
    per_file: dict[Path, int] = {}
    for meta in capture.metas:
        per_file[meta.path] = per_file.get(meta.path, 0) + 1
    return {m.path: out[b] for b, m in enumerate(capture.metas)
            if m.channel is None and per_file[m.path] == 1 and tuple(m.shape) == out.shape[1:]}
