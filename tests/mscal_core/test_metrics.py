import numpy as np
import pytest

from mscal_core.metrics import coefficient_of_variation, response_error, spectral_factor_error, vignetting_rms


def test_response_error_ignores_scale_and_sees_shape() -> None:
    k = np.arange(1024, dtype=float)
    u = np.clip(k - 32, 0, None)
    assert response_error(3.0 * u, u) == pytest.approx(0.0, abs=1e-12)
    bent = u * (1 + 0.05 * (k / 1023) ** 2)
    assert 0.01 < response_error(bent, u) < 0.05


def test_vignetting_and_spectral_errors() -> None:
    v = np.linspace(0.5, 1.0, 100)
    assert vignetting_rms(v * 1.01, v) == pytest.approx(0.01)
    s = np.linspace(1.5, 2.5, 25)
    assert spectral_factor_error(7 * s, s) == pytest.approx(0.0, abs=1e-12)
    s2 = s.copy()
    s2[3] *= 1.02
    assert 0.015 < spectral_factor_error(s2, s) < 0.021


def test_cv() -> None:
    assert coefficient_of_variation(np.array([1.0, 1.0, np.nan])) == 0.0
    assert coefficient_of_variation(np.array([0.9, 1.1])) == pytest.approx(0.1)
