"""mscal_core.quality.region_median: a region's median that the shoulder flag does not bias
(pixels flagged high counted as above it, the region flagged from half its pixels flagged)."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.quality import CENSOR_HIGH, CENSOR_LOW, FLAGS, region_median

SAT, SHOULDER, OUT, UNSEEN, BELOW = (FLAGS[k] for k in ("saturated", "response_shoulder", "outside_sweep",
                                                         "vignetting_unobserved", "below_sweep"))


def test_the_bits_that_censor_high() -> None:
    assert CENSOR_HIGH == SAT | SHOULDER | OUT and CENSOR_LOW == BELOW
    assert not CENSOR_HIGH & (UNSEEN | FLAGS["not_coregistered"] | FLAGS["no_value"])


def test_pixels_flagged_high_count_above_the_median_and_others_are_left_out() -> None:
    v = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    q = np.zeros(6, np.uint8)
    assert float(region_median(v, q)) == 3.5
    q[5] = SHOULDER  # 1..5 and one above: (3 + 4) / 2, the median with 6 in place
    assert float(region_median(v, q)) == 3.5
    v2 = v.copy()
    v2[5] = np.nan  # its value is never read
    assert float(region_median(v2, q)) == 3.5
    q[4] = UNSEEN  # left out: 1..4 and one above, the 3rd of 5
    assert float(region_median(v, q)) == 3.0
    q[4] = OUT | UNSEEN  # censored wins over left out: 1..4 and two above
    assert float(region_median(v, q)) == 3.5
    q[3] = UNSEEN  # 3 of 6 flagged: the region is flagged ...
    assert np.isnan(region_median(v, q))
    # ... unless allowed: 1..3 and two above, the 3rd of 5
    assert float(region_median(v, q, max_flagged_share=0.6)) == 3.0
    q[3] = SAT  # 1..3 and three above: the median is above every valid value, not a number
    assert np.isnan(region_median(v, q, max_flagged_share=0.9))


def test_one_median_per_row_of_bands() -> None:
    v = np.array([[1.0, 2.0, 3.0, 4.0], [10.0, 20.0, 30.0, 40.0], [5.0, 5.0, 5.0, 5.0]])
    q = np.array([[0, 0, 0, SHOULDER], [0, UNSEEN, 0, 0], [SAT, SAT, 0, 0]], np.uint8)
    np.testing.assert_array_equal(region_median(v, q), [2.5, 30.0, np.nan])
    assert region_median(v, np.uint8(0)).shape == (3,)  # a quality that broadcasts
    assert np.isnan(region_median(np.zeros((2, 0)), np.zeros((2, 0), np.uint8))).all()


def test_a_panel_cut_by_the_shoulder_flag_gets_the_median_of_all_its_pixels() -> None:
    """The shoulder flag cuts a uniform panel's readings at a value: the valid pixels are those
    whose noise read low. Their median is off by about the noise; counted with the flagged
    pixels above, it is the median of every pixel (those flagged all lie above it)."""
    rng = np.random.default_rng(5)
    truth = 0.9 + 0.02 * rng.standard_normal(4001)
    for cut in (0.91, 0.92, 0.95):  # 31 %, 16 %, 0.6 % of the panel flagged
        q = np.where(truth > cut, np.uint8(SHOULDER), np.uint8(0))
        valid_only = float(np.median(truth[q == 0]))
        assert float(region_median(truth, q)) == float(np.median(truth))
        assert valid_only < float(np.median(truth))
    q = np.where(truth > 0.905, np.uint8(SHOULDER), np.uint8(0))  # 40 % flagged
    assert float(np.median(truth)) - float(np.median(truth[q == 0])) > 0.01  # the bias left out
    assert float(region_median(truth, q)) == float(np.median(truth))
    q = np.where(truth > 0.899, np.uint8(SHOULDER), np.uint8(0))  # above half: flagged
    assert np.isnan(region_median(truth, q))


def test_region_median_refuses_what_does_not_fit() -> None:
    with pytest.raises(InputError, match="does not fit"):
        region_median(np.zeros((2, 5)), np.zeros((3, 5), np.uint8))
    with pytest.raises(InputError, match="flagged share"):
        region_median(np.zeros(5), np.zeros(5, np.uint8), max_flagged_share=0.0)


def test_bounds_give_the_median_of_a_panel_cut_where_v_is_high() -> None:
    """A uniform 0.9 panel over a 20 % V gradient, its DN cut at one value: the pixels the cut
    flags are those of highest V, not of highest reflectance. Counted above the median they
    bias it high; with each censored pixel's own bound (the reflectance it would have at the
    cut, the cut DN over its V) the product-limit median is the panel's, well past half the
    pixels cut."""
    rng = np.random.default_rng(3)
    n = 6000
    v = rng.uniform(0.8, 1.0, n)
    truth = 0.9 * (1.0 + 0.015 * rng.standard_normal(n))
    dn = truth * v
    for share in (0.1, 0.3, 0.46, 0.6):
        cut = float(np.quantile(dn, 1.0 - share))
        q = np.where(dn > cut, np.uint8(SHOULDER), np.uint8(0))
        above = float(region_median(truth, q, max_flagged_share=0.95))
        bounded = float(region_median(truth, q, max_flagged_share=0.95, censor_at=cut / v))
        print(f"{share:.0%} cut: counted above {above:.4f}, bounded {bounded:.4f}, all {np.median(truth):.4f}")
        assert abs(bounded - np.median(truth)) < 0.0015  # measured <= 0.0003
        if 0.3 <= share < 0.5:
            assert above - np.median(truth) > 0.005  # measured 0.0065, 0.0177
        if share > 0.5:
            assert np.isnan(above)  # above every valid value: no number
    assert np.isnan(region_median(truth, np.where(dn > np.quantile(dn, 0.4), np.uint8(SHOULDER), np.uint8(0)),
                                  censor_at=np.inf))  # still flagged from half the pixels by default


def test_bounds_agree_with_counting_above_when_every_bound_is_above() -> None:
    rng = np.random.default_rng(8)
    for n in (7, 8, 101, 400):
        x = rng.standard_normal(n)
        q = np.zeros(n, np.uint8)
        assert float(region_median(x, q, censor_at=np.zeros(n))) == float(np.median(x))
        q[np.argsort(x)[-n // 4:]] = SAT
        bounds = np.full(n, np.nan)
        bounds[q != 0] = x.max() + 1.0
        assert float(region_median(x, q, censor_at=bounds)) == float(region_median(x, q))
        assert float(region_median(x, q, censor_at=np.where(q != 0, np.inf, 0.0))) == float(region_median(x, q))


def test_readings_below_the_sweep_count_below() -> None:
    v = np.arange(1.0, 9.0)  # 1..8
    q = np.zeros(8, np.uint8)
    q[:3] = OUT | BELOW  # read below the sweep: the lowest three
    assert float(region_median(v, q)) == 4.5  # as if 1..3 were in place
    assert float(region_median(v, q, censor_at=np.full(8, np.inf))) == 4.5  # the product-limit median too
    q[:3] = OUT  # above the sweep: 4..8 and three above
    assert float(region_median(v, q)) == 7.5
    q[:5] = OUT | BELOW
    assert np.isnan(region_median(v, q, max_flagged_share=0.9))  # the median is among them: not known
    assert np.isnan(region_median(v, q, max_flagged_share=0.9, censor_at=np.full(8, np.inf)))


def test_censor_dn_bounds_each_reading_by_the_trusted_dn_under_it() -> None:
    from mscal_core.quality import censor_dn, dn_flag_table

    flags = dn_flag_table(2, 16, 14, dn_range=np.array([[2, 15], [0, 15]]))
    assert (flags[0, :2] == OUT | BELOW).all() and flags[0, 2] == 0 and not (flags[1] & BELOW).any()
    assert flags[0, 14] == SAT and not flags[0, 14] & BELOW
    flags[1, 9:11] |= SHOULDER  # a hole in the trusted range of band 1
    dn = np.array([[0, 1, 2, 13, 14, 15], [5, 9, 10, 11, 14, 15]], np.uint16)
    bound = censor_dn(dn, flags)
    np.testing.assert_array_equal(bound, [[0, 1, 2, 13, 13, 13], [5, 8, 8, 11, 13, 13]])
    assert bound.dtype == dn.dtype
    with pytest.raises(InputError, match="do not fit"):
        censor_dn(dn[:1], flags)
    with pytest.raises(InputError, match="do not fit"):
        region_median(np.zeros(5), np.zeros(5, np.uint8), censor_at=np.zeros(4))
