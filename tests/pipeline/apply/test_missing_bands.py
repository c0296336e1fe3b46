"""Captures that lack a band file (RedEdge-P captures built from the real RedEdge files):
without the panchromatic file (kept out of reflectance anyway) the camera is still recognised
from Make/Model and every capture processed; without a reflectance band the capture is
quarantined with that band named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import xarray as xr

from pipeline.apply.factory import FactoryOptions, apply_factory
from pipeline.ingest.identify import identify_camera
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import require_data


def test_rededge_p_without_its_panchromatic_files_is_processed(tmp_path: Path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "p")
    for p in folder.glob("IMG_*_6.tif"):
        p.unlink()
    ident = identify_camera(folder)
    assert ident.camera.name == "micasense-rededge-p"
    assert ident.probe["bands_per_capture"] == 5
    result = apply_factory(folder, tmp_path / "out", FactoryOptions(reference="dls"))
    run = result.run
    assert run["camera"] == "micasense-rededge-p"
    assert run["frames_out"] == 2 and run["frames"] == ["IMG_0000", "IMG_0001"]
    assert run["quarantined"] == [] and run_value(run, "skipped_bands") == []
    ds = xr.open_zarr(tmp_path / "out" / "reflectance.zarr")
    assert list(ds["band_name"].values) == ["Blue", "Green", "Red", "NIR", "Red edge"]


def test_a_capture_without_a_reflectance_band_is_quarantined_naming_it(tmp_path: Path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "p")
    (folder / "IMG_0001_3.tif").unlink()
    assert identify_camera(folder).camera.name == "micasense-rededge-p"
    out = tmp_path / "out"
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--reference", "dls"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == ["IMG_0000"] and run["frames_in"] == 2
    (q,) = run["quarantined"]
    assert q["reason"] == "capture IMG_0001: missing band file(s) 3 (Red)"


def test_a_card_without_a_reflectance_band_names_the_band(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Every capture lost its Red file: the camera is still known from its Model, and the
    refusal names the band, not an unknown camera."""
    require_data()
    folder = cf.rededge_p(tmp_path / "p")
    for p in folder.glob("IMG_*_3.tif"):
        p.unlink()
    assert identify_camera(folder).camera.name == "micasense-rededge-p"
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err
    assert "missing band file(s) 3 (Red)" in err and "no catalog camera matches" not in err
