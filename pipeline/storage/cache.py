"""Where mscal keeps what later runs reuse: the cache folder.

``mscal run`` keeps its content-addressed calibration stores in ``<cache>/calibration`` and
every fitted field calibration is recorded in the calibration library ``<cache>/library``
(:mod:`pipeline.calibrate.library`). The folder is found here, below every layer that uses
it (``pipeline.run.runner.default_cache_dir`` is this function).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["default_cache_dir"]


def default_cache_dir() -> Path:
    """``$MSCAL_CACHE_DIR``, else ``$XDG_CACHE_HOME/mscal``, else ``~/.cache/mscal``."""
    if os.environ.get("MSCAL_CACHE_DIR"):
        return Path(os.environ["MSCAL_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "mscal"
