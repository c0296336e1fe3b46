"""The log file of a command that runs Prefect or Dask (``mscal run``, ``serve``, ``demo``).

Prefect logs every flow and task run (and a full traceback for each failure) to the console,
and Dask's ``distributed`` adds its own console handlers: 60-110 lines around the one line
that says what went wrong. Inside :func:`command_log` those records go to
``OUT/logs/<UTC time>-<command>.log`` instead (and also to the terminal with ``-v``):

* every console handler (a ``StreamHandler`` on stderr/stdout) of the root logger and of the
  loggers that do not propagate (``prefect._internal``, ``uvicorn``, ``distributed``, ...)
  is taken off, and the file handler put in its place; Python warnings are logged too;
* an :class:`~mscal_core.errors.MscalError` leaving the block is written to the file with its
  traceback and gets the file's path as ``log_file`` (the command line prints both on one
  line); any other exception becomes an :class:`~mscal_core.errors.UnexpectedError` naming
  the file, its traceback in the file only.

Prefect's console handlers stay off after the block: its exit hook ("Stopping temporary
server") would otherwise print after the command's last line. The ``run`` progress bar writes
to the terminal and is no longer interleaved with Prefect's INFO lines.
"""

from __future__ import annotations

import importlib.util
import logging
import sys
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

from mscal_core.errors import MscalError, UnexpectedError

__all__ = ["LOGS_DIR", "command_log", "log_path"]

#: Folder of the log files inside an output folder.
LOGS_DIR = "logs"

#: Loggers that say every HTTP request Prefect's client makes to its server at INFO.
_CHATTY = ("httpx", "httpcore")

_FORMAT = "%(asctime)s %(levelname)-7s %(name)s%(run)s: %(message)s"


class _RunFormatter(logging.Formatter):
    """Prefect's flow and task run records carry the run's name: it is written after the logger's."""

    def format(self, record: logging.LogRecord) -> str:
        name = getattr(record, "task_run_name", None) or getattr(record, "flow_run_name", None)
        record.run = f" [{name}]" if name else ""
        return super().format(record)


def log_path(out: str | Path, command: str, now: datetime | None = None) -> Path:
    """``OUT/logs/<UTC time>-<command>.log`` (``20260601T100211Z-run.log``)."""
    stamp = (now or datetime.now(timezone.utc)).strftime("%Y%m%dT%H%M%SZ")
    return Path(out) / LOGS_DIR / f"{stamp}-{command}.log"


def _is_console(handler: logging.Handler) -> bool:
    if isinstance(handler, logging.FileHandler) or not isinstance(handler, logging.StreamHandler):
        return False
    stream = getattr(handler, "stream", None)
    return stream in (sys.stderr, sys.stdout, sys.__stderr__, sys.__stdout__) or \
        getattr(stream, "name", None) in ("<stderr>", "<stdout>") or type(handler).__name__.endswith("ConsoleHandler")


def _loggers() -> list[logging.Logger]:
    """The root logger and every logger that exists now."""
    manager = logging.Logger.manager
    return [logging.getLogger(), *(lg for lg in list(manager.loggerDict.values()) if isinstance(lg, logging.Logger))]


def _route_to(file_handler: logging.Handler, verbose: bool) -> list[logging.Logger]:
    """Put ``file_handler`` where records end: the root, and each logger that does not
    propagate and had a console handler (which is removed unless ``verbose``)."""
    routed = []
    for lg in _loggers():
        consoles = [h for h in lg.handlers if _is_console(h)]
        if not verbose:
            for h in consoles:
                lg.removeHandler(h)
        if lg is logging.getLogger() or (consoles and not lg.propagate):
            lg.addHandler(file_handler)
            routed.append(lg)
    return routed


@contextmanager
def command_log(out: str | Path, command: str, *, verbose: bool = False) -> Iterator[Path]:
    """Send the log records of the block (Prefect's, Dask's, mscal's) to a new log file in
    ``out`` (see the module); yields its path."""
    path = log_path(out, command)
    path.parent.mkdir(parents=True, exist_ok=True)
    if importlib.util.find_spec("distributed") is not None:
        import distributed  # noqa: F401  (it adds its console handlers on import: taken off below)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(_RunFormatter(_FORMAT))
    handler.setLevel(logging.DEBUG if verbose else logging.INFO)
    root = logging.getLogger()
    level = root.level
    root.setLevel(min(level, logging.INFO) if level else logging.INFO)
    logging.captureWarnings(True)
    chatty = {name: logging.getLogger(name).level for name in _CHATTY}
    for name in _CHATTY:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.WARNING)
    routed = _route_to(handler, verbose)
    log = logging.getLogger("mscal")
    log.info("%s", " ".join(sys.argv))
    try:
        yield path
    except MscalError as exc:
        log.error("%s", exc, exc_info=True)
        exc.log_file = str(path)
        raise
    except Exception as exc:  # a defect: the traceback in the file, one line on the terminal
        log.error("unexpected error", exc_info=True)
        raise UnexpectedError(f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": "),
                              log_file=path) from exc
    finally:
        for lg in routed:
            lg.removeHandler(handler)
        handler.close()
        logging.captureWarnings(False)
        root.setLevel(level)
        for name, lvl in chatty.items():
            logging.getLogger(name).setLevel(lvl)
