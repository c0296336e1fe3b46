"""``mscal index``: index maps of reflectance orthomosaics as Cloud Optimized GeoTIFFs."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import rasterio
import tifffile
from affine import Affine
from rasterio.enums import ColorInterp

from mscal_core.errors import InputError
from pipeline.products import indexmap
from pipeline.products.indexmap import index_map, parse_bands_option, resolve_bands

CRS = "EPSG:32632"
TRANSFORM = Affine(0.05, 0.0, 465000.0, 0.0, -0.05, 5250000.0)
H, W = 300, 520
NAMES = ["Blue", "Green", "Red", "NIR", "Rededge"]  # as ODM writes band names (alphanumeric)


def _reflectance(count: int = 5, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.02, 0.6, (count, H, W)).astype(np.float32)


def _write(path: Path, data: np.ndarray, descriptions=None, *, nodata=None, alpha=None, **tags) -> Path:
    count = data.shape[0] + (alpha is not None)
    profile = dict(driver="GTiff", height=H, width=W, count=count, dtype=data.dtype.name, crs=CRS,
                   transform=TRANSFORM, tiled=True, blockxsize=256, blockysize=256)
    if nodata is not None:
        profile["nodata"] = nodata
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(data, list(range(1, data.shape[0] + 1)))
        if alpha is not None:
            ds.write(alpha, count)
            ds.colorinterp = [ColorInterp.gray] + [ColorInterp.undefined] * (count - 2) + [ColorInterp.alpha]
        for i, d in enumerate(descriptions or []):
            if d is not None:
                ds.set_band_description(i + 1, d)
        for b, t in tags.items():  # b2={...}: tags of band 2
            ds.update_tags(int(b[1:]), **t)
    return path


def _ndvi(nir, red):
    with np.errstate(divide="ignore", invalid="ignore"):
        return ((nir - red) / (nir + red)).astype(np.float32)


def _assert_cog(path: Path) -> None:
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert ds.profile["tiled"] and ds.profile["blockxsize"] == ds.profile["blockysize"] == 256
        assert ds.overviews(1), "a COG of this size has overviews"
    with tifffile.TiffFile(path) as tf:
        pages = list(tf.pages)
        assert pages[0].shape == (H, W) and pages[0].is_tiled
        sizes = [p.shape[0] * p.shape[1] for p in pages]
        assert sizes == sorted(sizes, reverse=True) and len(pages) >= 2
        # COG layout: the IFDs come first, the smallest overview's tiles before the full-resolution ones
        assert all(p.offset < min(pages[-1].dataoffsets) for p in pages)
        assert max(pages[-1].dataoffsets) < min(o for o in pages[0].dataoffsets if o)


def test_float_ortho_ndvi_cog(tmp_path) -> None:
    data = _reflectance()
    data[2, 10:20, 30:40] = -9999.0  # nodata in red only
    data[3, 100, 100] = np.nan  # NaN in NIR
    ortho = _write(tmp_path / "ortho.tif", data, NAMES, nodata=-9999.0)
    out = index_map(ortho, "ndvi", tmp_path / "out" / "ndvi.tif")
    assert out == tmp_path / "out" / "ndvi.tif"
    with rasterio.open(out) as ds:
        assert ds.crs == rasterio.crs.CRS.from_string(CRS)
        assert ds.transform == TRANSFORM
        assert ds.dtypes[0] == "float32" and ds.count == 1 and np.isnan(ds.nodata)
        assert ds.descriptions == ("ndvi",)
        assert ds.tags()["BANDS"] == "nir=4,red=3" and ds.tags()["INDEX"] == "ndvi"
        got = ds.read(1)
    expected = _ndvi(data[3], data[2])
    expected[10:20, 30:40] = np.nan
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert np.isnan(got[10:20, 30:40]).all() and np.isnan(got[100, 100])
    assert np.isfinite(got).sum() == H * W - 100 - 1
    _assert_cog(out)
    assert sorted(os.listdir(tmp_path / "out")) == ["ndvi.tif"]


def test_uint16_ortho_is_scaled_back(tmp_path, monkeypatch) -> None:
    # an index with an additive constant sees the scale: (nir - red) + 1 on reflectance
    cat = tmp_path / "cat" / "indices"
    cat.mkdir(parents=True)
    (cat / "mscaltest_diff.yaml").write_text(
        "name: mscaltest_diff\ndescription: test\nexpression: nir - red + 1\n"
    )
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path / "cat"))
    refl = _reflectance()
    dn = np.rint(refl * 32768).astype(np.uint16)
    dn[3, 0:5, 0:5] = 65535  # our writers' nodata
    ortho = _write(tmp_path / "ortho16.tif", dn, NAMES, nodata=65535)
    out = index_map(ortho, "mscaltest_diff", tmp_path / "diff.tif")
    with rasterio.open(out) as ds:
        got = ds.read(1)
    expected = dn[3] / 32768.0 - dn[2] / 32768.0 + 1
    ok = np.ones((H, W), bool)
    ok[0:5, 0:5] = False
    np.testing.assert_allclose(got[ok], expected[ok], rtol=1e-6)
    assert np.isnan(got[~ok]).all()
    # NDVI does not see the scale: it is the NDVI of the DN, i.e. of the reflectance to quantisation
    out2 = index_map(ortho, "ndvi", tmp_path / "ndvi.tif")
    with rasterio.open(out2) as ds:
        nd = ds.read(1)
    np.testing.assert_allclose(nd[ok], _ndvi(dn[3].astype(np.float32), dn[2].astype(np.float32))[ok], rtol=1e-5)
    np.testing.assert_allclose(nd[ok], _ndvi(refl[3], refl[2])[ok], atol=1e-3)


def test_odm_alpha_band_masks_and_is_never_a_role(tmp_path) -> None:
    data = _reflectance(4)
    alpha = np.full((H, W), 255, np.float32)
    alpha[:, :50] = 0
    ortho = _write(tmp_path / "odm.tif", data, ["Green", "Red", "Rededge", "NIR", None], alpha=alpha)
    out = index_map(ortho, "ndre", tmp_path / "ndre.tif")
    with rasterio.open(out) as ds:
        got = ds.read(1)
        assert ds.tags()["BANDS"] == "nir=4,rededge=3"
    assert np.isnan(got[:, :50]).all()
    np.testing.assert_allclose(got[:, 50:], _ndvi(data[3], data[2])[:, 50:], rtol=1e-6)


@pytest.mark.parametrize(
    "descriptions, tags, expected",
    [
        # the paper's Ximea bands written by mscal (names b<nm>) and mosaicked: red 670, NIR 803
        (["b615", "b670", "b700", "b714", "b803"], {}, {"red": 2, "nir": 5, "rededge": 4}),
        (["b686", "b662", "b790", "b791", "b803"], {}, {"red": 2, "nir": 5}),
        (["475nm", "560 nm", "668", "NIR 840", "717"], {}, {"red": 3, "nir": 4, "rededge": 5}),
        (["blue", "green", "RED", "near-infrared", "Red edge"], {}, {"red": 3, "nir": 4, "rededge": 5}),
        (["B", "G", "R", "NIR", "RE"], {}, {"blue": 1, "green": 2, "red": 3, "nir": 4, "rededge": 5}),
        ([None] * 5, {"b2": {"wavelength": "0.665", "wavelength_units": "micrometers"},
                      "b5": {"CENTRAL_WAVELENGTH": "842"}, "b1": {"wavelength": "717 nm"}},
         {"red": 2, "nir": 5, "rededge": 1}),
    ],
)
def test_roles_from_descriptions_and_wavelengths(tmp_path, descriptions, tags, expected) -> None:
    ortho = _write(tmp_path / "o.tif", _reflectance(), descriptions, **tags)
    with rasterio.open(ortho) as ds:
        got = resolve_bands(ds, tuple(sorted(expected)))
    assert got == expected


def test_imagery_domain_wavelength(tmp_path) -> None:
    ortho = _write(tmp_path / "o.tif", _reflectance(), None)
    with rasterio.open(ortho, "r+") as ds:
        for b, um in enumerate([0.475, 0.56, 0.668, 0.84, 0.717], start=1):
            ds.update_tags(b, ns="IMAGERY", CENTRAL_WAVELENGTH_UM=str(um))
    with rasterio.open(ortho) as ds:
        assert resolve_bands(ds, ("nir", "red", "rededge")) == {"nir": 4, "red": 3, "rededge": 5}


def test_unmatched_role_names_file_and_descriptions(tmp_path) -> None:
    ortho = _write(tmp_path / "o.tif", _reflectance(), ["Blue", "Green", "Red", "Band 4", None])
    with pytest.raises(InputError) as err:
        index_map(ortho, "ndvi", tmp_path / "ndvi.tif")
    msg = str(err.value)
    assert str(ortho) in msg and "'nir'" in msg and "'Band 4'" in msg and "3='Red'" in msg and "--bands" in msg
    assert sorted(os.listdir(tmp_path)) == ["o.tif"]


def test_bands_option(tmp_path) -> None:
    data = _reflectance()
    ortho = _write(tmp_path / "o.tif", data, None)
    out = index_map(ortho, "ndvi", tmp_path / "n.tif", bands={"red": 3, "nir": 5})
    with rasterio.open(out) as ds:
        np.testing.assert_allclose(ds.read(1), _ndvi(data[4], data[2]), rtol=1e-6)
    with pytest.raises(InputError, match="bands 1..5"):
        index_map(ortho, "ndvi", tmp_path / "n2.tif", bands={"red": 3, "nir": 6})
    with pytest.raises(InputError, match="does not use"):
        index_map(ortho, "ndvi", tmp_path / "n2.tif", bands={"red": 3, "nri": 5})
    assert parse_bands_option("red=3, nir=5") == {"red": 3, "nir": 5}
    with pytest.raises(InputError, match="ROLE=NUMBER"):
        parse_bands_option("red:3")
    # a partial --bands completes from the descriptions
    ortho2 = _write(tmp_path / "o2.tif", data, ["Blue", "Green", "Red", "NIR", "Rededge"])
    with rasterio.open(ortho2) as ds:
        assert resolve_bands(ds, ("nir", "red"), {"nir": 5}) == {"nir": 5, "red": 3}


def test_ambiguous_descriptions(tmp_path) -> None:
    ortho = _write(tmp_path / "o.tif", _reflectance(), ["Red", "Red", "NIR", None, None])
    with rasterio.open(ortho) as ds, pytest.raises(InputError, match="all look like 'red'"):
        resolve_bands(ds, ("nir", "red"))


def test_many_windows_give_the_same_map(tmp_path, monkeypatch) -> None:
    data = _reflectance()
    ortho = _write(tmp_path / "o.tif", data, NAMES)
    monkeypatch.setattr(indexmap, "_WINDOW_H", 256)
    monkeypatch.setattr(indexmap, "_WINDOW_W", 256)
    assert len(list(indexmap._windows(H, W, 256))) == 2 * 3
    out = index_map(ortho, "ndvi", tmp_path / "n.tif")
    with rasterio.open(out) as ds:
        np.testing.assert_allclose(ds.read(1), _ndvi(data[3], data[2]), rtol=1e-6)


def test_missing_or_unreadable_input(tmp_path) -> None:
    with pytest.raises(InputError, match="not found"):
        index_map(tmp_path / "nope.tif", "ndvi", tmp_path / "n.tif")
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff")
    with pytest.raises(InputError, match="not a raster"):
        index_map(bad, "ndvi", tmp_path / "n.tif")
    assert sorted(os.listdir(tmp_path)) == ["bad.tif"]
