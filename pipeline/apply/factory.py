"""``mscal apply CAPTURE_DIR --calibration factory -o OUT``: cameras that carry factory
radiometric metadata (MicaSense, Parrot Sequoia, DJI P4 Multispectral / Mavic 3M, Sentera
Double 4K; the camera is recognised by :func:`pipeline.ingest.identify.identify_camera`, each
vendor's model is in :mod:`pipeline.ingest.camera_meta` and :mod:`mscal_core.factory`).

A frame is one capture (all its band files, grouped by file name, one XMP CaptureId per capture; :func:`pipeline.ingest.camera_meta.group_captures`). Per band file:

- radiance ``L_b`` with the file's own factory model (black level, ``a1/gain/exposure`` with
  the row-gradient terms, radial vignetting polynomial; :func:`pipeline.ingest.camera_meta.factory_radiance`);
- reflectance ``R_b = k_b L_b`` with one factor per band from the *reference*:

  - ``panel``: a capture of a reflectance panel of known reflectance ``rho_b`` in the same
    folder. The light on the panel is split into colour and brightness (Eq. 11-14,
    ``L_b(x) = S_b B(x) rho_b`` over a grid on the panel, gauge ``median(B) = 1``) and
    ``k_b = 1 / S_b``: a partly shaded panel sets the factor of its median-lit part instead
    of its mean. Several panel captures: ``k_b`` is their mean (each is in run.json). The
    panel region: XMP ReflectArea, else a marker in the panel's plane, else detected, else a
    pixel polygon (the last two from ``panel`` of a session.yaml in the folder or up to two
    levels above it; :func:`pipeline.ingest.session.parse_panel`);
  - ``dls``: the capture's own downwelling light sensor, ``k_b = pi / E_b`` (XMP Irradiance,
    W m-2 nm-1, no tilt correction).

  ``auto`` (default) takes the panel when ``--panel-reflectance`` is given, else the DLS.

Outputs as for every apply (SPEC "Outputs of apply"): ``reflectance.zarr`` with
``reflectance`` and ``radiance`` (frame, band, y, x) float32 and the indices, ``raw.zarr``
(the stored DN, frame x band x y x x), photogrammetry and NDVI TIFFs, ``run.json``. Bands are
*not* co-registered here (each band keeps its own pixel grid): per-pixel indices mix
neighbouring ground points near edges; ``reflectance.zarr`` says so in its attributes. With
``--registration REG.zarr`` (a store from ``mscal register``, issue 9) the radiance of each
band is warped onto the reference band's grid before the factor (the capture's own transforms
if it was registered, else the session's; NaN where a band does not cover).

With ``--field-calibration CALIB.zarr`` components of a field calibration of the same camera
replace the factory's (``--field-components``: ``response`` = U of Eq. 5-7 on the factory's
scale, ``vignetting`` = V of Eq. 8-10; :func:`pipeline.ingest.camera_meta.factory_radiance`); run.json
``components`` records where each came from.

Every output is written under a temporary name and renamed; a run that finds ``run.json``
matching its inputs (file names, sizes and modification times) and options does nothing.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import shutil
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import xarray as xr

import mscal_core
from mscal_core.errors import CalibrationStoreError, FrameError, InputError
from mscal_core.illumination import fit_illumination
from mscal_core.panel import sample_quad

from pipeline.apply.flight import (
    geometry_step,
    OUTPUT_COMPRESSORS,
    RUN_JSON,
    ApplyResult,
    Runner,
    _clean_temporaries,
    _index_roles,
    _install,
    _remove_frame_tiffs,
    _up_to_date,
    _versions,
    _write_json_atomic,
    export_band_indices,
    otsu_mask,
    write_frame,
)
from pipeline.ingest.camera_meta import (Capture, FieldParts, factory_radiance, group_captures, read_capture_pixels,
                                         reflectance_factor, sun_sensor_absolute, upright_meta)
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.catalog import Camera, Index, load_camera, load_index, reflectance_option
from pipeline.storage.chunks import FLAT_CHUNK_KEYS
from pipeline.ingest.discover import quarantine_entry
from pipeline.ingest.raw import raw_codec
from pipeline.apply.panel import PanelBand, panel_factors
from pipeline.ingest.session import PanelConfig, panel_config_near
from pipeline.products.writers import TMP_MARK, BandTags, FrameTags, write_band_tiff, write_ndvi_tiff

FACTORY = "factory"
REFERENCES = ("auto", "panel", "dls")  # + "none" (radiance only) when auto finds no usable sun sensor
PANEL_SEARCH = 3  # captures at each end of the folder searched for a panel when none is named
PANEL_GRID = 32  # cells per side of the panel grid for the S/B split (Eq. 11-14)
FIELD_COMPONENTS = ("response", "vignetting")  # store variables: inverse_response, vignetting


@dataclass(frozen=True)
class FactoryOptions:
    """Options of a factory-calibrated apply (see the module docstring)."""

    reference: str = "auto"  # auto | panel | dls
    panel_captures: tuple[str, ...] = ()  # capture names (e.g. IMG_0000); () = search the folder's ends
    panel_reflectance: str | None = None  # a number or a reflectance target name
    tiff_dtype: str = "uint16"
    export_bands: tuple[str, ...] | None = None
    indices: tuple[str, ...] = ("ndvi", "ndre")
    strict: bool = False
    registration: str | None = None  # a store from 'mscal register': bands aligned to its reference (issue 9)
    field_calibration: str | None = None  # a store from 'mscal calibrate' / 'mscal fit' of this camera
    field_components: tuple[str, ...] = ()  # of FIELD_COMPONENTS taken from it; () = all it holds
    camera: str | None = None  # --camera NAME: the catalog camera, instead of recognising it from the files

    def __post_init__(self) -> None:
        if self.reference not in REFERENCES:
            raise InputError(f"reference {self.reference!r} is not one of {', '.join(REFERENCES)}")
        unknown = [c for c in self.field_components if c not in FIELD_COMPONENTS]
        if unknown:
            raise InputError(f"--field-components {', '.join(unknown)}: not one of {', '.join(FIELD_COMPONENTS)}",
                             hint="e.g. --field-components vignetting (factory response, field vignetting)")
        if self.field_components and self.field_calibration is None:
            raise InputError("--field-components needs --field-calibration CALIB.zarr (the store to take them from)")

    def fingerprint(self) -> dict[str, Any]:
        d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items() if k != "strict"}
        for key in ("registration", "field_calibration"):  # runs before issues 9 / 6-components stay up to date
            if d[key] is None:
                d.pop(key)
        if not d["field_components"]:
            d.pop("field_components")
        if d["camera"] is None:
            d.pop("camera")
        return d


# --------------------------------------------------------------------------- camera and captures


def _stat_fingerprint(captures: Sequence[Capture]) -> str:
    h = hashlib.sha256()
    for c in captures:
        for p in c.files:
            st = p.stat()
            h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()


# --------------------------------------------------------------------------- reference


@dataclass(frozen=True)
class PanelReference:
    """Per-band factors from one panel capture: ``k_b = 1/S_b`` (Eq. 11-14 split) beside the
    plain ``rho_b / mean L_b`` and the DLS's ``pi / E_b`` of the same capture."""

    capture: str
    factor_split: tuple[float, ...]
    factor_mean: tuple[float, ...]
    factor_dls: tuple[float | None, ...]
    brightness_p10_p90: tuple[float, float]
    split_residual_rms: float
    region_source: tuple[str, ...]


def panel_reference(capture: Capture, dns: Sequence[np.ndarray], rho: Sequence[float],
                    parts: Sequence[FieldParts | None] | None = None, config: PanelConfig | None = None,
                    channels: dict[Path, np.ndarray] | None = None) -> PanelReference:
    """Factors of one panel capture (FrameError naming the file if no panel is found in a band);
    ``parts``: field components per band in place of the factory's; ``config``: session.yaml's
    ``panel`` (marker, polygon); ``channels``: whole images of multi-channel files (Sentera)."""
    parts = list(parts) if parts is not None else [None] * len(capture.metas)
    chans = [(channels or {}).get(m.path) for m in capture.metas]
    bands: list[PanelBand] = panel_factors(capture.metas, dns, rho, parts=parts, config=config, channels=chans)
    rows = []
    for meta, dn, band, part, ch in zip(capture.metas, dns, bands, parts, chans):
        rad = factory_radiance(meta, dn, part, ch)
        if len(band.region.corners) == 4:
            rows.append(sample_quad(rad, band.region.corners, PANEL_GRID).ravel())
    if len(rows) == len(bands):
        fit = fit_illumination(np.array(rows), np.array(rho, dtype=np.float64))
        split = tuple(float(1.0 / s) for s in fit.spectral_factor)
        b = fit.brightness[np.isfinite(fit.brightness)]
        spread = (float(np.percentile(b, 10)), float(np.percentile(b, 90)))
        resid = float(fit.residual_rms)
    else:  # a polygon from the session that is not a quadrilateral: the mean is all there is
        split = tuple(b.factor for b in bands)
        spread, resid = (float("nan"), float("nan")), float("nan")
    dls = tuple(
        reflectance_factor(m) for m in capture.metas
    )
    return PanelReference(
        capture=capture.name, factor_split=split, factor_mean=tuple(b.factor for b in bands), factor_dls=dls,
        brightness_p10_p90=spread, split_residual_rms=resid, region_source=tuple(b.region.source for b in bands),
    )


def _find_panels(captures: Sequence[Capture], named: Sequence[str], rho: Sequence[float], folder: Path,
                 parts: Sequence[FieldParts | None] | None = None, config: PanelConfig | None = None
                 ) -> list[PanelReference]:
    by_name = {c.name: c for c in captures}
    if named:
        unknown = [n for n in named if n not in by_name]
        if unknown:
            raise InputError(f"--panel names capture(s) {', '.join(unknown)} that are not in the folder", path=folder,
                             hint=f"captures: {', '.join(list(by_name)[:8])}{' ...' if len(by_name) > 8 else ''}")
        refs = []
        for n in named:
            try:
                _, dns, stacks = read_capture_pixels(by_name[n])
                refs.append(panel_reference(by_name[n], dns, rho, parts, config, stacks))
            except FrameError as exc:
                raise InputError(f"panel capture {n}: {exc.reason}", path=exc.path, hint=exc.hint) from None
        return refs
    ends = list(captures[:PANEL_SEARCH]) + [c for c in captures[-PANEL_SEARCH:] if c not in captures[:PANEL_SEARCH]]
    refs = []
    for c in ends:
        try:
            _, dns, stacks = read_capture_pixels(c)
            refs.append(panel_reference(c, dns, rho, parts, config, stacks))
        except FrameError:
            continue
    if not refs:
        raise InputError(
            f"no reflectance panel found in the first and last {PANEL_SEARCH} captures", path=folder,
            hint="name the panel capture with --panel IMG_XXXX, or use --reference dls",
        )
    return refs


# --------------------------------------------------------------------------- the pass


@dataclass(frozen=True)
class CapturePlan:
    camera: Camera
    raw_store: Path
    out_store: Path
    out: Path
    shape: tuple[int, int, int]
    reference: str  # panel | dls
    panel_factor: tuple[float, ...] | None
    sat: int
    indices: tuple[tuple[Index, dict[str, int]], ...]
    bands: tuple[tuple[int, BandTags], ...]
    tiff_dtype: str
    outputs: tuple[str, ...]
    registration: Path | None = None  # band transforms (issue 9): radiance and reflectance aligned
    relative_scale: float = 1.0  # one constant for every band of a relative sun-sensor route (see relative_scale)
    field: tuple[str, tuple[str, ...]] | None = None  # (store, components) replacing factory components


@dataclass(frozen=True)
class CaptureJob:
    index: int
    capture: Capture
    tags: FrameTags


@dataclass(frozen=True)
class CaptureOutcome:
    name: str
    sha256: str | None
    saturated: int
    quarantine: dict[str, str] | None = None
    no_reflectance: tuple[dict[str, str], ...] = ()  # bands written as radiance only, and why


def capture_factors(plan: CapturePlan, capture: Capture) -> np.ndarray:
    """``k_b`` of one capture: the panel's, or ``pi / E_b`` of its own DLS readings."""
    if plan.reference == "panel":
        assert plan.panel_factor is not None
        return np.asarray(plan.panel_factor, dtype=np.float64)
    if plan.reference == "none":
        return np.full(len(capture.metas), np.nan)
    k = []
    for meta in capture.metas:
        kb = reflectance_factor(meta)
        k.append(np.nan if kb is None else kb)  # radiance only for that band (see missing_reflectance)
    return np.asarray(k) * plan.relative_scale


RELATIVE_LEVEL = 0.5  # a relative sun-sensor route puts the first capture's brightest band median here


def relative_scale(captures: Sequence[Capture], reference: str) -> float:
    """The constant of a *relative* sun-sensor route (DJI, Sequoia: reflectance known up to one
    factor shared by the bands): chosen so that the brightest band's median over the first
    capture is :data:`RELATIVE_LEVEL`, which keeps the values in the range of the uint16
    photogrammetry TIFFs (0..2). 1 for absolute routes. Indices do not depend on it; values of
    two runs are comparable only through a panel."""
    if reference != "dls" or not captures or sun_sensor_absolute(captures[0].metas[0]):
        return 1.0
    cap = captures[0]
    try:
        _, dns, stacks = read_capture_pixels(cap)
    except FrameError:
        return 1.0
    medians = []
    for meta, dn in zip(cap.metas, dns):
        k = reflectance_factor(meta)
        if k is None:
            continue
        rad = factory_radiance(meta, dn, None, stacks.get(meta.path))
        rad = rad[np.asarray(dn) < (1 << 16) - 1]
        if rad.size and np.isfinite(rad).any():
            medians.append(float(np.nanmedian(rad)) * k)
    best = max(medians, default=0.0)
    return RELATIVE_LEVEL / best if best > 0 and math.isfinite(best) else 1.0


def missing_reflectance(plan: CapturePlan, capture: Capture) -> tuple[dict[str, str], ...]:
    """The bands of a capture whose sun-sensor factor is missing: their radiance is written,
    their reflectance is NaN; the capture is not quarantined (it has radiance)."""
    if plan.reference != "dls":
        return ()
    out = []
    for meta in capture.metas:
        if reflectance_factor(meta) is None:
            why = [p.message() for p in meta.problems if p.feature == "sun_sensor"]
            out.append({"capture": capture.name, "file": meta.path.name, "band": meta.band_name,
                        "reason": why[0] if why else f"no sun sensor reading (irradiance = {meta.irradiance!r})"})
    return tuple(out)


def process_capture(plan: CapturePlan, job: CaptureJob) -> CaptureOutcome:
    """One capture, every output: its raw.zarr chunk, radiance, reflectance, indices, mask,
    photogrammetry and NDVI TIFFs (one whole chunk per variable: no two tasks share a chunk)."""
    cap = job.capture
    try:
        sha, dns, stacks = read_capture_pixels(cap)
        if any(dn.shape != plan.shape[1:] for dn in dns):
            raise FrameError(f"band images {[d.shape for d in dns]} are not all {plan.shape[1:]}", path=cap.files[0])
        k = capture_factors(plan, cap)
        parts = field_parts(plan.field[0], plan.field[1], plan.camera.name) if plan.field else [None] * len(dns)
        rad = np.empty(plan.shape, np.float32)
        for b, (meta, dn) in enumerate(zip(cap.metas, dns)):
            rad[b] = factory_radiance(meta, dn, parts[b], stacks.get(meta.path))
    except FrameError as exc:
        return CaptureOutcome(cap.name, None, 0, quarantine_entry(Path(exc.path or cap.files[0]).name, exc))
    raw = np.stack(dns)
    saturated = raw >= plan.sat
    rad[saturated] = np.nan
    if plan.registration is not None:  # each band onto the reference band's grid (NaN where uncovered)
        rad = geometry_step(plan.registration, True, None, cap.name, rad)  # transforms of the stored frames
    try:  # then as meant to be seen (EXIF Orientation; Sequoia stores its frames rotated 180 degrees)
        rad, raw = upright_meta(cap.metas[0], rad), upright_meta(cap.metas[0], raw)
    except FrameError as exc:
        return CaptureOutcome(cap.name, None, 0, quarantine_entry(Path(exc.path or cap.files[0]).name, exc))
    rad, raw = np.ascontiguousarray(rad), np.ascontiguousarray(raw)
    saturated = raw >= plan.sat
    refl = rad * k.astype(np.float32)[:, None, None]
    write_frame(plan.raw_store / "dn", job.index, raw)
    write_frame(plan.out_store / "radiance", job.index, rad)
    write_frame(plan.out_store / "reflectance", job.index, refl)
    ndvi = None
    for ix, roles in plan.indices:
        val = ix.evaluate({role: refl[b] for role, b in roles.items()})
        write_frame(plan.out_store / ix.name, job.index, val)
        if ix.name == "ndvi":
            ndvi = val
    if ndvi is not None and "vegetation_mask" in plan.outputs:
        write_frame(plan.out_store / "vegetation_mask", job.index, otsu_mask(ndvi))
    for b, btags in plan.bands:
        write_band_tiff(plan.out / "photogrammetry" / f"{cap.name}_{btags.name}.tif", refl[b], job.tags, btags,
                        dtype=plan.tiff_dtype)
    if ndvi is not None:
        write_ndvi_tiff(plan.out / "ndvi" / f"{cap.name}.tif", ndvi, job.tags)
    return CaptureOutcome(cap.name, sha, int(np.count_nonzero(saturated)), no_reflectance=missing_reflectance(plan, cap))


def _coords(camera: Camera, captures: Sequence[Capture]) -> dict[str, Any]:
    def per_frame(get: Any) -> np.ndarray:
        return np.array([np.nan if get(c.metas[0]) is None else get(c.metas[0]) for c in captures], dtype=np.float64)

    times = [c.metas[0].time for c in captures]
    return {
        "frame": np.array([c.name for c in captures], dtype=object),
        "band": np.arange(camera.n_bands),
        "wavelength": ("band", np.array([m.wavelength_nm for m in captures[0].metas]), {"units": "nm"}),
        "band_name": ("band", np.array(camera.band_names, dtype=object)),
        "exposure_ms": ("frame", np.array([np.median([m.exposure_s * 1e3 for m in c.metas]) for c in captures]),
                        {"units": "ms", "long_name": "median exposure over the capture's bands"}),
        "band_exposure_ms": (("frame", "band"), np.array([[m.exposure_s * 1e3 for m in c.metas] for c in captures]),
                             {"units": "ms"}),
        "gain": ("frame", per_frame(lambda m: m.gain), {"units": "1"}),
        "irradiance": (("frame", "band"),
                       np.array([[np.nan if m.irradiance is None else m.irradiance for m in c.metas] for c in captures]),
                       {"units": captures[0].metas[0].irradiance_unit,
                        "long_name": "downwelling light sensor (XMP Irradiance or the camera's sun sensor)"}),
        "time": ("frame", np.array([np.datetime64(t.rstrip("Z"), "ns") if t else np.datetime64("NaT", "ns")
                                    for t in times])),
        "lat": ("frame", per_frame(lambda m: m.lat), {"units": "degrees_north"}),
        "lon": ("frame", per_frame(lambda m: m.lon), {"units": "degrees_east"}),
        "alt_m": ("frame", per_frame(lambda m: m.alt_m), {"units": "m"}),
        "capture_id": ("frame", np.array([c.capture_id for c in captures], dtype=object)),
    }


def _template(coords: dict[str, Any], shape: tuple[int, int, int], variables: dict[str, tuple[tuple[str, ...], Any, dict]],
              attrs: dict[str, Any]) -> xr.Dataset:
    import dask.array as da

    ds = xr.Dataset(coords=coords)
    n = len(coords["frame"])
    for name, (dims, dtype, vattrs) in variables.items():
        full = (n, *shape) if len(dims) == 4 else (n, *shape[1:])
        ds[name] = (dims, da.zeros(full, chunks=(1, *full[1:]), dtype=dtype), vattrs)
    ds.attrs.update(attrs)
    return ds


def _create(ds: xr.Dataset, path: Path, compressors: Any) -> None:
    encoding = {v: {"chunks": (1, *ds[v].shape[1:]), "compressors": compressors, "chunk_key_encoding": FLAT_CHUNK_KEYS}
                for v in ds.data_vars}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        ds.to_zarr(path, mode="w", compute=False, consolidated=True, zarr_format=3, encoding=encoding)


def _tmp(out: Path, name: str) -> Path:
    return out / f".{name}{TMP_MARK}{uuid.uuid4().hex[:8]}"


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


@functools.lru_cache(maxsize=2)
def field_parts(store: str, components: tuple[str, ...], camera_name: str) -> tuple[FieldParts, ...]:
    """Per band, the ``components`` of a field calibration ``store`` (loaded once per process)."""
    from pipeline.storage.store import open_calibration

    camera = load_camera(camera_name)
    ds = open_calibration(store, camera)
    lut = ds["inverse_response"].values.astype(np.float64) if "response" in components else None
    vig = ds["vignetting"].values.astype(np.float64) if "vignetting" in components else None
    return tuple(FieldParts(inverse_response=None if lut is None else lut[b], vignetting=None if vig is None else vig[b],
                            dn_shift=camera.dn_shift) for b in range(camera.n_bands))


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
    """``mscal apply CAPTURE_DIR --calibration factory -o OUT`` (see the module docstring)."""
    t_start = time.perf_counter()
    folder, out = Path(capture_dir), Path(out)
    if not folder.is_dir():
        raise InputError("capture folder not found", path=folder)
    ident = identify_camera(folder, options.camera)
    camera = ident.camera
    if options.field_calibration is not None and camera.factory_model not in (None, "micasense"):
        raise InputError(f"--field-calibration replaces parts of MicaSense's radiance model; camera {camera.name} "
                         f"has the {camera.factory_model} model", path=folder, hint="leave out --field-calibration")
    captures, problems = group_captures(folder, camera)
    quarantined = [{"file": Path(p["file"]).name, "reason": p["reason"]} for p in problems]
    if not captures:
        raise FrameError("no complete capture in the folder (all quarantined)", path=folder,
                         hint="; ".join(f"{q['file']}: {q['reason']}" for q in quarantined[:3]))
    shapes = {m.shape for c in captures for m in c.metas}
    if len(shapes) != 1:
        raise InputError(f"band images of different sizes {sorted(shapes)}", path=folder,
                         hint="bands of another resolution (e.g. thermal) need their own catalog camera")
    shape = (camera.n_bands, *shapes.pop())
    export = export_band_indices(camera, options.export_bands)
    indices = [load_index(n) for n in options.indices]
    if options.indices == FactoryOptions.indices:  # the defaults: only the indices this camera's bands allow
        indices = [ix for ix in indices if all(r in camera.index_bands for r in ix.inputs)]
    roles = {ix.name: _index_roles(camera, ix) for ix in indices}

    registration = _registration(options, camera, shape)
    field = _field(options, camera, shape)
    near = panel_config_near(folder)
    parts = field_parts(field[0], field[1], camera.name) if field else None
    fingerprint = {
        "inputs": _stat_fingerprint(captures), "options": options.fingerprint(), "calibration": FACTORY,
        "mscal_version": mscal_core.__version__,
    }
    if registration is not None:
        fingerprint["registration_sha256"] = registration[1]
    if field is not None:
        fingerprint["field_sha256"] = field[2]
    if near is not None:
        fingerprint["panel_config"] = {"session_yaml": str(near[1].resolve()), "panel": repr(near[0])}
    fingerprint = json.loads(json.dumps(fingerprint))
    out.mkdir(parents=True, exist_ok=True)
    previous = _up_to_date(out, fingerprint, ("reflectance.zarr", "raw.zarr"))
    if previous is not None:
        return ApplyResult(out, previous, up_to_date=True, quarantined=previous.get("quarantined", []))
    _clean_temporaries(out)

    reference = options.reference
    if reference == "auto":
        reference = "panel" if options.panel_reflectance is not None else "dls"
        if reference == "dls" and not any(reflectance_factor(m) is not None for c in captures for m in c.metas):
            reference = "none"  # radiance only: the camera's sun sensor gives no usable reflectance
    panels: list[PanelReference] = []
    panel_factor = None
    if reference == "panel":
        if options.panel_reflectance is None:
            raise InputError("--reference panel needs --panel-reflectance (a number or a target name)",
                             hint="e.g. --panel-reflectance micasense-rp02-1603036-sc")
        spec = reflectance_option(options.panel_reflectance)
        rho = [float(r) for r in spec.at(np.array([m.wavelength_nm for m in captures[0].metas]))]
        panels = _find_panels(captures, options.panel_captures, rho, folder, parts,
                              None if near is None else near[0])
        panel_factor = tuple(float(np.mean([p.factor_split[b] for p in panels])) for b in range(camera.n_bands))


    scale = relative_scale(captures, reference)
    t0 = time.perf_counter()
    with Runner(len(captures)) as runner:
        while True:  # a capture found unusable in the pass is quarantined and the pass redone without it
            ps = _Pass.start(out, camera, captures, shape, indices, roles, export, reference, panel_factor,
                             options, folder, None if field is None else field[:2], scale)
            outcomes = runner.run(ps.plan, [CaptureJob(f, c, _tags(camera, c)) for f, c in enumerate(captures)],
                                  fn=process_capture)
            bad = {o.name: o.quarantine for o in outcomes if o.quarantine is not None}
            if not bad:
                break
            ps.discard()
            for name, q in bad.items():
                _remove_frame_tiffs(out, [name], camera, export)
                quarantined.append(q)
            captures = [c for c in captures if c.name not in bad]
            if not captures:
                raise FrameError("no usable capture in the folder (all quarantined)", path=folder,
                                 hint="; ".join(f"{q['file']}: {q['reason']}" for q in quarantined[:3]))
    t_pass = time.perf_counter() - t0
    _install(out, ps.tmp_raw, "raw.zarr")
    _install(out, ps.tmp_refl)
    frames = [o.name for o in outcomes]
    quarantined.sort(key=lambda q: q["file"])
    run = {
        "flight": str(folder),
        "calibration": FACTORY,
        "calibration_sha256": None,
        "components": _components_record(field),
        "camera": camera.name,
        "reference": {**_reference_record(reference, panels, panel_factor, camera, captures[0]),
                      **({"relative_scale": scale} if scale != 1.0 else {})},
        "camera_identification": {"evidence": ident.evidence, "overridden": ident.overridden, **ident.probe},
        "radiance_unit": captures[0].metas[0].radiance_unit,
        "orientation": _orientation_record(captures[0]),
        "skipped_bands": [s for c in captures for s in c.skipped],
        "metadata_problems": [p.as_dict() for c in captures for p in c.problems],
        "reflectance_missing": [m for o in outcomes for m in o.no_reflectance],
        "frames_in": len(frames) + len(quarantined),
        "frames_out": len(frames),
        "frames": frames,
        "frames_sha256": {o.name: o.sha256 for o in outcomes},
        "quarantined": quarantined,
        "saturated_pixels": {"total": int(sum(o.saturated for o in outcomes)),
                             "per_frame": {o.name: o.saturated for o in outcomes}},
        "outputs": {"reflectance": "reflectance.zarr", "raw": "raw.zarr", "photogrammetry": "photogrammetry/",
                    "ndvi": "ndvi/"},
        "export_bands": [camera.bands[b].name for b in export],
        "versions": _versions(),
        "scheduler": runner.scheduler,
        "timings_s": {"apply": round(t_pass, 3), "total": round(time.perf_counter() - t_start, 3)},
        "fingerprint": fingerprint,
    }
    _write_json_atomic(out / RUN_JSON, run)
    return ApplyResult(out, run, up_to_date=False, quarantined=quarantined)


@dataclass
class _Pass:
    """One pass's output stores under their temporary names, and its plan."""

    plan: CapturePlan
    tmp_refl: Path
    tmp_raw: Path

    @staticmethod
    def start(out: Path, camera: Camera, captures: Sequence[Capture], shape: tuple[int, int, int],
              indices: Sequence[Index], roles: dict[str, dict[str, int]], export: Sequence[int], reference: str,
              panel_factor: tuple[float, ...] | None, options: FactoryOptions, folder: Path,
              field: tuple[str, tuple[str, ...]] | None = None, scale: float = 1.0) -> "_Pass":
        coords = _coords(camera, captures)
        attrs = {"Conventions": "CF-1.10", "camera": camera.name, "mscal_version": mscal_core.__version__,
                 "calibration": FACTORY, "reference": reference, "source": str(folder), "co_registered": 0,
                 "comment": "bands are not co-registered: each band keeps its own pixel grid",
                 "components": json.dumps(_components_record(None if field is None else (*field, "")))}
        if options.registration is not None:
            attrs.update({"co_registered": 1, "registration": str(options.registration),
                          "comment": "bands aligned to the reference band of the registration store "
                                     "(mscal register); NaN where a band does not cover the reference grid"})
        rvars: dict[str, tuple[tuple[str, ...], Any, dict]] = {
            "reflectance": (("frame", "band", "y", "x"), np.float32,
                            {"long_name": f"reflectance (factory radiance x {reference} factor)", "units": "1"}),
            "radiance": (("frame", "band", "y", "x"), np.float32,
                         {"long_name": "factory radiance", "units": captures[0].metas[0].radiance_unit}),
        }
        for ix in indices:
            rvars[ix.name] = (("frame", "y", "x"), np.float32, {"long_name": ix.description, "expression": ix.expression})
        if any(ix.name == "ndvi" for ix in indices):
            rvars["vegetation_mask"] = (("frame", "y", "x"), np.uint8,
                                        {"long_name": "vegetation (Otsu threshold of NDVI per frame)",
                                         "flag_values": [0, 1, 255], "flag_meanings": "other vegetation undefined"})
        tmp_refl, tmp_raw = _tmp(out, "reflectance.zarr"), _tmp(out, "raw.zarr")
        refl_ds = _template(coords, shape, rvars, attrs)
        _create(refl_ds, tmp_refl, OUTPUT_COMPRESSORS)
        raw_ds = _template(coords, shape, {"dn": (("frame", "band", "y", "x"), np.uint16,
                                                  {"long_name": "stored DN of each band file"})}, attrs)
        _create(raw_ds, tmp_raw, [raw_codec()])
        for sub in ("photogrammetry", "ndvi"):
            (out / sub).mkdir(exist_ok=True)
        first = captures[0].metas
        plan = CapturePlan(
            camera=camera, raw_store=tmp_raw, out_store=tmp_refl, out=out, shape=shape, reference=reference,
            panel_factor=panel_factor, sat=saturation_dn(camera), indices=tuple((ix, roles[ix.name]) for ix in indices),
            bands=tuple((b, BandTags(name=camera.bands[b].name, wavelength_nm=first[b].wavelength_nm,
                                     fwhm_nm=first[b].fwhm_nm, rig_camera_index=i))
                        for i, b in enumerate(export)),
            tiff_dtype=options.tiff_dtype, outputs=tuple(str(v) for v in refl_ds.data_vars),
            registration=None if options.registration is None else Path(options.registration),
            field=field, relative_scale=scale,
        )
        return _Pass(plan, tmp_refl, tmp_raw)

    def discard(self) -> None:
        shutil.rmtree(self.tmp_refl, ignore_errors=True)
        shutil.rmtree(self.tmp_raw, ignore_errors=True)


def saturation_dn(camera: Camera) -> int:
    """Stored value at and above which a pixel is clipped: the sensor's largest DN in the
    container's high bits (65520 for 12-bit data in 16-bit samples)."""
    return ((1 << camera.bit_depth) - 1) << camera.dn_shift


def _tags(camera: Camera, capture: Capture) -> FrameTags:
    m = capture.metas[0]
    return FrameTags(
        time=m.time, lat=m.lat, lon=m.lon, alt_m=m.alt_m,
        capture_uuid=str(uuid.uuid5(uuid.NAMESPACE_URL, f"mscal:{camera.name}:{capture.capture_id}")),
        exposure_ms=float(np.median([x.exposure_s * 1e3 for x in capture.metas])),
        camera_make="mscal", camera_model=camera.name,
    )


def _components_record(field: tuple[str, tuple[str, ...], str] | None) -> dict[str, str]:
    """Where each part of the radiance model came from: 'factory' or 'field:STORE'."""
    return {c: (f"field:{field[0]}" if field is not None and c in field[1] else FACTORY) for c in FIELD_COMPONENTS}


def _orientation_record(capture: Capture) -> str:
    o = capture.metas[0].orientation
    return "as stored" if o in (0, 1) else f"EXIF Orientation {o}: outputs turned upright (raw.zarr too)"


def _reference_record(reference: str, panels: Sequence[PanelReference], factor: tuple[float, ...] | None,
                      camera: Camera, first: Capture | None = None) -> dict[str, Any]:
    """What run.json says of the reference: the route, and for the panel route every panel
    capture's factors beside the DLS's on the same capture (their ratio compares the two)."""
    rec: dict[str, Any] = {"route": reference}
    meta = first.metas[0] if first is not None else None
    if reference == "none":
        rec["formula"] = "no reflectance (NaN): no panel given and the sun sensor gives no usable reflectance"
        rec["hint"] = "give a panel capture: --panel-reflectance TARGET"
        return rec
    if reference == "dls":
        if meta is None or sun_sensor_absolute(meta):
            rec["formula"] = "R_b = pi L_b / E_b, E_b the capture's XMP Irradiance (no tilt correction)"
        else:
            rec["formula"] = (f"R_b = L_b / E_b, E_b the capture's sun sensor ({meta.irradiance_unit}): reflectance "
                              "up to one unknown constant (indices are right; absolute values need a panel)")
            rec["scale"] = "relative"
        return rec
    rec["formula"] = "R_b = L_b / S_b, S_b from the panel's Eq. 11-14 split (median-lit panel)"
    rec["factor"] = dict(zip(camera.band_names, factor or ()))
    rec["panels"] = []
    for p in panels:
        ratio = {name: (ks / kd if kd else None) for name, ks, kd in zip(camera.band_names, p.factor_split, p.factor_dls)}
        rec["panels"].append({
            "capture": p.capture,
            "factor_split": dict(zip(camera.band_names, p.factor_split)),
            "factor_mean": dict(zip(camera.band_names, p.factor_mean)),
            "factor_dls": dict(zip(camera.band_names, p.factor_dls)),
            "panel_over_dls": ratio,
            "brightness_p10_p90": list(p.brightness_p10_p90),
            "split_residual_rms": p.split_residual_rms,
            "region_source": list(p.region_source),
        })
    return rec
