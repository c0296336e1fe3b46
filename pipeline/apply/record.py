"""The run record of an apply (``OUT/run.json``), shared by every camera's path: the
fingerprint of what a run computed from, the check that a previous run is still up to date,
and the completion marker written last (with the manifest of the outputs it completes)."""
from __future__ import annotations

import hashlib
import json
import logging
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Sequence

import cv2
import dask
import mscal_core
import numpy as np
import xarray as xr

from pipeline.apply.executor import Outcome, Runner, band_tiff_path
from pipeline.apply.light import IlluminationPlan
from pipeline.apply.options import ApplyOptions
from pipeline.apply.quality import Flagging, quality_record
from pipeline.ingest.catalog import Camera
from pipeline.storage.atomic import outputs_manifest, sync_file_system, write_json_atomic
from pipeline.storage.cache import code_digest
from pipeline.storage.run_layout import group_parts

RUN_JSON = "run.json"
log = logging.getLogger(__name__)

#: run.json's note of the outputs it completes (:func:`pipeline.storage.atomic.outputs_manifest`).
MANIFEST_KEY = "outputs_manifest"


def run_fingerprint(shas: Sequence[str], chash: str, options: ApplyOptions,
                    illum: IlluminationPlan | None = None) -> dict[str, Any]:
    """The fingerprint of a run with a field calibration store: the frames' content
    (``shas``), the store's hash, the options, the code, and the light when it varies in time."""
    fingerprint = {
        "calibration_sha256": chash,
        "options": options.fingerprint(),
        "mscal_version": mscal_core.__version__,
        "code_sha256": code_digest(),  # every source of mscal_core, pipeline and the catalogs
    }
    if illum is not None:  # light that varies in time: the mode and the factors (readings) count
        fingerprint["illumination"] = {"mode": illum.mode, "scale_sha256": illum.digest()}
    return content_fingerprint(fingerprint, shas)


def content_fingerprint(base: dict[str, Any], shas: Sequence[str]) -> dict[str, Any]:
    """run.json ``fingerprint`` of every apply: ``frames_sha256``, the digest of the frames'
    content hashes in frame order (:func:`frames_digest`: a snapshot frame's file, a capture's
    band files in band order), then ``base``, everything else the outputs depend on; as it
    reads back from run.json."""
    rest = {k: v for k, v in base.items() if k != "frames_sha256"}
    return json.loads(json.dumps({"frames_sha256": frames_digest(shas), **rest}))


def up_to_date(out: Path, base: dict[str, Any], shas: Sequence[str], stores: Sequence[str] = ("reflectance.zarr",)
               ) -> dict[str, Any] | None:
    """The one up-to-date rule of apply: the previous run's record when its fingerprint is
    this run's (:func:`content_fingerprint`: the frames' content, not their names or times)
    and its outputs are whole (:func:`previous_run`); else None."""
    return previous_run(out, content_fingerprint(base, shas), stores)


def previous_run(out: Path, fingerprint: dict[str, Any], stores: Sequence[str] = ("reflectance.zarr",)
                ) -> dict[str, Any] | None:
    """The previous run's record if it made the outputs (``stores`` in ``out``) of exactly these
    inputs and they are still whole: ``run.json``, the completion marker written last
    (:func:`write_run_record`), notes the outputs' files and sizes; a store that is missing,
    empty, has a file less or a truncated chunk does not match and the flight is redone. A
    ``run.json`` without that note (an older run's) is not trusted either."""
    run_path = out / RUN_JSON
    if not (run_path.is_file() and all((out / s).is_dir() for s in stores)):
        return None
    try:
        previous = json.loads(run_path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(previous, dict) or previous.get("fingerprint") != fingerprint:
        return None
    manifest = previous.get(MANIFEST_KEY)
    if not manifest or manifest != outputs_manifest(out, (previous.get("outputs") or {}).values()):
        log.warning("%s: outputs changed since run.json was written (incomplete or damaged): redoing them", out)
        return None
    return previous


def forget_run(out: Path) -> None:
    """Remove ``out/run.json`` before outputs are (re)written: until the new one is written
    last, nothing in ``out`` claims to be complete."""
    path = out / RUN_JSON
    if path.exists():
        path.unlink()
        sync_file_system(out)


def write_run_record(out: Path, record: dict[str, Any]) -> None:
    """Write ``out/run.json``, the completion marker of a flight, last: the outputs are flushed
    to the disk first (one ``syncfs``), their manifest goes into the record, and the record is
    written atomically and fsynced (file and folder). The manifest (a ``stat`` per file, 0.04 s
    of CPU for a 600-frame OUT) is taken while ``syncfs`` waits for the disk (0.1 s): it reads
    sizes, which flushing does not change; run.json is written only after both."""
    with ThreadPoolExecutor(1) as pool:
        synced = pool.submit(sync_file_system, out)
        record[MANIFEST_KEY] = outputs_manifest(out, (record.get("outputs") or {}).values())
        synced.result()  # its error, if any, before anything claims the outputs complete
    write_json_atomic(out / RUN_JSON, record)


def software_versions() -> dict[str, str]:
    versions = {"mscal": mscal_core.__version__, "python": platform.python_version(), "numpy": np.__version__,
                "dask": dask.__version__, "xarray": xr.__version__, "opencv": cv2.__version__}
    try:
        import zarr

        versions["zarr"] = zarr.__version__
    except ImportError:  # pragma: no cover
        pass
    return versions


def remove_frame_tiffs(out: Path, names: Sequence[str], camera: Camera, export: Sequence[int]) -> None:
    """Remove the TIFFs of frames ``names`` (survey or panel; also under the names of runs
    before band names lost their spaces)."""
    for name in names:
        for b in export:
            band = camera.bands[b].name
            for panel in (False, True):
                band_tiff_path(out, name, band, panel).unlink(missing_ok=True)
            (out / "photogrammetry" / f"{name}_{band}.tif").unlink(missing_ok=True)
        (out / "ndvi" / f"{name}.tif").unlink(missing_ok=True)


def illumination_record(illum: IlluminationPlan | None, calib: xr.Dataset, frames: Sequence[str]) -> dict[str, Any]:
    """run.json ``illumination`` of a run with a field calibration store: the mode and each
    frame's factors when the light varies in time, else that the store's S was used for every
    frame (and how many captures the store's S was fitted on)."""
    if illum is None:
        return {"varies_in_time": False, "captures": int(calib.sizes.get("capture", 1))}
    return {"varies_in_time": True, **illum.summary(list(frames))}


def frames_digest(shas: Sequence[str]) -> str:
    """sha256 of the frames' content hashes in frame order: run.json ``fingerprint.frames_sha256``
    for every camera (a snapshot frame's file, a capture's band files in band order)."""
    return hashlib.sha256("".join(map(str, shas)).encode()).hexdigest()


def run_record(*, flight: Path, camera: Camera, calibration: str, calibration_sha256: str | None,
               outcomes: Sequence[Outcome], frames_sha256: dict[str, str], quarantined: list[dict[str, str]],
               metadata_problems: Sequence[dict[str, Any]], outputs: dict[str, str], products: dict[str, Any],
               export: Sequence[int], runner: Runner, t_pass: float, t_start: float, fingerprint: dict[str, Any],
               parts: dict[str, Any], flagging: Flagging | None = None) -> dict[str, Any]:
    """``run.json`` of every apply (SPEC.md, Outputs of apply), one schema for every camera: the
    common keys, the same in name and meaning whatever the camera, then ``parts``, the keys of
    one kind of input (a snapshot flight's ``snapshot``, a capture folder's, the factory
    chain's), flat as the source gives them and nested here under their group's key
    (:func:`pipeline.storage.run_layout.group_parts`: ``captures``, ``factory``). ``t_pass``: seconds of the pass over the frames (ingest and Eq. 15: a capture is
    read in its task); ``t_start``: ``time.perf_counter()`` when the apply began; ``flagging``:
    the run's quality mask (run.json ``quality``, :func:`pipeline.apply.quality.quality_record`)."""
    frames = [o.name for o in outcomes]
    return {
        "flight": str(flight),
        "camera": camera.name,
        "calibration": calibration,
        "calibration_sha256": calibration_sha256,
        "frames_in": len(frames) + len(quarantined),
        "frames_out": len(frames),
        "frames": frames,
        "frames_sha256": frames_sha256,
        "quarantined": quarantined,
        "metadata_problems": list(metadata_problems),
        "saturated_pixels": {"total": int(sum(o.saturated for o in outcomes)),
                             "per_frame": {o.name: int(o.saturated) for o in outcomes}},
        **({} if flagging is None else {"quality": quality_record(flagging, {o.name: o.quality or {} for o in outcomes},
                                                                  {o.name: o.coregistration for o in outcomes})}),
        "outputs": outputs,
        "products": products,
        "export_bands": [camera.bands[b].name for b in export],
        "versions": software_versions(),
        "scheduler": runner.scheduler,
        "execution": runner.execution,
        "timings_s": {"pass": round(t_pass, 3), "total": round(time.perf_counter() - t_start, 3)},
        **group_parts(parts),
        "fingerprint": fingerprint,
    }
