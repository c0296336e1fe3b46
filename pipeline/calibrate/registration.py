"""Band co-registration of a session of multi-lens captures: estimate, store, read.

``mscal register CAPTURES... -o CALIB.zarr`` registers every band of each capture to a
reference band (:func:`mscal_core.registration.register_stack`), combines the captures whose
transforms pass the quality thresholds into one session transform per band (coordinate-wise
median of mapped grid points, :func:`mscal_core.homography.combine_homographies`), and
gives captures whose band failed the threshold the session transform for that band, naming
them. The result goes into the calibration store (new variables; stores without them load and
apply as before):

- ``band_transform (band, row3, col3)`` float64: the session homography of each band,
  reference pixels -> band pixels (identity for the reference band);
- ``capture_transform (capture, band, row3, col3)``: each registered capture's own
  transforms (the session's where it fell back), coordinate ``capture`` = capture name
  (``IMG_0001``: the frame name of a one-file-per-band capture);
- ``registration_ecc``, ``registration_inliers``, ``registration_residual_px``
  ``(capture, band)`` and ``registration_fallback (capture, band)`` bool: quality figures;
  ``registration_spread_px (band)``: spread of the captures about the session transform;
- attribute ``registration``: reference band, thresholds, the captures that fell back and why.

The apply pass aligns each frame with its capture's transforms, else the session's
(:func:`frame_transforms`).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import xarray as xr
from mscal_core.errors import CalibrationStoreError, FitError, FrameError, InputError
from mscal_core.homography import centre_reference, combine_homographies, rebase, transform_distance
from mscal_core.registration import BandRegistration, Thresholds, accept, register_stack

from pipeline.ingest.catalog import Camera, load_camera
from pipeline.ingest.grouping import Capture, capture_folder_of, group_captures, read_capture_pixels
from pipeline.storage.store import new_dataset, open_calibration, write_store

log = logging.getLogger(__name__)

REGISTRATION_VARS = (
    "band_transform", "capture_transform", "registration_ecc", "registration_inliers",
    "registration_residual_px", "registration_fallback", "registration_spread_px",
)
# Captures registered per session: the transform of a flight barely changes between captures
# at one altitude, so a dozen spread over the session give the median its robustness (half may
# fail) at a bounded cost (~10-50 s per 5-band 1.2 MP capture on one core).
MAX_CAPTURES = 12


@dataclass(frozen=True)
class CaptureResult:
    """One capture's registration: ``bands`` per band, ``accepted`` whether each passed."""

    name: str
    bands: tuple[BandRegistration, ...]
    accepted: tuple[bool, ...]


@dataclass(frozen=True)
class SessionRegistration:
    """Session transforms (band, 3, 3), reference band, per-capture results (transforms
    rebased onto ``reference``; failed bands replaced by the session's), the fallbacks
    ``[{capture, bands, reason}]`` and the spread per band (px)."""

    reference: int
    transforms: np.ndarray
    captures: tuple[CaptureResult, ...]
    capture_transforms: np.ndarray  # (capture, band, 3, 3)
    fallbacks: tuple[dict, ...]
    spread_px: np.ndarray
    thresholds: Thresholds
    shape: tuple[int, int]


def read_capture(capture: Capture) -> np.ndarray:
    """Band stack ``(band, H, W)`` float32 of one capture's files, as stored (the scale does not
    matter to registration), read as apply reads them
    (:func:`pipeline.ingest.grouping.read_capture_pixels`: TIFF band files, or each band's
    channel of a multi-channel JPEG)."""
    try:
        _, bands, _ = read_capture_pixels(capture)
    except FrameError as exc:
        raise InputError(f"capture {capture.name}: {exc.reason}", path=exc.path, hint=exc.hint) from None
    shapes = {b.shape for b in bands}
    if len(shapes) != 1 or bands[0].ndim != 2:
        raise InputError(f"capture {capture.name}: band files differ in size or are not single-band "
                         f"({', '.join(str(b.shape) for b in bands)})", path=capture.metas[0].path,
                         hint="every band file of a capture must be one image of the same size")
    return np.stack(bands).astype(np.float32)


def spread_captures(captures: Sequence[Capture], limit: int = MAX_CAPTURES) -> list[Capture]:
    """At most ``limit`` captures evenly spread over the list (first and last included)."""
    caps = list(captures)
    if len(caps) <= limit:
        return caps
    idx = np.unique(np.round(np.linspace(0, len(caps) - 1, limit)).astype(int))
    return [caps[i] for i in idx]


def _why(r: BandRegistration, th: Thresholds) -> str:
    parts = []
    if not (np.isfinite(r.ecc) and r.ecc >= th.min_ecc):
        parts.append(f"gradient correlation {r.ecc:.2f} < {th.min_ecc}")
    if r.n_matches >= th.min_inliers and r.n_inliers < th.min_inliers:
        parts.append(f"{r.n_inliers} feature inliers < {th.min_inliers}")
    if r.n_matches >= th.min_inliers and not (np.isfinite(r.residual_px) and r.residual_px <= th.max_residual_px):
        parts.append(f"residual {r.residual_px:.2f} px > {th.max_residual_px}")
    return "; ".join(parts) or "registration failed"


def register_session(stacks: Sequence[tuple[str, np.ndarray]], camera: Camera, *, reference: int | None = None,
                     thresholds: Thresholds = Thresholds(),
                     advance: Callable[[], None] | None = None) -> SessionRegistration:
    """Register ``(name, stack)`` captures and combine them (module docstring).

    The captures are registered to ``reference`` if given, else to the band of median
    wavelength, and then (``reference`` None) rebased onto the band in the middle of the rig
    (:func:`mscal_core.homography.centre_reference`: smallest warps, smallest lost border).
    :class:`FitError` if some band passes the thresholds in no capture."""
    if not stacks:
        raise InputError("no captures to register", hint="give capture folders or band files of the session")
    wl = np.asarray(camera.wavelengths, dtype=np.float64)
    anchor = int(np.argsort(wl)[len(wl) // 2]) if reference is None else int(reference)
    shape = stacks[0][1].shape[1:]
    results: list[CaptureResult] = []
    for name, stack in stacks:
        if stack.shape[0] != camera.n_bands or stack.shape[1:] != shape:
            raise InputError(f"capture {name} is {stack.shape}, expected ({camera.n_bands}, {shape[0]}, {shape[1]})",
                             hint=f"all captures of a session must come from one {camera.name}")
        t0 = time.perf_counter()
        regs = register_stack(stack, anchor, wavelengths=wl, thresholds=thresholds)
        ok = tuple(accept(r, thresholds) for r in regs)
        log.info("registered %s in %.1f s (%d/%d bands pass)", name, time.perf_counter() - t0, sum(ok), len(ok))
        results.append(CaptureResult(name, tuple(regs), ok))
        if advance is not None:  # one step per capture (a progress bar)
            advance()
    session = np.empty((camera.n_bands, 3, 3))
    spread = np.zeros(camera.n_bands)
    for b in range(camera.n_bands):
        good = [c.bands[b].homography for c in results if c.accepted[b]]
        if not good:
            worst = "; ".join(f"{c.name}: {_why(c.bands[b], thresholds)}" for c in results[:3])
            raise FitError(
                f"band {camera.band_names[b]} passes the registration thresholds in none of the {len(results)} capture(s) ({worst})",
                hint="register captures with more texture (a flight over crops or soil, not sky or water), or lower --min-ecc",
            )
        session[b], _ = combine_homographies(good, shape)
    ref = anchor
    if reference is None:
        ref = centre_reference(session, shape)
    own = [rebase(np.stack([c.bands[b].homography if c.accepted[b] else session[b] for b in range(camera.n_bands)]), ref)
           if c.accepted[ref] else None for c in results]
    session = rebase(session, ref)
    per_capture = np.stack([np.stack([o[b] if o is not None and c.accepted[b] else session[b]
                                      for b in range(camera.n_bands)]) for o, c in zip(own, results)])
    for b in range(camera.n_bands):  # spread about the session transform, on the final reference
        d = [np.median(transform_distance(per_capture[k, b], session[b], shape))
             for k, c in enumerate(results) if c.accepted[b]]
        spread[b] = float(np.median(d)) if d else float("nan")
    fallbacks = tuple(
        {"capture": c.name, "bands": [camera.band_names[b] for b in range(camera.n_bands) if not c.accepted[b]],
         "reason": "; ".join(f"{camera.band_names[b]}: {_why(c.bands[b], thresholds)}"
                             for b in range(camera.n_bands) if not c.accepted[b])}
        for c in results if not all(c.accepted)
    )
    for f in fallbacks:
        log.warning("capture %s fell back to the session transform for %s (%s)", f["capture"], ", ".join(f["bands"]), f["reason"])
    return SessionRegistration(ref, session, tuple(results), per_capture, fallbacks, spread, thresholds, tuple(shape))


def registration_dataset(reg: SessionRegistration, camera: Camera) -> xr.Dataset:
    """The registration's variables and ``registration`` attribute (module docstring)."""
    names = [c.name for c in reg.captures]

    def fig(attr: str, dtype: type) -> np.ndarray:
        return np.array([[getattr(r, attr) for r in c.bands] for c in reg.captures], dtype=dtype)

    ds = xr.Dataset(coords={"capture": np.array(names, dtype=object)})
    conv = {"convention": "homography: reference-band pixel (x=column, y=row, homogeneous) -> band pixel; "
                          "aligned_b(x) = band_b(H_b x)", "reference_band": camera.band_names[reg.reference]}
    ds["band_transform"] = (("band", "row3", "col3"), reg.transforms, conv)
    ds["capture_transform"] = (("capture", "band", "row3", "col3"), reg.capture_transforms, conv)
    ds["registration_ecc"] = (("capture", "band"), fig("ecc", np.float64),
                              {"long_name": "gradient correlation after alignment (estimation reference)"})
    ds["registration_inliers"] = (("capture", "band"), fig("n_inliers", np.int64),
                                  {"long_name": "feature matches agreeing within 2 px (weakest pair of the path)"})
    ds["registration_residual_px"] = (("capture", "band"), fig("residual_px", np.float64),
                                      {"long_name": "rms reprojection error of the inliers", "units": "px"})
    ds["registration_fallback"] = (("capture", "band"), ~np.array([c.accepted for c in reg.captures]),
                                   {"long_name": "failed the thresholds: the session transform is used"})
    ds["registration_spread_px"] = (("band",), reg.spread_px,
                                    {"long_name": "median distance of the captures' transforms to the session's", "units": "px"})
    ds.attrs["registration"] = {
        "reference_band": camera.band_names[reg.reference],
        "reference_index": int(reg.reference),
        "shape": list(reg.shape),
        "thresholds": asdict(reg.thresholds),
        "captures": names,
        "fallbacks": [dict(f) for f in reg.fallbacks],
        "paths": {c.name: [[int(x) for x in r.path] for r in c.bands] for c in reg.captures},
    }
    return ds


def with_registration(ds: xr.Dataset, reg: SessionRegistration, camera: Camera) -> xr.Dataset:
    """``ds`` (a calibration dataset) with its registration replaced by ``reg``."""
    ds = ds.drop_vars([v for v in REGISTRATION_VARS if v in ds] + (["capture"] if "capture" in ds.coords else []))
    rd = registration_dataset(reg, camera)
    out = ds.assign_coords(capture=rd["capture"])
    for v in rd.data_vars:
        out[v] = rd[v]
    out.attrs = {**ds.attrs, "registration": rd.attrs["registration"]}
    return out


def frame_transforms(ds: xr.Dataset, name: str) -> np.ndarray | None:
    """Transforms (band, 3, 3) for the frame or capture ``name``: its own if it was registered,
    else the session's; None if the store holds no registration."""
    if "band_transform" not in ds:
        return None
    if "capture_transform" in ds and "capture" in ds.coords:
        names = [str(c) for c in ds["capture"].values]
        if name in names:
            return np.asarray(ds["capture_transform"].values[names.index(name)], dtype=np.float64)
    return np.asarray(ds["band_transform"].values, dtype=np.float64)


def collect_captures(paths: Sequence[Path], camera: Camera) -> tuple[list[Capture], list[dict[str, str]]]:
    """Captures named by folders (every capture in it) or band files (their captures)."""
    captures: dict[str, Capture] = {}
    problems: list[dict[str, str]] = []
    by_folder: dict[Path, set[str] | None] = {}
    for p in paths:
        p = Path(p)
        if p.is_dir():
            by_folder[p] = None
        elif p.is_file():
            wanted = by_folder.setdefault(capture_folder_of(p, camera), set())
            if wanted is not None:
                wanted.add(p.name)
        else:
            raise InputError("capture folder or band file not found", path=p)
    for folder, files in by_folder.items():
        caps, probs = group_captures(folder, camera)
        problems += probs
        for c in caps:
            if files is None or any(m.path.name in files for m in c.metas):
                captures[f"{folder}/{c.name}"] = c
    return sorted(captures.values(), key=lambda c: c.name), problems


@contextmanager
def _no_progress(n: int) -> Iterator[Callable[[], None]]:
    yield lambda: None


def register_cli(paths: Sequence[Path], out: Path, camera_name: str | None, reference: str | None,
                 thresholds: Thresholds = Thresholds(), max_captures: int = MAX_CAPTURES,
                 progress: Callable[[int], Any] | None = None) -> tuple[xr.Dataset, list[dict]]:
    """``mscal register CAPTURES... -o CALIB.zarr``: add the registration to ``out`` (an
    existing calibration store keeps its other variables) or create a store holding only it.
    Returns the dataset written and the captures that could not be used. ``progress(n)``:
    a context manager yielding ``advance`` for ``n`` steps (one per capture read and one per
    capture registered; e.g. :func:`pipeline.run.console.progress` bound to a label)."""
    existing = None
    if Path(out).exists():
        existing = open_calibration(out)
        camera_name = camera_name or str(existing.attrs.get("camera"))
    if not camera_name:  # recognised from the files, as apply does
        from pipeline.ingest.identify import identify_camera

        first = Path(paths[0]) if paths else None
        if first is None or not first.exists():
            raise InputError("capture folder or band file not found", path=first)
        camera_name = identify_camera(first if first.is_dir() else first.parent).camera.name
    camera = load_camera(camera_name)
    if existing is not None:
        existing = open_calibration(out, camera)
    if camera.layout.kind == "mosaic":
        raise InputError(f"camera {camera.name} is a snapshot mosaic: its bands share one lens and need no registration",
                         hint="see 'mscal apply --centre-bands' for the mosaic's sub-pixel band offsets")
    ref_index = None
    if reference is not None:
        if reference not in camera.band_names:
            raise InputError(f"--reference {reference!r} is not a band of {camera.name}",
                             hint=f"bands: {', '.join(camera.band_names)}")
        ref_index = camera.band_names.index(reference)
    captures, problems = collect_captures(paths, camera)
    if not captures:
        why = "; ".join(f"{p['file']}: {p['reason']}" for p in problems[:3])
        raise InputError("no complete captures found" + (f" ({why})" if why else ""), path=paths[0] if paths else None,
                         hint=f"name folders or band files of {camera.name} captures (IMG_XXXX_<band>.tif)")
    chosen = spread_captures(captures, max_captures)
    with (progress or _no_progress)(2 * len(chosen)) as advance:
        stacks = []
        for c in chosen:
            stacks.append((c.name, read_capture(c)))
            advance()
        reg = register_session(stacks, camera, reference=ref_index, thresholds=thresholds, advance=advance)
    base = existing if existing is not None else new_dataset(camera)
    ds = with_registration(base, reg, camera)
    ds.attrs["registration"]["unused_files"] = problems
    ds.attrs["registration"]["registered_of"] = len(captures)
    write_store(ds, out)
    return ds, problems


def check_transforms(ds: xr.Dataset, n_bands: int, shape: tuple[int, int], path: Path) -> None:
    """A store's transforms fit frames of ``shape`` with ``n_bands`` bands."""
    if "band_transform" not in ds:
        return
    if ds["band_transform"].shape != (n_bands, 3, 3):
        raise CalibrationStoreError(f"band_transform is {ds['band_transform'].shape}, expected ({n_bands}, 3, 3)", path=path)
    reg_shape = tuple((ds.attrs.get("registration") or {}).get("shape", shape))
    if reg_shape != tuple(shape):
        raise CalibrationStoreError(
            f"band transforms were estimated on {reg_shape[1]}x{reg_shape[0]} images but frames are {shape[1]}x{shape[0]}",
            path=path, hint="register captures of this camera ('mscal register') or apply with --no-align")


__all__ = [
    "CaptureResult", "SessionRegistration", "check_transforms", "frame_transforms", "read_capture",
    "register_cli", "register_session", "registration_dataset", "spread_captures", "with_registration",
]
