"""Output paths checked before any work: writable, of the right kind, room for the outputs.

Every command that writes calls :func:`check_output` on its ``-o`` before it reads a frame, so
that a wrong path costs a second, not a minute of fitting, and so that mscal never replaces a
file or folder the user made. ``os.access`` is not enough (it says yes to root under /proc):
the check creates a file where the output will go and removes it.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from mscal_core.errors import InputError

from pipeline.storage.lock import LOCK_NAME, FolderLock

#: Errors of a probe write that mean "you cannot write there", with what to do.
_WHY = {
    errno.EACCES: "no permission to write there",
    errno.EPERM: "no permission to write there",
    errno.EROFS: "the file system is read-only",
    errno.ENOENT: "the file system does not take new files there",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is used up",
}


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def _probe(folder: Path, target: Path) -> None:
    """Create and remove a file in ``folder``; InputError naming ``target`` if that fails."""
    try:
        fd, name = tempfile.mkstemp(prefix=".mscal-probe-", dir=folder)
    except OSError as exc:
        why = _WHY.get(exc.errno or 0, exc.strerror or str(exc))
        raise InputError(f"cannot write here: {why} (tried {folder})", path=target,
                         hint="give -o a folder on a writable disk") from None
    os.close(fd)
    os.unlink(name)


def check_output(path: str | Path, *, kind: str = "folder", owned: Callable[[Path], bool] | None = None,
                 need_bytes: int = 0, what: str = "output") -> Path:
    """Check ``path`` before any work; return it as a Path.

    ``kind``: ``"folder"`` (an output folder mscal creates or adds to: an existing folder is
    fine), ``"store"`` (a store mscal replaces as a whole: an existing folder is replaced
    only if ``owned(path)`` says mscal wrote it) or ``"file"`` (one file, e.g. report.html:
    an existing file is replaced, a folder is refused). Refused, with :class:`InputError` naming
    the path: an existing file where a folder goes; an existing folder mscal did not write
    (``store``); a path under a file; a place where no file can be created (read-only, no
    permission, /proc); less free space than ``need_bytes``. Nothing is created except the
    missing parent folders' probe, which is removed again.
    """
    p = Path(path)
    if p.is_symlink() and not p.exists():
        raise InputError(f"the {what} path is a broken symbolic link", path=p, hint="remove it or give another -o")
    if kind == "file":
        if p.is_dir():
            raise InputError(f"the {what} path is an existing folder; mscal writes a file here", path=p,
                             hint="give -o a file name")
    elif p.exists() and not p.is_dir():
        raise InputError(f"the {what} path is an existing file; mscal writes a folder here and never replaces a "
                         "file it did not write", path=p, hint="give -o a new or empty folder, or remove the file")
    if kind == "store" and p.is_dir() and any(p.iterdir()) and not (owned and owned(p)):
        raise InputError(f"the {what} path is an existing folder that mscal did not write; it would be replaced",
                         path=p, hint="give -o a new name, or remove the folder yourself")
    base = _nearest_existing(p.parent if not p.exists() or kind == "file" else p)
    if not base.is_dir():
        raise InputError(f"the {what} path lies under {base}, which is a file, not a folder", path=p,
                         hint="give -o a path in a folder")
    _probe(base, p)
    if need_bytes > 0:
        free = shutil.disk_usage(base).free
        if free < need_bytes:
            raise InputError(f"not enough free space for the {what}: about {need_bytes / 2**20:.0f} MiB needed, "
                             f"{free / 2**20:.0f} MiB free on {base}", path=p,
                             hint="free space or give -o a folder on another disk")
    return p


def is_mscal_store(path: Path) -> bool:
    """Whether ``path`` is a Zarr store mscal wrote (its root ``zarr.json`` carries a
    ``format`` attribute of mscal's): only such a folder may be replaced by a new store."""
    try:
        meta = json.loads((Path(path) / "zarr.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return str((meta.get("attributes") or {}).get("format", "")).startswith("mscal-")


@contextlib.contextmanager
def guarded_output(path: str | Path, *, kind: str = "folder", wait: bool | float = False,
                   what: str = "output", need_bytes: int = 0) -> Iterator[Path]:
    """Check ``path`` (:func:`check_output`) and hold the lock of the output for the block.

    A folder output is locked by a file inside it; a store or a file output by a lock file
    beside it (``.NAME.lock``: the store itself is replaced whole). A second process refuses
    at once (:class:`~mscal_core.errors.LockedError`, naming the holder) or, with ``wait``,
    waits for the first to finish.
    """
    p = check_output(path, kind=kind, owned=is_mscal_store if kind == "store" else None, need_bytes=need_bytes,
                     what=what)
    folder, name = (p, LOCK_NAME) if kind == "folder" else (p.parent, f".{p.name}.lock")
    created = [d for d in (folder, *folder.parents) if not d.exists()]
    try:
        with FolderLock(folder, name=name, wait=wait, what="another mscal process"):
            yield p
    finally:
        _remove_if_unused(folder / name, created)


def _remove_if_unused(lock: Path, created: list[Path]) -> None:
    """A command that failed before writing anything leaves no trace: the folders the lock
    made are removed again when nothing was put in them (the lock removed its own file)."""
    for d in created:  # innermost first
        try:
            d.rmdir()
        except OSError:  # not empty (or gone): it holds outputs
            break
