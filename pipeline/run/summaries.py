"""What ``mscal run`` and ``mscal serve`` print when they end: the summary of a post-flight run
(a field session or a card session, one line per card flight) and of a look at the inbox, with
the warnings of the run's QA report (:func:`pipeline.run.console.report_warnings`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from pipeline.run.console import QUIET, Summary, console, note, report_warnings

__all__ = ["echo_run", "echo_serve", "run_warnings"]


def run_warnings(out: str | Path, record: dict) -> list[dict[str, Any]]:
    """The warnings of OUT/report.html of a post-flight run (its calibration and the flights
    it processed); none for a remote OUT (the report is there)."""
    from pipeline.run.runner import CALIBRATION_STORE, failed_flights, is_remote

    if is_remote(str(out)):
        return []
    failed = failed_flights(record)
    store = Path(out) / CALIBRATION_STORE  # a card session has none: the flights' warnings only
    flights = [Path(out) / "flights" / n for n in record["flights"] if n not in failed]
    flights = [f for f in flights if (f / "run.json").is_file()]
    if not store.exists() and not flights:
        return []
    return report_warnings(calibration=store if store.exists() else None, flights=flights)


def echo_run(record: dict, log_file: Path | None = None) -> None:
    for name, f in record["flights"].items():
        for q in f["quarantined"]:
            note(f"quarantined {name}/{q['file']}: {q['reason']}")
        if f.get("skipped"):
            note(f"skipped {len(f['skipped'])} file(s) of {name} that are not captures: "
                 f"{', '.join(s['file'] for s in f['skipped'][:5])}{' ...' if len(f['skipped']) > 5 else ''}")
    from pipeline.run.runner import failed_flights

    failed = failed_flights(record)
    for name, reason in failed.items():
        note(f"flight {name} was not processed: {reason}")
    if record.get("kind") == "card":
        for name, f in record["flights"].items():
            if f.get("status") != "failed":
                note(f"flight {name}: {_card_line(f)}")
        card = record["card"]
        kinds = sorted({f.get("calibration") for f in record["flights"].values() if f.get("calibration")})
        calib = (f"{card['camera']} serial {card['serial'] or 'unknown'}, "
                 f"{' and '.join(kinds) or 'none'} radiometry")
    else:
        calib = "calibration " + ("reused from the cache" if record["calibration_cached"]
                                  else "fitted: " + ", ".join(record["fitted"]))
    done = len(record["flights"]) - len(failed)
    out = record["out"]
    Summary("run", f"wrote {out} ({calib}; {done} flight(s)"
            f"{f', {len(failed)} not processed' if failed else ''}; {record['timings_s']['total']:.1f} s)",
            outputs={"run record": f"{out}/run.json",
                     "calibration store": f"{out}/{record['calibration']}" if record.get("calibration") else None,
                     "flights": f"{out}/flights/", "QA report": f"{out}/{record['report']}"},
            counts={"flights": len(record["flights"]), "flights_not_processed": len(failed),
                    "frames_out": sum(f.get("frames_out") or 0 for f in record["flights"].values()),
                    "quarantined": sum(len(f.get("quarantined") or []) for f in record["flights"].values())},
            warnings=run_warnings(out, record),
            details={"calibration_cached": record["calibration_cached"], "not_processed": failed,
                     **({"card": record["card"], "flights": {n: _card_line(f) for n, f in record["flights"].items()}}
                        if record.get("kind") == "card" else {})}).emit()
    if failed:  # as --strict does for frames: a script sees that something was skipped
        if log_file is not None:
            click.echo(f"details of the flight(s) not processed: {log_file}", err=True)
        raise SystemExit(3)


def _card_line(flight: dict[str, Any]) -> str:
    """One line on a card flight: its radiometry and why, its light reference and where the
    panel's reflectance came from (run.json says why the other references were not used)."""
    ref = flight.get("reference") or {}
    light = ref.get("route", "?")
    if ref.get("panel_reflectance"):
        light += f" (panel reflectance: {ref['panel_reflectance']})"
    elif ref.get("reason"):
        light += f" ({ref['reason']})"
    return (f"radiometry {flight.get('calibration', '?')}"
            + (f" {flight['field_calibration']}" if flight.get("field_calibration") else "")
            + (f" [{flight['calibration_source']}]" if flight.get("calibration_source") else "")
            + f"; light reference {light}")


def echo_serve(done: dict[str, str], out_root: Path) -> None:
    """One line per session processed, each followed by its report's warnings, and one per
    folder or file newly not processed with the reason (still being copied, empty, not a
    folder: named once, not at every look, :func:`pipeline.run.inbox.newly_waiting`; failed:
    why); with --json one JSON document per look at the inbox (one in all with
    --once); nothing when the inbox holds nothing new."""
    if not done:
        return
    from pipeline.run.inbox import load_state, load_waiting

    state, waits = load_state(out_root), load_waiting(out_root)
    docs, why = {}, {}
    for name, status in done.items():
        if status == "waiting":
            why[name] = waits.get(name, {}).get("reason", "")
            docs[name] = Summary("serve", f"{name}: not processed now: {why[name]}")
            continue
        run_json = out_root / name / "run.json"
        record = json.loads(run_json.read_text()) if status != "failed" and run_json.is_file() else None
        warnings = run_warnings(out_root / name, record) if record else []
        why[name] = detail = (state.get(name) or {}).get("detail", "") if status != "done" else ""
        docs[name] = Summary("serve", f"{name}: {status} -> {out_root / name}" + (f": {detail}" if detail else ""),
                             warnings=warnings)
    processed = [n for n, s in done.items() if s != "waiting"]
    if console().json:
        Summary("serve", f"{len(processed)} session(s) processed into {out_root}", outputs={"sessions": out_root},
                counts={"sessions": len(processed), "failed": sum(done[n] != "done" for n in processed),
                        "waiting": len(done) - len(processed)},
                details={"sessions": {n: {"status": done[n], "out": out_root / n, "warnings": d.warnings,
                                          "detail": why[n]} for n, d in docs.items()}}).emit()
        return
    for d in docs.values():
        for line in d.lines(QUIET):
            click.echo(line)
