"""Seeded synthetic calibration session of a multi-lens camera, with known truth.

One lens and sensor per band, MicaSense RedEdge-like. Pure arrays, no I/O
(``pipeline/sim/multilens.py`` writes the band files).

Each lens is its own camera (the paper fits "each band as its own camera"):

- geometry: its own distorted pinhole (focal length, principal point and OpenCV distortion
  drawn around RedEdge's published values, scaled to the image size) and its own pose in the
  rig (a few centimetres of offset and up to ~0.7 deg of rotation from the reference lens), so
  the marker is seen from a slightly different point, at a different place, by every band;
- sensor: its own :class:`~pipeline.sim.world.sensor.SensorModel` (12 bit, black level 250-330
  DN, mild non-linearity, a soft shoulder from 82-90 % of range, shot + read noise);
- optics: its own off-centre radial vignetting (corner falloff 35-45 %, centre off the
  principal point by up to 4 % of the image);
- filter: its own spectral factor ``S`` (1.5-2.5, also absorbing the lens's gain);
- exposure: each lens exposes on its own (auto exposure per lens, as MicaSense does), except
  in the response sweep (one manual exposure for all).

Scenes and light come from :mod:`pipeline.sim.world.scene` (the gray reflector with its ArUco
marker on a lawn, non-uniform light with a gradient and a soft shadow, gray panels on a
field), rendered by :func:`~pipeline.sim.world.scene.render` through each lens as a one-band
camera. Units as in the scene module: ``E = V S B R`` in linear DN per ms of each lens's own
``U`` gauge (``U(k_ref) = k_ref - black``), so ``U_true(I) = t E`` up to noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .scene import (
    FRONTAL,
    FieldScene,
    MarkerSpec,
    Panel,
    PeriodicNoise,
    Pose,
    ReflectorScene,
    SnapshotCamera,
    detect_marker_corners,
    pose_through,
    random_light,
    random_tilt,
    render,
    rot,
)
from .sensor import SensorModel

#: MicaSense RedEdge bands in file order: name, centre wavelength (nm), FWHM (nm), file suffix.
REDEDGE_BANDS = (("Blue", 475.0, 20.0, "1"), ("Green", 560.0, 20.0, "2"), ("Red", 668.0, 10.0, "3"),
                 ("NIR", 840.0, 40.0, "4"), ("Red edge", 717.0, 10.0, "5"))
#: RedEdge's full frame and its focal length there (pixels; the sample files' XMP ~1441-1452).
REDEDGE_SHAPE = (960, 1280)
REDEDGE_FOCAL_PX = 1447.0
#: Pixels per mm of the RedEdge sensor (EXIF FocalPlaneXResolution: 3.75 um pixels).
REDEDGE_PX_PER_MM = 266.666667
#: Gray panels of the validation captures (Eq. 15 check): centre (m), side (m), reflectance.
CHECK_PANELS = (Panel((-1.35, 0.0), 0.6, 0.05), Panel((-0.45, 0.0), 0.6, 0.20),
                Panel((0.45, 0.0), 0.6, 0.50), Panel((1.35, 0.0), 0.6, 0.90))


@dataclass(frozen=True)
class Lens:
    """One lens of the rig.

    ``camera`` a one-band pinhole (``pattern_shape`` (1, 1)), its sensor, its pose in the rig
    (``X_lens = rig_R X_ref + rig_t``), vignetting ``(H, W)`` max 1 and spectral factor.
    """

    name: str
    camera: SnapshotCamera
    sensor: SensorModel
    rig_R: np.ndarray
    rig_t: np.ndarray
    vignetting: np.ndarray
    vignetting_centre: np.ndarray
    spectral_factor: float

    def pose(self, ref: Pose) -> Pose:
        """Return this lens's marker pose when the reference lens sees the marker at ``ref``."""
        return Pose.from_matrix(self.rig_R @ ref.R, self.rig_R @ np.asarray(ref.tvec) + self.rig_t)

    @property
    def gauge(self) -> float:
        """``a`` with ``U_true(C(x)) = a x`` (the sensor's energy in this lens's U gauge)."""
        k = self.sensor.k_ref
        return float(self.sensor.inverse_response()[k] / float(self.sensor.x_for_dn(k)))

    def expose(self, energy: np.ndarray, t_ms: float, rng: np.random.Generator) -> np.ndarray:
        """Return one noisy uint16 frame of energy rate ``energy`` (this lens's U gauge) exposed ``t_ms`` ms."""
        return self.sensor.expose(np.asarray(energy) / self.gauge, t_ms, rng)

    def exposure_for(self, e_max: float, fraction: float) -> float:
        """Exposure (ms, to 0.1 us) putting energy rate ``e_max`` at ``fraction`` of range."""
        x = float(self.sensor.x_for_dn(fraction * self.sensor.dn_max)) * self.gauge
        return float(round(x / e_max, 4))


@dataclass(frozen=True)
class RigTruth:
    """Known truth of a synthetic rig: its lenses, the reference lens, reflector, marker and sun."""

    seed: int
    lenses: tuple[Lens, ...]
    reference: int  # the lens whose frame is the rig's (the middle of the rig)
    reflector_reflectance: np.ndarray  # (band,)
    reflector_size_m: tuple[float, float]
    marker: MarkerSpec
    sun_brightness: float

    @property
    def n_bands(self) -> int:
        """Number of bands (one per lens)."""
        return len(self.lenses)

    @property
    def wavelengths(self) -> np.ndarray:
        """Centre wavelength (nm) of each lens's band."""
        return np.array([ln.camera.wavelengths_nm[0] for ln in self.lenses])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (H, W) of every band (the first lens's grid)."""
        return tuple(self.lenses[0].camera.grid_shape)  # type: ignore[return-value]

    @property
    def inverse_response(self) -> np.ndarray:
        """Stack each lens's true inverse response ``U[k]`` (band, 2**bits)."""
        return np.stack([ln.sensor.inverse_response() for ln in self.lenses])

    @property
    def vignetting(self) -> np.ndarray:
        """Stack each lens's vignetting (band, H, W)."""
        return np.stack([ln.vignetting for ln in self.lenses])

    @property
    def spectral_factor(self) -> np.ndarray:
        """Spectral factor ``S`` of each lens (band,)."""
        return np.array([ln.spectral_factor for ln in self.lenses])

    @property
    def black_level(self) -> np.ndarray:
        """Sensor black level (DN) of each lens (band,)."""
        return np.array([ln.sensor.black_level for ln in self.lenses])

    def arrays(self) -> dict[str, np.ndarray]:
        """Camera truth as flat arrays (``truth.npz``)."""
        cams = [ln.camera for ln in self.lenses]
        return {
            "seed": np.array(self.seed), "wavelength_nm": self.wavelengths,
            "band_name": np.array([ln.name for ln in self.lenses]), "bits": np.array(cams[0].bits),
            "black_level": self.black_level, "inverse_response": self.inverse_response,
            "vignetting": self.vignetting.astype(np.float32),
            "vignetting_centre": np.stack([ln.vignetting_centre for ln in self.lenses]),
            "spectral_factor": self.spectral_factor, "reflector_reflectance": self.reflector_reflectance,
            "reflector_size_m": np.array(self.reflector_size_m),
            "intrinsics": np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams]),
            "dist": np.array([c.dist for c in cams]),
            "rig_R": np.stack([ln.rig_R for ln in self.lenses]), "rig_t": np.stack([ln.rig_t for ln in self.lenses]),
            "sun_brightness": np.array(self.sun_brightness),
        }


def _lens_vignetting(cam: SnapshotCamera, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Off-centre ``V = (1 + k rho^2)^-2``, max 1, mean corner value 55-65 % of the peak."""
    h, w = cam.grid_shape
    centre = np.array([cam.cx + rng.uniform(-0.04, 0.04) * w, cam.cy + rng.uniform(-0.04, 0.04) * h])
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rho2 = ((jj - centre[0]) ** 2 + (ii - centre[1]) ** 2) / cam.fx**2
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
    c_rho2 = ((corners[:, 0] - centre[0]) ** 2 + (corners[:, 1] - centre[1]) ** 2) / cam.fx**2
    target = 1.0 - rng.uniform(0.35, 0.45)
    lo, hi = 0.0, 20.0
    for _ in range(60):
        k = 0.5 * (lo + hi)
        lo, hi = (k, hi) if np.mean((1 + k * c_rho2) ** -2) > target else (lo, k)
    v = (1.0 + k * rho2) ** -2
    return (v / v.max()), centre


def make_rig_truth(seed: int = 0, *, shape: tuple[int, int] = REDEDGE_SHAPE, bands=REDEDGE_BANDS,
                   reflector_reflectance: float = 0.5, reflector_size_m: tuple[float, float] = (0.5, 0.5),
                   marker: MarkerSpec | None = None, reference: int = 3) -> RigTruth:
    """Seeded rig: per lens intrinsics, pose in the rig, sensor, vignetting and S (module docstring)."""
    rng = np.random.default_rng([seed, 31])
    h, w = shape
    scale = w / REDEDGE_SHAPE[1]
    lenses = []
    for b, (name, wl, _fwhm, _suffix) in enumerate(bands):
        f = REDEDGE_FOCAL_PX * scale * (1.0 + rng.normal(0.0, 0.004))
        dist = (-0.10 + rng.normal(0, 0.004), 0.14 + rng.normal(0, 0.01), rng.normal(0, 5e-4),
                rng.normal(0, 5e-4), -0.02 + rng.normal(0, 0.01))
        cam = SnapshotCamera(
            name=f"lens-{name}", fx=f, fy=f * (1.0 + 0.0 * rng.normal(0, 5e-4)),  # square pixels (one focal length in the XMP)
            cx=(w - 1) / 2 + rng.normal(0, 0.008) * w, cy=(h - 1) / 2 + rng.normal(0, 0.008) * h,
            dist=tuple(float(d) for d in dist), grid_shape=(h, w), sensor_shape=(h, w), pattern_shape=(1, 1),
            bits=12, wavelengths_nm=(float(wl),),
        )
        sensor = SensorModel(bits=12, black_level=float(rng.uniform(250, 330)), read_noise_dn=float(rng.uniform(2.5, 3.5)),
                             shot_noise_dn_at_full=float(rng.uniform(30, 40)), shoulder_start=float(rng.uniform(0.82, 0.9)),
                             curvature=float(rng.uniform(0.03, 0.08)))
        if b == reference:
            R, t = np.eye(3), np.zeros(3)
        else:
            R = rot(rng.normal(size=3), math.radians(rng.uniform(0.2, 0.7)))
            t = np.array([rng.uniform(-0.025, 0.025), rng.uniform(-0.02, 0.02), rng.normal(0, 0.002)])
        V, centre = _lens_vignetting(cam, rng)
        s = float(np.clip(2.0 + 0.3 * math.sin(0.013 * wl + 1.0) + rng.normal(0, 0.1), 1.5, 2.5))
        lenses.append(Lens(name, cam, sensor, R, t, V, centre, s))
    return RigTruth(seed=seed, lenses=tuple(lenses), reference=reference,
                    reflector_reflectance=np.full(len(lenses), float(reflector_reflectance)),
                    reflector_size_m=(float(reflector_size_m[0]), float(reflector_size_m[1])),
                    marker=marker or MarkerSpec(size_m=0.12, border_m=0.03),
                    sun_brightness=float(rng.uniform(260.0, 320.0)))


@dataclass
class RigFrames:
    """Captures of one dataset.

    ``dn`` list of (band, H, W) uint16 (12-bit values), ``exposure_ms`` (capture, band),
    ``names``, ``times_s`` (seconds after the session start), ``truth`` arrays.
    """

    kind: str
    dn: list[np.ndarray]
    exposure_ms: np.ndarray
    names: list[str]
    times_s: list[float]
    truth: dict[str, np.ndarray] = field(default_factory=dict)


def _marker_in_frame(lens: Lens, pose: Pose, marker: MarkerSpec, margin_px: float, min_side_px: float) -> bool:
    s = 0.5 * marker.size_m
    pc = pose.to_camera(np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]]))
    if np.any(pc[:, 2] <= 0.05):
        return False
    px = lens.camera.project(pc)
    h, w = lens.camera.grid_shape
    inside = np.all((px >= margin_px) & (px <= np.array([w - 1, h - 1]) - margin_px))
    return bool(inside and np.min(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1)) >= min_side_px)


def response_sweep(truth: RigTruth, *, seed: int = 0, n_frames: int = 12, step: float = 1.7,
                   decades: float = 2.5) -> RigFrames:
    """Simulate an exposure sweep of a static textured scene.

    The same exposures for every lens (manual exposure); each lens sees its own part of it.
    truth: ``energy`` (band, H, W).
    """
    rng = np.random.default_rng([seed, 32])
    h, w = truth.shape
    gy, gx = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    energy = np.empty((truth.n_bands, h, w), dtype=np.float32)
    for b, ln in enumerate(truth.lenses):
        base = PeriodicNoise(rng, 1.0, 7.0 * w / 409, n=512)(gx, gy)
        rank = np.argsort(np.argsort(base.ravel())).reshape(h, w)
        log_l = -decades * (1.0 - (rank + 0.5) / rank.size)
        tint = PeriodicNoise(rng, 1.0, 12.0 * w / 409, n=512)(gx + 31.0 * b, gy)
        e = ln.vignetting * ln.spectral_factor * 10.0 ** (log_l + 0.08 * tint)
        energy[b] = e * (1000.0 * rng.uniform(0.85, 1.15) / e.max())
    t0 = min(ln.exposure_for(float(energy[b].max()), rng.uniform(0.30, 0.40)) for b, ln in enumerate(truth.lenses))
    exposures = np.array([round(t0 * step**i, 4) for i in range(n_frames)])
    dn = [np.stack([ln.expose(energy[b], t, rng) for b, ln in enumerate(truth.lenses)]) for t in exposures]
    return RigFrames("response", dn, np.repeat(exposures[:, None], truth.n_bands, axis=1),
                     [f"IMG_{i:04d}" for i in range(n_frames)], [2.0 * i for i in range(n_frames)],
                     {"energy": energy})


def _render_lenses(truth: RigTruth, ref: Pose, scene, reflectance: np.ndarray, supersample: int):
    """Per lens: its pose, render, and ``B R`` (H, W) for its band."""
    out = []
    for b, ln in enumerate(truth.lenses):
        pose = ln.pose(ref)
        rend = render(ln.camera, pose, scene, supersample=supersample)
        out.append((pose, rend, rend.light_times_reflectance(reflectance[:, [b]])[0]))
    return out


def _least_covered(coverage: np.ndarray, cells: tuple[int, int]) -> np.ndarray:
    """Return the minimum of ``coverage`` (H, W) in each of ``cells`` (rows, columns) blocks."""
    h, w = coverage.shape
    if h % cells[0] == 0 and w % cells[1] == 0:
        return coverage.reshape(cells[0], h // cells[0], cells[1], w // cells[1]).min(axis=(1, 3))
    return np.array([[coverage[i * h // cells[0]:(i + 1) * h // cells[0], j * w // cells[1]:(j + 1) * w // cells[1]].min()
                      for j in range(cells[1])] for i in range(cells[0])])


def _vignetting_ref_pose(rng: np.random.Generator, ref_lens: Lens, coverage: np.ndarray, cells: tuple[int, int],
                         half_in: float, half_out: np.ndarray, max_tilt_deg: float,
                         distance_m: tuple[float, float]) -> Pose:
    """Draw a reference-lens reflector pose aimed at the least covered cell of ``coverage``.

    The reflector point ``q`` lies outside the marker (``half_in``) and inside the reflector
    (``half_out``).
    """
    h, w = coverage.shape
    cov = _least_covered(coverage, cells)
    cov = cov + rng.uniform(0, 0.5, cov.shape)
    ci, cj = np.unravel_index(np.argmin(cov), cov.shape)
    t_px = np.array([(cj + rng.uniform()) * w / cells[1], (ci + rng.uniform()) * h / cells[0]])
    while True:
        q = rng.uniform(-half_out, half_out)
        if np.max(np.abs(q)) >= half_in:
            break
    R = random_tilt(rng, max_tilt_deg) @ FRONTAL @ rot([0, 0, 1], rng.uniform(0, 2 * np.pi))
    return pose_through(ref_lens.camera, R, t_px, q, rng.uniform(*distance_m))


def _reflector_ref_pose(rng: np.random.Generator, ref_lens: Lens, shape: tuple[int, int]) -> Pose:
    """Draw a near-nadir close reference-lens pose (tilt up to 12 deg, 0.6-0.8 m, near the centre)."""
    h, w = shape
    R = random_tilt(rng, 12.0) @ FRONTAL @ rot([0, 0, 1], rng.normal(0, 0.15))
    t_px = np.array([ref_lens.camera.cx + rng.normal(0, 0.03 * w), ref_lens.camera.cy + rng.normal(0, 0.03 * h)])
    return pose_through(ref_lens.camera, R, t_px, np.zeros(2), rng.uniform(0.6, 0.8))


def _expose_gray(truth: RigTruth, rendered, gray, rng: np.random.Generator) -> tuple[list, list]:
    """Expose every lens on its own, its brightest gray pixel at 70-85 % of range: ``(dn, t)``."""
    frac = rng.uniform(0.70, 0.85)
    dn, ts = [], []
    for b, (ln, (_, _, br)) in enumerate(zip(truth.lenses, rendered)):
        energy = ln.vignetting * ln.spectral_factor * br
        t = ln.exposure_for(float(energy[gray[b]].max()), frac)
        dn.append(ln.expose(energy, t, rng))
        ts.append(t)
    return dn, ts


def marker_views(truth: RigTruth, *, seed: int = 0, kind: str = "vignetting", n_views: int = 24,
                 max_tilt_deg: float = 30.0, distance_m: tuple[float, float] = (0.8, 1.4), supersample: int = 3,
                 max_attempts: int = 300, fixed_light: bool = True, time0_s: float = 300.0) -> RigFrames:
    """Render the gray reflector with its marker as seen by the rig.

    ``kind="vignetting"``: from many viewpoints under one fixed non-uniform light (Eq. 8-10;
    the reflector aimed at the least covered part of the reference lens's image);
    ``kind="reflector"``: near-nadir close views, each under its own non-uniform light
    (Eq. 11-14). Every lens exposes on its own (brightest gray pixel at 70-85 % of range) and
    must see and detect the marker.

    truth: ``rvec``, ``tvec`` (view, band, 3) each lens's pose; ``gray_mask`` (view, band, H, W);
    ``light`` (view, 9) (:meth:`GradientShadowLight.from_params`).
    """
    rng = np.random.default_rng([seed, 33 if kind == "vignetting" else 34])
    ref_lens = truth.lenses[truth.reference]
    h, w = truth.shape
    mk = truth.marker
    light = random_light(rng, 0.8 * truth.sun_brightness, truth.reflector_size_m)
    coverage = np.zeros((h, w), dtype=np.int32)
    cells = (8, 10)
    half_in = 0.5 * mk.size_m + mk.border_m + 0.02
    half_out = np.array(truth.reflector_size_m) * 0.5 - 0.03
    dns, exps, rvecs, tvecs, masks, lights = [], [], [], [], [], []
    for k in range(n_views):
        if not fixed_light:
            light = random_light(rng, truth.sun_brightness * rng.uniform(0.9, 1.1), truth.reflector_size_m)
        scene = ReflectorScene(truth.wavelengths, truth.reflector_reflectance, truth.reflector_size_m, mk, light,
                               ground_seed=seed + 17 * k)
        for _ in range(max_attempts):
            if kind == "vignetting":
                ref = _vignetting_ref_pose(rng, ref_lens, coverage, cells, half_in, half_out, max_tilt_deg, distance_m)
            else:
                ref = _reflector_ref_pose(rng, ref_lens, (h, w))
            if not all(_marker_in_frame(ln, ln.pose(ref), mk, 6.0, 0.035 * w) for ln in truth.lenses):
                continue
            rendered = _render_lenses(truth, ref, scene, scene.reflectance, supersample)
            gray = [r.pure(ReflectorScene.GRAY) for _, r, _ in rendered]
            if min(g.sum() for g in gray) < 0.05 * h * w:
                continue
            dn, ts = _expose_gray(truth, rendered, gray, rng)
            if not all(detect_marker_corners(d, mk) is not None for d in dn):
                continue
            break
        else:  # pragma: no cover - seeded planning
            raise RuntimeError(f"could not plan {kind} view {k}")
        if kind == "vignetting":
            coverage += gray[truth.reference]
        dns.append(np.stack(dn))
        exps.append(ts)
        rvecs.append([p.rvec for p, _, _ in rendered])
        tvecs.append([p.tvec for p, _, _ in rendered])
        masks.append(np.stack(gray))
        lights.append(light.params())
    prefix = "IMG_1" if kind == "vignetting" else "IMG_2"
    return RigFrames(kind, dns, np.array(exps), [f"{prefix}{i:03d}" for i in range(n_views)],
                     [time0_s + 6.0 * i for i in range(n_views)],
                     {"rvec": np.array(rvecs), "tvec": np.array(tvecs), "gray_mask": np.array(masks),
                      "light": np.array(lights)})


def panel_captures(truth: RigTruth, *, seed: int = 0, n_frames: int = 3, height_m: float = 5.0,
                   panels=CHECK_PANELS, supersample: int = 3, time0_s: float = 1200.0) -> RigFrames:
    """Simulate near-nadir captures of gray panels on a crop field, for the Eq. 15 check.

    Under uniform sun (a different level per capture). truth: ``sun`` (n,), ``labels``
    (n, band, H, W) int8 panel index where a band's pixel lies well inside a panel, -1
    elsewhere; ``panel_reflectance`` (P,).
    """
    rng = np.random.default_rng([seed, 35])
    dns, exps, labels, suns = [], [], [], []
    for k in range(n_frames):
        sun = truth.sun_brightness * rng.uniform(0.75, 1.15)
        scene = FieldScene(truth.wavelengths, panels, sun, field_seed=seed)
        R = (rot([1, 0, 0], math.radians(rng.normal(0, 1.5))) @ rot([0, 1, 0], math.radians(rng.normal(0, 1.5)))
             @ FRONTAL @ rot([0, 0, 1], math.radians(rng.normal(0, 3.0))))
        ref = Pose.from_matrix(R, -R @ np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.3), height_m]))
        rendered = _render_lenses(truth, ref, scene, scene.reflectance, supersample)
        frac = rng.uniform(0.72, 0.82)
        dn, ts, lab = [], [], []
        for b, (ln, (_, rend, br)) in enumerate(zip(truth.lenses, rendered)):
            energy = ln.vignetting * ln.spectral_factor * br
            t = ln.exposure_for(float(energy.max()), frac)
            dn.append(ln.expose(energy, t, rng))
            ts.append(t)
            lb = np.full(truth.shape, -1, dtype=np.int8)
            for p in range(len(panels)):
                lb[rend.pure(1 + p)] = p
            lab.append(lb)
        dns.append(np.stack(dn))
        exps.append(ts)
        labels.append(np.stack(lab))
        suns.append(sun)
    return RigFrames("panels", dns, np.array(exps), [f"IMG_3{i:03d}" for i in range(n_frames)],
                     [time0_s + 2.0 * i for i in range(n_frames)],
                     {"sun": np.array(suns), "labels": np.array(labels),
                      "panel_reflectance": np.array([p.reflectance for p in panels])})


def _board_reflectance(camera: SnapshotCamera, pose: Pose, tex: np.ndarray, ppm: np.ndarray,
                       blur_px: float) -> np.ndarray:
    """Return the reflectance (0.04 ink .. 0.84 paper) of a board texture seen through ``camera``.

    Seen from ``pose``, on its sensor grid (2 x 2 samples per pixel, Gaussian PSF).
    """
    import cv2

    xn, yn, (dxx, dxy, dyx, dyy) = camera.sensor_rays()
    Rm, C = pose.R, pose.camera_centre
    acc = np.zeros(xn.shape, dtype=np.float32)
    for ox, oy in ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)):
        x = xn + dxx * ox + dxy * oy
        y = yn + dyx * ox + dyy * oy
        d = [Rm[0, j] * x + Rm[1, j] * y + Rm[2, j] for j in range(3)]  # ray in the board frame
        with np.errstate(divide="ignore", invalid="ignore"):
            sc = -C[2] / d[2]
        u = (C[0] + sc * d[0]) * ppm[0] - 0.5
        v = (C[1] + sc * d[1]) * ppm[1] - 0.5
        bad = ~(np.isfinite(sc) & (sc > 0))
        u[bad], v[bad] = -1e6, -1e6
        acc += cv2.remap(tex, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.3)
    return 0.04 + 0.8 * cv2.GaussianBlur(acc / 4.0, (0, 0), blur_px)


def _board_pose(rng: np.random.Generator, camera: SnapshotCamera, board_size_m, distance_m, max_tilt_deg) -> Pose:
    h, w = camera.grid_shape
    R = random_tilt(rng, max_tilt_deg) @ rot([0, 0, 1], rng.normal(0, 0.2))
    t_px = np.array([rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h])
    return pose_through(camera, R, t_px, np.array(board_size_m) / 2, rng.uniform(*distance_m))


def board_views(truth: RigTruth, board_image: np.ndarray, board_size_m: tuple[float, float], *, seed: int = 0,
                n_views: int = 16, distance_m: tuple[float, float] = (0.35, 0.6), max_tilt_deg: float = 40.0,
                blur_px: float = 0.7) -> RigFrames:
    """Simulate images of a printed calibration board held before the rig.

    ``board_image``: uint8, white 255, spanning ``board_size_m`` = (w, h) metres, its object
    frame x right and y down from the top-left corner, as OpenCV's boards; held at random
    tilts and positions, under uniform light. Every lens renders it through its own distorted
    pinhole (:meth:`SnapshotCamera.sensor_rays`, 2 x 2 samples per pixel, a Gaussian PSF),
    with its own vignetting, response and noise, exposed on its own. truth: ``rvec``, ``tvec``
    (view, band, 3) the board pose in each lens (object frame -> lens).
    """
    rng = np.random.default_rng([seed, 36])
    tex = np.asarray(board_image, dtype=np.float32) / 255.0
    ppm = np.array([tex.shape[1] / board_size_m[0], tex.shape[0] / board_size_m[1]])
    ref_lens = truth.lenses[truth.reference]
    dns, exps, rvecs, tvecs = [], [], [], []
    for _ in range(n_views):
        ref = _board_pose(rng, ref_lens.camera, board_size_m, distance_m, max_tilt_deg)
        dn, ts, rv, tv = [], [], [], []
        for ln in truth.lenses:
            pose = ln.pose(ref)
            refl = _board_reflectance(ln.camera, pose, tex, ppm, blur_px)
            energy = ln.vignetting * ln.spectral_factor * truth.sun_brightness * refl
            t = ln.exposure_for(float(energy.max()), 0.7)
            dn.append(ln.expose(energy, t, rng))
            ts.append(t)
            rv.append(pose.rvec)
            tv.append(pose.tvec)
        dns.append(np.stack(dn))
        exps.append(ts)
        rvecs.append(rv)
        tvecs.append(tv)
    return RigFrames("board", dns, np.array(exps), [f"IMG_4{i:03d}" for i in range(n_views)],
                     [100.0 + 5.0 * i for i in range(n_views)], {"rvec": np.array(rvecs), "tvec": np.array(tvecs)})


def snapshot_board_views(truth, board_image: np.ndarray, board_size_m: tuple[float, float], *, seed: int = 0,
                         n_views: int = 10, distance_m: tuple[float, float] = (0.35, 0.6),
                         max_tilt_deg: float = 40.0, blur_px: float = 1.2) -> list[np.ndarray]:
    """Simulate the board of :func:`board_views` seen by a snapshot camera.

    The camera of a :class:`~pipeline.sim.world.scene.SyntheticTruth` (one lens, the 5 x 5
    mosaic): raw sensor frames (uint16, DN in the low bits), rendered on the sensor grid, with
    the truth's vignetting, S, response and noise per band.
    """
    rng = np.random.default_rng([seed, 37])
    cam = truth.camera
    tex = np.asarray(board_image, dtype=np.float32) / 255.0
    ppm = np.array([tex.shape[1] / board_size_m[0], tex.shape[0] / board_size_m[1]])
    sensor = truth.sensor
    gauge = float(sensor.inverse_response()[sensor.k_ref] / float(sensor.x_for_dn(sensor.k_ref)))
    frames = []
    for _ in range(n_views):
        pose = _board_pose(rng, cam, board_size_m, distance_m, max_tilt_deg)
        refl = cam.split_bands(_board_reflectance(cam, pose, tex, ppm, blur_px))
        energy = truth.vignetting * truth.spectral_factor[:, None, None] * truth.sun_brightness * refl
        x = float(sensor.x_for_dn(0.7 * sensor.dn_max)) * gauge
        t = float(round(x / float(energy.max()), 4))
        dn = sensor.expose(energy / gauge, t, rng)
        frames.append(cam.mosaic(dn, fill=int(round(sensor.black_level))))
    return frames


__all__ = ["board_views", "snapshot_board_views", "CHECK_PANELS", "Lens", "REDEDGE_BANDS", "RigFrames", "RigTruth", "make_rig_truth", "marker_views",
           "panel_captures", "response_sweep"]
