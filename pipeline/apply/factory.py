"""``mscal apply CAPTURE_DIR --calibration factory -o OUT``: cameras that carry factory
radiometric metadata (MicaSense, Parrot Sequoia, DJI P4 Multispectral / Mavic 3M, Sentera
Double 4K; the camera is recognised by :func:`pipeline.ingest.identify.identify_camera`, or
named with ``--camera``; each vendor's model is in :mod:`pipeline.ingest.camera_meta` and
:mod:`mscal_core.factory`).

A frame is one capture (all its band files, grouped by file name, one XMP capture id per
capture, or one multi-channel file; in the folder or an SD-card tree below it;
:func:`pipeline.apply.captures.find_captures`). Bands the camera writes but reflectance does
not use (panchromatic, thermal) are read, left out and named in run.json ``skipped_bands``; a
thermal band's temperature in kelvin (the camera's own conversion) is written to its own
float32 TIFFs ``thermal/<capture>_<band>.tif`` (run.json ``thermal``;
:func:`pipeline.apply.executor.write_thermal`).
The factory chain runs in the one apply executor (:mod:`pipeline.apply.executor`). Per band:

- radiance ``L_b`` with the file's own factory model (MicaSense: black level,
  ``a1/gain/exposure`` with the row-gradient terms, vignetting polynomial; the other vendors'
  models in :func:`pipeline.ingest.cameras.dispatch.factory_radiance`; the unit, in run.json
  ``radiance_unit``, is the vendor's);
- reflectance ``R_b = k_b L_b`` with one factor per band from the *reference*:

  - ``panel``: a capture of a reflectance panel of known reflectance ``rho_b`` in the same
    folder. The light on the panel is split into colour and brightness (Eq. 11-14,
    ``L_b(x) = S_b B(x) rho_b`` over a grid on the panel, gauge ``median(B) = 1``) and
    ``k_b = 1 / S_b``: a partly shaded panel sets the factor of its median-lit part instead
    of its mean. Several panel captures: ``k_b`` is their mean (each is in run.json). The
    panel region: XMP ReflectArea, else a marker in the panel's plane, else detected, else a
    pixel polygon (the last two from ``panel`` of a session.yaml in the folder or up to two
    levels above it; :func:`pipeline.ingest.session.parse_panel`);
  - ``dls``: the capture's own downwelling light sensor, ``k_b = c / E_b`` with ``c`` the
    camera model's one fixed scale (:mod:`pipeline.ingest.sun_scale`: MicaSense pi, E in W m-2
    nm-1; DJI 1 as its guides write it; Sequoia Parrot's K fixed at 5e-4; run.json
    ``reference.sun_sensor_scale``), never a constant chosen from a run. A band without a usable
    reading keeps its radiance; its reflectance is NaN and named in run.json
    ``reflectance_missing`` (the capture is not quarantined; the summary and the report warn,
    ``reflectance_missing``). When no band of any capture has one, ``--reference dls`` is
    refused before anything is written (InputError naming a band file and the tag,
    :func:`pipeline.apply.factory_reference.sun_sensor_missing`);
  - ``none``: radiance only (reflectance NaN), when no panel is given and no band of any
    capture has a usable sun-sensor reflectance (Sentera: its sun sensor has no published
    conversion; a sun sensor whose tags are missing or unusable): run.json
    ``reference.reason`` names a file and the tag, and the summary and the report warn
    (``no_reflectance``).

  ``auto`` (default) takes the panel when ``--panel-reflectance`` is given, or when panel
  captures carry the panel's reflectance as the camera read it from the panel's QR code
  (MicaSense XMP ``Albedo`` with ``CalibrationPicture`` 2 in every band file, as MicaSense's
  own library uses it; each such capture with its own values; run.json
  ``reference.panel_reflectance`` says which; when no panel is found in them, the route it
  would have taken without them, the reason in ``reference.albedo_panel_unusable``), or when a
  panel capture's serial (XMP PanelSerial, else its QR code) is a catalog target's
  (:mod:`pipeline.apply.panel_search`; run.json ``reference.panel_serial``), else the DLS, else none.
  The route, the panel captures and run.json ``reference``:
  :mod:`pipeline.apply.factory_reference`.

Frames stored turned (EXIF Orientation; Sequoia: 180 degrees) are turned upright in every
output, raw.zarr included, after the band registration (run.json ``orientation``).

  With ``--illumination nearest|linear`` (panel route only) each capture gets the light of its
  time instead of the panels' mean: the panel captures' ``S_c = 1 / k_c`` interpolated in time
  and scaled by the captures' DLS readings between them (:func:`panel_light`).

Outputs as for every apply (SPEC "Outputs of apply"): ``reflectance.zarr`` with
``reflectance`` and ``radiance`` (frame, band, y, x) float32 and the indices, ``raw.zarr``
(the stored DN, frame x band x y x x), photogrammetry and NDVI TIFFs, ``run.json``. Bands whose
files carry their own registration (DJI: ``drone-dji:DewarpData`` and ``CalibratedHMatrix``,
the Image Processing Guides' steps 2-3; :func:`pipeline.ingest.cameras.dispatch.align_by_files`)
are put on the camera's designed image plane (``--no-align``: not); other cameras' bands are
*not* co-registered here (each band keeps its own pixel grid): per-pixel indices mix
neighbouring ground points near edges; ``reflectance.zarr`` says so in its attributes. With
``--registration REG.zarr`` (a store from ``mscal register``) the radiance of each
band is warped onto the reference band's grid before the factor (the capture's own transforms
if it was registered, else the session's; NaN where a band does not cover).

With ``--field-calibration CALIB.zarr`` components of a field calibration of the same camera
replace the factory's (``--field-components``: ``response`` = U of Eq. 5-7 on the factory's
scale, ``vignetting`` = V of Eq. 8-10; :func:`pipeline.ingest.cameras.dispatch.factory_radiance`); run.json
``components`` records where each came from.

Every output is written under a temporary name and renamed; a run that finds ``run.json``
matching its inputs (the band files' content) and options does nothing.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import mscal_core
import numpy as np
from mscal_core.errors import CalibrationStoreError, FrameError, InputError
from mscal_core.illumination import INTERPOLATION_MODES

from pipeline.apply.captures import CaptureRun, CaptureSource, capture_times, find_captures
from pipeline.apply.coregistration import COREGISTRATION_CHECK
from pipeline.apply.driver import drive
from pipeline.apply.execution import Execution, flight_size_hint, start_worker_server
from pipeline.apply.executor import FactoryChain, field_parts
from pipeline.apply.factory_reference import (
    ALBEDO_SOURCE,
    NO_SUN_SENSOR_HINT,
    PanelReference,
    reference_panels,
    reference_record,
    reference_route,
    serial_wanted,
    sun_sensor_missing,
)
from pipeline.apply.options import ApplyResult, export_band_indices
from pipeline.apply.panel_search import (
    find_panel_serial,
    panels_seen,
    seen_record,
)
from pipeline.apply.products import factor_record
from pipeline.apply.quality import run_flagging
from pipeline.apply.sun_check import SunCheck, sun_sensor_check
from pipeline.apply.sunlight import (
    RATIO_RULES,
    PanelSensorLight,
    check_times,
    light_warnings,
    panel_sensor_light,
    readings_missing,
)
from pipeline.ingest.camera_meta import METADATA_READING
from pipeline.ingest.cameras.dispatch import (
    factory_models,
    file_registration_note,
    has_file_registration,
    takes_field_parts,
)
from pipeline.ingest.catalog import Camera
from pipeline.ingest.grouping import Capture
from pipeline.ingest.identify import Identification, identify_camera
from pipeline.ingest.meta import FieldParts, sun_sensor_absolute
from pipeline.ingest.products import Products, indices_for
from pipeline.ingest.session import PanelConfig, panel_config_near
from pipeline.ingest.sun_scale import sun_scale_constant
from pipeline.ingest.sunsensor import SensorLight, sensor_light
from pipeline.ingest.targets import serial_targets_digest
from pipeline.storage.cache import code_digest

FACTORY = "factory"
REFERENCES = ("auto", "panel", "dls", "panel-dls")  # + "none" (radiance only) when auto finds no usable sun sensor
LIGHT_MODEL = ("sun sensor turned horizontal; panel-dls; one panel region for all bands; one fixed sun-sensor scale "
               "per camera model; DLS 2 unit rules checked against the clear sky; diffuse ratio fitted from the "
               "flight only where panels anchor the light")
FIELD_COMPONENTS = ("response", "vignetting")  # store variables: inverse_response, vignetting


@dataclass(frozen=True)
class FactoryOptions:
    """Options of a factory-calibrated apply (see the module docstring)."""

    reference: str = "auto"  # auto | panel | dls
    panel_captures: tuple[str, ...] = ()  # capture names (e.g. IMG_0000); () = search the folder's ends
    panel_reflectance: str | None = None  # a number or a reflectance target name
    tiff_dtype: str = "uint16"
    export_bands: tuple[str, ...] | None = None
    products: Products = Products()  # what is written beyond raw.zarr and reflectance (pipeline.ingest.products)
    strict: bool = False
    registration: str | None = None  # a store from 'mscal register': bands aligned to its reference
    illumination: str | None = None  # nearest | linear: the light between panel captures; None: their mean
    field_calibration: str | None = None  # a store from 'mscal calibrate' / 'mscal fit' of this camera
    field_components: tuple[str, ...] = ()  # of FIELD_COMPONENTS taken from it; () = all it holds
    execution: Execution = Execution()  # how the pass runs (not what it computes: not fingerprinted)
    camera: str | None = None  # --camera NAME: the catalog camera, instead of recognising it from the files
    align: bool = True  # False (--no-align): the band files' own registration (DJI) is not applied
    captures: tuple[str, ...] = ()  # only these captures of the folder (one flight of a card); () = all

    def __post_init__(self) -> None:
        if self.reference not in REFERENCES:
            raise InputError(f"reference {self.reference!r} is not one of {', '.join(REFERENCES)}")
        unknown = [c for c in self.field_components if c not in FIELD_COMPONENTS]
        if unknown:
            raise InputError(f"--field-components {', '.join(unknown)}: not one of {', '.join(FIELD_COMPONENTS)}",
                             hint="e.g. --field-components vignetting (factory response, field vignetting)")
        if self.illumination is not None and self.illumination not in INTERPOLATION_MODES:
            raise InputError(f"--illumination {self.illumination!r}: use one of {', '.join(INTERPOLATION_MODES)}")
        if self.illumination is not None and self.reference == "dls":
            raise InputError("--illumination is for the panel route: with --reference dls each capture already has "
                             "its own sun-sensor light", hint="leave --illumination out, or give --panel-reflectance")
        if self.field_components and self.field_calibration is None:
            raise InputError("--field-components needs --field-calibration CALIB.zarr (the store to take them from)")

    def fingerprint(self) -> dict[str, Any]:
        d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items() if k not in ("strict", "execution")}
        d["products"] = self.products.fingerprint()
        for key in ("registration", "field_calibration", "illumination"):  # earlier runs stay up to date
            if d[key] is None:
                d.pop(key)
        if not d["field_components"]:
            d.pop("field_components")
        if d["camera"] is None:
            d.pop("camera")
        if d["align"]:  # the default: earlier runs stay up to date
            d.pop("align")
        if not d["captures"]:
            d.pop("captures")
        return d


# --------------------------------------------------------------------------- the pass


def _registration(options: FactoryOptions, camera: Camera, shape: tuple[int, int, int]) -> tuple[Path, str] | None:
    """The ``--registration`` store (checked against the camera and image size) and the hash
    of its transforms, or None."""
    if options.registration is None:
        return None
    from pipeline.calibrate.registration import check_transforms
    from pipeline.storage.store import open_calibration

    path = Path(options.registration)
    ds = open_calibration(path, camera)
    if "band_transform" not in ds:
        raise CalibrationStoreError("store holds no band transforms", path=path,
                                    hint="make one with 'mscal register CAPTURES -o REG.zarr'")
    check_transforms(ds, camera.n_bands, shape[1:], path)
    h = hashlib.sha256()
    for name in ("band_transform", "capture_transform"):
        if name in ds:
            h.update(name.encode() + np.ascontiguousarray(ds[name].values).tobytes())
    return path, h.hexdigest()


def _field(options: FactoryOptions, camera: Camera, shape: tuple[int, int, int]
           ) -> tuple[str, tuple[str, ...], str] | None:
    """The ``--field-calibration`` store, the components taken from it (checked against the
    camera and image size) and the hash of those arrays, or None."""
    if options.field_calibration is None:
        return None
    from pipeline.storage.store import open_calibration

    path = Path(options.field_calibration)
    ds = open_calibration(path, camera)
    held = tuple(c for c in FIELD_COMPONENTS if ("inverse_response" if c == "response" else c) in ds)
    components = tuple(c for c in FIELD_COMPONENTS if c in (options.field_components or held))
    missing = [c for c in components if c not in held]
    if not components or missing:
        raise CalibrationStoreError(
            f"store holds no {' or '.join(missing or FIELD_COMPONENTS)} fit", path=path,
            hint="fit it with 'mscal fit response|vignetting' for this camera, or leave that component to the factory")
    if "vignetting" in components and tuple(ds["vignetting"].shape[1:]) != shape[1:]:
        raise CalibrationStoreError(f"vignetting is {tuple(ds['vignetting'].shape[1:])} pixels, the band files "
                                    f"{shape[1:]}", path=path, hint="use a store fitted on this camera's band files")
    h = hashlib.sha256()
    for c in components:
        name = "inverse_response" if c == "response" else c
        h.update(name.encode() + np.ascontiguousarray(ds[name].values).tobytes())
    return str(path.resolve()), components, h.hexdigest()


def apply_factory(capture_dir: str | Path, out: str | Path, options: FactoryOptions = FactoryOptions()) -> ApplyResult:
    """``mscal apply CAPTURE_DIR --calibration factory -o OUT`` (see the module docstring):
    the factory chain on the folder's captures (:class:`pipeline.apply.captures.CaptureSource`)
    through the one apply driver (:func:`pipeline.apply.driver.drive`)."""
    t_start = time.perf_counter()
    folder, out = Path(capture_dir), Path(out)
    if not folder.is_dir():
        raise InputError("capture folder not found", path=folder)
    start_worker_server(options.execution, flight_size_hint(folder))  # imports while the captures are read
    ident = _identify(folder, options)
    camera = ident.camera
    found = find_captures(folder, camera, options.captures)
    captures = found.captures
    if not captures:
        raise FrameError("no complete capture in the folder (all quarantined)", path=folder,
                         hint="; ".join(f"{q['file']}: {q['reason']}" for q in found.quarantined[:3]))
    shapes = {m.shape for c in captures for m in c.metas}
    if len(shapes) != 1:
        raise InputError(f"band images of different sizes {sorted(shapes)}", path=folder,
                         hint="bands of another resolution (e.g. thermal) need their own catalog camera")
    shape = (camera.n_bands, *shapes.pop())
    no_sun = sun_sensor_missing(captures)
    if options.reference == "dls" and no_sun is not None:  # before anything is read or written
        raise InputError(f"--reference dls, but no band of the {len(captures)} capture(s) has a usable sun-sensor "
                         f"reading; here: {no_sun[1]}", path=no_sun[0], hint=NO_SUN_SENSOR_HINT)
    export = export_band_indices(camera, options.export_bands)
    indices = indices_for(camera, options.products)  # NDVI if the bands make it; the others asked for

    registration = _registration(options, camera, shape)
    field = _field(options, camera, shape)
    near = panel_config_near(folder)
    parts = field_parts(field[0], field[1], camera.name) if field else None
    fingerprint = {
        "options": options.fingerprint(), "calibration": FACTORY,
        "mscal_version": mscal_core.__version__,
        "code_sha256": code_digest(),  # every source of mscal_core, pipeline and the catalogs
        "light_model": LIGHT_MODEL,  # results of earlier runs (raw sun-sensor readings) are not reused
        "metadata_reading": METADATA_READING,
        "coregistration": COREGISTRATION_CHECK,
    }
    if registration is not None:
        fingerprint["registration_sha256"] = registration[1]
    if field is not None:
        fingerprint["field_sha256"] = field[2]
    if near is not None:
        fingerprint["panel_config"] = {"session_yaml": str(near[1].resolve()), "panel": repr(near[0])}
    wanted = serial_wanted(options, captures)
    if wanted:  # the serial is read from the inputs; what its target says is in the catalog
        fingerprint["panel_serial_targets"] = serial_targets_digest()

    make_run = partial(_factory_run, options, folder, camera, captures, ident, field, near, parts, wanted, no_sun)
    return drive(CaptureSource(folder, camera, found, shape, indices, export, fingerprint, make_run,
                               options.products, options.execution), out, t_start)


def _factory_run(options: FactoryOptions, folder: Path, camera: Camera, captures: Sequence[Capture],
                 ident: Identification, field: tuple[str, tuple[str, ...], str] | None,
                 near: tuple[PanelConfig, Path] | None, parts: Sequence[FieldParts | None] | None, wanted: bool,
                 no_sun: tuple[Path, str] | None) -> CaptureRun:
    """The factory chain of a run that is not up to date: the light reference (the panel's
    serial when ``wanted``, the panels, the sun sensor and its check against the clear sky),
    each capture's factors, the stores' attributes and run.json's factory keys."""
    serial = find_panel_serial(captures, options.panel_captures) if wanted else None
    reference, panels, rho_source, unusable = reference_panels(
        options, reference_route(options, captures, serial), captures, folder, parts, None if near is None else near[0], serial)
    by_serial = serial is not None and serial.target is not None and rho_source == serial.rho_source
    notes = {} if serial is None or options.reference != "auto" else {
        "albedo": f"no {'--panel ' if options.panel_captures else ''}capture carries XMP Albedo with CalibrationPicture 2",
        **serial.record(by_serial, unusable)}
    panel_factor = None
    if panels:
        panel_factor = tuple(float(np.mean([p.factor_split[b] for p in panels])) for b in range(camera.n_bands))

    if options.illumination is not None and reference not in ("panel", "panel-dls"):
        raise InputError("--illumination is for the panel route: with the sun sensor (DLS) each capture already "
                         "has its own light", hint="leave --illumination out, or give --panel-reflectance")
    uses_panels = reference in ("panel", "panel-dls")
    # One search for panel captures the run does not use: they go to OUT/panels/, and with
    # --reference auto the summary and report say how to use them.
    unused = panels_seen(captures, options.panel_captures) if not uses_panels else []
    seen = unused if options.reference == "auto" else []
    times = capture_times(captures)
    # dls: each capture's factor from its own files (the diffuse ratio never fitted from the
    # flight); with panels the fit is part of the light's interpolation between them
    sensor = None if readings_missing(captures) else sensor_light(captures, times, fit_ratio=reference != "dls")
    check = None if sensor is None else sun_sensor_check(captures, sensor, times, camera.band_names)
    sensor = sensor if check is None else check.apply(sensor)  # each reading on its plausible unit rule
    panels = panels if check is None else check.panels(panels, [c.name for c in captures])
    light, scales = _capture_light(options, reference, captures, panels, times, sensor, folder)

    attrs = {"calibration": FACTORY, "reference": reference, "source": str(folder), "co_registered": 0,
             "comment": "bands are not co-registered: each band keeps its own pixel grid",
             "components": json.dumps(_components_record(None if field is None else (*field[:2], "")))}
    own = options.align and options.registration is None and all(
        has_file_registration(m) for c in captures for m in c.metas)
    if own:
        attrs.update({"co_registered": 1, "registration": "factory metadata",
                      "comment": "bands on the camera's designed image plane: "
                                 f"{file_registration_note([m for c in captures for m in c.metas])}"})
    if options.registration is not None:
        attrs.update({"co_registered": 1, "registration": str(options.registration),
                      "comment": "bands aligned to the reference band of the registration store "
                                 "(mscal register); NaN where a band does not cover the reference grid"})
    first = captures[0].metas[0]
    used = {ALBEDO_SOURCE: "the camera's XMP Albedo"}.get(rho_source or "", "the panel's serial" if by_serial
                                                          else "--panel-reflectance")
    panel_names = {p.capture: f"reflectance panel of the panel route ({used})" for p in panels}
    panel_names.update({name: "a reflectance panel (camera's panel flag, --panel, or detected); not used: "
                              "no --panel-reflectance" for name in unused})
    return CaptureRun(
        chain=FactoryChain(camera_clip_dn(camera), "panel" if reference == "panel-dls" else reference, panel_factor,
                           None if field is None else field[:2], run_flagging(options.products)),
        calibration=FACTORY, calibration_sha256=None, attrs=attrs,
        reflectance_name=f"reflectance (factory radiance x {reference} factor)", tiff_dtype=options.tiff_dtype,
        transforms=None if options.registration is None else Path(options.registration), factory_alignment=own,
        radiance_unit=first.radiance_unit, irradiance_unit=first.irradiance_unit,
        record=lambda caps: {"components": _components_record(field),
                             "reference": {**reference_record(reference, panels, panel_factor, camera, caps[0], no_sun,
                                                               rho_source, options.products.radiance),
                                           **({"albedo_panel_unusable": unusable}
                                              if unusable and serial is None else {}),
                                           **seen_record(seen), **notes},
                             "camera_identification": {"evidence": ident.evidence, "overridden": ident.overridden,
                                                       **ident.probe},
                             "radiance_unit": caps[0].metas[0].radiance_unit,
                             "radiance_factor": factor_record(reference, camera.band_names, panel_factor, bool(scales)),
                             "band_alignment": _alignment_record(options, own, caps),
                             "illumination": _light_record(options.illumination, panels, caps, scales, camera),
                             **light_record(reference, panels, captures, sensor, light, camera,
                                          options.illumination or DEFAULT_LIGHT_MODE, times, check)},
        scale=lambda name: scales.get(name),
        panels=panel_names, reference_band=_reference_band(options.registration, camera),
    )


def _reference_band(registration: str | None, camera: Camera) -> int | None:
    """The band a ``--registration`` store warps the others onto (its ``registration``
    attribute's ``reference_band``), or None."""
    if registration is None:
        return None
    from pipeline.storage.store import open_calibration

    name = (open_calibration(registration, camera).attrs.get("registration") or {}).get("reference_band")
    return camera.band_names.index(name) if name in camera.band_names else None


def _alignment_record(options: FactoryOptions, own: bool, captures: Sequence[Capture]) -> str:
    """run.json ``band_alignment``: how the bands were put on one pixel grid, if they were."""
    if options.registration is not None:
        return f"transforms of {options.registration} (mscal register)"
    if own:
        return f"factory metadata: {file_registration_note([m for c in captures for m in c.metas])}"
    if not options.align and any(has_file_registration(m) for c in captures for m in c.metas):
        return "none (--no-align: the band files' own registration was not applied)"
    return "none: each band keeps its own pixel grid"


def _identify(folder: Path, options: FactoryOptions) -> Identification:
    """The folder's camera (``--camera``, else recognised from the files); ``--field-calibration``
    refused up front for a camera whose radiance model takes no field calibration's parts
    (:func:`pipeline.ingest.cameras.dispatch.takes_field_parts`)."""
    ident = identify_camera(folder, options.camera)
    camera = ident.camera
    if options.field_calibration is not None and not takes_field_parts(camera.factory_model):
        takes = ", ".join(m for m in factory_models() if takes_field_parts(m)) or "none"
        raise InputError(f"--field-calibration replaces parts of a factory radiance model that takes them ({takes}); "
                         f"camera {camera.name} has the {camera.factory_model} model", path=folder,
                         hint="leave out --field-calibration")
    return ident


def camera_clip_dn(camera: Camera) -> int:
    """Stored value at and above which a pixel is clipped: the sensor's largest DN in the
    container's high bits (65520 for 12-bit data in 16-bit samples). A file whose own
    BitsPerSample holds less (12-bit packed) clips lower:
    :meth:`pipeline.ingest.meta.CaptureMeta.clipped_from`."""
    return ((1 << camera.bit_depth) - 1) << camera.dn_shift


def _components_record(field: tuple[str, tuple[str, ...], str] | None) -> dict[str, str]:
    """Where each part of the radiance model came from: 'factory' or 'field:STORE'."""
    return {c: (f"field:{field[0]}" if field is not None and c in field[1] else FACTORY) for c in FIELD_COMPONENTS}


def _capture_light(options: FactoryOptions, reference: str, captures: Sequence[Capture],
                   panels: Sequence[PanelReference], times: np.ndarray, sensor: SensorLight | None,
                   folder: Path) -> tuple[PanelSensorLight | None, dict[str, tuple[float, ...]]]:
    """``k_b`` of every capture that does not take the run's one factor: the sun sensor's
    (``dls``, tilt-corrected, :mod:`pipeline.apply.sunlight`), the panels' over time
    (``panel`` with ``--illumination``) or the panels anchored by the sensor (``panel-dls``,
    ``--illumination`` default linear)."""
    if reference == "dls" and sensor is not None:
        return None, {c.name: tuple(float(v) for v in sensor.factor[f]) for f, c in enumerate(captures)}
    if reference not in ("panel", "panel-dls") or (reference == "panel" and options.illumination is None):
        return None, {}
    if reference == "panel-dls" and sensor is None:
        raise InputError("--reference panel-dls: no capture in the folder has a sun-sensor reading", path=folder,
                         hint="use --reference panel (the panels alone), with --illumination to follow them in time")
    mode = options.illumination or DEFAULT_LIGHT_MODE
    light = panel_light(captures, panels, mode, folder, sensor if reference == "panel-dls" else None, times)
    return light, {c.name: tuple(float(v) for v in light.factor[f]) for f, c in enumerate(captures)}


#: ``panel-dls`` without ``--illumination``: the panel/sensor ratio linear in time between panels.
DEFAULT_LIGHT_MODE = "linear"


def panel_light(captures: Sequence[Capture], panels: Sequence[PanelReference], mode: str, folder: Path,
                sensor: SensorLight | None = None, times: np.ndarray | None = None) -> PanelSensorLight:
    """``k_b`` of every capture from the panel captures (and the sun sensor): each
    panel's ``1 / k_c`` (Eq. 11-14 split) interpolated to the capture's time (``nearest`` or
    ``linear``); with ``sensor``, the panel / sensor ratio per band is interpolated instead and
    multiplied by the capture's own tilt-corrected sensor reading
    (:func:`pipeline.apply.sunlight.panel_sensor_light`)."""
    times = capture_times(captures) if times is None else times
    names = [c.name for c in captures]
    check_times(captures, times, len(panels), folder)
    idx = [names.index(p.capture) for p in panels]
    return panel_sensor_light(np.array([p.factor_split for p in panels], dtype=np.float64), idx, times, sensor, mode)


def light_record(reference: str, panels: Sequence[PanelReference], captures: Sequence[Capture],
                 sensor: SensorLight | None, light: PanelSensorLight | None, camera: Camera,
                 mode: str = DEFAULT_LIGHT_MODE, times: np.ndarray | None = None,
                 check: SunCheck | None = None) -> dict[str, Any]:
    """run.json ``light``: per panel capture and band the panel's light ``1 / k`` beside the
    sun sensor's (tilt-corrected) and their ratio, per capture the light used, the warnings
    (numbers with thresholds) when panels and sensor disagree, and with several panels each
    panel's reflectance error when predicted from the others (``panel_check``); with ``check``,
    the sun sensor against the clear sky (``sun_sensor_check``, its warnings with the others)."""
    names, bands = [c.name for c in captures], list(camera.band_names)
    absolute = bool(captures) and sun_sensor_absolute(captures[0].metas[0])
    unit = "W m-2 nm-1 (pi / k)" if absolute else "relative (c / k)"
    scale = sun_scale_constant(captures[0].metas[0] if captures else None)
    rec: dict[str, Any] = {"route": reference, "irradiance_unit": unit}
    idx = {c.name: f for f, c in enumerate(captures)}
    rec["panels_over_time"] = [{
        "capture": p.capture,
        "panel_irradiance": dict(zip(bands, (round(scale / k, 6) for k in p.factor_split))),
        "sensor_irradiance": None if sensor is None else dict(zip(bands, (
            None if not np.isfinite(v) else round(scale * float(v), 6) for v in sensor.irradiance[idx[p.capture]]))),
    } for p in panels]
    if light is not None:
        rec["frame_irradiance"] = {n: dict(zip(bands, (round(scale / float(k), 6) for k in light.factor[f])))
                                   for f, n in enumerate(names)}
        rec["sensor_used"] = {n: bool(light.sensor_used[f].all()) for f, n in enumerate(names)}
        rec["panel_sensor_drift"] = dict(zip(bands, (None if not np.isfinite(d) else round(float(d), 6)
                                                     for d in light.drift)))
    if light is not None and len(panels) > 1:
        rec["panel_check"] = _panel_check(panels, names, sensor if reference == "panel-dls" else None, mode,
                                          capture_times(captures) if times is None else times, bands)
    rec["warnings"] = light_warnings(names, bands, sensor, light, [p.capture for p in panels])
    out = {"light": rec}
    if check is not None:
        rec["warnings"] += check.warnings
        out["sun_sensor_check"] = check.record
    if sensor is not None:
        out["sun_sensor"] = sensor.record(names, bands)
        if sensor.diffuse_ratio:
            out["sun_sensor"]["diffuse_ratio_rule"] = RATIO_RULES.get(reference, RATIO_RULES["panel"])
    return out


def _panel_check(panels: Sequence[PanelReference], names: Sequence[str], sensor: SensorLight | None, mode: str,
                 times: np.ndarray, bands: Sequence[str]) -> list[dict[str, Any]]:
    """Each panel's reflectance predicted from the other panels (and the sensor) over its own:
    ``k_pred / k_c - 1`` per band (0: they agree)."""
    k = np.array([p.factor_split for p in panels], dtype=np.float64)
    idx = [list(names).index(p.capture) for p in panels]
    out = []
    for c, p in enumerate(panels):
        others = [i for i in range(len(panels)) if i != c]
        pred = panel_sensor_light(k[others], [idx[i] for i in others], times, sensor, mode).factor[idx[c]]
        out.append({"capture": p.capture, "from": [panels[i].capture for i in others],
                    "reflectance_error": dict(zip(bands, (round(float(v), 6) for v in pred / k[c] - 1)))})
    return out


def _light_record(mode: str | None, panels: Sequence[PanelReference], captures: Sequence[Capture],
                  scales: dict[str, tuple[float, ...]], camera: Camera) -> dict[str, Any]:
    if not scales:
        return {"varies_in_time": False, "panels": [p.capture for p in panels],
                "note": "one factor per band for every capture (the panels' mean)"}
    return {"varies_in_time": True, "mode": mode or (DEFAULT_LIGHT_MODE if panels else None),
            "panels": [p.capture for p in panels],
            "per_frame": {c.name: dict(zip(camera.band_names, scales[c.name])) for c in captures}}
