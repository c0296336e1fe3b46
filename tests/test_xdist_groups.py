"""``make test`` runs ``pytest -n 2 --dist loadgroup``: tests marked with one ``xdist_group``
must run on one worker, or their shared session fixtures (a full ``mscal run``, a dask cluster)
are built once per worker. pytest 9.2 broke this silently (https://github.com/pytest-dev/pytest-xdist/issues/1386); this test
runs a tiny suite the way the Makefile does and checks where each test ran."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # two pytest worker processes start (~5 s)

_SUITE = '''
import os
import pytest

pytestmark = pytest.mark.xdist_group("shared")


def _record(name):
    with open(os.environ["WHERE"], "a") as f:
        f.write(f"{name} {os.environ['PYTEST_XDIST_WORKER']}\\n")


def test_a(): _record("a")
def test_b(): _record("b")
def test_c(): _record("c")
'''

_OTHER = '''
import os


def test_d():
    with open(os.environ["WHERE"], "a") as f:
        f.write(f"d {os.environ['PYTEST_XDIST_WORKER']}\\n")


def test_e():
    pass
'''


def test_loadgroup_keeps_one_group_on_one_worker(tmp_path: Path) -> None:
    (tmp_path / "test_grouped.py").write_text(_SUITE)
    (tmp_path / "test_other.py").write_text(_OTHER)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")  # not this repository's configuration
    where = tmp_path / "where.txt"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-q",
                           "-p", "no:cacheprovider", str(tmp_path)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "WHERE": str(where)})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    ran = dict(line.split() for line in where.read_text().splitlines())
    assert sorted(ran) == ["a", "b", "c", "d"]
    grouped = {ran[k] for k in "abc"}
    assert len(grouped) == 1, f"the xdist_group tests ran on {sorted(grouped)}: --dist loadgroup is not grouping"
