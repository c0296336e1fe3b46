"""``mscal apply``: Eq. 15 over a whole flight, all outputs in one pass over the frames.

1. discover the flight (bad frames quarantined with their reasons) and open ``OUT/raw.zarr``;
2. plan dask tasks of a few frames each (:func:`process_frames`): each frame's DN (from the file for a flight
   whose cube is still empty: read once, hashed, checked and written into raw.zarr; else from
   raw.zarr), Eq. 15 with the ``mscal_core`` kernel (U lookup, divide by t V S), optional
   normalisation, indices, Otsu mask, and every output of that frame: its whole chunk of each
   ``reflectance.zarr`` variable (no two tasks share a chunk), its photogrammetry TIFFs and
   its NDVI TIFF. Nothing is computed until the pass runs; each frame is read once;
3. run the pass on the caller's ``distributed`` client, or on local threads or worker
   processes (:class:`pipeline.apply.executor.Runner`); raw.zarr is committed every
   ``FRESH_BATCH`` frames as their outcomes come in (the workers go on meanwhile),
   reflectance.zarr is renamed into place;
4. write ``OUT/run.json`` last. Every output is written under a temporary name and renamed;
   a run that finds ``run.json`` matching its inputs, calibration and options does nothing.

Steps 1 and 2 are :class:`SnapshotFlight`'s, a source of the one apply driver
(:func:`pipeline.apply.driver.drive`), which runs the pass and does step 4 as for every camera.
"""
from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable, Sequence

import mscal_core
import numpy as np
import xarray as xr
from mscal_core.errors import FrameError, InputError
from mscal_core.quality import censor_dn
from mscal_core.reflectance import eq15_fast

from pipeline.apply.captures import field_captures
from pipeline.apply.driver import Done, drive
from pipeline.apply.execution import flight_size_hint, start_worker_server
from pipeline.apply.executor import (
    OUTPUT_COMPRESSORS,
    FieldChain,
    Job,
    Outcome,
    Plan,
    Runner,
    capture_uuid,
)
from pipeline.apply.light import IlluminationPlan, illumination_plan
from pipeline.apply.options import (
    ApplyOptions,
    ApplyResult,
    PanelPixels,
    PanelReflectance,
    calibration_clip_dn,
    calibration_hash,
    export_band_indices,
    index_roles,
    normalisation,
    pass_geometry,
)
from pipeline.apply.quality import Flagging, checked, run_flagging, sensor_flags, warp_bits
from pipeline.apply.record import illumination_record, remove_frame_tiffs, run_fingerprint, up_to_date
from pipeline.apply.stores import calibration_tables, geometry_step, quality_tables, read_frame_chunk
from pipeline.apply.template import create_store, frame_template, product_variables
from pipeline.calibrate.registration import check_transforms
from pipeline.ingest.catalog import Camera, Index, load_camera
from pipeline.ingest.medians import kept_medians
from pipeline.ingest.photo_tags import CameraOptics, optics_from_intrinsics
from pipeline.ingest.products import indices_for, radiance_refused
from pipeline.ingest.raw import (
    FRAME_COORDS,
    Cube,
    CubeWriter,
    frame_coords,
    frame_row,
    ingest_flight,
    open_cube,
    read_frame,
)
from pipeline.products.writers import BandTags, FrameTags
from pipeline.storage.atomic import temporary_folder_name
from pipeline.storage.store import FLIGHT_VARIABLES, FRAME_COORD_ATTRS, check_camera, open_calibration

log = logging.getLogger(__name__)
FRESH_BATCH = 64  # frames per commit of the single pass (a kill loses at most this much ingest)
READ_AHEAD = 4  # a frame's task starts reading the file this many frames on (prefetch_file)


# --------------------------------------------------------------------------- helpers


# --------------------------------------------------------------------------- outputs


def _frame_tags(coords: xr.Dataset, f: int, camera: Camera) -> FrameTags:
    """Photogrammetry tags of frame ``f`` (``capture_uuid`` from its sha256, empty if unknown)."""
    def opt(name: str) -> float | None:
        v = float(coords[name].values[f])
        return None if not np.isfinite(v) else v

    tval = coords["time"].values[f]
    time_iso = None if np.isnat(tval) else np.datetime_as_string(tval, unit="ms") + "Z"
    sha = str(coords["sha256"].values[f])
    make, model = catalog_make_model(camera)
    return FrameTags(
        time=time_iso, lat=opt("lat"), lon=opt("lon"), alt_m=opt("alt_m"),
        capture_uuid=capture_uuid(camera, sha) if sha else "",
        exposure_ms=float(coords["exposure_ms"].values[f]),
        camera_make=make, camera_model=model, rig_name=camera.name,
    )


def catalog_make_model(camera: Camera) -> tuple[str, str]:
    """EXIF Make and Model of a camera whose frames carry none: the catalog's ``exif``, else
    its ``identify`` make, else ``unknown``, and its catalog name."""
    if camera.exif is not None:
        return camera.exif.make, camera.exif.model
    return (camera.identify.make if camera.identify is not None else "unknown"), camera.name


def snapshot_optics(camera: Camera, calib: xr.Dataset, shape: tuple[int, int]) -> CameraOptics | None:
    """The lens of a snapshot mosaic camera's band grid for its TIFFs: the calibration's
    ``intrinsics`` (band-grid pixels; the band grid shares one lens) and the catalog's pixel
    pitch times the mosaic pattern; None when either is missing."""
    if "intrinsics" not in calib or camera.exif is None or camera.exif.pixel_um is None:
        return None
    rows, cols = camera.layout.pattern or (1, 1)
    pitch = (camera.exif.pixel_um * 1e-3 * cols, camera.exif.pixel_um * 1e-3 * rows)
    fx, fy, cx, cy, *dist = (float(v) for v in calib["intrinsics"].values[0])
    try:
        return optics_from_intrinsics(fx, fy, cx, cy, tuple(dist), pitch, width=int(shape[1]))
    except ValueError:
        return None



def output_template(coords: xr.Dataset, camera: Camera, shape: tuple[int, int, int], indices: Sequence[Index],
                    options: ApplyOptions, illum: IlluminationPlan | None = None) -> xr.Dataset:
    """``reflectance.zarr`` of a snapshot flight as a lazy dataset (coordinates, attributes,
    variables of zeros one chunk per frame: :func:`pipeline.apply.template.frame_template`);
    the apply pass writes its data frame by frame."""
    out_coords: dict[str, Any] = {
        "frame": coords["frame"].values.astype(object),
        "band": ("band", np.arange(shape[0]), dict(FRAME_COORD_ATTRS["band"])),
        "wavelength": ("band", camera.wavelengths, dict(FLIGHT_VARIABLES["wavelength"])),
        "band_name": ("band", np.array(camera.band_names, dtype=object)),
    }
    for c in ("exposure_ms", "gain", "time", "lat", "lon", "alt_m"):
        out_coords[c] = ("frame", coords[c].values, dict(coords[c].attrs))
    attrs: dict[str, Any] = {"Conventions": "CF-1.10", "camera": camera.name, "mscal_version": mscal_core.__version__}
    if illum is not None:
        out_coords.update(
            illumination_level=("frame", illum.level.astype(np.float64),
                                {"long_name": "brightness level beta of the light at the frame's time"}),
            illumination_scale=(("frame", "band"), illum.scale.astype(np.float64),
                                {"long_name": "factor on Eq. 15 reflectance: S / S(lambda, time)"}),
            irradiance=("frame", illum.irradiance.astype(np.float64),
                        {"long_name": "sun-sensor irradiance of the frame (NaN: none)"}),
        )
        attrs.update(illumination_mode=illum.mode, illumination_captures=list(illum.captures))
    variables = product_variables(indices, "reflectance (Eq. 15)", normalisation=options.normalise, quality=True)
    return frame_template(out_coords, shape, variables, attrs)


# --------------------------------------------------------------------------- apply


@dataclass
class _Pass:
    """One apply pass over the frames: the output store under its temporary name and the plan."""

    coords: xr.Dataset
    plan: Plan
    tmp_store: Path
    illum: IlluminationPlan | None = None

    def scale(self, f: int) -> tuple[float, ...] | None:
        """Frame ``f``'s illumination factors per band (None: the store's S)."""
        return None if self.illum is None else tuple(float(v) for v in self.illum.scale[f])


def _start_pass(out: Path, flight_dir: Path, coords: xr.Dataset, cube_shape: tuple[int, int, int], camera: Camera,
                calib_path: Path, raw_dn: Path, indices: Sequence[Index],
                roles: dict[str, dict[str, int]], export: Sequence[int], options: ApplyOptions, chash: str,
                sat: int, frame_dn: Callable[[int], np.ndarray], calib: xr.Dataset,
                geometry: tuple[bool, tuple[tuple[float, float], ...] | None, str | None] = (False, None, None)) -> _Pass:
    """The light of each frame, normalisation, the output store's layout (metadata and
    coordinates; data written per frame) under a temporary name, and the plan of the frames'
    tasks."""
    frames = [str(f) for f in coords["frame"].values]
    illum = illumination_plan(calib, frames, coords["time"].values, flight_dir, options.illumination)
    flagging = run_flagging(options.products, calib)
    panel_reflectance = _panel_from(frame_dn, _effective_exposure(coords), calib_path, sat, illum, frames, geometry,
                                    flagging)
    norm = normalisation(options, camera, frames, panel_reflectance)
    ds = output_template(coords, camera, cube_shape, indices, options, illum)
    ds.attrs.update({"calibration_sha256": chash, "source": str(flight_dir)})
    align, band_shift, reference = geometry
    if align:
        ds["reflectance"].attrs["aligned_to_band"] = reference
    if band_shift is not None:
        ds["reflectance"].attrs["band_positions"] = "resampled to the mosaic's centre position (--centre-bands)"
    tmp_store = temporary_folder_name(out / "reflectance.zarr")
    create_store(ds, tmp_store, OUTPUT_COMPRESSORS)
    optics = snapshot_optics(camera, calib, tuple(cube_shape[1:]))
    plan = Plan(
        camera=camera, chain=FieldChain(calib_path, sat, flagging), raw_dn=raw_dn, cube_shape=tuple(cube_shape),
        raw_medians=kept_medians(raw_dn.parent),
        out_store=tmp_store, outputs=tuple(str(v) for v in ds.data_vars), norm=norm,
        indices=tuple((ix, roles[ix.name]) for ix in indices),
        bands=tuple(
            (b, BandTags(name=camera.bands[b].name, wavelength_nm=camera.bands[b].wavelength_nm,
                         fwhm_nm=camera.bands[b].fwhm_nm, rig_camera_index=i, optics=optics))
            for i, b in enumerate(export)
        ),
        tiff_dtype=options.tiff_dtype, out=out, transforms=calib_path if align else None, band_shift=band_shift,
        tiffs=options.products.tiffs,
    )
    for sub in ("photogrammetry", "ndvi") if options.products.tiffs else ():
        (out / sub).mkdir(exist_ok=True)
    return _Pass(coords, plan, tmp_store, illum)


def _effective_exposure(coords: xr.Dataset) -> np.ndarray:
    return (coords["exposure_ms"] * coords["gain"]).values.astype(np.float64)


def _panel_from(plan_dn: Callable[[int], np.ndarray], t: np.ndarray, calib_path: Path, sat: int,
                illum: IlluminationPlan | None = None, names: Sequence[str] = (),
                geometry: tuple = (False, None, None), flagging: Flagging | None = None
                ) -> PanelReflectance:
    """Eq. 15 reflectance of frame ``f`` (with its light) on the pixel grid of the
    outputs (``geometry_step``), NaN where the run's quality mask flags a pixel unless kept;
    and, with a ``flagging``, the frame's quality mask on the same grid and the bounds of its
    censored pixels: Eq. 15 of the highest trusted DN under each reading
    (:func:`mscal_core.quality.censor_dn`), the least such a pixel's reflectance can be (a
    panel's median counts each above its own bound: :func:`pipeline.apply.options.normalisation`)."""
    def reflectance(f: int) -> PanelPixels:
        lut, inv_v = calibration_tables(str(calib_path), None if flagging is None else
                                        (sat, flagging.bound, flagging.keep_flagged))
        scale = None if illum is None else illum.scale[f][None]
        dn = plan_dn(f)
        refl = eq15_fast(dn[None], lut, inv_v, float(t[f]), sat, scale)[0]
        if flagging is None:
            q = censor_at = None
        else:
            q = sensor_flags(flagging, calib_path, sat, dn, refl)
            bound_dn = censor_dn(dn, quality_tables(str(calib_path), sat, flagging.bound)[0])
            censor_at = eq15_fast(bound_dn[None], lut, inv_v, float(t[f]), sat, scale)[0]
        align, band_shift, _ = geometry
        if align or band_shift is not None:
            def warp(stack: np.ndarray) -> np.ndarray:
                return geometry_step(calib_path, align, band_shift, str(names[f]), stack)
            refl = warp(refl)
            if q is not None:
                q, censor_at = warp_bits(q, warp), warp(censor_at)
        return PanelPixels(refl, q, censor_at)
    return reflectance


def _fresh_pass(cube: Cube, runner: Runner, start: Callable[..., _Pass], calib_path: Path, sat: int,
                batch: int) -> tuple[_Pass, list[Outcome]] | None:
    """Ingest and apply in one pass over the files, for a cube that has no frames yet.

    Frames are given indices in file-name order before they are read, assuming each can be
    used; every ``batch`` frames are committed to raw.zarr as their outcomes come in, while
    the workers go on with the frames after them (:meth:`Runner.stream`). A frame that cannot be used (or
    is a duplicate) would shift the frames after it: then the frames before it are committed
    and ``None`` is returned, and the caller goes the general way (ingest, then a pass over
    the cube), which gives the same outputs.
    """
    recs = list(cube.found.frames)
    coords = frame_coords(cube.camera, [frame_row(r, "") for r in recs])
    t = _effective_exposure(coords)

    def file_dn(f: int) -> np.ndarray:
        try:
            dn = read_frame(recs[f], cube.camera)[1]
        except FrameError as exc:
            raise InputError(f"--panel frame {recs[f].name} cannot be used: {exc.reason}", path=recs[f].path) from None
        assert dn is not None
        return dn

    ps = start(coords, file_dn)
    writer = CubeWriter(cube.path, cube.group, cube.committed, cube.shape, cube.camera, commit_every=len(recs) + 1,
                     pool=None, workers=1)  # type: ignore[arg-type]  (no chunk writes of its own)
    first = writer.reserve(len(recs))
    jobs = (Job(first + f, recs[f].name, _frame_tags(coords, f, cube.camera), float(t[f]), rec=recs[f],
                scale=ps.scale(f), ahead=recs[f + READ_AHEAD].path if f + READ_AHEAD < len(recs) else None)
            for f in range(len(recs)))
    seen: set[str] = set()
    outcomes: list[Outcome] = []
    results = runner.stream(ps.plan, jobs)
    try:
        for f, res in enumerate(results):
            if res.quarantine is not None or res.sha256 in seen:
                results.close()  # no task left writing: then the frames before this one are committed
                writer.commit()
                shutil.rmtree(ps.tmp_store, ignore_errors=True)
                return None
            assert res.sha256 is not None
            writer.register(recs[f], res.sha256)
            seen.add(res.sha256)
            outcomes.append(res)
            if len(outcomes) % batch == 0 and len(outcomes) < len(recs):
                writer.commit(room=len(recs) - len(outcomes))  # the workers go on meanwhile
    finally:
        results.close()
    writer.commit()
    shas = np.array([o.sha256 for o in outcomes], dtype=object)
    ps.coords = ps.coords.assign_coords(sha256=("frame", shas))
    return ps, outcomes


def _cube_pass(out: Path, runner: Runner, start: Callable[..., _Pass], calib_path: Path, sat: int, camera: Camera
               ) -> tuple[_Pass, list[Outcome]]:
    """A pass over the frames of raw.zarr (every frame already ingested)."""
    raw = xr.open_zarr(out / "raw.zarr")
    coords = xr.Dataset(coords={c: ("frame", raw[c].values, dict(raw[c].attrs)) for c in FRAME_COORDS})
    t = _effective_exposure(coords)
    raw_dn = out / "raw.zarr" / "dn"
    ps = start(coords, lambda f: read_frame_chunk(raw_dn, f))
    jobs = (Job(f, str(name), _frame_tags(coords, f, camera), float(t[f]), scale=ps.scale(f))
            for f, name in enumerate(coords["frame"].values))  # made a window at a time by the runner
    return ps, runner.run(ps.plan, jobs)


def apply_flight(
    flight_dir: str | Path, calibration: str | Path, out: str | Path, options: ApplyOptions = ApplyOptions()
) -> ApplyResult:
    """``mscal apply FLIGHT_DIR --calibration CALIB.zarr -o OUT``: the one driver
    (:func:`pipeline.apply.driver.drive`) over the flight's snapshot frames
    (:class:`SnapshotFlight`), or over its captures for a one-file-per-band camera
    (:func:`pipeline.apply.captures.field_captures`).

    A flight whose ``OUT/raw.zarr`` holds no frames yet is ingested and calibrated in one pass
    over its files (each read once); otherwise new frames are ingested first and the pass
    reads raw.zarr. Either way each frame's outputs are written by one task, and both ways
    give the same bytes. The tasks run on the caller's ``distributed`` client when one is
    active (``with distributed.Client(address):``), else on local worker processes.
    """
    t_start = time.perf_counter()
    flight_dir, out = Path(flight_dir), Path(out)
    if not flight_dir.is_dir():
        raise InputError("flight folder not found", path=flight_dir)
    if str(calibration) == "factory":
        raise InputError("--calibration factory needs factory radiometric metadata, which this camera's files do not carry",
                         hint="fit a calibration with 'mscal calibrate SESSION -o CALIB.zarr'")
    radiance_refused(options.products, f"the field calibration {calibration}")
    start_worker_server(options.execution, flight_size_hint(flight_dir))  # imports while the flight is read
    calib_path = Path(calibration)
    calib = open_calibration(calib_path, need="apply")
    camera = load_camera(str(calib.attrs.get("camera")))
    if camera.layout.kind == "file_per_band":  # one file per band: a capture is several files
        return drive(field_captures(flight_dir, calib_path, camera, options, calib), out, t_start)
    return drive(SnapshotFlight(flight_dir, calib_path, calib, camera, options), out, t_start)


class SnapshotFlight:
    """A flight of snapshot frames (one file a frame), ingested into ``OUT/raw.zarr`` and
    applied with a field calibration store: a source of :func:`pipeline.apply.driver.drive`."""

    def __init__(self, flight_dir: Path, calib_path: Path, calib: xr.Dataset, camera: Camera,
                 options: ApplyOptions) -> None:
        check_camera(calib, camera, calib_path)  # the store opened once (0.1 s a load)
        self.folder, self.calib_path, self.calib, self.camera, self.options = (
            flight_dir, calib_path, calib, camera, options)
        self.products, self.execution = options.products, options.execution
        self.chash = calibration_hash(calib)
        self.export = export_band_indices(camera, options.export_bands)
        self.indices = indices_for(camera, options.products)
        self.roles = {ix.name: index_roles(camera, ix) for ix in self.indices}
        self.sat = calibration_clip_dn(calib, camera)
        self.geometry = pass_geometry(calib, camera, options)
        self.cube: Cube | None = None
        self.fresh = False
        self.quarantined: list[dict[str, str]] = []

    def up_to_date(self, out: Path) -> dict[str, Any] | None:
        """A flight whose raw.zarr holds no frame yet is never up to date; otherwise the new
        frames are ingested and the frames' content hashes decide."""
        self.cube = cube = open_cube(self.folder, self.camera, out / "raw.zarr")
        self.fresh = cube.group is not None and cube.committed == 0 and len(cube.found.frames) > 0
        self.quarantined = list(cube.found.quarantined)
        if self.fresh:
            return None
        shas, illum = self._ingest(out, cube)
        previous = up_to_date(out, run_fingerprint([], self.chash, self.options, illum), shas)
        if previous is not None:
            previous["quarantined"] = self.quarantined
        return previous

    def _ingest(self, out: Path, cube: Cube | None) -> tuple[list[str], IlluminationPlan | None]:
        """Ingest what is new into raw.zarr: the frames' content hashes and light."""
        raw_path = out / "raw.zarr"
        ing = ingest_flight(self.folder, self.camera, raw_path, cube=cube)
        self.quarantined = list(ing.quarantined)
        raw = xr.open_zarr(raw_path)
        shas = [str(s) for s in raw["sha256"].values]
        if not shas:
            raise FrameError("no usable frames in the flight (all quarantined)", path=self.folder,
                             hint="; ".join(f"{q['file']}: {q['reason']}" for q in self.quarantined[:3]))
        illum = illumination_plan(self.calib, [str(f) for f in raw["frame"].values], raw["time"].values,
                                  self.folder, self.options.illumination)
        return shas, illum

    def prepare(self, out: Path) -> tuple[int, Path | None]:
        assert self.cube is not None
        return len(self.cube.found.frames), self.calib_path

    def _start(self, out: Path, coords: xr.Dataset, frame_dn: Callable[[int], np.ndarray]) -> _Pass:
        raw_path = out / "raw.zarr"
        shape = tuple(xr.open_zarr(raw_path)["dn"].shape[1:])
        v_shape = self.calib["vignetting"].shape[1:]
        if tuple(v_shape) != shape[1:]:
            raise InputError(
                f"calibration vignetting is {v_shape[1]}x{v_shape[0]} but frames are {shape[2]}x{shape[1]}",
                hint="use a calibration of this camera",
            )
        if self.geometry[0]:
            check_transforms(self.calib, shape[0], shape[1:], self.calib_path)
        return _start_pass(out, self.folder, coords, shape, self.camera, self.calib_path, raw_path / "dn",
                           self.indices, self.roles, self.export, self.options, self.chash, self.sat, frame_dn,
                           self.calib, self.geometry)

    def run_pass(self, out: Path, runner: Runner) -> Done:
        """The single pass over the files for a fresh flight (:func:`_fresh_pass`), else (or
        when a frame cannot be used in it) the general way: ingest, then a pass over raw.zarr."""
        cube = self.cube
        assert cube is not None
        done: tuple[_Pass, list[Outcome]] | None = None
        start = partial(self._start, out)
        if self.fresh:
            try:
                done = _fresh_pass(cube, runner, start, self.calib_path, self.sat, batch=FRESH_BATCH)
            finally:
                cube.release()
        single = done is not None
        if done is None:
            if self.fresh:  # a frame the single pass could not use: the general way
                self._ingest(out, None)
            remove_frame_tiffs(out, [Path(q["file"]).stem for q in self.quarantined], self.camera, self.export)
            done = _cube_pass(out, runner, start, self.calib_path, self.sat, self.camera)
        else:
            self.quarantined = sorted(self.quarantined, key=lambda q: q["file"])
        ps, outcomes = done
        frames = [o.name for o in outcomes]
        shas = [str(s) for s in ps.coords["sha256"].values]  # the pass's frames, in cube order
        names = [str(f) for f in ps.coords["frame"].values]
        flagging = ps.plan.chain.flagging
        return Done(
            outcomes=outcomes, stores=((ps.tmp_store, "reflectance.zarr"),), quarantined=self.quarantined,
            calibration=str(self.calib_path), calibration_sha256=self.chash, frames_sha256=dict(zip(names, shas)),
            fingerprint=run_fingerprint(shas, self.chash, self.options, ps.illum),
            outputs={"reflectance": "reflectance.zarr",
                     **({"photogrammetry": "photogrammetry/", "ndvi": "ndvi/"} if self.products.tiffs else {})},
            products=self.products.record(ps.plan.indices_made()), export=self.export,
            metadata_problems=[p for p in cube.found.metadata_problems if Path(str(p["file"])).stem in frames],
            parts={"illumination": illumination_record(ps.illum, self.calib, names), "snapshot": {"single_pass": single}},
            flagging=None if flagging is None else checked(flagging, ps.plan),
        )
