"""The session calibration: read the three calibration folders and run the three fits.

I/O and bookkeeping only; the maths is in ``mscal_core``. Each stage returns the fits and a
report (inputs with content hashes, frames skipped and why, residuals, timings) that goes
into the store's provenance.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import mscal_core
import numpy as np
import xarray as xr
from mscal_core import charuco, geometry, illumination, marker, response, vignetting
from mscal_core.errors import FitError, MscalError, SessionError
from mscal_core.mosaic import band_offsets

from pipeline.calibrate.bands import (
    BandViews,
    band_observations,
    energy,
    lens_vignetting_band,
    vignetting_band,
)
from pipeline.calibrate.intrinsics import fit_intrinsics_folder, parse_board, store_intrinsics
from pipeline.calibrate.pool import BandPool, band_workers
from pipeline.calibrate.sweep import SweepFits, read_stack, submit_sweep
from pipeline.ingest.captures import is_multilens, read_frames
from pipeline.ingest.catalog import Camera, load_camera
from pipeline.ingest.exif import NAT, time_ns
from pipeline.ingest.intrinsics import band_intrinsics_from_files, intrinsics_from_array
from pipeline.ingest.session import (
    FRAMES_CSV,
    IMAGE_SUFFIXES,
    FrameRecord,
    MarkerSpec,
    Session,
    load_session,
    read_frame_table,
)
from pipeline.ingest.sunsensor import SUN_SENSOR_MODEL, SUN_SENSOR_MODEL_ATTR, record_levels
from pipeline.storage.store import content_hashes, new_dataset, open_calibration, write_store

log = logging.getLogger("mscal.calibrate")

#: Reflector pixels closer than this to the reflector edge are not used (metres, or 2 % of
#: the reflector's smaller side if larger): they mix reflector and background.
EDGE_MARGIN_M = 0.01
#: Views are only screened for a wrong marker pose when at least this many remain.
MIN_VIEWS_TO_SCREEN = 12
#: Extra margin around the marker's white paper border (metres).
MARKER_MARGIN_M = 0.005


@dataclass
class StageReport:
    stage: str
    inputs: dict[str, str] = field(default_factory=dict)
    skipped: list[dict[str, str]] = field(default_factory=list)
    residuals: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    def as_attrs(self) -> dict[str, Any]:
        return {
            "inputs": self.inputs,
            "skipped": self.skipped,
            "residuals": self.residuals,
            "seconds": round(self.seconds, 3),
        }


def _workers() -> int:
    import os

    return max(1, min(4, os.cpu_count() or 1))


def _map(fn: Callable[[int], Any], n: int) -> list[Any]:
    """Run ``fn(0..n-1)`` on a small thread pool (numpy/OpenCV/scipy release the GIL)."""
    with ThreadPoolExecutor(max_workers=_workers()) as ex:
        return list(ex.map(fn, range(n)))


@contextmanager
def _pool(pool: BandPool | None, n_tasks: int, workers: int | None = None) -> Iterator[BandPool]:
    """``pool``, or a pool of its own for ``n_tasks`` band fits (``workers``:
    :func:`pipeline.calibrate.pool.band_workers`), closed on leaving."""
    if pool is not None:
        yield pool
        return
    with BandPool(band_workers(n_tasks, workers)) as own:
        yield own


# --------------------------------------------------------------------------- response (Eq. 5-7)


def fit_response_frames(
    folder: Path, camera: Camera, method: str = "forward", root: Path | None = None, pool: BandPool | None = None,
    sweep: SweepFits | None = None,
) -> tuple[list[response.ResponseFit], StageReport]:
    """Eq. 5-7 per band from an exposure sweep folder (frames.csv + frames); the bands are
    fitted on ``pool``'s workers (a pool of its own if None). ``sweep``: the same folder's fits
    already submitted (:func:`pipeline.calibrate.sweep.submit_sweep`, same method)."""
    t0 = time.perf_counter()
    report = StageReport("response")
    with _pool(pool, camera.n_bands) as p:
        if sweep is None or not sweep.is_for(Path(folder), method):
            sweep = submit_sweep(Path(folder), camera, method, p)
        recs, exposures_b = sweep.records, sweep.exposures
        report.inputs = content_hashes(record_files(recs), root or folder)
        results = [f.result() for f in sweep.futures]
    fits = []
    for b, (bad, fit) in enumerate(results):
        if bad:
            names = ", ".join(f"{recs[i].path.name} ({exposures_b[b][i]:g} ms)" for i in bad[:3])
            raise FitError(
                f"band {camera.bands[b].name}: brightness contradicts exposure for {names}",
                path=folder / "frames.csv",
                hint="check exposure_ms of these frames, or remove frames taken while the scene or light changed",
            )
        fits.append(fit)
    report.residuals = {
        "method": method,
        "residual_rms_dn": [round(f.residual_rms_dn, 4) for f in fits],
        "black_level": [round(f.black_level, 3) for f in fits],
        "observed_dn": [list(map(int, f.observed_dn)) for f in fits],
    }
    report.seconds = time.perf_counter() - min(t0, sweep.started)
    return fits, report


def response_dataset(camera: Camera, fits: Sequence[response.ResponseFit], report: StageReport) -> xr.Dataset:
    ds = new_dataset(camera)
    ds["inverse_response"] = (
        ("band", "dn"),
        np.stack([f.inverse_response for f in fits]),
        {"long_name": "inverse camera response U(k) (Eq. 5-7)", "units": "linear DN", "method": fits[0].method},
    )
    ds["black_level"] = ("band", np.array([f.black_level for f in fits]), {"units": "DN"})
    ds["saturation_dn"] = ("band", np.array([f.saturation_dn for f in fits], dtype=np.int32))
    ds.coords["dn"] = np.arange(2**camera.bit_depth, dtype=np.int32)
    if all(f.residual_by_dn is not None for f in fits):
        n_bins = len(fits[0].residual_by_dn)
        ds.coords["dn_bin"] = ("dn_bin", (np.arange(n_bins) + 0.5) * 2**camera.bit_depth / n_bins,
                               {"long_name": "centre of a DN bin of the response residual", "units": "DN"})
        ds["response_residual"] = (("band", "dn_bin"), np.stack([f.residual_by_dn for f in fits]),
                                   {"long_name": "rms of the sweep's fit residual I - C(t E) per DN bin (Eq. 5)",
                                    "units": "DN"})
    ds.attrs["response"] = report.as_attrs()
    return ds


# --------------------------------------------------------------------------- marker views


@dataclass(frozen=True)
class View:
    """A frame whose marker was found: its pose (of the band grid; of a multi-lens camera:
    the first band that found it) and, for a multi-lens camera, each lens's own pose (None
    where that band did not find the marker)."""

    record: FrameRecord
    pose: geometry.Pose
    band_poses: tuple[geometry.Pose | None, ...] | None = None
    #: How the pose was chosen between the two IPPE solutions (of a multi-lens camera: per band).
    choice: marker.PoseChoice | None = None
    band_choices: tuple[marker.PoseChoice | None, ...] | None = None

    def pose_for(self, band: int) -> geometry.Pose | None:
        return self.pose if self.band_poses is None else self.band_poses[band]

    def choice_for(self, band: int) -> marker.PoseChoice | None:
        return self.choice if self.band_choices is None else self.band_choices[band]


def record_files(records: Sequence[FrameRecord]) -> list[Path]:
    """Every file of the frames (a multi-lens capture has one per band)."""
    return [f for r in records for f in r.files]


# --------------------------------------------------------------------------- intrinsics


def with_intrinsics(session: Session, store: xr.Dataset | None = None,
                    records: Sequence[FrameRecord] | None = None) -> tuple[Session, str]:
    """The session with its intrinsics per band resolved, and where they came from:
    session.yaml (one for all bands, or per band) first, else the store's ``intrinsics``
    (``mscal fit intrinsics``), else board images in ``SESSION/intrinsics/`` (with its
    ``board.yaml``, fitted as ``mscal fit intrinsics`` does), else the band files' own
    metadata (MicaSense and Sentera perspective XMP, DJI DewarpData; the first capture of
    ``records``, else of ``vignetting/``).
    :class:`SessionError` if none gives them."""
    if session.intrinsics is not None or session.band_intrinsics is not None:
        return session, "session.yaml"
    camera = session.camera
    if store is not None and "intrinsics" in store:
        intr = intrinsics_from_array(store["intrinsics"].values)
        if len(intr) != camera.n_bands:
            raise SessionError(f"the store's intrinsics have {len(intr)} bands, camera {camera.name} {camera.n_bands}",
                               path=session.root / "session.yaml")
        return _set_intrinsics(session, intr), "calibration store"
    board_dir = session.root / "intrinsics"
    if (board_dir / "board.yaml").is_file():
        return _set_intrinsics(session, board_intrinsics(board_dir, camera)), "board images in intrinsics/"
    if records is None:
        try:
            records = read_frames(session.vignetting_dir, camera) if session.vignetting_dir.is_dir() else []
        except MscalError:  # a folder that cannot be read as frames: no metadata to take them from
            records = []
    for rec in list(records)[:1]:  # band files (multi-lens), or one file of all bands (Sentera JPEG)
        intr = band_intrinsics_from_files(rec.files, camera.n_bands)
        if intr is not None:
            return _set_intrinsics(session, intr), f"metadata of {rec.name}"
    raise SessionError(
        "intrinsics are missing",
        path=session.root / "session.yaml",
        hint="add intrinsics: {fx, fy, cx, cy, dist} (or one such mapping per band name), or pass "
             "--calibration with a store from 'mscal fit intrinsics'",
    )


def board_intrinsics(folder: Path, camera: Camera) -> tuple[geometry.Intrinsics, ...]:
    """:func:`pipeline.calibrate.intrinsics.fit_intrinsics_folder` of a session's board folder,
    fitted once per content (every stage of a calibration asks)."""
    stamp = tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file())
    return _board_intrinsics(str(folder), camera.name, stamp)


@functools.lru_cache(maxsize=8)
def _board_intrinsics(folder: str, camera_name: str, stamp: tuple) -> tuple[geometry.Intrinsics, ...]:
    import yaml

    path = Path(folder) / "board.yaml"
    board = parse_board(yaml.safe_load(path.read_text()), path)
    intr, _ = fit_intrinsics_folder(folder, load_camera(camera_name), board)
    return tuple(intr)


def _set_intrinsics(session: Session, intr: Sequence[geometry.Intrinsics]) -> Session:
    if is_multilens(session.camera):
        return dataclasses.replace(session, band_intrinsics=tuple(intr))
    return dataclasses.replace(session, intrinsics=intr[0])  # the band grid's, one for all bands


def add_intrinsics(ds: xr.Dataset, session: Session, source: str) -> xr.Dataset:
    """The intrinsics the fits used, per band: ``intrinsics (band, intrinsics_param)``."""
    intr = [session.intrinsics_for(b) for b in range(session.camera.n_bands)]
    if any(i is None for i in intr):
        return ds
    return store_intrinsics(ds, intr, source)  # type: ignore[arg-type]


def detection_image(bands: np.ndarray, inverse_response: np.ndarray) -> np.ndarray:
    """A single image for marker detection: the mean of the linearised bands, each scaled by
    its median so that no band dominates."""
    u = np.asarray(inverse_response)
    if bands.dtype.kind == "u" and bool(np.all(np.diff(u, axis=1) >= 0)):
        # U is monotone (it always is: Eq. 6 fits are made so): the median of U(I) is U at the
        # median DN, read off the DN histogram (no sort), and U(I) / median is a look-up in the
        # table U / median. The bands are summed in order, as mean(axis=0) does: same numbers.
        acc = np.zeros(bands.shape[1:], dtype=np.result_type(u.dtype, np.float64))
        for b in range(bands.shape[0]):
            med = _monotone_median(bands[b], u[b])
            acc += (u[b] / (med if med > 0 else 1.0))[bands[b]]
        return (acc / bands.shape[0]).astype(np.float32)
    lin = np.take_along_axis(u, bands.reshape(bands.shape[0], -1).astype(np.intp), axis=1)
    lin = lin.reshape(bands.shape)
    med = np.median(lin.reshape(lin.shape[0], -1), axis=1)
    med[med <= 0] = 1.0
    return (lin / med[:, None, None]).mean(axis=0).astype(np.float32)


def _monotone_median(dn: np.ndarray, table: np.ndarray) -> float:
    """``np.median(table[dn])`` for a non-decreasing ``table``: the table at the middle DN(s)."""
    c = np.cumsum(np.bincount(dn.ravel(), minlength=table.size))
    n = int(c[-1])
    hi = table[np.searchsorted(c, n // 2, side="right")]
    if n % 2:
        return hi
    return (table[np.searchsorted(c, n // 2 - 1, side="right")] + hi) / 2


def find_views(
    records: Sequence[FrameRecord],
    stack: np.ndarray,
    session: Session,
    inverse_response: np.ndarray,
    report: StageReport,
) -> list[tuple[int, View]]:
    """Marker pose for each frame; frames where the marker is not found are skipped and reported."""
    views: list[tuple[int, View]] = []
    if is_multilens(session.camera):
        return _find_views_per_lens(records, stack, session, inverse_response, report)
    # The detection image averages all bands; its pixel (i, j) sits at the mean band offset.
    centre = _offsets(session.camera).mean(axis=0)

    outlines = _pose_outlines(session)

    def one(i: int) -> tuple[int, View] | None:
        img = detection_image(stack[i], inverse_response)
        choice = marker_pose(img, session.marker, session.intrinsics, outlines, (float(centre[0]), float(centre[1])))
        return None if choice is None else (i, View(records[i], choice.pose, choice=choice))

    for i, res in enumerate(_map(one, len(records))):
        if res is None:
            report.skipped.append(
                {"file": records[i].path.name, "reason": f"{session.marker.label} not found"}
            )
        else:
            views.append(res)
    report.residuals["marker_poses"] = [{"file": v.record.path.name, **v.choice.as_record()}  # type: ignore[union-attr]
                                        for _, v in views]
    return views


def marker_pose(img: np.ndarray, mk: MarkerSpec, intrinsics: geometry.Intrinsics, outlines: list[tuple[float, float]],
                offset: tuple[float, float] = (0.0, 0.0)) -> marker.PoseChoice | None:
    """The pose of the session's marker, or ChArUco board, in a detection image whose pixel
    ``(i, j)`` sees image point ``(j + dx, i + dy)`` (``offset``); None if it is not found (a
    board: fewer than :data:`mscal_core.charuco.MIN_CORNERS` corners, or corners on a line)."""
    if mk.board is not None:
        found = charuco.detect_charuco(img, mk.board)
        if found is None:
            return None
        try:
            return charuco.charuco_pose(found[0] + np.asarray(offset), found[1], mk.board, intrinsics)
        except FitError:
            return None
    corners = geometry.detect_marker(img, mk.dictionary, mk.id)
    if corners is None:
        return None
    return marker.pose_in_image(img, corners, mk.dictionary, mk.size_m, intrinsics, outlines, offset)


def _pose_outlines(session: Session) -> list[tuple[float, float]]:
    """Half sizes of the outlines that choose between a marker's two poses
    (:func:`mscal_core.marker.choose_pose`): the reflector's edge, the farthest from the marker
    and so where the two solutions differ most (the paper's edge, near the marker, tells
    them apart far less)."""
    w, h = geometry.size_wh(session.reflector.size_m)
    return [(w / 2, h / 2)]


def _find_views_per_lens(
    records: Sequence[FrameRecord], stack: np.ndarray, session: Session, inverse_response: np.ndarray,
    report: StageReport,
) -> list[tuple[int, View]]:
    """A multi-lens camera: the marker is found, and its pose estimated, in each band image
    with that lens's intrinsics (each lens is its own camera)."""
    camera, mk = session.camera, session.marker

    outlines = _pose_outlines(session)

    def one(i: int) -> tuple[marker.PoseChoice | None, ...]:
        choices: list[marker.PoseChoice | None] = []
        for b in range(camera.n_bands):
            img = detection_image(stack[i, b:b + 1], inverse_response[b:b + 1])
            try:
                choice = marker_pose(img, mk, session.intrinsics_for(b), outlines)  # type: ignore[arg-type]
            except FitError:
                choice = None
            choices.append(choice)
        return tuple(choices)

    views: list[tuple[int, View]] = []
    records_out: list[dict[str, Any]] = []
    for i, choices in enumerate(_map(one, len(records))):
        poses = tuple(c.pose if c is not None else None for c in choices)
        found = [p for p in poses if p is not None]
        name = records[i].name
        if not found:
            report.skipped.append({"file": name, "reason": f"{mk.label} not found in any band"})
            continue
        lost = [camera.bands[b].name for b, p in enumerate(poses) if p is None]
        if lost:
            report.skipped.append({"file": name, "reason": f"marker not found in band(s) {', '.join(lost)}: "
                                                           "the capture is used for the other bands only"})
        views.append((i, View(records[i], found[0], poses, band_choices=choices)))
        records_out.append({"file": name, "bands": [c.as_record() if c is not None else None for c in choices]})
    report.residuals["marker_poses"] = records_out
    return views


@dataclass(frozen=True)
class FolderFrames:
    """A frame folder read: its records, their band stack ``(frame, band, H, W)`` and the
    content hashes of their files (the stage report's ``inputs``)."""

    records: list[FrameRecord]
    stack: np.ndarray
    inputs: dict[str, str]


def read_folder_frames(session: Session, folder: Path) -> FolderFrames:
    """:class:`FolderFrames` of a session's frame folder (``vignetting/``)."""
    recs = read_frames(folder, session.camera)
    return FolderFrames(recs, read_stack(recs, session.camera), content_hashes(record_files(recs), session.root))


def load_marker_frames(
    session: Session, folder: Path, inverse_response: np.ndarray, report: StageReport,
    frames: FolderFrames | None = None,
) -> tuple[list[FrameRecord], np.ndarray, list[tuple[int, View]]]:
    """Frames of a marker folder (vignetting/ or reflector/; ``frames`` if already read),
    their band stacks and the views whose marker was found; :class:`FitError` naming the
    folder if it was found in none."""
    frames = frames or read_folder_frames(session, folder)
    recs, stack = frames.records, frames.stack
    report.inputs = frames.inputs
    views = find_views(recs, stack, session, inverse_response, report)
    if not views:
        raise FitError(
            f"{session.marker.label} was not found in any of the "
            f"{len(recs)} frames",
            path=folder,
            hint="check marker.dictionary and marker.id in session.yaml, and that the marker is in view and sharp",
        )
    return recs, stack, views


def _exclude_half(session: Session) -> float:
    return session.marker.size_m / 2 + session.marker.border_m + MARKER_MARGIN_M


def _edge_margin(session: Session) -> float:
    return max(EDGE_MARGIN_M, 0.02 * min(session.reflector.size_m))


def _offsets(camera: Camera) -> np.ndarray:
    if camera.layout.kind == "mosaic" and camera.layout.pattern is not None:
        return band_offsets(camera.layout.pattern)
    return np.zeros((camera.n_bands, 2))


# --------------------------------------------------------------------------- vignetting (Eq. 8-10)


def fit_vignetting_frames(
    session: Session, inverse_response: np.ndarray, saturation_dn: np.ndarray, pool: BandPool | None = None,
    frames: Callable[[], FolderFrames] | None = None, started: Callable[[], None] | None = None,
) -> tuple[list[vignetting.VignettingFit], StageReport]:
    """Eq. 8-10 per band from the session's ``vignetting/`` views; the bands are fitted on
    ``pool``'s workers (a pool of its own if None). ``frames``: gives the folder already read
    (:func:`read_folder_frames`, e.g. read ahead while the response was fitted); ``started``:
    called once the marker was searched for and the band fits are on the workers (this
    process then only waits for them)."""
    t0 = time.perf_counter()
    camera = session.camera
    report = StageReport("vignetting")
    session, _ = with_intrinsics(session)
    with _pool(pool, camera.n_bands) as p:
        recs, stack, views = load_marker_frames(session, session.vignetting_dir, inverse_response, report,
                                                frames() if frames is not None else None)
        started = started or (lambda: None)
        if is_multilens(camera):
            fits, saturated = _fit_multilens_vignetting(session, stack, views, inverse_response, saturation_dn,
                                                        report, p, started)
            views_used: Any = [sum(v.pose_for(b) is not None for _, v in views) for b in range(camera.n_bands)]
        else:
            fits, saturated, views = _fit_band_vignetting(session, stack, views, inverse_response, saturation_dn,
                                                          report, p, started)
            views_used = len(views)
    report.residuals = {
        **report.residuals,
        "views_used": views_used,
        "views_total": len(recs),
        "residual_rms": [round(float(f.residual_rms), 5) for f in fits],
        "observed_fraction": [round(float(f.observed.mean()), 4) for f in fits],
        "saturated_fraction": [round(saturated.get(b, 0.0), 6) for b in range(camera.n_bands)],
    }
    report.seconds = time.perf_counter() - t0
    return fits, report


#: The reflector's cell boxes (:func:`mscal_core.geometry.reflector_cells`) already projected,
#: by pose (rvec, tvec bytes) and intrinsics: one projection per view serves every band.
CellCache = dict[tuple[bytes, geometry.Intrinsics], "np.ndarray | None"]


def _band_views(session: Session, stack: np.ndarray, b: int, use: Sequence[tuple[int, View]],
                inverse_response: np.ndarray, saturation_dn: np.ndarray, cells: CellCache) -> BandViews:
    """Band ``b``'s vignetting views ``use`` for :func:`pipeline.calibrate.bands.vignetting_band`:
    each view's window of the band (:func:`mscal_core.geometry.reflector_window`)."""
    intr = session.intrinsics_for(b)
    offset = tuple(float(o) for o in _offsets(session.camera)[b])
    size = tuple(float(x) for x in np.broadcast_to(np.asarray(session.reflector.size_m, dtype=np.float64), (2,)))
    shape = stack.shape[2:]
    windows = []
    for _, v in use:
        pose = v.pose_for(b)
        key = (np.concatenate([pose.rvec, pose.tvec]).tobytes(), intr)  # type: ignore[union-attr]
        if key not in cells:
            cells[key] = geometry.reflector_cells(pose, intr, size)  # type: ignore[arg-type]
        windows.append(geometry.window_of_cells(cells[key], shape, offset))  # type: ignore[arg-type]
    return BandViews(
        dn=tuple(stack[i, b, rows, cols] for (i, _), (rows, cols) in zip(use, windows)),
        windows=tuple(windows), shape=shape,
        exposures=tuple(v.record.band_exposure(b) for _, v in use),
        poses=tuple(v.pose_for(b) for _, v in use),  # type: ignore[misc]
        inverse_response=inverse_response[b], saturation_dn=int(saturation_dn[b]),
        intrinsics=intr, offset=offset, size_m=size,  # type: ignore[arg-type]
        exclude_half_m=_exclude_half(session), edge_margin_m=_edge_margin(session),
        grid=vignetting.cell_grid(session.reflector.size_m),
    )


def _fit_band_vignetting(session: Session, stack: np.ndarray, views: list[tuple[int, View]],
                         inverse_response: np.ndarray, saturation_dn: np.ndarray, report: StageReport,
                         pool: BandPool, started: Callable[[], None]
                         ) -> tuple[list[vignetting.VignettingFit], dict[int, float], list[tuple[int, View]]]:
    """Eq. 8-10 of a band-grid camera (one pose per view for all bands): the views are
    screened on one band first, then every band is fitted on the views kept, on ``pool``.

    Only the workers that would otherwise idle while the reference band is screened start
    other bands on all views (none with one worker); the rest wait for the screening. A band
    fitted on all views is fitted again if a view is dropped, from its first fit's V (the
    alternation then needs a few sweeps, no log-domain start): a session with a wrong marker
    pose costs a few band fits more, not every band twice."""
    camera = session.camera
    saturated: dict[int, float] = {}  # band -> saturated fraction of its reflector pixels (QA report)
    # Screen the views on one band first: a view whose marker pose is wrong (planar-pose
    # ambiguity, a mis-detected corner) disagrees with all the others and is dropped.
    ref = camera.n_bands // 2
    order = [ref] + [b for b in range(camera.n_bands) if b != ref]
    ahead = order[1:max(1, pool.workers)]  # the workers that would idle during the screening
    cells: CellCache = {}

    def submit(b: int, use: list[tuple[int, View]], screen: bool = False,
               start: np.ndarray | None = None) -> Future:
        return pool.submit(vignetting_band, _band_views(session, stack, b, use, inverse_response, saturation_dn,
                                                        cells), screen, start)

    futures = {b: submit(b, views, b == ref) for b in [ref, *ahead]}
    started()
    ref_fit, saturated[ref], frac = futures[ref].result()
    bad = set(vignetting.inconsistent_views(frac).tolist())
    if bad and len(views) - len(bad) < MIN_VIEWS_TO_SCREEN:
        # With few views the overlap is thin and a sound view that alone covers part of the
        # image also disagrees with the fit (a demo view with a 0.4 deg pose error measured
        # 4-6 %); dropping it costs more coverage than it removes error. Keep all, say so.
        report.residuals["views_not_screened"] = (
            f"{len(bad)} view(s) disagree with the others but only {len(views)} views were usable; "
            f"all kept (screening needs {MIN_VIEWS_TO_SCREEN} views left)"
        )
        bad = set()
    switched = _try_other_solutions(session, stack, views, bad, frac, ref_fit, inverse_response, saturation_dn, cells,
                                    ref, report)
    bad -= set(switched)
    if switched:
        views = [(i, switched.get(k, v)) for k, (i, v) in enumerate(views)]
    if bad or switched:
        med = float(np.nanmedian(frac))
        for k in sorted(bad):
            report.skipped.append({
                "file": views[k][1].record.path.name,
                "reason": f"inconsistent with the other views ({frac[k]:.0%} of its reflector pixels off "
                          f"by >10 %, median view {med:.1%}): marker pose likely wrong"
                          f"{_choice_note(views[k][1].choice)}",
            })
        views = [v for k, v in enumerate(views) if k not in bad]
        futures[ref] = submit(ref, views, start=ref_fit.vignetting)
    for b in order[len(ahead) + 1:]:
        futures[b] = submit(b, views)
    if bad:  # the bands started ahead on all views, again on the views kept
        for b in ahead:
            first = futures[b].result()[0]
            futures[b] = submit(b, views, start=first.vignetting)
    fits = []
    for b in range(camera.n_bands):
        fit, saturated[b], _ = futures[b].result()
        fits.append(fit)
    return fits, saturated, views


def _try_other_solutions(session: Session, stack: np.ndarray, views: list[tuple[int, View]], bad: set[int],
                         frac: np.ndarray, ref_fit: vignetting.VignettingFit, inverse_response: np.ndarray,
                         saturation_dn: np.ndarray, cells: CellCache, ref: int, report: StageReport) -> dict[int, View]:
    """The views screened out (``bad``) that the other IPPE solution of their marker makes
    consistent with the other views: each such view taken with that pose, by index.

    A view disagrees with the reference band's fit when its pose maps lawn or paper onto the
    reflector; if the mirrored solution (:mod:`mscal_core.marker`) brings its fraction of
    missed observations (:func:`mscal_core.vignetting.view_inconsistency`) under the screening
    limit (:func:`mscal_core.vignetting.inconsistent_views` of all views with its new fraction),
    the view is kept with that pose, and its record in ``marker_poses`` says so."""
    out: dict[int, View] = {}
    for k in sorted(bad):
        i, view = views[k]
        if view.choice is None or view.choice.alternative is None:
            continue
        other = dataclasses.replace(view, pose=view.choice.alternative, choice=view.choice.swapped("consistency"))
        obs, _ = band_observations(_band_views(session, stack, ref, [(i, other)], inverse_response, saturation_dn, cells))
        trial = frac.copy()
        trial[k] = vignetting.view_inconsistency(ref_fit, *obs[0])
        if np.isfinite(trial[k]) and k not in set(vignetting.inconsistent_views(trial).tolist()):
            out[k] = other
            log.info("vignetting view %s: the other IPPE solution agrees with the other views (%.0f%% -> %.0f%% "
                     "of its reflector pixels off)", view.record.path.name, 100 * frac[k], 100 * trial[k])
    names = {v.record.path.name: v for v in out.values()}
    for rec in report.residuals.get("marker_poses", []):
        if rec.get("file") in names:
            rec.update(names[rec["file"]].choice.as_record())  # type: ignore[union-attr]
    return out


def _choice_note(choice: marker.PoseChoice | None) -> str:
    """How a skipped view's pose was chosen between its two IPPE solutions, for its reason."""
    if choice is None:
        return ""
    e0, e1 = choice.reprojection_px
    second = f", {e1:.3f} px" if np.isfinite(e1) else ""
    return f" (IPPE solution {choice.solution} taken by {choice.by}; reprojection {e0:.3f} px{second})"


def _fit_multilens_vignetting(session: Session, stack: np.ndarray, views: list[tuple[int, View]],
                              inverse_response: np.ndarray, saturation_dn: np.ndarray, report: StageReport,
                              pool: BandPool, started: Callable[[], None]
                              ) -> tuple[list[vignetting.VignettingFit], dict[int, float]]:
    """Eq. 8-10 of a multi-lens camera: each lens on the views whose marker it found (its own
    poses), screened on its own fit like the band-grid camera's reference band, on ``pool``."""
    camera = session.camera
    uses = [[v for v in views if v[1].pose_for(b) is not None] for b in range(camera.n_bands)]
    for b, use in enumerate(uses):
        if not use:
            raise FitError(f"band {camera.bands[b].name}: the marker was found in none of its vignetting views",
                           hint="check that the marker is in view of every lens and sharp")
    cells: CellCache = {}
    futures = [pool.submit(lens_vignetting_band, _band_views(session, stack, b, uses[b], inverse_response,
                                                             saturation_dn, cells), MIN_VIEWS_TO_SCREEN)
               for b in range(camera.n_bands)]
    started()
    results = [f.result() for f in futures]
    fits, saturated = [], {}
    for b, (fit, saturated[b], frac, dropped) in enumerate(results):
        med = float(np.nanmedian(frac)) if dropped else 0.0
        for k in dropped:
            report.skipped.append({
                "file": uses[b][k][1].record.name,
                "reason": f"band {camera.bands[b].name}: inconsistent with the other views ({frac[k]:.0%} of its "
                          f"reflector pixels off by >10 %, median view {med:.1%}): marker pose likely wrong"
                          f"{_choice_note(uses[b][k][1].choice_for(b))}",
            })
        fits.append(fit)
    return fits, saturated


def add_vignetting(ds: xr.Dataset, fits: Sequence[vignetting.VignettingFit], report: StageReport) -> xr.Dataset:
    ds = ds.copy()
    ds["vignetting"] = (
        ("band", "y", "x"),
        np.stack([f.vignetting for f in fits]).astype(np.float32),
        {"long_name": "optical attenuation V (Eq. 8-10), max 1 per band"},
    )
    ds["vignetting_count"] = (
        ("band", "y", "x"),
        np.stack([np.minimum(f.count, 65535) for f in fits]).astype(np.uint16),
        {"long_name": "observations per pixel in the vignetting fit"},
    )
    ds["vignetting_observed"] = (
        ("band", "y", "x"),
        np.stack([f.observed for f in fits]).astype(bool),
        {"long_name": "False where V was filled smoothly (too few observations)"},
    )
    ds.attrs["vignetting"] = report.as_attrs()
    return ds


# --------------------------------------------------------------------------- illumination (Eq. 11-14)


#: Reflector frames more than this apart in time are different captures (seconds). A capture
#: (a few images of the reflector, turned or re-framed) takes well under a minute; the
#: captures of a session (before, during, after a flight) are minutes apart. Frames of
#: one folder without times are one capture; subfolders of ``reflector/`` are always one
#: capture each, whatever their times.
CAPTURE_GAP_S = 120.0
#: A reflector capture needs at least this many reflector pixels for Eq. 11-14.
MIN_REFLECTOR_PIXELS = 100


@dataclass(frozen=True)
class ReflectorCapture:
    """Reflector images taken under one light: ``frames`` are indices into the records of
    :func:`reflector_captures`; ``time_s`` the mean frame time (s since the epoch, UTC; NaN
    if unknown); ``irradiance`` the median sun-sensor level of its frames, None if any frame
    has none: frames.csv ``irradiance`` where given (raw), else the horizontal irradiance of the
    files' sun sensor, the geometric mean over the bands
    (:func:`pipeline.ingest.sunsensor.record_levels`, the function apply uses for the flight's
    frames and captures; the store marks it with ``sun_sensor_model``); ``irradiance_source``
    how the frames' levels were obtained (one per distinct source)."""

    name: str
    frames: tuple[int, ...]
    time_s: float
    irradiance: float | None
    folder: Path
    irradiance_source: tuple[str, ...] = ()


def _time_s(rec: FrameRecord) -> float:
    ns = time_ns(rec.time)
    return float("nan") if ns == NAT else ns / 1e9


def reflector_captures(folder: Path, camera: Camera | None = None) -> tuple[list[FrameRecord], list[ReflectorCapture]]:
    """The frames of ``reflector/`` and how they split into captures.

    Subfolders of ``folder`` that hold frames are one capture each (named after the
    subfolder); frames directly in ``folder`` are a capture too (named ``reflector``).
    Without subfolders, the frames are split where consecutive frame times are more than
    :data:`CAPTURE_GAP_S` apart (frames.csv ``time`` or EXIF DateTimeOriginal); frames
    without times are one capture. Records keep their folder's order (sorted by name), so a
    session with one capture reads exactly as before. Captures are sorted by time.
    """
    subs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")) if folder.is_dir() else []
    groups: list[tuple[str, Path, list[FrameRecord]]] = []
    has_top = any(p.is_file() and (p.suffix.lower() in IMAGE_SUFFIXES or p.name == FRAMES_CSV)
                  for p in folder.iterdir()) if folder.is_dir() else False
    def read(where: Path, recursive: bool) -> list[FrameRecord]:
        # a multi-lens camera's captures (band files) are the frames; else one file, one frame
        return read_frames(where, camera, recursive=recursive) if camera is not None else read_frame_table(where)

    if not subs or has_top:
        groups.append(("reflector", folder, read(folder, not subs)))
    for sub in subs:
        groups.append((sub.name, sub, read(sub, True)))
    records: list[FrameRecord] = []
    captures: list[ReflectorCapture] = []

    def add(name: str, where: Path, idx: list[int]) -> None:
        times = np.array([_time_s(records[i]) for i in idx])
        irr = record_levels([records[i] for i in idx])
        time_s = float(np.mean(times)) if np.all(np.isfinite(times)) else float("nan")
        level = float(np.median(irr.value)) if irr.value.size and np.all(np.isfinite(irr.value)) else None
        captures.append(ReflectorCapture(name, tuple(idx), time_s, level, where, tuple(dict.fromkeys(irr.source))))

    for name, where, recs in groups:
        first = len(records)
        records.extend(recs)
        idx = list(range(first, len(records)))
        if len(groups) > 1:
            add(name, where, idx)
            continue
        times = np.array([_time_s(r) for r in recs])
        known = np.isfinite(times)
        if not known.any():
            add(name, where, idx)
            continue
        if not known.all():
            missing = ", ".join(recs[i].path.name for i in np.flatnonzero(~known)[:3])
            raise SessionError(
                f"reflector frame(s) {missing} have no time while others do: the frames cannot be "
                "split into captures",
                path=where / FRAMES_CSV,
                hint="give every reflector frame a time, or put each capture in its own subfolder of reflector/",
            )
        order = np.argsort(times, kind="stable")
        cut = np.flatnonzero(np.diff(times[order]) > CAPTURE_GAP_S) + 1
        parts = np.split(order, cut)
        for k, part in enumerate(parts):
            add(name if len(parts) == 1 else f"capture_{k}", where, sorted(first + int(i) for i in part))
    if len(captures) > 1:
        undated = [c.name for c in captures if not np.isfinite(c.time_s)]
        if undated:
            raise SessionError(
                f"reflector capture(s) {', '.join(undated)} have no time: several captures need times to "
                "interpolate the light between them",
                path=folder,
                hint="add a time column (ISO 8601) to their frames.csv",
            )
        captures.sort(key=lambda c: c.time_s)
    return records, captures


@dataclass
class CaptureFit:
    """The illumination fit of one reflector capture: which of the result's views are its."""

    capture: ReflectorCapture
    fit: illumination.IlluminationFit
    views: tuple[int, ...]  # indices into IlluminationResult.views
    centre_brightness: float = float("nan")  # B at the reflector centre (plane fit); NaN: one capture


@dataclass
class IlluminationResult:
    """The illumination fit and, for the QA report, per reflector image used: its
    brightness map ``B(x)`` on the band grid (NaN off the reflector), its DN in ``qa_band``,
    its effective exposure and file name. ``fit`` is the first capture's (its S is the store's
    ``spectral_factor``); ``captures`` holds every capture's fit."""

    fit: illumination.IlluminationFit
    report: StageReport
    views: list[tuple[int, View]]
    brightness_maps: np.ndarray | None = None  # (image, H, W) float32
    qa_band: int = 0
    qa_dn: np.ndarray | None = None  # (image, H, W) uint16
    exposures: np.ndarray | None = None  # (image,) effective exposure, ms
    captures: list[CaptureFit] = field(default_factory=list)


def qa_band(camera: Camera) -> int:
    """The band the QA report shows images of: the camera's NIR index band (803 nm for the
    Ximea, as in the paper's figures), else the middle band."""
    if "nir" in camera.index_bands:
        return camera.band_for_wavelength(camera.index_bands["nir"])
    return camera.n_bands // 2


def read_reflector_frames(session: Session) -> tuple[list[ReflectorCapture], FolderFrames]:
    """The session's ``reflector/`` frames read (:func:`reflector_captures`), and their captures."""
    folder = session.reflector_dir
    if not folder.is_dir():
        raise SessionError("frame folder not found", path=folder)
    recs, captures = reflector_captures(folder, session.camera)
    return captures, FolderFrames(recs, read_stack(recs, session.camera), content_hashes(record_files(recs), session.root))


def fit_illumination_frames(
    session: Session, inverse_response: np.ndarray, saturation_dn: np.ndarray, vignetting_maps: np.ndarray,
    *, shared_pixels: bool = True, frames: Callable[[], tuple[list[ReflectorCapture], FolderFrames]] | None = None,
) -> IlluminationResult:
    """Eq. 11-14 from the session's ``reflector/`` image(s), per capture (:func:`reflector_captures`):
    S and B of each capture's images under its own light.

    Several captures: with ``shared_pixels`` (default) each is fitted on the sensor pixels
    every capture saw the reflector at (:func:`mscal_core.illumination.shared_reflector_pixels`),
    so an error of the vignetting estimate there biases every capture alike and cancels between
    them (bench/bench_light.py: the capture-to-capture error of S 0.5-0.6 % -> 0.11-0.13 % worst
    band); the fraction of reflector pixels kept is reported as ``shared_pixel_fraction`` (0
    when some capture would keep fewer than :data:`MIN_REFLECTOR_PIXELS`: all pixels are used,
    and the QA report warns). ``frames``: gives :func:`read_reflector_frames` already read."""
    t0 = time.perf_counter()
    camera = session.camera
    report = StageReport("illumination")
    session, _ = with_intrinsics(session)
    folder = session.reflector_dir
    captures, read = frames() if frames is not None else read_reflector_frames(session)
    recs, stack = read.records, read.stack
    report.inputs = read.inputs
    views = find_views(recs, stack, session, inverse_response, report)
    if not views:
        raise FitError(
            f"{session.marker.label} was not found in any of the "
            f"{len(recs)} frames",
            path=folder,
            hint="check marker.dictionary and marker.id in session.yaml, and that the marker is in view and sharp",
        )
    rho = session.reflector.reflectance.at(camera.wavelengths)
    shape = stack.shape[2:]
    columns, plane = [], []
    n_sat = np.zeros(camera.n_bands, dtype=np.int64)
    lens_rad: list[np.ndarray] = []
    if is_multilens(camera):
        views, uvs, masks, lens_rad = _lens_radiance(session, stack, views, inverse_response, saturation_dn,
                                                     vignetting_maps, qa_band(camera), report, n_sat)
        lens_masks = list(masks)
    else:
        centre = tuple(_offsets(camera).mean(axis=0))
        rays = geometry.pixel_rays(session.intrinsics, shape, centre)
        uvs = [geometry.pixels_to_plane(view.pose, session.intrinsics, shape, rays=rays) for _, view in views]
        masks = [geometry.reflector_mask(uv, session.reflector.size_m, _exclude_half(session), _edge_margin(session))
                 for uv in uvs]
    shared_fraction = None
    if len(captures) > 1 and shared_pixels:
        # compare the captures' light on the same sensor pixels: a vignetting error there is
        # then common to every capture and cancels between them (shared_reflector_pixels)
        owner = [next(c for c, cap in enumerate(captures) if i in cap.frames) for i, _ in views]
        before = sum(int(m.sum()) for m in masks)
        masks, shared = illumination.shared_reflector_pixels(masks, owner, MIN_REFLECTOR_PIXELS)
        shared_fraction = sum(int(m.sum()) for m in masks) / max(before, 1) if shared else 0.0
    for k, (i, view) in enumerate(views):
        uv, mask = uvs[k], masks[k]
        if lens_rad:  # sampled per lens on the reference band's pixels; keep those still in the mask
            columns.append(lens_rad[k][:, mask[lens_masks[k]]])
            plane.append(uv[mask] if len(captures) > 1 else None)
            continue
        rad = np.empty((camera.n_bands, int(mask.sum())), dtype=np.float64)
        for b in range(camera.n_bands):
            t = view.record.band_exposure(b)
            dn = stack[i, b][mask]
            n_sat[b] += int(np.count_nonzero(dn >= saturation_dn[b]))
            e = energy(dn, inverse_response[b], t, int(saturation_dn[b]))
            with np.errstate(divide="ignore", invalid="ignore"):
                rad[b] = e / vignetting_maps[b][mask]
        columns.append(rad)
        plane.append(uv[mask] if len(captures) > 1 else None)
    n_pixels = sum(c.shape[1] for c in columns)
    maps = np.full((len(views), *shape), np.nan, dtype=np.float32)
    image_brightness = np.full(len(views), np.nan)
    fits = [_fit_capture(cap, captures, views, columns, masks, plane, rho, folder, session, maps, image_brightness)
            for cap in captures]
    poses = report.residuals.get("marker_poses")
    report.residuals = _illumination_residuals(views, masks, fits, image_brightness, n_sat, n_pixels, shared_fraction)
    if poses is not None:
        report.residuals["marker_poses"] = poses
    report.seconds = time.perf_counter() - t0
    qb = qa_band(camera)
    return IlluminationResult(
        fits[0].fit, report, views, brightness_maps=maps, qa_band=qb,
        qa_dn=np.stack([stack[i, qb] for i, _ in views]),
        exposures=np.array([v.record.band_exposure(qb) for _, v in views]),
        captures=fits,
    )


def _illumination_residuals(views: list[tuple[int, View]], masks: list[np.ndarray], fits: list["CaptureFit"],
                            image_brightness: np.ndarray, n_sat: np.ndarray, n_pixels: int,
                            shared_fraction: float | None) -> dict[str, Any]:
    """The illumination stage's fit numbers for the store and the QA report."""
    out = {
        "images_used": len(views),
        "reflector_pixels": int(n_pixels),
        "reflector_pixels_per_image": [int(m.sum()) for m in masks],
        "residual_rms": round(float(max(f.fit.residual_rms for f in fits)), 5),
        "image_brightness": [round(float(v), 5) for v in image_brightness],
        "saturated_fraction": [round(float(v), 6) for v in n_sat / max(n_pixels, 1)],
    }
    if shared_fraction is not None:
        # 0.0: the captures barely overlap on the sensor, each was fitted on all its pixels
        out["shared_pixel_fraction"] = round(float(shared_fraction), 4)
    if len(fits) > 1:
        out["captures"] = [
            {"name": f.capture.name, "images": len(f.views), "residual_rms": round(float(f.fit.residual_rms), 5),
             "irradiance": f.capture.irradiance, "irradiance_source": list(f.capture.irradiance_source),
             "centre_brightness": round(f.centre_brightness, 5)}
            for f in fits
        ]
    return out


def _fit_capture(cap: Any, captures: Sequence[Any], views: list[tuple[int, View]], columns: list[np.ndarray],
                 masks: list[np.ndarray], plane: list[np.ndarray | None], rho: np.ndarray, folder: Path,
                 session: Session, maps: np.ndarray, image_brightness: np.ndarray) -> "CaptureFit":
    """Eq. 11-14 on one reflector capture's images: its S and B; B written into ``maps`` and
    each image's brightness into ``image_brightness`` (the images' rows of both); with several
    captures, the light's level at the reflector centre for comparing them."""
    mine = [k for k, (i, _) in enumerate(views) if i in set(cap.frames)]
    where = folder if len(captures) == 1 else cap.folder
    label = "" if len(captures) == 1 else f"capture {cap.name}: "
    if not mine:
        raise FitError(
            f"{label}{session.marker.label} was not found in any of its "
            f"{len(cap.frames)} frames",
            path=where,
            hint="check that the marker is in view and sharp, or remove the capture",
        )
    radiance = np.concatenate([columns[k] for k in mine], axis=1)
    if radiance.shape[1] < MIN_REFLECTOR_PIXELS:
        raise FitError(
            f"{label}only {radiance.shape[1]} reflector pixels found",
            path=where,
            hint="take the reflector image closer, or check reflector.size_m in session.yaml",
        )
    image_index = np.concatenate([np.full(columns[k].shape[1], j) for j, k in enumerate(mine)])
    fit = illumination.fit_illumination(radiance, rho, image_index=image_index)
    start = 0
    for j, k in enumerate(mine):
        n = int(masks[k].sum())
        maps[k][masks[k]] = fit.brightness[start:start + n]
        start += n
        if fit.image_brightness is not None:
            image_brightness[k] = fit.image_brightness[j]
    centre = float("nan")
    if len(captures) > 1:  # the light's level at the reflector centre, for comparing captures
        start = 0
        per_image = []
        for k in mine:
            n = int(masks[k].sum())
            per_image.append(illumination.centre_brightness(plane[k], fit.brightness[start:start + n]))
            start += n
        centre = float(np.nanmedian(per_image)) if np.isfinite(per_image).any() else 1.0
    return CaptureFit(cap, fit, tuple(mine), centre)


def _lens_radiance(session: Session, stack: np.ndarray, views: list[tuple[int, View]], inverse_response: np.ndarray,
                   saturation_dn: np.ndarray, vignetting_maps: np.ndarray, ref: int, report: StageReport,
                   n_sat: np.ndarray) -> tuple[list[tuple[int, View]], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Eq. 11-14 of a multi-lens camera needs every band's radiance at the same reflector
    point, but each lens sees the reflector at its own pixels. The reflector points are those
    seen by band ``ref``'s pixels (its own marker pose); each is projected into every other
    band with that lens's pose and intrinsics (``pi_i`` of Eq. 8), where ``U(I) / (t V)`` is
    sampled bilinearly. A point counts only where every band saw reflector there (inside its
    own reflector mask, not saturated). Views without a pose in every band are skipped.

    Returns the views used, per view the plane points (H, W, 2) and the mask on ``ref``'s
    grid, and the radiance (band, mask pixels) in the mask's row-major order."""
    import cv2

    camera = session.camera
    shape = stack.shape[2:]
    size, excl, edge = session.reflector.size_m, _exclude_half(session), _edge_margin(session)
    rays = [geometry.pixel_rays(session.intrinsics_for(b), shape) for b in range(camera.n_bands)]
    kept, uvs, masks, rads = [], [], [], []
    for i, view in views:
        if any(view.pose_for(b) is None for b in range(camera.n_bands)):
            report.skipped.append({"file": view.record.name,
                                   "reason": "marker not found in every band: not usable for Eq. 11-14"})
            continue
        uv = geometry.pixels_to_plane(view.pose_for(ref), session.intrinsics_for(ref), shape, rays=rays[ref])
        mask = geometry.reflector_mask(uv, size, excl, edge)
        pts = uv[mask]
        rad = np.empty((camera.n_bands, pts.shape[0]), dtype=np.float64)
        ok = np.ones(pts.shape[0], dtype=bool)
        for b in range(camera.n_bands):
            t = view.record.band_exposure(b)
            dn = stack[i, b]
            e_img = energy(dn, inverse_response[b], t, int(saturation_dn[b]))
            own = geometry.reflector_mask(geometry.pixels_to_plane(view.pose_for(b), session.intrinsics_for(b), shape,
                                                                   rays=rays[b]), size, excl, edge)
            n_sat[b] += int(np.count_nonzero(dn[own] >= saturation_dn[b]))
            valid = (own & np.isfinite(e_img)).astype(np.float32)
            if b == ref:
                xy = np.argwhere(mask)[:, ::-1].astype(np.float32)
            else:
                xy = geometry.project_to_pixels(pts, view.pose_for(b), session.intrinsics_for(b)).astype(np.float32)
            n = xy.shape[0]
            width = 1024  # remap's maps must stay below 32767 on each side
            pad = (-n) % width
            mx = np.pad(xy[:, 0], (0, pad), constant_values=-1e6).reshape(-1, width)
            my = np.pad(xy[:, 1], (0, pad), constant_values=-1e6).reshape(-1, width)

            def sample(img: np.ndarray) -> np.ndarray:
                return cv2.remap(np.ascontiguousarray(img, dtype=np.float32), mx, my, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0.0).ravel()[:n]

            ok &= sample(valid) > 0.999
            e = sample(np.nan_to_num(e_img, nan=0.0))
            v = sample(vignetting_maps[b])
            with np.errstate(divide="ignore", invalid="ignore"):
                rad[b] = e / v
        ok &= np.all(np.isfinite(rad), axis=0)
        m2 = mask.copy()
        m2[mask] = ok
        kept.append((i, view))
        uvs.append(uv)
        masks.append(m2)
        rads.append(rad[:, ok])
    if not kept:
        raise FitError("no reflector image has the marker in every band", path=session.reflector_dir,
                       hint="frame the marker so that every lens sees it")
    return kept, uvs, masks, rads


def add_illumination(ds: xr.Dataset, result: IlluminationResult) -> xr.Dataset:
    ds = ds.copy()
    ds["spectral_factor"] = (
        "band",
        np.asarray(result.fit.spectral_factor, dtype=np.float64),
        {"long_name": "spectral factor S (Eq. 11-14); reflector brightness B has median 1"
                      + ("; of the first reflector capture (capture_spectral_factor: every capture)"
                         if len(result.captures) > 1 else "")},
    )
    if result.brightness_maps is not None and result.qa_dn is not None:
        # For the QA report: B(x) of each reflector image and its DN in one band,
        # so the report can show Eq. 15 beside the Eq. 16 baseline without the session.
        ds = ds.assign_coords(
            reflector_image=np.arange(len(result.views)),
            reflector_file=("reflector_image", np.array([v.record.path.name for _, v in result.views], dtype=object)),
            reflector_exposure_ms=("reflector_image", np.asarray(result.exposures, dtype=np.float64),
                                   {"long_name": "effective exposure (exposure_ms x gain)"}),
        )
        ds["reflector_brightness"] = (
            ("reflector_image", "y", "x"), result.brightness_maps.astype(np.float32),
            {"long_name": "reflector brightness B(x) (Eq. 11-14), median 1; NaN off the reflector"},
        )
        ds["reflector_dn"] = (
            ("reflector_image", "y", "x"), result.qa_dn.astype(np.uint16),
            {"long_name": "reflector image DN in one band (QA report)", "band": int(result.qa_band)},
        )
    if result.captures:
        ds = add_captures(ds, result)
    ds.attrs["illumination"] = result.report.as_attrs()
    return ds


def add_captures(ds: xr.Dataset, result: IlluminationResult) -> xr.Dataset:
    """Per reflector capture: its S, brightness level, time and irradiance, on a
    ``capture`` dimension, and which capture each reflector image belongs to."""
    caps = result.captures
    s = np.stack([np.asarray(c.fit.spectral_factor, dtype=np.float64) for c in caps])
    if len(caps) > 1:
        # Each fit's S has its own gauge (median B = 1 over the pixels that capture saw); the
        # light of capture c is S_c times its reflector-centre brightness, relative to the
        # first capture's so that capture 0 keeps the store's S (illumination.centre_brightness).
        centre = np.array([c.centre_brightness for c in caps])
        s = s * (centre / centre[0])[:, None]
    level, _ = illumination.split_level(s)
    times = np.array([np.datetime64(int(round(c.capture.time_s * 1e9)), "ns") if np.isfinite(c.capture.time_s)
                      else np.datetime64("NaT", "ns") for c in caps], dtype="datetime64[ns]")
    ds = ds.assign_coords(
        capture=np.arange(len(caps)),
        capture_name=("capture", np.array([c.capture.name for c in caps], dtype=object)),
        capture_time=("capture", times, {"long_name": "mean time of the capture's frames (UTC)"}),
    )
    ds["capture_spectral_factor"] = (
        ("capture", "band"), s, {"long_name": "spectral factor S of each reflector capture (Eq. 11-14): the light at "
                                              "the reflector centre, in the gauge of the first capture's S"},
    )
    ds["capture_level"] = (
        "capture", np.asarray(level, dtype=np.float64),
        {"long_name": "brightness level of each capture: geometric mean of its S over the bands"},
    )
    ds["capture_irradiance"] = (
        "capture", np.array([np.nan if c.capture.irradiance is None else c.capture.irradiance for c in caps]),
        {"long_name": "median sun-sensor level of the capture's frames (NaN: none): horizontal irradiance, "
                      "geometric mean over the bands, or frames.csv irradiance as given",
         # apply makes the flight's levels alike only for stores that say so
         SUN_SENSOR_MODEL_ATTR: SUN_SENSOR_MODEL},
    )
    if "reflector_image" in ds.coords:
        owner = np.zeros(ds.sizes["reflector_image"], dtype=np.int32)
        for c, cf in enumerate(caps):
            owner[list(cf.views)] = c
        ds = ds.assign_coords(reflector_capture=("reflector_image", owner))
    return ds


# --------------------------------------------------------------------------- whole session


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
    with _pool(pool, camera.n_bands, workers) as pool, ThreadPoolExecutor(1) as aside:
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
    ires = fit_illumination_frames(session, U, sat, ds["vignetting"].values, frames=lambda: reflector)
    ds = add_illumination(ds, ires)
    advance()
    ds = add_intrinsics(ds, session, source)
    ds = provenance(ds, session.root)
    write_store(ds, out)
    advance()
    return ds


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
        keep = ["inverse_response", "black_level", "saturation_dn"] + (["vignetting", "vignetting_count", "vignetting_observed"] if stage == "illumination" else [])
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
        ds = add_illumination(ds, fit_illumination_frames(session, U, sat, ds["vignetting"].values))
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
