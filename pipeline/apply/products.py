"""Apply's side of the products choice (:mod:`pipeline.ingest.products`): outputs an earlier
run made that the choice does not (:func:`remove_unchosen`), and the factor from radiance to
reflectance that run.json keeps with or without the radiance cube (:func:`factor_record`)."""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Sequence

from pipeline.ingest.products import Products

#: Folders of per-frame TIFFs under OUT (all left out by ``--no-tiffs``).
TIFF_DIRS = ("photogrammetry", "panels", "thermal", "ndvi")


def remove_unchosen(out: Path, products: Products) -> None:
    """Outputs of an earlier run that this choice does not make: without TIFFs, the TIFF
    folders (mscal's own, under OUT). Radiance and indices need nothing here: reflectance.zarr
    is written whole under a temporary name and replaces the old store."""
    if not products.tiffs:
        for sub in TIFF_DIRS:
            shutil.rmtree(Path(out) / sub, ignore_errors=True)


def factor_record(route: str, bands: Sequence[str], factor: Sequence[float] | None, per_capture: bool) -> dict[str, Any]:
    """run.json ``radiance_factor`` of a factory run, with or without the radiance cube: the
    per-band factor ``k_b`` from radiance to reflectance, one for every capture (``per_band``)
    or one per capture (``per_capture``: where run.json lists them)."""
    rec: dict[str, Any] = {"formula": "reflectance_b = k_b x radiance_b", "route": route}
    if per_capture:
        rec["per_capture"] = "illumination.per_frame (k_b of each capture)"
    elif factor is not None:
        rec["per_band"] = dict(zip(bands, (float(k) for k in factor)))
    elif route == "none":
        rec["none"] = "no reference: reflectance is NaN (reference.reason)"
    else:
        rec["per_capture"] = "each band file's own sun-sensor reading (reflectance_missing: bands without one)"
    return rec
