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
"""
from __future__ import annotations

import hashlib
import json
import logging
import platform
import re
import shutil
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import dask
import dask.array as da
import mscal_core
import numpy as np
import xarray as xr
from mscal_core.alignment import align_bands, mosaic_centre_offsets
from mscal_core.errors import FrameError, InputError
from mscal_core.reflectance import eq15_fast, eq15_tables

from pipeline.apply.execution import Execution, flight_size_hint, start_worker_server
from pipeline.apply.executor import (  # noqa: F401  (re-exported: the executor's pieces were here before)
    OUTPUT_COMPRESSORS,
    FieldChain,
    Job,
    Outcome,
    Plan,
    Runner,
    band_tiff_path,
    calibration_tables,
    capture_uuid,
    geometry_step,
    read_frame_chunk,
    write_frame,
)
from pipeline.apply.light import DEFAULT_MODE, IlluminationPlan, illumination_plan, varies_in_time
from pipeline.apply.products import remove_unchosen
from pipeline.calibrate.registration import check_transforms, frame_transforms
from pipeline.ingest.catalog import Camera, Index, load_camera, reflectance_option
from pipeline.ingest.medians import kept_medians
from pipeline.ingest.photo_tags import CameraOptics, optics_from_intrinsics
from pipeline.ingest.products import Products, indices_for, radiance_refused
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
from pipeline.storage.atomic import (
    install_folder,
    outputs_manifest,
    remove_temporaries,
    sync_file_system,
    temporary_folder_name,
    write_json_atomic,
)
from pipeline.storage.cache import code_digest
from pipeline.storage.chunks import frame_encoding, unwritten_frames
from pipeline.storage.store import FLIGHT_VARIABLES, FRAME_COORD_ATTRS, cf_annotate, check_camera, open_calibration

RUN_JSON = "run.json"
log = logging.getLogger(__name__)
MAX_EXPORT_BANDS = 8
FRESH_BATCH = 64  # frames per commit of the single pass (a kill loses at most this much ingest)
READ_AHEAD = 4  # a frame's task starts reading the file this many frames on (prefetch_file)


@dataclass(frozen=True)
class PanelSpec:
    """A region of known reflectance in one frame: ``FRAME:x0,y0,x1,y1`` (band-grid pixels)."""

    frame: str
    box: tuple[int, int, int, int]
    reflectance: Any  # catalog.ReflectanceSpec

    @staticmethod
    def parse(text: str, reflectance: str) -> "PanelSpec":
        m = re.fullmatch(r"\s*([^:]+):\s*(\d+),\s*(\d+),\s*(\d+),\s*(\d+)\s*", text or "")
        if not m:
            raise InputError(
                f"--panel {text!r} is not FRAME:x0,y0,x1,y1",
                hint="e.g. --panel IMG_0003:120,80,140,95 (band-grid pixel columns and rows, end exclusive)",
            )
        x0, y0, x1, y1 = (int(m[i]) for i in range(2, 6))
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"--panel {text!r}: empty box (need x1 > x0 and y1 > y0)")
        return PanelSpec(m[1], (x0, y0, x1, y1), reflectance_option(reflectance))


@dataclass(frozen=True)
class ApplyOptions:
    normalise: str = "relative"  # relative | band:<name or nm> | panel
    panel: PanelSpec | None = None
    tiff_dtype: str = "uint16"
    export_bands: tuple[str, ...] | None = None
    products: Products = Products()  # what is written beyond raw.zarr and reflectance (pipeline.ingest.products)
    strict: bool = False
    illumination: str = DEFAULT_MODE  # nearest | linear: light between reflector captures
    align: bool = True  # align bands with the store's band_transform, if it has one
    centre_bands: bool = False  # snapshot mosaics: resample every band to the mosaic's centre position
    execution: Execution = Execution()  # how the pass runs (not what it computes: not fingerprinted)
    captures: tuple[str, ...] = ()  # one-file-per-band cameras: only these captures of the folder (one flight)

    def fingerprint(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("strict")
        d.pop("execution")
        if not d["captures"]:  # the default: earlier runs stay up to date
            d.pop("captures")
        d.pop("illumination")  # in the fingerprint only when the light varies (see run_fingerprint)
        for key, default in (("align", True), ("centre_bands", False)):  # runs before band alignment stay up to date
            if d[key] == default:
                d.pop(key)
        d["products"] = self.products.fingerprint()
        if self.panel is not None:
            d["panel"] = {"frame": self.panel.frame, "box": list(self.panel.box), "reflectance": repr(self.panel.reflectance)}
        return d


@dataclass
class ApplyResult:
    """What one apply did: ``run`` is ``OUT/run.json``'s record. ``calibration``: the
    calibration store as apply read it (in memory), for the caller's summary to use instead of
    reading the store again; None for ``--calibration factory``."""

    out: Path
    run: dict[str, Any]
    up_to_date: bool = False
    quarantined: list[dict[str, str]] = field(default_factory=list)
    calibration: xr.Dataset | None = field(default=None, repr=False, compare=False)


# --------------------------------------------------------------------------- helpers


def calibration_hash(ds: xr.Dataset) -> str:
    """sha256 of the calibration's arrays (U, V, S) and camera: what Eq. 15 depends on; with
    light that varies in time also the captures' S, level, time and irradiance."""
    h = hashlib.sha256(str(ds.attrs.get("camera")).encode())
    names = ["inverse_response", "vignetting", "spectral_factor"]
    if varies_in_time(ds):
        names += ["capture_spectral_factor", "capture_level", "capture_time", "capture_irradiance"]
    names += [n for n in ("band_transform", "capture_transform") if n in ds]  # only stores that have them
    for name in names:
        arr = np.ascontiguousarray(ds[name].values)
        h.update(name.encode())
        h.update(str(arr.dtype).encode() + str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def export_band_indices(camera: Camera, names: Sequence[str] | None) -> list[int]:
    names = list(names) if names else list(camera.export_bands) or camera.band_names[:MAX_EXPORT_BANDS]
    unknown = [n for n in names if n not in camera.band_names]
    if unknown:
        raise InputError(
            f"--export-bands names unknown band(s) {', '.join(unknown)}",
            hint=f"bands of {camera.name}: {', '.join(camera.band_names)}",
        )
    return [camera.band_names.index(n) for n in names]


def _band_index(camera: Camera, text: str) -> int:
    if text in camera.band_names:
        return camera.band_names.index(text)
    try:
        return camera.band_for_wavelength(float(text))
    except ValueError:
        raise InputError(f"--normalise band:{text}: no such band name or wavelength",
                         hint=f"bands: {', '.join(camera.band_names)}") from None


def index_roles(camera: Camera, index: Index) -> dict[str, int]:
    missing = [r for r in index.inputs if r not in camera.index_bands]
    if missing:
        raise InputError(
            f"index {index.name} needs band role(s) {', '.join(missing)} that camera {camera.name} does not define",
            hint=f"add them under index_bands in {camera.source}",
        )
    return {r: camera.band_for_wavelength(camera.index_bands[r]) for r in index.inputs}


# --------------------------------------------------------------------------- the lazy graph


def saturation_dn(calib: xr.Dataset, camera: Camera) -> int:
    """DN from which pixels are saturated (NaN in reflectance): the calibration's lowest, else
    the camera's full scale."""
    return int(calib["saturation_dn"].values.min()) if "saturation_dn" in calib else camera.dn_max


def _eq15_block(dn: np.ndarray, t: np.ndarray, lut: np.ndarray, inv_v: np.ndarray, sat: int) -> np.ndarray:
    return eq15_fast(dn, lut, inv_v, t.reshape(-1), sat)


def _aligned_block(refl: np.ndarray, names: np.ndarray, calib: xr.Dataset, block_info: dict | None = None) -> np.ndarray:
    f0 = block_info[0]["array-location"][0][0] if block_info else 0
    out = np.empty_like(refl)
    for k in range(refl.shape[0]):
        H = frame_transforms(calib, str(names[f0 + k]))
        out[k] = refl[k] if H is None else align_bands(refl[k], H)
    return out


def lazy_reflectance(raw: xr.Dataset, calib: xr.Dataset, camera: Camera, *, align: bool = False) -> xr.DataArray:
    """Eq. 15, ``R = U(I) / (t V S)``, as a dask-backed DataArray (frame, band, y, x); with
    ``align`` and a calibration holding band transforms, each frame's bands warped onto the
    reference band as the apply pass does (:func:`geometry_step`)."""
    dn = raw["dn"].data
    t = (raw["exposure_ms"] * raw["gain"]).values.astype(np.float64)
    t_da = da.from_array(t.reshape(-1, 1, 1, 1), chunks=(dn.chunks[0], 1, 1, 1))
    U = calib["inverse_response"].values
    V = calib["vignetting"].values
    S = calib["spectral_factor"].values
    if V.shape[1:] != dn.shape[2:]:
        raise InputError(
            f"calibration vignetting is {V.shape[2]}x{V.shape[1]} but frames are {dn.shape[3]}x{dn.shape[2]}",
            hint="use a calibration of this camera",
        )
    sat = saturation_dn(calib, camera)
    lut, inv_v = eq15_tables(U, V, S)
    refl = da.map_blocks(_eq15_block, dn, t_da, lut=lut, inv_v=inv_v, sat=sat, dtype=np.float32)
    if align and "band_transform" in calib:
        refl = da.map_blocks(_aligned_block, refl, names=raw["frame"].values, calib=calib, dtype=np.float32)
    return xr.DataArray(refl, dims=("frame", "band", "y", "x"), coords=raw["dn"].coords, name="reflectance")


def normalisation(
    options: ApplyOptions, camera: Camera, frames: Sequence[str],
    panel_reflectance: Callable[[int], np.ndarray],
) -> tuple[str, float | int | None]:
    """How relative reflectance is scaled: ``("none", None)``, ``("band", b)`` (per frame,
    that band's median becomes 1) or ``("scalar", k)`` (one factor from a panel of known
    reflectance, for every frame: Eq. 15's R is relative up to one scalar).

    ``panel_reflectance(f)`` gives Eq. 15 reflectance (band, y, x) of frame ``f``."""
    mode = options.normalise
    if mode == "relative":
        return "none", None
    if mode.startswith("band:"):
        return "band", _band_index(camera, mode.split(":", 1)[1])
    if mode == "panel":
        p = options.panel
        if p is None:
            raise InputError("--normalise panel needs --panel FRAME:x0,y0,x1,y1 and --panel-reflectance")
        frames = list(frames)
        if p.frame not in frames:
            raise InputError(f"--panel frame {p.frame!r} is not in the flight", hint=f"frames: {', '.join(frames[:5])}, ...")
        x0, y0, x1, y1 = p.box
        region = panel_reflectance(frames.index(p.frame))[:, y0:y1, x0:x1]
        rho = p.reflectance.at(camera.wavelengths)
        med = np.nanmedian(region.reshape(region.shape[0], -1), axis=1) if region.size else np.array([np.nan])
        if not np.any(np.isfinite(med) & (med > 0)):
            raise InputError(f"--panel region of {p.frame} has no valid pixels (saturated or outside the frame)")
        return "scalar", float(np.nanmedian(rho / med))
    raise InputError(f"--normalise {mode!r}: use relative, band:<name or nm>, or panel")


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
    """``reflectance.zarr`` as a lazy dataset (coordinates, attributes, variables of zeros
    one chunk per frame); the apply pass writes its data frame by frame."""
    n = coords.sizes.get("frame", 0)
    out_coords = {
        "frame": coords["frame"].values.astype(object),
        "band": ("band", np.arange(shape[0]), dict(FRAME_COORD_ATTRS["band"])),
        "wavelength": ("band", camera.wavelengths, dict(FLIGHT_VARIABLES["wavelength"])),
        "band_name": ("band", np.array(camera.band_names, dtype=object)),
    }
    for c in ("exposure_ms", "gain", "time", "lat", "lon", "alt_m"):
        out_coords[c] = ("frame", coords[c].values, dict(coords[c].attrs))
    ds = xr.Dataset(coords=out_coords)
    cube = unwritten_frames((n, *shape), np.float32)
    ds["reflectance"] = (("frame", "band", "y", "x"), cube,
                         {"long_name": "reflectance (Eq. 15)", "units": "1", "normalisation": options.normalise})
    plane = unwritten_frames((n, *shape[1:]), np.float32)
    for ix in indices:
        ds[ix.name] = (("frame", "y", "x"), plane, {"long_name": ix.description, "expression": ix.expression,
                                                     "units": "1"})
    if any(ix.name == "ndvi" for ix in indices):
        ds["vegetation_mask"] = (("frame", "y", "x"), plane.astype(np.uint8),
                                 {"long_name": "vegetation (Otsu threshold of NDVI per frame)",
                                  "flag_values": [0, 1, 255], "flag_meanings": "other vegetation undefined"})
    ds.attrs.update({"Conventions": "CF-1.10", "camera": camera.name, "mscal_version": mscal_core.__version__})
    if illum is not None:
        ds = ds.assign_coords(
            illumination_level=("frame", illum.level.astype(np.float64),
                                {"long_name": "brightness level beta of the light at the frame's time"}),
            illumination_scale=(("frame", "band"), illum.scale.astype(np.float64),
                                {"long_name": "factor on Eq. 15 reflectance: S / S(lambda, time)"}),
            irradiance=("frame", illum.irradiance.astype(np.float64),
                        {"long_name": "sun-sensor irradiance of the frame (NaN: none)"}),
        )
        ds.attrs["illumination_mode"] = illum.mode
        ds.attrs["illumination_captures"] = list(illum.captures)
    return cf_annotate(ds, FLIGHT_VARIABLES)


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
    panel_reflectance = _panel_from(frame_dn, _effective_exposure(coords), calib_path, sat, illum, frames, geometry)
    norm = normalisation(options, camera, frames, panel_reflectance)
    ds = output_template(coords, camera, cube_shape, indices, options, illum)
    ds.attrs.update({"calibration_sha256": chash, "source": str(flight_dir)})
    align, band_shift, reference = geometry
    if align:
        ds["reflectance"].attrs["aligned_to_band"] = reference
    if band_shift is not None:
        ds["reflectance"].attrs["band_positions"] = "resampled to the mosaic's centre position (--centre-bands)"
    tmp_store = temporary_folder_name(out / "reflectance.zarr")
    encoding = {v: frame_encoding(ds[v].shape, OUTPUT_COMPRESSORS) for v in ds.data_vars}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        ds.to_zarr(tmp_store, mode="w", compute=False, consolidated=True, zarr_format=3, encoding=encoding)
    optics = snapshot_optics(camera, calib, tuple(cube_shape[1:]))
    plan = Plan(
        camera=camera, chain=FieldChain(calib_path, sat), raw_dn=raw_dn, cube_shape=tuple(cube_shape),
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
                geometry: tuple = (False, None, None)) -> Callable[[int], np.ndarray]:
    """Eq. 15 reflectance of frame ``f`` (with its light) on the pixel grid of the
    outputs (``geometry_step``)."""
    def reflectance(f: int) -> np.ndarray:
        lut, inv_v = calibration_tables(str(calib_path))
        scale = None if illum is None else illum.scale[f][None]
        refl = eq15_fast(plan_dn(f)[None], lut, inv_v, float(t[f]), sat, scale)[0]
        align, band_shift, _ = geometry
        if align or band_shift is not None:
            refl = geometry_step(calib_path, align, band_shift, str(names[f]), refl)
        return refl
    return reflectance


def remove_frame_tiffs(out: Path, names: Sequence[str], camera: Camera, export: Sequence[int]) -> None:
    """Remove the TIFFs of frames ``names`` (survey or panel; also under the names of runs
    before band names lost their spaces)."""
    for name in names:
        for b in export:
            band = camera.bands[b].name
            for panel in (False, True):
                band_tiff_path(out, name, band, panel).unlink(missing_ok=True)
            (out / "photogrammetry" / f"{name}_{band}.tif").unlink(missing_ok=True)
        (out / "ndvi" / f"{name}.tif").unlink(missing_ok=True)


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


def _illumination_record(ps: _Pass, calib: xr.Dataset, options: ApplyOptions) -> dict[str, Any]:
    """run.json's ``illumination``: the mode and each frame's factors when the light varies
    in time, else that the store's S was used for every frame."""
    if ps.illum is None:
        n = calib.sizes.get("capture", 1)
        return {"varies_in_time": False, "captures": int(n)}
    return {"varies_in_time": True, **ps.illum.summary([str(f) for f in ps.coords["frame"].values])}


def run_fingerprint(shas: Sequence[str], chash: str, options: ApplyOptions,
                 illum: IlluminationPlan | None = None) -> dict[str, Any]:
    fingerprint = {
        "frames_sha256": hashlib.sha256("".join(map(str, shas)).encode()).hexdigest(),
        "calibration_sha256": chash,
        "options": options.fingerprint(),
        "mscal_version": mscal_core.__version__,
        "code_sha256": code_digest(),  # every source of mscal_core, pipeline and the catalogs
    }
    if illum is not None:  # light that varies in time: the mode and the factors (readings) count
        fingerprint["illumination"] = {"mode": illum.mode, "scale_sha256": illum.digest()}
    return json.loads(json.dumps(fingerprint))  # as it reads back from run.json


def previous_run(out: Path, fingerprint: dict[str, Any], stores: Sequence[str] = ("reflectance.zarr",)
                ) -> dict[str, Any] | None:
    """The previous run's record if it made the outputs (``stores`` in ``out``) of exactly these
    inputs and they are still whole: ``run.json``, the completion marker written last
    (:func:`write_run_record`), notes the outputs' files and sizes; a store that is missing,
    empty, has a file less or a truncated chunk does not match and the flight is redone. A
    ``run.json`` without that note (an older run's) is not trusted either."""
    run_path = out / RUN_JSON
    if not (run_path.is_file() and all((out / s).is_dir() for s in stores)):
        return None
    try:
        previous = json.loads(run_path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(previous, dict) or previous.get("fingerprint") != fingerprint:
        return None
    manifest = previous.get(MANIFEST_KEY)
    if not manifest or manifest != outputs_manifest(out, (previous.get("outputs") or {}).values()):
        log.warning("%s: outputs changed since run.json was written (incomplete or damaged): redoing them", out)
        return None
    return previous


#: run.json's note of the outputs it completes (:func:`pipeline.storage.atomic.outputs_manifest`).
MANIFEST_KEY = "outputs_manifest"


def forget_run(out: Path) -> None:
    """Remove ``out/run.json`` before outputs are (re)written: until the new one is written
    last, nothing in ``out`` claims to be complete."""
    path = out / RUN_JSON
    if path.exists():
        path.unlink()
        sync_file_system(out)


def write_run_record(out: Path, record: dict[str, Any]) -> None:
    """Write ``out/run.json``, the completion marker of a flight, last: the outputs are flushed
    to the disk first (one ``syncfs``), their manifest goes into the record, and the record is
    written atomically and fsynced (file and folder). The manifest (a ``stat`` per file, 0.04 s
    of CPU for a 600-frame OUT) is taken while ``syncfs`` waits for the disk (0.1 s): it reads
    sizes, which flushing does not change; run.json is written only after both."""
    with ThreadPoolExecutor(1) as pool:
        synced = pool.submit(sync_file_system, out)
        record[MANIFEST_KEY] = outputs_manifest(out, (record.get("outputs") or {}).values())
        synced.result()  # its error, if any, before anything claims the outputs complete
    write_json_atomic(out / RUN_JSON, record)


def software_versions() -> dict[str, str]:
    versions = {"mscal": mscal_core.__version__, "python": platform.python_version(), "numpy": np.__version__,
                "dask": dask.__version__, "xarray": xr.__version__, "opencv": cv2.__version__}
    try:
        import zarr

        versions["zarr"] = zarr.__version__
    except ImportError:  # pragma: no cover
        pass
    return versions


def pass_geometry(calib: xr.Dataset, camera: Camera, options: ApplyOptions
              ) -> tuple[bool, tuple[tuple[float, float], ...] | None, str | None]:
    """``(align, band_shift, reference band)`` of the pass (``geometry_step``)."""
    align = bool(options.align and "band_transform" in calib)
    reference = (calib.attrs.get("registration") or {}).get("reference_band") if align else None
    band_shift = None
    if options.centre_bands:
        if camera.layout.kind != "mosaic" or camera.layout.pattern is None:
            raise InputError(f"--centre-bands is for snapshot mosaic cameras; {camera.name} is {camera.layout.kind}",
                             hint="multi-lens cameras are aligned with 'mscal register' transforms instead")
        band_shift = tuple((float(dx), float(dy)) for dx, dy in mosaic_centre_offsets(camera.layout.pattern))
    return align, band_shift, reference


def apply_flight(
    flight_dir: str | Path, calibration: str | Path, out: str | Path, options: ApplyOptions = ApplyOptions()
) -> ApplyResult:
    """``mscal apply FLIGHT_DIR --calibration CALIB.zarr -o OUT``.

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
        from pipeline.apply.captures import apply_field_captures

        return replace(apply_field_captures(flight_dir, calib_path, out, camera, options, t_start, calib),
                       calibration=calib)
    check_camera(calib, camera, calib_path)  # the store opened once (0.1 s a load)
    chash = calibration_hash(calib)
    export = export_band_indices(camera, options.export_bands)
    indices = indices_for(camera, options.products)
    roles = {ix.name: index_roles(camera, ix) for ix in indices}
    sat = saturation_dn(calib, camera)
    geometry = pass_geometry(calib, camera, options)
    out.mkdir(parents=True, exist_ok=True)
    remove_temporaries(out)
    raw_path = out / "raw.zarr"

    def start(coords: xr.Dataset, frame_dn: Callable[[int], np.ndarray]) -> _Pass:
        shape = tuple(xr.open_zarr(raw_path)["dn"].shape[1:])
        v_shape = calib["vignetting"].shape[1:]
        if tuple(v_shape) != shape[1:]:
            raise InputError(
                f"calibration vignetting is {v_shape[1]}x{v_shape[0]} but frames are {shape[2]}x{shape[1]}",
                hint="use a calibration of this camera",
            )
        if geometry[0]:
            check_transforms(calib, shape[0], shape[1:], calib_path)
        return _start_pass(out, flight_dir, coords, shape, camera, calib_path, raw_path / "dn", indices,
                           roles, export, options, chash, sat, frame_dn, calib, geometry)

    t0 = time.perf_counter()
    cube = open_cube(flight_dir, camera, raw_path)
    n_hint = len(cube.found.frames)
    fresh = cube.group is not None and cube.committed == 0 and n_hint > 0
    quarantined = list(cube.found.quarantined)
    done: tuple[_Pass, list[Outcome]] | None = None
    with Runner(n_hint, options.execution, calibration=calib_path) as runner:
        if fresh:
            forget_run(out)
            remove_unchosen(out, options.products)
            try:
                done = _fresh_pass(cube, runner, start, calib_path, sat, batch=FRESH_BATCH)
            finally:
                cube.release()
        single = done is not None
        if done is None:  # the general way: ingest what is new, then a pass over the cube
            ing = ingest_flight(flight_dir, camera, raw_path, cube=None if fresh else cube)
            quarantined = list(ing.quarantined)
            raw = xr.open_zarr(raw_path)
            shas = [str(s) for s in raw["sha256"].values]
            if not shas:
                raise FrameError("no usable frames in the flight (all quarantined)", path=flight_dir,
                                 hint="; ".join(f"{q['file']}: {q['reason']}" for q in quarantined[:3]))
            illum = illumination_plan(calib, [str(f) for f in raw["frame"].values], raw["time"].values,
                                      flight_dir, options.illumination)
            fingerprint = run_fingerprint(shas, chash, options, illum)
            previous = previous_run(out, fingerprint)
            if previous is not None:
                previous["quarantined"] = quarantined
                return ApplyResult(out, previous, up_to_date=True, quarantined=quarantined, calibration=calib)
            forget_run(out)
            remove_unchosen(out, options.products)
            remove_frame_tiffs(out, [Path(q["file"]).stem for q in quarantined], camera, export)
            done = _cube_pass(out, runner, start, calib_path, sat, camera)
        else:
            quarantined = sorted(quarantined, key=lambda q: q["file"])
    ps, outcomes = done
    t_pass = time.perf_counter() - t0
    install_folder(ps.tmp_store, out / "reflectance.zarr")
    run = _run_record(flight_dir, calib_path, chash, calib, camera, export, options, ps, outcomes, quarantined, runner,
                      single, {"ingest_and_apply": round(t_pass, 3), "total": round(time.perf_counter() - t_start, 3)},
                      cube.found.metadata_problems)
    write_run_record(out, run)  # last: a run.json names a finished pass
    return ApplyResult(out, run, up_to_date=False, quarantined=quarantined, calibration=calib)


def _run_record(flight_dir: Path, calib_path: Path, chash: str, calib: xr.Dataset, camera: Camera,
                export: Sequence[int], options: ApplyOptions, ps: "_Pass", outcomes: Sequence[Outcome],
                quarantined: list[dict[str, str]], runner: Runner, single: bool,
                timings: dict[str, float], problems: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:
    """The flight's ``run.json`` after a pass (SPEC.md, Outputs of apply); ``problems``: the
    frames' metadata problems (:class:`pipeline.ingest.discover.Discovery`)."""
    frames = [o.name for o in outcomes]
    sat_counts = [o.saturated for o in outcomes]
    shas = [str(s) for s in ps.coords["sha256"].values]  # the pass's frames, in cube order
    return {
        "flight": str(flight_dir),
        "calibration": str(calib_path),
        "calibration_sha256": chash,
        "frames_in": len(frames) + len(quarantined),
        "frames_out": len(frames),
        "frames": frames,
        "quarantined": quarantined,
        "metadata_problems": [p for p in problems if Path(str(p["file"])).stem in frames],
        "saturated_pixels": {"total": int(np.sum(sat_counts)), "per_frame": {n: int(c) for n, c in zip(frames, sat_counts)}},
        "outputs": {"reflectance": "reflectance.zarr",
                    **({"photogrammetry": "photogrammetry/", "ndvi": "ndvi/"} if options.products.tiffs else {})},
        "products": options.products.record(ps.plan.indices_made()),
        "export_bands": [camera.bands[b].name for b in export],
        "versions": software_versions(),
        "scheduler": runner.scheduler,
        "execution": runner.execution,
        "single_pass": single,
        "timings_s": timings,
        "illumination": _illumination_record(ps, calib, options),
        "fingerprint": run_fingerprint(shas, chash, options, ps.illum),
    }
