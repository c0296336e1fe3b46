"""Write a complete synthetic session folder (SPEC.md layout) from the seeded forward model.

``write_session(path)`` renders every dataset with :mod:`pipeline.sim.world.scene` (camera,
targets, light) and :mod:`pipeline.sim.world.sensor` (response and noise), then writes::

    path/
      session.yaml            camera, intrinsics, reflector, marker (+ border_m), name, notes
      response/    sweep_00.tif ...      + frames.csv   exposure sweep of a static scene
      vignetting/  view_00.tif ...       + frames.csv   reflector + marker, many viewpoints
      reflector/   reflector_0.tif ...   + frames.csv   reflector under the flight's light
      flights/<name>/ IMG_0000.tif ...   + frames.csv   survey frames (with lat/lon/alt_m)
      truth.npz               true U, V, S, B, poses, flight reflectance (see below)

Frames are single-channel 16-bit TIFFs of the raw 2048 x 1088 mosaic, DN (10 bit) in the low
bits. ``frames.csv`` columns: ``file,exposure_ms,gain,time,lat,lon,alt_m`` (gain 1, time ISO
8601 UTC; lat/lon/alt_m only for flight frames, empty otherwise).

``truth.npz`` holds :meth:`pipeline.sim.world.scene.SyntheticSession.truth_arrays`: camera truth
(``inverse_response`` (25, 1024), ``vignetting`` (25, 217, 409), ``spectral_factor`` (25,),
``wavelength_nm``, ``reflector_reflectance``, ...) and per dataset its truth with the prefixes
``response_``, ``vignetting_``, ``reflector_``, ``flight_<name>_``. Units: ``U_true(I) = t E``
with ``E = V S B R`` (linear DN per ms), see the scene module.
"""

from __future__ import annotations

import csv
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import tifffile
import yaml

from pipeline.sim.world.scene import (
    CharucoBoardSpec,
    FrameSet,
    LightDrift,
    SyntheticSession,
    flight_frames,
    make_truth,
    reflector_images,
    synthesize_session,
)

__all__ = ["write_session", "write_frameset", "session_yaml", "write_orthomosaic", "write_light_drift"]

FRAMES_CSV_COLUMNS = ("file", "exposure_ms", "gain", "time", "lat", "lon", "alt_m")


def session_yaml(session: SyntheticSession) -> dict:
    """The ``session.yaml`` mapping of a synthetic session."""
    t = session.truth
    cam = t.camera
    rho = np.asarray(t.reflector_reflectance, dtype=float)
    if np.allclose(rho, rho[0]):
        reflectance: float | list = float(rho[0])
    else:
        order = np.argsort(cam.wavelengths)
        reflectance = [[float(cam.wavelengths[i]), float(rho[i])] for i in order]
    return {
        "camera": cam.name,
        "name": f"synthetic-seed{t.seed}-{session.size}",
        "notes": (
            f"synthetic session (pipeline.sim.synth, seed={t.seed}, size={session.size}); "
            "ground truth in truth.npz"
        ),
        "intrinsics": cam.intrinsics_dict(),
        "reflector": {
            "reflectance": reflectance,
            "size_m": [float(t.reflector_size_m[0]), float(t.reflector_size_m[1])],
        },
        "marker": marker_yaml(t.marker),
    }


def marker_yaml(marker) -> dict:
    """session.yaml ``marker`` of the truth's marker: ``{dictionary, id, size_m, border_m}``,
    or for a :class:`~pipeline.sim.world.scene.CharucoBoardSpec` ``{type: charuco, squares_x,
    squares_y, square_mm, marker_mm, dictionary, border_mm}`` (the board centred on the
    reflector, as ``pipeline.ingest.markers`` reads it)."""
    if isinstance(marker, CharucoBoardSpec):
        return {
            "type": "charuco",
            "squares_x": int(marker.squares_x),
            "squares_y": int(marker.squares_y),
            "square_mm": round(float(marker.square_m) * 1000, 6),
            "marker_mm": round(float(marker.marker_m) * 1000, 6),
            "dictionary": marker.dictionary,
            "border_mm": round(float(marker.border_m) * 1000, 6),
        }
    return {
        "dictionary": marker.dictionary,
        "id": int(marker.id),
        "size_m": float(marker.size_m),
        "border_m": float(marker.border_m),
    }


def _fmt(value, digits: int) -> str:
    return "" if value is None else f"{float(value):.{digits}f}"


def write_frameset(folder: Path, frames: FrameSet) -> list[Path]:
    """Write the raw mosaics of ``frames`` as TIFFs plus ``frames.csv`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    rows = []
    for k, name in enumerate(frames.names):
        fname = f"{name}.tif"
        p = folder / fname
        tifffile.imwrite(p, frames.raw(k), photometric="minisblack")
        paths.append(p)
        meta = frames.meta[k]
        rows.append({
            "file": fname,
            "exposure_ms": repr(float(frames.exposure_ms[k])),
            "gain": "1",
            "time": meta.get("time", ""),
            "lat": _fmt(meta.get("lat"), 8),
            "lon": _fmt(meta.get("lon"), 8),
            "alt_m": _fmt(meta.get("alt_m"), 3),
        })
    columns = FRAMES_CSV_COLUMNS
    if any("irradiance" in m for m in frames.meta):  # a sun sensor; otherwise no column
        columns = (*FRAMES_CSV_COLUMNS, "irradiance")
        for row, meta in zip(rows, frames.meta):
            row["irradiance"] = _fmt(meta.get("irradiance"), 6)
    with open(folder / "frames.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    return paths


def write_session(
    path: str | Path,
    *,
    seed: int = 0,
    size: str = "full",
    n_flight_frames: int | None = None,
    flights: Sequence[str] = ("field",),
    reflector_reflectance: float | Sequence[float] = 0.5,
    overwrite: bool = True,
    marker: str | CharucoBoardSpec = "aruco",
) -> Path:
    """Render and write a synthetic session folder; returns its path.

    ``size="full"``: 14-frame sweep (x1.66), 40 viewpoints (2 with the marker out of frame),
    3 reflector images, 8 frames per flight. ``size="small"``: 7-frame sweep (x3), 8
    viewpoints (1 without marker), 2 reflector images, 3 frames per flight.
    ``n_flight_frames`` overrides the flight length. With ``overwrite`` (default) the dataset
    folders of an existing session at ``path`` are replaced; otherwise an existing
    ``session.yaml`` there is an error. ``marker="charuco"`` (or a ``CharucoBoardSpec``) puts
    a ChArUco board (default 4 x 4 squares of 60 mm) at the reflector's centre in place of the
    ArUco marker and writes its ``marker: {type: charuco, ...}`` block.
    """
    root = Path(path)
    board = session_marker(marker)
    if (root / "session.yaml").exists() and not overwrite:
        raise FileExistsError(f"{root}: a session is already there (pass overwrite=True)")
    session = synthesize_session(seed, size=size, n_flight_frames=n_flight_frames,
                                 flights=tuple(flights),
                                 reflector_reflectance=reflector_reflectance, marker=board)
    return write_synthesized(session, root)


def session_marker(marker: str | CharucoBoardSpec) -> CharucoBoardSpec | None:
    """The board of ``marker`` (``"aruco"``: None, the default marker; ``"charuco"``: the
    default board; a ``CharucoBoardSpec``: itself)."""
    if isinstance(marker, CharucoBoardSpec):
        return marker
    if marker == "aruco":
        return None
    if marker == "charuco":
        return CharucoBoardSpec()
    raise ValueError(f"marker must be 'aruco', 'charuco' or a CharucoBoardSpec, got {marker!r}")


def write_synthesized(session: SyntheticSession, root: Path) -> Path:
    """Write an already synthesized session into the folder ``root`` (its dataset folders
    replaced): ``session.yaml``, the frame sets with their ``frames.csv``, ``truth.npz``."""
    root.mkdir(parents=True, exist_ok=True)
    for sub in ("response", "vignetting", "reflector", "flights"):
        if (root / sub).exists():
            shutil.rmtree(root / sub)
    with open(root / "session.yaml", "w") as fh:
        yaml.safe_dump(session_yaml(session), fh, sort_keys=False)
    write_frameset(root / "response", session.response)
    write_frameset(root / "vignetting", session.vignetting)
    write_frameset(root / "reflector", session.reflector)
    for name, fs in session.flights.items():
        write_frameset(root / "flights" / name, fs)
    np.savez_compressed(root / "truth.npz", **session.truth_arrays())
    return root


# --------------------------------------------------------------------------- orthomosaics


def write_orthomosaic(path: str | Path, ndvi: np.ndarray, *, crs: str, transform: Sequence[float],
                      invalid: np.ndarray | None = None, seed: int = 0, block: int | None = 256,
                      date: str | None = None, compress: str | None = None, dtype: str = "float32") -> Path:
    """A two-band float32 reflectance orthomosaic (``Red``, ``NIR``, NaN nodata) whose NDVI is
    ``ndvi`` (float64, ``(H, W)``, in [-0.9, 0.9]) up to float32 rounding.

    Red is drawn uniformly in [0.03, 0.20] (seeded); ``NIR = Red (1 + NDVI) / (1 - NDVI)``.
    ``invalid`` (bool ``(H, W)``) pixels are NaN in both bands. ``transform`` is a GDAL-order
    affine ``(a, b, c, d, e, f)``: ``x = a col + b row + c``, ``y = d col + e row + f``.
    ``block``: tile side (None: strips). ``date`` (YYYY-MM-DD) goes to ``TIFFTAG_DATETIME``.
    ``dtype="uint16"`` stores reflectance x 32768 with nodata 65535 (``pipeline.products.writers``'
    convention) instead of float32 with NaN (reflectance above 65534 / 32768 ~ 2 is clipped:
    keep NDVI <= 0.8 there).
    """
    import rasterio
    from affine import Affine

    ndvi = np.asarray(ndvi, dtype=np.float64)
    if np.nanmax(np.abs(ndvi)) > 0.9:
        raise ValueError("ndvi must be within [-0.9, 0.9]")
    rng = np.random.default_rng(seed)
    red = rng.uniform(0.03, 0.20, size=ndvi.shape)
    nir = red * (1.0 + ndvi) / (1.0 - ndvi)
    if dtype == "uint16":
        data = np.clip(np.rint(np.stack([red, nir]) * 32768.0), 0, 65534).astype(np.uint16)
        nodata: float = 65535
    elif dtype == "float32":
        data = np.stack([red, nir]).astype(np.float32)
        nodata = float("nan")
    else:
        raise ValueError(f"dtype {dtype!r}: float32 or uint16")
    if invalid is not None:
        data[:, invalid] = nodata
    h, w = ndvi.shape
    profile: dict = {"driver": "GTiff", "height": h, "width": w, "count": 2, "dtype": dtype,
                     "nodata": nodata, "crs": crs, "transform": Affine(*transform)}
    if block:
        profile.update(tiled=True, blockxsize=block, blockysize=block)
    if compress:
        profile["compress"] = compress
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
        dst.set_band_description(1, "Red")
        dst.set_band_description(2, "NIR")
        if date:
            dst.update_tags(TIFFTAG_DATETIME=date.replace("-", ":") + " 12:00:00")
    return path
def write_light_drift(
    path: str | Path,
    drift: LightDrift,
    *,
    seed: int = 0,
    capture_times_s: Sequence[float] = (1100.0, 3100.0),
    images_per_capture: int = 1,
    flights: dict[str, dict] | None = None,
    subfolders: bool = True,
    gradient_ratio: float = 2.0,
) -> dict[str, FrameSet]:
    """A session folder whose light drifts over the flight: ``session.yaml``,
    ``reflector/`` with one capture per time in ``capture_times_s`` (seconds after the
    session start; subfolders ``capture_0/``, ... or, with ``subfolders=False``, all frames in
    ``reflector/`` told apart by their times), each frame with a sun-sensor ``irradiance``,
    and ``flights/<name>/`` for each entry of ``flights`` (keyword arguments of
    :func:`pipeline.sim.world.scene.flight_frames`, e.g. ``n_frames``, ``time_offset_s``,
    ``frame_interval_s``, ``clouds``, ``irradiance``; default one 3-frame flight ``drift``
    from 1200 s every 900 s without clouds).

    The camera truth is ``make_truth(seed)``, as in :func:`write_session` with the same seed,
    so the response and vignetting of that session's calibration apply (``mscal fit
    illumination PATH --calibration CALIB``). Returns the flights' frame sets (with truth).
    """
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    truth = make_truth(seed)
    fake = SyntheticSession(truth=truth, response=None, vignetting=None, reflector=None, size="drift")  # type: ignore[arg-type]
    with open(root / "session.yaml", "w") as fh:
        yaml.safe_dump(session_yaml(fake), fh, sort_keys=False)
    if (root / "reflector").exists():
        shutil.rmtree(root / "reflector")
    captures = [
        reflector_images(truth, seed=seed + 101 * (c + 1), n_images=images_per_capture,
                         times_s=[t + 20.0 * i for i in range(images_per_capture)], drift=drift,
                         irradiance=True, name_prefix=f"capture{c}_", gradient_ratio=gradient_ratio)
        for c, t in enumerate(capture_times_s)
    ]
    if subfolders:
        for c, fs in enumerate(captures):
            write_frameset(root / "reflector" / f"capture_{c}", fs)
    else:
        write_frameset(root / "reflector", FrameSet(
            kind="reflector", dn=[d for fs in captures for d in fs.dn],
            exposure_ms=np.concatenate([fs.exposure_ms for fs in captures]),
            names=[n for fs in captures for n in fs.names], meta=[m for fs in captures for m in fs.meta],
            truth={}, camera=truth.camera, black_level=captures[0].black_level))
    flights = flights if flights is not None else {
        "drift": dict(n_frames=3, time_offset_s=1200.0, frame_interval_s=900.0, clouds=False)}
    out: dict[str, FrameSet] = {}
    for name, kw in flights.items():
        fs = flight_frames(truth, seed=seed, name=name, drift=drift, **kw)
        if (root / "flights" / name).exists():
            shutil.rmtree(root / "flights" / name)
        write_frameset(root / "flights" / name, fs)
        out[name] = fs
    return out

