"""Tests of mscal_core.reflectance: Eq. 15, panel normalisation, NDVI."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.reflectance import eq15, keep_valid, ndvi, normalise_to_panel, otsu_ndvi_threshold, vegetation_mask

BITS = 10
N_DN = 2**BITS
BLACK = 64


def linear_u(n_bands: int | None = None) -> np.ndarray:
    """U[k] = max(k - black, 0) (linear DN); per band a slightly different gain."""
    base = np.maximum(np.arange(N_DN, dtype=np.float64) - BLACK, 0.0)
    if n_bands is None:
        return base
    return base[None, :] * np.linspace(0.9, 1.1, n_bands)[:, None]


def forward_dn(refl, t, vig, s, b, u_gain=None):
    """DN for reflectance R: U(I) = t V S B R (integer, clipped to 10 bits)."""
    energy = t * vig * s[:, None, None] * b * refl
    if u_gain is not None:
        energy = energy / u_gain[:, None, None]
    return np.clip(np.rint(energy + BLACK), 0, N_DN - 1).astype(np.uint16)


@pytest.fixture()
def setup():
    rng = np.random.default_rng(0)
    n_bands, h, w = 4, 6, 8
    gy, gx = np.mgrid[0:h, 0:w]
    r2 = ((gx - 3.5) ** 2 + (gy - 2.5) ** 2) / 10
    vig = np.stack([1.0 - 0.04 * r2 * (1 + 0.1 * k) for k in range(n_bands)])
    s = np.array([1.5, 1.8, 2.2, 2.5])
    refl = rng.uniform(0.1, 0.6, (n_bands, h, w))
    return n_bands, h, w, vig, s, refl


def test_eq15_inverts_the_forward_model(setup):
    n_bands, h, w, vig, s, refl = setup
    t, b = 2.0, 150.0
    dn = forward_dn(refl, t, vig, s, b)
    out = eq15(dn, linear_u(), t, vig, s, b)
    assert out.dtype == np.float32 and out.shape == (n_bands, h, w)
    # exact up to the DN rounding: +-0.5 DN / (t V S B)
    bound = 0.5 / (t * vig * s[:, None, None] * b)
    assert np.all(np.abs(out - refl) <= bound * 1.0001 + 1e-6)
    # default B = 1: relative reflectance, one scale B
    np.testing.assert_allclose(eq15(dn, linear_u(), t, vig, s), out * b, rtol=1e-6)


def test_eq15_per_band_response_and_frame_stack(setup):
    n_bands, h, w, vig, s, refl = setup
    u = linear_u(n_bands)
    gains = u[:, -1] / (N_DN - 1 - BLACK)
    exposures = np.array([1.0, 2.0, 4.0])
    brightness = np.array([200.0, 90.0, 50.0])
    dn = np.stack([forward_dn(refl, t, vig, s, b, gains) for t, b in zip(exposures, brightness)])
    out = eq15(dn, u, exposures, vig, s, brightness)
    assert out.shape == (3, n_bands, h, w)
    bound = 0.5 * gains[:, None, None] / (exposures[:, None, None, None] * vig * s[:, None, None]
                                          * brightness[:, None, None, None])
    assert np.all(np.abs(out - refl) <= bound * 1.0001 + 1e-6)
    # a brightness map (H, W) and per-band exposures broadcast as well
    bmap = np.full((h, w), 200.0)
    one = eq15(dn[0], u, np.ones((n_bands, 1, 1)), vig, s, bmap)
    np.testing.assert_allclose(one, out[0], rtol=1e-6)


def test_eq15_saturation_zero_and_bad_values(setup):
    n_bands, h, w, vig, s, refl = setup
    dn = np.full((n_bands, h, w), 500, dtype=np.uint16)
    dn[0, 0, 0] = N_DN - 1  # saturated by default (dn_max)
    dn[0, 0, 1] = 900
    dn[0, 0, 2] = 10  # below black: U = 0 -> R = 0
    v = vig.copy()
    v[1, 0, 0] = 0.0
    v[1, 0, 1] = np.nan
    v[1, 0, 2] = -0.5
    out = eq15(dn, linear_u(), 1.0, v, s)
    assert np.isnan(out[0, 0, 0]) and np.isfinite(out[0, 0, 1])
    assert out[0, 0, 2] == 0.0
    assert np.isnan(out[1, 0, :3]).all()
    finite = out[np.isfinite(out)]
    assert (finite >= 0).all() and not np.isinf(out).any()
    assert np.isnan(out).sum() == 4
    # explicit saturation threshold
    out = eq15(dn, linear_u(), 1.0, vig, s, saturation_dn=900)
    assert np.isnan(out[0, 0, 1])
    out = eq15(dn, linear_u(), 1.0, vig, s, saturation_dn=N_DN)
    assert np.isfinite(out).all()
    # non-positive spectral factor or brightness -> NaN, not inf / negative
    out = eq15(dn, linear_u(), 1.0, vig, np.array([0.0, 1.0, -1.0, 1.0]), 2.0)
    assert np.isnan(out[[0, 2]]).all() and np.isfinite(out[[1, 3]]).all()
    u = linear_u()
    u[600] = -3.0  # a non-monotone glitch never gives a negative reflectance
    dn[2, 1, 1] = 600
    assert eq15(dn, u, 1.0, vig, s)[2, 1, 1] == 0.0


def test_eq15_input_errors(setup):
    n_bands, h, w, vig, s, refl = setup
    dn = np.full((n_bands, h, w), 500, dtype=np.uint16)
    u = linear_u()
    with pytest.raises(InputError, match="outside the response table"):
        eq15(dn + 1000, u, 1.0, vig, s)
    with pytest.raises(InputError):
        eq15(dn.astype(float) + 0.5, u, 1.0, vig, s)
    eq15(dn.astype(float), u, 1.0, vig, s)  # integral floats are fine
    with pytest.raises(InputError):
        eq15(dn, u, 0.0, vig, s)
    with pytest.raises(InputError):
        eq15(dn, u, 1.0, vig[:, :3], s)
    with pytest.raises(InputError):
        eq15(dn, u, 1.0, vig, s[:3])
    with pytest.raises(InputError):
        eq15(dn, linear_u(3), 1.0, vig, s)
    with pytest.raises(InputError):
        eq15(dn[0], u, 1.0, vig, s)
    with pytest.raises(InputError):
        eq15(dn[None], u, np.ones(2), vig, s)


def test_normalise_to_panel(setup):
    n_bands, h, w, vig, s, refl = setup
    panel = np.zeros((h, w), bool)
    panel[1:3, 1:4] = True
    truth = refl.copy()
    truth[:, panel] = np.array([0.5, 0.55, 0.6, 0.65])[:, None]
    relative = truth * np.array([3.0, 2.0, 5.0, 1.5])[:, None, None]  # unknown per-band scale
    relative[0, 1, 1] = np.nan  # a bad panel pixel is ignored
    out = normalise_to_panel(relative, panel, [0.5, 0.55, 0.6, 0.65])
    assert out.dtype == np.float32
    assert np.isnan(out[0, 1, 1])
    ok = np.isfinite(relative)
    np.testing.assert_allclose(out[ok], truth[ok], rtol=1e-6)
    # a frame stack with a per-frame scale and a scalar panel reflectance
    stack = np.stack([truth * 2.0, truth * 0.3])
    stack[:, :, panel] = 0.3 * np.array([2.0, 0.3])[:, None, None]
    out = normalise_to_panel(stack, panel, 0.5)
    np.testing.assert_allclose(out[:, :, panel], 0.5, rtol=1e-6)
    np.testing.assert_allclose(out[0], out[1], rtol=1e-6)
    # a band whose panel is all NaN -> NaN band; an empty mask -> error
    bad = relative.copy()
    bad[2][panel] = np.nan
    assert np.isnan(normalise_to_panel(bad, panel, 0.5)[2]).all()
    with pytest.raises(InputError):
        normalise_to_panel(relative, np.zeros((h, w), bool), 0.5)
    with pytest.raises(InputError):
        normalise_to_panel(relative, panel[:2], 0.5)


def test_ndvi():
    red = np.array([0.1, 0.5, 0.0, np.nan, 0.2, 0.0, -0.01, 0.3], dtype=np.float32)
    nir = np.array([0.5, 0.1, 0.4, 0.3, np.inf, 0.0, 0.5, -0.01], dtype=np.float32)
    out = ndvi(red, nir)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[:3], [0.4 / 0.6, -0.4 / 0.6, 1.0], rtol=1e-6)
    assert np.isnan(out[3:6]).all()
    # a negative reflectance pushes the value out of [-1, 1]: NaN, as the catalog's valid_range
    assert np.isnan(out[6]) and np.isnan(out[7])
    finite = out[np.isfinite(out)]
    assert (finite >= -1).all() and (finite <= 1).all()
    assert ndvi(np.array([0.1]), np.array([0.3])).dtype == np.float64


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_keep_valid_bytes_equal_where_with_canonical_nan(dtype) -> None:
    odd_nan = np.array([0xFFC00000], np.uint32).view(np.float32)[0]  # the sign-set NaN 0/0 makes on x86
    v = np.array([-1.0, 1.0, -1.0000001, 1.0000001, 0.25, -0.0, np.inf, -np.inf, np.nan, odd_nan], dtype)
    for valid_range in (None, (-1.0, 1.0), (-np.inf, 1.0)):
        bad = ~np.isfinite(v)
        if valid_range is not None:
            bad |= (v < valid_range[0]) | (v > valid_range[1])
        want = np.where(bad, np.nan, v).astype(dtype)
        got = keep_valid(v.reshape(2, 5), valid_range)
        assert got.dtype == dtype and got.tobytes() == want.tobytes()  # every NaN the canonical one
    kept = keep_valid(v, (-1.0, 1.0))
    assert kept[[0, 1, 4]].tolist() == [-1.0, 1.0, 0.25] and np.isnan(kept[[2, 3, 6, 7, 8, 9]]).all()
    assert np.signbit(kept[5])  # -0.0 kept as it is


def test_vegetation_mask_every_pixel_defined_or_not() -> None:
    """The same mask whether every pixel is defined (no gather, no scatter) or some are NaN."""
    rng = np.random.default_rng(11)
    v = np.concatenate([rng.normal(-0.2, 0.05, 600), rng.normal(0.6, 0.05, 400)]).astype(np.float32).reshape(25, 40)
    full = vegetation_mask(v)
    thr = otsu_ndvi_threshold(v)
    assert full.dtype == np.uint8 and full.shape == v.shape and full.flags.writeable
    assert -0.1 < thr < 0.4 and full.sum() == 400 and (full[v >= thr] == 1).all() and (full[v < thr] == 0).all()
    holed = v.copy()
    holed[0, :3] = np.nan  # three background pixels undefined: the rest split at the same level
    m = vegetation_mask(holed)
    assert (m[0, :3] == 255).all() and np.array_equal(m[1:], full[1:]) and np.array_equal(m[0, 3:], full[0, 3:])
    flat, holed_flat = np.full((3, 3), 0.3, np.float32), np.full((3, 3), 0.3, np.float32)
    holed_flat[0, 0] = np.nan  # one level either way: the same answer for the defined pixels
    assert np.array_equal(vegetation_mask(flat)[1:], vegetation_mask(holed_flat)[1:])


def test_ndvi_matches_the_catalog_index() -> None:
    from pipeline.ingest.catalog import load_index

    rng = np.random.default_rng(3)
    red = rng.uniform(-0.05, 0.6, (40, 50)).astype(np.float32)
    nir = rng.uniform(-0.05, 0.8, (40, 50)).astype(np.float32)
    red[0, :5] = [0, np.nan, np.inf, 0.2, -0.2]
    nir[0, :5] = [0, 0.3, 0.3, -0.2, 0.1]
    ours = ndvi(red, nir)
    stored = load_index("ndvi").evaluate({"red": red, "nir": nir})
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(stored))
    assert np.isnan(ours).sum() > 5  # the edge cases above and negative reflectances
    np.testing.assert_allclose(ours, stored, rtol=1e-6, equal_nan=True)


def test_vegetation_mask_and_its_threshold() -> None:
    from mscal_core.reflectance import otsu_ndvi_threshold, vegetation_mask

    rng = np.random.default_rng(5)
    nd = np.concatenate([rng.normal(0.1, 0.05, 500), rng.normal(0.7, 0.05, 500)]).astype(np.float32)
    nd[:3] = np.nan
    mask = vegetation_mask(nd)
    assert mask.dtype == np.uint8 and (mask[:3] == 255).all()
    assert set(np.unique(mask[3:])) == {0, 1}
    assert (mask[500:] == 1).mean() > 0.99 and (mask[3:500] == 0).mean() > 0.99
    t = otsu_ndvi_threshold(nd)
    assert 0.2 < t < 0.6
    ok = np.isfinite(nd)
    np.testing.assert_array_equal(mask[ok] == 1, nd[ok] >= t)  # the threshold the report shows
    assert (vegetation_mask(np.array([np.nan, 0.3])) == 255).all()
    assert np.isnan(otsu_ndvi_threshold(np.array([0.3])))


def test_eq15_fast_agrees_with_eq15() -> None:
    from mscal_core.reflectance import eq15, eq15_fast, eq15_tables

    rng = np.random.default_rng(4)
    n_bands, h, w = 5, 30, 40
    U = np.cumsum(rng.uniform(0, 2, size=(n_bands, 1024)), axis=1) - 20
    V = rng.uniform(0.4, 1.0, size=(n_bands, h, w))
    V[0, 0, 0] = 0.0
    S = rng.uniform(1.5, 2.5, size=n_bands)
    dn = rng.integers(0, 1024, size=(3, n_bands, h, w)).astype(np.uint16)
    t = np.array([1.5, 2.0, 7.25])
    ref = eq15(dn, U, t, V, S, saturation_dn=1000)
    lut, inv_v = eq15_tables(U, V, S)
    fast = eq15_fast(dn, lut, inv_v, t, 1000)
    assert fast.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    np.testing.assert_allclose(fast, ref, rtol=2e-6, equal_nan=True)
    assert np.isnan(fast[:, 0, 0, 0]).all() and (dn[:, 1:] >= 1000).sum() == np.isnan(fast[:, 1:]).sum()
    assert np.nanmin(fast) >= 0


def test_eq15_fast_writes_into_a_given_array() -> None:
    """``out``: the same values in the caller's array (apply passes a page-aligned one, written
    to the device without a copy); one that does not fit is refused, nothing computed."""
    from mscal_core.reflectance import eq15_fast, eq15_tables

    rng = np.random.default_rng(6)
    n_bands, h, w = 3, 12, 17
    U = np.cumsum(rng.uniform(0, 2, size=(n_bands, 1024)), axis=1)
    V = rng.uniform(0.4, 1.0, size=(n_bands, h, w))
    lut, inv_v = eq15_tables(U, V, np.full(n_bands, 2.0))
    dn = rng.integers(0, 1024, size=(2, n_bands, h, w)).astype(np.uint16)
    t = np.array([1.5, 3.0])
    out = np.full(dn.shape, -1.0, np.float32)
    got = eq15_fast(dn, lut, inv_v, t, 1000, out=out)
    assert got is out
    np.testing.assert_array_equal(out, eq15_fast(dn, lut, inv_v, t, 1000))
    for bad in (np.empty(dn.shape, np.float64), np.empty((2, n_bands, h, w + 1), np.float32),
                np.empty((2, n_bands, w, h), np.float32).transpose(0, 1, 3, 2)):
        with pytest.raises(InputError, match="out must be"):
            eq15_fast(dn, lut, inv_v, t, 1000, out=bad)


def test_eq15_fast_band_scale_is_eq15_with_another_s() -> None:
    """A per-frame, per-band factor k folded into the frame's table is Eq. 15 with S / k."""
    from mscal_core.reflectance import eq15, eq15_fast, eq15_tables

    rng = np.random.default_rng(5)
    n_bands, h, w = 4, 20, 30
    U = np.cumsum(rng.uniform(0, 2, size=(n_bands, 1024)), axis=1)
    V = rng.uniform(0.4, 1.0, size=(n_bands, h, w))
    S = rng.uniform(1.5, 2.5, size=n_bands)
    dn = rng.integers(0, 1024, size=(2, n_bands, h, w)).astype(np.uint16)
    t = np.array([1.5, 3.0])
    k = rng.uniform(0.7, 1.3, size=(2, n_bands))
    lut, inv_v = eq15_tables(U, V, S)
    fast = eq15_fast(dn, lut, inv_v, t, 1000, band_scale=k)
    for f in range(2):
        ref = eq15(dn[f], U, t[f], V, S / k[f], saturation_dn=1000)
        np.testing.assert_allclose(fast[f], ref, rtol=3e-6, equal_nan=True)
    plain = eq15_fast(dn, lut, inv_v, t, 1000)
    np.testing.assert_array_equal(eq15_fast(dn, lut, inv_v, t, 1000, band_scale=None), plain)
    with pytest.raises(InputError, match="positive and finite"):
        eq15_fast(dn, lut, inv_v, t, 1000, band_scale=np.zeros(n_bands))
    with pytest.raises(InputError, match="does not fit"):
        eq15_fast(dn, lut, inv_v, t, 1000, band_scale=np.ones((3, n_bands)))


def test_eq15_fast_refuses_dn_beyond_the_table_in_any_frame() -> None:
    """The lookup clips instead of checking each DN; one check per frame must still refuse a
    DN past the table (a 12-bit frame with a 10-bit calibration), in the last frame too."""
    from mscal_core.reflectance import eq15_fast, eq15_tables

    U = np.tile(np.linspace(0.0, 1.0, 1024), (2, 1))
    lut, inv_v = eq15_tables(U, np.ones((2, 4, 5)), np.ones(2))
    dn = np.full((3, 2, 4, 5), 1023, dtype=np.uint16)
    assert np.isfinite(eq15_fast(dn, lut, inv_v, 1.0, 1024)).all()  # the table's last DN is in it
    dn[2, 1, 3, 4] = 1024
    with pytest.raises(InputError, match="DN 1024 outside the response table 0..1023"):
        eq15_fast(dn, lut, inv_v, 1.0, 1024)
