"""Ingest a flight folder into the raw datacube ``OUT/raw.zarr`` (docs/architecture.md).

Layout (Zarr v3, consolidated, opened by ``xarray.open_zarr``):

- ``dn (frame, band, y, x)`` uint16 DN as read, one storage chunk per frame
  ``(1, n_bands, H, W)`` (Blosc lz4 + bit shuffle, :func:`raw_codec`);
- frame coordinates ``frame`` (file stem), ``exposure_ms``, ``gain``, ``time``
  (datetime64[ns], NaT if unknown), ``lat``, ``lon``, ``alt_m`` (NaN if unknown),
  ``source_file`` (file name in the flight folder), ``sha256`` (of the file's bytes);
- band coordinates ``band``, ``band_name``, ``wavelength`` (nm);
- CF attributes (``Conventions``, units, long names), ``camera``, ``bit_depth``,
  ``mscal_version``, ``format`` and the commit counter ``frames_committed``.

Incremental and idempotent: every file is hashed; a frame whose name and sha256 are in the
cube is not decoded again, a file whose name is in the cube with other content is quarantined
("changed since ingest", the cube keeps what it has), a file with the content of another
frame is quarantined as a duplicate, new frames are appended in file-name order. Frames that
cannot be used are quarantined with a reason naming the file (see :mod:`pipeline.ingest.discover`);
the rest go on.

Crash safety (SIGKILL at any moment). Every file Zarr writes is written to a temporary name
and renamed, so each chunk or metadata document is either old or new, never torn. The cube
is created under a temporary name and renamed into place. New frames are written whole
chunk by whole chunk beyond the committed count, then the coordinate arrays, then the
consolidated metadata, and last the ``frames_committed`` attribute. On open, anything beyond
``frames_committed`` is cut off (arrays resized back, their chunks deleted), so a killed run
followed by a re-run gives the same cube as one uninterrupted run. Apply's single pass
commits while its workers write the frames after the commit point
(:meth:`CubeWriter.commit` with ``room``): the readers' metadata shows the committed frames
only, and chunks a kill leaves beyond the arrays' shape are deleted on open too. One process at a time:
an advisory lock beside the cube (:func:`cube_lock`).

Memory is flat in the number of frames: frames stream through a small thread pool with a
bounded look-ahead (hash, read + demosaic; then the write of the frame's whole chunk, at most
``workers + 1`` in flight); the main thread takes results in file-name order, assigns frame
indices and commits every ``commit_every`` frames. No dask is involved in writing, and no two
writers ever touch one chunk (zarr v3 has no chunk locking: partial writes would race).

The tests SIGKILL an ingest between each of these steps (tests/pipeline/ingest/kill_points.py
wraps the functions that do them) and check that a re-run gives the same cube.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import threading
import time as _time
import warnings
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import mscal_core
import numpy as np
import zarr
from mscal_core.errors import FrameError, InputError
from zarr.core.sync import sync

from pipeline.ingest.catalog import Camera, load_camera
from pipeline.ingest.discover import Discovery, discover_flight, quarantine_entry
from pipeline.ingest.exif import time_ns
from pipeline.ingest.medians import DN_MEDIAN, DN_MEDIAN_ATTRS, band_medians, kept_medians
from pipeline.ingest.session import FrameRecord, stored_bands
from pipeline.storage.atomic import TMP_MARK, atomic_folder
from pipeline.storage.chunks import FrameChunks, frame_encoding
from pipeline.storage.lock import FolderLock
from pipeline.storage.store import FRAME_COORD_ATTRS, file_sha256

__all__ = ["Cube", "IngestResult", "cube_lock", "ingest_flight", "open_cube", "RAW_FORMAT", "FRAME_COORDS", "read_whole"]

log = logging.getLogger(__name__)

RAW_FORMAT = "mscal-raw/1"
FRAME_COORDS = ("frame", "exposure_ms", "gain", "time", "lat", "lon", "alt_m", "source_file", "sha256")
FRAME_VARS = ("dn", *FRAME_COORDS)
STRING_COORDS = ("frame", "source_file", "sha256")
COORD_CHUNK = 4096  # frames per chunk of a frame coordinate (rewritten whole at each commit)
TIME_UNITS = "nanoseconds since 1970-01-01"


@dataclass
class IngestResult:
    """What one ingest did. ``quarantined``: ``[{"file", "reason"}]`` of this run."""

    path: Path
    frames_added: int
    frames_already_present: int
    quarantined: list[dict[str, str]] = field(default_factory=list)
    n_frames: int = 0  # frames in the cube after this run
    added: list[str] = field(default_factory=list)  # names of the frames appended
    seconds: float = 0.0


# --------------------------------------------------------------------------- helpers


def _nan(v: float | None) -> float:
    return np.nan if v is None else float(v)


def _band_shape(camera: Camera) -> tuple[int, int, int] | None:
    """``(n_bands, H, W)`` of the camera's band stack, when the catalog fixes it."""
    lay = camera.layout
    if lay.kind == "mosaic" and lay.grid is not None:
        return (camera.n_bands, *lay.grid)
    if camera.sensor is not None:
        return (camera.n_bands, *camera.sensor)
    return None


def prefetch_file(path: Path) -> None:
    """Ask the kernel to start reading ``path`` into the page cache now, without waiting
    (``posix_fadvise(WILLNEED)``), so that a later read finds it there. The per-frame tasks
    call it for a frame a few places ahead of their own: a flight that is not in memory is
    otherwise read one file at a time, each read waiting behind the output writes on the
    device (measured on a 600-frame flight: 1.2 GB read at 4 ms per request). Never fails:
    a file that cannot be opened is left for its own task to report."""
    advise = getattr(os, "posix_fadvise", None)
    if advise is None:  # pragma: no cover - not POSIX
        return
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return
    try:
        advise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
    except OSError:
        pass
    finally:
        os.close(fd)


_read_buffer = threading.local()

#: Files up to this size are read whole into the reading thread's buffer, hashed and decoded
#: from it (:func:`read_frame`); larger ones are hashed as a stream and decoded from the file.
READ_ONCE_MAX_BYTES = 256 * 1024 * 1024


def read_whole(path: Path, size: int, hint: str) -> memoryview:
    """The first ``size`` bytes of ``path`` in this thread's buffer (reused from file to file,
    grown when needed; valid until this thread's next call: decode or copy before). A new
    ``bytes`` per file instead gives every file fresh memory to fault in. :class:`FrameError`
    naming the file, with ``hint``, if it ends before (it is being written or was cut short)."""
    buf = getattr(_read_buffer, "buf", None)
    if buf is None or len(buf) < size:
        buf = _read_buffer.buf = bytearray(size)
    view = memoryview(buf)[:size]
    done = 0
    with open(path, "rb", buffering=0) as fh:
        while done < size:
            k = fh.readinto(view[done:])
            if not k:
                raise FrameError("the file changed while it was being read (it ended early)", path=path, hint=hint)
            done += k
    return view


def read_frame(rec: FrameRecord, camera: Camera, known: "Callable[[str], bool] | None" = None
               ) -> tuple[str, np.ndarray | None]:
    """The sha256 of one frame file's bytes and, unless ``known(sha)`` says the cube has it
    already, its band stack (the file's size and time checked unchanged from before the hash
    to after the decode).

    A file is read once: into the thread's buffer, hashed and decoded from there (TIFFs by
    tifffile over that buffer, :func:`pipeline.ingest.tiff.tiff_pixels`). Hashing the
    file as a stream and then decoding it from the file took a 4.4 MB snapshot frame 3.9 ms
    of CPU, against 3.3 ms this way.

    :class:`FrameError` naming the file if it is unreadable, unusable, or changed while it was
    being read (a copy still in progress).
    """
    try:
        st0 = rec.path.stat()
        data = read_whole(rec.path, st0.st_size, "run ingest again") if st0.st_size <= READ_ONCE_MAX_BYTES else None
        sha = hashlib.sha256(data).hexdigest() if data is not None else file_sha256(rec.path)
    except OSError as exc:
        raise FrameError(f"cannot read: {exc.strerror}", path=rec.path) from None
    if known is not None and known(sha):
        return sha, None  # known: never decoded again
    try:
        bands = stored_bands(rec.path if data is None else data, rec.path, camera)
    except FrameError:
        raise
    except InputError as exc:  # e.g. the mosaic split of a frame too small for the camera
        raise FrameError(exc.reason, path=rec.path, hint=exc.hint) from None
    try:
        st1 = rec.path.stat()
    except OSError as exc:
        raise FrameError(f"cannot read: {exc.strerror}", path=rec.path) from None
    if (st0.st_size, st0.st_mtime_ns) != (st1.st_size, st1.st_mtime_ns):
        raise FrameError("the file changed while it was being read", path=rec.path, hint="run ingest again")
    return sha, bands


def _examine(
    rec: FrameRecord, camera: Camera, in_cube: dict[str, str], cube_shas: dict[str, str]
) -> tuple[str, np.ndarray | None]:
    """:func:`read_frame`, decoding only frames whose name and content the cube does not hold."""
    return read_frame(rec, camera, lambda sha: rec.name in in_cube or sha in cube_shas)


def shape_problem(bands_shape: tuple[int, ...], cube_shape: tuple[int, ...] | None) -> str | None:
    """Why a frame's band stack does not fit the cube (None if it does)."""
    if cube_shape is None or tuple(bands_shape) == tuple(cube_shape):
        return None
    b, c = bands_shape, cube_shape
    return (f"its band stack is {b[0]}x{b[1]}x{b[2]} but the datacube's is "
            f"{c[0]}x{c[1]}x{c[2]} (bands x rows x columns)")


def frame_row(rec: FrameRecord, sha: str) -> dict:
    """One frame's values of the cube's frame coordinates (as :meth:`CubeWriter.commit` stores them)."""
    return {
        "frame": rec.name,
        "exposure_ms": float(rec.exposure_ms),
        "gain": float(rec.gain),
        "time": time_ns(rec.time),
        "lat": _nan(rec.lat),
        "lon": _nan(rec.lon),
        "alt_m": _nan(rec.alt_m),
        "source_file": rec.path.name,
        "sha256": sha,
    }


def _column(name: str, values: list) -> np.ndarray:
    if name == "time":
        return np.array(values, dtype=np.int64)
    if name in STRING_COORDS:
        return np.array(values, dtype=np.dtypes.StringDType())
    return np.array(values, dtype=np.float64)


def frame_coords(camera: Camera, rows: list[dict]):
    """The cube's frame coordinates of ``rows`` (:func:`frame_row`) as an ``xarray.Dataset``,
    decoded as ``xarray.open_zarr`` gives them (time as datetime64[ns], NaT if unknown)."""
    template = _template(camera, (camera.n_bands, 0, 0))
    coords = {}
    for name in FRAME_COORDS:
        col = _column(name, [row[name] for row in rows])
        if name == "time":
            col = col.astype("datetime64[ns]")
        elif name in STRING_COORDS:
            col = col.astype(object)
        coords[name] = ("frame", col, dict(template[name].attrs))
    import xarray as xr

    return xr.Dataset(coords=coords)


def _consolidate(path: Path) -> None:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        zarr.consolidate_metadata(str(path))


def _set_committed(path: Path, n: int) -> None:
    """Write ``frames_committed`` (the commit point), keeping the consolidated metadata."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        g = zarr.open_group(str(path), mode="r+", use_consolidated=True)
        g.attrs.update({"frames_committed": int(n)})


# --------------------------------------------------------------------------- the cube


def _template(camera: Camera, shape: tuple[int, int, int]):
    """A cube with zero frames (an ``xarray.Dataset``): variables, coordinates, attributes."""
    import xarray as xr  # only to create a cube: appending needs zarr alone

    nb, h, w = shape
    sdt = np.dtypes.StringDType()
    none = np.zeros(0)
    ds = xr.Dataset(
        {
            "dn": (
                ("frame", "band", "y", "x"),
                np.zeros((0, nb, h, w), np.uint16),
                {
                    "long_name": "raw digital number (as stored by the camera, band grid)",
                    "units": "1",
                    "valid_min": 0,
                    "valid_max": camera.dn_max,
                },
            ),
            DN_MEDIAN: (("frame", "band"), np.zeros((0, nb), np.float64), dict(DN_MEDIAN_ATTRS)),
        },
        coords={
            "frame": ("frame", np.array([], dtype=sdt), dict(FRAME_COORD_ATTRS["frame"])),
            "exposure_ms": ("frame", none, dict(FRAME_COORD_ATTRS["exposure_ms"])),
            "gain": ("frame", none, dict(FRAME_COORD_ATTRS["gain"])),
            "time": ("frame", np.array([], dtype="datetime64[ns]"), dict(FRAME_COORD_ATTRS["time"])),
            "lat": ("frame", none, dict(FRAME_COORD_ATTRS["lat"])),
            "lon": ("frame", none, dict(FRAME_COORD_ATTRS["lon"])),
            "alt_m": ("frame", none, dict(FRAME_COORD_ATTRS["alt_m"])),
            "source_file": ("frame", np.array([], dtype=sdt), {"long_name": "file name in the flight folder"}),
            "sha256": ("frame", np.array([], dtype=sdt), {"long_name": "SHA-256 of the source file"}),
            "band": ("band", np.arange(nb), dict(FRAME_COORD_ATTRS["band"])),
            "band_name": ("band", np.array(camera.band_names, dtype=sdt), {"long_name": "band name"}),
            "wavelength": ("band", camera.wavelengths, {"long_name": "centre wavelength", "units": "nm"}),
        },
        attrs={
            "Conventions": "CF-1.10",
            "title": "mscal raw flight datacube",
            "source": "mscal ingest (raw frames and per-frame metadata of one flight)",
            "format": RAW_FORMAT,
            "camera": camera.name,
            "bit_depth": camera.bit_depth,
            "mscal_version": mscal_core.__version__,
            "frame_order": "file name order at first ingest; later frames appended in file name order",
            "frames_committed": 0,
        },
    )
    return ds


def raw_codec():  # zarr.codecs.BloscCodec
    """Codec of the raw DN cubes: Blosc lz4 level 1 on bit-shuffled uint16. Measured per frame
    (one thread): full-resolution Ximea (4.4 MB) 2.3 ms for 1.86x, against 9.7 ms for 1.94x
    with zstd level 1; MicaSense RedEdge band files 1.4-1.7x, always within 6 % of zstd's
    ratio at a quarter of its CPU. Byte shuffle instead of bit shuffle: 1.65x. The apply pass
    is bound by CPU and written bytes together, and zstd's extra 4 % of bytes cost less than
    its 7 ms. Existing cubes keep the codec their metadata names."""
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle", typesize=2)


def _encoding(shape: tuple[int, int, int], compress: bool = True) -> dict:
    codec = raw_codec()
    enc: dict = {"dn": frame_encoding((0, *shape), (codec,) if compress else None),
                 # one chunk per frame, as dn: written by whoever writes the frame's dn chunk
                 DN_MEDIAN: frame_encoding((0, shape[0]), None)}
    for name in FRAME_COORDS:
        enc[name] = {"chunks": (COORD_CHUNK,)}
    enc["time"].update({"units": TIME_UNITS, "calendar": "proleptic_gregorian", "dtype": "int64"})
    return enc


def _create(out: Path, camera: Camera, shape: tuple[int, int, int], compress: bool = True) -> None:
    """Create the empty cube under a temporary name and rename it into place."""
    with atomic_folder(out) as tmp:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Consolidated metadata")
            _template(camera, shape).to_zarr(
                tmp, mode="w", encoding=_encoding(shape, compress), consolidated=True, zarr_format=3
            )


def _root_meta(out: Path) -> dict:
    with (out / "zarr.json").open() as fh:
        return json.load(fh)


def _open(out: Path, camera: Camera) -> tuple[zarr.Group, int]:
    """Open the cube for appending and cut off anything beyond the committed frames."""
    bad = InputError(
        "not an mscal raw datacube (or damaged)",
        path=out,
        hint="remove it (or choose another output folder) to ingest the flight afresh",
    )
    try:
        root = _root_meta(out)
        g = zarr.open_group(str(out), mode="r+", use_consolidated=False)
        attrs = dict(g.attrs)
        arrays = {name: g[name] for name in FRAME_VARS}
        if DN_MEDIAN in g:  # cubes written before it was kept have none
            arrays[DN_MEDIAN] = g[DN_MEDIAN]
    except Exception:
        raise bad from None
    if attrs.get("format") != RAW_FORMAT or not isinstance(attrs.get("frames_committed"), int):
        raise bad
    if attrs.get("camera") != camera.name:
        raise InputError(
            f"the datacube holds frames of camera {attrs.get('camera')!r}, not {camera.name!r}",
            path=out,
            hint="use another output folder for this flight",
        )
    if arrays["time"].attrs.get("units") != TIME_UNITS:
        raise bad
    n = attrs["frames_committed"]
    changed = False
    for name, arr in arrays.items():
        if arr.shape[0] < n:
            raise bad
        if arr.shape[0] > n:  # a killed run: drop its uncommitted frames
            arr.resize((n, *arr.shape[1:]))
            changed = True
    stale = changed or not _consolidated_matches(root, arrays)
    # temporaries of writes that were killed (harmless to readers, but not left behind): zarr's
    # (.partial) and those of pipeline.storage.atomic (TMP_MARK)
    for pattern in ("*.partial", f"*{TMP_MARK}*"):
        for p in out.rglob(pattern) if stale else [*out.glob(pattern), *out.glob(f"*/{pattern}")]:
            if p.is_file():
                p.unlink(missing_ok=True)
    if stale:
        for name in ("dn", DN_MEDIAN):
            if (chunks := FrameChunks.open(out / name)) is not None:
                chunks.remove_from(n)
        _consolidate(out)
        _set_committed(out, n)
    return g, n


def _consolidated_matches(root: dict, arrays: dict[str, zarr.Array]) -> bool:
    """Whether the consolidated metadata (what readers see) has the arrays' real shapes."""
    try:
        meta = root["consolidated_metadata"]["metadata"]
        return all(tuple(meta[name]["shape"]) == tuple(arr.shape) for name, arr in arrays.items())
    except (KeyError, TypeError):
        return False


def cube_lock(out: Path) -> FolderLock:
    """The lock of the raw datacube ``out``: one ingest into it at a time. A file beside the
    cube (``.raw.zarr.lock``, as :func:`pipeline.storage.outputs.guarded_output` locks a
    store), not the output folder's own ``.mscal.lock`` that ``mscal apply`` and ``run`` hold
    while they ingest; a second process is refused at once, naming the first."""
    return FolderLock(out.parent, name=f".{out.name}.lock", what="another mscal process", output=out)


# --------------------------------------------------------------------------- ingest


@dataclass
class Cube:
    """An open raw datacube, locked for appending (:func:`open_cube`); ``release()`` it."""

    path: Path
    camera: Camera
    found: Discovery
    lock: FolderLock
    group: zarr.Group | None
    committed: int
    shape: tuple[int, int, int] | None
    names: list[str]
    shas: list[str]

    def release(self) -> None:
        self.lock.release()


def open_cube(flight_dir: str | Path, camera: Camera | str, out_zarr: str | Path, *, compress: bool = True) -> Cube:
    """Discover the flight's frames, lock the cube's folder, and open the cube (created empty
    if the camera fixes the band grid; uncommitted frames of a killed run cut off)."""
    flight_dir, out = Path(flight_dir), Path(out_zarr)
    if isinstance(camera, str):
        camera = load_camera(camera)
    found = discover_flight(flight_dir, camera)
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = cube_lock(out).acquire()
    try:
        for p in out.parent.glob(f".{out.name}{TMP_MARK}*"):  # a killed creation
            shutil.rmtree(p, ignore_errors=True)
        shape = _band_shape(camera)
        if not out.exists() and shape is not None:
            _create(out, camera, shape, compress)
        group, committed = _open(out, camera) if out.exists() else (None, 0)
        if group is not None:
            shape = tuple(group["dn"].shape[1:])
            names = [str(s) for s in group["frame"][:]]
            shas = [str(s) for s in group["sha256"][:]]
        else:
            names, shas = [], []
    except BaseException:
        lock.release()
        raise
    return Cube(out, camera, found, lock, group, committed, shape, names, shas)


def ingest_flight(
    flight_dir: str | Path,
    camera: Camera | str,
    out_zarr: str | Path,
    *,
    workers: int = 2,
    commit_every: int = 32,
    compress: bool = True,
    cube: Cube | None = None,
) -> IngestResult:
    """Ingest (append) the frames of ``flight_dir`` into the raw datacube ``out_zarr``.

    ``cube``: the cube as :func:`open_cube` just opened it (discovered and locked), if the
    caller has it; it is released here.

    ``workers`` threads hash, read and demosaic frames and write their chunks;
    ``commit_every`` frames are made durable at a time (a kill loses at most that much work);
    ``compress`` chooses the codec of a cube created now (an existing cube keeps its own).

    Returns counts and the frames quarantined in this run (each ``{"file", "reason"}``, the
    reason naming the file). Raises :class:`SessionError` for a flight folder or ``frames.csv``
    that cannot be read at all, :class:`InputError` for an output that is not an mscal raw
    datacube of this camera, :class:`LockedError` for one another process is writing.
    """
    t_start = _time.perf_counter()
    if cube is None:
        cube = open_cube(flight_dir, camera, out_zarr, compress=compress)
    camera, out, found, lock, group = cube.camera, cube.path, cube.found, cube.lock, cube.group
    committed, shape = cube.committed, cube.shape
    quarantined = list(found.quarantined)
    try:
        in_cube = dict(zip(cube.names, cube.shas))
        cube_by_sha = {s: n for n, s in in_cube.items()}
        new_by_sha: dict[str, str] = {}
        present = 0

        with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="mscal-ingest") as pool:
            writer = CubeWriter(out, group, committed, shape, camera, commit_every, pool, workers, compress)
            for rec, fut in _examined_in_order(found.frames, pool, 2 * max(1, workers), camera, in_cube, cube_by_sha):
                fname = rec.path.name
                try:
                    sha, bands = fut.result()
                except FrameError as exc:
                    quarantined.append(quarantine_entry(fname, exc))
                    continue
                seen = _already_seen(rec, sha, in_cube, cube_by_sha, new_by_sha)
                if seen == "present":
                    present += 1
                    continue
                if seen is not None:
                    quarantined.append(quarantine_entry(fname, seen))
                    continue
                assert bands is not None
                problem = writer.add(rec, sha, bands)
                del bands
                if problem:
                    quarantined.append(quarantine_entry(fname, FrameError(problem, path=rec.path)))
                else:
                    new_by_sha[sha] = rec.name
            writer.commit()
            if writer.group is None:  # nothing decodable and no size known: an empty cube
                _create(out, camera, (camera.n_bands, 0, 0))
                writer.group, writer.committed = _open(out, camera)
    finally:
        lock.release()

    quarantined.sort(key=lambda q: q["file"])
    result = IngestResult(
        path=out,
        frames_added=len(writer.added),
        frames_already_present=present,
        quarantined=quarantined,
        n_frames=writer.committed,
        added=writer.added,
        seconds=round(_time.perf_counter() - t_start, 3),
    )
    log.info("ingest %s: %d added, %d already present, %d quarantined, %d frames in %.1f s",
             flight_dir, result.frames_added, present, len(quarantined), result.n_frames, result.seconds)
    return result


def _examined_in_order(frames: list[FrameRecord], pool: ThreadPoolExecutor, lookahead: int, camera: Camera,
                       in_cube: dict[str, str], cube_by_sha: dict[str, str]) -> Iterator[tuple[FrameRecord, Future]]:
    """Each frame in file-name order with the future of :func:`_examine` (hash it; decode it
    only if it is new). Tasks run up to ``lookahead`` frames ahead in the pool; results are
    taken in order, so frame indices and quarantine decisions do not depend on timing."""
    window: deque[tuple[FrameRecord, Future]] = deque()
    todo = iter(frames)

    def refill() -> None:
        while len(window) < lookahead:
            rec = next(todo, None)
            if rec is None:
                return
            window.append((rec, pool.submit(_examine, rec, camera, in_cube, cube_by_sha)))

    refill()
    while window:
        rec, fut = window.popleft()
        refill()
        yield rec, fut


def _already_seen(rec: FrameRecord, sha: str, in_cube: dict[str, str], cube_by_sha: dict[str, str],
                  new_by_sha: dict[str, str]) -> str | FrameError | None:
    """``"present"`` if the cube holds this frame, the :class:`FrameError` to quarantine it
    with if its name is in the cube with other content or its content is there under another
    name (or was added in this run), None for a new frame."""
    if rec.name in in_cube:
        if in_cube[rec.name] == sha:
            return "present"
        return FrameError(
            "changed since ingest: its content differs from the frame of that name in the datacube",
            path=rec.path,
            hint="the datacube keeps the frame as first ingested; give a new frame a new name",
        )
    twin = cube_by_sha.get(sha) or new_by_sha.get(sha)
    if twin is not None:
        return FrameError(f"same content as frame {twin} (a duplicate)", path=rec.path)
    return None


class CubeWriter:
    """Appends frames to the cube: whole chunks first, coordinates next, commit counter last.

    Chunks are written by the pool's threads, each a whole chunk of its own frame index
    (never two writers on one chunk); ``dn`` is resized only when no write is in flight.
    """

    def __init__(self, out: Path, group: zarr.Group | None, committed: int, shape, camera: Camera,
                 commit_every: int, pool: ThreadPoolExecutor, workers: int, compress: bool = True):
        self.out, self.group, self.committed = out, group, committed
        self.compress = compress
        self.shape = None if shape is None else tuple(shape)
        self.camera = camera
        self.commit_every = max(1, commit_every)
        self.pool = pool
        self.max_writes = max(1, workers) + 1  # chunk writes in flight (memory bound)
        self.writes: deque[Future] = deque()
        self.dn: zarr.Array | None = None
        self.medians: zarr.Array | None = None  # DN_MEDIAN, if the cube keeps it
        self.n = committed  # frames whose chunk is written or being written
        self.pending: list[dict] = []
        self.added: list[str] = []
        self.n_commits = 0

    def _dn(self) -> zarr.Array:
        if self.dn is None:
            assert self.group is not None
            # a whole new frame is written at once: no need to look for all-fill chunks
            # (open_array's config= is not honoured in zarr 3.1; with_config is)
            self.dn = zarr.open_array(str(self.out / "dn"), mode="r+").with_config({"write_empty_chunks": True})
            medians = kept_medians(self.out)
            if medians is not None:
                self.medians = zarr.open_array(str(medians), mode="r+")
        return self.dn

    def _resize(self, n: int, delete: bool = True) -> None:
        """``dn`` (and the medians) to ``n`` frames; ``delete=False`` keeps the chunks beyond
        (metadata only: others are writing them)."""
        for arr in (self._dn(), self.medians):
            if arr is None or arr.shape[0] == n:
                continue
            if delete:
                arr.resize((n, *arr.shape[1:]))
            else:
                sync(arr.async_array.resize((n, *arr.shape[1:]), delete_outside_chunks=False))

    def add(self, rec: FrameRecord, sha: str, bands: np.ndarray) -> str | None:
        """Write one frame's chunk; returns a reason instead if it does not fit the cube."""
        if self.group is None:  # the first frame fixes the band grid of cameras without one
            _create(self.out, self.camera, tuple(bands.shape), self.compress)
            self.group, self.committed = _open(self.out, self.camera)
            self.shape = tuple(bands.shape)
        problem = shape_problem(bands.shape, self.shape)
        if problem:
            return problem
        dn = self._dn()
        if not self.pending:  # a new batch: room for it beyond the committed frames
            self._resize(self.committed + self.commit_every)
        self.writes.append(self.pool.submit(_write_chunk, dn, self.medians, self.n, bands))
        self.n += 1
        self.pending.append(frame_row(rec, sha))
        self._drain(self.max_writes)
        if len(self.pending) >= self.commit_every:
            self.commit()
        return None

    def reserve(self, n_frames: int) -> int:
        """Room for ``n_frames`` more frames beyond those written or being written, for chunks
        that others write (:meth:`register` them in order); returns the first new index."""
        if self._dn().shape[0] < self.n + n_frames:
            self._resize(self.n + n_frames)
        return self.n

    def register(self, rec: FrameRecord, sha: str) -> None:
        """Frame ``rec``'s whole chunk was written at index ``self.n`` by someone else."""
        self.n += 1
        self.pending.append(frame_row(rec, sha))

    def _drain(self, limit: int) -> None:
        while len(self.writes) > limit:
            self.writes.popleft().result()

    def commit(self, room: int = 0) -> None:
        """Make the frames registered so far durable. ``room``: frames beyond them whose
        chunks others are still writing (a pass that commits while its workers go on): their
        chunks are kept and ``dn`` grows back over them once the commit is made, so that
        what readers see (the consolidated metadata) is always the committed frames, and a
        killed run's frames beyond are cut off on open as before."""
        self._drain(0)
        g = self.group
        if g is None or (not self.pending and self._dn().shape[0] == self.committed):
            return
        k0, n = self.committed, self.n
        self.n_commits += 1
        for name in FRAME_COORDS:
            arr = g[name]
            if arr.shape[0] != n:
                arr.resize((n,))
            arr[k0:n] = _column(name, [row[name] for row in self.pending])
        self._resize(n, delete=room <= 0)
        _consolidate(self.out)
        if room > 0:  # before the count: a run killed after it is cut back on open, chunks and all
            self._resize(n + room)
        _set_committed(self.out, n)
        self.added.extend(row["frame"] for row in self.pending)
        self.pending.clear()
        self.committed = n


def _write_chunk(dn: zarr.Array, medians: zarr.Array | None, index: int, bands: np.ndarray) -> None:
    dn[index] = bands  # exactly one whole chunk
    if medians is not None:
        medians[index] = band_medians(bands)  # its own chunk too
