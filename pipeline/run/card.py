"""A flight as it comes off the camera's card: a session of the post-flight run with no field data.

Most multi-lens flights carry no field session (sweep, marker views, reflector): they carry the
camera's factory radiometry, panel captures before or after the survey and a sun sensor. A
folder is such a **card session** when it is not a field session (``session.yaml`` beside
``response/``, ``vignetting/`` or ``reflector/``); ``session.yaml`` is then optional
(:class:`CardSettings`: every key may be left out).

:func:`plan_card` says what a run does with it, before any pixel is read:

- **the camera** from the files (:func:`pipeline.ingest.identify.identify_camera`; make, model,
  band tags), or ``camera`` of ``session.yaml``; its serial number from the files (EXIF
  ``BodySerialNumber``, the maker's XMP serial) or ``serial`` of ``session.yaml``;
- **the flights**: captures in separate ``NNNNSET`` folders (MicaSense: one per power-up) are
  separate flights, and so are captures more than ``flight_gap_minutes`` apart (default
  :data:`DEFAULT_GAP_MINUTES`); each is applied into ``OUT/flights/<name>/``;
- **the calibration** of each flight: a field calibration named in ``session.yaml``, else the
  newest of the calibration library fitted for this camera model and serial before the flight
  (:mod:`pipeline.calibrate.library`), else the camera's factory radiometry. A field
  calibration replaces the factory's response and vignetting where the camera's radiance model
  takes them (MicaSense), and is the whole radiometry (Eq. 15) of files with no factory model
  (a snapshot camera's frames with ``frames.csv``).

The light reference (the camera's panel reflectance, the panel's serial number looked up in
``catalogs/targets``, the sun sensor, else none) is chosen by apply's ``auto`` route
(:mod:`pipeline.apply.factory`) unless ``reference`` / ``panel_reflectance`` of ``session.yaml``
say otherwise; each flight's ``run.json`` says which was used and why the others were not.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from mscal_core.errors import InputError, MscalError, SessionError

from pipeline.ingest.cameras.dispatch import takes_field_parts
from pipeline.ingest.catalog import Camera, load_camera, read_yaml, reflectance_option
from pipeline.ingest.exif import parse_utc
from pipeline.ingest.products import yaml_choice
from pipeline.ingest.schema import Strict, Text, check, finite_number, validate

#: Folders that make a session a field session (the paper's three fits).
FIELD_FOLDERS = ("response", "vignetting", "reflector")
#: Captures further apart than this are separate flights.
DEFAULT_GAP_MINUTES = 30.0
#: A MicaSense SD card's folder of one power-up (``0000SET``, ``0001SET``, ...).
SET_FOLDER = re.compile(r"^\d{4}SET$")
REFERENCES = ("auto", "panel", "dls", "panel-dls")
#: ``field_calibration`` value that keeps the library's calibrations out (factory radiometry only).
NO_FIELD = "none"


def is_field_session(folder: str | Path) -> bool:
    """A field session: ``session.yaml`` and at least one of :data:`FIELD_FOLDERS`."""
    folder = Path(folder)
    return (folder / "session.yaml").is_file() and any((folder / d).is_dir() for d in FIELD_FOLDERS)


@dataclass(frozen=True)
class CardSettings:
    """What a card session's optional ``session.yaml`` overrides."""

    camera: str | None = None
    serial: str | None = None
    reference: str = "auto"
    panel_reflectance: str | None = None
    field_calibration: str | None = None  # a store path, or NO_FIELD
    flight_gap_minutes: float = DEFAULT_GAP_MINUTES
    source: str | None = None  # the session.yaml read, if any
    products: dict[str, Any] | None = None  # the keys of its products (pipeline.ingest.products.yaml_choice)


class _CardYaml(Strict):
    """``session.yaml`` of a card session (every key optional)."""

    camera: Text | None = None
    serial: Text | None = None
    reference: Annotated[str, check(lambda v: str(v) in REFERENCES, f"is not one of {', '.join(REFERENCES)}", str,
                                    value_first=True)] = "auto"
    panel_reflectance: Any = None  # a number or a target's name: reflectance_option
    panel: Any = None  # pipeline.ingest.session.panel_config_near
    field_calibration: Any = None  # a store, or NO_FIELD
    flight_gap_minutes: Annotated[float, check(lambda v: finite_number(v) is not None and v > 0 or v == float("inf"),
                                               "must be a positive number", float)] = DEFAULT_GAP_MINUTES
    name: Any = None
    notes: Any = None
    products: Any = None  # pipeline.ingest.products.yaml_choice


def load_card_settings(folder: str | Path) -> CardSettings:
    """:class:`CardSettings` of ``folder/session.yaml`` (defaults when there is none)."""
    path = Path(folder) / "session.yaml"
    if not path.is_file():
        return CardSettings()
    data = read_yaml(path, SessionError)
    m = validate(_CardYaml, {} if data is None else data, path, SessionError,
                 label="session.yaml of a flight folder (no response/, vignetting/, reflector/)")
    store = m.field_calibration
    if store is not None and str(store) != NO_FIELD:
        p = Path(str(store))
        p = p if p.is_absolute() else (path.parent / p)
        if not p.exists():
            raise SessionError(f"field_calibration {store!r}: no such store", path=path,
                               hint=f"give a store from 'mscal calibrate', or '{NO_FIELD}' for factory radiometry")
        store = str(p.resolve())
    rho = m.panel_reflectance
    if rho is not None:
        try:
            reflectance_option(str(rho), "panel_reflectance")
        except MscalError as exc:
            raise SessionError(exc.reason, path=path, hint=exc.hint or "a number in (0, 1] or a catalogs/targets name"
                               ) from None
    return CardSettings(
        camera=m.camera, serial=None if m.serial is None else m.serial.strip(), reference=m.reference,
        panel_reflectance=None if rho is None else str(rho), field_calibration=None if store is None else str(store),
        flight_gap_minutes=m.flight_gap_minutes, source=str(path), products=yaml_choice(m.products, path),
    )


@dataclass(frozen=True)
class CardFlight:
    """One flight of a card: the folder apply reads, the captures of it that belong to this
    flight (() = all; names as apply names them in that folder), its time span (UTC ISO or
    None) and the calibration it gets."""

    name: str
    folder: str
    captures: tuple[str, ...] = ()
    start: str | None = None
    end: str | None = None
    calibration: str = "factory"  # factory | factory+field | field
    field_calibration: str | None = None
    calibration_source: str = ""


@dataclass(frozen=True)
class CardPlan:
    """What a post-flight run does with a card session (module docstring)."""

    root: str
    camera: str
    evidence: str
    make: str | None
    model: str | None
    serial: str | None
    factory: bool  # the files carry the camera's factory radiometry
    flights: tuple[CardFlight, ...]
    settings: CardSettings = field(default_factory=CardSettings)

    def record(self) -> dict[str, Any]:
        """run.json ``card``: the camera, its serial and how it was recognised."""
        return {"camera": self.camera, "make": self.make, "model": self.model, "serial": self.serial,
                "evidence": self.evidence, "factory_radiometry": self.factory,
                "session_yaml": self.settings.source}


def _time(t: np.datetime64) -> str | None:
    return None if np.isnat(t) else np.datetime_as_string(t, unit="s") + "Z"


def _iso_utc(dt: datetime) -> str:
    return dt.astimezone(timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


def split_by_time(times: np.ndarray, gap_s: float) -> list[np.ndarray]:
    """Indices of ``times`` (datetime64, NaT allowed) in runs where consecutive captures (in
    time order) are at most ``gap_s`` apart. Captures without a time stay with the run of the
    capture before them in name order (the first run when none is before them)."""
    n = len(times)
    if n == 0:
        return []
    known = np.flatnonzero(~np.isnat(times))
    if known.size == 0:
        return [np.arange(n)]
    order = known[np.argsort(times[known], kind="stable")]
    secs = (times[order] - times[order[0]]) / np.timedelta64(1, "s")
    cuts = np.flatnonzero(np.diff(secs) > gap_s) + 1
    groups = [list(g) for g in np.split(order, cuts)]
    owner = {int(i): k for k, g in enumerate(groups) for i in g}
    last = 0
    for i in range(n):  # captures without a time: with the one before them by name
        if i in owner:
            last = owner[i]
        else:
            groups[last].append(i)
    return [np.array(sorted(g)) for g in groups]


def _set_folder(capture_files: tuple[Path, ...], root: Path) -> Path:
    """The ``NNNNSET`` folder a capture lies in (below ``root``), else ``root``."""
    rel = capture_files[0].relative_to(root).parts[:-1]
    for k, part in enumerate(rel):
        if SET_FOLDER.match(part):
            return root.joinpath(*rel[:k + 1])
    return root


def _set_names(set_dirs: list[Path], root: Path) -> dict[Path, str]:
    """Flight names of the SET folders (and of ``root`` itself, for captures in no SET folder:
    ``flight``): the folder's name, or its path below ``root`` joined with ``_`` when two SET
    folders of the card share a name (two cards copied into one folder)."""
    short = {d: (d.name if d != root else "flight") for d in set_dirs}
    taken = [n for n in short.values()]
    return {d: (n if taken.count(n) == 1 else "_".join(d.relative_to(root).parts) or n) for d, n in short.items()}


def _calibration(settings: CardSettings, camera: Camera, serial: str | None, factory: bool, start: str | None,
                 library_root: Path | None, folder: Path) -> tuple[str, str | None, str]:
    """``(kind, store, why)`` of one flight: factory, factory+field (a factory model that takes
    the field response and vignetting, :func:`pipeline.ingest.cameras.dispatch.takes_field_parts`:
    MicaSense's) or field (Eq. 15 with the store's U, V, S)."""
    store, why = None, ""
    if settings.field_calibration == NO_FIELD:
        why = f"session.yaml field_calibration: {NO_FIELD}"
    elif settings.field_calibration is not None:
        store, why = settings.field_calibration, f"named in {settings.source}"
    else:
        from pipeline.calibrate.library import default_library_root, lookup

        flight_time = None if start is None else parse_utc(start)
        root = library_root if library_root is not None else default_library_root()
        entry = lookup(camera.name, serial, flight_time, root) if serial else None
        if entry is not None:
            store = str(entry.store)
            when = entry.session_time or entry.fitted_utc
            why = f"calibration library: the newest fitted for {camera.name} serial {serial} before the flight ({when})"
        elif serial is None:
            why = "no serial number in the files: the calibration library is not searched"
        else:
            why = f"no field calibration of {camera.name} serial {serial} fitted before the flight in the library {root}"
    if store is None:
        if not factory:
            raise InputError(
                f"the files carry no factory radiometry of {camera.name} and no field calibration is known ({why})",
                path=folder, hint=f"run 'mscal calibrate' on a field session of this camera (it is then recorded for serial "
                     f"{serial or '?'}), or name a store with field_calibration in session.yaml")
        return "factory", None, why
    if not factory:
        return "field", store, why
    if takes_field_parts(camera.factory_model):
        return "factory+field", store, why
    return "factory", None, (f"{why}; not used: the {camera.factory_model} radiance model takes no field components, "
                             "factory radiometry used")


def plan_card(folder: str | Path, library_root: str | Path | None = None) -> CardPlan:
    """Camera, serial, flights and each flight's calibration of a card session (module docstring).
    :class:`InputError` (one line, naming the folder) when the folder holds no capture of a
    known camera, captures of two cameras, or frames of a camera without factory radiometry
    and no field calibration."""
    from pipeline.apply.captures import capture_times, find_captures
    from pipeline.ingest.identify import identify_camera

    root = Path(folder)
    if not root.is_dir():
        raise InputError("flight folder not found", path=root)
    field = [d for d in FIELD_FOLDERS if (root / d).is_dir()]
    if field and not (root / "session.yaml").is_file():  # not a card: a field session without its file
        raise SessionError(f"session.yaml is missing beside {', '.join(d + '/' for d in field)}", path=root / "session.yaml",
                           hint="a field session needs session.yaml (camera, reflector, marker: see SPEC.md); a flight "
                                "folder off a card holds no response/, vignetting/ or reflector/")
    settings = load_card_settings(root)
    lib = None if library_root is None else Path(library_root)
    if (root / "frames.csv").is_file() or (settings.camera and load_camera(settings.camera).factory_model is None):
        return _plan_frames(root, settings, lib)
    ident = identify_camera(root, settings.camera)
    camera = ident.camera
    probe = ident.probe
    factory = camera.factory_model is not None and bool(probe.get("bands_per_capture"))
    serial = str(probe["serial"]) if probe.get("serial") else None
    if serial is None:  # files without the maker's metadata (camera named in session.yaml): their EXIF
        from pipeline.calibrate.library import camera_serial

        serial = camera_serial(root, camera)
    if settings.serial is not None:
        if serial is not None and serial.casefold() != settings.serial.casefold():
            raise SessionError(f"serial {settings.serial!r} is not the files' serial number {serial!r}",
                               path=settings.source, hint="leave serial out (the files say it), or correct it")
        serial = serial or settings.serial
    found = find_captures(root, camera)
    if not found.captures:
        why = "; ".join(f"{q['file']}: {q['reason']}" for q in found.quarantined[:2])
        raise InputError(f"no complete capture of {camera.name} in the folder" + (f" ({why})" if why else ""),
                         path=root, hint="copy the card's whole capture folders (every band file of a capture)")
    by_set: dict[Path, int] = {}
    for c in found.captures:
        s = _set_folder(c.files, root)
        by_set[s] = by_set.get(s, 0) + 1
    flights: list[CardFlight] = []
    gap_s = settings.flight_gap_minutes * 60.0
    names = _set_names(sorted(by_set), root)
    for set_dir in sorted(by_set):
        caps = find_captures(set_dir, camera).captures if set_dir != root or len(by_set) > 1 else found.captures
        # captures beside SET folders: only those not in one (apply of root would read the SET folders too)
        loose = set_dir == root and len(by_set) > 1
        if loose:
            caps = [c for c in caps if _set_folder(c.files, root) == root]
        times = capture_times(caps)
        parts = split_by_time(times, gap_s)
        for k, idx in enumerate(parts):
            name = names[set_dir] if len(parts) == 1 else f"{names[set_dir]}-{k + 1}"
            span = times[idx][~np.isnat(times[idx])]
            start = _time(span.min()) if span.size else None
            end = _time(span.max()) if span.size else None
            kind, store, why = _calibration(settings, camera, serial, factory, start, lib, root)
            flights.append(CardFlight(
                name=name, folder=str(set_dir),
                captures=tuple(caps[i].name for i in idx) if len(parts) > 1 or loose else (),
                start=start, end=end, calibration=kind, field_calibration=store, calibration_source=why))
    return CardPlan(root=str(root), camera=camera.name, evidence=ident.evidence, make=probe.get("make"),
                    model=probe.get("model"), serial=serial, factory=factory, flights=tuple(flights), settings=settings)


def _plan_frames(root: Path, settings: CardSettings, library_root: Path | None) -> CardPlan:
    """A snapshot camera's frames (``frames.csv`` in the folder, or in each of its subfolders):
    no factory radiometry, so a field calibration is needed (session.yaml's, else the library's)."""
    from pipeline.ingest.session import read_frame_table

    if settings.camera is None:
        raise InputError("frames with frames.csv but no camera: frames of a snapshot camera carry no make or model",
                         path=root, hint="add a session.yaml with 'camera: NAME' (and 'serial:') beside frames.csv")
    camera = load_camera(settings.camera)
    dirs = [root] if (root / "frames.csv").is_file() else sorted(p.parent for p in root.glob("*/frames.csv"))
    if not dirs:
        raise InputError(f"no frames.csv and no capture files of {camera.name} in the folder", path=root)
    flights = []
    for d in dirs:
        times = [parse_utc(rec.time) for rec in read_frame_table(d, on_frame_error=lambda name, exc: None) if rec.time]
        start = _iso_utc(min(times)) if times else None
        kind, store, why = _calibration(settings, camera, settings.serial, False, start, library_root, root)
        flights.append(CardFlight(name=d.name if d != root else "flight", folder=str(d), start=start,
                                  end=_iso_utc(max(times)) if times else None, calibration=kind,
                                  field_calibration=store, calibration_source=why))
    return CardPlan(root=str(root), camera=camera.name, evidence=f"camera {camera.name} of {settings.source}",
                    make=None, model=None, serial=settings.serial, factory=False, flights=tuple(flights),
                    settings=settings)


def plan_record(plan: CardPlan) -> dict[str, Any]:
    """The plan as JSON-able data (Prefect passes it between tasks; run.json keeps it)."""
    return asdict(plan)


def plan_from_record(data: dict[str, Any]) -> CardPlan:
    """Inverse of :func:`plan_record`."""
    d = dict(data)
    d["flights"] = tuple(CardFlight(**{**f, "captures": tuple(f.get("captures") or ())}) for f in d["flights"])
    d["settings"] = CardSettings(**d["settings"])
    return CardPlan(**d)
