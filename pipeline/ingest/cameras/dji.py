"""DJI P4 Multispectral and Mavic 3M: tags, radiance model, sunlight sensor and quirks.

- **Tags**: XMP ``drone-dji:`` SensorGain, ExposureTime (us), BlackLevel (BlackCurrent on the
  Mavic 3M), SensorGainAdjustment, VignettingData k0..k5, CalibratedOpticalCenterX/Y,
  BandName + BandFreq (``840(+/-26)nm``) or CentralWavelength.
- **Radiance**: the camera value of DJI's Image Processing Guides
  (:func:`mscal_core.vendors.dji_camera_value`, relative), with DJI's radial vignetting
  (:func:`mscal_core.vendors.dji_vignetting_correction`).
- **Sun sensor**: ``drone-dji:Irradiance`` (calibrated sunlight sensor value), used as the
  camera wrote it (:func:`compensated`), with the guides' scale 1 (:data:`SUN_SCALES`); the
  aircraft's attitude ``drone-dji:FlightYaw/Pitch/RollDegree`` (:data:`ATTITUDE`).
- **Quirks**: each band file's own registration (DewarpData, CalibratedHMatrix:
  :func:`factory_align`); the P4 Multispectral's RGB image numbered as the capture's
  first file (a companion image, not a band file).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np
from mscal_core.errors import FrameError, InputError
from mscal_core.geometry import Intrinsics
from mscal_core.vendors import dji_alignment_map, dji_camera_value, dji_vignetting_correction, remap_band

from pipeline.ingest.cameras.registry import AttitudeSource, FileRegistration, Maker, register
from pipeline.ingest.meta import (
    FIRMWARE_HINT,
    CaptureMeta,
    FieldParts,
    TagContext,
    VignettingTags,
    band_of,
    black_levels,
    check_exposure,
    check_wavelength,
    factory_vignetting,
    meta_fields,
    positive_irradiance,
)
from pipeline.ingest.sun_scale import SunScale
from pipeline.ingest.xmp import TagError, Xmp, parse_numbers

UNITS = {"dji": "1 (DJI camera value pCam (p - p_BL) V / (g t), relative)"}


#: The names of a DJI band's own values in :attr:`~pipeline.ingest.meta.CaptureMeta.maker_tags`:
#: ``drone-dji:SensorGainAdjustment`` (pCam), ``VignettingData`` k0..k5,
#: ``CalibratedOpticalCenterX/Y``, ``DewarpData`` (fx, fy, cx, cy, k1, k2, p1, p2, k3; None when
#: not written) and ``CalibratedHMatrix`` (9 row-major values; None when not written).
GAIN_ADJUSTMENT, VIGNETTING, CENTER, DEWARP, HMATRIX = "gain_adjustment", "vignetting", "center", "dewarp", "hmatrix"


def claims(ctx: TagContext) -> bool:
    """A DJI band file: ``drone-dji:SensorGain`` or ``drone-dji:VignettingData``."""
    return ctx.xmp.has("SensorGain", ("drone-dji",)) or ctx.xmp.has("VignettingData", ("drone-dji",))


def read(ctx: TagContext) -> list[CaptureMeta]:
    return [_dji(ctx)]


def _dji(ctx: TagContext) -> CaptureMeta:
    """DJI P4 Multispectral / Mavic 3M (drone-dji namespace, attributes)."""
    x, path = ctx.xmp, ctx.path
    dj = ("drone-dji",)
    name, wl, fwhm = _dji_band(ctx)
    black = black_levels(ctx) or (ctx.required("BlackLevel", dj, 1) if x.has("BlackLevel", dj) or not x.has(
        "BlackCurrent", dj) else ctx.required("BlackCurrent", dj, 1))  # BlackCurrent: the Mavic 3M manual's name
    gain = ctx.required("SensorGain", dj, 1)[0]
    if not gain > 0:
        raise FrameError(f"XMP drone-dji:SensorGain {gain!r} must be positive", path=path)
    exposure_us = ctx.required("ExposureTime", dj, 1)[0]
    exposure = exposure_us * 1e-6
    check_exposure(exposure, f"XMP drone-dji:ExposureTime {exposure_us:g} us =", path)
    adj = ctx.required("SensorGainAdjustment", dj, 1)[0]
    k = ctx.required("VignettingData", dj, 6)
    cx = ctx.required("CalibratedOpticalCenterX", dj, 1)[0]
    cy = ctx.required("CalibratedOpticalCenterY", dj, 1)[0]
    h, w = ctx.shape
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise FrameError(f"XMP drone-dji:CalibratedOpticalCenterX/Y ({cx:g}, {cy:g}) lies outside the {w} x {h} "
                         "image (it must be in pixels)", path=path)
    irr = positive_irradiance(ctx, "Irradiance", dj)
    dewarp = ctx.optional("dewarp", lambda: _dji_dewarp(x, path))
    hmat = ctx.optional("band_alignment", lambda: x.numbers("CalibratedHMatrix", dj, 9) or x.numbers(
        "DewarpHMatrix", dj, 9))
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=gain, black_levels=tuple(black), irradiance=irr, radiometry="dji",
        maker_tags=((GAIN_ADJUSTMENT, adj), (VIGNETTING, k), (CENTER, (cx, cy)), (DEWARP, dewarp), (HMATRIX, hmat)),
        irradiance_unit="1 (DJI calibrated sunlight sensor value)", **meta_fields(ctx),
    )


def _dji_band(ctx: TagContext) -> tuple[str, float, float | None]:
    """Band of a DJI file: Camera:BandName/CentralWavelength if written, else drone-dji:BandName
    and BandFreq ``840(+/-26)nm``."""
    x = ctx.xmp
    if x.has("CentralWavelength"):
        return band_of(ctx, ("drone-dji",))
    name = x.text("BandName", ("drone-dji",)) or x.text("BandName")
    freq = x.text("BandFreq", ("drone-dji",))
    m = _DJI_BAND_FREQ.match(freq or "")
    own = ctx.optional(None, lambda: x.numbers("CentralWavelength", ("drone-dji",), 1))
    if name is None or (m is None and own is None):
        raise FrameError("no band name and centre wavelength (XMP Camera:CentralWavelength, drone-dji:"
                         f"CentralWavelength or drone-dji:BandFreq like 840(+/-26)nm; got {freq!r})",
                         path=ctx.path, hint=FIRMWARE_HINT)
    wl = own[0] if own is not None else float(m[1])  # type: ignore[index]
    check_wavelength(wl, ctx.path)
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



def dewarp_intrinsics(x: Xmp, path: Path) -> Intrinsics | None:
    """The lens of a P4 Multispectral / Mavic 3M band file: ``drone-dji:DewarpData``
    ``date;fx,fy,cx,cy,k1,k2,p1,p2,k3`` with the principal point at
    ``CalibratedOpticalCenterX/Y + (cx, cy)`` (DJI Mavic 3M Image Processing Guide, section II
    step 2; OpenCV's distortion order already); None without DewarpData."""
    raw = x.text("DewarpData", ("drone-dji",))
    if raw is None:
        return None
    try:
        nums = [float(v) for v in raw.split(";", 1)[-1].replace(",", " ").split()]
        centre = (x.numbers("CalibratedOpticalCenterX", ("drone-dji",), 1),
                  x.numbers("CalibratedOpticalCenterY", ("drone-dji",), 1))
    except (ValueError, TagError):
        nums, centre = [], (None, None)
    if len(nums) != 9 or centre[0] is None or centre[1] is None:
        raise FrameError(f"XMP drone-dji:DewarpData {raw!r} (or CalibratedOpticalCenterX/Y) is unusable: expected "
                         "'date;fx,fy,cx,cy,k1,k2,p1,p2,k3'", path=path, hint="give the intrinsics in session.yaml instead")
    fx, fy, cx, cy, *dist = nums
    try:
        return Intrinsics(fx=fx, fy=fy, cx=centre[0][0] + cx, cy=centre[1][0] + cy, dist=tuple(dist))
    except InputError as exc:  # NaN, inf, a non-positive focal length: name the file and the tag
        raise FrameError(f"XMP drone-dji:DewarpData {raw!r} gives unusable intrinsics: {exc.reason}", path=path,
                         hint="give the intrinsics in session.yaml instead") from None


FACTORY_ALIGNMENT_NOTE = ("each band's drone-dji:DewarpData (distortion, camera matrix about CalibratedOpticalCenterX/Y) "
                          "and CalibratedHMatrix (onto the designed ideal image plane): DJI Image Processing Guide "
                          "steps 2-3; NaN where a band does not cover")


def has_factory_alignment(meta: CaptureMeta) -> bool:
    """Whether the band file carries its own registration to the camera's common image plane
    (DJI: ``CalibratedHMatrix``, with ``DewarpData`` when written)."""
    return meta.radiometry == "dji" and meta.maker_tag(HMATRIX) is not None and meta.maker_tag(CENTER) is not None


@lru_cache(maxsize=32)
def _alignment_map(shape: tuple[int, int], center: tuple[float, float], dewarp: tuple[float, ...] | None,
                   hmatrix: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    return dji_alignment_map(shape, center, dewarp, hmatrix)  # the same for every capture of a flight


def factory_align(metas: Sequence[CaptureMeta], stack: np.ndarray) -> np.ndarray:
    """Bands ``(band, H, W)`` of one capture (stored orientation) on the camera's common image
    plane with each band file's own registration (:func:`has_factory_alignment`;
    :func:`mscal_core.vendors.dji_alignment_map`); FrameError naming a band file without it."""
    out = np.empty(stack.shape, np.float32)
    for b, meta in enumerate(metas):
        if not has_factory_alignment(meta):
            raise FrameError("no band registration in the file's metadata (drone-dji:CalibratedHMatrix)", path=meta.path,
                             hint="align the bands with 'mscal register' and --registration, or apply with --no-align")
        out[b] = remap_band(stack[b], _alignment_map(meta.shape, meta.maker_tag(CENTER), meta.maker_tag(DEWARP),
                                                     meta.maker_tag(HMATRIX)))
    return out


def band_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None, channels: np.ndarray | None,
                  out: np.ndarray | None) -> np.ndarray:
    """DJI's camera value (:func:`mscal_core.vendors.dji_camera_value`)."""
    return dji_camera_value(dn, black_level=meta.black_level, sensor_gain=meta.gain,
                            exposure_us=meta.exposure_s * 1e6, vignetting=factory_vignetting(meta),
                            gain_adjustment=meta.maker_tag(GAIN_ADJUSTMENT) or 1.0)


def band_vignetting(radiometry: str, shape: tuple[int, int], tags: VignettingTags) -> np.ndarray:
    """DJI's radial vignetting about the calibrated optical centre
    (:func:`mscal_core.vendors.dji_vignetting_correction`)."""
    center, k = tags.maker_tag(CENTER), tags.maker_tag(VIGNETTING)
    assert center is not None and k is not None
    return dji_vignetting_correction(shape, center, k)


#: Images a camera saves beside its band files that are not band files, by catalog camera:
#: the file-name pattern (group ``capture``: the capture the image belongs to, as the camera's
#: ``capture_pattern`` names it in its band files) and why the image is left out. The P4
#: Multispectral numbers the six files of a capture as one: its RGB camera's ``DJI_XXX0.JPG``,
#: then the band files ``DJI_XXX1.TIF`` .. ``DJI_XXX5.TIF``.
COMPANION_IMAGES: dict[str, tuple[str, str]] = {
    "dji-p4-multispectral": (r"(?i)^DJI_(?P<capture>[0-9]+)0\.jpe?g$",
                             "RGB camera image of the DJI P4 Multispectral (not a band file)"),
}


DJI_GUIDES = ("DJI, P4 Multispectral Image Processing Guide v1.0 (2020.07) and Mavic 3M Image Processing Guide v1.0 "
              "(2023.08): reflectance = camera value x pCam (drone-dji:SensorGainAdjustment) / (X_LS x pLS) = "
              "drone-dji:Irradiance; the guides write no further constant (no pi): 1")

#: The fixed sun-sensor scale (:mod:`pipeline.ingest.sun_scale`), P4 Multispectral and Mavic 3M
#: (``c = 1``): the guides' reflectance of a band is the camera value times ``pCam`` over the
#: sunlight sensor's value, ``X pCam / (X_LS pLS)``, with ``pCam`` = ``drone-dji:SensorGainAdjustment``
#: (already in the camera value, :func:`mscal_core.vendors.dji_camera_value`) and ``X_LS pLS`` =
#: ``drone-dji:Irradiance`` ("calibrated sunlight sensor value"; the NDVI section of both guides).
#: The guides write no further constant (no pi, no panel): their reflectance is used as written.
#: Neither guide says whether that ratio is absolute (its NDVI needs only ratios of bands):
#: absolute values need a panel.
SUN_SCALES = {
    "dji": SunScale(1.0, "R = X pCam / Irradiance (X pCam: the camera value, Irradiance: drone-dji:Irradiance)",
                    DJI_GUIDES, False),
}

#: The aircraft's attitude, when the file has no sensor's own (a DJI reading needs none: it is
#: compensated, :func:`compensated`).
ATTITUDE = (
    AttitudeSource(40, "drone-dji:FlightYaw/Pitch/RollDegree",
                   lambda x: x.angles(("FlightYawDegree", "FlightPitchDegree", "FlightRollDegree"), ("drone-dji",),
                                      degrees=True)),
)

#: run.json's ``sun_sensor`` model of a reading the camera compensated itself.
DJI_COMPENSATED = "DJI Irradiance as written (compensated by the camera's built-in algorithm)"


def compensated(x: Xmp) -> bool:
    """True for ``drone-dji:Irradiance``: used as the camera wrote it, correction 1. The P4
    Multispectral Image Processing Guide calls it the "calibrated sunlight sensor value" and
    divides the camera value by it with no angle term; the Mavic 3M User Manual ("Photo File")
    says it is the "solar irradiance value after compensation by built-in algorithm"
    (``SunSensor`` is the one before). A tilt model on top of it corrected the aircraft's
    attitude twice (lines flown in opposite directions 14 % apart)."""
    return x.has("Irradiance", ("drone-dji",))


MAKER = register(Maker(
    name="dji", model="dji", units=UNITS, claims=claims, read=read, radiance=band_radiance,
    vignetting=band_vignetting, order=10, sun_sensor_tag="XMP drone-dji:Irradiance",
    companion_images=COMPANION_IMAGES, sun_scales=SUN_SCALES, attitude=ATTITUDE, compensated=compensated,
    compensated_model=DJI_COMPENSATED,
    # the reading (compensated) and the aircraft's attitude (ATTITUDE), kept on each band's metadata
    sun_sensor_xmp=frozenset({"Irradiance", "FlightYawDegree", "FlightPitchDegree", "FlightRollDegree"}),
    capture_id_tags=(("drone-dji", "CaptureUUID"),), namespaces={"drone-dji": ("http://www.dji.com/drone-dji/1.0",)},
    time_tags=(("drone-dji", "UTCAtExposure"),),  # UTC, more precise than EXIF DateTimeOriginal (pipeline.ingest.exif)
    intrinsics=dewarp_intrinsics, vignetting_tags="XMP drone-dji:VignettingData",
    # the camera body's serial ("Camera SN", DJI Mavic 3M user manual, photo file fields)
    serial_tags=(("drone-dji", "CameraSerialNumber"),),
    file_registration=FileRegistration(has=has_factory_alignment, align=factory_align, note=FACTORY_ALIGNMENT_NOTE),
))
