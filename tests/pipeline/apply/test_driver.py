"""The one apply driver (:func:`pipeline.apply.driver.drive`): its steps in order for any
source, the up-to-date short cut, and one run.json schema for every camera."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xarray as xr

from pipeline.apply.driver import Done, drive
from pipeline.apply.execution import Execution
from pipeline.apply.executor import Outcome
from pipeline.apply.flight import apply_flight
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.products import Products
from pipeline.storage.atomic import temporary_folder_name

#: run.json keys every apply writes, whatever the camera (docs/products.md, "run.json").
COMMON = {"flight", "camera", "calibration", "calibration_sha256", "frames_in", "frames_out", "frames",
          "frames_sha256", "quarantined", "metadata_problems", "saturated_pixels", "outputs", "products",
          "export_bands", "versions", "scheduler", "execution", "timings_s", "fingerprint", "outputs_manifest"}


class FakeSource:
    """A source whose pass writes one tiny store; it notes the driver's calls."""

    def __init__(self, folder: Path, previous: dict[str, Any] | None = None) -> None:
        self.folder, self.previous = folder, previous
        self.camera = load_camera("generic-rgb8")
        self.products, self.execution, self.calib = Products(), Execution(scheduler="threads", workers=1), None
        self.calls: list[str] = []

    def up_to_date(self, out: Path) -> dict[str, Any] | None:
        self.calls.append("up_to_date")
        return self.previous

    def prepare(self, out: Path) -> tuple[int, Path | None]:
        self.calls.append("prepare")
        assert not (out / "run.json").exists()  # removed before anything is rewritten
        return 2, None

    def run_pass(self, out: Path, runner: Any) -> Done:
        self.calls.append("run_pass")
        tmp = temporary_folder_name(out / "reflectance.zarr")
        xr.Dataset({"reflectance": ("frame", np.array([0.25, 0.5], dtype=np.float32))}).to_zarr(tmp, zarr_format=3, consolidated=False)
        outcomes = [Outcome("a", "1" * 64, 3), Outcome("b", "2" * 64, 4)]
        return Done(outcomes=outcomes, stores=((tmp, "reflectance.zarr"),),
                    quarantined=[{"file": "c.tif", "reason": "truncated"}], calibration="calib.zarr",
                    calibration_sha256="f" * 64, frames_sha256={"a": "1" * 64, "b": "2" * 64},
                    fingerprint={"frames_sha256": "0" * 64}, outputs={"reflectance": "reflectance.zarr"},
                    products=self.products.record([]), export=(0, 1, 2),
                    parts={"fake": {"note": 1}, "illumination": {"varies_in_time": False}, "skipped": [],
                           "reference": {"route": "dls"}})


def test_the_driver_runs_a_source_and_writes_its_record_last(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text("{}")  # an earlier run's: removed before the pass
    source = FakeSource(tmp_path)
    res = drive(source, out, 0.0)
    assert source.calls == ["up_to_date", "prepare", "run_pass"]
    assert not res.up_to_date and res.quarantined == [{"file": "c.tif", "reason": "truncated"}]
    run = json.loads((out / "run.json").read_text())
    assert COMMON <= set(run) and run["fake"] == {"note": 1}
    # the source's keys: shared ones at the top, a capture folder's and the factory chain's under theirs
    assert run["illumination"] == {"varies_in_time": False}
    assert run["captures"] == {"skipped": []} and run["factory"] == {"reference": {"route": "dls"}}
    assert not {"skipped", "reference"} & set(run)
    assert (run["frames_in"], run["frames_out"], run["frames"]) == (3, 2, ["a", "b"])
    assert run["saturated_pixels"] == {"total": 7, "per_frame": {"a": 3, "b": 4}}
    assert run["export_bands"] == list(load_camera("generic-rgb8").band_names[:3])
    assert run["scheduler"] == "threads" and run["timings_s"]["pass"] >= 0.0
    np.testing.assert_allclose(xr.open_zarr(out / "reflectance.zarr")["reflectance"].values, [0.25, 0.5])
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []  # the store renamed into place


def test_an_up_to_date_source_is_neither_prepared_nor_run(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text('{"kept": true}')
    previous = {"quarantined": [{"file": "x.tif", "reason": "empty"}]}
    source = FakeSource(tmp_path, previous)
    res = drive(source, out, 0.0)
    assert source.calls == ["up_to_date"]
    assert res.up_to_date and res.run is previous and res.quarantined == previous["quarantined"]
    assert (out / "run.json").read_text() == '{"kept": true}'


@pytest.mark.slow
def test_a_snapshot_flight_is_up_to_date_by_content(small, tmp_path) -> None:
    """The rule of every camera (:func:`pipeline.apply.record.up_to_date`) on a snapshot
    flight: a copy of the flight with new modification times is up to date; the record has the
    common keys and the snapshot's own."""
    session, calib = small
    flight = tmp_path / "flight"
    shutil.copytree(session / "flights" / "field", flight)
    out = tmp_path / "out"
    first = apply_flight(flight, calib, out)
    assert not first.up_to_date
    run = json.loads((out / "run.json").read_text())
    assert COMMON <= set(run) and {"illumination", "snapshot"} <= set(run)
    assert run["fingerprint"]["frames_sha256"] == first.run["fingerprint"]["frames_sha256"]
    for p in flight.rglob("*"):
        st = p.stat()
        os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    again = apply_flight(flight, calib, out)
    assert again.up_to_date and again.run["fingerprint"] == run["fingerprint"]
    assert json.loads((out / "run.json").read_text()) == run
