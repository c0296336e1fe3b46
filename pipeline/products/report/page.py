"""The report as a page, a dict and markdown: :func:`build_sections` gathers the sections,
:func:`write_report` writes the self-contained HTML (and ``calibration.json``) atomically,
:func:`report_markdown` / :func:`report_dict` give the same warnings and tables.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Sequence

import numpy as np
import xarray as xr
from mscal_core.errors import InputError
from mscal_core.illumination import colour_change

from pipeline.products.report.calibration import (
    calibration_warnings,
    reflector_corrections,
    reflector_image_names,
    stage_results,
)
from pipeline.products.report.figures import figure_png
from pipeline.products.report.inputs import FlightResults, as_calibration, open_flight
from pipeline.products.report.season import season_sections
from pipeline.products.report.sections import Section, Table, band_table, calibration_section, flight_section, fmt_value
from pipeline.products.report.thresholds import QAWarning
from pipeline.storage.atomic import write_text_atomic

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- machine-readable


def build_sections(calibration: str | Path | xr.Dataset | None = None,
                   flights: Iterable[str | Path | FlightResults] = (), stats: Any = None) -> list[Section]:
    """The report's sections; nothing is rendered yet. ``stats``: an ``mscal stats`` table
    (DataFrame or its Parquet/CSV path) for the season plots."""
    ds = as_calibration(calibration)
    fl = [f if isinstance(f, FlightResults) else open_flight(f) for f in flights]
    if ds is None and not fl and stats is None:
        raise InputError("nothing to report",
                         hint="give --calibration CALIB.zarr, --flight OUT_DIR and/or --stats TABLE.parquet")
    sections = [calibration_section(ds, fl)] if ds is not None else []
    sections += [flight_section(f, ds) for f in fl]
    if stats is not None:
        sections += season_sections(stats)
    return sections


def write_season_report(stats: Any, out_html: str | Path, title: str | None = None) -> Path:
    """A self-contained page of the season plots of an ``mscal stats`` table, atomically."""
    out_html = Path(out_html)
    write_text_atomic(out_html, sections_html(season_sections(stats), title or "mscal season report"))
    return out_html


def calibration_summary(ds: xr.Dataset) -> dict[str, Any]:
    """``calibration.json``: per-band fit numbers, stage summaries, warnings."""
    t = band_table(ds)
    stages = {}
    for stage in ("response", "vignetting", "illumination"):
        st = stage_results(ds, stage)
        if st:
            stages[stage] = {"residuals": st.get("residuals", {}), "skipped": st.get("skipped", []),
                             "inputs": len(st.get("inputs") or {}), "seconds": st.get("seconds")}
    out: dict[str, Any] = {
        "camera": ds.attrs.get("camera"), "mscal_version": ds.attrs.get("mscal_version"),
        "created_utc": ds.attrs.get("created_utc"), "fits": ds.attrs.get("fits", []),
        "bands": [dict(zip(t.columns, row)) for row in t.rows], "stages": stages,
        "warnings": [asdict(w) for w in calibration_warnings(ds)],
    }
    if "capture_spectral_factor" in ds:
        change = colour_change(ds["capture_spectral_factor"].values)
        out["reflector_captures"] = [
            {"name": str(ds["capture_name"].values[c]),
             "time": None if np.isnat(ds["capture_time"].values[c]) else str(ds["capture_time"].values[c])[:23] + "Z",
             "level": float(ds["capture_level"].values[c]),
             "irradiance": None if not np.isfinite(ds["capture_irradiance"].values[c]) else float(ds["capture_irradiance"].values[c]),
             "colour_change_from_previous": None if c == 0 else float(change[c - 1])}
            for c in range(ds.sizes["capture"])]
    if "reflector_dn" in ds:
        out["reflector_eq15_vs_eq16"] = [
            {"image": reflector_image_names(ds)[r["image"]], "eq15_spread": r["eq15_spread"], "eq16_spread": r["eq16_spread"]}
            for r in reflector_corrections(ds)]
    return json.loads(json.dumps(out, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def report_dict(calibration: str | Path | xr.Dataset | None = None,
                flights: Iterable[str | Path | FlightResults] = ()) -> dict[str, Any]:
    """The report's warnings and tables as a JSON-able dict (no figures)."""
    return _sections_dict(build_sections(calibration, flights))


def _sections_dict(sections: Sequence[Section]) -> dict[str, Any]:
    return {"sections": [{
        "title": s.title, "warnings": [asdict(w) for w in s.warnings],
        "tables": [{"title": t.title, "columns": t.columns, "rows": [[fmt_value(v) for v in r] for r in t.rows], "note": t.note}
                   for t in s.tables],
        "figures": [c for c, _ in s.figures]} for s in sections]}


def _md_cell(v: Any) -> str:
    return fmt_value(v).replace("|", "\\|").replace("\n", " ")


def report_markdown(calibration: str | Path | xr.Dataset | None = None,
                    flights: Iterable[str | Path | FlightResults] = (), title: str | None = None) -> str:
    """The report's warnings and tables as markdown (e.g. a Prefect markdown artifact)."""
    return sections_markdown(build_sections(calibration, flights), title)


def sections_markdown(sections: Sequence[Section], title: str | None = None) -> str:
    lines = [f"# {title or 'mscal QA report'}", ""]
    for s in sections:
        lines += [f"## {s.title}", ""]
        if s.warnings:
            lines += ["| warning | message | value | threshold |", "| --- | --- | --- | --- |"]
            lines += [f"| {w.code} | {_md_cell(w.message)} | {fmt_value(w.value)} | {fmt_value(w.threshold)} |" for w in s.warnings]
        else:
            lines.append("No warnings.")
        lines.append("")
        for t in s.tables:
            lines += [f"### {t.title}", ""]
            if t.rows:
                lines += ["| " + " | ".join(t.columns) + " |", "|" + " --- |" * len(t.columns)]
                lines += ["| " + " | ".join(_md_cell(v) for v in r) + " |" for r in t.rows]
            if t.note:
                lines.append(f"_{t.note}_")
            lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- HTML

CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1300px;color:#222;padding:0 1em}
h1{font-size:1.5em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;font-size:.8em;margin:.5em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#f0f0f0}
td:first-child,th:first-child{text-align:left}
.warn{background:#fff4e0;border-left:4px solid #e69500;padding:.4em .8em;margin:.3em 0}
.ok{background:#e8f6e8;border-left:4px solid #3a3;padding:.4em .8em}
.quarantined td{background:#fde8e8}
figure{margin:1em 0}img{max-width:100%;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
.note{font-size:.8em;color:#666}
"""

#: Counts images that failed to decode once the page has loaded (checked by the slow test).
BROKEN_IMAGES_SCRIPT = (
    "window.addEventListener('load',function(){var n=0;"
    "document.querySelectorAll('img').forEach(function(i){if(!i.complete||i.naturalWidth===0){n++;}});"
    "document.body.setAttribute('data-broken-images',String(n));});"
)

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"


def _html_table(t: Table) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in t.columns)
    body = []
    for r in t.rows:
        cls = ' class="quarantined"' if "quarantined" in r else ""
        body.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(fmt_value(v))}</td>" for v in r) + "</tr>")
    note = f'<p class="note">{html.escape(t.note)}</p>' if t.note else ""
    table = f"<table><tr>{head}</tr>{''.join(body)}</table>" if t.rows else ""
    return f"<h3>{html.escape(t.title)}</h3>{table}{note}"


def _html_warnings(ws: Sequence[QAWarning]) -> str:
    if not ws:
        return '<p class="ok">No warnings.</p>'
    return "".join(f'<p class="warn"><b>{html.escape(w.code)}</b>: {html.escape(w.message)} '
                   f"(value {fmt_value(w.value)}, threshold {fmt_value(w.threshold)})</p>" for w in ws)


def _html_figure(caption: str, build: Callable[[], Figure]) -> str:
    png = base64.b64encode(figure_png(build())).decode("ascii")
    alt = html.escape(caption)
    return (f'<figure><img src="data:image/png;base64,{png}" alt="{alt}">'
            f"<figcaption>{alt}</figcaption></figure>")


def sections_html(sections: Sequence[Section], title: str, advance: Callable[[], None] | None = None) -> str:
    """The whole page: inline CSS, embedded PNGs, no external resource of any kind.
    ``advance``: called after each figure is rendered (a progress bar)."""
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f'<meta http-equiv="Content-Security-Policy" content="{CSP}">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<nav>" + " · ".join(f'<a href="#{html.escape(s.anchor)}">{html.escape(s.title)}</a>' for s in sections) + "</nav>",
    ]
    for s in sections:
        parts.append(f'<section id="{html.escape(s.anchor)}"><h2>{html.escape(s.title)}</h2>')
        parts.append(_html_warnings(s.warnings))
        parts += [_html_table(t) for t in s.tables]
        for c, fn in s.figures:
            parts.append(_html_figure(c, fn))
            if advance is not None:
                advance()
        parts.append("</section>")
    parts.append(f"<script>{BROKEN_IMAGES_SCRIPT}</script></body></html>")
    return "\n".join(parts)


def write_report(out_html: str | Path, *, calibration: str | Path | xr.Dataset | None = None,
                 flights: Iterable[str | Path | FlightResults] = (), title: str | None = None,
                 stats: Any = None) -> Path:
    """Write the self-contained ``out_html`` (atomically); with a calibration, also
    ``calibration.json`` beside it; with ``stats`` (an ``mscal stats`` table), the season
    plots. Returns the HTML path."""
    return write_report_and_markdown(out_html, calibration=calibration, flights=flights, title=title,
                                     stats=stats)[0]


def write_report_and_markdown(out_html: str | Path, *, calibration: str | Path | xr.Dataset | None = None,
                              flights: Iterable[str | Path | FlightResults] = (), title: str | None = None,
                              stats: Any = None) -> tuple[Path, str]:
    """:func:`write_report`, also returning the page's warnings and tables as markdown (for a
    Prefect artifact), from the same sections (the plots are made once)."""
    out_html, sections = write_report_sections(out_html, calibration=calibration, flights=flights, title=title,
                                               stats=stats)
    return out_html, sections_markdown(sections, _title(title, as_calibration(calibration)))


def _title(title: str | None, ds: xr.Dataset | None) -> str:
    return title or "mscal QA report" + (f": {ds.attrs.get('camera')}" if ds is not None else "")


def write_report_sections(out_html: str | Path, *, calibration: str | Path | xr.Dataset | None = None,
                          flights: Iterable[str | Path | FlightResults] = (), title: str | None = None,
                          stats: Any = None,
                          progress: Callable[[int], Any] | None = None) -> tuple[Path, list[Section]]:
    """:func:`write_report`, also returning the page's sections (their warnings are the
    page's). ``progress(n)``: a context manager yielding ``advance`` for the ``n`` figures
    (e.g. :func:`pipeline.run.console.progress` bound to a label)."""
    out_html = Path(out_html)
    ds = as_calibration(calibration)
    sections = build_sections(ds, flights, stats)
    if progress is None:
        page = sections_html(sections, _title(title, ds))
    else:
        with progress(sum(len(s.figures) for s in sections)) as advance:
            page = sections_html(sections, _title(title, ds), advance)
    if ds is not None:
        write_text_atomic(out_html.parent / "calibration.json", json.dumps(calibration_summary(ds), indent=2))
    write_text_atomic(out_html, page)
    return out_html, sections
