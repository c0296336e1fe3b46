"""mscal_core.sunsensor: a tilted sun sensor's reading to horizontal irradiance."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core import sunsensor as ss

D = np.deg2rad


def test_level_sensor_looks_up_and_angles_follow_the_sun() -> None:
    np.testing.assert_allclose(ss.sensor_normal(0.3, 0, 0), [0, 0, -1], atol=1e-15)  # yaw alone: still up
    n = ss.sensor_normal(0.0, D(10), 0.0)  # nose up 10 deg: the normal leans back (south when facing north)
    assert ss.tilt_angle(n) == pytest.approx(D(10))
    assert n[0] < 0
    sun = ss.sun_vector(D(40), D(180))  # sun in the south, 40 deg up
    assert ss.incidence_angle(sun, ss.sensor_normal(0, 0, 0)) == pytest.approx(D(50))
    assert ss.incidence_angle(sun, n) == pytest.approx(D(40))  # leaning 10 deg towards it
    assert ss.incidence_angle(sun, ss.sensor_normal(0.0, D(-10), 0.0)) == pytest.approx(D(60))
    east = ss.sun_vector(D(30), D(90))
    np.testing.assert_allclose(east, [0, np.cos(D(30)), -np.sin(D(30))], atol=1e-15)
    # rolling right wing down tilts the normal towards the east (NED, right-handed)
    assert ss.incidence_angle(east, ss.sensor_normal(0, 0, D(20))) == pytest.approx(D(40))


def test_fresnel_against_textbook_values() -> None:
    # one air-glass interface, n = 1.5: R = ((1 - 1.5) / 2.5)^2 = 0.04 at normal incidence
    assert ss.fresnel_transmission(0.0, (1.0, 1.5)) == pytest.approx(0.96)
    # at Brewster's angle p-polarised light is not reflected: T = 1 - Rs / 2
    b = np.arctan(1.5)
    rs = ((np.cos(b) - 1.5 * np.cos(np.arcsin(np.sin(b) / 1.5))) / (np.cos(b) + 1.5 * np.cos(np.arcsin(np.sin(b) / 1.5)))) ** 2
    assert ss.fresnel_transmission(b, (1.0, 1.5)) == pytest.approx(1 - rs / 2, rel=1e-12)
    tau = ss.relative_transmission(D(np.array([0, 30, 60, 80, 90])))
    assert tau[0] == 1.0 and np.all(np.diff(tau) < 0) and tau[-1] < 1e-12
    assert 0.95 < tau[1] < 1.0 and 0.5 < tau[3] < 0.8
    td = ss.diffuse_transmission()
    assert 0.8 < td < 0.95
    assert ss.diffuse_transmission(n=8192) == pytest.approx(td, rel=1e-5)  # the integral converged


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_round_trip_on_random_attitudes(seed: int) -> None:
    """The forward model's reading, inverted with the true diffuse ratio, gives the true
    horizontal irradiance to 1e-12 whatever the tilt, while the raw reading is off by up to
    tens of percent."""
    rng = np.random.default_rng(seed)
    n = 500
    el, az = D(rng.uniform(20, 70, n)), D(rng.uniform(0, 360, n))
    yaw, pitch, roll = D(rng.uniform(0, 360, n)), D(rng.normal(0, 8, n)), D(rng.normal(0, 8, n))
    direct = rng.uniform(0.5, 1.5, n)
    ratio = rng.uniform(0.1, 1.2, n)
    reading = ss.sensor_reading(direct, ratio * direct, el, az, yaw, pitch, roll)
    truth = direct * np.sin(el) + ratio * direct
    got = ss.horizontal_irradiance(reading, el, az, yaw, pitch, roll, diffuse_ratio=ratio)
    assert got.sun_visible.all()
    np.testing.assert_allclose(got.horizontal, truth, rtol=1e-12)
    np.testing.assert_allclose(got.direct, direct, rtol=1e-12)
    raw_error = np.abs(reading / truth - 1)
    assert raw_error.max() > 0.1  # the uncorrected reading is far off somewhere


def test_wrong_diffuse_ratio_costs_less_than_ignoring_tilt() -> None:
    """A clear-sky ratio (1/6) under a true 1/4 sky: the tilt correction still beats the raw
    reading for a sensor tilted 15 degrees towards and away from a 35-degree sun."""
    el, az = D(35), D(180)
    for pitch in (D(15), D(-15)):
        reading = ss.sensor_reading(1.0, 0.25, el, az, 0.0, pitch, 0.0)
        truth = np.sin(el) + 0.25
        est = ss.horizontal_irradiance(reading, el, az, 0.0, pitch, 0.0).horizontal
        assert abs(est / truth - 1) < abs(reading / truth - 1) / 3


def test_sun_behind_the_sensor_is_flagged() -> None:
    got = ss.horizontal_irradiance(0.2, D(10), D(0), 0.0, D(30), 0.0)  # sun low in the north, sensor leaning south
    assert not bool(got.sun_visible)
    assert np.isfinite(got.horizontal)  # diffuse light alone, resting on the ratio


def test_dls2_horizontal_is_direct_times_sin_elevation_plus_scattered() -> None:
    assert ss.dls2_horizontal(2.0, 0.5, np.radians(30.0)) == pytest.approx(2.0 * 0.5 + 0.5)
    assert ss.dls2_horizontal(2.0, 0.5, np.radians(-5.0)) == pytest.approx(0.5)  # sun down: the sky alone


def test_anchored_irradiance_follows_the_sensor_on_the_panels_scale() -> None:
    # two panels at t = 0 and 10; the sensor reads 0.8 of the panels' light at t = 0 and 0.9 at t = 10
    ep = np.array([[1.0, 2.0], [0.8, 1.6]])
    es = ep * np.array([[0.8], [0.9]])
    w = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0], [0.0, 1.0]])  # t = 0, 5, 10, 20 (held beyond)
    ef = np.array([[0.8, 1.6], [0.6, 1.2], [0.72, 1.44], [0.45, 0.9]])
    light = ss.anchored_irradiance(ep, es, w, ef)
    q = np.array([1 / 0.8, 0.5 / 0.8 + 0.5 / 0.9, 1 / 0.9, 1 / 0.9])
    np.testing.assert_allclose(light.ratio[:, 0], q)
    np.testing.assert_allclose(light.irradiance, q[:, None] * ef)
    np.testing.assert_allclose(light.irradiance[[0, 2]], ep)  # the panels get their own light back
    assert light.sensor_used.all()
    # a frame without a reading, and a band whose panels have none, fall back to the panels
    ef2 = ef.copy()
    ef2[1, 0] = np.nan
    es2 = es.copy()
    es2[0, 1] = np.nan
    light2 = ss.anchored_irradiance(ep, es2, w, ef2)
    assert light2.irradiance[1, 0] == pytest.approx(0.9) and not light2.sensor_used[1, 0]
    np.testing.assert_allclose(light2.irradiance[:, 1], w @ ep[:, 1])
    assert not light2.sensor_used[:, 1].any()
    with pytest.raises(ValueError, match="shapes disagree"):
        ss.anchored_irradiance(ep, es, w[:, :1], ef)


def test_ratio_drift_measures_disagreement_between_panels_and_sensor() -> None:
    ep = np.array([[1.0, 1.0], [0.8, 0.8]])
    es = np.array([[0.5, 0.5], [0.4, 0.44]])
    np.testing.assert_allclose(ss.ratio_drift(ep, es), [0.0, 2.0 / (0.8 / 0.44) - 1.0])
    assert np.isnan(ss.ratio_drift(ep, np.array([[0.5, 0.5], [np.nan, 0.4]]))[0])


def test_diffuse_ratio_is_recovered_from_readings_at_changing_attitudes() -> None:
    rng = np.random.default_rng(3)
    n = 40
    el = np.radians(np.linspace(45, 40, n))
    az = np.radians(np.linspace(200, 210, n))
    yaw = rng.uniform(-np.pi, np.pi, n)
    pitch, roll = np.radians(rng.normal(0, 6, n)), np.radians(rng.normal(0, 6, n))
    direct = np.linspace(1.0, 0.9, n)  # a slow fade
    for true in (0.08, 0.3):
        reading = ss.sensor_reading(direct, true * direct, el, az, yaw, pitch, roll)
        reading = reading * (1 + 0.002 * rng.normal(0, 1, n))
        fit = ss.fit_diffuse_ratio(reading, el, az, yaw, pitch, roll)
        assert fit.ratio == pytest.approx(true, rel=0.15) and fit.n == n
        assert fit.roughness < 0.5 * fit.roughness_at  # clearly better than the clear-sky 1/6
    few = ss.fit_diffuse_ratio(reading[:2], el[:2], az[:2], yaw[:2], pitch[:2], roll[:2])
    assert few.ratio == pytest.approx(ss.CLEAR_SKY_DIFFUSE_RATIO) and few.n == 2
