"""Dataset 4 of a session: survey frames of a crop field with gray panels (the target of Eq. 15)."""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence

import cv2
import numpy as np

from ._camera import FRONTAL, Pose, SnapshotCamera, rot
from ._light import LightDrift
from ._render import Render, disk_kernel, render
from ._targets import FieldScene, Panel
from ._truth import FrameSet, SyntheticTruth, expose_frame, exposure_for, session_time

NDVI_RED_NM = 670.0


NDVI_NIR_NM = 803.0


FIELD_LAT_LON = (47.4502, 8.6821)


FIELD_GROUND_ALT_M = 438.0


DEFAULT_PANELS = (
    Panel((-4.5, 0.0), 1.2, 0.05),
    Panel((-1.5, 0.0), 1.2, 0.20),
    Panel((1.5, 0.0), 1.2, 0.50),
    Panel((4.5, 0.0), 1.2, 0.90),
)


def _survey_pose(rng, along_m: float, altitude_m: float) -> tuple[Pose, float, float, float]:
    """Pose of a survey frame about ``along_m`` north of the field centre.

    Height, across-track offset and along-track jitter at random, small roll / pitch (<= 3 deg)
    and yaw. Returns ``(pose, across_m, along_m, height_m)``.
    """
    height = altitude_m + rng.normal(0.0, 0.3)
    cu = rng.uniform(-1.5, 1.5)
    cv_ = along_m + rng.normal(0, 0.2)
    R = (rot([1, 0, 0], np.deg2rad(np.clip(rng.normal(0, 1.2), -3, 3)))
         @ rot([0, 1, 0], np.deg2rad(np.clip(rng.normal(0, 1.2), -3, 3)))
         @ FRONTAL @ rot([0, 0, 1], np.deg2rad(rng.normal(0, 3.0))))
    return Pose.from_matrix(R, -R @ np.array([cu, cv_, height])), cu, cv_, height


def _material_labels(cam: SnapshotCamera, scene: FieldScene, rend: Render, n_panels: int) -> np.ndarray:
    """Label every pure pixel with its material.

    (H, W) int8 material index of every pixel that is pure in every band (0 soil, 1 vegetation,
    2 + p panel p), -1 where mixed.
    """
    h, w = cam.grid_shape
    labels = np.full((h, w), -1, dtype=np.int8)
    # vegetation / soil purity: cover 1 / 0 everywhere within the PSF's reach
    cover = scene.vegetation_cover(rend.sensor_u, rend.sensor_v)
    disk = disk_kernel(rend.reach_px)
    veg_pure = np.all(cam.split_bands(cv2.erode(cover, disk) >= 1.0), axis=0)
    soil_pure = np.all(cam.split_bands(cv2.dilate(cover, disk) <= 0.0), axis=0)
    ground_pure = rend.pure(0)
    labels[ground_pure & soil_pure] = 0
    labels[ground_pure & veg_pure] = 1
    for p in range(n_panels):
        labels[rend.pure(1 + p)] = 2 + p
    return labels


def flight_frames(truth: SyntheticTruth, *, seed: int = 0, n_frames: int = 8,
                  name: str = "field", altitude_m: float = 25.0, spacing_m: float = 1.8,
                  panels: Sequence[Panel] = DEFAULT_PANELS, supersample: int = 3,
                  time_offset_s: float = 1200.0, frame_interval_s: float = 2.0,
                  drift: LightDrift | None = None, clouds: bool = True, irradiance: bool = False,
                  exposure_fraction: tuple[float, float] = (0.72, 0.82)) -> FrameSet:
    """Render nadir-ish survey frames of a crop field with gray panels (target of Eq. 15).

    Frames are taken along a north-going line at ~``altitude_m`` (GSD ~5.7 cm per band-grid
    pixel at 25 m), ``spacing_m`` apart, with small roll/pitch/yaw, so the panel row (v = 0) is
    seen in several frames at different image rows. Light is uniform within a frame,
    ``B = sun_k`` with ``sun_k`` (clouds) unknown to the fit; its colour ``S`` is the one of the
    reflector images. Exposure per frame (auto exposure): brightest pixel at 72-82 %
    (``exposure_fraction``).
    Reflectance: soil and a green crop (rows 0.75 m apart, gaps, weeds; brightness textures that
    scale all bands alike), panels spectrally flat.

    Parameters
    ----------
    truth : SyntheticTruth
        The camera truth (:func:`make_truth`).
    seed : int
        Seed of the dataset (with the truth's, it fixes every random draw).
    n_frames : int
        Number of frames.
    name : str
        Name of the flight (also seeds it).
    altitude_m : float
        Flying height above the ground.
    spacing_m : float
        Distance between frames.
    panels : sequence of Panel
        The gray panels in the field.
    supersample : int
        Supersampling of edge pixels (:func:`render`).
    time_offset_s, frame_interval_s : float
        Frame ``k`` is taken at ``time_offset_s + frame_interval_s k``.
    drift : LightDrift, optional
        The sun is also multiplied by ``drift.level(time)`` and ``S`` by
        ``drift.colour(time)``.
    clouds : bool
        False drops the random per-frame factor 0.75-1.15.
    irradiance : bool
        Write the frame's sun brightness into its ``meta`` as a sun-sensor reading.
    exposure_fraction : tuple of float
        Range of the brightest pixel's share of the DN range (auto exposure); above the
        response's shoulder start it puts the bright panel on the shoulder.

    Returns
    -------
    FrameSet
        ``kind="flight"``; truth: ``rvec``, ``tvec`` (n, 3); ``sun`` (n,); ``reflectance``
        (n, n_bands, H, W) float16: the true reflectance of each pixel's footprint
        (= U(I) / (t V S sun)); ``labels`` (n, H, W) int8: material index (into
        ``material_names``) where the pixel is pure in every band, -1 where mixed;
        ``material_names`` (M,); ``material_reflectance`` (M, n_bands); ``ndvi`` (n, H, W)
        float32 from the 670 / 803 nm bands of ``reflectance``; ``panel_reflectance`` (P,);
        ``panel_centre_m`` (P, 2); ``height_m`` (n,); ``ndvi_bands`` (2,).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    cam = truth.camera
    tag = zlib.crc32(name.encode()) & 0x7FFFFFFF
    rng = np.random.default_rng([seed, 5, tag])
    lat0, lon0 = FIELD_LAT_LON
    red, nir = cam.band_index(NDVI_RED_NM), cam.band_index(NDVI_NIR_NM)
    out = {k: [] for k in ("dn", "t", "rvec", "tvec", "sun", "refl", "labels", "ndvi", "height")}
    meta = []
    scene0 = None
    for k in range(n_frames):
        tau = time_offset_s + frame_interval_s * k
        cloud = rng.uniform(0.75, 1.15)  # drawn in every case: the seeded stream stays the same
        sun = truth.sun_brightness * (cloud if clouds else 1.0)
        S = truth.spectral_factor
        if drift is not None:
            sun *= drift.level(tau)
            S = truth.spectral_factor * drift.colour(tau, cam.wavelengths)
        scene = FieldScene(cam.wavelengths, panels, sun, field_seed=seed)
        scene0 = scene0 or scene
        pose, cu, cv_, height = _survey_pose(rng, (k - 0.5 * (n_frames - 1)) * spacing_m, altitude_m)
        rend = render(cam, pose, scene, supersample=supersample)
        br = rend.light_times_reflectance(scene.reflectance)
        energy = (truth.vignetting * S[:, None, None] * br).astype(np.float32)
        t = exposure_for(truth, float(energy.max()), rng.uniform(*exposure_fraction))
        dn = expose_frame(truth, energy, t, rng)
        refl = br / sun
        labels = _material_labels(cam, scene, rend, len(panels))
        with np.errstate(divide="ignore", invalid="ignore"):
            ndvi = ((refl[nir] - refl[red]) / (refl[nir] + refl[red])).astype(np.float32)
        out["dn"].append(dn)
        out["t"].append(t)
        out["rvec"].append(pose.rvec)
        out["tvec"].append(pose.tvec)
        out["sun"].append(sun)
        out["refl"].append(refl.astype(np.float16))
        out["labels"].append(labels)
        out["ndvi"].append(ndvi)
        out["height"].append(height)
        meta.append({
            "time": session_time(tau),
            "lat": lat0 + cv_ / 111_320.0,
            "lon": lon0 + cu / (111_320.0 * math.cos(math.radians(lat0))),
            "alt_m": FIELD_GROUND_ALT_M + height,
        })
        if irradiance:
            meta[-1]["irradiance"] = float(sun)
    return FrameSet(
        kind="flight", dn=out["dn"], exposure_ms=np.array(out["t"]),
        names=[f"IMG_{i:04d}" for i in range(n_frames)], meta=meta,
        truth={
            "rvec": np.array(out["rvec"]), "tvec": np.array(out["tvec"]),
            "sun": np.array(out["sun"]), "reflectance": np.array(out["refl"]),
            "labels": np.array(out["labels"]), "ndvi": np.array(out["ndvi"]),
            "material_names": np.array(scene0.material_names),
            "material_reflectance": scene0.reflectance,
            "panel_reflectance": np.array([p.reflectance for p in panels]),
            "panel_centre_m": np.array([p.centre_m for p in panels]),
            "height_m": np.array(out["height"]),
            "ndvi_bands": np.array([red, nir]),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )
