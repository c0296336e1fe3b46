"""Marker views: the frames of ``vignetting/`` and ``reflector/`` read, the marker (or ChArUco
board) found in each and its pose estimated (per lens for a multi-lens camera), and the
margins around the marker and the reflector's edge whose pixels the fits do not use.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from mscal_core import charuco, geometry, marker
from mscal_core.errors import FitError
from mscal_core.mosaic import band_offsets

from pipeline.calibrate.stage import StageReport, record_files
from pipeline.calibrate.sweep import read_stack
from pipeline.ingest.captures import is_multilens, read_frames
from pipeline.ingest.catalog import Camera
from pipeline.ingest.session import FrameRecord, MarkerSpec, Session
from pipeline.storage.store import content_hashes

#: Reflector pixels closer than this to the reflector edge are not used (metres, or 2 % of
#: the reflector's smaller side if larger): they mix reflector and background.
EDGE_MARGIN_M = 0.01
#: Extra margin around the marker's white paper border (metres).
MARKER_MARGIN_M = 0.005


def _workers() -> int:
    import os

    return max(1, min(4, os.cpu_count() or 1))


def _map(fn: Callable[[int], Any], n: int) -> list[Any]:
    """Run ``fn(0..n-1)`` on a small thread pool (numpy/OpenCV/scipy release the GIL)."""
    with ThreadPoolExecutor(max_workers=_workers()) as ex:
        return list(ex.map(fn, range(n)))


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

    def with_choice(self, band: int, choice: marker.PoseChoice) -> View:
        """The view with ``choice`` taken for ``band``'s pose (of a band-grid camera: for every
        band); of a multi-lens camera ``pose`` follows when it was that band's."""
        if self.band_poses is None:
            return replace(self, pose=choice.pose, choice=choice)
        poses, choices = list(self.band_poses), list(self.band_choices or (None,) * len(self.band_poses))
        pose = choice.pose if poses[band] is self.pose else self.pose
        poses[band], choices[band] = choice.pose, choice
        return replace(self, pose=pose, band_poses=tuple(poses), band_choices=tuple(choices))


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
    centre = camera_offsets(session.camera).mean(axis=0)

    outlines = _pose_outlines(session)

    def one(i: int) -> tuple[tuple[int, View] | None, int]:
        img = detection_image(stack[i], inverse_response)
        choice, n = marker_pose_corners(img, session.marker, session.intrinsics, outlines,
                                        (float(centre[0]), float(centre[1])))
        return (None if choice is None else (i, View(records[i], choice.pose, choice=choice))), n

    corners: dict[int, int] = {}
    for i, (res, n) in enumerate(_map(one, len(records))):
        if res is None:
            found = f" (only {n} corner{'s' if n > 1 else ''})" if session.marker.board is not None and n else ""
            report.skipped.append(
                {"file": records[i].path.name, "reason": f"{session.marker.label} not found{found}"}
            )
        else:
            views.append(res)
            corners[i] = n
    report.residuals["marker"] = marker_record(session.marker)
    report.residuals["marker_poses"] = [{"file": v.record.path.name, **v.choice.as_record(),  # type: ignore[union-attr]
                                         "corners": corners[i]} for i, v in views]
    return views


def marker_record(mk: MarkerSpec) -> dict[str, Any]:
    """The stage report's ``marker``: ``type`` (``aruco`` or ``charuco``) and ``label``."""
    return {"type": "aruco" if mk.board is None else "charuco", "label": mk.label}


def marker_pose(img: np.ndarray, mk: MarkerSpec, intrinsics: geometry.Intrinsics, outlines: list[tuple[float, float]],
                offset: tuple[float, float] = (0.0, 0.0)) -> marker.PoseChoice | None:
    """The pose of the session's marker, or ChArUco board, in a detection image whose pixel
    ``(i, j)`` sees image point ``(j + dx, i + dy)`` (``offset``); None if it is not found (a
    board: fewer than :data:`mscal_core.charuco.MIN_CORNERS` corners, or corners on a line)."""
    return marker_pose_corners(img, mk, intrinsics, outlines, offset)[0]


def marker_pose_corners(img: np.ndarray, mk: MarkerSpec, intrinsics: geometry.Intrinsics,
                        outlines: list[tuple[float, float]], offset: tuple[float, float] = (0.0, 0.0)
                        ) -> tuple[marker.PoseChoice | None, int]:
    """:func:`marker_pose` and the corners it was found from (a marker: 4; a board: its
    chessboard corners, also when too few; 0 when nothing was found)."""
    if mk.board is not None:
        found = charuco.detect_charuco(img, mk.board, min_corners=1)
        if found is None:
            return None, 0
        n = len(found[1])
        if n < charuco.MIN_CORNERS:
            return None, n
        try:
            return charuco.charuco_pose(found[0] + np.asarray(offset), found[1], mk.board, intrinsics), n
        except FitError:
            return None, n
    corners = geometry.detect_marker(img, mk.dictionary, mk.id)
    if corners is None:
        return None, 0
    return marker.pose_in_image(img, corners, mk.dictionary, mk.size_m, intrinsics, outlines, offset), 4


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
    report.residuals["marker"] = marker_record(mk)
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


def exclude_half(session: Session) -> float:
    """Half size of the square around the marker (its paper border and a margin) whose
    reflector pixels are not used."""
    return session.marker.size_m / 2 + session.marker.border_m + MARKER_MARGIN_M


def edge_margin(session: Session) -> float:
    """Reflector pixels closer than this to the reflector's edge are not used (metres)."""
    return max(EDGE_MARGIN_M, 0.02 * min(session.reflector.size_m))


def camera_offsets(camera: Camera) -> np.ndarray:
    """Each band's offset ``(dx, dy)`` on the band grid: the snapshot mosaic's, else zeros."""
    if camera.layout.kind == "mosaic" and camera.layout.pattern is not None:
        return band_offsets(camera.layout.pattern)
    return np.zeros((camera.n_bands, 2))
