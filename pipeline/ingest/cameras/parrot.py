"""Parrot Sequoia: tags, radiance model, sunshine sensor and quirks.

- **Tags**: EXIF ExposureTime, ISO, FNumber; XMP ``Camera:`` BandName, CentralWavelength,
  SensorModel (A, B, C), VignettingPolynomial2D + VignettingPolynomial2DName.
- **Radiance**: Parrot's sensor model (SEQ AN 01,
  :func:`mscal_core.vendors.sequoia_irradiance`): irradiance on the imager, SI-homogeneous
  with an arbitrary scale.
- **Sun sensor**: the sunshine sensor's ``Camera:IrradianceList`` records
  (:func:`sunshine_records`, :func:`mscal_core.vendors.sunshine_irradiance`), its fixed
  scale ``K`` (:data:`SUN_SCALES`) and its own angles (:data:`ATTITUDE`).
- **Quirks**: frames stored rotated 180 degrees (EXIF Orientation 3,
  :func:`pipeline.ingest.meta.upright_meta`); the position only in the capture's RGB JPEG
  (:func:`sibling_position`).
"""

from __future__ import annotations

import base64
import itertools
import math
import struct
from pathlib import Path

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.factory import vignetting_2d
from mscal_core.vendors import sequoia_irradiance, sunshine_irradiance

from pipeline.ingest.cameras.registry import AttitudeSource, Maker, register
from pipeline.ingest.exif import jpeg_exif
from pipeline.ingest.gps import exif_position as _gps
from pipeline.ingest.meta import (
    FIRMWARE_HINT,
    CaptureMeta,
    FieldParts,
    TagContext,
    VignettingTags,
    band_of,
    black_levels,
    exif_exposure,
    exif_iso,
    factory_vignetting,
    meta_fields,
    radiance_tag,
    tag_number,
)
from pipeline.ingest.sun_scale import SunScale
from pipeline.ingest.xmp import TagError, Xmp

UNITS = {"sequoia": "1 (Parrot SEQ AN 01 irradiance on the sensor, SI-homogeneous with an arbitrary scale)"}


#: The name in :attr:`~pipeline.ingest.meta.CaptureMeta.maker_tags` of a band's
#: ``Camera:SensorModel`` (A, B, C of Parrot's sensor model).
SENSOR_MODEL = "sensor_model"


def claims(ctx: TagContext) -> bool:
    """A Sequoia file: ``Camera:SensorModel``, or EXIF Make Parrot."""
    return ctx.xmp.has("SensorModel", ("Camera",)) or (ctx.make or "").lower() == "parrot"


def read(ctx: TagContext) -> list[CaptureMeta]:
    return [_sequoia(ctx)]


def _sequoia(ctx: TagContext) -> CaptureMeta:
    """Parrot Sequoia: SensorModel (A, B, C), VignettingPolynomial2D, IrradianceList."""
    x, path = ctx.xmp, ctx.path
    exposure = exif_exposure(ctx.exif, path)
    iso = exif_iso(ctx.exif, path)
    name, wl, fwhm = band_of(ctx)
    model = ctx.required("SensorModel", ("Camera",), 3)
    if "FNumber" not in ctx.exif:
        raise FrameError("no EXIF FNumber tag (Parrot's sensor model needs it)", path=path, hint=FIRMWARE_HINT)
    f_number = tag_number(ctx.exif["FNumber"], "EXIF FNumber", path)
    if not (math.isfinite(f_number) and 0.5 < f_number < 64):
        raise FrameError(f"EXIF FNumber {f_number!r} is not an f-number", path=path)
    poly2d = radiance_tag(ctx, "VignettingPolynomial2D")
    exps2d = radiance_tag(ctx, "VignettingPolynomial2DName")
    if not (poly2d and exps2d) or len(exps2d) != 2 * len(poly2d):
        raise FrameError("no usable vignetting model: needs XMP VignettingPolynomial2D and "
                         "VignettingPolynomial2DName (two exponents per coefficient)", path=path, hint=FIRMWARE_HINT)
    irr = ctx.optional("sun_sensor", lambda: _sequoia_sunshine(x, path))
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=iso / 100.0, black_levels=black_levels(ctx), vignetting_polynomial_2d=poly2d, vignetting_polynomial_2d_exponents=exps2d, irradiance=irr,
        radiometry="sequoia", f_number=f_number, iso=iso, maker_tags=((SENSOR_MODEL, (model[0], model[1], model[2])),),
        irradiance_unit="1 (sunshine CH0 / (gain x ms x golden sensitivity), relative)", **meta_fields(ctx),
    )



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
    exposure ms, CH0, CH1 rows); :func:`mscal_core.vendors.sunshine_irradiance`, divided by
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
            _, gps = jpeg_exif(path.read_bytes(), path)
            lat, lon, alt = _gps(gps)
        except (OSError, FrameError, TypeError, ValueError, ZeroDivisionError, IndexError, KeyError):
            return None
        if lat is None or lon is None or not (math.isfinite(lat) and math.isfinite(lon)) or (lat, lon) == (0.0, 0.0):
            return None
        return lat, lon, alt
    return None


def band_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None, channels: np.ndarray | None,
                  out: np.ndarray | None) -> np.ndarray:
    """Irradiance on the imager by Parrot's sensor model (:func:`mscal_core.vendors.sequoia_irradiance`)."""
    model = meta.maker_tag(SENSOR_MODEL)
    assert model is not None and meta.f_number is not None and meta.iso is not None
    return sequoia_irradiance(dn, f_number=meta.f_number, exposure_s=meta.exposure_s, iso=meta.iso,
                              sensor_model=model, vignetting=factory_vignetting(meta))


def band_vignetting(radiometry: str, shape: tuple[int, int], tags: VignettingTags) -> np.ndarray:
    """Parrot's 2-D polynomial vignetting (:func:`mscal_core.factory.vignetting_2d`)."""
    assert tags.poly_2d is not None and tags.exponents_2d is not None
    return vignetting_2d(shape, tags.poly_2d, tags.exponents_2d)


#: The fixed sun-sensor scale (:mod:`pipeline.ingest.sun_scale`, ``c = 5e-4``): Parrot's sensor
#: model gives the irradiance on the imager ``I`` (SEQ AN 01, :func:`mscal_core.vendors.sequoia_irradiance`)
#: and on the sunshine sensor ``E`` (:func:`mscal_core.vendors.sunshine_irradiance`), both
#: "homogeneous to SI units but with an arbitrary scaling factor"; reflectance is ``R = K I / E``
#: with ``K`` a constant of the sensors' responses (Parrot developer forum, "Reflectance
#: estimation" and "About radiometric calibration": "K is a constant that depends on sensors
#: responses", found once with a target of known reflectance). Parrot publishes no K: mscal fixes
#: ``K = 5e-4`` for the camera model, chosen once (2026-12) so that the one real capture in
#: ../shared/data lies in the uint16 TIFFs' range (its band medians 0.15 .. 0.41, NIR 99th
#: percentile 1.2): the same for every Sequoia and run; absolute values need a panel.
SUN_SCALES = {
    "sequoia": SunScale(5e-4, "R = K I / E, K = 5e-4 (I: SEQ AN 01 irradiance on the imager, E: sunshine sensor "
                              "CH0 / (gain x ms x golden sensitivity))",
                        "Parrot SEQ AN 01 and developer forum ('Reflectance estimation', 'About radiometric "
                        "calibration': R = K I / E, K a constant of the sensors' responses); Parrot publishes no K: "
                        "mscal fixes K = 5e-4 for the camera model (chosen once so that the real sample capture "
                        "lies in 0..2), never from a run's data", False),
}


def sunshine_angles(x: Xmp) -> tuple[float, float, float] | None:
    """The sunshine sensor's own yaw, pitch, roll (radians) of its last ``IrradianceList``
    record (Parrot developer forum "Details of Irradiance List tag for Sunshine sensor"; a
    linear sensor with no black level), None without one. A list that cannot be decoded gives
    none here: it is named where the reading itself is read."""
    try:
        recs = sunshine_records(x)
    except TagError:
        return None
    if not recs:
        return None
    last = recs[-1]
    return math.radians(last[5]), math.radians(last[6]), math.radians(last[7])


#: The sunshine sensor's angles; else the aircraft's ``Camera:Yaw/Pitch/Roll``
#: (:mod:`pipeline.ingest.sunsensor`, every maker's fallback).
ATTITUDE = (AttitudeSource(30, "Camera:IrradianceList (sunshine sensor)", sunshine_angles),)


MAKER = register(Maker(
    name="parrot", model="sequoia", units=UNITS, claims=claims, read=read, radiance=band_radiance,
    vignetting=band_vignetting, order=20, sun_sensor_tag="XMP Camera:IrradianceList (sunshine sensor)",
    sun_scales=SUN_SCALES, attitude=ATTITUDE, sun_sensor_xmp=frozenset({"IrradianceList"}),
    vignetting_tags="XMP VignettingPolynomial2D", sibling_position=sibling_position,
))
