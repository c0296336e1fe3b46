"""The one apply driver: every camera's apply runs the same steps, in the same order, here.

1. ``OUT`` made, temporaries of a killed run removed;
2. the source says whether ``OUT/run.json`` already holds this run (:meth:`Source.up_to_date`:
   by the frames' content, :func:`pipeline.apply.record.up_to_date`); then nothing is written;
3. otherwise ``run.json`` is removed (until the new one is written last nothing in ``OUT``
   claims to be complete) and outputs of an earlier run that this run's products leave out;
4. the source prepares its pass (:meth:`Source.prepare`: the light reference, the bands'
   alignment; reads that come before the workers start) and runs it on one
   :class:`pipeline.apply.executor.Runner` (:meth:`Source.run_pass`): the executor writes each
   frame's chunks of the stores (under temporary names) and its TIFFs;
5. the stores are renamed into place and ``run.json`` (:func:`pipeline.apply.record.run_record`,
   one schema for every camera; the source's own keys in ``Done.parts``) is written last.

A source is one kind of input: a snapshot flight ingested into ``raw.zarr``
(:class:`pipeline.apply.flight.SnapshotFlight`) or a folder of captures
(:class:`pipeline.apply.captures.CaptureSource`, with a field calibration store or with the
factory chain of :mod:`pipeline.apply.factory`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, Sequence

import xarray as xr

from pipeline.apply.execution import Execution, capture_pixels
from pipeline.apply.executor import Outcome, Runner
from pipeline.apply.options import ApplyResult
from pipeline.apply.products import remove_unchosen
from pipeline.apply.quality import Flagging
from pipeline.apply.record import forget_run, run_record, write_run_record
from pipeline.ingest.catalog import Camera
from pipeline.ingest.products import Products
from pipeline.storage.atomic import install_folder, remove_temporaries


@dataclass
class Done:
    """What a source's pass made, for the driver to install and record."""

    outcomes: Sequence[Outcome]  # one per frame written, in frame order
    stores: Sequence[tuple[Path, str]]  # (temporary path, name in OUT), renamed into place in this order
    quarantined: list[dict[str, str]]  # [{file, reason}]
    calibration: str  # run.json "calibration": a store's path or "factory"
    calibration_sha256: str | None
    frames_sha256: dict[str, str]  # frame -> content hash
    fingerprint: dict[str, Any]  # with the frames' content (:func:`pipeline.apply.record.content_fingerprint`)
    outputs: dict[str, str]  # run.json "outputs": kind -> path under OUT
    products: dict[str, Any]  # run.json "products"
    export: Sequence[int]  # the bands of the TIFFs
    metadata_problems: Sequence[dict[str, Any]] = ()
    parts: dict[str, Any] | None = None  # run.json keys of this kind of input, flat (nested by run_record)
    flagging: Flagging | None = None  # the run's quality mask, checked (:func:`pipeline.apply.quality.checked`)


class Source(Protocol):
    """One kind of input of apply (see the module docstring)."""

    folder: Path  # run.json "flight"
    camera: Camera
    products: Products
    execution: Execution
    calib: xr.Dataset | None  # the calibration store as read (ApplyResult.calibration); None: factory

    def up_to_date(self, out: Path) -> dict[str, Any] | None:
        """The previous run's record when it made the outputs of exactly these inputs (by
        content) and options, with this run's ``quarantined``; else None."""

    def prepare(self, out: Path) -> tuple[int, Path | None]:
        """Everything decided before the workers start; returns the number of frames and the
        calibration store the workers load (None: none)."""

    def run_pass(self, out: Path, runner: Runner) -> Done:
        """The pass over the frames on ``runner``; the stores under temporary names."""


def drive(source: Source, out: Path, t_start: float) -> ApplyResult:
    """Apply ``source`` into ``out`` (see the module docstring). ``t_start``:
    ``time.perf_counter()`` when the apply began (run.json ``timings_s.total``); the
    ``timings_s.pass`` counts from the up-to-date check (every read of the inputs) to the
    last frame written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_temporaries(out)
    t0 = time.perf_counter()
    previous = source.up_to_date(out)
    if previous is not None:
        return ApplyResult(out, previous, up_to_date=True, quarantined=previous.get("quarantined", []),
                           calibration=source.calib)
    forget_run(out)
    remove_unchosen(out, source.products)
    n_frames, warm = source.prepare(out)
    with Runner(n_frames, source.execution, calibration=warm, pixels=capture_pixels(source.camera)) as runner:
        done = source.run_pass(out, runner)
    t_pass = time.perf_counter() - t0
    for tmp, name in done.stores:
        install_folder(tmp, out / name)
    record = run_record(
        flight=source.folder, camera=source.camera, calibration=done.calibration,
        calibration_sha256=done.calibration_sha256, outcomes=done.outcomes, frames_sha256=done.frames_sha256,
        quarantined=done.quarantined, metadata_problems=done.metadata_problems, outputs=done.outputs,
        products=done.products, export=done.export, runner=runner, t_pass=t_pass, t_start=t_start,
        fingerprint=done.fingerprint, parts=done.parts or {}, flagging=done.flagging)
    write_run_record(out, record)  # last: a run.json names a finished pass
    return ApplyResult(out, record, up_to_date=False, quarantined=done.quarantined, calibration=source.calib)
