"""The post-flight run (``mscal run``) apart from its Prefect wiring.

``flows/post_flight.py`` calls these one at a time; everything that is not wiring lives
here, free of Prefect, so that it can be tested on its own:

- Prefect's environment for an offline, self-contained run (:func:`configure_prefect`);
- the calibration cache: one content-addressed store per stage under the cache folder,
  keyed by the content of that stage's inputs, of the stages before it and of the code
  (:func:`plan_calibration`), so that a changed ``reflector/`` re-fits only illumination;
- staging of fsspec URLs (``s3://...``): remote inputs are copied into a local work folder,
  the run is local, the outputs are uploaded with ``run.json`` last (:func:`stage_in`,
  :func:`upload`);
- one flight under a Dask client (:func:`apply_one`), the run record ``OUT/run.json``
  (:func:`run_record`) and its Markdown summary.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Iterator

import mscal_core
from mscal_core.errors import InputError, MscalError, SessionError

from pipeline.apply.execution import Execution, scheduler_for
from pipeline.apply.flight import apply_flight
from pipeline.apply.light import INTERPOLATION_MODES
from pipeline.apply.options import ApplyOptions
from pipeline.apply.record import RUN_JSON
from pipeline.calibrate.fit import STAGES
from pipeline.ingest.catalog import load_camera, read_yaml
from pipeline.ingest.grouping import DEFAULT_CAPTURE_PATTERN
from pipeline.ingest.products import Products, indices_for, radiance_refused, resolve
from pipeline.ingest.session import Session, load_session, read_frame_table
from pipeline.run.card import (
    CardFlight,
    CardPlan,
    is_field_session,
    load_card_settings,
    plan_card,
    plan_from_record,
    plan_record,
)
from pipeline.storage.atomic import write_json_atomic
from pipeline.storage.cache import code_digest, default_cache_dir
from pipeline.storage.run_layout import run_value
from pipeline.storage.store import content_hashes, file_sha256, open_calibration, write_store

log = logging.getLogger(__name__)

RUN_FORMAT = "mscal-run/1"
CALIBRATION_STORE = "calibration.zarr"
#: Inputs of each stage besides the stores of the stages before it (folders of the session).
STAGE_FOLDERS = {"response": "response", "vignetting": "vignetting", "illumination": "reflector"}


# --------------------------------------------------------------------------- environment


def configure_prefect(home: str | Path | None = None) -> Path:
    """Set Prefect's environment for an offline run on its embedded server; returns PREFECT_HOME.

    Must run before ``prefect`` is imported (Prefect reads its settings once). Values already
    in the environment win, so a configured Prefect (``PREFECT_API_URL`` of a real server, a
    profile) is used as is. ``PREFECT_HOME`` defaults to ``home`` or ``<cache>/prefect``
    (:func:`default_cache_dir`): the SQLite database of the embedded server lives there.
    """
    if "prefect" in sys.modules:  # too late to change what Prefect reads; say what it uses
        return Path(os.environ.get("PREFECT_HOME", Path.home() / ".prefect"))
    os.environ.setdefault("PREFECT_HOME", str(home or default_cache_dir() / "prefect"))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    # The first start creates and migrates the SQLite database (~15-25 s on a busy machine).
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "300")
    Path(os.environ["PREFECT_HOME"]).mkdir(parents=True, exist_ok=True)
    return Path(os.environ["PREFECT_HOME"])


def versions() -> dict[str, str]:
    """Software versions recorded in ``run.json``."""
    out = {"mscal": mscal_core.__version__, "mscal_code": code_digest()[:16], "python": platform.python_version()}
    for dist in ("prefect", "dask", "distributed", "xarray", "zarr", "numpy", "fsspec"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out


def is_transient(exc: BaseException | None) -> bool:
    """Worth a retry: an I/O failure (network, storage), not bad input or a failed fit."""
    return isinstance(exc, (OSError, TimeoutError)) and not isinstance(exc, (MscalError, FileNotFoundError))


# --------------------------------------------------------------------------- calibration cache


@dataclass(frozen=True)
class StagePlan:
    """One fit: its cache key, its store in the cache, the store it builds on, and whether
    the store already exists (then the fit is skipped)."""

    name: str
    key: str
    store: str
    partial: str | None
    cached: bool


@dataclass(frozen=True)
class CalibrationPlan:
    stages: tuple[StagePlan, ...]

    @property
    def final_store(self) -> str:
        """The last stage's store: the complete calibration."""
        return self.stages[-1].store

    @property
    def cached(self) -> bool:
        """True when no stage needs fitting."""
        return all(s.cached for s in self.stages)


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def folder_hashes(folder: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of every file in a calibration folder."""
    if not folder.is_dir():
        raise SessionError("calibration folder not found", path=folder,
                           hint="a session holds response/, vignetting/ and reflector/ (README, Session folder)")
    return content_hashes((p for p in folder.rglob("*") if p.is_file()), folder)


def stage_keys(session: Session, response_method: str) -> dict[str, str]:
    """Cache key of each stage: its own inputs plus the key of the stage before it, so a
    changed input changes the keys of exactly the stages that depend on it."""
    code = code_digest()
    yaml_sha = fits_yaml_digest(session.root / "session.yaml")
    keys: dict[str, str] = {}
    before = {"code": code, "method": response_method, "camera": session.camera.name,
              "camera_catalog": file_sha256(Path(session.camera.source)) if session.camera.source else ""}
    for stage in STAGES:
        inputs = {"stage": stage, "before": before,
                  "files": folder_hashes(session.root / STAGE_FOLDERS[stage])}
        if stage != "response":  # marker, reflector and intrinsics matter from here on
            inputs["session_yaml"] = yaml_sha
        keys[stage] = _digest(inputs)
        before = {"key": keys[stage]}
    return keys


def fits_yaml_digest(path: Path) -> str:
    """sha256 of session.yaml as the fits see it: its keys and values except ``products``
    (what apply writes, no input of any fit), so that choosing other products re-fits nothing
    (nor does a comment or a change of layout)."""
    data = read_yaml(path, SessionError)
    rest = {str(k): v for k, v in data.items() if k != "products"} if isinstance(data, dict) else data
    return hashlib.sha256(json.dumps(rest, sort_keys=True, default=str).encode()).hexdigest()


def plan_calibration(session_dir: str | Path, cache_dir: str | Path, response_method: str = "forward") -> CalibrationPlan:
    """Which stages of the session's calibration are in the cache and which need fitting."""
    session = load_session(session_dir)
    root = Path(cache_dir) / "calibration"
    stages: list[StagePlan] = []
    partial: str | None = None
    for stage, key in stage_keys(session, response_method).items():
        store = root / f"{stage}-{key[:32]}.zarr"
        stages.append(StagePlan(stage, key, str(store), partial, whole_store(store)))
        partial = str(store)
    return CalibrationPlan(tuple(stages))


def whole_store(store: Path) -> bool:
    """Whether a cached stage store can be reused: it exists (it appears only whole, by the
    durable rename of :func:`pipeline.storage.store.write_store`) and reads back (a damaged
    chunk does not); a store that does not is fitted again and replaced."""
    if not (store / "zarr.json").is_file():
        return False
    try:
        open_calibration(store)
    except MscalError as exc:
        log.warning("cached calibration %s cannot be reused, fitting it again: %s", store, exc)
        return False
    return True


def publish_calibration(cached_store: str | Path, out_dir: str | Path) -> Path:
    """Write the calibration into ``out_dir/calibration.zarr`` (atomically) and return it."""
    return write_store(open_calibration(cached_store, need="apply"), Path(out_dir) / CALIBRATION_STORE)


def flight_dirs(session_dir: str | Path) -> dict[str, str]:
    """``{flight name: folder}`` of ``SESSION/flights/*``."""
    return {p.name: str(p) for p in load_session(session_dir).flight_dirs()}


def session_problem(session_dir: str | Path, cache_dir: str | Path | None = None,
                    products: dict[str, Any] | None = None) -> str | None:
    """Why a session folder cannot be run (one line naming the file), or None: a field
    session's session.yaml that is not valid, a card session of no known camera or of two,
    products (the command line's ``products``, over session.yaml's) its flights cannot make."""
    try:
        check_products(session_dir, products, cache_dir)
    except MscalError as exc:
        return str(exc).splitlines()[0]
    return None


def session_products(session_dir: str | Path, products: dict[str, Any] | None = None) -> Products:
    """The products of a session's flights: the command line's choice (``products``, the keys
    it gives) over session.yaml's ``products`` key, over the defaults (docs/products.md)."""
    if is_field_session(session_dir):
        return resolve(load_session(session_dir).products, products)
    return resolve(load_card_settings(session_dir).products, products)


def check_products(session_dir: str | Path, products: dict[str, Any] | None = None,
                   cache_dir: str | Path | None = None) -> Products:
    """:func:`session_products`, checked against the session before anything runs: radiance
    only where every flight has factory radiometry, each index asked for one the camera's
    bands make (InputError saying which and how to fix it). Also checks the session itself
    (session.yaml, a card session's camera and calibrations)."""
    if is_field_session(session_dir):
        session = load_session(session_dir)
        chosen = resolve(session.products, products)
        radiance_refused(chosen, "a field session's calibration (Eq. 15 with its U, V, S)")
        indices_for(session.camera, chosen)
        return chosen
    plan = plan_card(session_dir, _library(cache_dir))
    chosen = resolve(plan.settings.products, products)
    field = [f.name for f in plan.flights if f.calibration == "field"]
    if field:
        radiance_refused(chosen, f"the field calibration of flight(s) {', '.join(field)}")
    indices_for(load_camera(plan.camera), chosen)
    return chosen


def session_kind(session_dir: str | Path) -> str:
    """``field`` (session.yaml with response/, vignetting/ or reflector/: the paper's fits run)
    or ``card`` (a flight folder as it comes off the camera, :mod:`pipeline.run.card`)."""
    return "field" if is_field_session(session_dir) else "card"


def plan_card_session(session_dir: str | Path, cache_dir: str | Path | None = None) -> dict[str, Any]:
    """:func:`pipeline.run.card.plan_card` of a card session, as data; the calibration library
    is the one under ``cache_dir`` (default :func:`default_cache_dir`)."""
    return plan_record(plan_card(session_dir, _library(cache_dir)))


def _library(cache_dir: str | Path | None) -> Path:
    """The calibration library of the cache folder ``cache_dir`` (default :func:`default_cache_dir`)."""
    return (Path(cache_dir) if cache_dir else default_cache_dir()) / "library"


def apply_card(plan: dict[str, Any], name: str, out: str, *, dask_address: str | None = None,
               scheduler: str = "auto", workers: int = 0, direct_io: bool | None = None,
               products: dict[str, Any] | None = None) -> dict[str, Any]:
    """One flight ``name`` of a card session's plan (:func:`plan_card_session`) into ``out``;
    ``products``: the command line's choice, over the plan's session.yaml products."""
    card = plan_from_record(plan)
    flight = next(f for f in card.flights if f.name == name)
    return apply_card_flight(card, flight, out, dask_address=dask_address, scheduler=scheduler, workers=workers,
                             direct_io=direct_io, products=resolve(card.settings.products, products))


def failed_card_flight(flight: dict[str, Any], error: BaseException | None) -> dict[str, Any]:
    """:func:`failed_flight` of a card session's flight, with what its plan said of it (its
    captures, time span, calibration and why)."""
    keep = ("calibration", "field_calibration", "calibration_source", "start", "end", "captures")
    return {**failed_flight(flight["folder"], error), "kind": "card", **{k: flight.get(k) for k in keep}}


def record_calibration(session_dir: str | Path, store: str | Path, cache_dir: str | Path | None = None
                       ) -> dict[str, str]:
    """Record a field session's fitted calibration in the calibration library under
    ``cache_dir`` (:mod:`pipeline.calibrate.library`), keyed by its camera and serial number:
    ``{"store": the library's copy}`` (recording the same calibration again adds nothing), or
    ``{"not_recorded": why}`` when the session's frames cannot say its serial or time (the
    run goes on: its calibration is published all the same)."""
    from pipeline.calibrate.library import record_fitted

    try:
        return {"store": str(record_fitted(store, session_dir, library_root=_library(cache_dir)))}
    except (MscalError, OSError) as exc:  # a full disk, an unwritable cache: the run's outputs come first
        log.warning("calibration not recorded in the calibration library: %s", exc)
        return {"not_recorded": str(exc).splitlines()[0]}


# --------------------------------------------------------------------------- Dask and apply


DASK_ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://[^\s/]+(:\d+)?/?$")


@contextmanager
def dask_client(address: str | None, n_frames: int, execution: Execution = Execution()) -> Iterator[str]:
    """The Dask scheduler ``apply_flight`` computes on, as the default ``distributed`` client
    for the duration; yields how the frames are computed.

    With ``address``: that ``dask scheduler`` and its workers (they must see the same paths,
    e.g. a shared file system). Without: a ``LocalCluster`` of one single-threaded worker
    process per core (or ``execution.workers``) when ``--scheduler processes`` asks for
    processes (:func:`pipeline.apply.execution.scheduler_for`), else apply's own scheduler
    (``auto``: its own pool of worker processes for a long flight, without a cluster).
    """
    if address:
        from distributed import Client

        try:
            client = Client(address, timeout="15s", set_as_default=True)
        except OSError as exc:
            raise InputError(f"cannot reach the Dask scheduler at {address} ({exc})",
                             hint="start 'dask scheduler' and 'dask worker ADDRESS', or leave --dask-address out") from None
        with client:
            yield f"dask scheduler {address}"
        return
    if execution.scheduler != "processes" or scheduler_for(n_frames, execution)[0] != "processes":
        yield "in-process"
        return
    from distributed import Client, LocalCluster

    n = execution.workers or os.cpu_count() or 1
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster, set_as_default=True):
        yield f"local cluster of {n} worker processes"


def count_frames(flight_dir: str | Path, camera: str | None = None) -> int:
    """Frames (captures) listed or found in a flight folder (bad ones included), without
    decoding any: for a camera that writes one file per band, its band files over its bands."""
    if camera is not None:
        cam = load_camera(camera)
        if cam.layout.kind == "file_per_band":
            pattern = re.compile(cam.layout.capture_pattern or DEFAULT_CAPTURE_PATTERN)
            files = sum(1 for p in Path(flight_dir).rglob("*") if pattern.match(p.name))
            return -(-files // cam.n_bands)
    return len(read_frame_table(flight_dir, on_frame_error=lambda name, exc: None))


def apply_one(flight_dir: str, calibration: str, out: str, *, normalise: str = "relative",
              dask_address: str | None = None, illumination: str = "linear", scheduler: str = "auto",
              workers: int = 0, direct_io: bool | None = None, products: dict[str, Any] | None = None
              ) -> dict[str, Any]:
    """``apply_flight`` under :func:`dask_client`; returns the flight's summary for run.json.
    ``scheduler``, ``workers``, ``direct_io``: :class:`pipeline.apply.execution.Execution`;
    ``products``: the session's choice (:func:`session_products`, as its ``record()``)."""
    t0 = time.perf_counter()
    camera = open_calibration(calibration, need="apply").attrs.get("camera")
    execution = Execution(scheduler=scheduler, workers=workers, direct_io=direct_io)
    execution.install()  # before a local cluster starts its worker processes
    with dask_client(dask_address, count_frames(flight_dir, None if camera is None else str(camera)), execution) as where:
        res = apply_flight(flight_dir, calibration, out,
                           ApplyOptions(normalise=normalise, illumination=illumination, execution=execution,
                                        products=resolve(products)))
    illumination = {k: v for k, v in res.run.get("illumination", {}).items() if k != "per_frame"}
    return _flight_summary(res, where, t0, illumination=illumination)


def _flight_summary(res: Any, where: str, t0: float, **extra: Any) -> dict[str, Any]:
    """A flight's summary in the run's run.json from apply's result (``res.run``: the flight's
    run.json): counts, calibration hash, whether it was up to date and where it was computed."""
    run = res.run
    return {
        "status": "done",
        "frames_in": run["frames_in"],
        "frames_out": run["frames_out"],
        "quarantined": res.quarantined,
        "skipped": run_value(run, "skipped", []),
        "saturated_pixels": run["saturated_pixels"]["total"],
        "calibration_sha256": run.get("calibration_sha256"),
        "up_to_date": res.up_to_date,
        "computed_on": "nothing (up to date)" if res.up_to_date else where,
        "execution": run.get("execution"),
        "products": run.get("products"),
        **extra,
        "seconds": round(time.perf_counter() - t0, 3),
    }


#: What a card flight's summary keeps of its run.json ``reference``: the route, where the
#: panel's reflectance came from, and why the other references were not used.
CARD_REFERENCE_KEYS = ("route", "panel_reflectance", "reason", "albedo", "albedo_panel_unusable", "panel_serial",
                       "panel_serial_none", "panel_serial_unknown", "panel_serial_unusable")


def apply_card_flight(plan: CardPlan, flight: CardFlight, out: str | Path, *, dask_address: str | None = None,
                      scheduler: str = "auto", workers: int = 0, direct_io: bool | None = None,
                      products: Products = Products()) -> dict[str, Any]:
    """Apply one flight of a card session (:mod:`pipeline.run.card`) into ``out`` under
    :func:`dask_client`: its field calibration (Eq. 15), or the factory model (with the field
    response and vignetting for ``factory+field``); returns its summary for the run's run.json."""
    from pipeline.apply.factory import FactoryOptions, apply_factory

    t0 = time.perf_counter()
    execution = Execution(scheduler=scheduler, workers=workers, direct_io=direct_io)
    execution.install()
    n = len(flight.captures) or count_frames(flight.folder, plan.camera)
    with dask_client(dask_address, n, execution) as where:
        if flight.calibration == "field":
            res = apply_flight(flight.folder, flight.field_calibration, out,
                               ApplyOptions(execution=execution, captures=flight.captures, products=products))
        else:
            s = plan.settings
            res = apply_factory(flight.folder, out, FactoryOptions(
                reference=s.reference, panel_reflectance=s.panel_reflectance, camera=plan.camera,
                field_calibration=flight.field_calibration if flight.calibration == "factory+field" else None,
                execution=execution, captures=flight.captures, products=products))
    ref = run_value(res.run, "reference") or {}
    return _flight_summary(
        res, where, t0, kind="card", calibration=flight.calibration, field_calibration=flight.field_calibration,
        calibration_source=flight.calibration_source, reference={k: ref[k] for k in CARD_REFERENCE_KEYS if k in ref},
        start=flight.start, end=flight.end)


def failed_flight(flight_dir: str, error: BaseException | None) -> dict[str, Any]:
    """The run.json summary of a flight that could not be applied (empty, every frame
    quarantined, unreadable): the other flights of the session are processed all the same."""
    reason = str(error) if error is not None else "failed"
    if error is not None and not isinstance(error, MscalError):
        reason = f"{type(error).__name__}: {reason}"
    return {"status": "failed", "reason": reason.splitlines()[0] if reason else "failed", "flight": str(flight_dir),
            "frames_in": 0, "frames_out": 0, "quarantined": [], "skipped": [], "saturated_pixels": 0,
            "calibration_sha256": None, "up_to_date": False, "computed_on": "nothing (failed)", "seconds": 0.0}


def failed_flights(record: dict[str, Any]) -> dict[str, str]:
    """``{flight: reason}`` of the flights of a run record that failed."""
    return {n: f.get("reason", "failed") for n, f in record.get("flights", {}).items() if f.get("status") == "failed"}


# --------------------------------------------------------------------------- storage


def is_remote(url: str | Path) -> bool:
    """True for an fsspec URL of another file system (``s3://``, ``gs://``, ...)."""
    m = re.match(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://", str(url))
    return bool(m) and m.group(1).lower() not in ("file", "local")


def _fs(url: str):  # fsspec file system, path
    import fsspec

    return fsspec.core.url_to_fs(url)


@dataclass(frozen=True)
class RunPaths:
    """Where a run reads and writes locally; ``work`` is set when remote URLs are staged."""

    session: str
    out: str
    work: str | None
    work_is_temporary: bool


def run_paths(session: str, out: str, work_dir: str | None = None) -> RunPaths:
    """Local paths of a run: the URLs themselves when local; under a work folder (given, or a
    new temporary one) when remote."""
    if not (is_remote(session) or is_remote(out)):
        return RunPaths(str(session), str(out), None, False)
    work = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="mscal-work-"))
    work.mkdir(parents=True, exist_ok=True)
    return RunPaths(
        str(work / "session") if is_remote(session) else str(session),
        str(work / "out") if is_remote(out) else str(out),
        str(work), work_dir is None,
    )


def stage_in(url: str, local: str | Path) -> Path:
    """Copy the folder at ``url`` into ``local`` (emptied first) and return ``local``."""
    fs, root = _fs(url)
    local = Path(local)
    if local.exists():
        shutil.rmtree(local)
    remote = sorted(p for p in fs.find(root) if not p.endswith("/"))
    if not remote:
        raise SessionError("no files found", path=url, hint="check the URL and the storage credentials")
    prefix = root.rstrip("/") + "/"
    targets = [local / p[len(prefix):] for p in remote]
    for t in {t.parent for t in targets}:
        t.mkdir(parents=True, exist_ok=True)
    fs.get(remote, [str(t) for t in targets])
    return local


def upload(local: str | Path, url: str) -> int:
    """Copy the folder ``local`` to ``url``: the old ``run.json`` there is removed first and
    the new one uploaded last, so a partial upload is never taken for a finished run.
    Returns the number of files uploaded."""
    fs, root = _fs(url)
    root = root.rstrip("/")
    local = Path(local)
    files = sorted(p for p in local.rglob("*") if p.is_file())
    last = local / RUN_JSON
    if fs.exists(f"{root}/{RUN_JSON}"):
        fs.rm(f"{root}/{RUN_JSON}")
    first = [p for p in files if p != last]
    if first:
        fs.put([str(p) for p in first], [f"{root}/{p.relative_to(local).as_posix()}" for p in first])
    if last.is_file():
        fs.put_file(str(last), f"{root}/{RUN_JSON}")
    return len(files)


def remove_work(paths: RunPaths) -> None:
    """Delete the work folder of a run if the run created it."""
    if paths.work and paths.work_is_temporary:
        shutil.rmtree(paths.work, ignore_errors=True)


def check_run_inputs(session: str, out: str, *, normalise: str = "relative", dask_address: str | None = None,
                     catalog_root: str | None = None, illumination: str = "linear",
                     cache_dir: str | None = None, products: dict[str, Any] | None = None) -> None:
    """Fail fast, before Prefect starts: a session that is not there (a field session whose
    session.yaml is not valid, a card session of no known camera), an unusable option,
    products its flights cannot make (:func:`check_products`)."""
    if catalog_root is not None and is_remote(catalog_root):
        raise InputError(f"--catalog-root {catalog_root!r} must be a local folder",
                         hint="leave it out to catalogue OUT itself (uploaded with the run)")
    if is_remote(session):
        fs, root = _fs(session)
        if not fs.exists(root.rstrip("/")) or not fs.ls(root.rstrip("/")):
            raise SessionError("no files found", path=session, hint="check the URL and the storage credentials")
    elif not Path(session).is_dir():
        raise SessionError("session folder not found", path=session,
                           hint="pass a field session (session.yaml, response/, vignetting/, reflector/) or a flight "
                                "folder as it comes off the camera's card")
    else:
        check_products(session, products, cache_dir)
    if dask_address and not DASK_ADDRESS.match(dask_address):
        raise InputError(f"--dask-address {dask_address!r} is not a scheduler address", hint="e.g. tcp://10.0.0.5:8786")
    if not (normalise == "relative" or re.fullmatch(r"band:\S+", normalise)):
        raise InputError(f"--normalise {normalise!r}: use relative or band:<name or nm>",
                         hint="panel normalisation needs 'mscal apply --panel' on one flight")
    if illumination not in INTERPOLATION_MODES:
        raise InputError(f"--illumination {illumination!r}: use one of {', '.join(INTERPOLATION_MODES)}")
    if not is_remote(out) and Path(out).exists() and not Path(out).is_dir():
        raise InputError("output exists and is not a folder", path=out)


# --------------------------------------------------------------------------- run record


class Timings:
    """Seconds spent per named step: ``with timings.step("x"): ...``."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.seconds: dict[str, float] = {}

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t, 3)

    def total(self) -> dict[str, float]:
        return {**self.seconds, "total": round(time.perf_counter() - self.t0, 3)}


REPORT_HTML = "report.html"


def qa_report(out_dir: str | Path, flights: Iterable[str]) -> str:
    """``OUT/report.html`` (and ``OUT/calibration.json``) of the run's calibration and flights
    (:mod:`pipeline.products.report`); returns the same warnings and tables as markdown."""
    from pipeline.products.report import write_report_and_markdown

    out_dir = Path(out_dir)
    calibration = out_dir / CALIBRATION_STORE
    _, markdown = write_report_and_markdown(out_dir / REPORT_HTML,
                                            calibration=calibration if calibration.exists() else None,
                                            flights=[out_dir / "flights" / name for name in flights])
    return markdown


def update_catalog(root: str | Path, out_url: str | None = None) -> dict[str, Any]:
    """Update the STAC catalog of ``root`` (:func:`pipeline.products.stac.update_catalog`) after a run.
    ``out_url``: the run's OUT when ``root`` is its staged local copy (names the catalog and
    its default collection after the URL's last part instead of the staging folder).

    Bad content elsewhere under the root (another flight's broken output, a project file with
    a typo) must not fail the run whose outputs are already complete: such an
    :class:`MscalError` is returned as ``{"error": message}`` and logged; I/O errors propagate
    (the flow retries them)."""
    from pipeline.products.stac import update_catalog as _update

    name = out_url.rstrip("/").rsplit("/", 1)[-1] if out_url and is_remote(out_url) else None
    try:
        return _update(root, root_name=name)
    except MscalError as exc:
        log.warning("STAC catalog of %s not updated: %s", root, exc)
        return {"error": str(exc), "catalog": str(Path(root) / "catalog.json")}


def run_record(*, session: str, out: str, plan: CalibrationPlan, flights: dict[str, dict[str, Any]],
               timings: Timings, dask_address: str | None, flow_run_id: str | None = None) -> dict[str, Any]:
    """The contents of ``OUT/run.json`` (SPEC.md, Outputs of the post-flight flow)."""
    return _record(
        {"kind": "field", "calibration": CALIBRATION_STORE, "calibration_cached": plan.cached,
         "calibration_stages": {s.name: {"key": s.key, "cached": s.cached,
                                         "seconds": 0.0 if s.cached else timings.seconds.get(f"fit_{s.name}", 0.0)}
                                for s in plan.stages},
         "fitted": [s.name for s in plan.stages if not s.cached]},
        session=session, out=out, flights=flights, timings=timings, dask_address=dask_address,
        flow_run_id=flow_run_id)


def card_run_record(*, session: str, out: str, plan: dict[str, Any], flights: dict[str, dict[str, Any]],
                    timings: Timings, dask_address: str | None, flow_run_id: str | None = None) -> dict[str, Any]:
    """``OUT/run.json`` of a card session: as :func:`run_record` with nothing fitted, plus
    ``card`` (the camera, its serial and how they were found) and per flight the calibration
    it got and why (``calibration``, ``field_calibration``, ``calibration_source``) and its
    light reference (``reference``)."""
    return _record(
        {"kind": "card", "calibration": None, "calibration_cached": False, "calibration_stages": {}, "fitted": [],
         "card": plan_from_record(plan).record()},
        session=session, out=out, flights=flights, timings=timings, dask_address=dask_address,
        flow_run_id=flow_run_id)


def _record(calibration: dict[str, Any], *, session: str, out: str, flights: dict[str, dict[str, Any]],
            timings: Timings, dask_address: str | None, flow_run_id: str | None) -> dict[str, Any]:
    return {
        "report": REPORT_HTML,
        "format": RUN_FORMAT,
        "session": str(session),
        "out": str(out),
        **calibration,
        "flights": {name: {**summary, "outputs": None if summary.get("status") == "failed" else f"flights/{name}/"}
                    for name, summary in flights.items()},
        "status": "partial" if any(f.get("status") == "failed" for f in flights.values()) else "done",
        "dask_address": dask_address,
        "versions": versions(),
        "timings_s": timings.total(),
        "prefect_flow_run_id": flow_run_id,
        "finished_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def write_run_json(out_dir: str | Path, record: dict[str, Any]) -> Path:
    """``OUT/run.json``, atomically (temporary name, then rename)."""
    path = Path(out_dir) / RUN_JSON
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, record)
    return path


def flight_table(record: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per flight, for the run's table artifact."""
    return [
        {"flight": name, "status": f.get("status", "done"), "frames_in": f["frames_in"], "frames_out": f["frames_out"],
         "quarantined": len(f["quarantined"]), "saturated_pixels": f["saturated_pixels"],
         "up_to_date": f["up_to_date"], "seconds": f["seconds"]}
        for name, f in record["flights"].items()
    ]


def summary_markdown(record: dict[str, Any]) -> str:
    """A short Markdown summary of a run (Prefect artifact, README-style)."""
    stages = ", ".join(f"{k} " + ("cached" if v["cached"] else f"fitted in {v['seconds']:.1f} s")
                       for k, v in record["calibration_stages"].items())
    if record.get("kind") == "card":
        card = record["card"]
        calib = (f"card session of {card['camera']} (serial {card['serial'] or 'unknown'}): "
                 + "; ".join(f"{n} {f.get('calibration', 'failed')}" for n, f in record["flights"].items()))
        holds = "`run.json`, `flights/<name>/`"
    else:
        calib = f"{'reused from the cache' if record['calibration_cached'] else 'fitted'} ({stages})"
        holds = f"`run.json`, `{record['calibration']}`, `flights/<name>/`"
    lines = [
        f"# mscal post-flight run: {record['session']}",
        "",
        f"- outputs: `{record['out']}` ({holds})",
        f"- calibration: {calib}",
        f"- total {record['timings_s']['total']:.1f} s",
        "",
        "| flight | frames out / in | quarantined | saturated px | |",
        "|---|---|---|---|---|",
    ]
    for row in flight_table(record):
        state = "up to date" if row["up_to_date"] else f"{row['seconds']:.1f} s"
        lines.append(f"| {row['flight']} | {row['frames_out']} / {row['frames_in']} | {row['quarantined']} "
                     f"| {row['saturated_pixels']} | {state} |")
    return "\n".join(lines) + "\n"


__all__ = [
    "CalibrationPlan", "RunPaths", "StagePlan", "Timings", "apply_card", "apply_card_flight", "apply_one", "card_run_record", "failed_card_flight", "check_run_inputs", "configure_prefect",
    "default_cache_dir", "flight_dirs", "is_remote", "is_transient", "plan_calibration", "plan_card_session", "publish_calibration", "record_calibration", "session_kind", "session_problem",
    "remove_work", "run_paths", "run_record", "session_products", "check_products", "update_catalog", "stage_in", "summary_markdown", "upload", "write_run_json",
]
