"""Per-pixel quality flags of Eq. 15 (mscal_core.quality): the tables, their fold into the
reflectance tables, one frame's mask and its counts."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.quality import (
    FLAGS,
    dn_flag_table,
    flag_counts,
    frame_flags,
    mask_tables,
    pixel_flag_table,
    shoulder_mask,
)
from mscal_core.reflectance import eq15_fast, eq15_tables

SAT, SHOULDER, OUT, UNSEEN = (FLAGS[k] for k in ("saturated", "response_shoulder", "outside_sweep",
                                                  "vignetting_unobserved"))


def _uncertainty(n_bands: int = 2, n_dn: int = 16) -> np.ndarray:
    unc = np.full((n_bands, n_dn), 0.01)
    unc[:, 12:] = 0.05  # the shoulder below the clip
    unc[1, 10] = 0.031  # just above the bound
    unc[:, :2] = np.nan  # outside the fit: no uncertainty, not a shoulder
    return unc


def test_dn_flag_table_sets_each_bit_where_its_rule_says() -> None:
    t = dn_flag_table(2, 16, 15, _uncertainty(), 0.03, np.array([[2, 13], [3, 14]]))
    assert t.dtype == np.uint8 and t.shape == (2, 16)
    below = OUT | FLAGS["below_sweep"]  # under the sweep: outside it, and below it
    assert t[0].tolist() == [below, below, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, SHOULDER, SHOULDER, SHOULDER | OUT,
                             SAT | SHOULDER | OUT]
    assert t[1, 10] == SHOULDER and t[1, 2] == below and t[1, 14] == SHOULDER and t[1, 15] == SAT | SHOULDER | OUT
    # a looser bound: 0.031 trusted, 0.05 not
    assert dn_flag_table(2, 16, 15, _uncertainty(), 0.04)[1, 10] == 0
    # without the optional tables only the clip is checked
    assert np.flatnonzero(dn_flag_table(1, 16, 14)[0]).tolist() == [14, 15]


def test_dim_readings_are_not_the_shoulder() -> None:
    """The relative uncertainty of U is U-shaped: large at dim readings (the noise of one
    reading beside a small U) and on the shoulder. Only the upper branch is flagged."""
    k = np.arange(1024, dtype=np.float64)
    unc = np.where(k < 30, np.nan, 0.3 * np.exp(-(k - 30) / 40) + 0.012 + 0.04 * np.clip((k - 980) / 40, 0, None))
    unc = np.stack([unc, unc])
    unc[1, 30:60] = np.inf  # U = 0 at and below black: no relative uncertainty, not flagged either
    m = shoulder_mask(unc, 0.03)
    low = np.flatnonzero(unc[0] > 0.03)
    assert low.min() == 30 and m[0, 30:900].sum() == 0  # dim and above the bound, not flagged
    first = int(np.flatnonzero(m[0]).min())
    assert 997 <= first <= 999 and m[0, first:].all()  # 0.012 + 0.04 (k - 980) / 40 passes 0.03 at 998
    assert np.array_equal(m[0, first:], unc[0, first:] > 0.03)
    assert m[1, :60].sum() == 0 and np.array_equal(m[1], m[0])
    assert not shoulder_mask(np.full((1, 8), np.nan)).any()


def test_the_fits_own_share_has_its_own_bound_on_the_upper_branch() -> None:
    """The fit's share (systematic, kept whole by a region's mean) flags a DN of its upper
    branch (above the DN where it is least) where it passes its bound, even with the total
    under the total's bound and below the total's own least DN (980 here); a large share at
    dim readings is not flagged, and NaN share is not checked."""
    k = np.arange(1024, dtype=np.float64)
    unc = np.where(k < 30, np.nan, 0.3 * np.exp(-(k - 30) / 40) + 0.012 + 0.04 * np.clip((k - 980) / 40, 0, None))
    fit = np.where(k < 30, np.nan, 0.02 * np.exp(-(k - 30) / 40) + 0.002 + 0.004 * np.clip((k - 900) / 40, 0, None))
    m = shoulder_mask(unc[None], 0.03, fit[None], 0.005)
    first = int(np.flatnonzero(m[0]).min())
    assert first == int(np.flatnonzero((k > 500) & (fit > 0.005)).min()) and 929 <= first <= 931
    assert m[0, first:].all() and not m[0, :first].any()  # the dim end's share (0.022 at DN 30) is not
    assert int(np.argmin(np.where(np.isfinite(unc), unc, np.inf))) > 975  # the total's upper branch starts later
    assert np.array_equal(m, shoulder_mask(unc[None], 0.03, fit[None], 0.005) | shoulder_mask(unc[None], 0.03))
    assert np.array_equal(shoulder_mask(unc[None], 0.03, np.full((1, 1024), np.nan)), shoulder_mask(unc[None], 0.03))
    table = dn_flag_table(1, 1024, 1023, unc[None], 0.03, None, fit[None], 0.005)
    assert np.array_equal((table & FLAGS["response_shoulder"]) != 0, m)
    with pytest.raises(InputError, match="response fit uncertainty bound must be positive, got 0"):
        dn_flag_table(1, 1024, 1023, unc[None], 0.03, None, fit[None], 0.0)
    with pytest.raises(InputError, match=r"response fit uncertainty of shape \(1, 8\) does not fit 1 bands x 1024 DN"):
        dn_flag_table(1, 1024, 1023, unc[None], 0.03, None, np.zeros((1, 8)))


def test_dn_flag_table_refuses_what_does_not_fit() -> None:
    with pytest.raises(InputError, match="does not fit 2 bands x 16 DN"):
        dn_flag_table(2, 16, 15, np.zeros((2, 8)))
    with pytest.raises(InputError, match="bound must be positive"):
        dn_flag_table(2, 16, 15, _uncertainty(), 0.0)
    with pytest.raises(InputError, match="does not fit 2 bands"):
        dn_flag_table(2, 16, 15, dn_range=np.array([[1, 2]]))


def test_masked_tables_give_eq15_with_nan_where_flagged() -> None:
    rng = np.random.default_rng(3)
    u = np.cumsum(rng.uniform(0.5, 1.0, (2, 16)), axis=1)
    v = rng.uniform(0.5, 1.0, (2, 5, 6))
    s = np.array([2.0, 4.0])
    cov = np.ones((2, 5, 6), np.uint16)
    cov[1, 0, :3] = 0
    lut, inv_v = eq15_tables(u, v, s)
    dn_flags = dn_flag_table(2, 16, 15, _uncertainty(), 0.03, np.array([[2, 13], [3, 14]]))
    pixel = pixel_flag_table(cov)
    assert pixel.dtype == np.uint8 and pixel.sum() == 3 * UNSEEN
    mlut, minv = mask_tables(lut, inv_v, dn_flags, pixel)
    dn = rng.integers(0, 16, (1, 2, 5, 6)).astype(np.uint16)
    plain = eq15_fast(dn, lut, inv_v, 2.0, 15)[0]
    masked = eq15_fast(dn, mlut, minv, 2.0, 15)[0]
    q = frame_flags(dn[0], dn_flags, pixel)
    assert np.array_equal(np.isnan(masked), q != 0)  # NaN exactly where flagged
    assert np.array_equal(masked[q == 0], plain[q == 0])  # and the unflagged values unchanged
    # looking up only the NaN pixels gives the same mask
    assert np.array_equal(frame_flags(dn[0], dn_flags, pixel, reflectance=masked), q)
    with pytest.raises(InputError, match="outside the flag table"):
        frame_flags(np.full((2, 5, 6), 16, np.uint16), dn_flags, pixel)


def test_flag_counts_count_each_bit_per_band() -> None:
    q = np.zeros((3, 4, 5), np.uint8)
    q[0, 0, :3] = SHOULDER
    q[0, 1, 0] = SHOULDER | UNSEEN
    q[2, 3, :] = FLAGS["no_value"]
    assert flag_counts(q) == [{"response_shoulder": 4, "vignetting_unobserved": 1}, {}, {"no_value": 5}]
