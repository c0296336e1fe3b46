"""The exposure sweep (``response/``): its frames read and its per-band fits (Eq. 5-7) handed
to the band workers, with light imports only (numpy, the session reader, the pool).

``mscal calibrate`` starts the sweep's fits here, before it imports the rest of the
calibration (xarray, zarr: about a second on one core), so the workers fit while the main
process imports; :func:`pipeline.calibrate.response_stage.fit_response_frames` collects them (or
submits them itself when nothing was started).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from mscal_core.errors import FitError, SessionError

from pipeline.calibrate.bands import response_band
from pipeline.calibrate.pool import BandPool
from pipeline.ingest.captures import read_frames
from pipeline.ingest.catalog import Camera
from pipeline.ingest.session import FRAMES_CSV, FrameRecord, load_session, read_bands


def read_stack(records: Sequence[FrameRecord], camera: Camera) -> np.ndarray:
    """All frames as ``(frame, band, H, W)`` uint16; frames of different shape are an error."""
    first = read_bands(records[0], camera)
    out = np.empty((len(records), *first.shape), dtype=np.uint16)
    out[0] = first
    for i, rec in enumerate(records[1:], start=1):
        b = read_bands(rec, camera)
        if b.shape != first.shape:
            raise SessionError(
                f"frame size {b.shape[1:]} differs from {records[0].path.name}'s {first.shape[1:]}",
                path=rec.path,
            )
        out[i] = b
    return out


@dataclass(frozen=True)
class SweepFits:
    """A sweep folder's frames and its band fits on their way: the folder and method they were
    started for, the records, each band's exposures, one future per band of
    :func:`pipeline.calibrate.bands.response_band`'s result, and when the reading started
    (``time.perf_counter``: the stage's time counts from there)."""

    folder: Path
    method: str
    records: list[FrameRecord]
    exposures: list[np.ndarray]
    futures: list[Future]
    started: float

    def is_for(self, folder: Path, method: str) -> bool:
        """Whether these are the fits of ``folder`` with ``method``."""
        return self.method == method and Path(self.folder).resolve() == Path(folder).resolve()


def submit_sweep(folder: Path, camera: Camera, method: str, pool: BandPool) -> SweepFits:
    """Read the sweep folder (frames.csv + frames) and submit every band's fit to ``pool``;
    :class:`FitError` naming frames.csv when it has fewer than 2 distinct exposures."""
    started = time.perf_counter()
    recs = read_frames(folder, camera)
    exposures = np.array([r.effective_exposure for r in recs])
    if np.unique(exposures).size < 2:
        raise FitError(
            f"the sweep has {np.unique(exposures).size} distinct exposure(s); the response fit needs at least 2",
            path=folder / FRAMES_CSV,
            hint="capture the static scene at several exposure times",
        )
    stack = read_stack(recs, camera)
    nb = stack.shape[1]
    # a multi-lens camera exposes each lens
    exposures_b = [np.array([r.band_exposure(b) for r in recs]) for b in range(nb)]
    futures = [pool.submit(response_band, stack[:, b], exposures_b[b], camera.bit_depth, method) for b in range(nb)]
    return SweepFits(Path(folder), method, recs, exposures_b, futures, started)


def start_sweep(session_dir: str | os.PathLike[str], method: str, pool: BandPool) -> SweepFits:
    """:func:`submit_sweep` of a session folder's ``response/``."""
    session = load_session(session_dir)
    return submit_sweep(session.response_dir, session.camera, method, pool)
