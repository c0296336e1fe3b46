"""MicaSense (RedEdge, RedEdge-M/-MX, MX Dual, RedEdge-P, Altum, Altum-PT): tags, radiance
model, DLS sun sensor and quirks.

- **Tags**: EXIF ExposureTime, ISOSpeed (gain = ISO/100), BlackLevel (else XMP DarkRowValue);
  XMP ``MicaSense:``/``Camera:`` BandName, CentralWavelength, WavelengthFWHM,
  RadiometricCalibration (a1, a2, a3), VignettingCenter + VignettingPolynomial or
  VignettingPolynomial2D + VignettingPolynomial2DName.
- **Radiance**: micasense/imageprocessing ``image.py`` ``radiance()``
  (:func:`mscal_core.factory.radiance`, W m-2 sr-1 nm-1); a field calibration may replace the
  response and/or vignetting (:class:`~pipeline.ingest.meta.FieldParts`).
- **Sun sensor**: DLS 1 ``Camera:Irradiance``, DLS 2 ``HorizontalIrradiance`` with its scale;
  the fixed scale ``R = pi L / E`` (:data:`SUN_SCALES`), the DLS's orientation
  (:data:`ATTITUDE`) and DLS 2's measured direct/scattered split (:func:`dls2_split`,
  :func:`dls2_correction`), for :mod:`pipeline.ingest.sunsensor`; the unit rules of its
  readings (:func:`dls_unit_rules`), checked against the clear sky by :mod:`pipeline.apply.sun_check`.
- **Quirks**: legacy RedEdge firmware's wrong shortest exposure; Altum's LWIR band (thermal,
  centi-kelvin DN) and a panchromatic band, read but kept out of reflectance.

It is also the fallback: a file no other maker claims is read as a MicaSense band file.
"""

from __future__ import annotations

import math

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.factory import field_response_scale, field_response_signal, radiance, thermal_kelvin, vignetting_map
from mscal_core.sunsensor import dls2_horizontal

from pipeline.ingest.cameras.registry import AttitudeSource, Maker, SunSplit, register
from pipeline.ingest.meta import (
    FIRMWARE_HINT,
    CaptureMeta,
    FieldParts,
    TagContext,
    VignettingTags,
    band_of,
    black_levels,
    exposure_and_gain,
    factory_vignetting,
    meta_fields,
    positive_irradiance,
    radiance_tag,
    tag_number,
)
from pipeline.ingest.sun_scale import SunScale
from pipeline.ingest.xmp import TagError, Xmp

UNITS = {
    "micasense": "W m-2 sr-1 nm-1",
    "thermal": "K",
    "panchro": "W m-2 sr-1 nm-1",
}


def _kept_out(ctx: TagContext) -> str | None:
    """The band name of an LWIR or panchromatic band file, else None."""
    x = ctx.xmp
    band = x.text("BandName") or x.text("BandName", ("drone-dji",))
    if band is not None and (band.upper() == "LWIR" or band.casefold().startswith("panchro")):
        return band
    return None


def read(ctx: TagContext) -> list[CaptureMeta]:
    """The band of a MicaSense file (an LWIR band as thermal, a panchromatic band with its
    radiometric model when it has a full one)."""
    band = _kept_out(ctx)
    if band is not None and band.upper() == "LWIR":
        return [_band_only(ctx, band, "thermal")]
    if band is not None:
        try:
            return [_micasense(ctx, panchro=True)]
        except FrameError:  # a band kept out of reflectance need not carry a full radiometric model
            return [_band_only(ctx, band, "panchro")]
    return [_micasense(ctx)]


def _micasense(ctx: TagContext, panchro: bool = False) -> CaptureMeta:
    """MicaSense: micasense/imageprocessing ``image.py`` ``radiance()`` (cameras.md §1.3)."""
    x, path = ctx.xmp, ctx.path
    exposure, gain = exposure_and_gain(ctx.exif, path)
    exposure = micasense_exposure(exposure, ctx.model)
    name, wl, fwhm = band_of(ctx, ("drone-dji",))  # as _kept_out reads it
    black = black_levels(ctx)
    dark = ctx.optional(None, lambda: x.numbers("DarkRowValue"))
    if not black and not dark:
        raise FrameError("no EXIF BlackLevel and no XMP DarkRowValue tag", path=path, hint=FIRMWARE_HINT)
    cal = ctx.required("RadiometricCalibration", count=3)
    if cal[0] <= 0:
        raise FrameError(f"XMP RadiometricCalibration a1 = {cal[0]!r} must be positive", path=path, hint=FIRMWARE_HINT)
    center = radiance_tag(ctx, "VignettingCenter", 2)
    poly = radiance_tag(ctx, "VignettingPolynomial")
    poly2d = radiance_tag(ctx, "VignettingPolynomial2D")
    exps2d = radiance_tag(ctx, "VignettingPolynomial2DName")
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
    irr = dls_irradiance(ctx)
    return CaptureMeta(
        path=path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exposure, gain=gain, black_levels=black, dark_row_values=dark,
        radiometric_calibration=(cal[0], cal[1], cal[2]),
        vignetting_center=(center[0], center[1]) if center else None, vignetting_polynomial=poly,
        vignetting_polynomial_2d=poly2d, vignetting_polynomial_2d_exponents=exps2d, irradiance=irr,
        radiometry="panchro" if panchro else "micasense", iso=gain * 100.0,
        **meta_fields(ctx),
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


def dls_irradiance(ctx: TagContext) -> float | None:
    """Spectral irradiance on the DLS, W m-2 nm-1: ``Camera:Irradiance`` (the reading on the
    sensor's own plane), else DLS 2's ``HorizontalIrradiance``; either times the file's
    irradiance scale (:func:`irradiance_scale`). DLS 2 firmware still writes the
    legacy ``Irradiance`` tag beside ``HorizontalIrradiance``, in the same uW cm-2 nm-1 as its
    other irradiance tags ("DLS2 irradiance units",
    https://github.com/micasense/imageprocessing/issues/47): read
    unscaled it gave reflectance 100x too low."""
    ns = ("Camera", "MicaSense", "DLS")
    irr = positive_irradiance(ctx, "Irradiance", ("Camera", "MicaSense"))
    if irr is None:
        irr = positive_irradiance(ctx, "HorizontalIrradiance", ns)
    if irr is None:
        return None
    scale = irradiance_scale(ctx)
    return None if scale is None else irr * scale


def irradiance_scale(ctx: TagContext) -> float | None:
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


#: The DLS's irradiance tags' namespaces.
DLS_NS = ("Camera", "MicaSense", "DLS")
#: The two unit rules MicaSense documents for DLS 2 files without ``IrradianceScaleToSIUnits``
#: (:func:`dls_unit_rules`).
LIBRARY_RULE = "x 0.01: uW cm-2 nm-1 (MicaSense library, DLS 2 without IrradianceScaleToSIUnits)"
AS_WRITTEN_RULE = "x 1: W m-2 nm-1 as written (DLS 2 firmware that wrote SI units without the scale tag)"
DLS1_RULE = "x 1: W m-2 nm-1 (DLS 1)"


def dls_unit_rules(x: Xmp) -> tuple[dict[str, float], float]:
    """A MicaSense band file's unit rules ``{rule: scale to W m-2 nm-1}`` and the scale the
    reader applied (:func:`irradiance_scale`), for :mod:`pipeline.apply.sun_check`: the file's
    ``IrradianceScaleToSIUnits`` when it has a positive one; else, for DLS 2's
    ``HorizontalIrradiance``, two rules that disagree: micasense/imageprocessing ``metadata.py``
    ``irradiance_scale_factor()`` takes the tags in uW cm-2 nm-1 (x 0.01, the reader's), but a
    RedEdge-M with firmware 7.4.0 and a DLS 2 v1.3.0 wrote ``SpectralIrradiance`` 0.77 and
    ``HorizontalIrradiance`` 0.20 already in W m-2 nm-1 at a sun elevation of 8.5 degrees (read
    x 0.01 they were 80 times too low against the flight's own panel); else DLS 1, x 1."""
    try:
        v = x.numbers("IrradianceScaleToSIUnits", DLS_NS)
    except TagError:
        v = None
    if v is not None and math.isfinite(v[0]) and v[0] > 0:
        return {f"x {v[0]:g}: XMP IrradianceScaleToSIUnits": float(v[0])}, float(v[0])
    if x.has("HorizontalIrradiance", DLS_NS):
        return {LIBRARY_RULE: 0.01, AS_WRITTEN_RULE: 1.0}, 0.01
    return {DLS1_RULE: 1.0}, 1.0



def _band_only(ctx: TagContext, band: str, radiometry: str) -> CaptureMeta:
    """A band read for what it is but never part of reflectance: LWIR (Altum, Altum-PT;
    centi-kelvin DN) or a panchromatic band without a full radiometric model."""
    x = ctx.xmp
    wl = ctx.optional(None, lambda: x.number("CentralWavelength")) or 11000.0
    exposure = tag_number(ctx.exif["ExposureTime"], "EXIF ExposureTime", ctx.path) if "ExposureTime" in ctx.exif else 0.0
    return CaptureMeta(
        path=ctx.path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=band, wavelength_nm=wl, fwhm_nm=None,
        exposure_s=exposure, gain=1.0, black_levels=(), irradiance=None, radiometry=radiometry,
        **meta_fields(ctx),
    )



def band_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None, channels: np.ndarray | None,
                  out: np.ndarray | None) -> np.ndarray:
    """Radiance of a MicaSense band (:func:`mscal_core.factory.radiance`), with the field's
    response and/or vignetting in ``parts`` in place of the factory's; kelvin for LWIR."""
    if meta.radiometry == "thermal":
        return thermal_kelvin(dn)
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


def band_vignetting(radiometry: str, shape: tuple[int, int], tags: VignettingTags) -> np.ndarray:
    """MicaSense's radial or 2-D polynomial vignetting (:func:`mscal_core.factory.vignetting_map`);
    none (ones) for LWIR."""
    if radiometry == "thermal":
        return np.ones(shape)
    return vignetting_map(shape, tags.center, tags.poly, poly_2d=tags.poly_2d, exponents_2d=tags.exponents_2d)


#: The fixed sun-sensor scale (:mod:`pipeline.ingest.sun_scale`): ``R = pi L / E`` with ``L`` in
#: W m-2 sr-1 nm-1 and ``E`` in W m-2 nm-1 (micasense/imageprocessing ``image.py``
#: ``reflectance()``; MicaSense "Tutorial 3 - DLS Sensor Basic Usage"): absolute.
SUN_SCALES = {
    "micasense": SunScale(math.pi, "R = pi L / E (L W m-2 sr-1 nm-1, E W m-2 nm-1)",
                          "MicaSense, micasense/imageprocessing image.py reflectance() and Tutorial 3 (DLS): pi", True),
}

#: The DLS's orientation for the tilt model (MicaSense, "Tutorial 3 - DLS Sensor Basic Usage" and
#: ``micasense/dls.py`` of micasense/imageprocessing): ``DLS:Yaw/Pitch/Roll`` (radians, the DLS's
#: own IMU), else ``Camera:IrradianceYaw/Pitch/Roll`` (degrees); DLS 1 readings use the clear-sky
#: diffuse ratio 1/6 (``dir_dif_ratio = 6``).
ATTITUDE = (
    AttitudeSource(10, "DLS:Yaw/Pitch/Roll", lambda x: x.angles(("Yaw", "Pitch", "Roll"), ("DLS",), degrees=False)),
    AttitudeSource(20, "Camera:IrradianceYaw/Pitch/Roll",
                   lambda x: x.angles(("IrradianceYaw", "IrradiancePitch", "IrradianceRoll"), ("Camera", "MicaSense"),
                                      degrees=True)),
)


def dls2_split(x: Xmp) -> SunSplit | None:
    """DLS 2 ``DirectIrradiance``, ``ScatteredIrradiance`` and ``HorizontalIrradiance``, or None
    (the sensor measures the split; its ratio replaces 1/6 in the tilt model)."""
    ns = ("DLS", "Camera", "MicaSense")
    d, s = x.number("DirectIrradiance", ns), x.number("ScatteredIrradiance", ns)
    if d is None or s is None or not (d > 0 and s >= 0):
        return None
    h = x.number("HorizontalIrradiance", ns)
    return SunSplit(float(d), float(s), (float(h) if h is not None and h > 0 else None))


def dls2_correction(x: Xmp, split: SunSplit, elevation: float) -> float | None:
    """``E_h / E_meas`` of a DLS 2 reading that is its ``HorizontalIrradiance`` (the file holds
    no tilted ``Irradiance``): ``E_h = E_dir sin(el) + E_scattered`` with the elevation
    recomputed from time and position (micasense/imageprocessing ``image.py``
    ``compute_horizontal_irradiance_dls2``: "for cases where the camera system did not do it
    correctly"); 1 without a horizontal value. None when the file holds the tilted reading as
    well: the tilt model runs with the measured ratio."""
    if x.number("Irradiance", ("Camera", "MicaSense")) is not None:
        return None
    h = split.horizontal
    return float(dls2_horizontal(split.direct, split.scattered, elevation)) / h if h else 1.0


#: The XMP properties the DLS hooks read (:data:`ATTITUDE`, :func:`dls2_split`,
#: :func:`dls2_correction`) and the unit check of its readings
#: (:func:`irradiance_scale`'s tags, :func:`dls_unit_rules`), kept on each band's metadata.
SUN_SENSOR_XMP = frozenset({
    "Yaw", "Pitch", "Roll", "IrradianceYaw", "IrradiancePitch", "IrradianceRoll", "Irradiance",
    "DirectIrradiance", "ScatteredIrradiance", "HorizontalIrradiance", "IrradianceScaleToSIUnits",
})

#: MicaSense's own XMP namespaces (its files write the Pix4D camera schema's tags in ``MicaSense:``
#: as well, so it is one of the namespaces looked up when a reader names none) and its DLS's.
NAMESPACES = {"MicaSense": ("http://micasense.com/MicaSense/1.0",), "DLS": ("http://micasense.com/DLS/1.0",)}

#: Radiometries of bands read but never part of reflectance: Altum's LWIR band, a panchromatic band.
KEPT_OUT = frozenset({"thermal", "panchro"})

MAKER = register(Maker(
    name="micasense", model="micasense", units=UNITS, claims=lambda ctx: _kept_out(ctx) is not None, read=read,
    radiance=band_radiance, vignetting=band_vignetting, order=0, fallback=True,
    sun_sensor_tag="XMP Camera:Irradiance (DLS 1) or DLS:HorizontalIrradiance (DLS 2)",
    sun_scales=SUN_SCALES, attitude=ATTITUDE, sun_split=dls2_split, split_correction=dls2_correction,
    sun_sensor_xmp=SUN_SENSOR_XMP, sun_unit_rules=dls_unit_rules, kept_out=KEPT_OUT,
    capture_id_tags=(("MicaSense", "CaptureId"),), namespaces=NAMESPACES, default_namespaces=("MicaSense",),
    vignetting_tags="XMP VignettingCenter/VignettingPolynomial or VignettingPolynomial2D", field_parts=True,
    # OpenDroneMap's opendm/photo.py reads a capture's id from MicaSense:CaptureId, among others
    capture_id_output=("MicaSense", "http://micasense.com/MicaSense/1.0/", "CaptureId"),
))
