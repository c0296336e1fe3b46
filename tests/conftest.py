"""Hypothesis profiles for the property-based (fuzz) tests.

``mscal-short`` (the default, in ``make test``): seeded (``derandomize``: the same examples on
every run and machine), few examples, no example database. ``mscal-long``: many examples, for
the tests marked ``long`` (``make test-long``). ``HYPOTHESIS_PROFILE=mscal-long`` runs the
short variants with the long profile too. No deadline in either: nothing depends on the
machine's speed or load.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

import pytest
from hypothesis import HealthCheck, settings

_COMMON = dict(
    deadline=None,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
settings.register_profile("mscal-short", derandomize=True, max_examples=60, **_COMMON)
settings.register_profile("mscal-long", derandomize=False, max_examples=2000, **_COMMON)
# pytest -n 2 already fills the cores: calibrations in tests fit their bands in-process instead
# of spawning band workers each (tests that check the workers set the variable themselves).
os.environ.setdefault("MSCAL_CALIBRATE_WORKERS", "1")
# `mscal calibrate` records every store it writes into the calibration library of the cache
# folder: the tests' stores go to one temporary cache per test process, not the user's.
_CACHE = tempfile.mkdtemp(prefix="mscal-test-cache-")
os.environ["MSCAL_CACHE_DIR"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, True)
SHORT = os.environ.get("HYPOTHESIS_PROFILE", "mscal-short")
settings.load_profile(SHORT)


@pytest.fixture(params=["short", pytest.param("long", marks=pytest.mark.long)])
def fuzz_settings(request) -> settings:
    """The Hypothesis settings of a fuzz test: the short profile (or HYPOTHESIS_PROFILE) in
    ``make test``, the long one for its ``long``-marked twin."""
    return settings.get_profile(SHORT if request.param == "short" else "mscal-long")
