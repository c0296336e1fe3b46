"""Post-flight flow tests: Prefect isolated from the user's, offline, on its embedded server.

Prefect reads its settings once, at import, and its embedded server is started once per
process (~15-25 s): every test process gets its own temporary PREFECT_HOME here, before
anything imports Prefect, and the flow tests of that process share it. The calibration cache
is one temporary folder per test process too, so that later runs reuse the first run's fits.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

_HOME = Path(tempfile.mkdtemp(prefix="mscal-test-prefect-"))
os.environ.pop("PREFECT_API_URL", None)  # never a real server
os.environ.pop("PREFECT_PROFILE", None)
os.environ["PREFECT_HOME"] = str(_HOME)
os.environ["MSCAL_CACHE_DIR"] = str(_HOME / "cache")

from pipeline.run.runner import configure_prefect

configure_prefect()

FLIGHTS = ("field", "orchard")
REFLECTANCE_VARS = ("reflectance", "ndvi", "vegetation_mask")  # the default products


def pytest_sessionfinish(session, exitstatus) -> None:
    """Remove the temporary PREFECT_HOME. Prefect's exit hook, which stops the embedded server,
    logs to the streams pytest has closed by then: its "prefect" logger is quietened first."""
    import logging

    logging.getLogger("prefect").setLevel(logging.CRITICAL)
    shutil.rmtree(_HOME, ignore_errors=True)


@pytest.fixture(scope="session")
def flow_session(tmp_path_factory) -> Path:
    """The demo's small synthetic session with two 3-frame flights."""
    from pipeline.sim.synth import write_session

    return write_session(tmp_path_factory.mktemp("flows") / "session", seed=0, size="small", flights=FLIGHTS)


@pytest.fixture(scope="session")
def first_run(flow_session, tmp_path_factory) -> Path:
    """``mscal run`` on the session with an empty calibration cache: everything fitted."""
    from pipeline.run.cli import main

    out = tmp_path_factory.mktemp("run1") / "out"
    assert not (Path(os.environ["MSCAL_CACHE_DIR"]) / "calibration").exists()
    assert main(["run", str(flow_session), "-o", str(out)]) == 0
    return out


def output_files(flight_out: Path) -> dict[str, bytes]:
    """Bytes of every TIFF a flight wrote, by path relative to the flight's output folder."""
    return {str(p.relative_to(flight_out)): p.read_bytes()
            for sub in ("photogrammetry", "ndvi") for p in sorted((flight_out / sub).glob("*.tif"))}


def assert_same_flight_outputs(a: Path, b: Path) -> None:
    """Two runs' outputs of one flight are identical: every reflectance.zarr array, every TIFF byte."""
    ra, rb = xr.open_zarr(a / "reflectance.zarr"), xr.open_zarr(b / "reflectance.zarr")
    assert list(ra["frame"].values) == list(rb["frame"].values)
    for v in REFLECTANCE_VARS:
        np.testing.assert_array_equal(ra[v].values, rb[v].values, err_msg=v)
    fa, fb = output_files(a), output_files(b)
    assert len(fa) > 0 and sorted(fa) == sorted(fb)
    assert [k for k in fa if fa[k] != fb[k]] == []


MULTILENS_SESSION_YAML = """camera: micasense-rededge
intrinsics: {fx: 1450, fy: 1450, cx: 640, cy: 480, dist: [0, 0, 0, 0, 0]}
reflector: {reflectance: 0.5, size_m: [0.3, 0.3]}
marker: {dictionary: DICT_4X4_50, id: 0, size_m: 0.08}
"""


@pytest.fixture(scope="session")
def multilens_session(tmp_path_factory) -> tuple[Path, Path]:
    """A session of the multi-lens MicaSense RedEdge: its flight ``field`` holds the
    real sample captures as an SD card writes them (``0000SET/000/``), and a calibration cache
    (returned beside the session; tests point MSCAL_CACHE_DIR at it) already holds every stage's
    store, a store for the MicaSense bands from the factory model
    (:func:`tests.micasense_data.factory_store`): the run fits nothing (multi-lens cameras have
    no field fit here), it applies."""
    from pipeline.run.runner import plan_calibration
    from tests.micasense_data import factory_store, require_data

    data = require_data()
    root = tmp_path_factory.mktemp("multilens")
    session = root / "session"
    for d in ("response", "vignetting", "reflector"):
        (session / d).mkdir(parents=True)
        (session / d / "frames.csv").write_text("file,exposure_ms\n")
    flight = session / "flights" / "field" / "0000SET" / "000"
    flight.mkdir(parents=True)
    for p in sorted(data.glob("IMG_*.tif")):
        shutil.copy(p, flight / p.name)
    (session / "session.yaml").write_text(MULTILENS_SESSION_YAML)
    cache = root / "cache"
    store = factory_store(root / "store.zarr")
    for stage in plan_calibration(session, cache).stages:
        shutil.copytree(store, stage.store)
    return session, cache
