"""The post-flight Prefect flow: wiring only, each task one ``pipeline`` call on paths.

``post_flight``: stage remote inputs, calibrate the session (each stage taken from the cache
when its inputs are unchanged), apply the calibration to every ``SESSION/flights/<name>/``,
write ``OUT/run.json``, update the STAC catalog of the output root, upload remote outputs
(``run.json`` last), and summarise the run as Prefect artifacts. ``process_inbox``: one pass
over an inbox of session folders (``mscal serve``), each complete, unprocessed session through
``post_flight``; it updates OUT_ROOT's catalog.

Import this module only after :func:`pipeline.run.runner.configure_prefect`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run
from prefect.tasks import exponential_backoff

from pipeline.calibrate import fit as calibrate
from pipeline.run import inbox, runner
from pipeline.run.console import progress


def _transient(task_: Any, task_run: Any, state: Any) -> bool:
    """Retry only I/O failures (network, storage); bad input and failed fits fail at once."""
    return runner.is_transient(state.result(raise_on_failure=False))


#: I/O tasks: retried with exponential backoff (2 s, 4 s, 8 s).
IO = {"retries": 3, "retry_delay_seconds": exponential_backoff(backoff_factor=2),
      "retry_condition_fn": _transient, "cache_policy": NO_CACHE}


@task(**IO)
def stage_in(url: str, local: str) -> str:
    return str(runner.stage_in(url, local))


@task(cache_policy=NO_CACHE)
def plan_calibration(session: str, cache_dir: str, response_method: str) -> runner.CalibrationPlan:
    return runner.plan_calibration(session, cache_dir, response_method)


@task(cache_policy=NO_CACHE, task_run_name="fit-{stage}")
def fit_stage(stage: str, session: str, store: str, partial: str | None, response_method: str) -> str:
    calibrate.fit_stage(stage, session, store, partial, response_method)
    return store


@task(**IO)
def publish_calibration(store: str, out: str) -> str:
    return str(runner.publish_calibration(store, out))


@task(cache_policy=NO_CACHE)
def list_flights(session: str) -> dict[str, str]:
    return runner.flight_dirs(session)


@task(**IO, task_run_name="apply-{name}")
def apply_flight(name: str, flight_dir: str, calibration: str, out: str, normalise: str,
                 dask_address: str | None, illumination: str = "linear", scheduler: str = "auto",
                 workers: int = 0, direct_io: bool | None = None,
                 products: dict[str, Any] | None = None) -> dict[str, Any]:
    try:
        return runner.apply_one(flight_dir, calibration, out, normalise=normalise, dask_address=dask_address,
                                illumination=illumination, scheduler=scheduler, workers=workers, direct_io=direct_io,
                                products=products)
    except Exception:  # the run goes on without this flight; its traceback goes to the run's log file
        get_run_logger().exception("flight %s could not be processed", name)
        raise


@task(cache_policy=NO_CACHE)
def record_calibration(session: str, store: str, cache_dir: str) -> dict[str, str]:
    return runner.record_calibration(session, store, cache_dir)


@task(cache_policy=NO_CACHE)
def plan_card(session: str, cache_dir: str) -> dict[str, Any]:
    return runner.plan_card_session(session, cache_dir)


@task(**IO, task_run_name="apply-{name}")
def apply_card(name: str, plan: dict[str, Any], out: str, dask_address: str | None, scheduler: str = "auto",
               workers: int = 0, direct_io: bool | None = None,
               products: dict[str, Any] | None = None) -> dict[str, Any]:
    try:
        return runner.apply_card(plan, name, out, dask_address=dask_address, scheduler=scheduler, workers=workers,
                                 direct_io=direct_io, products=products)
    except Exception:  # the run goes on without this flight; its traceback goes to the run's log file
        get_run_logger().exception("flight %s could not be processed", name)
        raise


@task(cache_policy=NO_CACHE)
def write_report(out: str, flights: list[str]) -> str:
    return runner.qa_report(out, flights)


@task(**IO)
def write_run_json(out: str, record: dict[str, Any]) -> str:
    return str(runner.write_run_json(out, record))


@task(**IO)
def update_catalog(root: str, out_url: str | None) -> dict[str, Any]:
    return runner.update_catalog(root, out_url)


@task(**IO)
def upload(local: str, url: str) -> int:
    return runner.upload(local, url)


@flow(name="post-flight")
def post_flight(
    session: str,
    out: str,
    response_method: Literal["forward", "alternating"] = "forward",
    normalise: str = "relative",
    dask_address: str | None = None,
    cache_dir: str | None = None,
    work_dir: str | None = None,
    catalog_root: str | None = None,
    illumination: Literal["nearest", "linear"] = "linear",
    scheduler: Literal["auto", "threads", "processes"] = "auto",
    workers: int = 0,
    direct_io: bool | None = None,
    products: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Calibrate SESSION once and apply it to each of its flights; outputs in OUT.

    ``session``/``out``: folders or fsspec URLs (``s3://bucket/prefix``). ``dask_address``:
    ``tcp://HOST:PORT`` of a running ``dask scheduler`` (default: a local cluster for long
    flights). ``cache_dir``: the calibration cache (default :func:`runner.default_cache_dir`).
    ``work_dir``: where remote inputs and outputs are staged (default: a temporary folder).
    ``catalog_root``: the local output root whose STAC catalog is updated after the run
    (default: OUT itself; ``process_inbox`` gives its OUT_ROOT).
    ``illumination``: how the light of several reflector captures is interpolated to each
    frame's time (``nearest`` or ``linear``).
    ``scheduler``, ``workers``, ``direct_io``: how apply runs without ``dask_address``
    (:class:`pipeline.apply.execution.Execution`; recorded per flight in run.json).
    ``products``: the keys of the products choice the command line gives (``radiance``,
    ``indices``, ``tiffs``), over session.yaml's ``products`` (:func:`runner.session_products`).
    """
    log = get_run_logger()
    timings = runner.Timings()
    paths = runner.run_paths(session, out, work_dir)
    if runner.is_remote(session):
        with timings.step("stage_in"):
            stage_in(session, paths.session)
    cache = str(cache_dir or runner.default_cache_dir())
    if runner.session_kind(paths.session) == "card":
        return _card_flight(session, out, paths, cache, timings, dask_address=dask_address, catalog_root=catalog_root,
                            scheduler=scheduler, workers=workers, direct_io=direct_io, products=products)
    chosen = runner.session_products(paths.session, products).record()
    plan = plan_calibration(paths.session, cache, response_method)
    flights = list_flights(paths.session)
    summaries: dict[str, dict[str, Any]] = {}
    # one bar for the run: each stage, each flight and the report (stderr on a terminal, not -q)
    with progress(len(plan.stages) + len(flights) + 1, "post-flight") as advance:
        for st in plan.stages:
            if st.cached:
                log.info("%s: inputs unchanged, calibration reused from the cache (%s), not re-fitted", st.name, st.store)
            else:
                with timings.step(f"fit_{st.name}"):
                    fit_stage(st.name, paths.session, st.store, st.partial, response_method)
            advance(1)
        published = publish_calibration(plan.final_store, paths.out)
        library = record_calibration(paths.session, plan.final_store, cache)
        for name, flight_dir in flights.items():
            with timings.step(f"apply_{name}"):
                # apply reads OUT/calibration.zarr (the same arrays as the cached store), so that a
                # flight's run.json names the calibration it applied by its place among the outputs
                state = apply_flight(name, flight_dir, str(Path(published).resolve()),
                                     str(Path(paths.out) / "flights" / name),
                                     normalise, dask_address, illumination, scheduler, workers, direct_io,
                                     chosen, return_state=True)
            summaries[name] = _outcome(state, flight_dir)
            advance(1)
        qa_markdown = _report(paths.out, summaries, timings)
        advance(1)
    record = runner.run_record(session=session, out=out, plan=plan, flights=summaries, timings=timings,
                               dask_address=dask_address, flow_run_id=flow_run.id)
    record["calibration_library"] = library
    _finish(record, qa_markdown, session, out, paths, catalog_root)
    log.info("calibration %s; %d flight(s); outputs in %s",
             "reused from the cache (nothing re-fitted)" if plan.cached else f"fitted: {', '.join(record['fitted'])}",
             len(summaries), out)
    return record


def _outcome(state: Any, flight_dir: str) -> dict[str, Any]:
    """A flight's summary; one bad flight (empty, every frame quarantined, unreadable) does not
    cost the others theirs."""
    return state.result() if state.is_completed() else \
        runner.failed_flight(flight_dir, state.result(raise_on_failure=False))


def _report(out: str, summaries: dict[str, dict[str, Any]], timings: runner.Timings) -> str:
    """OUT/report.html of the flights processed; its markdown for the artifact."""
    with timings.step("report"):
        return write_report(out, [n for n, f in summaries.items() if f.get("status") != "failed"])


def _finish(record: dict[str, Any], qa_markdown: str, session: str, out: str, paths: runner.RunPaths,
            catalog_root: str | None) -> None:
    """run.json, the STAC catalog, the upload and the artifacts of a run (both kinds of session)."""
    write_run_json(paths.out, record)
    update_catalog(catalog_root or paths.out, None if catalog_root else out)  # a bad root is logged, not fatal
    if runner.is_remote(out):
        upload(paths.out, out)
    runner.remove_work(paths)
    create_markdown_artifact(runner.summary_markdown(record), key="mscal-post-flight",
                             description=f"mscal run {session}")
    create_table_artifact(runner.flight_table(record), key="mscal-flights", description="flights of the run")
    create_markdown_artifact(qa_markdown, key="mscal-qa-report", description="QA report: fits, warnings, flights")
    log = get_run_logger()
    for name, reason in runner.failed_flights(record).items():
        log.warning("flight %s was not processed: %s", name, reason)


def _card_flight(session: str, out: str, paths: runner.RunPaths, cache: str, timings: runner.Timings, *,
                 dask_address: str | None, catalog_root: str | None, scheduler: str, workers: int,
                 direct_io: bool | None, products: dict[str, Any] | None = None) -> dict[str, Any]:
    """A card session (a flight folder as it comes off the camera): each of its flights with the
    camera's factory radiometry or the library's field calibration of its serial, no fits."""
    plan = plan_card(paths.session, cache)
    summaries: dict[str, dict[str, Any]] = {}
    with progress(len(plan["flights"]) + 1, "post-flight") as advance:
        for flight in plan["flights"]:
            name = flight["name"]
            with timings.step(f"apply_{name}"):
                state = apply_card(name, plan, str(Path(paths.out) / "flights" / name), dask_address, scheduler,
                                   workers, direct_io, products, return_state=True)
            summaries[name] = state.result() if state.is_completed() else \
                runner.failed_card_flight(flight, state.result(raise_on_failure=False))
            advance(1)
        qa_markdown = _report(paths.out, summaries, timings)
        advance(1)
    record = runner.card_run_record(session=session, out=out, plan=plan, flights=summaries, timings=timings,
                                    dask_address=dask_address, flow_run_id=flow_run.id)
    _finish(record, qa_markdown, session, out, paths, catalog_root)
    get_run_logger().info("card session: camera %s serial %s; %d flight(s); outputs in %s", plan["camera"],
                          plan["serial"], len(summaries), out)
    return record


@flow(name="process-inbox")
def process_inbox(inbox_dir: str, out_root: str, settle_seconds: float = 600.0,
                  response_method: Literal["forward", "alternating"] = "forward",
                  dask_address: str | None = None, cache_dir: str | None = None,
                  products: dict[str, Any] | None = None) -> dict[str, str]:
    """One pass over INBOX: every complete, unprocessed session (a field session or a flight
    folder off a camera's card) through ``post_flight`` into ``OUT_ROOT/<session name>``; each
    recorded in the serve state file; one that cannot be run (no known camera, two cameras) is
    recorded as failed with the reason, and the others go on. Returns ``{name: status}`` of the
    sessions processed in this pass (done, partial, failed) and of what was not processed now
    (``waiting``: still being copied, empty, not a folder; the reason is in the state file).
    ``products``: the command line's products choice, for every session (over its session.yaml's)."""
    log = get_run_logger()
    done: dict[str, str] = {}
    for p in inbox.pending_sessions(inbox_dir, out_root, settle_seconds):
        log.info("session %s: complete and not processed yet", p.name)
        problem = runner.session_problem(p.path, cache_dir, products)  # no known camera, a bad session.yaml, ...
        if problem is not None:
            log.warning("session %s not processed: %s", p.name, problem)
            inbox.record(Path(out_root), p.name, listing=p.listing, content=p.content, status="failed", detail=problem)
            done[p.name] = "failed"
            continue
        state = post_flight(p.path, str(Path(out_root) / p.name), response_method=response_method,
                            dask_address=dask_address, cache_dir=cache_dir, catalog_root=str(out_root),
                            products=products, return_state=True)
        status = "done" if state.is_completed() else "failed"
        detail = "" if status == "done" else str(state.message or "")
        if status == "done":  # processed, but some flights could not be: said in the state file
            failed = runner.failed_flights(state.result())
            if failed:
                status, detail = "partial", "; ".join(f"{n}: {r}" for n, r in failed.items())
        inbox.record(Path(out_root), p.name, listing=p.listing, content=p.content, status=status, detail=detail)
        done[p.name] = status
    waits = inbox.waiting(inbox_dir, settle_seconds)  # every look: in the state file
    news = inbox.newly_waiting(inbox.load_waiting(Path(out_root)), waits)  # the summary: what changed
    inbox.record_waiting(Path(out_root), waits)
    for name, why in waits.items():
        log.info("%s not processed now: %s", name, why)
    done.update({name: "waiting" for name in news})
    return done
