"""Datasets 2 and 3 of a session: reflector views for vignetting (Eq. 8-10) and reflector images (Eq. 11-14)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ._camera import FAR, FRONTAL, Pose, SnapshotCamera, rot
from ._light import GradientShadowLight, LightDrift
from ._render import detect_marker_corners, marker_pose_from_image, pose_error, render
from ._targets import CharucoBoardSpec, MarkerSpec, ReflectorScene
from ._truth import FrameSet, SyntheticTruth, expose_frame, exposure_for, session_time


def random_tilt(rng, max_tilt_deg: float) -> np.ndarray:
    phi = rng.uniform(0, 2 * np.pi)
    # more small tilts than large ones, like a hand-held camera, up to max_tilt_deg
    theta = np.deg2rad(max_tilt_deg) * math.sqrt(rng.uniform(0, 1))
    return rot([math.cos(phi), math.sin(phi), 0.0], theta)


def _plane_grid(size_m, step_m=0.0025):
    uu = np.arange(-0.5 * size_m[0], 0.5 * size_m[0] + 1e-9, step_m)
    vv = np.arange(-0.5 * size_m[1], 0.5 * size_m[1] + 1e-9, step_m)
    return uu, vv


def random_light(rng, brightness: float, size_m, shadow: bool = True,
                  nonuniformity: float = 1.0, gradient_dir: float | None = None) -> GradientShadowLight:
    """Random 2:1 gradient + soft shadow (35-50 % deep) on the reflector.

    ``nonuniformity`` ``a`` scales how uneven the light is, with the same random draws:
    gradient ratio ``2**a`` and shadow transmission ``(1 - depth)**a`` (``a = 0``: uniform
    light; ``1``: the default; ``2``: a 4:1 gradient and a 58-75 % deep shadow).
    ``gradient_dir`` (radians in the plane) replaces the random direction of the gradient
    (drawn all the same, so the other draws do not move).
    """
    if nonuniformity < 0:
        raise ValueError(f"light nonuniformity must be >= 0, got {nonuniformity}")
    ratio = 2.0 if nonuniformity == 1.0 else 2.0**nonuniformity
    if not shadow:
        gdir = rng.uniform(0, 2 * np.pi)
        return GradientShadowLight(brightness=brightness, extent_m=size_m, gradient_ratio=ratio,
                                   gradient_dir=gdir if gradient_dir is None else float(gradient_dir))
    sdir = rng.uniform(0, 2 * np.pi)
    # the shadow edge crosses the reflector so that 20-35 % of it is in shadow
    half = 0.5 * size_m[0] * abs(math.cos(sdir)) + 0.5 * size_m[1] * abs(math.sin(sdir))
    gdir = rng.uniform(0, 2 * np.pi)
    if gradient_dir is not None:
        gdir = float(gradient_dir)
    depth = rng.uniform(0.35, 0.5)
    if nonuniformity != 1.0:
        depth = 1.0 - (1.0 - depth) ** nonuniformity
    return GradientShadowLight(
        brightness=brightness, gradient_dir=gdir, gradient_ratio=ratio,
        extent_m=size_m, shadow_depth=depth, shadow_dir=sdir,
        shadow_offset_m=half * rng.uniform(0.3, 0.6), shadow_softness_m=rng.uniform(0.008, 0.015),
    )


def frame_marker_ok(cam: SnapshotCamera, pose: Pose, marker: MarkerSpec | CharucoBoardSpec, margin_px: float,
                     min_side_px: float) -> tuple[bool, np.ndarray]:
    su, sv = marker.half_extent()  # a board: its outline
    pts = np.array([[-su, sv, 0], [su, sv, 0], [su, -sv, 0], [-su, -sv, 0]])
    pc = pose.to_camera(pts)
    if np.any(pc[:, 2] <= 0.05):
        return False, np.zeros((4, 2))
    px = cam.project(pc)
    h, w = cam.grid_shape
    inside = np.all((px[:, 0] >= margin_px) & (px[:, 0] <= w - 1 - margin_px)
                    & (px[:, 1] >= margin_px) & (px[:, 1] <= h - 1 - margin_px))
    side = np.min(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1))
    return bool(inside and side >= min_side_px), px


def pose_through(cam: SnapshotCamera, R: np.ndarray, pixel: np.ndarray, q: np.ndarray,
                  depth: float) -> Pose:
    """Return the pose that makes a pixel see a plane point at a depth.

    Pose with rotation R such that image point ``pixel`` sees plane point ``q`` and the marker
    centre is at camera depth ~``depth``.
    """
    r = np.append(cam.rays(pixel.reshape(1, 2))[0], 1.0)
    Rq = R @ np.array([q[0], q[1], 0.0])
    lam = depth + Rq[2]
    return Pose.from_matrix(R, lam * r - Rq)


def _facing(pose: Pose, max_view_deg: float) -> bool:
    C = pose.camera_centre
    return C[2] > 0 and C[2] / np.linalg.norm(C) >= math.cos(math.radians(max_view_deg))


#: Coarse cells (rows, columns) of the image in which :func:`vignetting_views` looks for the
#: least covered part.
_COVERAGE_CELLS = (14, 26)


def _aim_at_border(rng, h: int, w: int) -> np.ndarray:
    """Image point near a random border, where a view with its marker out of frame aims the reflector."""
    side = int(rng.integers(4))
    t_px = np.array([rng.uniform(0, w - 1), rng.uniform(0, h - 1)])
    if side == 0:
        t_px[0] = rng.uniform(0, 25)
    elif side == 1:
        t_px[0] = rng.uniform(w - 26, w - 1)
    elif side == 2:
        t_px[1] = rng.uniform(0, 15)
    else:
        t_px[1] = rng.uniform(h - 16, h - 1)
    return t_px


def _aim_least_covered(rng, coverage: np.ndarray) -> np.ndarray:
    """Random image point in the coarse cell whose least covered pixel is least covered (ties broken at random)."""
    h, w = coverage.shape
    ch, cw = _COVERAGE_CELLS
    row_starts = np.linspace(0, h, ch + 1).astype(int)[:-1]
    col_starts = np.linspace(0, w, cw + 1).astype(int)[:-1]
    cov = np.minimum.reduceat(np.minimum.reduceat(coverage, row_starts, axis=0),
                              col_starts, axis=1).astype(np.float64)
    cov += rng.uniform(0, 0.5, cov.shape)
    cy_, cx_ = np.unravel_index(np.argmin(cov), cov.shape)
    return np.array([(cx_ + rng.uniform()) * w / cw, (cy_ + rng.uniform()) * h / ch])


def _random_view_pose(rng, cam: SnapshotCamera, t_px: np.ndarray, half_in: float,
                      half_out: np.ndarray, max_tilt_deg: float,
                      distance_m: tuple[float, float]) -> Pose:
    """Draw a random view pose aimed at a pixel.

    A pose that puts a random point of the gray part of the reflector (outside the marker and
    its paper) at pixel ``t_px``, with a random tilt, roll and marker distance.
    """
    while True:
        q = rng.uniform(-half_out, half_out)
        if np.max(np.abs(q)) >= half_in:
            break
    yaw = rot([0, 0, 1], rng.uniform(0, 2 * np.pi))
    R = random_tilt(rng, max_tilt_deg) @ FRONTAL @ yaw
    depth = rng.uniform(*distance_m)
    return pose_through(cam, R, t_px, q, depth)


def _view_geometry_ok(cam: SnapshotCamera, pose: Pose, mk: MarkerSpec | CharucoBoardSpec, missing: bool,
                      partial: bool = False) -> bool:
    """Check that a planned view sees the marker as intended.

    The camera faces the reflector and the marker is fully in frame (or, for a view meant to
    miss it, clearly out of frame and not behind the camera; for a view meant to cut it, one
    to three of its corners in frame). A ChArUco board: its outline's corners.
    """
    if not _facing(pose, 60.0):
        return False
    ok, px = frame_marker_ok(cam, pose, mk, margin_px=4.0, min_side_px=16.0)
    if partial:
        h, w = cam.grid_shape
        if pose.to_camera(np.zeros((1, 3)))[0, 2] <= 0.05:
            return False
        inside = (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
        return 1 <= int(inside.sum()) <= 3
    if missing:
        centre = px.mean(axis=0)
        h, w = cam.grid_shape
        out_by = max(-centre[0], centre[0] - (w - 1), -centre[1], centre[1] - (h - 1))
        behind = pose.to_camera(np.zeros((1, 3)))[0, 2] <= 0.05
        return not (behind or out_by < 0.6 * np.ptp(px[:, 0]) + 3)
    return bool(ok)


def _shoot_view(truth: SyntheticTruth, scene: ReflectorScene, pose: Pose, rng, missing: bool,
                supersample: int, detect_bands: list[int],
                exposure_fraction: tuple[float, float] = (0.70, 0.85), partial: bool = False):
    """Render and expose one planned view.

    ``(gray mask, exposure, DN)``, or None when too little of the gray reflector is in view or
    ArUco does not behave as planned (found in every detection band, or, for a view meant to
    miss it, in none). A ChArUco board cut by the frame's border (``partial``) is kept whether
    or not its corners in view are found: finding part of a board is what it is for.
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rend = render(cam, pose, scene, supersample=supersample)
    gray = rend.pure(ReflectorScene.GRAY)
    if gray.sum() < (0.03 if missing else 0.05) * h * w:
        return None
    energy = (truth.vignetting * truth.spectral_factor[:, None, None]
              * rend.light_times_reflectance(scene.reflectance)).astype(np.float32)
    t = exposure_for(truth, float(energy[:, gray].max()), rng.uniform(*exposure_fraction))
    dn = expose_frame(truth, energy, t, rng)
    if partial and isinstance(truth.marker, CharucoBoardSpec):
        return gray, t, dn
    found = [detect_marker_corners(dn[b], truth.marker) is not None for b in detect_bands]
    if missing and any(found):
        return None
    if not missing and not all(found):
        return None
    return gray, t, dn


def vignetting_views(truth: SyntheticTruth, *, seed: int = 0, n_views: int = 40,
                     n_missing: int = 1, max_tilt_deg: float = 35.0,
                     distance_m: tuple[float, float] = (0.8, 1.6), supersample: int = 4,
                     max_attempts: int = 400, light_nonuniformity: float = 1.0,
                     light_gradient_dir: float | None = None, n_partial: int = 0,
                     exposure_fraction: tuple[float, float] = (0.70, 0.85)) -> FrameSet:
    """Render the gray reflector + marker from many viewpoints under fixed non-uniform light (Eq. 8-10).

    The light ``B(p)`` (2:1 gradient + soft shadow) is fixed on the plane, so the radiance
    ``L_b(p) = S_b B(p) R_s`` is the same from every viewpoint (Lambertian). Views are planned
    greedily: each aims a random reflector point (outside the marker and its paper) at the
    least covered part of the image, with a random tilt (<= ``max_tilt_deg`` from the optical
    axis), roll and marker distance in ``distance_m``, and is kept only if the marker projects
    fully inside the frame and is detected by ArUco in bands 0, 12 and 24. ``n_missing`` views
    (spread over the sequence) have the marker out of frame while the reflector is partly in
    view: the pipeline must skip them. Exposure: brightest gray-reflector pixel at 70-85 %.

    Parameters
    ----------
    truth : SyntheticTruth
        The camera truth (:func:`make_truth`).
    seed : int
        Seed of the dataset (with the truth's, it fixes every random draw).
    n_views : int
        Views in the dataset, ``n_missing`` of them without the marker.
    n_missing : int
        Views with the marker out of frame.
    max_tilt_deg : float
        Largest tilt of the camera from the reflector's normal.
    distance_m : tuple of float
        Range of the marker's distance.
    supersample : int
        Supersampling of edge pixels (:func:`render`).
    max_attempts : int
        Planning attempts per view before giving up.
    light_nonuniformity : float
        How uneven the light is (0 uniform, 1 default, 2 a 4:1 gradient and a deeper shadow;
        see :func:`random_light`).
    light_gradient_dir : float, optional
        Direction of the light's gradient on the reflector (radians; default random).
    n_partial : int
        Further views (counted in ``n_views``) with the marker cut by the frame's border (one
        to three corners in frame, so ArUco does not find it) while the reflector is partly in
        view; spread over the sequence like the missing ones. Default 0.
    exposure_fraction : tuple of float
        Range of the brightest gray-reflector pixel's share of the DN range.

    Returns
    -------
    FrameSet
        ``kind="vignetting"``; truth: ``rvec``, ``tvec`` (n, 3); ``marker_in_frame`` (n,) bool
        (the whole marker, or board, in frame);
        ``pose_error_deg``, ``pose_error_rel`` (n,) error of the pose from ArUco + IPPE on band
        0 (NaN if missing); ``found_default_detector`` (n,) the marker is also found with
        OpenCV's default ``minMarkerDistanceRate`` (see :func:`detect_marker_corners`);
        ``gray_mask`` (n, H, W) pixels on the gray reflector in every band (no edge, marker or
        paper); ``coverage`` (H, W) number of views with the pixel on the gray reflector;
        ``light`` (9,) light parameters (``GradientShadowLight.from_params`` rebuilds it);
        ``plane_u`` (Nu,), ``plane_v`` (Nv,), ``B_plane`` (Nv, Nu) the brightness on a 2.5 mm
        grid of the reflector (L = S B R_s). With a ChArUco board (``truth.marker`` a
        :class:`CharucoBoardSpec`), also ``board_corners`` (n,) the chessboard corners found in
        band 0 (0: not found) and ``rejected_renders`` (n,) rendered views thrown away before
        each was kept (the board not found in a detection band, too little gray in view).

    Raises
    ------
    RuntimeError
        If a view cannot be planned in ``max_attempts`` (a bug of the seeded planner).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rng = np.random.default_rng([seed, 3])
    light = random_light(rng, 0.8 * truth.sun_brightness, truth.reflector_size_m,
                          nonuniformity=light_nonuniformity, gradient_dir=light_gradient_dir)
    scene = ReflectorScene(cam.wavelengths, truth.reflector_reflectance, truth.reflector_size_m,
                           truth.marker, light, ground_seed=seed)
    mk = truth.marker
    half_in = 0.5 * mk.size_m + mk.border_m + 0.02
    half_out = np.array(truth.reflector_size_m) * 0.5 - 0.03
    missing_at = set(
        np.linspace(0, n_views - 1, n_missing + 2)[1:-1].round().astype(int).tolist()
    ) if n_missing else set()
    partial_at: set[int] = set()
    if n_partial:  # missing and partial views alternate over the sequence
        spread = np.linspace(0, n_views - 1, n_missing + n_partial + 2)[1:-1].round().astype(int).tolist()
        picks = ([i for i in range(len(spread)) if i % 2 == 1]
                 + [i for i in range(len(spread)) if i % 2 == 0])[:n_partial]
        partial_at = {spread[i] for i in picks}
        missing_at = set(spread) - partial_at
    coverage = np.zeros((h, w), dtype=np.int32)
    out_dn, exposures, rvecs, tvecs, in_frame, masks = [], [], [], [], [], []
    pose_err, default_ok, n_corners, n_rejected = [], [], [], []
    board = isinstance(truth.marker, CharucoBoardSpec)
    detect_bands = sorted({0, cam.n_bands // 2, cam.n_bands - 1})
    for k in range(n_views):
        partial = k in partial_at
        missing = k in missing_at or partial
        rejected = 0
        for _attempt in range(max_attempts):
            t_px = _aim_at_border(rng, h, w) if missing else _aim_least_covered(rng, coverage)
            if partial:  # the marker's centre near the border: part of it out of frame
                R = random_tilt(rng, max_tilt_deg) @ FRONTAL @ rot([0, 0, 1], rng.uniform(0, 2 * np.pi))
                pose = pose_through(cam, R, t_px, np.zeros(2), rng.uniform(*distance_m))
            else:
                pose = _random_view_pose(rng, cam, t_px, half_in, half_out, max_tilt_deg, distance_m)
            if not _view_geometry_ok(cam, pose, mk, missing and not partial, partial):
                continue
            view = _shoot_view(truth, scene, pose, rng, missing, supersample, detect_bands,
                               exposure_fraction, partial)
            if view is not None:
                gray, t, dn = view
                break
            rejected += 1
        else:  # pragma: no cover - planning is seeded; this would be a bug in the planner
            raise RuntimeError(f"could not plan vignetting view {k} in {max_attempts} attempts")
        if not missing:
            coverage += gray
            est = marker_pose_from_image(dn[0], 0, cam, mk)
            perr = pose_error(est, pose) if est is not None else (np.nan, np.nan)
            default_found = detect_marker_corners(dn[0], mk, 0.125) is not None
        else:
            perr, default_found = (np.nan, np.nan), False
        pose_err.append(perr)
        default_ok.append(default_found)
        if board:
            found = detect_marker_corners(dn[0], mk)
            n_corners.append(0 if found is None else len(found))
            n_rejected.append(rejected)
        out_dn.append(dn)
        exposures.append(t)
        rvecs.append(pose.rvec)
        tvecs.append(pose.tvec)
        in_frame.append(not missing)
        masks.append(gray)
    uu, vv = _plane_grid(truth.reflector_size_m)
    U, Vg = np.meshgrid(uu, vv)
    n = len(out_dn)
    return FrameSet(
        kind="vignetting", dn=out_dn, exposure_ms=np.array(exposures),
        names=[f"view_{i:02d}" for i in range(n)],
        meta=[{"time": session_time(300.0 + 6.0 * i)} for i in range(n)],
        truth={
            "rvec": np.array(rvecs), "tvec": np.array(tvecs),
            "marker_in_frame": np.array(in_frame), "gray_mask": np.array(masks),
            "coverage": coverage,
            "pose_error_deg": np.array([e[0] for e in pose_err]),
            "pose_error_rel": np.array([e[1] for e in pose_err]),
            "found_default_detector": np.array(default_ok), "light": light.params(),
            "plane_u": uu, "plane_v": vv, "B_plane": light(U, Vg),
            **({"marker_partial": np.array([k in partial_at for k in range(n)])} if n_partial else {}),
            **({"board_corners": np.array(n_corners), "rejected_renders": np.array(n_rejected)} if board else {}),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )


def reflector_images(truth: SyntheticTruth, *, seed: int = 0, n_images: int = 3,
                     distance_m: tuple[float, float] = (0.55, 0.75), max_tilt_deg: float = 12.0,
                     supersample: int = 4, max_attempts: int = 200,
                     times_s: Sequence[float] | None = None, drift: LightDrift | None = None,
                     irradiance: bool = False, name_prefix: str = "reflector_",
                     gradient_ratio: float = 2.0, light_nonuniformity: float = 1.0,
                     light_gradient_dir: float | None = None,
                     exposure_fraction: tuple[float, float] = (0.70, 0.85)) -> FrameSet:
    """Render the gray reflector under the illumination of the flight (input of Eq. 11-14).

    Near-nadir views from 0.55-0.75 m, the reflector filling much of the frame. Each image has
    its own light: sun brightness (x 0.9-1.1) with a 2:1 linear gradient across the reflector
    in a random direction and a soft shadow over 20-35 % of it; the light colour S is the
    flight's. Exposure: brightest gray-reflector pixel at 70-85 %.

    Parameters
    ----------
    truth : SyntheticTruth
        The camera truth (:func:`make_truth`).
    seed : int
        Seed of the dataset (with the truth's, it fixes every random draw).
    n_images : int
        Number of images.
    distance_m : tuple of float
        Range of the camera's distance.
    max_tilt_deg : float
        Largest tilt of the camera.
    supersample : int
        Supersampling of edge pixels (:func:`render`).
    max_attempts : int
        Planning attempts per image.
    times_s : sequence of float, optional
        Time of each image in seconds after ``SESSION_START`` (default 900 + 20 k).
    drift : LightDrift, optional
        Light that changes over the flight: the brightness is the sun's times
        ``drift.level(time)`` (no random factor), the colour ``S`` times ``drift.colour(time)``,
        and the light has a ``gradient_ratio`` gradient but no shadow (the reflector fully in
        the sun, as a capture for the light's level should be).
    irradiance : bool
        Write a sun-sensor reading (the brightness, in arbitrary units) into each frame's
        ``meta``.
    name_prefix : str
        Prefix of the frame names.
    gradient_ratio : float
        Gradient of the light with ``drift``.
    light_nonuniformity, light_gradient_dir, exposure_fraction
        As in :func:`vignetting_views`.

    Returns
    -------
    FrameSet
        ``kind="reflector"``; truth: ``rvec``, ``tvec`` (n, 3); ``B`` (n, H, W) float32
        brightness at the band-grid pixel centres (band 0 sample positions; NaN where the ray
        misses the plane); ``gray_mask`` (n, H, W); ``light`` (n, 9)
        (``GradientShadowLight.from_params``); ``plane_u``, ``plane_v``, ``B_plane`` (n, Nv,
        Nu).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    cam = truth.camera
    h, w = cam.grid_shape
    rng = np.random.default_rng([seed, 4])
    mk = truth.marker
    uu, vv = _plane_grid(truth.reflector_size_m)
    U, Vg = np.meshgrid(uu, vv)
    dns, exposures, rvecs, tvecs, Bs, masks, lights, Bp = [], [], [], [], [], [], [], []
    times = [900.0 + 20.0 * i for i in range(n_images)] if times_s is None else [float(x) for x in times_s]
    S = truth.spectral_factor
    for k in range(n_images):
        jitter = rng.uniform(0.9, 1.1)  # drawn in every case: the seeded stream stays the same
        if drift is None:
            light = random_light(rng, truth.sun_brightness * jitter, truth.reflector_size_m,
                                  nonuniformity=light_nonuniformity, gradient_dir=light_gradient_dir)
        else:
            light = GradientShadowLight(brightness=truth.sun_brightness * drift.level(times[k]),
                                        gradient_dir=rng.uniform(0, 2 * np.pi), gradient_ratio=gradient_ratio,
                                        extent_m=truth.reflector_size_m)
            S = truth.spectral_factor * drift.colour(times[k], cam.wavelengths)
        scene = ReflectorScene(cam.wavelengths, truth.reflector_reflectance,
                               truth.reflector_size_m, mk, light, ground_seed=seed + 17 * k)
        for _attempt in range(max_attempts):
            R = random_tilt(rng, max_tilt_deg) @ FRONTAL @ rot([0, 0, 1], rng.normal(0, 0.15))
            t_px = np.array([cam.cx + rng.normal(0, 15), cam.cy + rng.normal(0, 8)])
            pose = pose_through(cam, R, t_px, np.zeros(2), rng.uniform(*distance_m))
            ok, _ = frame_marker_ok(cam, pose, mk, margin_px=6.0, min_side_px=20.0)
            if not ok:
                continue
            rend = render(cam, pose, scene, supersample=supersample)
            gray = rend.pure(ReflectorScene.GRAY)
            energy = (truth.vignetting * S[:, None, None]
                      * rend.light_times_reflectance(scene.reflectance)).astype(np.float32)
            t = exposure_for(truth, float(energy[:, gray].max()), rng.uniform(*exposure_fraction))
            dn = expose_frame(truth, energy, t, rng)
            if detect_marker_corners(dn[0], mk) is None:
                continue
            break
        else:  # pragma: no cover
            raise RuntimeError(f"could not plan reflector image {k}")
        u0, v0 = rend.plane_uv(0)
        B = light(u0, v0).astype(np.float32)
        B[(np.abs(u0) >= FAR / 2)] = np.nan
        dns.append(dn)
        exposures.append(t)
        rvecs.append(pose.rvec)
        tvecs.append(pose.tvec)
        Bs.append(B)
        masks.append(gray)
        lights.append(light.params())
        Bp.append(light(U, Vg))
    meta = [{"time": session_time(times[i])} for i in range(n_images)]
    if irradiance:
        for i in range(n_images):
            meta[i]["irradiance"] = float(lights[i][0])  # the brightness the image was rendered with
    return FrameSet(
        kind="reflector", dn=dns, exposure_ms=np.array(exposures),
        names=[f"{name_prefix}{i}" for i in range(n_images)],
        meta=meta,
        truth={
            "rvec": np.array(rvecs), "tvec": np.array(tvecs), "B": np.array(Bs),
            "gray_mask": np.array(masks), "light": np.array(lights),
            "plane_u": uu, "plane_v": vv, "B_plane": np.array(Bp),
        },
        camera=cam, black_level=int(round(truth.black_level)),
    )
