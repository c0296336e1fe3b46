"""The scene part of the synthetic forward model: geometry, targets, light, datasets.

Checked independently of the fitting code: poses are recovered with cv2.aruco +
cv2.solvePnP directly, physics with the true U, V, S, B.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mscal_core.mosaic import demosaic
from pipeline.sim.world import scene as S


@pytest.fixture(scope="module")
def truth():
    return S.make_truth(0)


def _detect(image, marker_id=3):
    img = image.astype(np.float64)
    lo, hi = np.percentile(img, [0.5, 99.5])
    img8 = np.clip(np.rint((img - lo) / (hi - lo) * 255), 0, 255).astype(np.uint8)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 3
    params.minMarkerDistanceRate = 0.05
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = det.detectMarkers(img8)
    if ids is None or marker_id not in ids.ravel():
        return None
    return corners[list(ids.ravel()).index(marker_id)].reshape(4, 2).astype(np.float64)


def _object_corners(s):
    h = s / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def _rot_err_deg(Ra, Rb):
    return math.degrees(math.acos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def _close_views(truth, n, seed):
    """Tilted (20-35 deg) views from 0.55-0.75 m with the marker near the image centre."""
    cam = truth.camera
    rng = np.random.default_rng(seed)
    poses = []
    while len(poses) < n:
        ax = rng.uniform(0, 2 * np.pi)
        R = (S.rot([np.cos(ax), np.sin(ax), 0], np.radians(rng.uniform(20, 35))) @ S.FRONTAL
             @ S.rot([0, 0, 1], rng.uniform(0, 2 * np.pi)))
        px = np.array([rng.uniform(130, 280), rng.uniform(70, 150)])
        pose = S.pose_through(cam, R, px, np.zeros(2), rng.uniform(0.55, 0.75))
        ok, _ = S.frame_marker_ok(cam, pose, truth.marker, 8.0, 20.0)
        if ok:
            poses.append(pose)
    return poses


def _energy(truth, rend, scene):
    return (truth.vignetting * truth.spectral_factor[:, None, None]
            * rend.light_times_reflectance(scene.reflectance)).astype(np.float32)


def test_projection_is_opencvs_and_rays_invert_it(truth):
    cam = truth.camera
    pts = np.random.default_rng(0).uniform([-0.6, -0.3, 0.8], [0.6, 0.3, 1.6], (200, 3))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.matrix, cam.dist_coeffs)
    px = cam.project(pts)
    assert np.abs(px - ref.reshape(-1, 2)).max() < 1e-9
    rays = cam.rays(px)
    assert np.abs(rays - pts[:, :2] / pts[:, 2:]).max() < 1e-10
    assert cam.grid_shape == (217, 409) and cam.sensor_shape == (1088, 2048)
    assert cam.wavelengths[12] == 752 and cam.wavelengths[24] == 670 and cam.wavelengths[7] == 803


def test_marker_detected_and_pose_recovered_with_opencv_convention(truth):
    """ArUco + SOLVEPNP_IPPE_SQUARE with corners TL (-s/2,+s/2), TR, BR, BL recover the pose:
    within 1 deg / 1 % from the corners averaged over the 25 bands (each shifted by its band
    offset), within 2 deg / 1.5 % from a single band (0.2-0.3 px corner noise)."""
    cam = truth.camera
    rng = np.random.default_rng(1)
    light = S.random_light(rng, 250.0, truth.reflector_size_m)
    scene = S.ReflectorScene(cam.wavelengths, 0.5, truth.reflector_size_m, truth.marker, light, 0)
    obj = _object_corners(truth.marker.size_m)
    for pose in _close_views(truth, 3, seed=2):
        rend = S.render(cam, pose, scene)
        energy = _energy(truth, rend, scene)
        t = S.exposure_for(truth, float(energy[:, rend.pure(1)].max()), 0.8)
        dn = S.expose_frame(truth, energy, t, rng)
        true_px = cam.project(pose.to_camera(obj))
        all_corners = []
        for b in range(cam.n_bands):
            corners = _detect(dn[b])
            assert corners is not None, f"marker not found in band {b}"
            corners = corners + cam.band_offsets[b]  # band pixel -> band-grid point
            # same corner order as the marker frame: TL, TR, BR, BL
            assert np.abs(corners - true_px).max() < 1.0
            all_corners.append(corners)
        estimates = [np.mean(all_corners, axis=0)] + all_corners[::6]
        for k, corners in enumerate(estimates):
            ok, rvec, tvec = cv2.solvePnP(obj, corners.reshape(4, 1, 2), cam.matrix,
                                          cam.dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            assert ok
            tol_deg, tol_rel = (1.0, 0.01) if k == 0 else (2.0, 0.015)  # 25 bands / one band
            assert _rot_err_deg(pose.R, cv2.Rodrigues(rvec)[0]) < tol_deg
            assert np.linalg.norm(tvec.ravel() - pose.tvec) / np.linalg.norm(pose.tvec) < tol_rel


def test_rendered_marker_edge_is_where_the_projection_puts_it(truth):
    """Sub-pixel 50 % crossings of the black square's left edge: unbiased (< 0.05 px)."""
    cam = truth.camera
    light = S.GradientShadowLight(brightness=300.0, gradient_ratio=1.0)
    scene = S.ReflectorScene(cam.wavelengths, 0.5, (0.5, 0.5), truth.marker, light, 0)
    pose = S.Pose.from_matrix(S.rot([1, 0.3, 0], 0.3) @ S.FRONTAL @ S.rot([0, 0, 1], 0.2),
                              np.array([0.02, 0.01, 0.9]))
    rend = S.render(cam, pose, scene)
    br = rend.light_times_reflectance(scene.reflectance)
    h = truth.marker.size_m / 2
    for b in (0, 18):
        dx, dy = cam.band_offsets[b]
        errs = []
        for v in np.linspace(-0.8 * h, 0.8 * h, 25):
            p = cam.project(pose.to_camera(np.array([[-h, v, 0.0]])))[0]
            i = int(round(p[1] - dy))
            # edge point on that band's row i: bisect along the edge
            lo_v, hi_v = -h, h
            f = lambda vv: cam.project(pose.to_camera(np.array([[-h, vv, 0.0]])))[0][1] - (i + dy)
            if f(lo_v) * f(hi_v) > 0:
                continue
            for _ in range(60):
                mid = 0.5 * (lo_v + hi_v)
                lo_v, hi_v = (mid, hi_v) if f(lo_v) * f(mid) > 0 else (lo_v, mid)
            xe = cam.project(pose.to_camera(np.array([[-h, lo_v, 0.0]])))[0][0]
            j0 = int(np.floor(xe - dx))
            row = br[b, i, j0 - 4:j0 + 6]
            xs = np.arange(j0 - 4, j0 + 6) + dx
            mid_level = 0.5 * (row[:3].mean() + row[-3:].mean())
            k = np.nonzero((row[:-1] >= mid_level) & (row[1:] < mid_level))[0]
            if len(k) != 1:
                continue
            k = k[0]
            errs.append(xs[k] + (row[k] - mid_level) / (row[k] - row[k + 1]) - xe)
        assert len(errs) > 15
        assert abs(np.mean(errs)) < 0.05


def test_vignetting_truth_off_centre_per_band_with_30_to_50_percent_corner_falloff(truth):
    V = truth.vignetting
    assert V.shape == (25, 217, 409)
    np.testing.assert_allclose(V.max(axis=(1, 2)), 1.0)
    corners = V[:, [0, 0, -1, -1], [0, -1, 0, -1]]
    assert corners.min() >= 0.5 and corners.max() <= 0.7  # falloff 30-50 % at every corner
    centres = truth.vignetting_centre
    assert np.all(np.abs(centres - [204.0, 108.0]).max(axis=1) > 0.5)  # off-centre
    assert centres[:, 0].std() > 2.0 and centres[:, 1].std() > 1.0  # differs by band
    assert np.ptp(corners.mean(axis=1)) > 0.03  # strength differs by band
    for b in (0, 12, 24):  # maximum at the band's own centre
        i, j = np.unravel_index(np.argmax(V[b]), V[b].shape)
        assert abs(j - centres[b, 0]) <= 1.5 and abs(i - centres[b, 1]) <= 1.5


def test_spectral_factor_and_inverse_response_truth(truth):
    Sf = truth.spectral_factor
    assert Sf.shape == (25,) and Sf.min() >= 1.5 and Sf.max() <= 2.5 and np.ptp(Sf) > 0.3
    U = truth.inverse_response
    assert U.shape == (25, 1024)
    k_ref = 511
    np.testing.assert_allclose(U[:, k_ref], k_ref - truth.black_level)
    assert np.all(np.diff(U, axis=1) >= 0) and np.all(U[:, :32] == 0)


def test_response_sweep_is_consistent_with_eq4(truth):
    rs = S.response_sweep(truth, seed=0, n_frames=5, step=3.0)
    t = rs.exposure_ms
    np.testing.assert_allclose(t[1:] / t[:-1], 3.0, rtol=2e-3)
    E = rs.truth["energy"]
    lo, hi = np.percentile(E, [1, 99])
    assert 2.3 < np.log10(hi / lo) < 3.2  # radiance spans ~2.5 decades (plus V)
    U = truth.inverse_response[0]
    dn = rs.dn[3].astype(int)
    ok = (dn > 150) & (dn < 850)
    ratio = U[dn[ok]] / (t[3] * E[ok])  # Eq. 4: U(I) = t E
    assert abs(np.median(ratio) - 1) < 0.01
    assert rs.dn[0].dtype == np.uint16 and rs.raw(0).shape == (1088, 2048)
    np.testing.assert_array_equal(demosaic(rs.raw(2), (5, 5), grid_shape=(217, 409)), rs.dn[2])
    # the shortest exposure is short, the longest saturates much of the scene
    assert (rs.dn[0] >= 1023).mean() == 0 and (rs.dn[-1] >= 1023).mean() > 0.2


def test_gradient_shadow_light_is_2_to_1_with_a_soft_shadow():
    light = S.GradientShadowLight(brightness=300.0, gradient_dir=0.7, gradient_ratio=2.0,
                                  extent_m=(0.5, 0.5), shadow_depth=0.4, shadow_dir=2.0,
                                  shadow_offset_m=0.1, shadow_softness_m=0.01)
    u, v = np.meshgrid(np.linspace(-0.25, 0.25, 401), np.linspace(-0.25, 0.25, 401))
    g = light.gradient(u, v)
    assert g.max() / g.min() == pytest.approx(2.0, rel=1e-6)
    sh = light.shadow(u, v)
    assert sh.min() == pytest.approx(0.6, abs=0.01) and sh.max() == pytest.approx(1.0, abs=0.01)
    q = np.linspace(-0.25, 0.25, 2001)
    s1 = light.shadow(q * np.cos(2.0), q * np.sin(2.0))
    assert np.abs(np.diff(s1) / np.diff(q)).max() < 0.4 / (4 * 0.01) * 1.01  # smooth edge


def test_reflector_images_truth(truth):
    rf = S.reflector_images(truth, seed=0, n_images=1)
    T = rf.truth
    gray, B = T["gray_mask"][0], T["B"][0]
    assert gray.mean() > 0.4  # the reflector fills much of the frame
    light = S.GradientShadowLight.from_params(T["light"][0])
    u, v = np.meshgrid(T["plane_u"], T["plane_v"])
    g = light.gradient(u, v)
    assert g.max() / g.min() == pytest.approx(2.0, rel=1e-3)  # 2:1 gradient across it
    in_shadow = light.shadow(u, v) < 1 - 0.5 * light.shadow_depth
    assert 0.1 < in_shadow.mean() < 0.45
    assert B[gray].max() / B[gray].min() > 1.8
    # Eq. 2/4/11 on band 0 (B is given at band 0's sample positions): U(I)/(t V) = S B R_s
    U = truth.inverse_response[0]
    dn = rf.dn[0][0].astype(int)
    ok = gray & (dn < 850) & (dn > 100)
    L = U[dn[ok]] / (rf.exposure_ms[0] * truth.vignetting[0][ok])
    ratio = L / (truth.spectral_factor[0] * B[ok] * truth.reflector_reflectance[0])
    assert abs(np.median(ratio) - 1) < 0.01
    # brightest gray-reflector pixel at 70-85 % of range (plus noise)
    assert 0.65 * 1023 < rf.dn[0][:, gray].max() < 0.9 * 1023


def test_vignetting_views_small(truth):
    fs = S.vignetting_views(truth, seed=3, n_views=4, n_missing=1)
    T = fs.truth
    assert len(fs) == 4 and T["marker_in_frame"].tolist().count(False) == 1
    k_missing = int(np.flatnonzero(~T["marker_in_frame"])[0])
    assert all(_detect(fs.dn[k_missing][b]) is None for b in (0, 12, 24))
    d = np.linalg.norm(T["tvec"], axis=1)
    for k in np.flatnonzero(T["marker_in_frame"]):
        assert _detect(fs.dn[k][0]) is not None
        assert 0.75 < d[k] < 1.8
        # tilt of the plane normal from the optical axis <= 35 deg
        R = cv2.Rodrigues(T["rvec"][k])[0]
        assert math.degrees(math.acos(-R[2, 2])) <= 35.5
        gray = T["gray_mask"][k]
        assert 0.65 * 1023 < fs.dn[k][:, gray].max() < 0.9 * 1023
    # Eq. 1-4: U(I)/t = V S B R_s on the gray reflector, B fixed on the plane (all views)
    light = S.GradientShadowLight.from_params(T["light"])
    U = truth.inverse_response[5]
    k = int(np.flatnonzero(T["marker_in_frame"])[0])
    R = cv2.Rodrigues(T["rvec"][k])[0]
    pose = S.Pose(T["rvec"][k], T["tvec"][k])
    ii, jj = np.nonzero(T["gray_mask"][k])
    px = np.stack([jj + truth.camera.band_offsets[5, 0], ii + truth.camera.band_offsets[5, 1]], 1)
    rays = np.c_[truth.camera.rays(px), np.ones(len(px))]
    C = pose.camera_centre
    D = rays @ R  # plane-frame directions (R^T d)
    s = -C[2] / D[:, 2]
    uv = C[:2] + s[:, None] * D[:, :2]
    B = light(uv[:, 0], uv[:, 1])
    dn = fs.dn[k][5][ii, jj].astype(int)
    ok = (dn > 100) & (dn < 850)
    model = fs.exposure_ms[k] * truth.vignetting[5][ii, jj] * truth.spectral_factor[5] * B * 0.5
    assert abs(np.median(U[dn[ok]] / model[ok]) - 1) < 0.01


def test_flight_truth(truth):
    fl = S.flight_frames(truth, seed=0, n_frames=3)
    T = fl.truth
    names = list(T["material_names"])
    assert names[:2] == ["soil", "vegetation"] and len(names) == 6
    red, nir = T["ndvi_bands"]
    assert truth.camera.wavelengths[red] == 670 and truth.camera.wavelengths[nir] == 803
    Rveg = T["material_reflectance"][1]
    ndvi_veg = (Rveg[nir] - Rveg[red]) / (Rveg[nir] + Rveg[red])
    assert 0.75 < ndvi_veg < 0.92 and Rveg[red] < 0.06 and Rveg[nir] > 0.4
    labels, ndvi = T["labels"], T["ndvi"]
    assert 0.78 < np.median(ndvi[labels == 1]) < 0.9
    assert np.median(ndvi[labels == 0]) < 0.3
    # panels: pure pixels carry the panel reflectance, in every band
    for p, rho in enumerate(T["panel_reflectance"]):
        sel = labels == 2 + p
        counts = sel.reshape(len(fl), -1).sum(axis=1)
        assert (counts > 100).sum() >= 2  # seen in several frames ...
        rows = [np.mean(np.nonzero(sel[k])[0]) for k in range(len(fl)) if counts[k] > 100]
        assert np.ptp(rows) > 20  # ... at different image positions
        np.testing.assert_allclose(T["reflectance"].transpose(1, 0, 2, 3)[:, sel].astype(float),
                                   rho, atol=2e-3)
    # Eq. 15 with the true U, V, S and the frame's sun: R = U(I) / (t V S B)
    U = truth.inverse_response
    for k in range(len(fl)):
        sel = labels[k] == 4  # the 0.5 panel
        for b in (red, nir, 0):
            dn = fl.dn[k][b][sel].astype(int)
            R = U[b][dn] / (fl.exposure_ms[k] * truth.vignetting[b][sel]
                            * truth.spectral_factor[b] * T["sun"][k])
            assert abs(np.median(R) - 0.5) < 0.01
    assert np.ptp(T["sun"]) > 0 and np.ptp(fl.exposure_ms) > 0
    assert all(47 < m["lat"] < 48 and 8 < m["lon"] < 9 and m["alt_m"] > 400 for m in fl.meta)
    assert max(d.max() for d in fl.dn) < 0.86 * 1023  # auto exposure: no saturation


def test_seeded_reproducible_and_seed_dependent():
    a, b, c = S.make_truth(4), S.make_truth(4), S.make_truth(5)
    assert np.array_equal(a.vignetting, b.vignetting)
    assert not np.array_equal(a.vignetting, c.vignetting)
    assert np.array_equal(a.spectral_factor, b.spectral_factor)
    r1 = S.reflector_images(a, seed=4, n_images=1)
    r2 = S.reflector_images(b, seed=4, n_images=1)
    r3 = S.reflector_images(a, seed=5, n_images=1)
    assert np.array_equal(r1.dn[0], r2.dn[0]) and r1.exposure_ms[0] == r2.exposure_ms[0]
    assert not np.array_equal(r1.dn[0], r3.dn[0])


@pytest.mark.slow
@pytest.mark.long  # ~20 s (full-size dataset): make test-long; the small datasets stay in make test
def test_full_vignetting_dataset_covers_the_whole_image(truth):
    fs = S.vignetting_views(truth, seed=0, n_views=40, n_missing=2)
    T = fs.truth
    assert len(fs) == 40 and (~T["marker_in_frame"]).sum() == 2
    assert T["coverage"].min() >= 2  # every pixel, corners included, on the gray reflector
    d = np.linalg.norm(T["tvec"], axis=1)
    assert d.min() < 1.0 and d.max() > 1.4
    err = T["pose_error_deg"][T["marker_in_frame"]]
    assert np.median(err) < 2.0


def test_light_nonuniformity_scales_gradient_and_shadow_with_the_same_draws():
    size = (0.5, 0.5)
    uu, vv = np.meshgrid(np.linspace(-0.24, 0.24, 97), np.linspace(-0.24, 0.24, 97))

    def light(a):
        return S.random_light(np.random.default_rng(3), 300.0, size, nonuniformity=a)

    default, flat, strong = light(1.0), light(0.0), light(2.0)
    # a = 1 is the default light, draw for draw
    assert default.params().tolist() == S.random_light(np.random.default_rng(3), 300.0, size).params().tolist()
    assert default.gradient_ratio == 2.0
    # a = 0: uniform; a = 2: 4:1 gradient and shadow transmission squared
    np.testing.assert_allclose(flat(uu, vv), 300.0, rtol=1e-6)
    assert strong.gradient_ratio == 4.0
    np.testing.assert_allclose(1.0 - strong.shadow_depth, (1.0 - default.shadow_depth) ** 2, rtol=1e-12)
    spread = [float(b.max() / b.min()) for b in (default(uu, vv), strong(uu, vv))]
    assert spread[1] > 1.5 * spread[0] > 1.5 * 2.0
    with pytest.raises(ValueError, match="nonuniformity"):
        light(-0.5)
