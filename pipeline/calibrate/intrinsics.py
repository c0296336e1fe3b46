"""``mscal fit intrinsics FRAMES -o CALIB.zarr``: camera intrinsics per band from images of a
ChArUco board or a checkerboard (:mod:`mscal_core.intrinsics`), into a calibration store.

FRAMES is a folder of board images as the camera writes them: a multi-lens camera's captures
(one file per band; every lens is calibrated on its own band files), the snapshot camera's raw
mosaics (every band image is detected, its corners moved to the band grid by the band's
offset, and one calibration of the band grid is fitted from all of them: one lens), or an
ordinary camera's images (one calibration for all channels). The board comes from
``FRAMES/board.yaml`` (``kind: charuco|checkerboard``, ``squares: [columns, rows]``,
``square_m``, ``marker_m`` and ``dictionary`` for ChArUco) or the command's options. The
camera from ``--camera``, else the ``session.yaml`` of FRAMES's parent (``SESSION/intrinsics/``).

The store holds ``intrinsics (band, intrinsics_param)`` (``fx, fy, cx, cy, k1, k2, p1, p2,
k3``; pixels of each band's image) and the attribute ``intrinsics`` (images used and the
reprojection rms per band, images without the board). ``mscal calibrate --calibration`` and
``mscal fit vignetting|illumination --calibration`` use them when session.yaml gives none.

Which intrinsics a session's fits use (:func:`with_intrinsics`): session.yaml's, else a
store's, else the board images of ``SESSION/intrinsics/``, else the band files' metadata.
"""

from __future__ import annotations

import dataclasses
import functools
import re
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import xarray as xr
import yaml
from mscal_core import intrinsics as board_fit
from mscal_core.errors import InputError, MscalError, SessionError
from mscal_core.geometry import Intrinsics
from mscal_core.mosaic import band_offsets

from pipeline.ingest.captures import is_multilens, read_frames
from pipeline.ingest.catalog import Camera, load_camera
from pipeline.ingest.grouping import DEFAULT_CAPTURE_PATTERN
from pipeline.ingest.intrinsics import (
    INTRINSICS_PARAMS,
    band_intrinsics_from_files,
    intrinsics_array,
    intrinsics_from_array,
)
from pipeline.ingest.session import IMAGE_SUFFIXES, FrameRecord, Session, stored_bands
from pipeline.storage.store import content_hashes, new_dataset, write_store

BOARD_EXAMPLE = "board.yaml: {kind: charuco, squares: [7, 5], square_m: 0.04, marker_m: 0.03, dictionary: DICT_4X4_50}"


def store_intrinsics(ds: xr.Dataset, intr: Sequence[Intrinsics], source: str) -> xr.Dataset:
    """``ds`` with ``intrinsics (band, intrinsics_param)`` (one row per band) and its source."""
    ds = ds.copy()
    ds.coords["intrinsics_param"] = np.array(INTRINSICS_PARAMS, dtype=object)
    ds["intrinsics"] = (("band", "intrinsics_param"), intrinsics_array(intr),
                        {"long_name": "pinhole + OpenCV distortion per band (fx, fy, cx, cy in the band's pixels)",
                         "source": source})
    return ds


def parse_board(data: Any, path: Path) -> board_fit.Board:
    if not isinstance(data, dict):
        raise SessionError("the board must be a mapping", path=path, hint=BOARD_EXAMPLE)
    unknown = sorted(set(data) - {"kind", "squares", "square_m", "marker_m", "dictionary"})
    if unknown or "kind" not in data or "squares" not in data or "square_m" not in data:
        raise SessionError(f"board needs kind, squares, square_m{' (unknown: ' + ', '.join(unknown) + ')' if unknown else ''}",
                           path=path, hint=BOARD_EXAMPLE)
    try:
        sq = data["squares"]
        sq = [int(v) for v in (sq.lower().split("x") if isinstance(sq, str) else sq)]
        return board_fit.Board(kind=str(data["kind"]), squares=(sq[0], sq[1]), square_m=float(data["square_m"]),
                               marker_m=None if data.get("marker_m") is None else float(data["marker_m"]),
                               dictionary=str(data.get("dictionary", "DICT_4X4_50")))
    except (TypeError, ValueError, IndexError):
        raise SessionError(f"board {data!r} is not valid", path=path, hint=BOARD_EXAMPLE) from None
    except InputError as exc:
        raise SessionError(exc.reason, path=path, hint=BOARD_EXAMPLE) from None


def _camera_for(folder: Path, name: str | None) -> Camera:
    if name:
        return load_camera(name)
    for d in (folder, folder.parent):
        p = d / "session.yaml"
        if p.is_file():
            data = yaml.safe_load(p.read_text())
            if isinstance(data, dict) and data.get("camera"):
                return load_camera(str(data["camera"]))
    raise SessionError("--camera NAME is required (no session.yaml beside the folder)", path=folder)


def _band_images(folder: Path, camera: Camera) -> list[tuple[str, list[Path]]]:
    """``[(frame name, files)]``: a capture's band files (multi-lens), else one file."""
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not is_multilens(camera):
        return [(p.name, [p]) for p in files]
    pattern = re.compile(camera.layout.capture_pattern or DEFAULT_CAPTURE_PATTERN)
    suffixes = [str(b.file_suffix) for b in camera.bands]
    groups: dict[str, dict[str, Path]] = {}
    for p in files:
        m = pattern.match(p.name)
        if m:
            groups.setdefault(str(p.parent.relative_to(folder) / m["capture"]), {})[m["band"]] = p
    return [(name, [g.get(s) for s in suffixes]) for name, g in sorted(groups.items())]  # type: ignore[misc]


def fit_intrinsics_folder(folder: str | Path, camera: Camera, board: board_fit.Board,
                          fix_k3: bool = False) -> tuple[list[Intrinsics], dict]:
    """Intrinsics per band (see the module docstring) and a report."""
    folder = Path(folder)
    frames = _band_images(folder, camera)
    if not frames:
        raise SessionError("no board images found", path=folder, hint=f"put the camera's {', '.join(IMAGE_SUFFIXES)} files here")
    nb = camera.n_bands
    multilens = is_multilens(camera)
    offsets = band_offsets(camera.layout.pattern) if camera.layout.kind == "mosaic" and camera.layout.pattern \
        else np.zeros((nb, 2))
    per_band: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(nb)]
    shapes: list[tuple[int, int] | None] = [None] * nb
    skipped: list[dict[str, str]] = []
    for name, files in frames:
        if multilens:
            images = [None if f is None else stored_bands(Path(f), f, camera)[0] for f in files]
        else:
            images = list(stored_bands(Path(files[0]), files[0], camera))
        missing = []
        for b, img in enumerate(images):
            if img is None:
                missing.append(camera.bands[b].name)
                continue
            shapes[b] = img.shape
            found = board_fit.detect_board(img, board)
            if found is None:
                missing.append(camera.bands[b].name)
                continue
            per_band[b].append((found[0], found[1] + offsets[b]))
        if missing:
            skipped.append({"file": name, "reason": f"board not found in band(s) {', '.join(missing)}"})
    report: dict[str, Any] = {"board": board.__dict__ | {"squares": list(board.squares)}, "images": len(frames),
                              "skipped": skipped}
    try:
        if multilens:
            fits = []
            for b in range(nb):
                try:
                    fits.append(board_fit.calibrate(per_band[b], shapes[b] or (1, 1), fix_k3=fix_k3))
                except MscalError as exc:
                    raise type(exc)(f"band {camera.bands[b].name}: {exc.reason}", path=folder, hint=exc.hint) from None
            report["views"] = [f.views for f in fits]
            report["rms_px"] = [round(f.rms_px, 4) for f in fits]
            return [f.intrinsics for f in fits], report
        joint = board_fit.calibrate([v for band in per_band for v in band], shapes[0] or (1, 1), fix_k3=fix_k3)
    except MscalError as exc:
        if exc.path is None:
            raise type(exc)(exc.reason, path=folder, hint=exc.hint) from None
        raise
    report["views"] = [len(v) for v in per_band]
    report["rms_px"] = [round(joint.rms_px, 4)] * nb
    return [joint.intrinsics] * nb, report


def fit_intrinsics_cli(frames: str | Path, out: str | Path, *, camera_name: str | None = None,
                       board: dict | None = None, fix_k3: bool = False) -> xr.Dataset:
    """``mscal fit intrinsics FRAMES -o CALIB.zarr``."""
    t0 = time.perf_counter()
    folder = Path(frames)
    if not folder.is_dir():
        raise SessionError("board image folder not found", path=folder)
    camera = _camera_for(folder, camera_name)
    byaml = folder / "board.yaml"
    if board is None and byaml.is_file():
        spec = parse_board(yaml.safe_load(byaml.read_text()), byaml)
    elif board is not None:
        spec = parse_board(board, folder)
    else:
        raise SessionError("no board given", path=folder, hint=f"--board charuco --squares 7x5 --square-m 0.04 "
                                                             f"--marker-m 0.03, or {BOARD_EXAMPLE}")
    intr, report = fit_intrinsics_folder(folder, camera, spec, fix_k3)
    report["fix_k3"] = fix_k3
    ds = store_intrinsics(new_dataset(camera), intr, f"board images ({spec.kind}), mscal fit intrinsics")
    files = [f for _, fs in _band_images(folder, camera) for f in fs if f is not None]
    report["inputs"] = content_hashes(files, folder)
    report["seconds"] = round(time.perf_counter() - t0, 3)
    ds.attrs["intrinsics"] = report
    import mscal_core

    ds.attrs["mscal_version"] = mscal_core.__version__
    write_store(ds, out)
    return ds


__all__ = ["fit_intrinsics_cli", "fit_intrinsics_folder", "parse_board", "store_intrinsics"]


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


def board_intrinsics(folder: Path, camera: Camera) -> tuple[Intrinsics, ...]:
    """:func:`pipeline.calibrate.intrinsics.fit_intrinsics_folder` of a session's board folder,
    fitted once per content (every stage of a calibration asks)."""
    stamp = tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file())
    return _board_intrinsics(str(folder), camera.name, stamp)


@functools.lru_cache(maxsize=8)
def _board_intrinsics(folder: str, camera_name: str, stamp: tuple) -> tuple[Intrinsics, ...]:
    import yaml

    path = Path(folder) / "board.yaml"
    board = parse_board(yaml.safe_load(path.read_text()), path)
    intr, _ = fit_intrinsics_folder(folder, load_camera(camera_name), board)
    return tuple(intr)


def _set_intrinsics(session: Session, intr: Sequence[Intrinsics]) -> Session:
    if is_multilens(session.camera):
        return dataclasses.replace(session, band_intrinsics=tuple(intr))
    return dataclasses.replace(session, intrinsics=intr[0])  # the band grid's, one for all bands


def add_intrinsics(ds: xr.Dataset, session: Session, source: str) -> xr.Dataset:
    """The intrinsics the fits used, per band: ``intrinsics (band, intrinsics_param)``."""
    intr = [session.intrinsics_for(b) for b in range(session.camera.n_bands)]
    if any(i is None for i in intr):
        return ds
    return store_intrinsics(ds, intr, source)  # type: ignore[arg-type]
