"""The output stores of every apply as lazy datasets, one builder for every camera:
``reflectance.zarr``'s variables (:func:`product_variables`), a store of one chunk per frame
for each (:func:`frame_template`) and its layout written before the pass
(:func:`create_store`); the pass writes each frame's chunks
(:func:`pipeline.apply.executor.process_frames`)."""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import xarray as xr

from pipeline.apply.quality import ATTRS as QUALITY_ATTRS
from pipeline.ingest.catalog import Index
from pipeline.storage.chunks import frame_encoding, unwritten_frames
from pipeline.storage.store import FLIGHT_VARIABLES, cf_annotate

#: A variable of a frame store: its dimensions, dtype and attributes.
Variable = tuple[tuple[str, ...], Any, dict[str, Any]]


def product_variables(indices: Sequence[Index], reflectance_name: str, *, normalisation: str | None = None,
                      radiance_unit: str | None = None, quality: bool = False) -> dict[str, Variable]:
    """``reflectance.zarr``'s variables: ``reflectance`` (its ``long_name`` says which chain
    made it; ``normalisation`` when the run scales it), ``quality`` (its per-pixel flags,
    :mod:`pipeline.apply.quality`) when ``quality``, ``radiance`` in ``radiance_unit`` when
    given (the factory chain's), each index and, with NDVI, ``vegetation_mask``."""
    refl = {"long_name": reflectance_name, "units": "1"}
    if normalisation is not None:
        refl["normalisation"] = normalisation
    variables: dict[str, Variable] = {"reflectance": (("frame", "band", "y", "x"), np.float32, refl)}
    if quality:
        variables["quality"] = (("frame", "band", "y", "x"), np.uint8, dict(QUALITY_ATTRS))
    if radiance_unit is not None:
        variables["radiance"] = (("frame", "band", "y", "x"), np.float32,
                                 {"long_name": "factory radiance", "units": radiance_unit})
    for ix in indices:
        variables[ix.name] = (("frame", "y", "x"), np.float32,
                              {"long_name": ix.description, "expression": ix.expression, "units": "1"})
    if any(ix.name == "ndvi" for ix in indices):
        variables["vegetation_mask"] = (("frame", "y", "x"), np.uint8,
                                        {"long_name": "vegetation (Otsu threshold of NDVI per frame)",
                                         "flag_values": [0, 1, 255], "flag_meanings": "other vegetation undefined"})
    return variables


def frame_template(coords: dict[str, Any], shape: tuple[int, int, int], variables: dict[str, Variable],
                   attrs: dict[str, Any]) -> xr.Dataset:
    """A lazy dataset of ``variables`` (zeros, one chunk per frame) of frames of ``shape``
    (band, y, x) on ``coords``, with ``attrs`` and the CF attributes of the flight variables."""
    ds = xr.Dataset(coords=coords)
    n = ds.sizes["frame"]
    for name, (dims, dtype, vattrs) in variables.items():
        full = (n, *shape) if len(dims) == 4 else (n, shape[0]) if dims == ("frame", "band") else (n, *shape[1:])
        ds[name] = (dims, unwritten_frames(full, dtype), vattrs)
    ds.attrs.update(attrs)
    return cf_annotate(ds, FLIGHT_VARIABLES)


def quality_compressors() -> tuple:  # (zarr.codecs.BloscCodec,)
    """Codec of ``reflectance.zarr/quality``: Blosc lz4 level 1 on bit-shuffled uint8. The mask is
    mostly zeros: uncompressed it is a quarter of the reflectance chunk's bytes (2.2 MB a
    full-resolution snapshot frame), and the apply pass is bound by the bytes it writes; with
    17 % of its pixels flagged the chunk took 62 KB for 0.8 ms of encoding. (The other
    variables, ``vegetation_mask`` included, are uncompressed: ``OUTPUT_COMPRESSORS``.)"""
    from zarr.codecs import BloscCodec

    return (BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle", typesize=1),)


def create_store(ds: xr.Dataset, path: Path, compressors: Any) -> None:
    """Write the layout of ``ds`` (metadata, coordinates; no chunk of its variables) at ``path``;
    ``quality`` with its own codec (:func:`quality_compressors`), the others with ``compressors``."""
    encoding = {v: frame_encoding(ds[v].shape, quality_compressors() if v == "quality" else compressors)
                for v in ds.data_vars}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        ds.to_zarr(path, mode="w", compute=False, consolidated=True, zarr_format=3, encoding=encoding)
