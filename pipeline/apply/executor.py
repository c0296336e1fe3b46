"""The one apply executor: one capture in, every output of it written.

A *capture* is one exposure of all bands: one file (a snapshot mosaic or a multichannel
image; ``Job.rec``, or its chunk of ``raw.zarr`` when it was ingested before) or one file per
band (``Job.capture``, grouped by :func:`pipeline.ingest.grouping.group_captures`). The
radiometric model is one per-band chain chosen per run (``Plan.chain``):

- :class:`FieldChain`: Eq. 15, ``R = U(I) / (t V S)``, with U, V, S of a calibration store
  (``mscal calibrate``), the light of the capture's time folded in (``Job.scale``);
- :class:`FactoryChain`: the camera's own metadata per band file (each vendor's radiance
  model, :func:`pipeline.ingest.cameras.dispatch.factory_radiance`; MicaSense's optionally with
  field U and/or V in place of the factory's), times one factor per band (a panel's, the
  capture's sun sensor's -- NaN for a band without a usable reading, its radiance is kept --,
  or NaN for a radiance-only run; ``Job.scale`` overrides it).

:func:`process_frames` reads each capture (hashing and checking it; a new one is written into
``raw.zarr``), runs the chain, puts the bands on one pixel grid (the band files' own
registration, DJI's DewarpData and CalibratedHMatrix: ``Plan.factory_alignment``, refined by
image registration per capture: ``Plan.refine``; band transforms or ``--centre-bands``, :func:`geometry_step`;
:mod:`pipeline.apply.bandgrid`, which also measures what is left on sampled captures), turns a capture read from its files upright (EXIF
Orientation: Parrot Sequoia stores its frames rotated 180 degrees; the band transforms belong
to the stored frames, so they come first; raw.zarr is turned too), normalises, and writes its
whole chunk of every ``reflectance.zarr`` variable, its photogrammetry TIFFs and its NDVI TIFF. :class:`Runner`
runs the tasks on the caller's ``distributed`` client, else on local threads or processes.
The drivers (:mod:`pipeline.apply.flight` for frames ingested into raw.zarr,
:mod:`pipeline.apply.captures` for folders of captures) only plan the jobs and the stores.
"""
from __future__ import annotations

import itertools
import logging
import uuid
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import dask
import dask.threaded
import numpy as np
from mscal_core.errors import FrameError, InputError, ProcessesUnavailable
from mscal_core.quality import CENSOR_HIGH, region_median
from mscal_core.reflectance import eq15_fast, vegetation_mask

from pipeline.apply.bandgrid import grid_and_residuals
from pipeline.apply.execution import (
    Execution,
    distributed_client,
    scheduler_for,
    take_worker_environment,
    worker_context,
    worker_environment,
)
from pipeline.apply.frame_writes import WRITER_THREADS, FrameWrites  # noqa: F401  (WRITER_THREADS: re-exported)
from pipeline.apply.quality import Flagging, finish_counted, not_coregistered, on_grid, sensor_flags, warp_bits
from pipeline.apply.stores import calibration_tables, geometry_step, read_frame_chunk, warm_calibration, write_frame
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance, is_temperature
from pipeline.ingest.catalog import Camera, Index, load_camera
from pipeline.ingest.discover import quarantine_entry
from pipeline.ingest.grouping import Capture, read_capture_pixels
from pipeline.ingest.medians import band_medians
from pipeline.ingest.meta import FieldParts, no_reflectance_reason, reflectance_factor, upright_meta
from pipeline.ingest.raw import prefetch_file, read_frame, shape_problem
from pipeline.ingest.session import FrameRecord
from pipeline.ingest.tiff import decode_raw
from pipeline.products.writers import (
    BandTags,
    FrameTags,
    band_tiff_parts,
    file_band_name,
    ndvi_tiff_parts,
    write_band_tiff,
    write_tiff_file,
)
from pipeline.storage.directio import aligned_empty
from pipeline.storage.process import die_with_parent, reuse_freed_memory, start_pool

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- helpers


def capture_uuid(camera: Camera, sha256: str) -> str:
    """Deterministic CaptureUUID of a frame (the same on every re-run)."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"mscal:{camera.name}:{sha256}"))


# Output variables are written uncompressed: lz4 gains only 1.24x on float32 reflectance for
# 5.8 ms of CPU per full-resolution frame, more than writing the bytes it saves costs.
OUTPUT_COMPRESSORS: tuple = ()


# --------------------------------------------------------------------------- radiometric chains


@dataclass(frozen=True)
class FieldChain:
    """Eq. 15 with every component from a calibration store (U, V, S; the ``field`` chain)."""

    calibration: Path
    sat: int  # DN (the calibration's) from which a pixel is saturated
    flagging: Flagging | None = None  # the quality mask (pipeline.apply.quality); None: none made

    kind = "field"


@dataclass(frozen=True)
class FactoryChain:
    """The camera's own radiometric metadata per band file (``field``: components of a store
    that replace the factory's), times ``k_b`` (the panel's, else the capture's sun sensor's,
    else NaN: radiance only)."""

    sat: int  # stored DN from which a pixel is clipped (the camera's; a file's own depth may lower it: clipped_from)
    reference: str = "dls"  # panel | dls | none (radiance only)
    panel_factor: tuple[float, ...] | None = None
    field: tuple[str, tuple[str, ...]] | None = None  # (store, components) replacing the factory's
    flagging: Flagging | None = None  # the quality mask (pipeline.apply.quality); None: none made

    kind = "factory"


@lru_cache(maxsize=2)
def field_parts(store: str, components: tuple[str, ...], camera_name: str) -> tuple[FieldParts, ...]:
    """Per band, the ``components`` of a field calibration ``store`` (loaded once per process)."""
    from pipeline.storage.store import open_calibration

    camera = load_camera(camera_name)
    ds = open_calibration(store, camera)
    lut = ds["inverse_response"].values.astype(np.float64) if "response" in components else None
    vig = ds["vignetting"].values.astype(np.float64) if "vignetting" in components else None
    return tuple(FieldParts(inverse_response=None if lut is None else lut[b], vignetting=None if vig is None else vig[b],
                            dn_shift=camera.dn_shift, sensor_bits=camera.bit_depth) for b in range(camera.n_bands))


def capture_factors(chain: FactoryChain, capture: Capture) -> np.ndarray:
    """``k_b`` of one capture: the panel's; or its own sun sensor's
    (:func:`pipeline.ingest.meta.reflectance_factor`: ``c / E_b``, ``c`` the camera
    model's fixed scale, :mod:`pipeline.ingest.sun_scale`), NaN for a band without
    a usable reading (:func:`missing_reflectance` names it); NaN for every band when the run
    has no reference (radiance only)."""
    if chain.reference == "panel":
        assert chain.panel_factor is not None
        return np.asarray(chain.panel_factor, dtype=np.float64)
    if chain.reference == "none":
        return np.full(len(capture.metas), np.nan)
    k = [reflectance_factor(meta) for meta in capture.metas]
    return np.array([np.nan if kb is None else kb for kb in k], dtype=np.float64)


def missing_reflectance(chain: FieldChain | FactoryChain, capture: Capture) -> tuple[dict[str, str], ...]:
    """The bands of a capture on the sun-sensor route without a usable reading: their radiance
    is written, their reflectance is NaN, the capture is not quarantined (run.json
    ``reflectance_missing``)."""
    if not isinstance(chain, FactoryChain) or chain.reference != "dls":
        return ()
    out = []
    for meta in capture.metas:
        why = no_reflectance_reason(meta)
        if why is not None:
            out.append({"capture": capture.name, "file": meta.path.name, "band": meta.band_name, "reason": why})
    return tuple(out)


def band_exposures(capture: Capture) -> np.ndarray:
    """Effective exposure ``t`` (ms x gain) of each band file of a capture (Eq. 15's t)."""
    return np.array([m.exposure_s * 1e3 * m.gain for m in capture.metas], dtype=np.float64)


# --------------------------------------------------------------------------- the task


@dataclass(frozen=True)
class Plan:
    """What every capture's task needs: paths and small values, no arrays (it is sent to
    worker processes with each task)."""

    camera: Camera
    chain: FieldChain | FactoryChain
    raw_dn: Path  # raw.zarr's dn array: a stored capture is read from it, a new one written into it
    cube_shape: tuple[int, int, int]
    out_store: Path
    outputs: tuple[str, ...]
    indices: tuple[tuple[Index, dict[str, int]], ...]
    bands: tuple[tuple[int, BandTags], ...]
    tiff_dtype: str
    out: Path
    norm: tuple[str, float | int | None] = ("none", None)
    transforms: Path | None = None  # a store whose band transforms put the bands on the reference band's grid
    band_shift: tuple[tuple[float, float], ...] | None = None  # --centre-bands: (dx, dy) per band
    factory_alignment: bool = False  # each band file's own registration (DJI), cameras.dispatch.align_by_files
    refine: Any = None  # coregistration.Refinement: image registration per capture on top of it (bandgrid)
    coreg_reference: int | None = None  # the band the measured captures' residual shifts are against (bandgrid)
    raw_medians: Path | None = None  # raw.zarr's dn_median (frame, band), written with each new frame's DN
    tiffs: bool = True  # the per-frame TIFFs (photogrammetry, panels, thermal, NDVI); False: --no-tiffs

    def indices_made(self) -> list[Index]:
        """The indices the pass writes (run.json ``products``)."""
        return [ix for ix, _ in self.indices]


@dataclass(frozen=True)
class Job:
    """One capture of the pass. ``rec``: a new single-file capture, read from its file,
    checked and written into raw.zarr at ``index``; ``capture``: a one-file-per-band capture
    (always read from its files); neither: read from raw.zarr."""

    index: int
    name: str
    tags: FrameTags
    t: float = 1.0  # effective exposure of a single-file capture (exposure_ms x gain); band files carry their own
    rec: FrameRecord | None = None
    capture: Capture | None = None
    scale: tuple[float, ...] | None = None  # per band: field S / S(lambda, time); factory k_b
    ahead: Path | None = None  # the file of a capture a few places on, to read ahead (prefetch_file)
    panel: bool = False  # a panel capture: its band TIFFs go to OUT/panels/, apart from the survey frames
    measure: bool = False  # the bands' residual shifts are measured on its pixels (bandgrid.grid_residuals)


#: Folders of the per-frame TIFFs under OUT: survey frames (photogrammetry input), panel
#: captures (kept out of photogrammetry), NDVI of the survey frames.
PHOTOGRAMMETRY_DIR, PANELS_DIR, NDVI_DIR = "photogrammetry", "panels", "ndvi"


def band_tiff_path(out: Path, capture: str, band: str, panel: bool = False) -> Path:
    """``OUT/photogrammetry/<capture>_<band>.tif`` (``OUT/panels/`` for a panel capture), the
    band's name without spaces (:func:`pipeline.products.writers.file_band_name`)."""
    return Path(out) / (PANELS_DIR if panel else PHOTOGRAMMETRY_DIR) / f"{capture}_{file_band_name(band)}.tif"


@dataclass(frozen=True)
class Outcome:
    name: str
    sha256: str | None  # of the file(s), for a capture read from its files
    saturated: int
    quarantine: dict[str, str] | None = None  # a capture that cannot be used: nothing written
    no_reflectance: tuple[dict[str, str], ...] = ()  # bands written as radiance only, and why (missing_reflectance)
    thermal: tuple[dict[str, str], ...] = ()  # thermal bands written in kelvin (write_thermal), or why not
    coregistration: dict[str, Any] | None = None  # residual shifts of a measured capture (bandgrid.grid_residuals)
    quality: dict[str, dict[str, int]] | None = None  # per band the pixels of each flag (pipeline.apply.quality)


def capture_dn(plan: Plan, job: Job) -> tuple[np.ndarray, str | None, dict[Path, np.ndarray]]:
    """DN (band, y, x) of a job's capture, as stored: from its file(s) (checked; FrameError) or
    from raw.zarr; its content hash (None from raw.zarr); the whole ``(H, W, C)`` image of each
    multi-channel file (Sentera's colour transform needs every channel;
    :func:`pipeline.ingest.grouping.read_capture_pixels`)."""
    if job.capture is not None:
        return _capture_files(job.capture, plan.cube_shape)
    if job.rec is None:
        return read_frame_chunk(plan.raw_dn, job.index), None, {}
    sha, dn = read_frame(job.rec, plan.camera)
    assert dn is not None
    problem = shape_problem(dn.shape, plan.cube_shape)
    if problem:
        raise FrameError(problem, path=job.rec.path)
    return dn, sha, {}


def _capture_files(capture: Capture, shape: tuple[int, int, int]) -> tuple[np.ndarray, str, dict[Path, np.ndarray]]:
    cube = np.empty(shape, np.uint16)  # plain band files are decoded straight into it
    sha, dns, channels = read_capture_pixels(capture, out=cube)
    if any(dn.shape != shape[1:] for dn in dns):
        raise FrameError(f"band images {[d.shape for d in dns]} are not all {shape[1:]}", path=capture.files[0])
    if len(dns) != shape[0]:
        return np.stack(dns), sha, channels
    for b, dn in enumerate(dns):
        if not np.may_share_memory(dn, cube[b]):  # decoded elsewhere (not a plain band file)
            cube[b] = dn
    return cube, sha, channels


def radiometry(camera: Camera, chain: FieldChain | FactoryChain, job: Job, dn: np.ndarray,
               channels: dict[Path, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, int, np.ndarray | None]:
    """The chain on one capture's DN: ``(signal, factor, radiance, saturated pixels, quality)``.
    ``signal`` goes onto the common pixel grid before the per-band ``factor`` (None: 1);
    ``radiance`` (factory chain) is the signal kept as an output; ``channels``: the whole image
    of each multi-channel band file (:func:`capture_dn`); ``quality``: the mask on the stored grid
    (:mod:`pipeline.apply.quality`; None without ``chain.flagging``). FrameError: unusable."""
    flagging = chain.flagging
    if isinstance(chain, FieldChain):
        lut, inv_v = calibration_tables(str(chain.calibration), None if flagging is None else
                                        (chain.sat, flagging.bound, flagging.keep_flagged))
        q = None
        # into a page-aligned array: its reflectance.zarr chunk goes to the device straight from
        # it (write_file), without an 8.9 MB copy per full-resolution snapshot frame
        refl = aligned_empty((1, *dn.shape), np.float32)
        if job.capture is None:
            eq15_fast(dn[None], lut, inv_v, job.t, chain.sat,
                      None if job.scale is None else np.asarray(job.scale)[None], out=refl)
            if flagging is not None:
                q = sensor_flags(flagging, chain.calibration, chain.sat, dn, refl[0])
            return refl[0], None, None, int(np.count_nonzero(dn >= chain.sat)), q
        # band files to sensor DN, each by what it stores (Camera.shift_for): a RedEdge's 16-bit
        # file by 4, its 12-bit file not at all; snapshot DN are sensor DN already
        shifts = [camera.shift_for(m.bits_per_sample) for m in job.capture.metas]
        if len(set(shifts)) == 1:
            d = np.right_shift(dn, shifts[0]) if shifts[0] else dn
        else:
            d = np.stack([np.right_shift(dn[b], s) for b, s in enumerate(shifts)])
        k = (np.ones(dn.shape[0]) if job.scale is None else np.asarray(job.scale, dtype=np.float64))
        eq15_fast(d[None], lut, inv_v, 1.0, chain.sat, (k / band_exposures(job.capture))[None], out=refl)
        if flagging is not None:
            q = sensor_flags(flagging, chain.calibration, chain.sat, d, refl[0])
        return refl[0], None, None, int(np.count_nonzero(d >= chain.sat)), q
    cap = job.capture
    if cap is None:
        raise InputError("the factory chain needs the band files' own metadata (one-file-per-band captures)")
    k = np.asarray(job.scale, dtype=np.float64) if job.scale is not None else capture_factors(chain, cap)
    parts = field_parts(chain.field[0], chain.field[1], camera.name) if chain.field else [None] * dn.shape[0]
    rad = aligned_empty(dn.shape, np.float32)  # written to raw chunks without a copy (write_file)
    for b, meta in enumerate(cap.metas):
        factory_radiance(meta, dn[b], parts[b], (channels or {}).get(meta.path), out=rad[b])
    saturated = np.empty(dn.shape, bool)
    for b, meta in enumerate(cap.metas):  # each file clips at its own depth's top (12-bit: 4095)
        np.greater_equal(dn[b], meta.clipped_from(chain.sat), out=saturated[b])
    np.copyto(rad, np.float32(np.nan), where=saturated)
    q = None if flagging is None else saturated.view(np.uint8)  # FLAGS["saturated"] == 1
    return rad, k, rad, int(np.count_nonzero(saturated)), q


def capture_reflectance(camera: Camera, chain: FieldChain | FactoryChain, job: Job, transforms: Path | None = None,
                        band_shift: Sequence[tuple[float, float]] | None = None
                        ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Reflectance (band, y, x) of one capture read from its band files, on the outputs' pixel
    grid, before normalisation (a panel's region is measured on it); writes nothing. With a
    quality mask in the chain (``chain.flagging``), that and the mask on the same grid."""
    assert job.capture is not None
    sha, dns, channels = read_capture_pixels(job.capture)
    signal, factor, _, _, q = radiometry(camera, chain, job, np.stack(dns), channels)
    meta = job.capture.metas[0]

    def warp(stack: np.ndarray) -> np.ndarray:
        if transforms is not None or band_shift is not None:
            stack = geometry_step(transforms or Path(), transforms is not None, band_shift, job.name, stack)
        return upright_meta(meta, stack)

    signal = warp(signal)
    signal = signal if factor is None else signal * factor.astype(np.float32)[:, None, None]
    return signal if q is None else (signal, warp_bits(q, warp))


def write_raw(plan: Plan, index: int, dn: np.ndarray) -> None:
    """A new frame's raw.zarr chunk, and its band medians where the cube keeps them."""
    write_frame(plan.raw_dn, index, dn)
    if plan.raw_medians is not None:
        write_frame(plan.raw_medians, index, band_medians(dn))


@dataclass
class _Writing:
    """A frame whose outputs are made and on their way to disk (:func:`process_frames`)."""

    job: Job
    sha256: str | None
    saturated: int
    tags: FrameTags
    writes: FrameWrites
    coregistration: dict[str, Any] | None = None
    quality: dict[str, dict[str, int]] | None = None


#: At most this many frames of a task have their files on the way to disk while the next
#: frame is computed (:func:`process_frames`), ...
WRITING_FRAMES = 2
#: ... and more than one only while those frames' outputs total at most this many bytes (a
#: full-resolution snapshot frame hands ~16 MB to its writes, a 5-band MicaSense capture
#: ~60 MB: a factory pass keeps one frame writing, and its memory as before).
WRITING_BYTES = 64 * 1024 * 1024


def process_frames(plan: Plan, jobs: Sequence[Job]) -> list[Outcome]:
    """Captures one after the other, every output of each (:func:`start_frame`), one
    :class:`Outcome` per job in job order. A frame's files are still being written while the
    next frames are computed (up to :data:`WRITING_FRAMES` frames writing, within
    :data:`WRITING_BYTES`); its outcome is made once they are on disk, and every frame's
    are before this returns. On an error nothing is left writing behind it.

    Why: with the wait at the end of every frame, the computing thread spent ~40 % of a
    600-frame snapshot apply waiting for its own writes; with one frame writing behind, it
    still waited whenever a frame's writes took longer than the next frame's computing (the
    device is shared by both workers). Two frames writing (3 and 5 measured too, no better):
    600 frames, 4 alternating runs each (both without raw.zarr's commit barriers), median
    wall 10.47 -> 9.98 s, peak RSS +15 MiB (docs/benchmarks.md)."""
    outcomes: list[Outcome] = []
    pending: deque[Outcome | _Writing] = deque()  # in job order; the _Writing ones still writing

    def writing() -> list[_Writing]:
        return [p for p in pending if isinstance(p, _Writing)]

    def finish_due(limit: int) -> None:
        while pending:
            w = writing()
            over = len(w) > limit or (len(w) > 1 and sum(x.writes.nbytes for x in w) > WRITING_BYTES)
            if isinstance(pending[0], _Writing) and not over:
                return
            done = pending.popleft()
            outcomes.append(finish_frame(plan, done) if isinstance(done, _Writing) else done)

    try:
        for job in jobs:
            pending.append(start_frame(plan, job))
            finish_due(WRITING_FRAMES)  # these write on while the next frame is computed
        finish_due(0)
    except BaseException:
        for w in writing():
            w.writes.wait(raise_errors=False)
        raise
    return outcomes


def start_frame(plan: Plan, job: Job) -> Outcome | _Writing:
    """One capture, every output made and handed to the writer threads: (for a capture read
    from its files) its raw.zarr chunk, the radiometric chain, the common pixel grid,
    normalisation, indices, Otsu mask, its chunk of each reflectance.zarr variable (one whole
    chunk per variable: no two tasks share a chunk), its photogrammetry and NDVI TIFFs. First
    it asks for a later capture's file to be read ahead (``job.ahead``). A capture that
    cannot be used is returned as its quarantine :class:`Outcome`, nothing written."""
    if job.ahead is not None:
        prefetch_file(job.ahead)
    try:
        dn, sha, channels = capture_dn(plan, job)
        signal, factor, radiance, saturated, q = radiometry(plan.camera, plan.chain, job, dn, channels)
        stored = signal
        signal, residuals, warp = grid_and_residuals(plan, job, signal)
        if q is not None:
            q = on_grid(q, warp)
    except FrameError as exc:
        return _quarantined(job, exc)
    moved = signal is not stored
    if job.capture is not None:  # as meant to be seen, after the transforms (they belong to the stored frames)
        try:
            signal, dn = (np.ascontiguousarray(upright_meta(job.capture.metas[0], a)) for a in (signal, dn))
            if q is not None:
                q = np.ascontiguousarray(upright_meta(job.capture.metas[0], q))
        except FrameError as exc:
            return _quarantined(job, exc)
    if radiance is not None:  # an output only when chosen (--products radiance)
        radiance = signal if "radiance" in plan.outputs else None
    writes = FrameWrites()
    try:
        tags, flagged = _write_products(plan, job, dn, sha, signal, factor, radiance, writes, (q, residuals, moved))
    except BaseException:
        writes.wait(raise_errors=False)  # nothing of this frame is left writing behind the error
        raise
    return _Writing(job, sha, saturated, tags, writes, residuals, flagged)


def finish_frame(plan: Plan, w: _Writing) -> Outcome:
    """A started frame's outcome, once its files are on disk (the first write error raised),
    with its thermal bands written."""
    w.writes.wait()
    job = w.job
    missing = () if job.capture is None else missing_reflectance(plan.chain, job.capture)
    return Outcome(job.name, w.sha256, w.saturated, no_reflectance=missing, thermal=write_thermal(plan, job, w.tags),
                   coregistration=w.coregistration, quality=w.quality)


def _write_products(plan: Plan, job: Job, dn: np.ndarray, sha: str | None, signal: np.ndarray,
                    factor: np.ndarray | None, radiance: np.ndarray | None, writes: FrameWrites,
                    quality: tuple[np.ndarray | None, dict[str, Any] | None, bool] = (None, None, False)
                    ) -> tuple[FrameTags, dict[str, dict[str, int]] | None]:
    """:func:`start_frame`'s outputs of one capture: the raw chunk (a new capture), radiance,
    reflectance (``signal`` times ``factor``, normalised, in place), its quality mask
    (``quality``: the mask on the grid, the capture's residuals, whether the grid moved its
    pixels; :func:`pipeline.apply.quality.finish_counted`), indices, mask, TIFFs.
    Chunks go to ``writes`` once nothing changes them; the TIFFs are made here meanwhile.
    Returns the frame's tags (with its CaptureUUID) and its flagged pixels per band and flag."""
    tags = job.tags
    if sha is not None:
        writes.submit(write_raw, plan, job.index, dn)
        if job.rec is not None:
            tags = replace(tags, capture_uuid=capture_uuid(plan.camera, sha))
    store = plan.out_store
    if radiance is not None:  # written first, here: reflectance is made from it in place
        write_frame(store / "radiance", job.index, radiance)
    refl = signal
    if factor is not None:  # in place (the same products as signal * factor, no new 25 MB cube)
        refl *= factor.astype(np.float32)[:, None, None]
    kind, value = plan.norm
    if kind == "scalar":
        refl *= np.float32(value)
    elif kind == "band":
        b, q = int(value), quality[0]
        if q is not None and np.bitwise_and(q[b], CENSOR_HIGH).any():
            # the band's pixels flagged high count as above its median (their values are NaN
            # or not defensible): the valid pixels alone would read low
            med = float(region_median(refl[b].ravel(), q[b].ravel()))
        else:
            med = np.nanmedian(refl[b])
        refl *= np.float32(1.0 / med) if np.isfinite(med) and med > 0 else np.float32(np.nan)
    q, residuals, moved = quality
    flagged = None
    if q is not None and plan.chain.flagging is not None:
        q, flagged = finish_counted(plan.chain.flagging, q, refl, not_coregistered(plan, residuals), moved,
                                    [b.name for b in plan.camera.bands])
        if "quality" in plan.outputs:
            writes.submit(write_frame, store / "quality", job.index, q)
    writes.submit(write_frame, store / "reflectance", job.index, refl)  # only read from here on
    ndvi = None
    for ix, roles in plan.indices:
        val = ix.evaluate({role: refl[b] for role, b in roles.items()})
        writes.submit(write_frame, store / ix.name, job.index, val)
        if ix.name == "ndvi":
            ndvi = val
    if ndvi is not None and "vegetation_mask" in plan.outputs:
        writes.submit(write_frame, store / "vegetation_mask", job.index, vegetation_mask(ndvi))
    for b, btags in plan.bands if plan.tiffs else ():  # encoded here, written by the writer thread
        writes.submit(write_tiff_file, band_tiff_path(plan.out, job.name, btags.name, job.panel),
                      band_tiff_parts(refl[b], tags, btags, dtype=plan.tiff_dtype))
    if ndvi is not None and not job.panel and plan.tiffs:
        writes.submit(write_tiff_file, plan.out / NDVI_DIR / f"{job.name}.tif", ndvi_tiff_parts(ndvi, tags))
    return tags, flagged


def write_thermal(plan: Plan, job: Job, tags: FrameTags) -> tuple[dict[str, str], ...]:
    """The thermal bands of a capture (band files kept out of reflectance whose reader says
    ``thermal``: MicaSense Altum / Altum-PT LWIR) as temperature in kelvin with the camera's own
    conversion (:func:`pipeline.ingest.cameras.dispatch.factory_radiance`), each in its own float32
    TIFF ``thermal/<capture>_<band>.tif``, upright, on the thermal band's own grid; never part
    of reflectance. One ``{file, band, written | reason}`` per thermal band file."""
    out: list[dict[str, str]] = []
    for s in job.capture.skipped if job.capture is not None and plan.tiffs else ():
        path = Path(s["file"])
        try:
            meta = read_capture_meta(path)
            if not is_temperature(meta):
                continue
            kelvin = upright_meta(meta, factory_radiance(meta, np.asarray(decode_raw(path.read_bytes(), path))))
        except FrameError as exc:
            out.append({"file": path.name, "band": s["band"], "reason": f"not written: {exc.reason}"})
            continue
        except Exception as exc:  # a truncated file: tifffile raises what it raises
            out.append({"file": path.name, "band": s["band"], "reason": f"not written: unreadable ({type(exc).__name__})"})
            continue
        name = f"{job.name}_{file_band_name(meta.band_name)}.tif"
        (plan.out / "thermal").mkdir(exist_ok=True)
        write_band_tiff(plan.out / "thermal" / name, kelvin.astype(np.float32), tags,
                        BandTags(name=meta.band_name, wavelength_nm=meta.wavelength_nm, fwhm_nm=meta.fwhm_nm,
                                 rig_camera_index=meta.rig_camera_index or 0), dtype="float32")
        out.append({"file": path.name, "band": meta.band_name, "written": f"thermal/{name}"})
    return tuple(out)


def _quarantined(job: Job, exc: FrameError) -> Outcome:
    """The outcome of a capture that cannot be used: nothing written, the file named."""
    if job.capture is not None:
        file = Path(exc.path or job.capture.files[0]).name
    else:
        assert job.rec is not None  # a chunk of raw.zarr is never unusable for these reasons
        file = job.rec.path.name
    return Outcome(job.name, None, 0, quarantine_entry(file, exc))


# --------------------------------------------------------------------------- running the tasks


def _worker_init(environment: dict[str, str], calibration: str | None = None) -> None:
    """Worker processes: take the main process's ``MSCAL_*`` settings (``environment``,
    :func:`pipeline.apply.execution.worker_environment`), die with the parent (a killed run
    leaves no writer behind), keep Blosc single-threaded (the workers already fill the
    cores), reuse freed memory (:func:`reuse_freed_memory`), and load the Eq. 15 tables of
    ``calibration`` if given (:func:`warm_calibration`): while the main process still makes
    the output stores and the plan, not when the first frame arrives (0.1 s of a 600-frame
    apply's start)."""
    take_worker_environment(environment)
    die_with_parent()
    reuse_freed_memory()
    try:
        from numcodecs import blosc

        blosc.set_nthreads(1)
    except ImportError:  # pragma: no cover
        pass
    if calibration is not None:
        warm_calibration(calibration)


#: Frames handed to the scheduler at a time (:meth:`Runner.run`): large enough that the
#: workers' wait at the end of a window (at most one frame each) is noise, small enough that
#: the task graph's memory stays flat over any flight.
RUN_WINDOW = 512


#: At most this many frames in one task (:func:`process_frames`): within a task a frame's
#: writes overlap the next frame's computing, and only the last frame's are waited for
#: with nothing to compute meanwhile.
FRAMES_PER_TASK = 8


def frames_per_task(n_jobs: int, parallelism: int) -> int:
    """Frames per task for ``n_jobs`` jobs on ``parallelism`` workers: up to
    ``FRAMES_PER_TASK``, and at least four tasks per worker (a short flight, or the end of a
    window, keeps every worker busy to the end)."""
    return max(1, min(FRAMES_PER_TASK, n_jobs // (4 * max(1, parallelism))))


#: Tasks given to the process pool per worker beyond the one whose outcome is waited for
#: (:meth:`Runner.stream`): every worker always has its next task while the outcomes are
#: taken in job order; a task's outcomes are small.
TASKS_AHEAD = 3


def _results(item: tuple[Future, bool]) -> list[Any]:
    fut, many = item
    result = fut.result()
    return list(result) if many else [result]


class Runner:
    """Runs the per-frame tasks on the caller's ``distributed`` client if one is active (dask
    graphs), else on worker processes (long flights: straight to the process pool) or threads
    (dask's threaded scheduler); see :func:`scheduler_for`.
    Worker processes are forked when the runner is made, from a server that
    :func:`pipeline.apply.execution.start_worker_server` may have started earlier (its imports
    then ran beside the main process's); each takes the main process's ``MSCAL_*`` settings of
    now (:func:`pipeline.apply.execution.worker_environment`). Given ``calibration`` (the
    store whose Eq. 15 tables the frames use), each worker loads its tables as it starts;
    ``pixels``: a capture's output pixels (:func:`pipeline.apply.execution.capture_pixels`),
    which may add a spare worker (:func:`pipeline.apply.execution.spare_workers`)."""

    def __init__(self, n_frames: int, execution: Execution = Execution(), calibration: str | Path | None = None,
                 pixels: int = 0):
        execution.install()
        reuse_freed_memory()  # the threads scheduler's frames run in this process
        self.client = distributed_client()
        self.pool: ProcessPoolExecutor | None = None
        self.scheduler, self.workers = ("distributed", 0) if self.client is not None else scheduler_for(n_frames, execution, pixels)
        if self.scheduler == "processes":
            try:
                self.pool = start_pool(self.workers, worker_context, _worker_init,
                                       (worker_environment(), None if calibration is None else str(calibration)))
            except ProcessesUnavailable as exc:
                if execution.scheduler == "processes":  # asked for: say so, and how to run instead
                    raise ProcessesUnavailable(
                        exc.reason, hint="run on threads: --scheduler threads, or MSCAL_APPLY_SCHEDULER=threads") from exc
                # chosen here (auto): the same outputs on threads, only slower
                log.warning("%s: running on %d threads instead", exc.reason, self.workers)
                self.scheduler = "threads"
        self.execution = execution.record(self.scheduler, self.workers)

    def run(self, plan: Any, jobs: Iterable[Any], fn: Callable[[Any, Any], Any] | None = None) -> list[Any]:
        """The outcome of every job, in job order (:meth:`stream`, collected)."""
        return list(self.stream(plan, jobs, fn))

    def stream(self, plan: Any, jobs: Iterable[Any], fn: Callable[[Any, Any], Any] | None = None) -> Iterator[Any]:
        """The outcome of every job, in job order, each as soon as it and those before it are
        done: :func:`process_frames` on runs of up to ``FRAMES_PER_TASK`` jobs
        (:func:`frames_per_task`), or, given ``fn``, ``fn(plan, job)`` one job a task.

        ``jobs`` (may be a generator) is drawn ``RUN_WINDOW`` jobs at a time: one dask graph
        for every frame (the tasks, their keys, the scheduler's state) grew with the flight,
        and a 5,000-frame flight of small frames peaked at 436 MiB against 393 MiB with
        windows. On worker processes the tasks go to the pool directly, at most
        :data:`TASKS_AHEAD` per worker beyond the outcome being waited for, with no barrier
        between windows or between the caller's steps: a caller that commits every 64 frames
        lets the workers compute on meanwhile (with a dask graph per batch, both workers
        waited at the end of each batch for the slower one and for the commit). Closing the
        iterator early (or an error) cancels the tasks not started and waits for the others:
        nothing is left writing behind the caller."""
        runs = self._runs(jobs, fn)
        if self.pool is None:
            for f, window, many in runs:
                for result in self._run_window(plan, window, f):
                    yield from (result if many else (result,))
            return
        ahead: deque[tuple[Future, bool]] = deque()
        limit = TASKS_AHEAD * max(1, self.workers)
        try:
            for f, window, many in runs:
                for arg in window:
                    ahead.append((self.pool.submit(f, plan, arg), many))
                    while len(ahead) > limit:
                        yield from _results(ahead.popleft())
            while ahead:
                yield from _results(ahead.popleft())
        finally:
            for fut, _ in ahead:
                fut.cancel()
            futures_wait([fut for fut, _ in ahead])

    def _runs(self, jobs: Iterable[Any], fn: Callable[[Any, Any], Any] | None
              ) -> Iterator[tuple[Callable[[Any, Any], Any], list[Any], bool]]:
        """``(function, its task arguments, whether each returns a list of outcomes)`` per
        window of ``RUN_WINDOW`` jobs, drawn from ``jobs`` one window at a time."""
        it = iter(jobs)
        while window := list(itertools.islice(it, RUN_WINDOW)):
            if fn is not None:
                yield fn, window, False
                continue
            size = frames_per_task(len(window), self.parallelism())
            yield process_frames, [window[k:k + size] for k in range(0, len(window), size)], True

    def parallelism(self) -> int:
        """Tasks that run at once: the local workers, or the client's threads."""
        if self.client is not None:
            try:
                return max(1, sum(self.client.nthreads().values()))
            except Exception:  # a client that cannot say: one task a frame spreads best
                return RUN_WINDOW
        return max(1, self.workers)

    def _run_window(self, plan: Any, jobs: list[Any], fn: Callable[[Any, Any], Any]) -> list[Any]:
        # arguments wrapped whole: dask would otherwise walk every dataclass field of every
        # argument of every task looking for collections (15 ms a task)
        token = uuid.uuid4().hex
        plan_d = dask.delayed(plan, traverse=False, name=f"mscal-plan-{token}")
        tasks = [
            dask.delayed(fn, pure=False)(plan_d, dask.delayed(job, traverse=False, name=f"mscal-job-{token}-{k}"))
            for k, job in enumerate(jobs)
        ]
        if self.client is not None:
            return list(dask.compute(*tasks))
        # the schedulers' functions, not their names: a name makes dask import distributed
        # (0.2 s) to look for a client, which distributed_client has done already
        return list(dask.compute(*tasks, scheduler=dask.threaded.get, num_workers=self.workers))

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None

    def __enter__(self) -> "Runner":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


