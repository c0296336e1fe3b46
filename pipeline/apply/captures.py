"""Folders of captures as the camera writes them, and the apply pass over them.

A one-file-per-band camera (MicaSense RedEdge, Parrot Sequoia, DJI P4 Multispectral and the
like) writes one file per band per capture (``IMG_0000_1.tif ... IMG_0000_5.tif``), on an SD
card in a tree of sets and sub-folders (``0000SET/000/IMG_0000_1.tif``); a Sentera Double 4K
one multi-channel JPEG per capture. :func:`find_captures` finds every capture in such a tree
(grouped by name and XMP capture id in each folder by
:func:`pipeline.ingest.grouping.group_captures`, the one grouping of captures), quarantines
incomplete or duplicated ones, and names the other files it skips (logs, ``diag.dat``, the
camera's ``.bin`` files).

:class:`CaptureSource` is such a folder as a source of the one apply driver
(:func:`pipeline.apply.driver.drive`), whatever the radiometric chain: the factory's
(:mod:`pipeline.apply.factory`) or a field calibration store's (:func:`field_captures`). Its
pass writes the outputs every apply writes
(``reflectance.zarr``, ``raw.zarr``, photogrammetry and NDVI TIFFs, ``run.json`` with the
bands the camera wrote but reflectance leaves out (``skipped_bands``), the tag problems that
disabled a feature (``metadata_problems``), the orientation of the outputs and, for the
factory chain, the bands without reflectance (``reflectance_missing``)): stores under
temporary names, renamed into place; a capture found unusable during the pass is
quarantined and the pass redone without it; a run whose fingerprint matches ``run.json``
does nothing.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import mscal_core
import numpy as np
import xarray as xr
from mscal_core.errors import CalibrationStoreError, FrameError, InputError

from pipeline.apply.coregistration import COREGISTRATION_CHECK, METADATA, Refinement, RunCoregistration, prepare
from pipeline.apply.driver import Done
from pipeline.apply.execution import Execution
from pipeline.apply.executor import OUTPUT_COMPRESSORS, FactoryChain, FieldChain, Job, Plan, Runner, capture_reflectance
from pipeline.apply.light import illumination_plan
from pipeline.apply.options import (
    ApplyOptions,
    calibration_clip_dn,
    calibration_hash,
    export_band_indices,
    index_roles,
    normalisation,
    pass_geometry,
)
from pipeline.apply.quality import checked, run_flagging
from pipeline.apply.record import (
    RUN_JSON,
    content_fingerprint,
    illumination_record,
    remove_frame_tiffs,
    run_fingerprint,
    up_to_date,
)
from pipeline.apply.template import create_store, frame_template, product_variables
from pipeline.calibrate.registration import check_transforms
from pipeline.ingest.camera_meta import METADATA_READING
from pipeline.ingest.cameras.registry import capture_id_output
from pipeline.ingest.catalog import Camera, Index
from pipeline.ingest.gps import without_unreachable
from pipeline.ingest.grouping import Capture, capture_folder_of, capture_pattern, companion_images, group_captures
from pipeline.ingest.medians import DN_MEDIAN, DN_MEDIAN_ATTRS
from pipeline.ingest.photo_tags import CameraOptics, read_optics
from pipeline.ingest.products import Products, indices_for
from pipeline.ingest.raw import raw_codec
from pipeline.products.writers import BandTags, FrameTags
from pipeline.storage.atomic import temporary_folder_name
from pipeline.storage.run_layout import run_value
from pipeline.storage.store import (
    CF_VARIABLES,
    FLIGHT_VARIABLES,
    FRAME_COORD_ATTRS,
    check_camera,
    open_calibration,
)

__all__ = ["CaptureFolder", "CaptureRun", "CaptureSource", "capture_tags", "field_captures", "find_captures",
           "is_capture_folder", "unchanged_run"]

# Files left out without a word (every other file that is not a capture is named in run.json's
# ``skipped``): the file systems' own, the uploader's READY marker (mscal serve) and a card
# session's session.yaml (mscal run).
_IGNORED_NAMES = {".ds_store", "thumbs.db", "ready", "session.yaml"}


@dataclass
class CaptureFolder:
    """The captures of a folder tree (sorted by name), the captures quarantined, and the files
    that are not band files (skipped)."""

    captures: list[Capture]
    quarantined: list[dict[str, str]]
    skipped: list[dict[str, str]]


def is_capture_folder(folder: Path, camera: Camera) -> bool:
    """Whether ``folder`` (or a folder below it) holds band files of ``camera``."""
    pattern = capture_pattern(camera)
    return any(pattern.match(p.name) for p in Path(folder).rglob("*") if p.is_file())


def find_captures(folder: str | Path, camera: Camera, only: Sequence[str] = ()) -> CaptureFolder:
    """Every capture of ``camera`` in ``folder`` and the folders below it (an SD card's
    ``0000SET/000/``); with ``only``, just the captures of those names (one flight of a folder
    holding several, :mod:`pipeline.run.card`). Capture names are the file names without the band suffix; when two
    folders of the tree hold captures of the same name (a new set restarts the numbering),
    every capture below ``folder`` is named by its path, ``0000SET_000_IMG_0000``. Two
    captures with the same XMP CaptureId anywhere in the tree: the later one is a copy and
    quarantined."""
    folder = Path(folder)
    pattern = capture_pattern(camera)
    dirs: list[Path] = []
    skipped: list[dict[str, str]] = []
    files = [p for p in sorted(folder.rglob("*"))
             if not p.is_dir() and not any(part.startswith(".") for part in p.relative_to(folder).parts)]
    companions = companion_images(files, camera)  # the camera's own other images (DJI's RGB JPEGs)
    for p in files:
        if pattern.match(p.name):
            d = capture_folder_of(p, camera)  # a folder_per_band camera's session folder
            if d not in dirs:
                dirs.append(d)
        elif p in companions:
            skipped.append({"file": str(p.relative_to(folder)), "reason": companions[p]})
        elif p.name.lower() not in _IGNORED_NAMES and p.name not in (RUN_JSON,):
            skipped.append({"file": str(p.relative_to(folder)),
                            "reason": f"not a capture file of {camera.name} (names matching {pattern.pattern})"})
    found: list[tuple[Path, Capture]] = []
    quarantined: list[dict[str, str]] = []
    for d in sorted(dirs):
        caps, problems = group_captures(d, camera)
        found += [(d, c) for c in caps]
        quarantined += [{"file": str(Path(q["file"]).relative_to(folder)) if Path(q["file"]).is_absolute()
                         else q["file"], "reason": q["reason"]} for q in problems]
    names = [c.name for _, c in found]
    if len(set(names)) != len(names):
        found = [(d, dataclasses.replace(c, name="_".join((*d.relative_to(folder).parts, c.name)))) for d, c in found]
    owner: dict[str, str] = {}
    captures: list[Capture] = []
    for d, c in sorted(found, key=lambda dc: dc[1].name):
        if c.capture_id in owner:
            quarantined.append({"file": str(c.files[0].relative_to(folder)),
                                "reason": f"capture {c.name}: same XMP CaptureId as {owner[c.capture_id]} "
                                          "(a copy of that capture?)"})
            continue
        owner[c.capture_id] = c.name
        captures.append(c)
    if only:
        keep = set(only)
        missing = sorted(keep - {c.name for c in captures})
        if missing:
            raise InputError(f"capture(s) {', '.join(missing[:5])} of the flight are not in the folder", path=folder,
                             hint="the folder changed since the flight was planned: run again")
        captures = [c for c in captures if c.name in keep]
    captures = without_unreachable(captures)  # a position the flight could not have reached: left out
    return CaptureFolder(captures, sorted(quarantined, key=lambda q: q["file"]), skipped)


def inputs_listing(captures: Sequence[Capture]) -> str:
    """sha256 of the band files' names and sizes: run.json ``inputs_listing``, the quick check
    of :func:`unchanged_run` (a file of another name or size has other content)."""
    h = hashlib.sha256()
    for c in captures:
        for p in c.files:
            h.update(f"{c.name}/{p.name}:{p.stat().st_size};".encode())
    return h.hexdigest()


def capture_digest(capture: Capture) -> str:
    """Content hash of a capture: sha256 over its files in band order, the hash the pass
    computes as it reads them (:func:`pipeline.ingest.camera_meta.read_capture_pixels`)."""
    h = hashlib.sha256()
    for path in capture.files:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 22):
                h.update(chunk)
    return h.hexdigest()


def unchanged_run(out: Path, captures: Sequence[Capture], fingerprint: dict[str, Any]) -> dict[str, Any] | None:
    """The previous run's record if it made the outputs of exactly these captures' content
    and ``fingerprint`` (everything but the frames): by content, as for every apply
    (:func:`pipeline.apply.record.previous_run`). The listing of names and sizes short-cuts
    only to "changed": when it differs from the record's no file is read; when it is the same
    the files are hashed and their content decides (a copy with new times is up to date, a
    file rewritten with its size and time kept is not)."""
    try:
        recorded = run_value(json.loads((out / RUN_JSON).read_text()), "inputs_listing")
    except (OSError, ValueError, AttributeError):
        return None
    if recorded != inputs_listing(captures):
        return None
    return up_to_date(out, fingerprint, [capture_digest(c) for c in captures], ("reflectance.zarr", "raw.zarr"))


_UUID_HEX = re.compile(r"^[0-9A-Fa-f]{32}$")


def capture_tags(camera: Camera, capture: Capture) -> FrameTags:
    """Photogrammetry tags of a capture: its first band file's time, position, EXIF Make and
    Model and XMP RigName, the median exposure; ``Camera:CaptureUUID`` the source's own when
    it is one (32 hex digits: Parrot, DJI), else derived from its capture id (the same on
    every run, shared by its bands); a capture whose files carry their own id keeps it in the
    XMP property its maker names (:attr:`pipeline.ingest.cameras.registry.Maker.capture_id_output`:
    MicaSense's ``MicaSense:CaptureId``)."""
    m = capture.metas[0]
    cid = str(capture.capture_id)
    own = cid.replace("-", "")
    derived = str(uuid.uuid5(uuid.NAMESPACE_URL, f"mscal:{camera.name}:{cid}"))
    make = m.make or (camera.identify.make if camera.identify is not None else "unknown")
    out_tag = capture_id_output(m.radiometry)
    return FrameTags(
        time=m.time, lat=m.lat, lon=m.lon, alt_m=m.alt_m,
        capture_uuid=own if _UUID_HEX.match(own) else derived,
        exposure_ms=float(np.median([x.exposure_s * 1e3 for x in capture.metas])),
        camera_make=make, camera_model=m.model or camera.name, rig_name=m.rig_name or m.model or camera.name,
        maker_tags=((*out_tag, cid),) if out_tag is not None and cid != capture.name else (),
    )


def band_optics(capture: Capture, export: Sequence[int], reference: int | None = None) -> list[CameraOptics | None]:
    """The lens of each exported band, from ``capture``'s band files (the lens of a band does
    not change between captures), turned upright with the frames; with ``reference`` (bands
    warped onto that band's grid by a registration) every band gets the reference band's."""
    out: list[CameraOptics | None] = []
    for b in export:
        meta = capture.metas[b if reference is None else reference]
        try:
            optics = read_optics(meta.path)
        except FrameError:
            out.append(None)
            continue
        h, w = meta.shape
        out.append(optics.upright(meta.orientation, w, h))
    return out


def metadata_panels(captures: Sequence[Capture]) -> dict[str, str]:
    """Captures whose own metadata say they show a reflectance panel: a MicaSense
    ``ReflectArea``, or Pix4D's ``Camera:CalibrationPicture`` >= 1 (1 and 2: a radiometric
    calibration target)."""
    out = {}
    for c in captures:
        if any(m.reflect_area is not None for m in c.metas):
            out[c.name] = "XMP ReflectArea (the camera located a reflectance panel)"
            continue
        flag = c.metas[0].calibration_picture
        if flag is not None and flag >= 1:
            out[c.name] = f"XMP Camera:CalibrationPicture = {flag} (a radiometric calibration target)"
    return out


def capture_times(captures: Sequence[Capture]) -> np.ndarray:
    """datetime64[ns] of each capture (NaT: none)."""
    return np.array([np.datetime64(c.metas[0].time.rstrip("Z"), "ns") if c.metas[0].time else np.datetime64("NaT", "ns")
                     for c in captures])


def capture_time_zones(captures: Sequence[Capture]) -> dict[str, Any]:
    """run.json ``capture_times``: how many captures have a time in UTC (the file says its
    zone: DJI UTCAtExposure, EXIF OffsetTimeOriginal), a time as written (zone unknown) or
    none, and the first capture of each kind. A flight with both UTC and as-written times has
    them on two clocks (the QA report warns, ``mixed_time_zones``)."""
    kinds: dict[str, list[str]] = {"utc": [], "as_written": [], "missing": []}
    for c in captures:
        t = c.metas[0].time
        kinds["missing" if not t else "utc" if t.endswith("Z") else "as_written"].append(c.name)
    return {**{k: len(v) for k, v in kinds.items()}, "first": {k: v[0] for k, v in kinds.items() if v}}


def capture_coords(camera: Camera, captures: Sequence[Capture], irradiance_unit: str = "W m-2 nm-1") -> dict[str, Any]:
    def per_frame(get: Any) -> np.ndarray:
        return np.array([np.nan if get(c.metas[0]) is None else get(c.metas[0]) for c in captures], dtype=np.float64)

    cf = FRAME_COORD_ATTRS
    return {
        "frame": ("frame", np.array([c.name for c in captures], dtype=object), dict(cf["frame"])),
        "band": ("band", np.arange(camera.n_bands), dict(cf["band"])),
        "wavelength": ("band", np.array([m.wavelength_nm for m in captures[0].metas]), dict(CF_VARIABLES["wavelength"])),
        "band_name": ("band", np.array(camera.band_names, dtype=object)),
        "exposure_ms": ("frame", np.array([np.median([m.exposure_s * 1e3 for m in c.metas]) for c in captures]),
                        {**cf["exposure_ms"], "long_name": "median exposure over the capture's bands"}),
        "band_exposure_ms": (("frame", "band"), np.array([[m.exposure_s * 1e3 for m in c.metas] for c in captures]),
                             dict(FLIGHT_VARIABLES["band_exposure_ms"])),
        "gain": ("frame", per_frame(lambda m: m.gain), dict(cf["gain"])),
        "irradiance": (("frame", "band"),
                       np.array([[np.nan if m.irradiance is None else m.irradiance for m in c.metas] for c in captures]),
                       {"units": irradiance_unit,
                        "long_name": "downwelling light sensor (XMP Irradiance or the camera's sun sensor)"}),
        "time": ("frame", capture_times(captures), dict(cf["time"])),
        "lat": ("frame", per_frame(lambda m: m.lat), dict(cf["lat"])),
        "lon": ("frame", per_frame(lambda m: m.lon), dict(cf["lon"])),
        "alt_m": ("frame", per_frame(lambda m: m.alt_m), dict(cf["alt_m"])),
        "capture_id": ("frame", np.array([c.capture_id for c in captures], dtype=object)),
    }


@dataclass
class CaptureRun:
    """What a driver decides before the pass: the chain, and what the outputs record.

    ``scale(capture_name)``: per band factors of a capture (``Job.scale``) or None;
    ``extra_coords(captures)``: more per-frame coordinates of reflectance.zarr (the light of
    each capture); ``record(captures)``: keys of run.json beside the common ones."""

    chain: FieldChain | FactoryChain
    calibration: str  # run.json "calibration": a store's path or "factory"
    calibration_sha256: str | None
    attrs: dict[str, Any]
    reflectance_name: str
    tiff_dtype: str = "uint16"
    norm: tuple[str, float | int | None] = ("none", None)
    transforms: Path | None = None
    factory_alignment: bool = False  # bands on the camera's common plane by each file's own registration (DJI)
    radiance_unit: str = "W m-2 sr-1 nm-1"  # of the factory chain's radiance (the vendor's model)
    irradiance_unit: str = "W m-2 nm-1"  # of the captures' sun-sensor readings
    scale: Callable[[str], tuple[float, ...] | None] = lambda name: None
    extra_coords: Callable[[Sequence[Capture]], dict[str, Any]] = lambda captures: {}
    record: Callable[[Sequence[Capture]], dict[str, Any]] = lambda captures: {}
    panels: dict[str, str] = dataclasses.field(default_factory=dict)  # panel captures -> why: TIFFs in OUT/panels/
    reference_band: int | None = None  # the band a registration warps the others onto (their lens is its)
    refine: Refinement | None = None  # image registration on top of the files' own, per capture (coregistration)
    coreg_reference: int | None = None  # the band measured captures' residual shifts are against


class CaptureSource:
    """A folder of captures (one file per band, or one multi-channel file) with the chain of
    the run that ``make_run`` builds (a field calibration store's, :func:`field_captures`, or
    the factory's, :func:`pipeline.apply.factory.apply_factory`): a source of
    :func:`pipeline.apply.driver.drive`. ``fingerprint``: everything but the captures'
    content that the outputs depend on; ``make_run`` is called only when the outputs are not
    up to date (an up-to-date run reads no pixels)."""

    def __init__(self, folder: Path, camera: Camera, found: CaptureFolder, shape: tuple[int, int, int],
                 indices: Sequence[Index], export: Sequence[int], fingerprint: dict[str, Any],
                 make_run: Callable[[], CaptureRun], products: Products, execution: Execution,
                 calib: xr.Dataset | None = None) -> None:
        self.folder, self.camera, self.found, self.shape = folder, camera, found, shape
        self.indices, self.export, self.fingerprint, self.make_run = indices, export, fingerprint, make_run
        self.roles = {ix.name: index_roles(camera, ix) for ix in indices}
        self.products, self.execution, self.calib = products, execution, calib

    def up_to_date(self, out: Path) -> dict[str, Any] | None:
        return unchanged_run(out, self.found.captures, self.fingerprint)

    def prepare(self, out: Path) -> tuple[int, Path | None]:
        """The run (its light reference), the panel captures and the bands' alignment."""
        captures = self.found.captures
        run = self.make_run()
        self.panels = {**metadata_panels(captures), **run.panels}
        self.run, self.coreg = coregistered(self.camera, captures, run, self.panels)
        return len(captures), run.chain.calibration if isinstance(run.chain, FieldChain) else None

    def run_pass(self, out: Path, runner: Runner) -> Done:
        """The pass of the one executor over the captures; a capture found unusable in it is
        quarantined and the pass redone without it."""
        camera, export, run, coreg, panels = self.camera, self.export, self.run, self.coreg, self.panels
        captures = list(self.found.captures)
        listed = list(captures)  # every capture found: the fingerprint's frames (one quarantined in the pass too)
        quarantined = list(self.found.quarantined)
        while True:
            tmp_refl, tmp_raw, plan = _start(out, camera, captures, self.shape, self.indices, self.roles, export, run,
                                             self.products)
            jobs = [Job(f, c.name, capture_tags(camera, c), capture=c, scale=run.scale(c.name), panel=c.name in panels,
                        measure=c.name in coreg.measured) for f, c in enumerate(captures)]
            outcomes = runner.run(plan, jobs)
            bad = {o.name: o.quarantine for o in outcomes if o.quarantine is not None}
            if not bad:
                break
            shutil.rmtree(tmp_refl, ignore_errors=True)
            shutil.rmtree(tmp_raw, ignore_errors=True)
            for name, q in bad.items():
                remove_frame_tiffs(out, [name], camera, export)
                quarantined.append(q)
            captures = [c for c in captures if c.name not in bad]
            if not captures:
                raise FrameError("no usable capture in the folder (all quarantined)", path=self.folder,
                                 hint="; ".join(f"{q['file']}: {q['reason']}" for q in quarantined[:3]))
        frames = [o.name for o in outcomes]
        quarantined.sort(key=lambda q: q["file"])
        shas = {o.name: o.sha256 for o in outcomes if o.sha256 is not None}
        outputs = {"reflectance": "reflectance.zarr", "raw": "raw.zarr",
                   **({"photogrammetry": "photogrammetry/", "panels": "panels/", "ndvi": "ndvi/"}
                      if self.products.tiffs else {})}
        parts: dict[str, Any] = {
            **run.record(captures),
            "inputs_listing": inputs_listing(listed),
            "skipped": self.found.skipped,
            "skipped_bands": [{**s, "file": _relative(s["file"], self.folder)} for c in captures for s in c.skipped],
            "orientation": _orientation_record(captures[0]),
            "capture_times": capture_time_zones(captures),
            "panels": [{"capture": name, "reason": why} for name, why in sorted(panels.items()) if name in frames],
            **coreg.record(camera, {o.name: o.coregistration for o in outcomes if o.coregistration}),
        }
        if isinstance(run.chain, FactoryChain):
            parts["reflectance_missing"] = [m for o in outcomes for m in o.no_reflectance]
        thermal = [{"capture": o.name, **t} for o in outcomes for t in o.thermal]
        if thermal:
            parts["thermal"] = {"unit": "K", "formula": "the camera's own conversion of its thermal band (MicaSense "
                                                        "LWIR: K = DN / 100); never mixed into reflectance",
                                "files": thermal}
            outputs["thermal"] = "thermal/"
        return Done(
            outcomes=outcomes, stores=((tmp_raw, "raw.zarr"), (tmp_refl, "reflectance.zarr")), quarantined=quarantined,
            calibration=run.calibration, calibration_sha256=run.calibration_sha256,
            frames_sha256={o.name: str(o.sha256) for o in outcomes},
            fingerprint=content_fingerprint(self.fingerprint, [shas.get(c.name) or capture_digest(c) for c in listed]),
            outputs=outputs, products=self.products.record(self.indices), export=export,
            metadata_problems=[p.as_dict() for c in captures for p in c.problems], parts=parts,
            flagging=None if run.chain.flagging is None else checked(run.chain.flagging, plan))


def _relative(file: str, folder: Path) -> str:
    try:
        return str(Path(file).relative_to(folder))
    except ValueError:
        return file


def _orientation_record(capture: Capture) -> str:
    o = capture.metas[0].orientation
    return "as stored" if o in (0, 1) else f"EXIF Orientation {o}: outputs turned upright (raw.zarr too)"


def coregistered(camera: Camera, captures: Sequence[Capture], run: CaptureRun,
                 panels: dict[str, str]) -> tuple[CaptureRun, RunCoregistration]:
    """The run with the bands' alignment chosen on the pixels, and what the pass measures
    (:func:`pipeline.apply.coregistration.prepare`)."""
    coreg = prepare(camera, captures, run.factory_alignment, run.transforms is not None, run.reference_band, set(panels))
    choice = coreg.choice
    if choice is None or coreg.reference is None:
        return dataclasses.replace(run, coreg_reference=coreg.reference), coreg
    # each capture judged on its own pixels, the flight's choice for those without texture
    refine = Refinement(coreg.reference, tuple(camera.band_names), choice.factory_alignment, choice.refine,
                        choice.label or METADATA)
    if choice.label is None:
        return dataclasses.replace(run, refine=refine, coreg_reference=coreg.reference), coreg
    attrs = {**run.attrs, "co_registered": 1, "registration": choice.label,
             "comment": f"{choice.label}: per band a transform from band {camera.band_names[coreg.reference or 0]} "
                        "(run.json coregistration); NaN where a band does not cover"}
    return dataclasses.replace(run, refine=refine, attrs=attrs, coreg_reference=coreg.reference), coreg


def _start(out: Path, camera: Camera, captures: Sequence[Capture], shape: tuple[int, int, int], indices: Sequence[Index],
           roles: dict[str, dict[str, int]], export: Sequence[int], run: CaptureRun,
           products: Products) -> tuple[Path, Path, Plan]:
    """The pass's output stores under temporary names, and its plan."""
    coords = {**capture_coords(camera, captures, run.irradiance_unit), **run.extra_coords(captures)}
    factory = isinstance(run.chain, FactoryChain)
    rvars = product_variables(indices, run.reflectance_name,
                              radiance_unit=run.radiance_unit if factory and products.radiance else None,
                              quality=run.chain.flagging is not None)
    attrs = {"Conventions": "CF-1.10", "camera": camera.name, "mscal_version": mscal_core.__version__, **run.attrs}
    tmp_refl, tmp_raw = temporary_folder_name(out / "reflectance.zarr"), temporary_folder_name(out / "raw.zarr")
    refl_ds = frame_template(coords, shape, rvars, attrs)
    create_store(refl_ds, tmp_refl, OUTPUT_COMPRESSORS)
    raw_ds = frame_template(coords, shape, {
        "dn": (("frame", "band", "y", "x"), np.uint16, {"long_name": "stored DN of each band file", "units": "1"}),
        DN_MEDIAN: (("frame", "band"), np.float64, dict(DN_MEDIAN_ATTRS)),
    }, attrs)
    create_store(raw_ds, tmp_raw, [raw_codec()])
    for sub in ("photogrammetry", "panels", "ndvi") if products.tiffs else ():
        (out / sub).mkdir(exist_ok=True)
    first = captures[0].metas
    optics = band_optics(captures[0], export, run.reference_band if run.transforms is not None else None)
    plan = Plan(
        camera=camera, chain=run.chain, raw_dn=tmp_raw / "dn", cube_shape=shape, out_store=tmp_refl,
        raw_medians=tmp_raw / DN_MEDIAN,
        outputs=tuple(str(v) for v in refl_ds.data_vars), indices=tuple((ix, roles[ix.name]) for ix in indices),
        bands=tuple((b, BandTags(name=camera.bands[b].name, wavelength_nm=first[b].wavelength_nm,
                                 fwhm_nm=first[b].fwhm_nm, rig_camera_index=i, optics=optics[i]))
                    for i, b in enumerate(export)),
        tiff_dtype=run.tiff_dtype, out=out, norm=run.norm, transforms=run.transforms,
        factory_alignment=run.factory_alignment, refine=run.refine, coreg_reference=run.coreg_reference,
        tiffs=products.tiffs,
    )
    return tmp_refl, tmp_raw, plan


def field_captures(folder: Path, calib_path: Path, camera: Camera, options: ApplyOptions,
                   calib: xr.Dataset | None = None) -> CaptureSource:
    """``mscal apply FLIGHT --calibration CALIB.zarr`` for a folder of one-file-per-band
    captures, as a source of :func:`pipeline.apply.driver.drive`: Eq. 15 with the store's U,
    V and S per band file (its own exposure and gain), the light of each capture's time (the
    captures' sun-sensor levels, horizontal for a store that says so:
    :func:`pipeline.apply.light.frame_levels`), the store's band transforms, the
    normalisation of ``options``. ``calib``: the store at ``calib_path`` already opened
    (:func:`pipeline.storage.store.open_calibration` with ``need="apply"``), checked here
    against ``camera``; None: opened here."""
    if calib is None:
        calib = open_calibration(calib_path, camera, need="apply")
    else:
        check_camera(calib, camera, calib_path)
    if "band_name" in calib.coords and [str(n) for n in calib["band_name"].values] != list(camera.band_names):
        raise CalibrationStoreError(
            f"store bands {', '.join(map(str, calib['band_name'].values))} are not the bands of {camera.name} "
            f"({', '.join(camera.band_names)})", path=calib_path, hint="use a calibration of this camera")
    found = find_captures(folder, camera, options.captures)
    captures = found.captures
    if not captures:
        raise FrameError(f"no complete capture of {camera.name} (the store's camera) in the folder", path=folder,
                         hint="; ".join(f"{q['file']}: {q['reason']}" for q in found.quarantined[:3])
                         or "a capture is one band file per band, e.g. IMG_0000_1.tif ... IMG_0000_5.tif")
    shapes = {m.shape for c in captures for m in c.metas}
    v_shape = tuple(calib["vignetting"].shape[1:])
    if shapes != {v_shape}:
        raise InputError(f"calibration vignetting is {v_shape[1]}x{v_shape[0]} but band files are "
                         f"{', '.join(f'{w}x{h}' for h, w in sorted(shapes))}", path=folder,
                         hint="use a calibration of this camera")
    shape = (camera.n_bands, *v_shape)
    chash = calibration_hash(calib)
    export = export_band_indices(camera, options.export_bands)
    indices = indices_for(camera, options.products)
    align, band_shift, reference = pass_geometry(calib, camera, options)
    if align:
        check_transforms(calib, camera.n_bands, v_shape, calib_path)
    chain = FieldChain(calib_path, calibration_clip_dn(calib, camera), run_flagging(options.products, calib))
    names = [c.name for c in captures]
    illum = illumination_plan(calib, names, capture_times(captures), folder, options.illumination, captures=captures)
    scales = {} if illum is None else {n: tuple(float(v) for v in illum.scale[f]) for f, n in enumerate(names)}
    transforms = calib_path if align else None
    fingerprint = {**run_fingerprint([], chash, options, illum), "layout": "captures",
                   "metadata_reading": METADATA_READING, "coregistration": COREGISTRATION_CHECK}
    attrs = {"calibration_sha256": chash, "source": str(folder), "calibration": str(calib_path)}
    if align:
        attrs["aligned_to_band"] = reference

    def panel_reflectance(f: int) -> tuple[np.ndarray, None]:
        c = captures[f]
        job = Job(f, c.name, capture_tags(camera, c), capture=c, scale=scales.get(c.name))
        try:
            return capture_reflectance(camera, chain, job, transforms, band_shift), None
        except FrameError as exc:
            raise InputError(f"--panel capture {c.name} cannot be used: {exc.reason}", path=exc.path) from None

    def extra_coords(caps: Sequence[Capture]) -> dict[str, Any]:
        if illum is None:
            return {}
        rows = [names.index(c.name) for c in caps]
        return {"illumination_level": ("frame", illum.level[rows].astype(np.float64),
                                       {"long_name": "brightness level beta of the light at the capture's time"}),
                "illumination_scale": (("frame", "band"), illum.scale[rows].astype(np.float64),
                                       {"long_name": "factor on Eq. 15 reflectance: S / S(lambda, time)"})}

    def record(caps: Sequence[Capture]) -> dict[str, Any]:
        return {"illumination": illumination_record(illum, calib, [c.name for c in caps])}

    def make_run() -> CaptureRun:
        return CaptureRun(
            chain=chain, calibration=str(calib_path), calibration_sha256=chash, attrs=attrs,
            reflectance_name="reflectance (Eq. 15)", tiff_dtype=options.tiff_dtype,
            norm=normalisation(options, camera, names, panel_reflectance), transforms=transforms,
            scale=lambda name: scales.get(name), extra_coords=extra_coords, record=record,
            panels={options.panel.frame: "--panel names it"} if options.panel is not None else {},
            reference_band=camera.band_names.index(reference) if align and reference in camera.band_names else None,
        )

    return CaptureSource(folder, camera, found, shape, indices, export, fingerprint, make_run,
                         options.products, options.execution, calib)
