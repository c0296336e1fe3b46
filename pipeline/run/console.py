"""What the command line prints: ``-v/-q/--json`` of every command, progress bars, and the
summary every command ends with.

- :class:`Console` (kept in the click context's ``meta``, so a subcommand's ``-q`` and the
  group's ``-q`` are one setting): verbosity and ``--json``.
- :func:`progress`: a progress bar on stderr, only when stderr is a terminal and not ``-q``
  (stdout stays clean for ``--json``).
- :class:`Summary`: the last thing a command prints: one line, where the outputs are, counts,
  and each quality warning with its number and threshold; with ``--json`` one JSON document
  instead (and nothing else on stdout).
- :func:`report_warnings`: the warnings of the QA report (``report.html``), from the same
  function the report uses (:func:`pipeline.products.report.build_sections`): thresholds are
  in :mod:`pipeline.products.report.thresholds` only.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import click

QUIET, NORMAL, VERBOSE = 0, 1, 2
_META_KEY = "mscal.console"
#: Log level per verbosity: -q only errors, default warnings, -v each stage's progress.
LOG_LEVELS = {QUIET: logging.ERROR, NORMAL: logging.WARNING, VERBOSE: logging.INFO}


@dataclass
class Console:
    """The output settings of one ``mscal`` invocation."""

    verbosity: int = NORMAL
    json: bool = False


def console() -> Console:
    """The current invocation's :class:`Console` (defaults outside a click command)."""
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return Console()
    return ctx.meta.setdefault(_META_KEY, Console())


def _set_verbosity(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if not value:
        return
    c = console()
    level = VERBOSE if param.name == "verbose" else QUIET
    if c.verbosity not in (NORMAL, level):
        raise click.UsageError("give -v or -q, not both", ctx=ctx)
    c.verbosity = level
    logging.getLogger().setLevel(LOG_LEVELS[level])


def _set_json(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value:
        console().json = True


def common_options() -> list[click.Option]:
    """``-v``, ``-q`` and ``--json``: new objects for each command (click owns them)."""
    return [
        click.Option(["-v", "--verbose"], is_flag=True, expose_value=False, callback=_set_verbosity,
                     help="Log the progress of each stage (INFO lines on stderr)."),
        click.Option(["-q", "--quiet"], is_flag=True, expose_value=False, callback=_set_verbosity,
                     help="Only errors on stderr: no progress bars, no notes; the summary keeps its first line "
                          "and the quality warnings."),
        click.Option(["--json"], is_flag=True, expose_value=False, callback=_set_json,
                     help="Print the summary as one JSON document on stdout, and nothing else there."),
    ]


def note(message: str) -> None:
    """An informational line on stderr (skipped files, quarantined frames); silent with -q."""
    if console().verbosity > QUIET:
        click.echo(message, err=True)


def stderr_is_tty() -> bool:
    return sys.stderr.isatty()


@contextmanager
def progress(total: int, label: str) -> Iterator[Callable[..., None]]:
    """A progress bar of ``total`` steps on stderr, when it is a terminal and not ``-q``;
    yields ``advance(n=1)``."""
    if total <= 0 or console().verbosity == QUIET or not stderr_is_tty():
        yield lambda n=1: None
        return
    with click.progressbar(length=total, label=label, file=sys.stderr) as bar:
        yield lambda n=1: bar.update(n)


def _plain(v: Any) -> Any:
    """JSON-safe: numpy scalars to Python, NaN/inf to None, paths to strings."""
    if hasattr(v, "item") and not isinstance(v, (list, dict, str)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    return v


def report_warnings(calibration: str | Path | None = None, flights: Iterable[str | Path] = ()) -> list[dict[str, Any]]:
    """The quality warnings ``report.html`` shows for ``calibration`` and ``flights`` (apply
    OUT folders): section, code, message, value and threshold of each."""
    from pipeline.products.report import build_sections

    sections = build_sections(calibration, list(flights))
    return [{"section": s.title, **_plain(asdict(w))} for s in sections for w in s.warnings]


def _fmt(v: Any) -> str:
    from pipeline.products.report.sections import fmt_value

    return fmt_value(v) if v is not None else "n/a"


@dataclass
class Summary:
    """The summary a command ends with. ``headline``: one line (``wrote OUT (...)``);
    ``outputs``: what was written where; ``counts``: the numbers of the headline, by name;
    ``warnings``: as :func:`report_warnings` gives them; ``details``: more, for ``--json``."""

    command: str
    headline: str
    outputs: dict[str, Any] = field(default_factory=dict)
    counts: dict[str, Any] = field(default_factory=dict)
    warnings: list[dict[str, Any]] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)

    def document(self) -> dict[str, Any]:
        return _plain({"command": self.command, "summary": self.headline, "outputs": self.outputs,
                       "counts": self.counts, "warnings": self.warnings, **self.details})

    def lines(self, verbosity: int = NORMAL) -> list[str]:
        out = [self.headline]
        if verbosity > QUIET:
            out += [f"  {k}: {v}" for k, v in self.outputs.items() if v is not None]
        if self.warnings:
            out.append(f"  {len(self.warnings)} quality warning(s) (as in report.html):")
        for w in self.warnings:
            out.append(f"  warning {w['code']}: {w['message']} (value {_fmt(w.get('value'))}, "
                       f"threshold {_fmt(w.get('threshold'))})")
        return out

    def emit(self) -> None:
        """Print the summary: lines, or with ``--json`` one JSON document."""
        c = console()
        if c.json:
            click.echo(json.dumps(self.document(), indent=2, default=str))
            return
        for line in self.lines(c.verbosity):
            click.echo(line)
