"""The illumination stage (Eq. 11-14): the spectral factor S and the reflector brightness B of
each reflector capture (:mod:`pipeline.calibrate.captures`) from the marker views of
``reflector/``, on the sensor pixels every capture shares; a multi-lens camera's radiance
sampled per lens at the same reflector points; the stage's part of the calibration store
(with each capture's S, level, time and sun-sensor irradiance).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import xarray as xr
from mscal_core import geometry, illumination
from mscal_core.errors import FitError, SessionError

from pipeline.calibrate.bands import energy
from pipeline.calibrate.captures import ReflectorCapture, reflector_captures
from pipeline.calibrate.intrinsics import with_intrinsics
from pipeline.calibrate.stage import StageReport, record_files
from pipeline.calibrate.sweep import read_stack
from pipeline.calibrate.views import (
    FolderFrames,
    View,
    camera_offsets,
    edge_margin,
    exclude_half,
    load_marker_frames,
)
from pipeline.ingest.captures import is_multilens
from pipeline.ingest.catalog import Camera
from pipeline.ingest.session import Session
from pipeline.ingest.sunsensor import SUN_SENSOR_MODEL, SUN_SENSOR_MODEL_ATTR
from pipeline.storage.store import content_hashes

#: A reflector capture needs at least this many reflector pixels for Eq. 11-14.
MIN_REFLECTOR_PIXELS = 100


@dataclass
class CaptureFit:
    """The illumination fit of one reflector capture: which of the result's views are its."""

    capture: ReflectorCapture
    fit: illumination.IlluminationFit
    views: tuple[int, ...]  # indices into IlluminationResult.views
    centre_brightness: float = float("nan")  # B at the reflector centre (plane fit); NaN: one capture
    observed_fraction: float = 1.0  # share of its reflector pixels S was fitted from (V observed there)


@dataclass
class IlluminationResult:
    """The illumination fit and, for the QA report, per reflector image used: its
    brightness map ``B(x)`` on the band grid (NaN off the reflector), its DN in ``qa_band``,
    its effective exposure and file name. ``fit`` is the first capture's (its S is the store's
    ``spectral_factor``); ``captures`` holds every capture's fit."""

    fit: illumination.IlluminationFit
    report: StageReport
    views: list[tuple[int, View]]
    brightness_maps: np.ndarray | None = None  # (image, H, W) float32
    qa_band: int = 0
    qa_dn: np.ndarray | None = None  # (image, H, W) uint16
    exposures: np.ndarray | None = None  # (image,) effective exposure, ms
    captures: list[CaptureFit] = field(default_factory=list)


def qa_band(camera: Camera) -> int:
    """The band the QA report shows images of: the camera's NIR index band (803 nm for the
    Ximea, as in the paper's figures), else the middle band."""
    if "nir" in camera.index_bands:
        return camera.band_for_wavelength(camera.index_bands["nir"])
    return camera.n_bands // 2


def read_reflector_frames(session: Session) -> tuple[list[ReflectorCapture], FolderFrames]:
    """The session's ``reflector/`` frames read (:func:`reflector_captures`), and their captures."""
    folder = session.reflector_dir
    if not folder.is_dir():
        raise SessionError("frame folder not found", path=folder)
    recs, captures = reflector_captures(folder, session.camera)
    return captures, FolderFrames(recs, read_stack(recs, session.camera), content_hashes(record_files(recs), session.root))


def fit_illumination_frames(
    session: Session, inverse_response: np.ndarray, saturation_dn: np.ndarray, vignetting_maps: np.ndarray,
    *, shared_pixels: bool = True, frames: Callable[[], tuple[list[ReflectorCapture], FolderFrames]] | None = None,
    vignetting_observed: np.ndarray | None = None,
) -> IlluminationResult:
    """Eq. 11-14 from the session's ``reflector/`` image(s), per capture (:func:`reflector_captures`):
    S and B of each capture's images under its own light.

    Several captures: with ``shared_pixels`` (default) each is fitted on the sensor pixels
    every capture saw the reflector at (:func:`mscal_core.illumination.shared_reflector_pixels`),
    so an error of the vignetting estimate there biases every capture alike and cancels between
    them (bench/bench_light.py: the capture-to-capture error of S 0.5-0.6 % -> 0.11-0.13 % worst
    band); the fraction of reflector pixels kept is reported as ``shared_pixel_fraction`` (0
    when some capture would keep fewer than :data:`MIN_REFLECTOR_PIXELS`: all pixels are used,
    and the QA report warns). ``frames``: gives :func:`read_reflector_frames` already read.

    ``vignetting_observed`` (band, y, x) bool, the vignetting fit's ``observed``: on a band-grid
    camera S is fitted from the reflector pixels where every band's V was observed, not filled,
    when each image of the capture has :data:`MIN_REFLECTOR_PIXELS` of them (else from all);
    B, each image's brightness and the residual are still over every reflector pixel (Eq. 14
    with that S). A filled V is a radial model extrapolated from the views: its error at the
    reflector would go into S band by band (a session of 6 usable views, 13 % of the grid
    observed: S 2.5 % off from every pixel), while on observed pixels V's error is the one the
    flight's pixels share. The share of pixels S came from is ``spectral_factor_pixel_fraction``."""
    t0 = time.perf_counter()
    camera = session.camera
    report = StageReport("illumination")
    session, _ = with_intrinsics(session)
    folder = session.reflector_dir
    captures, read = frames() if frames is not None else read_reflector_frames(session)
    recs, stack, views = load_marker_frames(session, folder, inverse_response, report, frames=read)
    rho = session.reflector.reflectance.at(camera.wavelengths)
    shape = stack.shape[2:]
    columns, plane = [], []
    n_sat = np.zeros(camera.n_bands, dtype=np.int64)
    lens_rad: list[np.ndarray] = []
    if is_multilens(camera):
        views, uvs, masks, lens_rad = _lens_radiance(session, stack, views, inverse_response, saturation_dn,
                                                     vignetting_maps, qa_band(camera), report, n_sat)
        lens_masks = list(masks)
    else:
        centre = tuple(camera_offsets(camera).mean(axis=0))
        rays = geometry.pixel_rays(session.intrinsics, shape, centre)
        uvs = [geometry.pixels_to_plane(view.pose, session.intrinsics, shape, rays=rays) for _, view in views]
        masks = [geometry.reflector_mask(uv, session.reflector.size_m, exclude_half(session), edge_margin(session))
                 for uv in uvs]
    shared_fraction = None
    if len(captures) > 1 and shared_pixels:
        # compare the captures' light on the same sensor pixels: a vignetting error there is
        # then common to every capture and cancels between them (shared_reflector_pixels)
        owner = [next(c for c, cap in enumerate(captures) if i in cap.frames) for i, _ in views]
        before = sum(int(m.sum()) for m in masks)
        masks, shared = illumination.shared_reflector_pixels(masks, owner, MIN_REFLECTOR_PIXELS)
        shared_fraction = sum(int(m.sum()) for m in masks) / max(before, 1) if shared else 0.0
    seen = None
    if vignetting_observed is not None and not lens_rad:
        seen = np.asarray(vignetting_observed, dtype=bool).all(axis=0)
    observed = [None if seen is None else seen[m] for m in masks]
    for k, (i, view) in enumerate(views):
        uv, mask = uvs[k], masks[k]
        if lens_rad:  # sampled per lens on the reference band's pixels; keep those still in the mask
            columns.append(lens_rad[k][:, mask[lens_masks[k]]])
            plane.append(uv[mask] if len(captures) > 1 else None)
            continue
        rad = np.empty((camera.n_bands, int(mask.sum())), dtype=np.float64)
        for b in range(camera.n_bands):
            t = view.record.band_exposure(b)
            dn = stack[i, b][mask]
            n_sat[b] += int(np.count_nonzero(dn >= saturation_dn[b]))
            e = energy(dn, inverse_response[b], t, int(saturation_dn[b]))
            with np.errstate(divide="ignore", invalid="ignore"):
                rad[b] = e / vignetting_maps[b][mask]
        columns.append(rad)
        plane.append(uv[mask] if len(captures) > 1 else None)
    n_pixels = sum(c.shape[1] for c in columns)
    maps = np.full((len(views), *shape), np.nan, dtype=np.float32)
    image_brightness = np.full(len(views), np.nan)
    fits = [_fit_capture(cap, captures, views, columns, masks, plane, rho, folder, session, maps, image_brightness,
                         observed) for cap in captures]
    poses = report.residuals.get("marker_poses")
    report.residuals = _illumination_residuals(views, masks, fits, image_brightness, n_sat, n_pixels, shared_fraction)
    if poses is not None:
        report.residuals["marker_poses"] = poses
    report.seconds = time.perf_counter() - t0
    qb = qa_band(camera)
    return IlluminationResult(
        fits[0].fit, report, views, brightness_maps=maps, qa_band=qb,
        qa_dn=np.stack([stack[i, qb] for i, _ in views]),
        exposures=np.array([v.record.band_exposure(qb) for _, v in views]),
        captures=fits,
    )


def _illumination_residuals(views: list[tuple[int, View]], masks: list[np.ndarray], fits: list["CaptureFit"],
                            image_brightness: np.ndarray, n_sat: np.ndarray, n_pixels: int,
                            shared_fraction: float | None) -> dict[str, Any]:
    """The illumination stage's fit numbers for the store and the QA report."""
    out = {
        "images_used": len(views),
        "reflector_pixels": int(n_pixels),
        "reflector_pixels_per_image": [int(m.sum()) for m in masks],
        "residual_rms": round(float(max(f.fit.residual_rms for f in fits)), 5),
        "image_brightness": [round(float(v), 5) for v in image_brightness],
        "saturated_fraction": [round(float(v), 6) for v in n_sat / max(n_pixels, 1)],
        "spectral_factor_pixel_fraction": round(float(min(f.observed_fraction for f in fits)), 4),
    }
    if shared_fraction is not None:
        # 0.0: the captures barely overlap on the sensor, each was fitted on all its pixels
        out["shared_pixel_fraction"] = round(float(shared_fraction), 4)
    if len(fits) > 1:
        out["captures"] = [
            {"name": f.capture.name, "images": len(f.views), "residual_rms": round(float(f.fit.residual_rms), 5),
             "irradiance": f.capture.irradiance, "irradiance_source": list(f.capture.irradiance_source),
             "centre_brightness": round(f.centre_brightness, 5)}
            for f in fits
        ]
    return out


def _fit_capture(cap: Any, captures: Sequence[Any], views: list[tuple[int, View]], columns: list[np.ndarray],
                 masks: list[np.ndarray], plane: list[np.ndarray | None], rho: np.ndarray, folder: Path,
                 session: Session, maps: np.ndarray, image_brightness: np.ndarray,
                 observed: Sequence[np.ndarray | None]) -> "CaptureFit":
    """Eq. 11-14 on one reflector capture's images: its S and B; B written into ``maps`` and
    each image's brightness into ``image_brightness`` (the images' rows of both); with several
    captures, the light's level at the reflector centre for comparing them. S from the pixels
    ``observed`` marks (per view, over its mask's pixels; None: all) when every image has
    :data:`MIN_REFLECTOR_PIXELS` of them."""
    mine = [k for k, (i, _) in enumerate(views) if i in set(cap.frames)]
    where = folder if len(captures) == 1 else cap.folder
    label = "" if len(captures) == 1 else f"capture {cap.name}: "
    if not mine:
        raise FitError(
            f"{label}{session.marker.label} was not found in any of its "
            f"{len(cap.frames)} frames",
            path=where,
            hint="check that the marker is in view and sharp, or remove the capture",
        )
    radiance = np.concatenate([columns[k] for k in mine], axis=1)
    if radiance.shape[1] < MIN_REFLECTOR_PIXELS:
        raise FitError(
            f"{label}only {radiance.shape[1]} reflector pixels found",
            path=where,
            hint="take the reflector image closer, or check reflector.size_m in session.yaml",
        )
    image_index = np.concatenate([np.full(columns[k].shape[1], j) for j, k in enumerate(mine)])
    fit_pixels = None
    if all(observed[k] is not None and int(observed[k].sum()) >= MIN_REFLECTOR_PIXELS for k in mine):
        fit_pixels = np.concatenate([observed[k] for k in mine])
    fit = illumination.fit_illumination(radiance, rho, image_index=image_index, fit_pixels=fit_pixels)
    fraction = 1.0 if fit_pixels is None else float(np.mean(fit_pixels))
    start = 0
    for j, k in enumerate(mine):
        n = int(masks[k].sum())
        maps[k][masks[k]] = fit.brightness[start:start + n]
        start += n
        if fit.image_brightness is not None:
            image_brightness[k] = fit.image_brightness[j]
    centre = float("nan")
    if len(captures) > 1:  # the light's level at the reflector centre, for comparing captures
        start = 0
        per_image = []
        for k in mine:
            n = int(masks[k].sum())
            per_image.append(illumination.centre_brightness(plane[k], fit.brightness[start:start + n]))
            start += n
        centre = float(np.nanmedian(per_image)) if np.isfinite(per_image).any() else 1.0
    return CaptureFit(cap, fit, tuple(mine), centre, fraction)


def _lens_radiance(session: Session, stack: np.ndarray, views: list[tuple[int, View]], inverse_response: np.ndarray,
                   saturation_dn: np.ndarray, vignetting_maps: np.ndarray, ref: int, report: StageReport,
                   n_sat: np.ndarray) -> tuple[list[tuple[int, View]], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Eq. 11-14 of a multi-lens camera needs every band's radiance at the same reflector
    point, but each lens sees the reflector at its own pixels. The reflector points are those
    seen by band ``ref``'s pixels (its own marker pose); each is projected into every other
    band with that lens's pose and intrinsics (``pi_i`` of Eq. 8), where ``U(I) / (t V)`` is
    sampled bilinearly. A point counts only where every band saw reflector there (inside its
    own reflector mask, not saturated). Views without a pose in every band are skipped.

    Returns the views used, per view the plane points (H, W, 2) and the mask on ``ref``'s
    grid, and the radiance (band, mask pixels) in the mask's row-major order."""
    import cv2

    camera = session.camera
    shape = stack.shape[2:]
    size, excl, edge = session.reflector.size_m, exclude_half(session), edge_margin(session)
    rays = [geometry.pixel_rays(session.intrinsics_for(b), shape) for b in range(camera.n_bands)]
    kept, uvs, masks, rads = [], [], [], []
    for i, view in views:
        if any(view.pose_for(b) is None for b in range(camera.n_bands)):
            report.skipped.append({"file": view.record.name,
                                   "reason": "marker not found in every band: not usable for Eq. 11-14"})
            continue
        uv = geometry.pixels_to_plane(view.pose_for(ref), session.intrinsics_for(ref), shape, rays=rays[ref])
        mask = geometry.reflector_mask(uv, size, excl, edge)
        pts = uv[mask]
        rad = np.empty((camera.n_bands, pts.shape[0]), dtype=np.float64)
        ok = np.ones(pts.shape[0], dtype=bool)
        for b in range(camera.n_bands):
            t = view.record.band_exposure(b)
            dn = stack[i, b]
            e_img = energy(dn, inverse_response[b], t, int(saturation_dn[b]))
            own = geometry.reflector_mask(geometry.pixels_to_plane(view.pose_for(b), session.intrinsics_for(b), shape,
                                                                   rays=rays[b]), size, excl, edge)
            n_sat[b] += int(np.count_nonzero(dn[own] >= saturation_dn[b]))
            valid = (own & np.isfinite(e_img)).astype(np.float32)
            if b == ref:
                xy = np.argwhere(mask)[:, ::-1].astype(np.float32)
            else:
                xy = geometry.project_to_pixels(pts, view.pose_for(b), session.intrinsics_for(b)).astype(np.float32)
            n = xy.shape[0]
            width = 1024  # remap's maps must stay below 32767 on each side
            pad = (-n) % width
            mx = np.pad(xy[:, 0], (0, pad), constant_values=-1e6).reshape(-1, width)
            my = np.pad(xy[:, 1], (0, pad), constant_values=-1e6).reshape(-1, width)

            def sample(img: np.ndarray) -> np.ndarray:
                return cv2.remap(np.ascontiguousarray(img, dtype=np.float32), mx, my, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0.0).ravel()[:n]

            ok &= sample(valid) > 0.999
            e = sample(np.nan_to_num(e_img, nan=0.0))
            v = sample(vignetting_maps[b])
            with np.errstate(divide="ignore", invalid="ignore"):
                rad[b] = e / v
        ok &= np.all(np.isfinite(rad), axis=0)
        m2 = mask.copy()
        m2[mask] = ok
        kept.append((i, view))
        uvs.append(uv)
        masks.append(m2)
        rads.append(rad[:, ok])
    if not kept:
        raise FitError("no reflector image has the marker in every band", path=session.reflector_dir,
                       hint="frame the marker so that every lens sees it")
    return kept, uvs, masks, rads


def add_illumination(ds: xr.Dataset, result: IlluminationResult) -> xr.Dataset:
    ds = ds.copy()
    ds["spectral_factor"] = (
        "band",
        np.asarray(result.fit.spectral_factor, dtype=np.float64),
        {"long_name": "spectral factor S (Eq. 11-14); reflector brightness B has median 1"
                      + ("; of the first reflector capture (capture_spectral_factor: every capture)"
                         if len(result.captures) > 1 else "")},
    )
    if result.brightness_maps is not None and result.qa_dn is not None:
        # For the QA report: B(x) of each reflector image and its DN in one band,
        # so the report can show Eq. 15 beside the Eq. 16 baseline without the session.
        ds = ds.assign_coords(
            reflector_image=np.arange(len(result.views)),
            reflector_file=("reflector_image", np.array([v.record.path.name for _, v in result.views], dtype=object)),
            reflector_exposure_ms=("reflector_image", np.asarray(result.exposures, dtype=np.float64),
                                   {"long_name": "effective exposure (exposure_ms x gain)"}),
        )
        ds["reflector_brightness"] = (
            ("reflector_image", "y", "x"), result.brightness_maps.astype(np.float32),
            {"long_name": "reflector brightness B(x) (Eq. 11-14), median 1; NaN off the reflector"},
        )
        ds["reflector_dn"] = (
            ("reflector_image", "y", "x"), result.qa_dn.astype(np.uint16),
            {"long_name": "reflector image DN in one band (QA report)", "band": int(result.qa_band)},
        )
    if result.captures:
        ds = add_captures(ds, result)
    ds.attrs["illumination"] = result.report.as_attrs()
    return ds


def add_captures(ds: xr.Dataset, result: IlluminationResult) -> xr.Dataset:
    """Per reflector capture: its S, brightness level, time and irradiance, on a
    ``capture`` dimension, and which capture each reflector image belongs to."""
    caps = result.captures
    s = np.stack([np.asarray(c.fit.spectral_factor, dtype=np.float64) for c in caps])
    if len(caps) > 1:
        # Each fit's S has its own gauge (median B = 1 over the pixels that capture saw); the
        # light of capture c is S_c times its reflector-centre brightness, relative to the
        # first capture's so that capture 0 keeps the store's S (illumination.centre_brightness).
        centre = np.array([c.centre_brightness for c in caps])
        s = s * (centre / centre[0])[:, None]
    level, _ = illumination.split_level(s)
    times = np.array([np.datetime64(int(round(c.capture.time_s * 1e9)), "ns") if np.isfinite(c.capture.time_s)
                      else np.datetime64("NaT", "ns") for c in caps], dtype="datetime64[ns]")
    ds = ds.assign_coords(
        capture=np.arange(len(caps)),
        capture_name=("capture", np.array([c.capture.name for c in caps], dtype=object)),
        capture_time=("capture", times, {"long_name": "mean time of the capture's frames (UTC)"}),
    )
    ds["capture_spectral_factor"] = (
        ("capture", "band"), s, {"long_name": "spectral factor S of each reflector capture (Eq. 11-14): the light at "
                                              "the reflector centre, in the gauge of the first capture's S"},
    )
    ds["capture_level"] = (
        "capture", np.asarray(level, dtype=np.float64),
        {"long_name": "brightness level of each capture: geometric mean of its S over the bands"},
    )
    ds["capture_irradiance"] = (
        "capture", np.array([np.nan if c.capture.irradiance is None else c.capture.irradiance for c in caps]),
        {"long_name": "median sun-sensor level of the capture's frames (NaN: none): horizontal irradiance, "
                      "geometric mean over the bands, or frames.csv irradiance as given",
         # apply makes the flight's levels alike only for stores that say so
         SUN_SENSOR_MODEL_ATTR: SUN_SENSOR_MODEL},
    )
    if "reflector_image" in ds.coords:
        owner = np.zeros(ds.sizes["reflector_image"], dtype=np.int32)
        for c, cf in enumerate(caps):
            owner[list(cf.views)] = c
        ds = ds.assign_coords(reflector_capture=("reflector_image", owner))
    return ds
