"""Where mscal keeps what later runs reuse (the cache folder), and the digest of the code that
made it (:func:`code_digest`).

``mscal run`` keeps its content-addressed calibration stores in ``<cache>/calibration`` and
every fitted field calibration is recorded in the calibration library ``<cache>/library``
(:mod:`pipeline.calibrate.library`). The folder is found here, below every layer that uses
it (``pipeline.run.runner.default_cache_dir`` is this function).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.resources
import os
from pathlib import Path

__all__ = ["CODE_PACKAGES", "code_digest", "default_cache_dir", "source_digest"]

#: The packages whose sources every result of mscal may depend on: :func:`code_digest`.
CODE_PACKAGES = ("mscal_core", "pipeline")


def default_cache_dir() -> Path:
    """``$MSCAL_CACHE_DIR``, else ``$XDG_CACHE_HOME/mscal``, else ``~/.cache/mscal``."""
    if os.environ.get("MSCAL_CACHE_DIR"):
        return Path(os.environ["MSCAL_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "mscal"


def source_digest(roots: dict[str, Path]) -> str:
    """sha256 over every ``*.py`` and ``*.yaml`` file under each folder of ``roots`` (``{name:
    folder}``), each named by ``name/`` and its path below the folder (POSIX, sorted): the same
    sources give the same digest in any process, at any place on disk; a changed, added,
    removed or renamed source changes it. Other files (a README, ``__pycache__``) do not count."""
    h = hashlib.sha256()
    for name in sorted(roots):
        root = Path(roots[name])
        files = sorted(p for p in root.rglob("*") if p.suffix in (".py", ".yaml") and p.is_file()
                       and "__pycache__" not in p.relative_to(root).parts)
        for p in files:
            rel = f"{name}/{p.relative_to(root).as_posix()}"
            h.update(rel.encode() + b"\0" + hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


@functools.cache
def code_digest() -> str:
    """The digest (:func:`source_digest`) of this process's mscal: every source file of the
    ``mscal_core`` and ``pipeline`` packages, whichever of their modules a stage imports (or
    imports by name at run time, as the calibration's workers do), and the shipped catalogs
    (``catalogs/``). Part of the calibration cache's keys and of apply's run fingerprint: an
    edit of any of them makes a cached result of older code stale. Computed once per process,
    from the files the process found its modules in (a long-running process keeps the code it
    imported)."""
    roots = {name: Path(str(importlib.resources.files(name))) for name in (*CODE_PACKAGES, "catalogs")}
    return source_digest(roots)
