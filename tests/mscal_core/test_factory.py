"""mscal_core.factory: MicaSense's published radiometric model, on hand-computed numbers and on
the real RedEdge panel capture (values MicaSense's own tests assert, see the data README)."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.factory import (
    field_response_scale,
    field_response_signal,
    panel_stats,
    polygon_mask,
    radial_vignetting,
    radiance,
    vignetting_2d,
    vignetting_map,
)
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.tiff import read_raw
from tests.micasense_data import PANEL_CORNERS, PANEL_RADIANCE, PANEL_RAW_DN, band_file


def test_radial_vignetting_is_one_over_the_polynomial() -> None:
    v = radial_vignetting((5, 7), center=(3.0, 2.0), poly=[0.1, 0.01])
    assert v[2, 3] == 1.0
    r = np.hypot(6 - 3.0, 4 - 2.0)
    assert v[4, 6] == pytest.approx(1.0 / (1 + 0.1 * r + 0.01 * r**2))


def test_2d_vignetting_uses_normalised_coordinates_and_exponent_pairs() -> None:
    # 1 + 0.5 u^1 v^0 + 0.25 u^0 v^2, u = x / W, v = y / H
    v = vignetting_2d((4, 8), [1.0, 0.5, 0.25], [0, 0, 1, 0, 0, 2])
    assert v[0, 0] == 1.0
    assert v[2, 4] == pytest.approx(1.0 / (1 + 0.5 * 0.5 + 0.25 * 0.5**2))
    with pytest.raises(ValueError, match="two exponents per coefficient"):
        vignetting_2d((4, 8), [1.0, 0.5], [0, 0, 1])
    with pytest.raises(ValueError, match="no vignetting model"):
        vignetting_map((4, 8))


def test_radiance_formula_by_hand() -> None:
    dn = np.array([[20000.0, 4000.0], [20000.0, 20000.0]])
    te, g, a1, a2, a3 = 0.002, 2.0, 1e-4, 1e-7, 1e-6
    vig = np.array([[1.0, 1.0], [1.0, 1.5]])
    out = radiance(dn, exposure_s=te, gain=g, black_level=4800, calibration=(a1, a2, a3), vignetting=vig)
    p = (20000 - 4800) / 65536
    assert out[0, 0] == pytest.approx(a1 / g * p / te)  # row 0: no row gradient
    assert out[1, 1] == pytest.approx(1.5 * a1 / g * p / (te + a2 * 1 - a3 * te * 1))
    assert out[0, 1] == 0.0  # below the black level: floored, never negative


def test_radiance_in_place_equals_the_expression_bit_for_bit() -> None:
    """radiance() works in place on one float64 array; every product keeps the
    order of the published expression, so the values are the expression's, bit for bit, and
    ``out`` (float32) holds them rounded once."""
    rng = np.random.default_rng(3)
    dn = rng.integers(0, 65535, size=(37, 29), dtype=np.uint16)
    vig = 1.0 + rng.random((37, 29))
    te, g, bl, cal = 0.0013, 2.0, 4800.5, (2.7e-4, 3.1e-7, 1.4e-5)
    y = np.arange(37, dtype=np.float64)[:, None]
    row = te / (te + cal[1] * y - cal[2] * te * y)
    p = (dn.astype(np.float64) - bl) / 65536.0
    expected = np.maximum(vig * p * row * (cal[0] / (g * te)), 0.0)
    kw = dict(exposure_s=te, gain=g, black_level=bl, calibration=cal, vignetting=vig)
    got = radiance(dn, **kw)
    assert got.dtype == np.float64 and np.array_equal(got, expected)
    assert (expected == 0).sum() > 50  # the floor is exercised
    out = np.full(dn.shape, -1.0, np.float32)
    assert radiance(dn, out=out, **kw) is out
    assert np.array_equal(out, expected.astype(np.float32))
    nan_vig = vig.copy()
    nan_vig[::5, ::3] = np.nan  # a field vignetting's undefined pixels: NaN kept, the rest floored as before
    out = np.full(dn.shape, -1.0, np.float32)
    with np.errstate(invalid="ignore"):
        want = np.maximum(nan_vig * p * row * (cal[0] / (g * te)), 0.0).astype(np.float32)
    assert np.array_equal(radiance(dn, out=out, **{**kw, "vignetting": nan_vig}), want, equal_nan=True)
    assert np.isnan(out).sum() == np.isnan(nan_vig).sum() and not np.signbit(out[out == 0]).any()
    signal = rng.random((37, 29))  # a field response in place of p - p_BL
    assert np.array_equal(radiance(dn, signal=signal, **kw), np.maximum(vig * signal * row * (cal[0] / (g * te)), 0.0))


def test_factory_vignetting_is_computed_once_and_read_only() -> None:
    """The map depends on the band's tags only: one computation per process and tags, shared
    by every capture, and read-only so that no caller can change it for the next capture."""
    from pipeline.ingest.meta import factory_vignetting

    meta = read_capture_meta(band_file("0000", 2))
    v = factory_vignetting(meta)
    assert factory_vignetting(read_capture_meta(band_file("0001", 2))) is v  # same camera band, other capture
    assert np.array_equal(v, vignetting_map(meta.shape, meta.vignetting_center, meta.vignetting_polynomial))
    assert not v.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        v[0, 0] = 0.0
    assert factory_vignetting(read_capture_meta(band_file("0000", 3))) is not v  # another band, its own map


def test_panel_stats_counts_and_saturation() -> None:
    img = np.arange(20.0).reshape(4, 5)
    mask = polygon_mask(img.shape, [(1, 1), (3, 1), (3, 2), (1, 2)])
    assert mask.sum() == 6  # 3 x 2 pixels, edges included
    s = panel_stats(img, mask, saturation=12)
    assert (s.mean, s.count, s.saturated) == (pytest.approx(np.mean([6, 7, 8, 11, 12, 13])), 6, 1)


@pytest.mark.parametrize("band", [1, 2, 3, 4, 5])
def test_panel_raw_dn_matches_micasense(band: int) -> None:
    path = band_file("0000", band)
    dn = read_raw(path)
    mask = polygon_mask(dn.shape, PANEL_CORNERS[band - 1])
    stats = panel_stats(dn, mask, saturation=65000)
    assert stats.mean == pytest.approx(PANEL_RAW_DN[band - 1], rel=1e-3)
    assert stats.saturated == 0


@pytest.mark.parametrize("band", [1, 2, 3, 4, 5])
def test_panel_factory_radiance_matches_micasense(band: int) -> None:
    path = band_file("0000", band)
    meta = read_capture_meta(path)
    rad = factory_radiance(meta, read_raw(path))
    mask = polygon_mask(rad.shape, PANEL_CORNERS[band - 1])
    assert panel_stats(rad, mask).mean == pytest.approx(PANEL_RADIANCE[band - 1], rel=1e-3)


def test_vignetting_polynomial_divides() -> None:
    """The polynomial form is pinned by the data: the panel sits near the vignetting centre
    (V about 1.004 there), yet multiplying by the polynomial instead misses by > 0.5 %."""
    path = band_file("0000", 1)
    meta = read_capture_meta(path)
    dn = read_raw(path)
    mask = polygon_mask(dn.shape, PANEL_CORNERS[0])
    right = vignetting_map(meta.shape, meta.vignetting_center, meta.vignetting_polynomial)
    kwargs = dict(exposure_s=meta.exposure_s, gain=meta.gain, black_level=meta.black_level,
                  calibration=meta.radiometric_calibration)
    wrong = panel_stats(radiance(dn, vignetting=1.0 / right, **kwargs), mask).mean
    good = panel_stats(radiance(dn, vignetting=right, **kwargs), mask).mean
    assert abs(good / PANEL_RADIANCE[0] - 1) < 1e-3 < 5e-3 < abs(wrong / PANEL_RADIANCE[0] - 1)


def test_field_response_is_put_on_the_factory_scale_from_the_lower_half() -> None:
    k = np.arange(4096, dtype=np.float64)
    black = 4800.0  # stored DN (300 sensor DN << 4)
    u = 2.5 * (k * 16 - black)  # a field U that is linear, in its own units
    c = field_response_scale(u, dn_shift=4, black_level=black, bits_per_sample=16)
    assert c == pytest.approx(1 / (2.5 * 65536), rel=1e-12)
    shoulder = u.copy()
    shoulder[3000:] *= 1.3  # a different shoulder near saturation does not move the scale
    assert field_response_scale(shoulder, dn_shift=4, black_level=black) == pytest.approx(c, rel=1e-12)
    dn = np.array([[4800, 4816], [32768, 65520]], dtype=np.uint16)
    sig = field_response_signal(dn, shoulder, dn_shift=4, scale=c)
    np.testing.assert_allclose(sig[0], [0.0, 16 / 65536], atol=1e-15)
    assert sig[1, 1] == pytest.approx(1.3 * (65520 - black) / 65536)
    # with that signal the radiance is the factory's where the field U is linear
    rad = radiance(dn, exposure_s=0.001, gain=1.0, black_level=black, calibration=(1.0, 0.0, 0.0),
                   vignetting=np.ones((2, 2)), signal=sig)
    plain = radiance(dn, exposure_s=0.001, gain=1.0, black_level=black, calibration=(1.0, 0.0, 0.0),
                     vignetting=np.ones((2, 2)))
    np.testing.assert_allclose(rad[:, 0], plain[:, 0])
    np.testing.assert_allclose(rad[0], plain[0])
    assert rad[1, 1] == pytest.approx(1.3 * plain[1, 1])
    with pytest.raises(ValueError, match="no scale"):
        field_response_scale(np.zeros(4096), dn_shift=4, black_level=black)


def test_dji_alignment_map_is_the_guides_undistort_then_warp() -> None:
    """DJI's steps 2-3 as OpenCV calls (cv2.undistort with the camera matrix about the optical
    centre plus DewarpData's cx, cy, then cv2.warpPerspective with CalibratedHMatrix) and the
    one map of :func:`dji_alignment_map` give the same image (a smooth one: two resamplings
    against one differ only by interpolation)."""
    import cv2

    from mscal_core.vendors import dji_alignment_map, remap_band

    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    img = (1000 + 400 * np.sin(x / 9.0) * np.cos(y / 13.0) + 2 * x).astype(np.float32)
    dewarp = (480.0, 478.0, 6.0, -4.0, -0.3, 0.2, 0.0007, -0.0005, -0.1)
    center = (160.0, 120.0)
    hm = np.array([[1.002, 0.004, 2.5], [-0.003, 0.999, -1.5], [1e-6, -2e-6, 1.0]])
    k = np.array([[dewarp[0], 0, center[0] + dewarp[2]], [0, dewarp[1], center[1] + dewarp[3]], [0, 0, 1]])
    steps = cv2.warpPerspective(cv2.undistort(img, k, np.array(dewarp[4:]), None, k), hm, (w, h),
                                flags=cv2.INTER_LINEAR)
    ours = remap_band(img, dji_alignment_map((h, w), center, dewarp, hm.ravel()))
    inner = (slice(20, h - 20), slice(20, w - 20))
    assert np.isfinite(ours[inner]).all()
    np.testing.assert_allclose(ours[inner], steps[inner], atol=6.0)  # of a 1000 +- 400 image
    assert np.abs(ours[inner] - steps[inner]).mean() < 0.5
    # step 3 alone (no DewarpData): the homography's inverse, a pure shift here
    shift = remap_band(img, dji_alignment_map((h, w), center, None, [1, 0, 3, 0, 1, -2, 0, 0, 1]))
    np.testing.assert_allclose(shift[10:-10, 10:-10], img[12:-8, 7:-13], atol=1e-3)


def test_sentera_relative_radiance_by_hand() -> None:
    """(sum_j M[b, j] DN_j - black) / (g t), floored at 0, NaN where a channel in the mix clips."""
    from mscal_core.vendors import sentera_relative_radiance

    channels = np.array([[[100, 40, 7], [255, 10, 0]], [[20, 60, 255], [50, 50, 50]]], np.uint8)
    matrix = (1.0, -0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # band 0 = R - G/2; channel 2 not in it
    got = sentera_relative_radiance(channels[:, :, 0], black_level=0.0, gain=2.0, exposure_s=0.01, bits_per_sample=8,
                                    channels=channels, matrix=matrix, channel=0)
    # (100 - 20) / 0.02 = 4000; R clipped -> NaN; 20 - 30 < 0 -> 0; (50 - 25) / 0.02 = 1250
    np.testing.assert_array_equal(got, [[4000.0, np.nan], [0.0, 1250.0]])
    own = sentera_relative_radiance(np.array([[10, 4095]], np.uint16), black_level=2.0, gain=1.0, exposure_s=0.5,
                                    bits_per_sample=12)
    np.testing.assert_array_equal(own, [[16.0, np.nan]])
