"""Opt-in products (docs/products.md): the default set, radiance and further indices on
request, no TIFFs for analytics-only runs; recorded in run.json, part of the re-run check,
and the files of the default set byte-identical with or without the opt-in ones."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.apply.factory import FactoryOptions, apply_factory
from pipeline.ingest.products import Products
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests.micasense_data import require_data

TIFF_DIRS = ("photogrammetry", "panels", "thermal", "ndvi")
DEFAULT_VARS = {"reflectance", "quality", "ndvi", "vegetation_mask"}


def _files(out: Path, top: tuple[str, ...]) -> dict[str, bytes]:
    """Bytes of every file under ``out/<top>`` (metadata zarr.json left out), by relative path."""
    return {str(p.relative_to(out)): p.read_bytes() for t in top for p in sorted((out / t).rglob("*"))
            if p.is_file() and p.name != "zarr.json"}


def _chunks(out: Path, variables=("reflectance", "ndvi", "vegetation_mask")) -> dict[str, bytes]:
    return _files(out, tuple(f"reflectance.zarr/{v}" for v in variables) + ("raw.zarr",))


def _run(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


@pytest.fixture(scope="module")
def micasense(tmp_path_factory) -> dict[str, Path]:
    """The MicaSense sample applied with the factory chain three ways."""
    data = require_data()
    root = tmp_path_factory.mktemp("products")
    outs = {"default": [], "all": ["--products", "radiance", "--indices", "ndre"], "lean": ["--no-tiffs"]}
    for name, extra in outs.items():
        assert main(["-q", "apply", str(data), "--calibration", "factory", "-o", str(root / name), *extra]) == 0
    return {name: root / name for name in outs}


def test_default_run_writes_the_survey_set(micasense) -> None:
    out = micasense["default"]
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert set(ds.data_vars) == DEFAULT_VARS  # no radiance, no ndre
    run = _run(out)
    assert run["products"] == {"radiance": False, "indices": ["ndvi"], "tiffs": True, "keep_flagged": False, "shoulder_bound": 0.03}
    assert run["fingerprint"]["options"]["products"] == run["products"]
    assert sorted(p.name for p in (out / "ndvi").glob("*.tif")) == ["IMG_0001.tif"]  # IMG_0000 is the panel
    assert len(list((out / "photogrammetry").glob("*.tif"))) == 5 and len(list((out / "panels").glob("*.tif"))) == 5
    assert set(run["outputs"]) == {"reflectance", "raw", "photogrammetry", "panels", "ndvi"}
    # the factory chain checks the flags it can without a field store (bands not aligned: no
    # co-registration to fail); run.json counts the array's
    assert run["quality"]["checked"] == ["saturated", "no_value"]
    assert "bound" not in run["quality"] and "fit_bound" not in run["quality"]  # no shoulder checked
    q = ds["quality"].values
    names = [str(b) for b in ds["band_name"].values]
    bits = run["quality"]["flags"]
    want = {names[b]: {f: int(np.count_nonzero(q[:, b] & bit)) for f, bit in bits.items()
                       if np.count_nonzero(q[:, b] & bit)} for b in range(q.shape[1])}
    assert run["quality"]["totals"] == {b: c for b, c in want.items() if c}
    assert np.array_equal(np.isnan(ds["reflectance"].values), q != 0)  # NaN: flagged (saturated or no value)
    # the factor from radiance to reflectance stays in run.json without the radiance cube
    assert run_value(run, "radiance_factor")["route"] == "panel-dls"
    assert set(run["illumination"]["per_frame"]["IMG_0001"]) == {"Blue", "Green", "Red", "NIR", "Red edge"}
    ndvi = ds["ndvi"].isel(frame=1).values
    refl = ds["reflectance"].isel(frame=1).values
    red, nir = refl[2], refl[3]
    np.testing.assert_allclose(ndvi[100, 100], (nir[100, 100] - red[100, 100]) / (nir[100, 100] + red[100, 100]),
                               rtol=1e-6)
    assert 0.0 < float(np.nanmean(ndvi)) < 1.0


def test_opt_in_products_add_files_and_change_none(micasense) -> None:
    """--products radiance --indices ndre: radiance and ndre beside the default set, whose chunk
    files and TIFFs are byte-for-byte the default run's; reflectance is radiance times the
    per-band factor run.json records."""
    a, b = micasense["default"], micasense["all"]
    assert _chunks(a) == _chunks(b) and len(_chunks(a)) > 0
    assert _files(a, TIFF_DIRS) == _files(b, TIFF_DIRS) and len(_files(a, TIFF_DIRS)) == 11
    ds = xr.open_zarr(b / "reflectance.zarr")
    assert set(ds.data_vars) == DEFAULT_VARS | {"radiance", "ndre"}
    run = _run(b)
    assert run["products"] == {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": True, "keep_flagged": False, "shoulder_bound": 0.03}
    k = run["illumination"]["per_frame"]["IMG_0001"]
    refl, rad = ds["reflectance"].isel(frame=1).values, ds["radiance"].isel(frame=1).values
    for b_idx, band in enumerate(ds["band_name"].values):
        assert np.nanmedian(refl[b_idx] / rad[b_idx]) == pytest.approx(k[str(band)], rel=1e-5)
    ndre = ds["ndre"].isel(frame=1).values
    nir, edge = refl[3], refl[4]
    np.testing.assert_allclose(ndre[50, 60], (nir[50, 60] - edge[50, 60]) / (nir[50, 60] + edge[50, 60]), rtol=1e-6)


def test_no_tiffs_writes_the_same_stores_and_no_tiff(micasense) -> None:
    a, lean = micasense["default"], micasense["lean"]
    assert [t for t in TIFF_DIRS if (lean / t).exists()] == []
    assert list(lean.rglob("*.tif")) == []
    assert _chunks(a) == _chunks(lean)
    run = _run(lean)
    assert run["products"] == {"radiance": False, "indices": ["ndvi"], "tiffs": False, "keep_flagged": False, "shoulder_bound": 0.03}
    assert set(run["outputs"]) == {"reflectance", "raw"}


def test_a_changed_choice_redoes_the_flight_and_leaves_nothing_stale(micasense, tmp_path) -> None:
    """Same choice: up to date. Another: redone, and what the new choice does not make (the
    TIFFs, the radiance variable) is gone from OUT."""
    data = require_data()
    out = tmp_path / "out"
    shutil.copytree(micasense["all"], out)
    radiance = FactoryOptions(products=Products(radiance=True, indices=("ndvi", "ndre")))
    res = apply_factory(data, out, radiance)
    assert res.up_to_date and res.run["products"]["radiance"] is True
    res = apply_factory(data, out, FactoryOptions(products=Products(tiffs=False)))
    assert not res.up_to_date
    assert set(xr.open_zarr(out / "reflectance.zarr").data_vars) == DEFAULT_VARS  # radiance and ndre gone
    assert [t for t in TIFF_DIRS if (out / t).exists()] == [] and _run(out)["products"]["tiffs"] is False
    assert _chunks(out) == _chunks(micasense["default"])
    assert apply_factory(data, out, FactoryOptions(products=Products(tiffs=False))).up_to_date
    res = apply_factory(data, out, FactoryOptions())
    assert not res.up_to_date and _files(out, TIFF_DIRS) == _files(micasense["default"], TIFF_DIRS)


def test_products_a_camera_cannot_make_are_refused(tmp_path, capsys) -> None:
    """An index the camera's bands cannot make, radiance without factory radiometry: one line
    saying what is wrong and how to fix it, nothing written."""
    nrgb = require_data().parent / "sentera-d4k" / "nRGB"
    if not nrgb.is_dir():
        pytest.skip("Sentera sample not found")
    assert main(["apply", str(nrgb), "--calibration", "factory", "-o", str(tmp_path / "o"), "--indices", "ndre"]) == 2
    err = capsys.readouterr().err.strip()
    assert ("index ndre needs band role(s) nir, rededge that camera sentera-d4k-nrgb does not have (its index roles: "
            "blue, green, red)") in err and "leave ndre out of --indices" in err and "\n" not in err
    assert not (tmp_path / "o" / "run.json").exists()


def test_snapshot_products(small, tmp_path, capsys) -> None:
    """The snapshot (field calibration, Eq. 15) path: --indices ndre adds ndre and changes no
    file of the default set; --no-tiffs writes the same stores; radiance is refused (Eq. 15
    has none)."""
    session, calib = small
    flight = session / "flights" / "field"
    outs = {"default": [], "ndre": ["--indices", "ndre"], "lean": ["--no-tiffs"]}
    for name, extra in outs.items():
        assert main(["-q", "apply", str(flight), "--calibration", str(calib), "-o", str(tmp_path / name), *extra]) == 0
    a, b, lean = (tmp_path / n for n in outs)
    assert set(xr.open_zarr(a / "reflectance.zarr").data_vars) == DEFAULT_VARS
    assert set(xr.open_zarr(b / "reflectance.zarr").data_vars) == DEFAULT_VARS | {"ndre"}
    assert _chunks(a) == _chunks(b) == _chunks(lean) and len(_chunks(a)) > 0
    assert _files(a, TIFF_DIRS) == _files(b, TIFF_DIRS) and len(_files(a, TIFF_DIRS)) == 3 * 9  # 8 bands + NDVI
    assert list(lean.rglob("*.tif")) == [] and _run(lean)["products"]["tiffs"] is False
    assert _run(b)["products"] == {"radiance": False, "indices": ["ndvi", "ndre"], "tiffs": True, "keep_flagged": False, "shoulder_bound": 0.03}
    assert main(["apply", str(flight), "--calibration", str(calib), "-o", str(tmp_path / "r"),
                 "--products", "radiance"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"the field calibration {calib} gives reflectance (Eq. 15) and no radiance" in err and "\n" not in err
    # a re-run into the default OUT with --no-tiffs: redone, TIFFs gone, the same chunks
    assert main(["-q", "apply", str(flight), "--calibration", str(calib), "-o", str(a), "--no-tiffs"]) == 0
    assert list(a.rglob("*.tif")) == [] and _chunks(a) == _chunks(lean)


def test_card_session_products_from_session_yaml_and_the_command_line(tmp_path) -> None:
    """A card session's session.yaml products reach its flights, the command line's keys over
    them (here --tiffs over 'tiffs: false'); each flight's summary carries them."""
    from pipeline.run.runner import apply_card, check_products, plan_card_session

    card = tmp_path / "card"
    card.mkdir()
    for p in require_data().glob("IMG_000*_*.tif"):
        shutil.copy(p, card / p.name)
    (card / "session.yaml").write_text("products: {radiance: true, indices: [ndre], tiffs: false}\n")
    assert check_products(card).record() == {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": False, "keep_flagged": False, "shoulder_bound": 0.03}
    plan = plan_card_session(card)
    (flight,) = plan["flights"]
    out = tmp_path / "out"
    summary = apply_card(plan, flight["name"], str(out), products={"tiffs": True})
    assert summary["products"] == {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": True, "keep_flagged": False, "shoulder_bound": 0.03}
    assert set(xr.open_zarr(out / "reflectance.zarr").data_vars) == DEFAULT_VARS | {"radiance", "ndre"}
    assert len(list((out / "photogrammetry").glob("*.tif"))) == 5
    lean = tmp_path / "lean"
    assert apply_card(plan, flight["name"], str(lean))["products"]["tiffs"] is False
    assert list(lean.rglob("*.tif")) == []


def test_the_missing_reflectance_warning_says_where_the_radiance_is() -> None:
    """A band without a sun-sensor reading has NaN reflectance; its radiance is in the
    outputs only when chosen, and the report's warning says which."""
    from pipeline.products.report.sections import reference_warnings

    missing = [{"capture": "IMG_0001", "file": "IMG_0001_3.tif", "band": "Red", "reason": "no reading"}]
    run = {"reference": {"route": "dls"}, "reflectance_missing": missing}
    texts = {}
    for name, products in (("old", None), ("radiance", {"radiance": True}), ("default", {"radiance": False})):
        (w,) = reference_warnings({**run, **({} if products is None else {"products": products})})
        texts[name] = w.message
    assert "are NaN, radiance kept (run.json" in texts["old"] and "radiance kept" in texts["radiance"]
    assert "are NaN, radiance written with --products radiance (run.json" in texts["default"]
