"""What the report reads: an ``mscal apply`` OUT folder (:func:`open_flight`) and a
calibration store or dataset (:func:`as_calibration`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import xarray as xr
from mscal_core.errors import InputError

from pipeline.ingest.catalog import Camera, load_camera
from pipeline.storage.store import open_calibration

# --------------------------------------------------------------------------- inputs


@dataclass
class FlightResults:
    """The stored results of one ``mscal apply`` OUT folder (arrays stay lazy: read when indexed)."""

    out: Path
    run: dict[str, Any]
    reflectance: xr.Dataset
    raw: xr.Dataset | None
    camera: Camera | None

    @property
    def name(self) -> str:
        return Path(str(self.run.get("flight") or self.out)).name or self.out.name


def open_flight(out: str | Path) -> FlightResults:
    """Open an apply OUT folder; :class:`InputError` naming what is missing."""
    out = Path(out)
    run_path = out / "run.json"
    if not run_path.is_file():
        raise InputError("no run.json: not an 'mscal apply' output folder", path=out,
                         hint="run 'mscal apply FLIGHT_DIR --calibration CALIB.zarr -o OUT' first")
    try:
        run = json.loads(run_path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"run.json is unreadable ({type(exc).__name__})", path=run_path,
                         hint="run 'mscal apply' again to rewrite it") from None
    if not (out / "reflectance.zarr").is_dir():
        raise InputError("reflectance.zarr is missing", path=out, hint="run 'mscal apply' again")
    # lazily indexed, not dask (chunks=None): the report reads coordinates, per-frame medians
    # and a few sampled frames, each by indexing first; through dask each read was a graph
    # of one task per stored chunk (300 for a 300-frame flight's dn_median) and the first
    # compute imported distributed to look for a client
    refl = xr.open_zarr(out / "reflectance.zarr", chunks=None)
    raw = xr.open_zarr(out / "raw.zarr", chunks=None) if (out / "raw.zarr").is_dir() else None
    camera = None
    name = refl.attrs.get("camera")
    if name:
        try:
            camera = load_camera(str(name))
        except InputError:
            camera = None
    return FlightResults(out, run, refl, raw, camera)


def as_calibration(calibration: str | Path | xr.Dataset | None) -> xr.Dataset | None:
    if calibration is None or isinstance(calibration, xr.Dataset):
        return calibration
    return open_calibration(calibration)


