"""The synthetic sensor: response shape, true inverse response in the project gauge, noise
levels and clipping (pipeline.sim.world.sensor)."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from pipeline.sim.world.sensor import SensorModel

SENSOR = SensorModel()  # 10-bit, black 32, read 1.5 DN, shot 9 DN at full scale


def test_defaults_are_the_documented_sensor() -> None:
    s = SENSOR
    assert (s.bits, s.black_level, s.read_noise_dn, s.shot_noise_dn_at_full) == (10, 32.0, 1.5, 9.0)
    assert s.shoulder_start == 0.85 and s.dn_max == 1023 and s.k_ref == 511
    assert 0 < s.curvature < 0.1


def test_response_is_monotone_from_black_to_saturation() -> None:
    x = np.linspace(0.0, 3000.0, 30001)
    c = SENSOR.response(x)
    assert c[0] == pytest.approx(32.0)
    assert np.all(np.diff(c) >= 0)
    assert c.max() == 1023.0
    # saturates at a finite energy and stays there
    x_sat = float(SENSOR.x_for_dn(1023))
    assert 1000 < x_sat < 1400
    assert np.all(SENSOR.response(np.array([x_sat * 1.01, 1e6])) == 1023.0)
    # near-linear start: slope 1 DN per unit x at 0
    assert (SENSOR.response(np.array([1e-3]))[0] - 32.0) / 1e-3 == pytest.approx(1.0, rel=1e-3)


def test_curvature_is_mild_and_shoulder_is_soft() -> None:
    s = SENSOR
    x = np.linspace(0.0, float(s.x_for_dn(0.85 * 1023)), 200)[1:]
    c = s.response(x) - s.black_level
    # below the shoulder: a few % compression, never more
    ratio = c / x
    assert 0.95 < ratio.min() < 0.99 and ratio.max() <= 1.0
    # slope just below the shoulder start equals the slope just above (no kink),
    # and has dropped to about a third of the linear slope at saturation
    xs = float(s.x_for_dn(0.85 * 1023))
    h = 1e-3
    below = (s.response(np.array([xs - h])) - s.response(np.array([xs - 2 * h])))[0] / h
    above = (s.response(np.array([xs + 2 * h])) - s.response(np.array([xs + h])))[0] / h
    assert above == pytest.approx(below, rel=1e-3)
    xsat = float(s.x_for_dn(1023))
    top = (s.response(np.array([xsat - h])) - s.response(np.array([xsat - 2 * h])))[0] / h
    assert top / below == pytest.approx(1 / 3, rel=0.02)


def test_x_for_dn_inverts_the_response() -> None:
    x = np.linspace(0.0, float(SENSOR.x_for_dn(1022.9)), 500)
    assert np.allclose(SENSOR.x_for_dn(SENSOR.response(x)), x, atol=1e-6)
    assert SENSOR.x_for_dn(10.0) == 0.0


def test_inverse_response_gauge() -> None:
    u = SENSOR.inverse_response()
    assert u.shape == (1024,) and u.dtype == np.float64
    assert np.all(u[:33] == 0.0)  # U = 0 at and below the black level (32)
    assert u[511] == pytest.approx(511 - 32)
    assert np.all(np.diff(u) >= 0) and np.all(np.diff(u[33:]) > 0)
    # U is C^-1 rescaled: U(C(x)) proportional to x
    x = np.array([100.0, 300.0, 600.0, 900.0])
    k = SENSOR.response(x)
    interp = np.interp(k, np.arange(1024), u)
    assert np.allclose(interp / x, interp[0] / x[0], rtol=1e-4)


def test_gamma_8bit_camera() -> None:
    s = SensorModel(
        bits=8, black_level=0.0, read_noise_dn=0.6, shot_noise_dn_at_full=2.0, gamma=2.2
    )
    u = s.inverse_response()
    assert u.shape == (256,) and u[0] == 0.0 and u[127] == pytest.approx(127.0)
    assert np.all(np.diff(u) > 0)
    # strongly convex U (display gamma): U(64) much less than half of U(128)
    assert u[64] / u[128] < 0.3


def test_dark_frame_noise_is_read_noise() -> None:
    rng = np.random.default_rng(1)
    frame = SENSOR.expose(np.zeros(200_000), 10.0, rng)
    assert frame.dtype == np.uint16
    assert frame.mean() == pytest.approx(32.0, abs=0.02)
    assert frame.std() == pytest.approx(np.sqrt(1.5**2 + 1 / 12), rel=0.02)


@pytest.mark.parametrize("fraction", [0.25, 0.6])
def test_shot_noise_variance_scales_with_signal(fraction: float) -> None:
    """variance = read^2 + shot_full^2 * (mu - black) / (dn_max - black) (+ 1/12 rounding)."""
    s = SENSOR
    mu = s.black_level + fraction * (s.dn_max - s.black_level)
    energy = np.full(200_000, float(s.x_for_dn(mu)))
    frame = s.expose(energy, 1.0, np.random.default_rng(2)).astype(np.float64)
    expected_var = 1.5**2 + 81.0 * fraction + 1 / 12
    assert frame.mean() == pytest.approx(mu, abs=0.1)
    assert frame.var() == pytest.approx(expected_var, rel=0.03)


def test_noise_rms_at_full_scale() -> None:
    s = SENSOR
    assert np.sqrt(s.noise_variance(1023.0)) == pytest.approx(np.sqrt(81 + 2.25))
    # empirically at 96.5 % of full scale (the clip is 3.9 sigma above)
    mu = 0.965 * 1023
    frame = s.expose(np.full(200_000, float(s.x_for_dn(mu))), 1.0, np.random.default_rng(3))
    shot_rms = np.sqrt(frame.astype(np.float64).var() - 1.5**2 - 1 / 12)
    assert shot_rms == pytest.approx(9.0 * np.sqrt((mu - 32) / 991), rel=0.03)


def test_clipping_and_saturation() -> None:
    s = SENSOR
    rng = np.random.default_rng(4)
    frame = s.expose(np.array([0.0, 1.0, 1e3, 1e9]), 50.0, rng)
    assert frame.dtype == np.uint16 and frame[-1] == 1023 and frame[-2] == 1023
    # far beyond saturation every sample reads exactly dn_max (noise is added before the clip)
    far = s.expose(np.full(10_000, 3 * float(s.x_for_dn(1023))), 1.0, rng)
    assert np.all(far == 1023)
    # a zero-black sensor clips dark noise at 0, never wraps around
    s0 = SensorModel(black_level=0.0, read_noise_dn=3.0)
    dark = s0.expose(np.zeros(10_000), 1.0, rng)
    assert dark.min() == 0 and dark.max() < 20


def test_expose_is_seeded() -> None:
    e = np.linspace(0, 1, 1000)
    a = SENSOR.expose(e, 500.0, np.random.default_rng(7))
    b = SENSOR.expose(e, 500.0, np.random.default_rng(7))
    assert np.array_equal(a, b)
    assert a.shape == e.shape


def test_bad_parameters_are_rejected() -> None:
    with pytest.raises(InputError):
        SensorModel(black_level=1000.0)
    with pytest.raises(InputError):
        SensorModel(curvature=1.5)
    with pytest.raises(InputError):
        SENSOR.expose(np.ones(3), 0.0, np.random.default_rng(0))
