"""The session calibration: the three stages run in order on one set of band workers, and the
calibration store written with its provenance; ``mscal calibrate`` and ``mscal fit
response|vignetting|illumination``.

I/O and bookkeeping only; the maths is in ``mscal_core``. The stages are
:mod:`pipeline.calibrate.response_stage` (Eq. 5-7), :mod:`pipeline.calibrate.vignetting_stage`
(Eq. 8-10) and :mod:`pipeline.calibrate.illumination_stage` (Eq. 11-14); each returns the fits
and a report (:class:`pipeline.calibrate.stage.StageReport`: inputs with content hashes, frames
skipped and why, residuals, timings) that goes into the store's provenance.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import mscal_core
import numpy as np
import xarray as xr
from mscal_core.errors import SessionError

from pipeline.calibrate.illumination_stage import add_illumination, fit_illumination_frames, read_reflector_frames
from pipeline.calibrate.intrinsics import add_intrinsics, with_intrinsics
from pipeline.calibrate.pool import BandPool, pool_or_own
from pipeline.calibrate.response_stage import fit_response_frames, response_dataset
from pipeline.calibrate.sweep import SweepFits
from pipeline.calibrate.views import read_folder_frames
from pipeline.calibrate.vignetting_stage import add_vignetting, fit_vignetting_frames
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.session import Session, load_session
from pipeline.storage.store import open_calibration, write_store

log = logging.getLogger("mscal.calibrate")


def provenance(ds: xr.Dataset, session_root: Path | None) -> xr.Dataset:
    ds.attrs.update(
        {
            "mscal_version": mscal_core.__version__,
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "session": str(session_root) if session_root else "",
            "fits": [k for k in ("response", "vignetting", "illumination") if k in ds.attrs],
        }
    )
    return ds


#: Steps of :func:`calibrate_session` that call its ``advance``: the three fits and the write.
CALIBRATE_STEPS = 4


def calibrate_session(session_dir: str | Path, out: str | Path, *, response_method: str = "forward",
                      calibration: str | Path | None = None, advance: Callable[[], None] | None = None,
                      pool: BandPool | None = None, sweep: SweepFits | None = None,
                      workers: int | None = None) -> xr.Dataset:
    """``mscal calibrate``: the three fits from a session folder, written to ``out``.
    ``calibration``: a store whose ``intrinsics`` (``mscal fit intrinsics``) are used when
    session.yaml gives none (nothing else is taken from it). ``advance``: called after each
    of :data:`CALIBRATE_STEPS` steps (a progress bar). ``pool``: the band fits' workers,
    started by the caller (a pool of its own if None, of ``workers`` processes: 0 one per
    core, 1 none, None ``MSCAL_CALIBRATE_WORKERS`` or one per core, see
    :func:`pipeline.calibrate.pool.band_workers`; :func:`pipeline.calibrate.pool.session_pool`
    makes one), closed here once the band fits are done;
    ``sweep``: the response fits already submitted to it
    (:func:`pipeline.calibrate.sweep.start_sweep`)."""
    advance = advance or (lambda: None)
    session = load_session(session_dir)
    camera = session.camera
    partial = open_calibration(calibration, camera) if calibration is not None else None
    session, source = with_intrinsics(session, partial)
    # one set of workers for both per-band stages; the vignetting frames are read (and
    # hashed) on a thread while the workers fit the response
    with pool_or_own(pool, camera.n_bands, workers) as pool, ThreadPoolExecutor(1) as aside:
        # what does not wait for the fits is done aside, while the workers fit: the vignetting
        # frames are read during the response fits (the marker search needs them next); the
        # response's part of the store and the reflector frames are made during the vignetting
        # fits, once the marker search (which competes for this process) is done
        views_ahead = aside.submit(read_folder_frames, session, session.vignetting_dir)
        log.info("response: fitting %d bands from %s", camera.n_bands, session.response_dir)
        rfits, rrep = fit_response_frames(session.response_dir, camera, response_method, session.root, pool, sweep)
        advance()
        later: list[Future] = []

        def meanwhile() -> None:
            later.extend([aside.submit(response_dataset, camera, rfits, rrep),
                          aside.submit(read_reflector_frames, session)])

        U = np.stack([f.inverse_response for f in rfits])  # the store's inverse_response and saturation_dn
        sat = np.array([f.saturation_dn for f in rfits], dtype=np.int32)
        log.info("vignetting: fitting from %s", session.vignetting_dir)
        vfits, vrep = fit_vignetting_frames(session, U, sat, pool, frames=views_ahead.result, started=meanwhile)
        ds, reflector = (f.result() for f in later)
        # the band fits are done: the vignetting frames (180 MB on the full synthetic session)
        # and the workers (their freed memory kept for reuse) are let go before the
        # illumination fit and the store, the peak's moment
        views_ahead = None
        pool.close()
    ds = add_vignetting(ds, vfits, vrep)
    advance()
    log.info("illumination: fitting from %s", session.reflector_dir)
    ires = fit_illumination_frames(session, U, sat, ds["vignetting"].values, frames=lambda: reflector,
                                   vignetting_observed=observed_vignetting(ds))
    ds = add_illumination(ds, ires)
    advance()
    ds = add_intrinsics(ds, session, source)
    ds = provenance(ds, session.root)
    write_store(ds, out)
    advance()
    return ds


def observed_vignetting(ds: xr.Dataset) -> np.ndarray | None:
    """The store's ``vignetting_observed`` (band, y, x), None when it has none."""
    return ds["vignetting_observed"].values if "vignetting_observed" in ds else None


def _session_or_folder(path: Path) -> tuple[Path, Session | None]:
    if (path / "session.yaml").is_file():
        session = load_session(path)
        return session.response_dir, session
    return path, None


def fit_response_cli(path: str | Path, out: str | Path, camera_name: str | None, method: str) -> xr.Dataset:
    """``mscal fit response DIR``: DIR is a frame folder with frames.csv, or a session."""
    folder, session = _session_or_folder(Path(path))
    if session is not None:
        if camera_name and camera_name != session.camera.name:
            raise SessionError(
                f"--camera {camera_name} contradicts session.yaml's camera {session.camera.name}",
                path=session.root / "session.yaml",
            )
        camera = session.camera
    else:
        if not camera_name:
            raise SessionError("--camera NAME is required for a frame folder", path=folder)
        camera = load_camera(camera_name)
    fits, report = fit_response_frames(folder, camera, method, session.root if session else folder)
    ds = provenance(response_dataset(camera, fits, report), session.root if session else None)
    write_store(ds, out)
    return ds


def fit_stage_cli(stage: str, session_dir: str | Path, out: str | Path, partial: str | Path | None,
                  response_method: str = "forward") -> xr.Dataset:
    """``mscal fit vignetting|illumination SESSION``: fits that stage; earlier stages come from
    ``--calibration PARTIAL.zarr`` when given, otherwise they are fitted too."""
    session = load_session(session_dir)
    camera = session.camera
    source = "session.yaml"
    if partial is not None:
        ds = open_calibration(partial, camera, need=stage)
        session, source = with_intrinsics(session, ds)
        keep = ["inverse_response", "black_level", "saturation_dn", "response_uncertainty", "response_dn_range"] + (
            ["vignetting", "vignetting_count", "vignetting_observed", "vignetting_coverage"]
            if stage == "illumination" else [])
        ds = ds[[v for v in keep if v in ds]]
    else:
        rfits, rrep = fit_response_frames(session.response_dir, camera, response_method, session.root)
        ds = response_dataset(camera, rfits, rrep)
    U = ds["inverse_response"].values
    sat = ds["saturation_dn"].values if "saturation_dn" in ds else np.full(camera.n_bands, camera.dn_max)
    if stage == "vignetting" or "vignetting" not in ds:
        vfits, vrep = fit_vignetting_frames(session, U, sat)
        ds = add_vignetting(ds, vfits, vrep)
    if stage == "illumination":
        ds = add_illumination(ds, fit_illumination_frames(session, U, sat, ds["vignetting"].values,
                                                          vignetting_observed=observed_vignetting(ds)))
    session, source = with_intrinsics(session) if source == "session.yaml" else (session, source)
    ds = add_intrinsics(ds, session, source)
    ds = provenance(ds, session.root)
    write_store(ds, out)
    return ds


#: The fits in dependency order: each needs the stores of the ones before it.
STAGES = ("response", "vignetting", "illumination")


def fit_stage(stage: str, session_dir: str | Path, out: str | Path, partial: str | Path | None = None,
              response_method: str = "forward") -> xr.Dataset:
    """One stage of a session's calibration into ``out``: ``response`` from the session's
    sweep; ``vignetting`` and ``illumination`` on top of ``partial``, the store of the stage
    before (the post-flight flow caches each stage's store, so a changed input re-fits only
    the stages that depend on it)."""
    if stage == "response":
        return fit_response_cli(session_dir, out, None, response_method)
    if stage not in STAGES:
        raise ValueError(f"unknown calibration stage {stage!r}; stages: {', '.join(STAGES)}")
    return fit_stage_cli(stage, session_dir, out, partial, response_method)
