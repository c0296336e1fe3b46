"""The calibration store (SPEC.md): a Zarr store that ``xarray.open_zarr`` opens.

Variables: ``inverse_response (band, dn)``, ``vignetting (band, y, x)``,
``spectral_factor (band)``; coordinates ``band`` (index), ``band_name`` and ``wavelength``
(nm) on ``band``. A partial store (after ``mscal fit response`` alone) holds only what was
fitted. Provenance is in the attributes. Stores are written to a temporary name next to the
target and renamed into place, so a reader never sees half a store and a failed write loses
nothing that was there before.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np
import xarray as xr
import zarr  # noqa: F401 - imported with this module, not by xarray at the first write (see below)
from mscal_core.errors import CalibrationStoreError
from mscal_core.quality import dn_flag_table

from pipeline.storage.atomic import atomic_folder

if TYPE_CHECKING:  # only for annotations: storage imports nothing of ingest at run time
    from pipeline.ingest.catalog import Camera

STORE_FORMAT = "mscal-calibration/1"


def file_sha256(path: Path) -> str:
    with path.open("rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def content_hashes(paths: Iterable[Path], root: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of the input files a fit used."""
    out: dict[str, str] = {}
    for p in sorted(set(paths)):
        try:
            rel = str(p.relative_to(root))
        except ValueError:
            rel = str(p)
        out[rel] = file_sha256(p)
    return out


def new_dataset(camera: Camera) -> xr.Dataset:
    """An empty calibration dataset with the camera's band coordinates."""
    ds = xr.Dataset(
        coords={
            "band": np.arange(camera.n_bands),
            "band_name": ("band", np.array(camera.band_names, dtype=object)),
            "wavelength": ("band", camera.wavelengths, {"units": "nm", "long_name": "centre wavelength"}),
        }
    )
    ds.attrs.update({"format": STORE_FORMAT, "camera": camera.name, "bit_depth": camera.bit_depth})
    return ds


#: CF attributes of every variable a calibration store may hold (units udunits-2: "1" for
#: dimensionless ratios, "count" for digital numbers). :func:`write_store` adds what a
#: variable lacks; attributes a fit set itself are kept.
CF_CONVENTIONS = "CF-1.10"
CF_VARIABLES: dict[str, dict[str, str]] = {
    "wavelength": {"units": "nm", "standard_name": "radiation_wavelength", "long_name": "centre wavelength"},
    "inverse_response": {"units": "count", "long_name": "inverse camera response U(k) (Eq. 5-7), linear DN"},
    "black_level": {"units": "count", "long_name": "black level of the response fit"},
    "saturation_dn": {"units": "count", "long_name": "lowest DN treated as saturated"},
    "response_residual": {"units": "count", "long_name": "rms residual of the response fit per DN bin"},
    "dn_bin": {"units": "count", "long_name": "centre of a DN bin of the response residual"},
    "vignetting": {"units": "1", "long_name": "optical attenuation V (Eq. 8-10), max 1 per band"},
    "vignetting_count": {"units": "1", "long_name": "number of reflector observations of the pixel"},
    "spectral_factor": {"units": "1", "long_name": "spectral factor S of the illumination (Eq. 11-14)"},
    "capture_spectral_factor": {"units": "1", "long_name": "spectral factor S of each reflector capture"},
    "capture_level": {"units": "1", "long_name": "brightness level of each reflector capture"},
    "capture_irradiance": {"units": "1", "long_name": "sun-sensor level at each reflector capture "
                                                      "(horizontal when sun_sensor_model says so, else the raw reading)"},
    "reflector_brightness": {"units": "1", "long_name": "brightness B(x) of each reflector image (Eq. 11-14)"},
    "reflector_dn": {"units": "count", "long_name": "reflector image in the NIR band"},
    "reflector_exposure_ms": {"units": "ms", "long_name": "exposure time of each reflector image"},
    "registration_ecc": {"units": "1", "long_name": "gradient correlation after registration"},
    "registration_inliers": {"units": "1", "long_name": "feature inliers of the registration"},
    "vignetting_observed": {"units": "1", "long_name": "V observed at the pixel (false: filled smoothly)"},
    "intrinsics": {"units": "1", "long_name": "pinhole + OpenCV distortion per band (fx, fy, cx, cy in the "
                                              "band's pixels; distortion dimensionless)"},
    "band_transform": {"units": "1", "long_name": "homography of each band onto the reference band (pixels)"},
    "capture_transform": {"units": "1", "long_name": "homography of each band of each registered capture (pixels)"},
    "dn": {"units": "count", "long_name": "digital number"},
    "band": {"units": "1", "long_name": "band index"},
    "capture": {"units": "1", "long_name": "reflector capture index"},
    "reflector_image": {"units": "1", "long_name": "reflector image index"},
    "reflector_capture": {"units": "1", "long_name": "reflector capture of each reflector image"},
}


#: CF attributes of the per-frame coordinates of every flight store (``raw.zarr`` and the
#: ``reflectance.zarr`` of both apply paths, field and factory): one set, used by all writers.
#: ``time`` has no ``units`` attribute: xarray writes its encoding's units itself.
FRAME_COORD_ATTRS: dict[str, dict[str, str]] = {
    "frame": {"long_name": "frame name (file stem, or capture name)"},
    "exposure_ms": {"long_name": "exposure time", "units": "ms"},
    "gain": {"long_name": "linear sensor gain", "units": "1"},
    "time": {"standard_name": "time", "long_name": "acquisition time (UTC where the source gave an offset)"},
    "lat": {"standard_name": "latitude", "long_name": "latitude (WGS84)", "units": "degrees_north"},
    "lon": {"standard_name": "longitude", "long_name": "longitude (WGS84)", "units": "degrees_east"},
    "alt_m": {"long_name": "altitude of the camera", "units": "m"},
    "band": {"long_name": "band index", "units": "1"},
}

#: CF attributes of the variables of the flight stores beyond their frame coordinates.
FLIGHT_VARIABLES: dict[str, dict[str, str]] = {
    **FRAME_COORD_ATTRS,
    "wavelength": CF_VARIABLES["wavelength"],
    "reflectance": {"units": "1"},
    "dn": {"units": "1"},
    "band_exposure_ms": {"long_name": "exposure time of each band file", "units": "ms"},
    "illumination_level": {"units": "1"},
    "illumination_scale": {"units": "1"},
    "vegetation_mask": {"units": "1"},
    "irradiance": {"units": "1", "long_name": "sun-sensor irradiance (the sensor's own unit)"},
}


def cf_annotate(ds: xr.Dataset, table: dict[str, dict[str, str]] | None = None) -> xr.Dataset:
    """``ds`` with the CF ``Conventions`` attribute and the units and names of ``table``
    (default :data:`CF_VARIABLES`) wherever a variable lacks them (in place; returned for
    chaining)."""
    ds.attrs.setdefault("Conventions", CF_CONVENTIONS)
    for name, attrs in (CF_VARIABLES if table is None else table).items():
        if name in ds.variables:
            for k, v in attrs.items():
                ds[name].attrs.setdefault(k, v)
    return ds


def _to_jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def write_store(ds: xr.Dataset, path: str | Path) -> Path:
    """Write ``ds`` to ``path`` atomically (temporary sibling, then rename into place) and
    durably (every file fsynced before the rename, the folder after it): a calibration store
    that exists is whole, after a power loss too."""
    path = Path(path)
    # zarr is imported when this module is (0.3 s of CPU): xarray would import it here, and
    # ``mscal calibrate`` writes at its end, on one core, while its fits keep both busy before
    ds = cf_annotate(ds.copy())
    ds.attrs = _to_jsonable(dict(ds.attrs))
    for v in ds.variables.values():
        v.encoding = {}
    with atomic_folder(path, durable=True) as tmp, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        ds.to_zarr(tmp, mode="w", consolidated=True, zarr_format=3)
    return path


REQUIRED_FOR = {
    "apply": ("inverse_response", "vignetting", "spectral_factor"),
    "illumination": ("inverse_response", "vignetting"),
    "vignetting": ("inverse_response",),
}


def check_camera(ds: xr.Dataset, camera: Camera, path: str | Path) -> None:
    """CalibrationStoreError unless the calibration ``ds`` (opened from ``path``) is for
    ``camera``: its name, band count and response table length (:func:`open_calibration`
    with a camera checks this; a caller that first opened the store to learn its camera checks
    the same store with it)."""
    if ds.attrs.get("camera") != camera.name:
        raise CalibrationStoreError(
            f"store is for camera {ds.attrs.get('camera')!r}, not {camera.name!r}",
            path=path,
            hint="use a calibration fitted for this camera",
        )
    if ds.sizes.get("band") != camera.n_bands:
        raise CalibrationStoreError(f"store has {ds.sizes.get('band')} bands, camera {camera.n_bands}", path=path)
    if "inverse_response" in ds and ds.sizes.get("dn") != 2**camera.bit_depth:
        raise CalibrationStoreError(
            f"inverse_response covers {ds.sizes.get('dn')} DN, camera has {2**camera.bit_depth}", path=path
        )


def open_calibration(path: str | Path, camera: Camera | None = None, need: str | None = None) -> xr.Dataset:
    """Open and check a calibration store; loads it into memory (it is small: read straight
    into numpy, without dask, 0.1 s instead of 0.5 s the first time in a process)."""
    path = Path(path)
    if not path.exists():
        raise CalibrationStoreError("calibration store not found", path=path)
    try:
        ds = xr.open_zarr(path, chunks=None).load()
    except Exception as exc:
        raise CalibrationStoreError(
            f"not a readable Zarr calibration store ({type(exc).__name__})",
            path=path,
            hint="re-create it with 'mscal calibrate' or 'mscal fit'",
        ) from None
    if ds.attrs.get("format") != STORE_FORMAT:
        raise CalibrationStoreError("not an mscal calibration store (format attribute missing)", path=path)
    if camera is not None:
        check_camera(ds, camera, path)
    if need is not None:
        missing = [v for v in REQUIRED_FOR[need] if v not in ds]
        if missing:
            raise CalibrationStoreError(
                f"store lacks {', '.join(missing)} needed for {need}",
                path=path,
                hint="fit those first ('mscal fit response|vignetting') or run 'mscal calibrate'",
            )
    return ds


def dn_flags_of(ds: xr.Dataset, sat: int, bound: float) -> np.ndarray:
    """The flags of every DN of every band of a calibration (:func:`mscal_core.quality.dn_flag_table`
    with its optional ``response_uncertainty``, ``response_fit_uncertainty`` and
    ``response_dn_range``): (band, DN) uint8."""
    n_bands, n_dn = ds["inverse_response"].shape
    unc = ds["response_uncertainty"].values if "response_uncertainty" in ds else None
    fit = ds["response_fit_uncertainty"].values if "response_fit_uncertainty" in ds else None
    rng = ds["response_dn_range"].transpose("band", "end").sel(end=["low", "high"]).values \
        if "response_dn_range" in ds else None
    return dn_flag_table(n_bands, n_dn, sat, unc, bound, rng, fit)
