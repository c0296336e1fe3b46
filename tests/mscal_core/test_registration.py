"""Band co-registration on synthetic multi-lens captures with known transforms."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from mscal_core import alignment, homography
from mscal_core import registration as reg
from mscal_core.errors import InputError
from pipeline.sim.world.multilens import REDEDGE_WAVELENGTHS_NM, multilens_capture


@lru_cache(maxsize=None)
def _capture(seed: int, texture: float = 0.12):
    return multilens_capture(seed, texture=texture)


@lru_cache(maxsize=None)
def _registered(seed: int, texture: float = 0.12):
    cap = _capture(seed, texture)
    return reg.register_stack(cap.dn, cap.reference, wavelengths=REDEDGE_WAVELENGTHS_NM)


@pytest.mark.parametrize("seed, texture", [(0, 0.12), (1, 0.0)])
def test_residual_misalignment_below_0_3_px(seed: int, texture: float) -> None:
    """Shifts up to 20 px, rotations up to 1 deg, 1 % scale, perspective, 0.5 px bush
    parallax, different band appearance (vegetation dark in red, bright in NIR); texture 0 is
    a low-texture field (only crop rows and bushes)."""
    cap = _capture(seed, texture)
    regs = _registered(seed, texture)
    shape = cap.dn.shape[1:]
    for b, r in enumerate(regs):
        d = homography.transform_distance(r.homography, cap.homographies[b], shape)
        assert np.sqrt(np.mean(d**2)) < 0.3, (b, r)
        assert d.max() < 0.5, (b, r)
        assert reg.accept(r), (b, r)
        shift = np.linalg.norm(homography.map_points(cap.homographies[b], [[160, 120]]) - [[160, 120]])
        if b != cap.reference:
            assert shift > 2.0  # the test is not trivially satisfied by the identity
            assert r.ecc > 0.5 and r.n_inliers >= 12 and r.residual_px < 1.0
    assert regs[cap.reference].method == "identity"


def test_alignment_restores_band_to_band_gradient_correlation() -> None:
    cap = _capture(0, 0.12)
    regs = _registered(0, 0.12)
    aligned = alignment.align_bands(cap.dn.astype(np.float32), np.stack([r.homography for r in regs]))
    ok = np.isfinite(aligned).all(axis=0)
    assert 0.6 < ok.mean() < 1.0  # the border no band covers is NaN, the rest kept
    ref = cap.reference
    for b in range(len(regs)):
        if b == ref:
            np.testing.assert_array_equal(aligned[b], cap.dn[b].astype(np.float32))
            continue
        before = reg.gradient_correlation(cap.dn[ref], cap.dn[b], ok)
        after = reg.gradient_correlation(aligned[ref], np.nan_to_num(aligned[b]), ok)
        assert before < 0.3 and after > 0.6 and after > before + 0.4, (b, before, after)


def test_aligned_ndvi_matches_the_truth_at_edges() -> None:
    """NDVI of the aligned bands against the NDVI of the true reflectance on the reference
    grid: the unaligned bands give errors of tenths at every crop-row edge."""
    cap = _capture(0, 0.12)
    regs = _registered(0, 0.12)
    red, nir = 2, 3
    dn = cap.dn.astype(np.float32) - 100.0  # black level of the synthetic sensor
    true = (cap.reflectance[nir] - cap.reflectance[red]) / (cap.reflectance[nir] + cap.reflectance[red])

    def ndvi_error(stack: np.ndarray) -> float:
        # per-band gain and vignetting differ: normalise each band by its ratio to the truth
        r = stack[red] / np.nanmedian(stack[red] / cap.reflectance[red])
        n = stack[nir] / np.nanmedian(stack[nir] / cap.reflectance[nir])
        err = np.abs((n - r) / (n + r) - true)[20:-20, 20:-20]
        return float(np.nanpercentile(err, 95))

    aligned = alignment.align_bands(dn, np.stack([r.homography for r in regs]))
    before, after = ndvi_error(dn), ndvi_error(aligned)
    assert before > 0.3
    assert after < 0.5 * before and after < 0.2, (before, after)


def test_unrelated_band_fails_the_threshold() -> None:
    cap = _capture(0, 0.12)
    rng = np.random.default_rng(5)
    noise = rng.normal(1000.0, 30.0, cap.dn.shape[1:]).astype(np.float32)
    g_ref = reg.gradient_image(cap.dn[cap.reference])
    r = reg.register_band(g_ref, reg.gradient_image(noise))
    assert not reg.accept(r)
    assert r.ecc < reg.Thresholds().min_ecc or r.n_inliers < reg.Thresholds().min_inliers


def test_feature_route_alone_locates_the_band() -> None:
    cap = _capture(0, 0.12)
    g = [reg.gradient_image(b) for b in cap.dn]
    f = [reg.detect_features(x) for x in g]
    h = reg.feature_homography(*reg.feature_matches(f[cap.reference], f[4]))
    assert h is not None
    d = homography.transform_distance(h, cap.homographies[4], g[0].shape)
    assert d.max() < 1.5


def test_combine_is_robust_to_a_wrong_estimate() -> None:
    shape = (240, 320)
    truth = np.array([[1.001, 0.01, 12.0], [-0.01, 0.999, -7.0], [1e-6, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    est = []
    for _ in range(4):
        h = truth.copy()
        h[:2, 2] += rng.normal(0, 0.1, 2)
        est.append(h)
    est.append(np.array([[1.0, 0.0, 40.0], [0.0, 1.0, 30.0], [0.0, 0.0, 1.0]]))  # an outlier
    h, spread = homography.combine_homographies(est, shape)
    assert homography.transform_distance(h, truth, shape).max() < 0.15
    assert spread < 0.3
    mean = np.mean(est, axis=0)
    assert homography.transform_distance(mean, truth, shape).max() > 5  # a mean would not do


def test_rebase_and_centre_reference() -> None:
    shape = (240, 320)
    hs = np.stack([np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) for dx in (0.0, 10.0, 20.0)])
    assert homography.centre_reference(hs, shape) == 1
    rb = homography.rebase(hs, 1)
    np.testing.assert_allclose(rb[1], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rb[0][:2, 2], [-10.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rb[2][:2, 2], [10.0, 0.0], atol=1e-12)


def test_align_bands_checks_the_band_count() -> None:
    with pytest.raises(InputError, match="2 band transforms for a 3-band stack"):
        alignment.align_bands(np.zeros((3, 8, 8), np.float32), np.tile(np.eye(3), (2, 1, 1)))


def test_mosaic_centre_offsets_and_shift() -> None:
    off = alignment.mosaic_centre_offsets((5, 5))
    np.testing.assert_allclose(off[0], [-0.4, -0.4])
    np.testing.assert_allclose(off[12], [0.0, 0.0])
    np.testing.assert_allclose(off[5 * 4 + 1], [(1 - 2) / 5, (4 - 2) / 5])
    # a plane sampled at each band's own positions becomes the plane at the centre positions
    h, w = 20, 30
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    def f(x, y):
        return 0.5 * x - 0.25 * y + 0.01 * x * y - 0.02 * y**2 + 3

    stack = np.stack([f(xs + dx, ys + dy) for dx, dy in off])
    out = alignment.shift_bands(stack, off)
    centre = f(xs, ys)
    inner = np.s_[2:-2, 2:-2]
    for b in range(25):
        np.testing.assert_allclose(out[b][inner], centre[inner], atol=1e-9)
    assert np.isnan(out[0][0, 0]) and np.isnan(out[24][-1, -1])  # sources outside: NaN


def test_local_motion_reads_shift_rotation_and_scale() -> None:
    from mscal_core.homography import local_motion

    a, s, t = np.radians(0.8), 1.01, (3.5, -2.0)
    c, n = np.cos(a) * s, np.sin(a) * s
    sim = np.array([[c, -n, t[0]], [n, c, t[1]], [0.0, 0.0, 1.0]])
    dx, dy, rot, scale = local_motion(sim, (0.0, 0.0))
    assert (dx, dy) == pytest.approx(t) and rot == pytest.approx(0.8) and scale == pytest.approx(1.01)
    # at another point the shift is the mapped point minus the point; rotation/scale unchanged
    p = np.array([100.0, 50.0])
    q = sim[:2, :2] @ p + sim[:2, 2]
    assert local_motion(sim, tuple(p))[:2] == pytest.approx(tuple(q - p))
    # with perspective: the Jacobian matches finite differences of the mapping
    h = sim.copy()
    h[2, :2] = [2e-5, -1e-5]
    x0 = np.array([320.0, 240.0])

    def f(x: np.ndarray) -> np.ndarray:
        v = h @ np.r_[x, 1.0]
        return v[:2] / v[2]

    eps = 1e-3
    jac = np.stack([(f(x0 + e) - f(x0 - e)) / (2 * eps) for e in np.eye(2) * eps], axis=1)
    dx, dy, rot, scale = local_motion(h * 3.0, tuple(x0))  # scale of H itself is irrelevant
    assert (dx, dy) == pytest.approx(tuple(f(x0) - x0))
    assert rot == pytest.approx(np.degrees(np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1])), abs=1e-6)
    assert scale == pytest.approx(np.sqrt(abs(np.linalg.det(jac))), rel=1e-6)
