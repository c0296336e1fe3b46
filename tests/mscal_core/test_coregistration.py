"""Residual band shifts measured on the pixels (mscal_core.coregistration)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mscal_core.alignment import align_bands
from mscal_core.coregistration import (
    band_residual,
    pooled_affines,
    pooled_translations,
    sample_every,
    stack_residuals,
    tile_boxes,
    translation_transforms,
)


def _scene(shape: tuple[int, int] = (1100, 1500), seed: int = 3) -> np.ndarray:
    """A seeded random smooth pattern (texture at several scales, as fields and trees)."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape, np.float32)
    for sigma, weight in ((2.0, 1.0), (6.0, 2.0), (20.0, 4.0)):
        out += weight * cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), sigma)
    return out


def _band(scene: np.ndarray, h: np.ndarray, shape: tuple[int, int] = (960, 1280)) -> np.ndarray:
    """``band(H x) = scene(x)`` seen on a ``shape`` grid about the scene's (50, 60) px offset:
    the band a lens whose reference-to-band map is ``H`` writes."""
    off = np.array([[1, 0, 60], [0, 1, 50], [0, 0, 1]], np.float64)
    return cv2.warpPerspective(scene, off @ np.linalg.inv(h), (shape[1], shape[0]),
                               flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)


def _shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1]], np.float64)


def test_a_known_shift_is_measured_to_a_tenth_of_a_pixel() -> None:
    scene = _scene()
    ref, band = _band(scene, np.eye(3)), _band(scene, _shift(12.4, -7.3))
    r = band_residual(ref, band)
    assert r.n_tiles == 9  # texture everywhere: every tile used
    assert r.dx == pytest.approx(12.4, abs=0.1) and r.dy == pytest.approx(-7.3, abs=0.1)
    assert r.median_px == pytest.approx(np.hypot(12.4, 7.3), abs=0.1)
    assert band_residual(ref, ref).median_px < 0.01


def test_contrast_reversed_bands_and_nan_borders_are_measured() -> None:
    """Red and NIR over vegetation: one band the negative of the other, a warped band NaN where
    it does not cover (its first 40 columns)."""
    scene = _scene()
    ref = _band(scene, np.eye(3))
    band = 5.0 - 0.5 * _band(scene, _shift(-3.0, 4.0))
    band[:, :40] = np.nan
    r = band_residual(ref, band)
    assert r.n_tiles == 9
    assert r.dx == pytest.approx(-3.0, abs=0.1) and r.dy == pytest.approx(4.0, abs=0.1)


def test_flat_tiles_are_left_out_and_a_flat_band_measures_nothing() -> None:
    scene = _scene()
    ref, band = _band(scene, np.eye(3)), _band(scene, _shift(5.0, 0.0))
    y0, y1, x0, x1 = tile_boxes(ref.shape)[4]
    for img in (ref, band):
        img[y0 - 20:y1 + 20, x0 - 20:x1 + 20] = 1.0  # a panel filling the middle tile
    r = band_residual(ref, band)
    assert r.n_tiles == 8 and r.dx == pytest.approx(5.0, abs=0.1)
    flat = band_residual(np.full((480, 640), 2.0, np.float32), np.full((480, 640), 3.0, np.float32))
    assert flat.n_tiles == 0 and np.isnan(flat.median_px)


def test_pooled_translation_and_affine_align_the_bands() -> None:
    """Three captures of one rig (a rotation and scale on top of a shift in band 2): the pooled
    translation aligns the shifted band to < 0.1 px, the pooled affine the rotated one to < 0.2 px."""
    h_rot = np.vstack([cv2.getRotationMatrix2D((640.0, 480.0), 0.4, 1.004), [0, 0, 1]]) @ _shift(8.0, -5.0)
    stacks = []
    for seed in (1, 2, 3):
        scene = _scene(seed=seed)
        stacks.append(np.stack([_band(scene, np.eye(3)), _band(scene, _shift(-6.0, 9.0)), _band(scene, h_rot)]))
    per_capture = [stack_residuals(s, 0) for s in stacks]
    assert per_capture[0][2].median_px > 5
    t = pooled_translations(per_capture)
    assert t[0].tolist() == [0.0, 0.0] and t[1] == pytest.approx([-6.0, 9.0], abs=0.1)
    a = pooled_affines(per_capture)
    assert a is not None and a[0].tolist() == np.eye(3).tolist()
    for s in stacks:
        after_t = stack_residuals(align_bands(s, translation_transforms(t)), 0)
        after_a = stack_residuals(align_bands(s, a), 0)
        assert after_t[1].median_px < 0.1 and after_a[1].median_px < 0.1
        assert after_a[2].median_px < 0.2 and after_t[2].median_px > 1.0  # a translation cannot undo a rotation


def test_every_nth_capture_at_most_the_limit() -> None:
    assert sample_every(10, 24) == 1 and sample_every(24, 24) == 1
    assert sample_every(25, 24) == 2 and sample_every(600, 24) == 25 and len(range(0, 601, sample_every(601, 24))) <= 24
