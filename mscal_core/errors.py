"""The one exception hierarchy of mscal.

Every message says what is wrong and how to fix it, and names the file when a file is at
fault. The command line prints ``str(error)`` on one line and exits non-zero; it never shows
a traceback for an :class:`MscalError`.
"""

from __future__ import annotations

from pathlib import Path


class MscalError(Exception):
    """Base class of every error mscal raises on purpose."""

    exit_code = 2
    #: The log file holding the details (traceback, Prefect's and Dask's records) of a command
    #: that runs Prefect or Dask, when one was written (:mod:`pipeline.run.logs`).
    log_file: str | None = None

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        self.path = None if path is None else str(path)
        self.hint = hint
        self.reason = message
        text = message if self.path is None else f"{self.path}: {message}"
        if hint:
            text = f"{text} ({hint})"
        super().__init__(text)


class InputError(MscalError):
    """Bad user input: a file, folder, option or value that cannot be used as given."""


class CatalogError(InputError):
    """A catalog entry (camera, target, index) is missing or invalid."""


class SessionError(InputError):
    """A session folder or its session.yaml is missing or invalid."""


class FrameError(InputError):
    """One frame cannot be used: missing, unreadable, truncated, no exposure time."""


class FitError(MscalError):
    """A calibration fit cannot proceed on the data given (e.g. too few exposures)."""


class LockedError(MscalError):
    """Another process is writing into the same output; nothing was written.

    Exit status 75 (EX_TEMPFAIL: the same command can succeed later).
    """

    exit_code = 75


class UnexpectedError(MscalError):
    """Not an error of the input but a defect of mscal (an exception it did not expect).

    Exit status 1. The command line says it in one line naming the log file that holds the
    traceback.
    """

    exit_code = 1

    def __init__(self, message: str, *, log_file: str | Path | None = None):
        super().__init__(f"unexpected error: {message}",
                         hint="a defect of mscal, not of your input: please report it with the log file")
        self.log_file = None if log_file is None else str(log_file)


class CalibrationStoreError(InputError):
    """A calibration store is missing, incomplete or does not match the camera."""


class ProcessesUnavailable(MscalError):
    """Worker processes cannot start on this system.

    No working POSIX semaphores (AWS Lambda, some sandboxes), no temporary folder for the
    worker server's socket, no processes left. Where mscal chose processes itself it runs on
    threads (or in its own process) instead.
    """
