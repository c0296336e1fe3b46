"""``mscal apply``: Eq. 15 over a whole flight, lazily, all outputs in one pass.

1. ingest the flight folder into ``OUT/raw.zarr`` (incremental; bad frames quarantined);
2. build a dask graph over the datacube (one chunk = one frame): U lookup, divide by t V S
   (``mscal_core.reflectance.eq15``), optional normalisation, indices;
3. compute once: ``OUT/reflectance.zarr``, the per-frame photogrammetry TIFFs and NDVI TIFFs
   and the saturation counts come from the same chunks in a single ``dask.compute``;
4. write ``OUT/run.json`` last. Every output is written under a temporary name and renamed;
   a run that finds ``run.json`` matching its inputs, calibration and options does nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import shutil
import time
import uuid
import warnings
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence

import cv2
import dask
import dask.array as da
import numpy as np
import xarray as xr

import mscal_core
from mscal_core.errors import FrameError, InputError
from mscal_core.reflectance import eq15_fast, eq15_tables

from .catalog import Camera, Index, load_camera, load_index, parse_reflectance
from .ingest import ingest_flight
from .store import open_calibration
from .writers import TMP_MARK, BandTags, FrameTags, write_band_tiff, write_ndvi_tiff

RUN_JSON = "run.json"
MAX_EXPORT_BANDS = 8


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
        try:
            value: Any = float(reflectance)
        except ValueError:
            value = reflectance
        return PanelSpec(m[1], (x0, y0, x1, y1), parse_reflectance(value, "--panel-reflectance", "--panel-reflectance"))


@dataclass(frozen=True)
class ApplyOptions:
    normalise: str = "relative"  # relative | band:<name or nm> | panel
    panel: PanelSpec | None = None
    tiff_dtype: str = "uint16"
    export_bands: tuple[str, ...] | None = None
    indices: tuple[str, ...] = ("ndvi", "ndre")
    strict: bool = False

    def fingerprint(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("strict")
        if self.panel is not None:
            d["panel"] = {"frame": self.panel.frame, "box": list(self.panel.box), "reflectance": repr(self.panel.reflectance)}
        return d


@dataclass
class ApplyResult:
    out: Path
    run: dict[str, Any]
    up_to_date: bool = False
    quarantined: list[dict[str, str]] = field(default_factory=list)


# --------------------------------------------------------------------------- helpers


def calibration_hash(ds: xr.Dataset) -> str:
    """sha256 of the calibration's arrays (U, V, S) and camera: what Eq. 15 depends on."""
    h = hashlib.sha256(str(ds.attrs.get("camera")).encode())
    for name in ("inverse_response", "vignetting", "spectral_factor"):
        arr = np.ascontiguousarray(ds[name].values)
        h.update(name.encode())
        h.update(str(arr.dtype).encode() + str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _clean_temporaries(out: Path) -> None:
    """Remove what a killed run left under temporary names."""
    if not out.is_dir():
        return
    for p in list(out.rglob(f"*{TMP_MARK}*")):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        elif p.exists():
            p.unlink(missing_ok=True)


def _write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}{TMP_MARK}{uuid.uuid4().hex[:8]}")
    with tmp.open("w") as fh:
        json.dump(data, fh, indent=2, sort_keys=True)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


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


def _index_roles(camera: Camera, index: Index) -> dict[str, int]:
    missing = [r for r in index.inputs if r not in camera.index_bands]
    if missing:
        raise InputError(
            f"index {index.name} needs band role(s) {', '.join(missing)} that camera {camera.name} does not define",
            hint=f"add them under index_bands in {camera.source}",
        )
    return {r: camera.band_for_wavelength(camera.index_bands[r]) for r in index.inputs}


def capture_uuid(camera: Camera, sha256: str) -> str:
    """Deterministic CaptureUUID of a frame (the same on every re-run)."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"mscal:{camera.name}:{sha256}"))


def otsu_mask(ndvi: np.ndarray) -> np.ndarray:
    """The paper's vegetation segmentation: Otsu threshold of the NDVI of one frame (uint8 0/1,
    255 where NDVI is not defined)."""
    ok = np.isfinite(ndvi)
    out = np.full(ndvi.shape, 255, dtype=np.uint8)
    if ok.sum() < 2:
        return out
    scaled = np.clip((ndvi[ok] + 1.0) * 127.5, 0, 255).astype(np.uint8)
    thr, _ = cv2.threshold(scaled.reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    out[ok] = (scaled > thr).astype(np.uint8)
    return out


# --------------------------------------------------------------------------- the lazy graph


def _eq15_block(dn: np.ndarray, t: np.ndarray, lut: np.ndarray, inv_v: np.ndarray, sat: int) -> np.ndarray:
    return eq15_fast(dn, lut, inv_v, t.reshape(-1), sat)


def lazy_reflectance(raw: xr.Dataset, calib: xr.Dataset, camera: Camera) -> xr.DataArray:
    """Eq. 15, ``R = U(I) / (t V S)``, as a dask-backed DataArray (frame, band, y, x)."""
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
    sat = int(calib["saturation_dn"].values.min()) if "saturation_dn" in calib else camera.dn_max
    lut, inv_v = eq15_tables(U, V, S)
    refl = da.map_blocks(_eq15_block, dn, t_da, lut=lut, inv_v=inv_v, sat=sat, dtype=np.float32)
    return xr.DataArray(refl, dims=("frame", "band", "y", "x"), coords=raw["dn"].coords, name="reflectance")


def normalisation(
    calib: xr.Dataset, raw: xr.Dataset, camera: Camera, options: ApplyOptions
) -> tuple[str, float | int | None]:
    """How relative reflectance is scaled: ``("none", None)``, ``("band", b)`` (per frame,
    that band's median becomes 1) or ``("scalar", k)`` (one factor from a panel of known
    reflectance, for every frame: Eq. 15's R is relative up to one scalar)."""
    mode = options.normalise
    if mode == "relative":
        return "none", None
    if mode.startswith("band:"):
        return "band", _band_index(camera, mode.split(":", 1)[1])
    if mode == "panel":
        p = options.panel
        if p is None:
            raise InputError("--normalise panel needs --panel FRAME:x0,y0,x1,y1 and --panel-reflectance")
        frames = [str(f) for f in raw["frame"].values]
        if p.frame not in frames:
            raise InputError(f"--panel frame {p.frame!r} is not in the flight", hint=f"frames: {', '.join(frames[:5])}, ...")
        x0, y0, x1, y1 = p.box
        refl = lazy_reflectance(raw, calib, camera)
        region = refl.isel(frame=frames.index(p.frame), x=slice(x0, x1), y=slice(y0, y1)).values
        rho = p.reflectance.at(camera.wavelengths)
        med = np.nanmedian(region.reshape(region.shape[0], -1), axis=1) if region.size else np.array([np.nan])
        if not np.any(np.isfinite(med) & (med > 0)):
            raise InputError(f"--panel region of {p.frame} has no valid pixels (saturated or outside the frame)")
        return "scalar", float(np.nanmedian(rho / med))
    raise InputError(f"--normalise {mode!r}: use relative, band:<name or nm>, or panel")


# --------------------------------------------------------------------------- outputs


def _frame_tags(raw: xr.Dataset, f: int, camera: Camera) -> FrameTags:
    def opt(name: str) -> float | None:
        v = float(raw[name].values[f])
        return None if not np.isfinite(v) else v

    tval = raw["time"].values[f]
    time_iso = None if np.isnat(tval) else np.datetime_as_string(tval, unit="ms") + "Z"
    return FrameTags(
        time=time_iso, lat=opt("lat"), lon=opt("lon"), alt_m=opt("alt_m"),
        capture_uuid=capture_uuid(camera, str(raw["sha256"].values[f])),
        exposure_ms=float(raw["exposure_ms"].values[f]),
        camera_make="mscal", camera_model=camera.name,
    )


def scheduler_for(n_frames: int) -> tuple[str, int]:
    """Dask scheduler of the per-frame pass.

    The per-frame work holds the GIL most of the time (Zarr's I/O loop, TIFF encoding): more
    threads do not go faster, processes do. Worker processes cost ~1.5 s to start, so short
    flights stay in-process. ``MSCAL_APPLY_SCHEDULER`` (threads|processes) overrides.
    """
    cpus = os.cpu_count() or 1
    choice = os.environ.get("MSCAL_APPLY_SCHEDULER", "")
    if choice not in ("threads", "processes"):
        choice = "processes" if cpus > 1 and n_frames >= 8 * cpus else "threads"
    return choice, (cpus if choice == "processes" else 1)


def _compressor():  # noqa: ANN202
    import zarr.codecs

    # Fast and still ~2x on float32 reflectance: zarr's default zstd level 3 costs several
    # times more CPU than the whole Eq. 15 kernel.
    return zarr.codecs.BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")


_COMPRESSOR = _compressor()


@lru_cache(maxsize=8)
def _zarr_array(store: str, name: str, mode: str):  # noqa: ANN202
    import zarr

    return zarr.open_array(store, path=name, mode=mode)


@lru_cache(maxsize=2)
def _tables(calibration: str) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 15 tables of a calibration store, once per process."""
    ds = xr.open_zarr(calibration)
    return eq15_tables(ds["inverse_response"].values, ds["vignetting"].values, ds["spectral_factor"].values)


def output_template(raw: xr.Dataset, calib: xr.Dataset, camera: Camera, indices: Sequence[Index],
                    options: ApplyOptions) -> xr.Dataset:
    """``reflectance.zarr`` as a lazy dataset: coordinates, attributes and the lazy Eq. 15
    reflectance (``lazy_reflectance``) with its indices; the apply pass writes its data."""
    refl = lazy_reflectance(raw, calib, camera)
    coords = {
        "frame": raw["frame"].values.astype(object),
        "band": raw["band"].values,
        "wavelength": ("band", camera.wavelengths, {"units": "nm"}),
        "band_name": ("band", np.array(camera.band_names, dtype=object)),
    }
    for c in ("exposure_ms", "gain", "time", "lat", "lon", "alt_m"):
        coords[c] = ("frame", raw[c].values, dict(raw[c].attrs))
    ds = xr.Dataset(coords=coords)
    ds["reflectance"] = (("frame", "band", "y", "x"), refl.data,
                         {"long_name": "reflectance (Eq. 15)", "units": "1", "normalisation": options.normalise})
    plane = da.zeros((refl.shape[0], *refl.shape[2:]), chunks=(1, *refl.shape[2:]), dtype=np.float32)
    for ix in indices:
        ds[ix.name] = (("frame", "y", "x"), plane, {"long_name": ix.description, "expression": ix.expression})
    if any(ix.name == "ndvi" for ix in indices):
        ds["vegetation_mask"] = (("frame", "y", "x"), plane.astype(np.uint8),
                                 {"long_name": "vegetation (Otsu threshold of NDVI per frame)",
                                  "flag_values": [0, 1, 255], "flag_meanings": "other vegetation undefined"})
    ds.attrs.update({"Conventions": "CF-1.10", "camera": camera.name, "mscal_version": mscal_core.__version__})
    return ds


@dataclass(frozen=True)
class FramePlan:
    """Everything one frame's task needs: paths and small values, no arrays (it is sent to
    worker processes once per task)."""

    raw_store: Path
    out_store: Path
    calibration: Path
    outputs: tuple[str, ...]
    sat: int
    norm: tuple[str, float | int | None]
    indices: tuple[tuple[Index, dict[str, int]], ...]
    bands: tuple[tuple[int, BandTags], ...]
    tiff_dtype: str
    out: Path


def process_frame(plan: FramePlan, f: int, name: str, t: float, tags: FrameTags) -> int:
    """One frame, every output: Eq. 15, normalisation, indices, Otsu mask, its chunk of each
    reflectance.zarr variable (one whole chunk per variable: no two tasks share a chunk), its
    photogrammetry and NDVI TIFFs. Returns its saturated pixel count."""
    dn = np.asarray(_zarr_array(str(plan.raw_store), "dn", "r")[f])
    lut, inv_v = _tables(str(plan.calibration))
    refl = eq15_fast(dn[None], lut, inv_v, t, plan.sat)[0]
    outputs = {v: _zarr_array(str(plan.out_store), v, "r+") for v in plan.outputs}
    kind, value = plan.norm
    if kind == "scalar":
        refl *= np.float32(value)
    elif kind == "band":
        med = np.nanmedian(refl[int(value)])
        refl *= np.float32(1.0 / med) if np.isfinite(med) and med > 0 else np.float32(np.nan)
    outputs["reflectance"][f] = refl
    ndvi = None
    for ix, roles in plan.indices:
        val = ix.evaluate({role: refl[b] for role, b in roles.items()})
        outputs[ix.name][f] = val
        if ix.name == "ndvi":
            ndvi = val
    if ndvi is not None and "vegetation_mask" in outputs:
        outputs["vegetation_mask"][f] = otsu_mask(ndvi)
    for b, btags in plan.bands:
        write_band_tiff(plan.out / "photogrammetry" / f"{name}_{btags.name}.tif", refl[b], tags, btags,
                        dtype=plan.tiff_dtype)
    if ndvi is not None:
        write_ndvi_tiff(plan.out / "ndvi" / f"{name}.tif", ndvi, tags)
    return int(np.count_nonzero(dn >= plan.sat))


def apply_flight(
    flight_dir: str | Path, calibration: str | Path, out: str | Path, options: ApplyOptions = ApplyOptions()
) -> ApplyResult:
    """``mscal apply FLIGHT_DIR --calibration CALIB.zarr -o OUT``."""
    t_start = time.perf_counter()
    flight_dir, out = Path(flight_dir), Path(out)
    if not flight_dir.is_dir():
        raise InputError("flight folder not found", path=flight_dir)
    if str(calibration) == "factory":
        raise InputError("--calibration factory needs factory radiometric metadata, which this camera's files do not carry",
                         hint="fit a calibration with 'mscal calibrate SESSION -o CALIB.zarr'")
    calib_path = Path(calibration)
    probe = open_calibration(calib_path, need="apply")
    camera = load_camera(str(probe.attrs.get("camera")))
    calib = open_calibration(calib_path, camera, need="apply")
    chash = calibration_hash(calib)
    export = export_band_indices(camera, options.export_bands)
    indices = [load_index(n) for n in options.indices]
    roles = {ix.name: _index_roles(camera, ix) for ix in indices}
    out.mkdir(parents=True, exist_ok=True)
    _clean_temporaries(out)

    t0 = time.perf_counter()
    ing = ingest_flight(flight_dir, camera, out / "raw.zarr")
    t_ingest = time.perf_counter() - t0
    quarantined = list(ing.quarantined)
    raw = xr.open_zarr(out / "raw.zarr")
    # frame coordinates in memory once (they are small); dn stays lazy
    raw = raw.assign_coords({c: raw[c].load() for c in raw.coords if c != "frame"})
    frames = [str(f) for f in raw["frame"].values]
    fingerprint = {
        "frames_sha256": hashlib.sha256("".join(map(str, raw["sha256"].values)).encode()).hexdigest(),
        "calibration_sha256": chash,
        "options": options.fingerprint(),
        "mscal_version": mscal_core.__version__,
    }
    fingerprint = json.loads(json.dumps(fingerprint))  # as it reads back from run.json
    run_path = out / RUN_JSON
    if run_path.is_file() and (out / "reflectance.zarr").is_dir():
        try:
            previous = json.loads(run_path.read_text())
        except (OSError, ValueError):
            previous = {}
        if previous.get("fingerprint") == fingerprint:
            previous["quarantined"] = quarantined
            return ApplyResult(out, previous, up_to_date=True, quarantined=quarantined)
    if not frames:
        raise FrameError("no usable frames in the flight (all quarantined)", path=flight_dir,
                         hint="; ".join(f"{q['file']}: {q['reason']}" for q in quarantined[:3]))

    # ----- the output store's layout (metadata and coordinates only; data written per frame)
    sat = int(calib["saturation_dn"].values.min()) if "saturation_dn" in calib else camera.dn_max
    norm = normalisation(calib, raw, camera, options)
    ds = output_template(raw, calib, camera, indices, options)
    ds.attrs.update({"calibration_sha256": chash, "source": str(flight_dir)})
    tmp_store = out / f".reflectance.zarr{TMP_MARK}{uuid.uuid4().hex[:8]}"
    encoding = {v: {"chunks": (1, *ds[v].shape[1:]), "compressors": [_COMPRESSOR]} for v in ds.data_vars}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        ds.to_zarr(tmp_store, mode="w", compute=False, consolidated=True, zarr_format=3, encoding=encoding)

    plan = FramePlan(
        raw_store=out / "raw.zarr", out_store=tmp_store, calibration=calib_path,
        outputs=tuple(str(v) for v in ds.data_vars), sat=sat, norm=norm,
        indices=tuple((ix, roles[ix.name]) for ix in indices),
        bands=tuple(
            (b, BandTags(name=camera.bands[b].name, wavelength_nm=camera.bands[b].wavelength_nm,
                         fwhm_nm=camera.bands[b].fwhm_nm, rig_camera_index=i))
            for i, b in enumerate(export)
        ),
        tiff_dtype=options.tiff_dtype, out=out,
    )
    for sub in ("photogrammetry", "ndvi"):
        (out / sub).mkdir(exist_ok=True)
    t_eff = (raw["exposure_ms"] * raw["gain"]).values.astype(np.float64)
    tasks = [
        dask.delayed(process_frame, pure=False)(plan, f, name, float(t_eff[f]), _frame_tags(raw, f, camera))
        for f, name in enumerate(frames)
    ]
    t0 = time.perf_counter()
    scheduler, workers = scheduler_for(len(frames))
    sat_counts = dask.compute(*tasks, scheduler=scheduler, num_workers=workers)
    t_compute = time.perf_counter() - t0
    final = out / "reflectance.zarr"
    if final.exists():
        old = out / f".reflectance.zarr.old{TMP_MARK}{uuid.uuid4().hex[:8]}"
        os.replace(final, old)
        os.replace(tmp_store, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp_store, final)
    # TIFFs of frames no longer in the flight (none, unless files were removed) are left alone.

    versions = {"mscal": mscal_core.__version__, "python": platform.python_version(), "numpy": np.__version__,
                "dask": dask.__version__, "xarray": xr.__version__, "opencv": cv2.__version__}
    try:
        import zarr

        versions["zarr"] = zarr.__version__
    except ImportError:  # pragma: no cover
        pass
    run = {
        "flight": str(flight_dir),
        "calibration": str(calib_path),
        "calibration_sha256": chash,
        "frames_in": len(frames) + len(quarantined),
        "frames_out": len(frames),
        "frames": frames,
        "quarantined": quarantined,
        "saturated_pixels": {"total": int(np.sum(sat_counts)), "per_frame": {n: int(c) for n, c in zip(frames, sat_counts)}},
        "outputs": {"reflectance": "reflectance.zarr", "photogrammetry": "photogrammetry/", "ndvi": "ndvi/"},
        "export_bands": [camera.bands[b].name for b in export],
        "versions": versions,
        "timings_s": {"ingest": round(t_ingest, 3), "compute_and_write": round(t_compute, 3),
                      "total": round(time.perf_counter() - t_start, 3)},
        "fingerprint": fingerprint,
    }
    _write_json_atomic(run_path, run)
    return ApplyResult(out, run, up_to_date=False, quarantined=quarantined)
