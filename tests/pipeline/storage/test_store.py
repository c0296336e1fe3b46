"""The calibration store: opens with xarray.open_zarr, atomic writes, checked on open."""

import os

import numpy as np
import pytest
import xarray as xr

from mscal_core.errors import CalibrationStoreError
from pipeline.ingest.catalog import load_camera
from pipeline.storage.store import new_dataset, open_calibration, write_store


def _calib(camera_name: str = "ximea-mq022hg-sm5x5-nir") -> xr.Dataset:
    cam = load_camera(camera_name)
    ds = new_dataset(cam)
    ds.coords["dn"] = np.arange(2**cam.bit_depth)
    ds["inverse_response"] = (("band", "dn"), np.tile(np.arange(2**cam.bit_depth, dtype=float), (cam.n_bands, 1)))
    ds["vignetting"] = (("band", "y", "x"), np.ones((cam.n_bands, 4, 5), np.float32))
    ds["spectral_factor"] = ("band", np.linspace(1.5, 2.5, cam.n_bands))
    ds.attrs["response"] = {"skipped": [{"file": "x.tif", "reason": "test"}], "residuals": {"rms": np.float64(0.5)}}
    return ds


def test_roundtrip_with_open_zarr(tmp_path) -> None:
    p = write_store(_calib(), tmp_path / "c.zarr")
    ds = xr.open_zarr(p)
    assert set(["inverse_response", "vignetting", "spectral_factor"]) <= set(ds.data_vars)
    assert ds["inverse_response"].dims == ("band", "dn")
    assert ds["vignetting"].dims == ("band", "y", "x")
    assert float(ds.wavelength.sel(band=24)) == 670.0
    assert ds.attrs["response"]["skipped"][0]["file"] == "x.tif"
    assert ds.attrs["response"]["residuals"]["rms"] == 0.5
    assert ds.attrs["camera"] == "ximea-mq022hg-sm5x5-nir"


def test_overwrite_is_atomic_and_leaves_no_temporaries(tmp_path) -> None:
    p = tmp_path / "c.zarr"
    write_store(_calib(), p)
    ds = _calib()
    ds["spectral_factor"] = ds["spectral_factor"] * 2
    write_store(ds, p)
    assert float(xr.open_zarr(p).spectral_factor[0]) == pytest.approx(3.0)
    assert sorted(os.listdir(tmp_path)) == ["c.zarr"]


def test_failed_write_keeps_the_old_store(tmp_path, monkeypatch) -> None:
    p = tmp_path / "c.zarr"
    write_store(_calib(), p)
    real = xr.Dataset.to_zarr

    def half_then_fail(self, store, **kw):  # writes part of the new store, then the disk fills
        real(self[["inverse_response"]], store, **kw)
        raise OSError("No space left on device")

    monkeypatch.setattr(xr.Dataset, "to_zarr", half_then_fail)
    bad = _calib()
    bad["spectral_factor"] = bad["spectral_factor"] * 0
    with pytest.raises(OSError, match="No space left"):
        write_store(bad, p)
    assert float(xr.open_zarr(p).spectral_factor[0]) == pytest.approx(1.5)
    assert sorted(os.listdir(tmp_path)) == ["c.zarr"]


def test_check_camera_of_an_opened_store(tmp_path) -> None:
    """apply opens the store once to learn its camera, then checks that same store against the
    catalog camera: a name, band count or response length that does not fit is refused with
    the store's path."""
    from dataclasses import replace

    from pipeline.storage.store import check_camera

    p = write_store(_calib(), tmp_path / "c.zarr")
    ds = open_calibration(p, need="apply")
    cam = load_camera("ximea-mq022hg-sm5x5-nir")
    check_camera(ds, cam, p)
    with pytest.raises(CalibrationStoreError, match="not 'generic-rgb8'") as err:
        check_camera(ds, load_camera("generic-rgb8"), p)
    assert "c.zarr" in str(err.value)
    with pytest.raises(CalibrationStoreError, match="store has 24 bands, camera 25"):
        check_camera(ds.isel(band=slice(0, 24)), cam, p)
    with pytest.raises(CalibrationStoreError, match="inverse_response covers 1024 DN, camera has 4096"):
        check_camera(ds, replace(cam, bit_depth=12), p)


def test_open_checks_camera_and_content(tmp_path) -> None:
    p = write_store(_calib(), tmp_path / "c.zarr")
    assert open_calibration(p, load_camera("ximea-mq022hg-sm5x5-nir"), need="apply").sizes["band"] == 25
    with pytest.raises(CalibrationStoreError, match="store is for camera 'ximea-mq022hg-sm5x5-nir', not 'generic-rgb8'"):
        open_calibration(p, load_camera("generic-rgb8"))
    partial = _calib().drop_vars(["vignetting", "spectral_factor"])
    q = write_store(partial, tmp_path / "u.zarr")
    with pytest.raises(CalibrationStoreError, match="lacks vignetting needed for illumination"):
        open_calibration(q, need="illumination")
    with pytest.raises(CalibrationStoreError, match="calibration store not found"):
        open_calibration(tmp_path / "none.zarr")
    (tmp_path / "junk.zarr").mkdir()
    with pytest.raises(CalibrationStoreError, match="junk.zarr"):
        open_calibration(tmp_path / "junk.zarr")


def test_cf_conventions_and_units_on_every_variable(tmp_path) -> None:
    """CF-1.10: the Conventions attribute and udunits units on every variable the fits write;
    what a fit set itself is kept."""
    from pipeline.storage.store import CF_VARIABLES

    ds = _calib()
    ds["saturation_dn"] = ("band", np.full(ds.sizes["band"], 1000))
    ds["reflector_exposure_ms"] = ("reflector_image", np.array([2.0, 3.0]))
    ds["spectral_factor"].attrs["long_name"] = "S as the fit named it"
    src = dict(ds["spectral_factor"].attrs)
    out = xr.open_zarr(write_store(ds, tmp_path / "c.zarr"))
    assert out.attrs["Conventions"] == "CF-1.10"
    units = {k: out[k].attrs.get("units") for k in ("vignetting", "spectral_factor", "saturation_dn",
                                                    "reflector_exposure_ms", "inverse_response", "wavelength")}
    assert units == {"vignetting": "1", "spectral_factor": "1", "saturation_dn": "count",
                     "reflector_exposure_ms": "ms", "inverse_response": "count", "wavelength": "nm"}
    assert out["spectral_factor"].attrs["long_name"] == "S as the fit named it"
    assert out["wavelength"].attrs["standard_name"] == "radiation_wavelength"
    assert dict(ds["spectral_factor"].attrs) == src  # the caller's dataset is not changed
    assert all("units" in a or k == "vignetting_observed" for k, a in CF_VARIABLES.items())
