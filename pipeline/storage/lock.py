"""One writer per output folder: an advisory lock that names its holder.

A lock is a file in the folder (``.mscal.lock`` by default) held with ``flock``, removed by its
holder when it finishes. The kernel drops the lock when its process ends, however it ends
(SIGKILL, power loss aside), so a lock whose process is gone is simply taken over (its file
stays until then); what the holder wrote into the file (pid, host, start time, command) is
only there to name it in the message a second process gets:

    OUT: another mscal run is writing here: pid 4127 on farm-pc, since 2026-06-01T10:02:11Z,
    `mscal run session -o OUT` (wait for it, or run again with --wait)

``flock`` locks are per open file description: two :class:`FolderLock` of one process on one
folder exclude each other too. On file systems without ``flock`` (some network mounts) the
lock is a no-op there and says so in the log.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import shlex
import socket
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType

from mscal_core.errors import LockedError

log = logging.getLogger(__name__)

LOCK_NAME = ".mscal.lock"
#: How often a waiting process tries again.
POLL_S = 0.2


def holder_info() -> dict[str, object]:
    """What this process writes into a lock it holds."""
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command": shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else "?",
    }


def describe_holder(text: str) -> str:
    """One line naming the holder from a lock file's content (whatever state it is in)."""
    try:
        h = json.loads(text)
        return f"pid {h['pid']} on {h['host']}, since {h['started']}, `{h['command']}`"
    except (ValueError, KeyError, TypeError):
        return "a process that has not said who it is yet"


#: How long a refused process waits for a holder that has just taken the lock to write who it is.
SAY_WHO_S = 2.0


def _holder_text(fd: int) -> str:
    """The lock file's content, once its holder has written it: a holder takes the lock, then
    writes (see :meth:`FolderLock.acquire`); a second process that comes in between waits a
    moment (:data:`SAY_WHO_S`) rather than say that it does not know who holds the lock."""
    deadline = time.monotonic() + SAY_WHO_S
    while True:
        text = os.pread(fd, 4096, 0).decode(errors="replace")
        try:
            json.loads(text)
            return text
        except ValueError:
            if time.monotonic() >= deadline:
                return text
        time.sleep(0.02)


class FolderLock:
    """Exclusive lock on ``folder`` (created if missing), as a context manager.

    ``wait``: False refuses at once with :class:`LockedError` naming the holder; True waits
    as long as it takes; a number waits that many seconds, then refuses. ``what`` names the
    writer in the message ("mscal run", "the raw datacube"); ``output``: the path the message
    names (what the lock guards, e.g. a store beside its lock file; default ``folder``).
    """

    def __init__(self, folder: str | Path, *, name: str = LOCK_NAME, wait: bool | float = False,
                 what: str = "another mscal process", output: str | Path | None = None) -> None:
        self.folder = Path(folder)
        self.path = self.folder / name
        self.wait = wait
        self.what = what
        self.output = self.folder if output is None else Path(output)
        self._fd: int | None = None

    def acquire(self) -> "FolderLock":
        """Take the lock (see the class); returns self."""
        self.folder.mkdir(parents=True, exist_ok=True)
        deadline = None if self.wait is True else time.monotonic() + float(self.wait or 0)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                if self._lock(fd, deadline) and not self._same_file(fd):
                    os.close(fd)  # the holder removed the file as it finished: lock the new one
                    continue
                os.ftruncate(fd, 0)
                os.pwrite(fd, json.dumps(holder_info()).encode(), 0)
            except BaseException:
                os.close(fd)
                raise
            self._fd = fd
            return self

    def _lock(self, fd: int, deadline: float | None) -> bool:
        """flock ``fd``, waiting until ``deadline``; False where the file system has no locks."""
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                if deadline is not None and time.monotonic() >= deadline:
                    holder = describe_holder(_holder_text(fd))
                    raise LockedError(f"{self.what} is writing here: {holder}", path=self.output,
                                      hint="wait for it to finish, or run the same command again with --wait") from None
                time.sleep(POLL_S)
            except OSError as exc:
                if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                    raise
                log.warning("%s: the file system does not lock files (%s); concurrent runs into this folder "
                            "are not excluded", self.folder, exc.strerror)
                return False

    def _same_file(self, fd: int) -> bool:
        """Whether the locked descriptor is still the file at :attr:`path` (a holder that
        finished removed it: a waiter must not hold a lock on a file nobody else will open)."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return False
        me = os.fstat(fd)
        return (st.st_dev, st.st_ino) == (me.st_dev, me.st_ino)

    def release(self) -> None:
        """Let the lock go, removing the lock file first (while still holding it: a process
        waiting on the old file sees it gone and locks a new one, see :meth:`acquire`)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            if self._same_file(fd):
                os.unlink(self.path)
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    @property
    def held(self) -> bool:
        """Whether this object holds the lock now."""
        return self._fd is not None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.release()
