"""One folder's band files grouped into captures (:class:`Capture`: a capture's bands'
metadata in catalog order, checked complete and of one capture id), the images beside them
that are no band files, and a capture's pixels.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
from mscal_core.errors import FrameError

from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.cameras.dispatch import companion_image_patterns, sibling_position
from pipeline.ingest.meta import CaptureMeta
from pipeline.ingest.xmp import TagProblem

if TYPE_CHECKING:
    from pipeline.ingest.catalog import Camera

DEFAULT_CAPTURE_PATTERN = r"^(?P<capture>.+)_(?P<band>[0-9]+)\.tif$"


@dataclass(frozen=True)
class Capture:
    """One capture: its bands' metadata in band (catalog) order, and the files of bands that
    are read but not part of reflectance (``skipped``: ``{file, band, reason}``)."""

    name: str  # file name stem without the band suffix, e.g. IMG_0000
    capture_id: str
    metas: tuple[CaptureMeta, ...]  # ordered by band (catalog order, else by suffix)
    skipped: tuple[dict[str, str], ...] = ()

    @property
    def files(self) -> tuple[Path, ...]:
        out: list[Path] = []
        for m in self.metas:
            if m.path not in out:
                out.append(m.path)
        return tuple(out)

    @property
    def problems(self) -> list[TagProblem]:
        seen: list[TagProblem] = []
        for m in self.metas:
            for p in m.problems:
                if p not in seen:
                    seen.append(p)
        return seen


def capture_pattern(camera: Camera | None) -> re.Pattern[str]:
    """The file-name pattern of a camera's captures (named groups ``capture`` and ``band``)."""
    text = (camera.layout.capture_pattern if camera is not None else None) or DEFAULT_CAPTURE_PATTERN
    return re.compile(text)


#: Images a camera saves beside its band files that are not band files, by catalog camera: the
#: file-name pattern (group ``capture``: the capture the image belongs to, as the camera's
#: ``capture_pattern`` names it in its band files) and why the image is left out; each maker's
#: (:attr:`pipeline.ingest.cameras.registry.Maker.companion_images`).
COMPANION_IMAGES: dict[str, tuple[str, str]] = companion_image_patterns()


def companion_images(files: Sequence[Path], camera: Camera) -> dict[Path, str]:
    """Of ``files``, the images ``camera`` saves with its band files (:data:`COMPANION_IMAGES`)
    whose capture has band files among ``files`` in the same folder, with why each is left
    out of the captures. A file only named like one (no band file of its capture beside it)
    is not one."""
    entry = COMPANION_IMAGES.get(camera.name)
    if entry is None:
        return {}
    companion, reason = re.compile(entry[0]), entry[1]
    bands = capture_pattern(camera)
    captures = {(p.parent, m["capture"]) for p in files if (m := bands.match(p.name)) is not None}
    out = {}
    for p in files:
        m = companion.match(p.name)
        if m is not None and not bands.match(p.name) and (p.parent, m["capture"]) in captures:
            out[p] = reason
    return out


def group_captures(
    folder: str | Path, camera: Camera | None = None
) -> tuple[list[Capture], list[dict[str, str]]]:
    """Group a folder's band files into captures by their name and check them.

    With ``camera`` its ``capture_pattern`` and band list are used: every band's file must be
    present and its XMP BandName must be the catalog's (case aside); files of the camera's
    ``skip_bands`` (a panchromatic or thermal band) are named in ``Capture.skipped``. Without
    it, the band suffixes seen in the folder are expected in every capture. The band files of
    one capture must carry one XMP capture id, and no two captures may share one (the later
    name is a copy). One file holding several bands (a Sentera JPEG) is one capture. A
    ``folder_per_band`` camera (Sentera 6X) is given its session folder: the files of one name
    in its band folders are one capture, each band known by its XMP BandName.

    Returns the complete captures (sorted by name) and one problem per incomplete or unusable
    capture as ``[{file, reason}]`` (``file`` the offending band file, else the capture's first
    file), for the run's quarantine list.
    """
    folder = Path(folder)
    pattern = capture_pattern(camera)
    per_file = camera is not None and camera.layout.kind == "file_per_capture"
    per_folder = camera is not None and camera.layout.kind == "folder_per_band"
    skip = {s.name.casefold(): s for s in (camera.skip_bands if camera is not None else ())}
    by_name: dict[str, dict[str, CaptureMeta]] = {}
    unusable: dict[str, list[tuple[Path, str]]] = {}
    skipped: dict[str, list[dict[str, str]]] = {}
    for path in band_files(folder, per_folder):
        m = pattern.match(path.name)
        if m is None or not path.is_file():
            continue
        bands = by_name.setdefault(m["capture"], {})
        try:
            metas = read_file_metas(path)
        except FrameError as exc:
            s = next((s for s in skip.values() if not (per_file or per_folder) and s.file_suffix == m["band"]), None)
            if s is not None:  # the file of a band kept out of reflectance anyway: named, not fatal
                skipped.setdefault(m["capture"], []).append(
                    {"file": str(path), "band": s.name, "reason": f"{s.reason}; unreadable: {exc.reason}"})
            else:
                unusable.setdefault(m["capture"], []).append((path, exc.reason))
            continue
        if per_file:
            for meta in metas:
                bands[str(meta.channel)] = meta
        elif per_folder:  # a band folder's file: the band is its XMP BandName
            key = metas[0].band_name.casefold()
            if key in bands:
                unusable.setdefault(m["capture"], []).append(
                    (path, f"band {metas[0].band_name} also in {bands[key].path.parent.name}/ (two folders of one band?)"))
            bands[key] = metas[0]
        else:
            bands[m["band"]] = metas[0]
    for name, bands in by_name.items():  # bands kept out of reflectance, recognised by their XMP BandName
        for key in [k for k, meta in bands.items() if meta.band_name.casefold() in skip]:
            s = skip[bands[key].band_name.casefold()]
            skipped.setdefault(name, []).append({"file": str(bands[key].path), "band": s.name, "reason": s.reason})
            del bands[key]
    problems: list[dict[str, str]] = []
    captures: list[Capture] = []
    owner: dict[str, str] = {}  # capture id -> the first capture name that carries it
    for name in sorted(by_name):
        bands = by_name[name]
        files = [m.path for m in bands.values()] + [p for p, _ in unusable.get(name, [])]
        files += [Path(s["file"]) for s in skipped.get(name, [])]
        first = min(files)
        if name in unusable:
            (path, why), more = unusable[name][0], len(unusable[name]) - 1
            problems.append({"file": str(path), "reason": f"capture {name}: band file {path.name}: {why}"
                             + (f" (and {more} more unusable band file(s))" if more else "")})
            continue
        expected = _by_band_name(bands, camera) or _expected_suffixes(camera, by_name)
        reason = _capture_problem(bands, expected, name, camera)
        ids = sorted({m.capture_id for m in bands.values() if m.capture_id})
        if reason is None and len(ids) > 1:
            reason = f"capture {name}: its band files carry {len(ids)} different XMP CaptureIds (files of other captures renamed?)"
        cid = ids[0] if ids else name
        if reason is None and cid in owner:
            reason = f"capture {name}: same XMP CaptureId as {owner[cid]} (a copy of that capture?)"
        if reason:
            problems.append({"file": str(first), "reason": reason})
            continue
        owner[cid] = name
        metas = tuple(bands[s] for s in expected)
        captures.append(Capture(name=name, capture_id=cid, metas=metas if per_folder else _placed(name, metas),
                                skipped=tuple(skipped.get(name, []))))
    return captures, problems


def _placed(name: str, metas: tuple[CaptureMeta, ...]) -> tuple[CaptureMeta, ...]:
    """The band files' metadata, positioned from the capture's RGB JPEG
    (:func:`pipeline.ingest.cameras.dispatch.sibling_position`) when none of them has a position of its own."""
    if any(m.lat is not None for m in metas):
        return metas
    pos = sibling_position(metas[0], name)
    return metas if pos is None else tuple(replace(m, lat=pos[0], lon=pos[1], alt_m=pos[2]) for m in metas)


def band_files(folder: Path, per_folder: bool = False) -> list[Path]:
    """The files of a capture folder, sorted; with ``per_folder`` (layout ``folder_per_band``:
    a session folder holding one folder per band) the files of its sub-folders."""
    if not per_folder:
        return sorted(folder.iterdir())
    return sorted((p for d in folder.iterdir() if d.is_dir() and not d.name.startswith(".") for p in d.iterdir()),
                  key=lambda p: (p.name, p.parent.name))


def capture_folder_of(path: Path, camera: Camera) -> Path:
    """The folder :func:`group_captures` takes for a band file of ``camera``: its own, or for
    a ``folder_per_band`` camera the session folder above its band folder."""
    return path.parent.parent if camera.layout.kind == "folder_per_band" else path.parent


def _by_band_name(bands: dict[str, CaptureMeta], camera: Camera | None) -> list[str] | None:
    """The file keys in catalog band order when every catalog band is found, once, by its XMP
    BandName (case aside) and no other band is left: the manufacturer's file numbering then
    does not matter. None otherwise (the suffix check names what is wrong)."""
    if camera is None or len(bands) != camera.n_bands:
        return None
    by = {}
    for key, meta in bands.items():
        by.setdefault(meta.band_name.casefold(), []).append(key)
    keys = []
    for b in camera.bands:
        found = by.get(b.name.casefold(), [])
        if len(found) != 1:
            return None
        keys.append(found[0])
    return keys


def _expected_suffixes(camera: Camera | None, by_id: dict[str, dict[str, CaptureMeta]]) -> list[str]:
    if camera is not None:
        if camera.layout.kind == "file_per_capture":
            return [str(b.channel) for b in camera.bands]
        if camera.layout.kind == "folder_per_band":
            return [b.name.casefold() for b in camera.bands]
        return [str(b.file_suffix) for b in camera.bands]
    seen = {s for bands in by_id.values() for s in bands}
    return sorted(seen, key=lambda s: (len(s), s))


def _capture_problem(
    bands: dict[str, CaptureMeta], expected: list[str], name: str, camera: Camera | None
) -> str | None:
    """Why a capture's files do not make one complete capture, or None."""
    missing = [s for s in expected if s not in bands]
    extra = sorted(set(bands) - set(expected))
    if camera is not None and camera.layout.kind == "file_per_capture":
        extra = []  # channels the catalog does not use (e.g. Sentera's Garbage) are not an error
    if missing or extra:
        named = {str(b.file_suffix): f"{b.file_suffix} ({b.name})" for b in (camera.bands if camera else ())}
        parts = ([f"missing band file(s) {', '.join(named.get(s, s) for s in missing)}"] if missing else []) + (
            [f"unexpected band file(s) {', '.join(extra)}"] if extra else []
        )
        return f"capture {name}: {'; '.join(parts)}"
    if camera is not None:
        wrong = [
            f"_{k} is {bands[k].band_name!r}, catalog says {b.name!r}"
            for k, b in zip(expected, camera.bands)
            if bands[k].band_name.casefold() != b.name.casefold()
        ]
        if wrong:
            return f"capture {name}: band names differ from camera {camera.name}: {'; '.join(wrong)}"
    return None


def capture_irradiance(capture: Capture) -> float | None:
    """One raw irradiance level of a one-file-per-band capture: the mean of its bands' XMP
    Irradiance (each band's sensor reading), None unless every band has one. Only ratios of
    these levels are used (:func:`mscal_core.illumination.frame_illumination`). Kept for
    calibration stores from before horizontal levels (raw ``capture_irradiance``); newer stores use the
    horizontal level of :func:`pipeline.ingest.sunsensor.capture_levels`."""
    values = [m.irradiance for m in capture.metas]
    if not values or any(v is None or not v > 0 for v in values):
        return None
    return float(sum(values) / len(values))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- pixels


def read_capture_pixels(capture: Capture, out: np.ndarray | None = None
                        ) -> tuple[str, list[np.ndarray], dict[Path, np.ndarray]]:
    """Content hash (over the capture's files, in band order), the stored DN of each band
    (its channel, for a multi-channel file) and the whole ``(H, W, C)`` image of every
    multi-channel file (for :func:`factory_radiance`'s colour transform). ``out``: a uint16
    ``(band, H, W)`` cube into which a one-band file of that shape is decoded where it can be
    (its DN are then ``out[b]``; the caller copies the others)."""
    from hashlib import sha256

    from pipeline.ingest.raw import read_whole
    from pipeline.ingest.tiff import decode_raw

    h = sha256()
    decoded: dict[Path, np.ndarray] = {}
    into = _band_slots(capture, out)
    for path in capture.files:  # each read into the thread's buffer, decoded before the next
        data = read_whole(path, path.stat().st_size, "wait for the copy to finish, or re-copy the file")
        h.update(data)
        try:
            decoded[path] = np.asarray(decode_raw(data, path, into.get(path)))
        except FrameError:
            raise
        except Exception as exc:  # tifffile raises IndexError/ValueError on truncated files
            raise FrameError(f"unreadable band file ({type(exc).__name__}: {exc})", path=path) from None
    dns = []
    stacks: dict[Path, np.ndarray] = {}
    for meta in capture.metas:
        img = decoded[meta.path]
        if meta.channel is not None:
            if img.ndim != 3 or img.shape[2] <= meta.channel:
                raise FrameError(f"image {img.shape} has no channel {meta.channel} (band {meta.band_name})",
                                 path=meta.path)
            stacks[meta.path] = img
            img = img[:, :, meta.channel]
        if img.shape != meta.shape:
            raise FrameError(f"image {img.shape} does not match its metadata {meta.shape}", path=meta.path)
        dns.append(np.asarray(img).astype(np.uint16, copy=False))
    return h.hexdigest(), dns, stacks


def _band_slots(capture: Capture, out: np.ndarray | None) -> dict[Path, np.ndarray]:
    """``out[b]`` of each one-band file whose shape it has (:func:`read_capture_pixels`)."""
    if out is None or out.ndim != 3 or out.dtype != np.uint16 or len(capture.metas) != out.shape[0]:
        return {}
    per_file: dict[Path, int] = {}
    for meta in capture.metas:
        per_file[meta.path] = per_file.get(meta.path, 0) + 1
    return {m.path: out[b] for b, m in enumerate(capture.metas)
            if m.channel is None and per_file[m.path] == 1 and tuple(m.shape) == out.shape[1:]}
