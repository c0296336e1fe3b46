"""mscal_core.zonal: the statistics and their definitions on hand-checked numbers."""

import math

import numpy as np
import pytest

from mscal_core.zonal import zonal_statistics


def test_definitions_on_hand_checked_values() -> None:
    v = np.array([0.1, 0.4, np.nan, 0.2, 0.3, np.inf], dtype=np.float32)  # 4 valid of 6 given
    s = zonal_statistics(v, n_pixels=8)
    assert (s.n_pixels, s.n_valid) == (8, 4)
    assert s.valid_fraction == 0.5
    assert s.mean == pytest.approx(0.25, abs=1e-7)
    assert s.std == pytest.approx(math.sqrt(0.0125), abs=1e-7)  # population: sum((v-m)^2)/n
    assert s.median == pytest.approx(0.25, abs=1e-7)
    # type 7: h = (n-1) p = 0.3 -> 0.1 + 0.3 (0.2 - 0.1); h = 2.7 -> 0.3 + 0.7 (0.4 - 0.3)
    assert s.p10 == pytest.approx(0.13, abs=1e-7)
    assert s.p90 == pytest.approx(0.37, abs=1e-7)


def test_no_valid_value_and_bad_counts() -> None:
    s = zonal_statistics(np.full(3, np.nan), n_pixels=3)
    assert s.n_valid == 0 and s.valid_fraction == 0.0 and math.isnan(s.median) and math.isnan(s.mean)
    assert math.isnan(zonal_statistics(np.empty(0), 0).valid_fraction)
    with pytest.raises(ValueError, match="smaller than"):
        zonal_statistics(np.ones(5), n_pixels=4)
