"""Process settings of mscal's workers and main process (pipeline.storage.process)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = (
    "from numpy._core.multiarray import _set_madvise_hugepage as hp\n"
    "from pipeline.storage.process import reuse_freed_memory\n"
    "before = hp(True); hp(before)\n"
    "reuse_freed_memory()\n"
    "print(before, hp(True))\n"
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="huge pages are a Linux setting")
@pytest.mark.parametrize(("env", "want"), [(None, "True False"), ("1", "True True"), ("0", "False False")])
def test_new_arrays_use_small_pages_unless_numpy_is_told_otherwise(env: str | None, want: str) -> None:
    """A worker's memory settings turn NumPy's huge-page advice off (slow first touches on a VM
    whose memory goes back to the host), but NUMPY_MADVISE_HUGEPAGE, when set, decides."""
    environ = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if env is not None:
        environ["NUMPY_MADVISE_HUGEPAGE"] = env
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=environ, timeout=120,
                         check=True)
    assert out.stdout.strip() == want
