"""``mscal run``: the post-flight flow end to end on the small synthetic session."""

from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.apply.options import calibration_hash
from pipeline.products.report import report_dict
from pipeline.run.cli import main
from pipeline.sim.evaluate import evaluate_calibration
from pipeline.storage.store import open_calibration

from .conftest import FLIGHTS, assert_same_flight_outputs

STAGES = ["response", "vignetting", "illumination"]
pytestmark = pytest.mark.xdist_group("flows")  # one worker: one Prefect server, one cache


def _run_json(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def test_first_run_fits_everything_and_writes_every_output(flow_session: Path, first_run: Path) -> None:
    run = _run_json(first_run)
    assert run["format"] == "mscal-run/1"
    assert run["calibration_cached"] is False
    assert run["fitted"] == STAGES
    assert all(run["calibration_stages"][s]["seconds"] > 0 for s in STAGES)
    assert sorted(run["flights"]) == sorted(FLIGHTS)
    assert run["kind"] == "field"
    # recorded in the calibration library (the snapshot frames name no serial: "unknown")
    recorded = Path(run["calibration_library"]["store"])
    assert recorded.parent.name == "unknown" and (recorded / "zarr.json").is_file()
    ds = open_calibration(first_run / "calibration.zarr", need="apply")
    errors = evaluate_calibration(flow_session, ds)
    assert errors["response_max_error"] < 0.02
    assert errors["spectral_factor_max_error"] < 0.02
    for name in FLIGHTS:
        f = run["flights"][name]
        assert (f["frames_in"], f["frames_out"], f["quarantined"], f["up_to_date"]) == (3, 3, [], False)
        flight = json.loads((first_run / "flights" / name / "run.json").read_text())
        assert flight["calibration_sha256"] == f["calibration_sha256"] == calibration_hash(ds)
        refl = xr.open_zarr(first_run / "flights" / name / "reflectance.zarr")["reflectance"]
        assert refl.shape == (3, 25, 217, 409)
        quality = xr.open_zarr(first_run / "flights" / name / "reflectance.zarr")["quality"].values
        assert np.array_equal(np.isfinite(refl.values), quality == 0) and (quality == 0).mean() > 0.75
        assert len(list((first_run / "flights" / name / "photogrammetry").glob("*.tif"))) == 3 * 8
    assert {"prefect", "dask", "distributed", "mscal_code"} <= set(run["versions"])
    # the QA report of the whole run: calibration plus one section per flight, images inline
    assert run["report"] == "report.html" and (first_run / "calibration.json").is_file()
    page = (first_run / "report.html").read_text()
    assert all(f"flights/{name}" in page or name in page for name in FLIGHTS)
    assert page.count('<img src="data:image/png;base64,') >= 6 + 3 * len(FLIGHTS)
    assert run["timings_s"]["total"] >= sum(run["calibration_stages"][s]["seconds"] for s in STAGES)
    # the flow catalogued its flights: OUT/catalog.json, one item per flight, valid STAC
    from pipeline.products.stac import validate_catalog

    items = sorted(p.stem for p in (first_run / "stac").glob("*/items/*.json"))
    assert items == sorted(FLIGHTS)
    assert validate_catalog(first_run) == 1 + 1 + len(FLIGHTS)
    item = json.loads(next((first_run / "stac").glob("*/items/field.json")).read_text())
    assert item["properties"]["mscal:calibration_sha256"] == run["flights"]["field"]["calibration_sha256"]
    assert item["properties"]["mscal:calibration_cached"] is False and item["geometry"]["type"] in ("Polygon", "LineString")
    # each flight names the calibration it applied by its place among the outputs, not the cache
    flight_run = json.loads((first_run / "flights" / "field" / "run.json").read_text())
    assert flight_run["calibration"] == str((first_run / "calibration.zarr").resolve())
    item_file = next((first_run / "stac").glob("*/items/field.json"))
    assert (item_file.parent / item["properties"]["mscal:calibration"]).resolve() == (
        first_run / "calibration.zarr").resolve()  # the STAC item points at it too (relative)


def test_second_run_refits_nothing_and_says_so(flow_session: Path, first_run: Path, capsys) -> None:
    from prefect.artifacts import Artifact

    before = {p: p.stat().st_mtime_ns for p in _cached_stores()}
    assert [p.name.split("-")[0] for p in before] == ["illumination", "response", "vignetting"]
    assert main(["run", str(flow_session), "-o", str(first_run)]) == 0
    assert "calibration reused from the cache" in capsys.readouterr().out
    run = _run_json(first_run)
    assert run["calibration_cached"] is True
    assert run["fitted"] == []
    assert all(v["cached"] and v["seconds"] == 0.0 for v in run["calibration_stages"].values())
    assert {p: p.stat().st_mtime_ns for p in _cached_stores()} == before  # no store rewritten
    assert all(run["flights"][n]["up_to_date"] for n in FLIGHTS)
    summary = Artifact.get("mscal-post-flight")
    assert summary is not None and "reused from the cache" in summary.data
    assert "| field | 3 / 3 | 0 |" in summary.data


def _cached_stores() -> list[Path]:
    return sorted((Path(os.environ["MSCAL_CACHE_DIR"]) / "calibration").glob("*.zarr"))


def test_changed_reflector_refits_only_illumination(flow_session: Path, first_run: Path, tmp_path: Path) -> None:
    session = tmp_path / "session"
    shutil.copytree(flow_session, session)
    table = session / "reflector" / "frames.csv"
    with table.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2
    (session / "reflector" / rows[1]["file"]).unlink()
    with table.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerow(rows[0])
    out = tmp_path / "out"
    assert main(["run", str(session), "-o", str(out)]) == 0
    run = _run_json(out)
    assert run["calibration_cached"] is False
    assert run["fitted"] == ["illumination"]
    assert [run["calibration_stages"][s]["cached"] for s in STAGES] == [True, True, False]
    old = open_calibration(first_run / "calibration.zarr")
    new = open_calibration(out / "calibration.zarr")
    for v in ("inverse_response", "vignetting"):
        np.testing.assert_array_equal(new[v].values, old[v].values)
    s_old, s_new = old["spectral_factor"].values, new["spectral_factor"].values
    # Refitted from one reflector image instead of two: S is known up to the brightness
    # normalisation of the images used, so it moves by one common factor, its shape stays.
    ratio = s_new / s_old
    assert abs(ratio.mean() - 1) > 1e-3
    assert ratio.std() / ratio.mean() < 0.01
    assert new.attrs["illumination"]["residuals"]["images_used"] == 1
    assert all(not run["flights"][n]["up_to_date"] for n in FLIGHTS)


def test_short_flights_compute_in_process(first_run: Path) -> None:
    """Short flights run in-process by default (no cluster start-up for three frames)."""
    run = _run_json(first_run)
    assert {run["flights"][n]["computed_on"] for n in FLIGHTS} <= {"in-process", "nothing (up to date)"}
    assert run["dask_address"] is None


# ~20 s, a third whole run: make test-long. make test keeps the check through the S3 run, a
# rerun elsewhere with the cached calibration compared byte for byte with the first run.
@pytest.mark.long
def test_identical_outputs_of_a_rerun_into_a_new_folder(flow_session: Path, first_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "again"
    assert main(["run", str(flow_session), "-o", str(out)]) == 0
    assert _run_json(out)["calibration_cached"] is True
    for name in FLIGHTS:
        assert_same_flight_outputs(first_run / "flights" / name, out / "flights" / name)


def test_bad_input_is_one_line_and_exit_2_before_prefect_starts(tmp_path: Path, capsys) -> None:
    assert main(["run", str(tmp_path / "nowhere"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"mscal: error: {tmp_path / 'nowhere'}: session folder not found (pass a field session (session.yaml, response/, vignetting/, "
                   "reflector/) or a flight folder as it comes off the camera's card)"]
    assert not (tmp_path / "out").exists()


def test_bad_dask_address_and_normalise_are_rejected(flow_session: Path, tmp_path: Path, capsys) -> None:
    assert main(["run", str(flow_session), "-o", str(tmp_path / "o"), "--dask-address", "localhost"]) == 2
    assert "--dask-address 'localhost' is not a scheduler address" in capsys.readouterr().err
    assert main(["run", str(flow_session), "-o", str(tmp_path / "o"), "--normalise", "panel"]) == 2
    assert "--normalise 'panel'" in capsys.readouterr().err


@pytest.mark.long  # ~38 s: a second whole demo run; make test keeps the flow through first_run
def test_demo_runs_the_whole_flow_and_says_where_the_outputs_are(first_run: Path, tmp_path: Path, capsys) -> None:
    """The demo's session is the flows' test session (seed 0, small, two flights): its
    calibration comes from the cache, so this checks the demo's wiring, not the fits again."""
    assert main(["demo", "-o", str(tmp_path / "demo"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)  # one JSON document, nothing else
    assert doc["command"] == "demo" and doc["outputs"]["outputs"] == str(tmp_path / "demo")
    assert doc["outputs"]["run record"] == str(tmp_path / "demo" / "run.json")
    assert doc["demo"]["errors_vs_truth"]["response_max_error"] < 0.02
    # the report's warnings on the demo calibration (7 of 8 views used: vignetting coverage)
    assert [w["code"] for w in doc["warnings"]] == [
        w["code"] for s in report_dict(tmp_path / "demo" / "calibration.zarr",
                                       [tmp_path / "demo" / "flights" / n for n in FLIGHTS])["sections"]
        for w in s["warnings"]]
    summary = json.loads((tmp_path / "demo" / "evaluation.json").read_text())
    assert summary["calibration_cached"] is True
    assert sorted(summary["flights"]) == sorted(FLIGHTS)
    assert summary["errors_vs_truth"]["response_max_error"] < 0.02
    for name in FLIGHTS:
        assert_same_flight_outputs(first_run / "flights" / name, tmp_path / "demo" / "flights" / name)


def test_io_tasks_retry_io_errors_but_not_bad_input() -> None:
    """The retry policy of the flow's I/O tasks, on Prefect's engine (no delay here)."""
    from prefect import flow, task

    from flows.post_flight import IO
    from mscal_core.errors import InputError

    calls: list[str] = []

    @task(**{**IO, "retry_delay_seconds": 0})
    def flaky(kind: str) -> int:
        calls.append(kind)
        if calls.count(kind) == 1:
            raise ConnectionResetError("connection reset") if kind == "io" else InputError("bad session")
        return calls.count(kind)

    @flow
    def io() -> int:
        return flaky("io")

    @flow
    def bad() -> int:
        return flaky("bad")

    assert io() == 2  # failed once, retried, succeeded
    with pytest.raises(InputError, match="bad session"):
        bad()
    assert calls.count("bad") == 1  # not retried


def test_run_on_a_multilens_session_applies_its_captures(multilens_session, tmp_path, monkeypatch) -> None:
    """``mscal run`` on a session naming a one-file-per-band camera: the flight's
    captures go through the one executor with the session's calibration, same layout as
    every flight, and the run's record and report cover it."""
    session, cache = multilens_session
    monkeypatch.setenv("MSCAL_CACHE_DIR", str(cache))
    out = tmp_path / "out"
    assert main(["run", str(session), "-o", str(out)]) == 0
    run = _run_json(out)
    assert run["calibration_cached"] is True and run["fitted"] == []
    # its frame folders are empty (the stores come from the cache): no serial to record it under
    assert "no captures of camera micasense-rededge found" in run["calibration_library"]["not_recorded"]
    f = run["flights"]["field"]
    assert (f["frames_in"], f["frames_out"], f["quarantined"], f["up_to_date"]) == (2, 2, [], False)
    flight = out / "flights" / "field"
    ds = xr.open_zarr(flight / "reflectance.zarr")
    assert list(ds["frame"].values) == ["IMG_0000", "IMG_0001"]
    assert ds["reflectance"].shape == (2, 5, 960, 1280)
    assert f["calibration_sha256"] == calibration_hash(open_calibration(out / "calibration.zarr", need="apply"))
    assert len(list((flight / "photogrammetry").glob("*.tif"))) == 2 * 5
    assert sorted(p.name for p in (flight / "ndvi").glob("*.tif")) == ["IMG_0000.tif", "IMG_0001.tif"]
    # the same as mscal apply of the flight with the session's store
    alone = tmp_path / "alone"
    assert main(["apply", str(session / "flights" / "field"), "--calibration", str(out / "calibration.zarr"),
                 "-o", str(alone)]) == 0
    assert_same_flight_outputs(flight, alone)
    assert "<h2>Flight: field</h2>" in (out / "report.html").read_text()
    assert main(["run", str(session), "-o", str(out)]) == 0
    assert _run_json(out)["flights"]["field"]["up_to_date"] is True


def test_one_bad_flight_does_not_cost_the_others(flow_session: Path, first_run: Path, tmp_path: Path,
                                                 capsys) -> None:
    """An empty flight folder beside good ones: the good flights get their outputs, the bad
    one is named in run.json and on stderr, and the exit status is 3."""
    session = tmp_path / "session"
    shutil.copytree(flow_session, session)
    (session / "flights" / "empty").mkdir()
    out = tmp_path / "out"
    assert main(["run", str(session), "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "flight empty was not processed:" in err
    run = _run_json(out)
    assert run["status"] == "partial" and run["calibration_cached"] is True
    assert run["flights"]["empty"]["status"] == "failed" and run["flights"]["empty"]["outputs"] is None
    assert "empty" in run["flights"]["empty"]["reason"] and "\n" not in run["flights"]["empty"]["reason"]
    for name in FLIGHTS:
        assert run["flights"][name]["status"] == "done"
        assert_same_flight_outputs(first_run / "flights" / name, out / "flights" / name)


def test_products_of_a_run_follow_session_yaml_and_the_command_line(flow_session: Path, first_run: Path,
                                                                    tmp_path: Path) -> None:
    """session.yaml's products reach every flight of ``mscal run`` without re-fitting the
    calibration (products are no input of a fit); --tiffs on the command line wins over
    session.yaml's ``tiffs: false``; the same choice again is up to date, another redoes the
    flights. The default set's arrays are those of the first run."""
    session = tmp_path / "session"
    shutil.copytree(flow_session, session)
    with (session / "session.yaml").open("a") as fh:
        fh.write("products: {indices: [ndre], tiffs: false}\n")
    out = tmp_path / "out"
    assert main(["-q", "run", str(session), "-o", str(out)]) == 0
    run = _run_json(out)
    assert run["calibration_cached"] is True and run["fitted"] == []
    for name in FLIGHTS:
        flight = out / "flights" / name
        assert run["flights"][name]["products"] == {"radiance": False, "indices": ["ndvi", "ndre"], "tiffs": False, "keep_flagged": False, "shoulder_bound": 0.03}
        assert list(flight.rglob("*.tif")) == []
        ds, first = xr.open_zarr(flight / "reflectance.zarr"), xr.open_zarr(first_run / "flights" / name / "reflectance.zarr")
        assert set(ds.data_vars) == {"reflectance", "quality", "ndvi", "ndre", "vegetation_mask"}
        for v in ("reflectance", "ndvi", "vegetation_mask"):
            np.testing.assert_array_equal(ds[v].values, first[v].values, err_msg=v)
    assert main(["-q", "run", str(session), "-o", str(out), "--tiffs"]) == 0
    run = _run_json(out)
    assert not any(run["flights"][n]["up_to_date"] for n in FLIGHTS)
    assert all(run["flights"][n]["products"]["tiffs"] for n in FLIGHTS)
    assert len(list((out / "flights" / "field" / "photogrammetry").glob("*.tif"))) == 3 * 8
    assert main(["-q", "run", str(session), "-o", str(out), "--tiffs"]) == 0
    assert all(_run_json(out)["flights"][n]["up_to_date"] for n in FLIGHTS)
