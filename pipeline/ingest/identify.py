"""Which catalog camera wrote a folder of captures, from the files' own metadata.

The camera is recognised from EXIF Make/Model and the XMP camera tags of a whole capture --
``Camera:RigName``, the band names and how many band files share one capture id
(``MicaSense:CaptureId``, ``Camera:CaptureUUID``, ``drone-dji:CaptureUUID``) -- never from one
file's name or band name: a RedEdge-MX Dual capture is ten files with one CaptureId, a RedEdge
capture five. Each catalog camera with a ``factory_model`` says how it is recognised
(``identify`` in ``catalogs/cameras/<name>.yaml``). ``--camera NAME`` skips all this.
"""

from __future__ import annotations

import fnmatch
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mscal_core.errors import FrameError, InputError

from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.catalog import Camera, list_entries, load_camera
from pipeline.ingest.grouping import COMPANION_IMAGES, companion_images
from pipeline.ingest.meta import CaptureMeta

IMAGE_SUFFIXES = (".tif", ".tiff", ".jpg", ".jpeg")
PROBE_FILES = 24  # band files read to recognise a camera (metadata only)


@dataclass
class Probe:
    """What the first band files of a folder say about their camera."""

    folder: Path
    metas: list[CaptureMeta] = field(default_factory=list)
    unreadable: list[tuple[Path, str]] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)  # a camera's other images (DJI's RGB JPEGs)
    cut: Path | None = None  # the last file read when the folder had more: its capture may be partial

    def captures(self) -> list[list[CaptureMeta]]:
        """The files read, grouped by capture id (and by name without its last ``_part``, so
        that a copied capture stays apart; a file without an id is a capture of its own)."""
        groups: dict[tuple[str, str], list[CaptureMeta]] = {}
        for m in self.metas:
            key = (m.capture_id or str(m.path), m.path.stem.rsplit("_", 1)[0] if m.capture_id else "")
            if m not in groups.setdefault(key, []):
                groups[key].append(m)
        return list(groups.values())

    def best_capture(self) -> list[CaptureMeta]:
        """The band files of one typical capture: of :meth:`captures`, a group of the most
        common size (an incomplete capture does not decide), the largest of those."""
        groups = self.captures()
        if not groups:
            return []
        sizes = Counter(len(g) for g in groups)
        return max(groups, key=lambda g: (sizes[len(g)], len(g)))

    def describe(self) -> dict[str, object]:
        cap = self.best_capture()
        first = cap[0] if cap else None
        return {
            "make": first.make if first else None,
            "model": first.model if first else None,
            "rig_name": first.rig_name if first else None,
            "serial": first.serial if first else None,
            "firmware": first.software if first else None,
            "bands_per_capture": len(cap),
            "band_names": [m.band_name for m in sorted(cap, key=_band_order)],
        }


def _band_order(m: CaptureMeta) -> tuple[int, str]:
    return (m.rig_camera_index if m.rig_camera_index is not None else 10**6, m.path.name)


def probe_folder(folder: str | Path, limit: int = PROBE_FILES) -> Probe:
    """Read the metadata of the folder's first ``limit`` image files: its own, then (an SD
    card's ``0000SET/000/``) those of the folders below it, by depth, then name, then folder
    (hidden folders left out): files of one name in sibling folders (a Sentera 6X session's
    band folders) are read together. The images a catalog camera saves beside its band files
    (a DJI P4 Multispectral's RGB ``DJI_XXX0.JPG``: :func:`companion_images`) are not read,
    but named in ``Probe.skipped``."""
    folder = Path(folder)
    probe = Probe(folder)
    files = sorted((p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                    and not any(part.startswith(".") for part in p.relative_to(folder).parts)),
                   key=lambda p: (len(p.relative_to(folder).parts), p.name, p))
    others: dict[Path, str] = {}
    for name in sorted(set(COMPANION_IMAGES) & set(list_entries("cameras"))):
        others.update(companion_images(files, load_camera(name)))
    probe.skipped = [(p, others[p]) for p in files if p in others]
    files = [p for p in files if p not in others]
    if len(files) > limit:
        probe.cut = files[limit - 1]
    for path in files[:limit]:
        try:
            probe.metas.extend(read_file_metas(path))
        except FrameError as exc:
            probe.unreadable.append((path, exc.reason))
    return probe


def factory_cameras() -> list[Camera]:
    """The catalog cameras whose files carry a factory radiometric model."""
    out = []
    for name in list_entries("cameras"):
        cam = load_camera(name)
        if cam.factory_model is not None and cam.identify is not None:
            out.append(cam)
    return out


def _matches(pattern: str, value: str | None) -> bool:
    return value is not None and fnmatch.fnmatchcase(value.casefold(), pattern.casefold())


def score(camera: Camera, probe: Probe) -> int | None:
    """How well a camera fits the probe (higher is better), None if it cannot be it."""
    return score_capture(camera, probe.best_capture())


def score_capture(camera: Camera, cap: list[CaptureMeta]) -> int | None:
    """How well a camera fits the band files of one capture, None if it cannot be it.

    A capture with fewer files than the camera writes still fits a camera its EXIF Model
    names (``identify.models``): one whose reflectance bands are all there and only files of
    ``skip_bands`` are missing (a RedEdge-P copied without its panchromatic files) scores one
    point less than a whole capture; one that lacks a reflectance band scores two less (the
    camera is known; the capture is quarantined with the band named). Without a Model to go
    by, the files of a capture must be all there."""
    ident = camera.identify
    if ident is None or not cap:
        return None
    first = cap[0]
    if (first.make or "").casefold() != ident.make.casefold():
        return None
    points = 1
    named = False  # the EXIF Model names the camera
    if ident.models:
        if not any(_matches(m, first.model) for m in ident.models):
            return None
        points += 4
        named = True
    if ident.rig_names:
        if not any(_matches(r, first.rig_name) for r in ident.rig_names):
            return None
        points += 2
    names = Counter(m.band_name.casefold() for m in cap)
    reflectance = all(names[b.name.casefold()] for b in camera.bands)
    if ident.bands_per_capture is not None:
        missing = ident.bands_per_capture - len(cap)  # every band file of one capture id, skipped bands included
        if missing == 0:
            points += 2
        elif not (named and missing > 0):
            return None
        elif reflectance and missing <= len(camera.skip_bands):
            points += 1  # only files of bands kept out of reflectance are missing
    if not reflectance:
        if not named:
            return None
        return points - 1
    return points + 1


@dataclass(frozen=True)
class Identification:
    camera: Camera
    evidence: str  # what in the files named it
    probe: dict[str, object]
    overridden: bool = False


def identify_camera(folder: str | Path, name: str | None = None) -> Identification:
    """The catalog camera of a capture folder (``name``: given with ``--camera``, not guessed)."""
    folder = Path(folder)
    probe = probe_folder(folder)
    if name is not None:
        return Identification(load_camera(name), f"--camera {name}", probe.describe(), overridden=True)
    desc = probe.describe()
    if not probe.metas:
        why = "; ".join(f"{p.name}: {r}" for p, r in probe.unreadable[:2])
        raise InputError("no TIFF with factory radiometric metadata (nor a JPEG) in the folder" + (f" ({why})" if why else ""),
                         path=folder, hint="give the folder of the camera's band files, or name it with --camera NAME")
    scored = [(s, c) for c in factory_cameras() if (s := score(c, probe)) is not None]
    if not scored:
        known = ", ".join(c.name for c in factory_cameras())
        raise InputError(
            f"no catalog camera matches Make {desc['make']!r}, Model {desc['model']!r}, rig {desc['rig_name']!r}, "
            f"{desc['bands_per_capture']} band(s) per capture {desc['band_names']}",
            path=folder, hint=f"name it with --camera NAME (known: {known}) or add catalogs/cameras/NAME.yaml")
    scored.sort(key=lambda sc: -sc[0])
    if len(scored) > 1 and scored[0][0] == scored[1][0]:
        raise InputError(f"the files fit cameras {scored[0][1].name} and {scored[1][1].name} equally",
                         path=folder, hint="name it with --camera NAME")
    cam = scored[0][1]
    _check_one_camera(probe)
    evidence = (f"EXIF Make {desc['make']!r}, Model {desc['model']!r}"
                + (f", XMP RigName {desc['rig_name']!r}" if desc["rig_name"] else "")
                + f", {desc['bands_per_capture']} band(s) per capture id: {', '.join(map(str, desc['band_names']))}")
    return Identification(cam, evidence, desc)


def _check_one_camera(probe: Probe) -> None:
    """An :class:`InputError` when complete captures of another catalog camera sit in the
    folder tree beside the first's (a Sentera Double 4K card's NDRE/ and nRGB/ folders): one
    run would keep one camera's captures and quarantine the other's as incomplete."""
    cams = factory_cameras()
    where: dict[str, set[str]] = {}
    for cap in probe.captures():
        if probe.cut is not None and any(m.path == probe.cut for m in cap):
            continue  # possibly cut short by the probe's limit
        scored = sorted(((s, c.name) for c in cams if (s := score_capture(c, cap)) is not None), reverse=True)
        if not scored or (len(scored) > 1 and scored[0][0] == scored[1][0]):
            continue
        rel = cap[0].path.parent.relative_to(probe.folder)
        where.setdefault(scored[0][1], set()).add(str(rel) if str(rel) != "." else ".")
    if len(where) > 1:
        found = "; ".join(f"{name} in {', '.join(sorted(d))}" for name, d in sorted(where.items()))
        raise InputError(f"the folder holds captures of {len(where)} cameras ({found}): one run applies one camera",
                         path=probe.folder, hint="give each camera's folder to its own run, or name the one to "
                         "apply with --camera NAME (the other's captures are then quarantined)")


def _has_images(d: Path) -> bool:
    return any(p.suffix.lower() in IMAGE_SUFFIXES for p in d.iterdir() if p.is_file())


def _folder_camera(d: Path, camera: str | None, lines: list[str]) -> Identification | None:
    """The camera of a folder holding image files (a line for it in ``lines``; None and a
    line saying why when it is not recognised), or of a folder whose band folders hold them
    (a Sentera 6X session: ``folder_per_band``; None and no line when it is not one)."""
    if not _has_images(d):
        if not any(_has_images(s) for s in d.iterdir() if s.is_dir()):
            return None
        try:
            ident = identify_camera(d, camera)
        except (InputError, FrameError):
            return None
        if ident.camera.layout.kind != "folder_per_band":
            return None
        lines.append(f"{d}:")
        return ident
    lines.append(f"{d}:")
    try:
        return identify_camera(d, camera)
    except (InputError, FrameError) as exc:
        lines.append(f"  camera: not recognised: {exc}")
        return None


def _other_images(d: Path, camera: Camera) -> list[str]:
    """Lines naming the images ``camera`` saves in folder ``d`` beside its band files
    (:func:`companion_images`: a DJI P4 Multispectral's RGB JPEGs), left out of the captures."""
    others = companion_images(sorted(p for p in d.iterdir() if p.is_file()), camera)
    lines = []
    for why in sorted(set(others.values())):
        names = sorted(p.name for p, w in others.items() if w == why)
        lines.append(f"  skipped {len(names)} file(s), {why}: {', '.join(names[:3])}{' ...' if len(names) > 3 else ''}")
    return lines


def describe_folders(folder: str | Path, camera: str | None = None) -> list[str]:
    """Lines for ``mscal cameras FOLDER``: per folder holding image files (FOLDER and its
    subfolders), the camera and why, the captures, bands, features, and problems."""
    from pipeline.ingest.grouping import group_captures

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("folder not found", path=folder)
    dirs = [folder] + sorted(p for p in folder.rglob("*") if p.is_dir())
    lines: list[str] = []
    covered: set[Path] = set()  # band folders of a session already described
    for d in dirs:
        if d in covered:
            continue
        ident = _folder_camera(d, camera, lines)
        if ident is None:
            continue
        if ident.camera.layout.kind == "folder_per_band":
            covered.update(p for p in d.rglob("*") if p.is_dir())
        cam = ident.camera
        caps, problems = group_captures(d, cam)
        lines.append(f"  camera: {cam.name} ({cam.description}); {ident.evidence}")
        lines.append(f"  captures: {len(caps)} complete, {len(problems)} quarantined")
        lines += _other_images(d, cam)
        for q in problems[:5]:
            lines.append(f"    quarantined {Path(q['file']).name}: {q['reason']}")
        if caps:
            first = caps[0]
            bands = ", ".join(f"{m.band_name} {m.wavelength_nm:g} nm" for m in first.metas)
            lines.append(f"  bands: {bands}")
            for s in first.skipped:
                lines.append(f"  skipped band {s['band']} ({Path(s['file']).name}): {s['reason']}")
            feats: dict[str, bool] = {}
            for c in caps:
                for m in c.metas:
                    for k, v in m.features().items():
                        feats[k] = feats.get(k, True) and v
            m0 = first.metas[0]
            lines.append(f"  radiance model: {m0.radiometry} ({m0.radiance_unit})")
            if m0.orientation not in (0, 1):
                lines.append(f"  stored with EXIF Orientation {m0.orientation}: turned upright by apply")
            lines.append("  features: " + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in feats.items()))
            seen = set()
            for c in caps:
                for p in c.problems:
                    key = (p.tag, p.reason, p.feature)
                    if key in seen:
                        continue
                    seen.add(key)
                    lines.append(f"  tag problem: {Path(p.file).name}: {p.message()}")
    if not lines:
        raise InputError("no image files (TIFF or JPEG) in the folder or below it", path=folder)
    return lines
