"""Zarr stores as a process of the apply pass holds them: a frame's whole chunk written or read
(direct when the layout allows), and each calibration store read once per process and store
(its Eq. 15 tables, its band transforms for :func:`geometry_step`). Every cache is keyed by the
store's path and the time its metadata was written, so a store replaced at the same path is
read again."""
from __future__ import annotations

import logging
import os
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np
import xarray as xr
from mscal_core.alignment import align_bands, shift_bands
from mscal_core.quality import FLAGS, mask_tables, pixel_flag_table
from mscal_core.reflectance import eq15_tables

from pipeline.calibrate.registration import frame_transforms
from pipeline.storage.chunks import FrameChunks
from pipeline.storage.store import dn_flags_of

log = logging.getLogger(__name__)


def _stamp(path: Path) -> tuple[str, int]:
    """Cache key of a Zarr node: its path and the time its metadata was written (a store
    replaced at the same path is not mistaken for the old one)."""
    return str(path), os.stat(path / "zarr.json").st_mtime_ns


@lru_cache(maxsize=16)
def _zarr_array(key: tuple[str, int]):
    import zarr

    return zarr.open_array(key[0], mode="r+").with_config({"write_empty_chunks": True})


@lru_cache(maxsize=16)
def _frame_chunks(key: tuple[str, int]) -> FrameChunks | None:
    return FrameChunks.open(key[0])


def write_frame(array: Path, f: int, data: np.ndarray) -> None:
    """Frame ``f``'s whole chunk of the Zarr array at ``array`` (direct when the layout allows)."""
    key = _stamp(array)
    fc = _frame_chunks(key)
    if fc is not None:
        fc.write(f, data)
    else:
        _zarr_array(key)[f] = data


def read_frame_chunk(array: Path, f: int) -> np.ndarray:
    key = _stamp(array)
    fc = _frame_chunks(key)
    return fc.read(f) if fc is not None else np.asarray(_zarr_array(key)[f])


def calibration_tables(calibration: str, flags: tuple[int, float, bool] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 15 tables of a calibration store, once per process and store. ``flags``:
    ``(saturation DN, bound, keep_flagged)`` of the quality mask (:func:`quality_tables`); unless
    ``keep_flagged``, the tables are NaN where a DN or a pixel is flagged
    (:func:`mscal_core.quality.mask_tables`)."""
    key = _stamp(Path(calibration))
    if flags is None or flags[2]:
        return _tables_of(key)
    return _masked_tables(key, *flags[:2])


def quality_tables(calibration: str, sat: int, bound: float) -> tuple[np.ndarray, np.ndarray | None, tuple[str, ...]]:
    """The quality mask's tables of a calibration store, once per process and store: per band
    and DN (:func:`mscal_core.quality.dn_flag_table`), per band and pixel
    (:func:`mscal_core.quality.pixel_flag_table`; None without ``vignetting_coverage``), and
    the flags the store lets one check (its optional ``response_uncertainty`` with
    ``response_fit_uncertainty``, ``response_dn_range``, ``vignetting_coverage``)."""
    return _quality_of(_stamp(Path(calibration)), int(sat), float(bound))


def pixel_flag_sets(calibration: str, sat: int, bound: float) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """Per band of a calibration store's pixel flag table (:func:`quality_tables`; the same for
    every frame), the flat positions of the pixels it flags and their flags, once per process
    and store; None when the store has no pixel table."""
    return _pixel_sets_of(_stamp(Path(calibration)), int(sat), float(bound))


def quality_checks(ds: xr.Dataset) -> tuple[str, ...]:
    """The flags of the quality mask a calibration store lets one check (field chain): the
    clip, no value and co-registration always, the others with the store's optional variables."""
    out = {"saturated", "not_coregistered", "no_value"}
    for names, var in ((("response_shoulder",), "response_uncertainty"),
                       (("outside_sweep", "below_sweep"), "response_dn_range"),
                       (("vignetting_unobserved",), "vignetting_coverage")):
        if var in ds:
            out.update(names)
    return tuple(f for f in FLAGS if f in out)  # in bit order


@lru_cache(maxsize=2)
def _quality_of(key: tuple[str, int], sat: int, bound: float) -> tuple[np.ndarray, np.ndarray | None, tuple[str, ...]]:
    ds = _store_of(key)
    pixel = pixel_flag_table(ds["vignetting_coverage"].values) if "vignetting_coverage" in ds else None
    return dn_flags_of(ds, sat, bound), pixel, quality_checks(ds)


@lru_cache(maxsize=2)
def _pixel_sets_of(key: tuple[str, int], sat: int, bound: float) -> list[tuple[np.ndarray, np.ndarray]] | None:
    _, pixel, _ = _quality_of(key, sat, bound)
    return None if pixel is None else flag_positions(pixel)


def flag_positions(pixel: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per band of a pixel flag table ``(band, H, W)``, the flat positions of the pixels it
    flags and their flags (:func:`pixel_flag_sets`)."""
    flat = [np.flatnonzero(pixel[b]) for b in range(pixel.shape[0])]
    return [(at, pixel[b].ravel()[at]) for b, at in enumerate(flat)]


@lru_cache(maxsize=2)
def _masked_tables(key: tuple[str, int], sat: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
    lut, inv_v = _tables_of(key)
    dn_flags, pixel, _ = _quality_of(key, sat, bound)
    return mask_tables(lut, inv_v, dn_flags, pixel)


def loaded_calibrations() -> int:
    """How many calibration stores' Eq. 15 tables this process holds (:func:`calibration_tables`)."""
    return _tables_of.cache_info().currsize


def warm_calibration(calibration: str | Path) -> None:
    """Load the Eq. 15 tables of ``calibration`` now (:func:`calibration_tables`), so the first
    frame does not wait for them. A store that cannot be read is left to the frames, whose own
    load raises the error that says what is wrong (nothing is cached for it)."""
    try:
        calibration_tables(str(calibration))
    except Exception:  # raised again, with its message, by the first frame
        log.debug("calibration %s not loaded ahead of the frames", calibration, exc_info=True)


@lru_cache(maxsize=2)
def _tables_of(key: tuple[str, int]) -> tuple[np.ndarray, np.ndarray]:
    ds = _store_of(key)  # the process's one in-memory copy of the store (also read for band transforms)
    return eq15_tables(ds["inverse_response"].values, ds["vignetting"].values, ds["spectral_factor"].values)


@lru_cache(maxsize=2)
def _store_of(key: tuple[str, int]) -> xr.Dataset:
    """A calibration store in memory, once per process and store (read straight into numpy:
    no dask for a small store)."""
    return xr.open_zarr(key[0], chunks=None).load()


def geometry_step(calibration: Path, align: bool, band_shift: Sequence[tuple[float, float]] | None, name: str,
                  refl: np.ndarray) -> np.ndarray:
    """Eq. 15 reflectance (band, y, x) of frame ``name`` put on one pixel grid: the
    bands of a multi-lens camera warped onto the reference band (``align``: the capture's own
    transforms if it was registered, else the session's; ``mscal_core.alignment.align_bands``,
    NaN where a band does not cover), or a snapshot mosaic's bands resampled to the mosaic's
    centre position (``band_shift``). Unchanged otherwise. Eq. 15 runs before: U, V and S
    belong to each band's own pixels."""
    if align:
        H = frame_transforms(_store_of(_stamp(Path(calibration))), name)
        if H is not None:
            refl = align_bands(refl, H)
    if band_shift is not None:
        refl = shift_bands(refl, np.asarray(band_shift, dtype=np.float64))
    return refl
