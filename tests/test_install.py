"""A non-editable install works away from the checkout: the catalogs ship as package data.

The venv is made quickly: no pip of its own and no downloads; a ``.pth`` file puts the
project venv's site-packages (dependencies, pip, setuptools) after the new venv's own, and
mscal itself is installed with ``--no-deps --no-build-isolation`` from a copy of the
sources (an in-tree build would leave ``build/`` in the checkout).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.micasense_data import DATA, require_data

ROOT = Path(__file__).resolve().parents[1]


def _fresh_install(tmp_path: Path) -> Path:
    """A venv holding a non-editable install of this checkout; returns its bin folder."""
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "__pycache__", "*.egg-info", "build", "dist", ".pytest_cache", "tests", "bench"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    Path(purelib, "project-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-index", str(src)], check=True, env=_clean_env(), cwd=tmp_path)
    shutil.rmtree(src)  # nothing may be read from the sources once installed
    return venv / "bin"


def _clean_env() -> dict[str, str]:
    """This process's environment without anything that points Python at the checkout."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MSCAL_CATALOG_PATH", "VIRTUAL_ENV")}


@pytest.mark.slow
def test_installed_mscal_applies_the_factory_model_from_another_folder(tmp_path) -> None:
    require_data()
    bin_dir = _fresh_install(tmp_path)
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = subprocess.run(
        [str(bin_dir / "python"), "-c",
         "import catalogs, pipeline; from pipeline.ingest.catalog import CATALOG_ROOT, list_entries; "
         "print(catalogs.__file__); print(pipeline.__file__); print(CATALOG_ROOT); print(list_entries('cameras'))"],
        check=True, capture_output=True, text=True, cwd=work, env=_clean_env()).stdout.splitlines()
    site = str(tmp_path / "venv")
    assert all(line.startswith(site) for line in where[:3]), where  # not the checkout's copies
    assert "micasense-rededge" in where[3]
    out = tmp_path / "x"
    run = subprocess.run([str(bin_dir / "mscal"), "apply", str(DATA), "--calibration", "factory", "-o", str(out)],
                         capture_output=True, text=True, cwd=work, env=_clean_env())
    assert run.returncode == 0, run.stderr[-3000:]
    record = json.loads((out / "run.json").read_text())
    assert record["frames_out"] == 2 and record["quarantined"] == []
    # 2 captures x 5 bands: the survey capture's TIFFs for photogrammetry, the panel capture's apart
    assert len(list((out / "photogrammetry").glob("*.tif"))) == 5
    assert len(list((out / "panels").glob("*.tif"))) == 5
