"""Sentera Double 4K (JPEG, three channels) and 6X (one TIFF per band): tags, radiance model,
sun sensor and quirks.

- **Tags**: EXIF ExposureTime, ISO (gain = ISO/100), BlackLevel; XMP ``Camera:`` BandName and
  CentralWavelength (one per channel of a multi-channel file), WavelengthFWHM,
  ColorTransform (the crosstalk matrix).
- **Radiance**: crosstalk-corrected DN / (ISO/100 x exposure), relative
  (:func:`mscal_core.vendors.sentera_relative_radiance`); no vignetting model.
- **Sun sensor**: the ILS ``Camera:SunSensor`` counts, kept as the band's reading; they have
  no published conversion to reflectance (no fixed scale: a panel gives it), but are
  proportional to the light (:func:`sun_factor`); the tilt model with ``Camera:Yaw/Pitch/Roll``
  (the shared fallback of :mod:`pipeline.ingest.sunsensor`).
- **Quirks**: a ``Garbage`` channel (wavelength 0) written for the crosstalk only, skipped;
  the 6X's capture id in EXIF ImageUniqueID.
"""

from __future__ import annotations

import math

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.vendors import sentera_relative_radiance

from pipeline.ingest.cameras.registry import Maker, register
from pipeline.ingest.meta import (
    CaptureMeta,
    FieldParts,
    TagContext,
    VignettingTags,
    black_levels,
    check_wavelength,
    clean_text,
    exposure_and_gain,
    meta_fields,
)

UNITS = {"sentera": "1 (DN, crosstalk-corrected by Camera:ColorTransform where written, / (ISO/100 * exposure s), relative)"}


#: The name in :attr:`~pipeline.ingest.meta.CaptureMeta.maker_tags` of a band's
#: ``Camera:ColorTransform`` (the whole crosstalk matrix, row-major; None when not written).
CHANNEL_MIX = "channel_mix"


def claims(ctx: TagContext) -> bool:
    """A Sentera file: ``Camera:ColorTransform``, or EXIF Make Sentera."""
    return ctx.xmp.has("ColorTransform", ("Camera",)) or (ctx.make or "").lower() == "sentera"


def read(ctx: TagContext) -> list[CaptureMeta]:
    """Sentera Double 4K (JPEG, three channels, Camera:ColorTransform) and 6X (one TIFF per
    band). Radiance is relative: crosstalk-corrected DN / (ISO/100 x exposure), Sentera's
    "autoexposure" normalisation (SenteraLLC py-radiometric-corrections); the ILS
    (``Camera:SunSensor``) is kept as the band's sun-sensor reading, in counts."""
    x, path = ctx.xmp, ctx.path
    exposure, gain = exposure_and_gain(ctx.exif, path)
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
    common = meta_fields(ctx)
    if common["capture_id"] is None:  # 6X: EXIF ImageUniqueID "<session>_<capture number>", one per capture
        common["capture_id"] = clean_text(ctx.exif.get("ImageUniqueID"))
    out = []
    for i, (name, wl) in enumerate(zip(names, wls)):
        if wl <= 0 or name.lower() == "garbage":  # a channel Sentera writes for crosstalk only
            continue
        check_wavelength(wl, path)
        out.append(CaptureMeta(
            path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl,
            fwhm_nm=fwhms[i] if i < len(fwhms) and fwhms[i] > 0 else None, exposure_s=exposure, gain=gain,
            black_levels=black_levels(ctx), irradiance=sun[i] if sun is not None and sun[i] > 0 else None, radiometry="sentera",
            channel=i if len(names) > 1 else None, maker_tags=((CHANNEL_MIX, matrix),), iso=gain * 100.0,
            irradiance_unit="1 (Sentera ILS counts)", **common,
        ))
    if not out:
        raise FrameError("no usable band (every CentralWavelength is 0)", path=path)
    return out


def band_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None, channels: np.ndarray | None,
                  out: np.ndarray | None) -> np.ndarray:
    """Relative radiance of a Sentera band (:func:`mscal_core.vendors.sentera_relative_radiance`),
    crosstalk-corrected with the whole image ``channels`` of a multi-channel file."""
    matrix = meta.maker_tag(CHANNEL_MIX)
    mixing = matrix is not None and meta.channel is not None
    if mixing and channels is None:
        raise FrameError("the colour transform needs every channel of the file", path=meta.path)
    return sentera_relative_radiance(
        dn, black_level=meta.black_level, gain=meta.gain, exposure_s=meta.exposure_s,
        bits_per_sample=meta.bits_per_sample, channels=channels if mixing else None,
        matrix=matrix if mixing else None, channel=meta.channel if mixing else None)


def band_vignetting(radiometry: str, shape: tuple[int, int], tags: VignettingTags) -> np.ndarray:
    """Sentera writes no vignetting model: ones."""
    return np.ones(shape)


def sun_factor(meta: CaptureMeta) -> float | None:
    """ILS counts: no reflectance on their own, but proportional to the light: ``1 / E`` serves
    the panel-anchored route (the panel sets the scale)."""
    e = meta.irradiance
    return None if e is None or not math.isfinite(e) or e <= 0 else 1.0 / e


def no_reflectance(meta: CaptureMeta) -> str:
    """Why the ILS gives no reflectance on its own: its counts have no published conversion."""
    return "Sentera's sun sensor (ILS) counts have no published conversion to reflectance"


MAKER = register(Maker(
    name="sentera", model="sentera", units=UNITS, claims=claims, read=read, radiance=band_radiance,
    vignetting=band_vignetting, order=30, sun_factor=sun_factor, no_reflectance=no_reflectance,
    namespaces={"ILS": ("http://sentera.com/ILS/1.0",)},  # the incident light sensor (seen in the Double 4K's files)
))
