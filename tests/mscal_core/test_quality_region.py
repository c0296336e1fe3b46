"""mscal_core.quality.region_median: a region's median that the shoulder flag does not bias
(pixels flagged high counted as above it, the region flagged from half its pixels flagged)."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.quality import CENSOR_HIGH, FLAGS, region_median

SAT, SHOULDER, OUT, UNSEEN = (FLAGS[k] for k in ("saturated", "response_shoulder", "outside_sweep",
                                                  "vignetting_unobserved"))


def test_the_bits_that_censor_high() -> None:
    assert CENSOR_HIGH == SAT | SHOULDER | OUT
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
