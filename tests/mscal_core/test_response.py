"""Inverse response from an exposure sweep (Eq. 5-7), on the synthetic sensor.

Accuracy is the max |U error| over 5-95 % of the DN range, relative to U at 95 %, after a
least-squares scale alignment of the estimate on the truth (U is known up to scale).
"""

from __future__ import annotations

import time
from functools import lru_cache

import cv2
import numpy as np
import pytest

from mscal_core.errors import FitError, InputError
from mscal_core.response import (
    ResponseFit,
    check_exposure_consistency,
    fit_response,
    fit_response_alternating,
    predict_dn,
    predict_heldout_rms,
)
from mscal_core.synth.sensor import SensorModel

# name -> (sensor, n_frames, exposure step)
SETTINGS: dict[str, tuple[SensorModel, int, float]] = {
    "14x1.66": (SensorModel(), 14, 1.66),
    "shot-noise-x2": (SensorModel(shot_noise_dn_at_full=18.0), 14, 1.66),
    "7x3": (SensorModel(), 7, 3.0),
}
RGB8 = SensorModel(bits=8, black_level=0.0, read_noise_dn=0.6, shot_noise_dn_at_full=2.0, gamma=2.2)


def make_sweep(
    sensor: SensorModel, n_frames: int, step: float, n_pixels: int, seed: int,
    decades: float = 2.5, top_x: float = 500.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A static scene (energies log-uniform over ``decades``, max 100 linear DN / ms) seen at
    exposures ``t_i = t_0 step^i`` ms, the brightest pixel at ``top_x`` in the first frame."""
    rng = np.random.default_rng(seed)
    energy = 100.0 * 10 ** rng.uniform(-decades, 0.0, n_pixels)
    t = top_x / 100.0 * step ** np.arange(n_frames)
    return np.stack([sensor.expose(energy, ti, rng) for ti in t]), t


def u_error(u: np.ndarray, u_true: np.ndarray) -> float:
    """Max |a U - U_true| over DN 5..95 % of the range / U_true(95 %), a by least squares."""
    dn_max = u.size - 1
    k = np.arange(int(np.ceil(0.05 * dn_max)), int(np.floor(0.95 * dn_max)) + 1)
    a = np.dot(u[k], u_true[k]) / np.dot(u[k], u[k])
    return float(np.max(np.abs(a * u[k] - u_true[k])) / u_true[k[-1]])


@lru_cache(maxsize=None)
def _fit(setting: str, seed: int, method: str) -> tuple[ResponseFit, float]:
    sensor, n, step = SETTINGS[setting]
    dn, t = make_sweep(sensor, n, step, 4000, seed)
    fit = fit_response(dn, t, sensor.bits, method=method)
    return fit, u_error(fit.inverse_response, sensor.inverse_response())


# ------------------------------------------------------------------ accuracy (acceptance)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_forward_fit_within_2_percent(setting: str, seed: int) -> None:
    fit, err = _fit(setting, seed, "forward")
    assert err <= 0.02  # acceptance criterion
    assert err <= 0.008  # measured 0.09-0.63 % over seeds 0-7
    assert fit.method == "forward"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 3, 4, 5])
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_forward_fit_within_2_percent_more_seeds(setting: str, seed: int) -> None:
    _, err = _fit(setting, seed, "forward")
    assert err <= 0.02


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_plain_alternation_is_biased_and_worse(setting: str) -> None:
    """Eq. 6/7 as printed converges to a biased fixed point (3.3-4.5 % here)."""
    alt, err_alt = _fit(setting, 0, "alternating")
    _, err_fwd = _fit(setting, 0, "forward")
    assert alt.method == "alternating"
    assert err_alt > 0.02
    assert err_alt > 5 * err_fwd
    u = alt.inverse_response
    assert np.all(np.diff(u) >= 0) and u[511] == pytest.approx(511 - alt.black_level)


def test_alternating_function_is_the_alternating_method() -> None:
    sensor, n, step = SETTINGS["7x3"]
    dn, t = make_sweep(sensor, n, step, 1000, 3)
    a = fit_response_alternating(dn, t, 10)
    b = fit_response(dn, t, 10, method="alternating")
    assert np.array_equal(a.inverse_response, b.inverse_response)


# ------------------------------------------------------------------ the fit's contract


def test_fit_contract_gauge_black_level_and_bookkeeping() -> None:
    fit, _ = _fit("14x1.66", 0, "forward")
    u = fit.inverse_response
    assert u.shape == (1024,) and u.dtype == np.float64
    assert np.all(np.diff(u) >= 0)
    assert fit.black_level == pytest.approx(32.0, abs=0.5)
    k = np.arange(1024)
    assert np.all(u[k <= fit.black_level] == 0.0) and np.all(u[k > fit.black_level + 1] > 0)
    assert u[511] == pytest.approx(511 - fit.black_level)
    assert fit.saturation_dn == 1023
    lo, hi = fit.observed_dn
    assert lo <= 34 and hi == 1022
    assert 3.0 < fit.residual_rms_dn < 6.0  # read + shot noise of this scene (~4.1 DN)
    assert 14 * 1000 < fit.n_samples <= 14 * 4000
    assert 1 <= fit.iterations <= 60


def test_black_level_is_estimated() -> None:
    sensor = SensorModel(black_level=64.0)
    dn, t = make_sweep(sensor, 10, 1.66, 3000, 5)
    fit = fit_response(dn, t, 10)
    assert fit.black_level == pytest.approx(64.0, abs=0.7)
    assert np.all(fit.inverse_response[:64] == 0.0)
    assert u_error(fit.inverse_response, sensor.inverse_response()) < 0.01


def test_saturation_dn_excludes_samples_and_top_is_extrapolated() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 4000, 0)
    fit = fit_response(dn, t, 10, saturation_dn=900)
    u, ut = fit.inverse_response, sensor.inverse_response()
    assert fit.saturation_dn == 900 and fit.observed_dn[1] <= 899
    assert np.all(np.diff(u) >= 0) and np.all(np.isfinite(u))
    # extrapolated linearly above the highest unsaturated DN
    top = u[fit.observed_dn[1] :]
    assert np.allclose(np.diff(top), np.diff(top)[0]) and np.diff(top)[0] > 0
    # exact where observed: 5 .. 85 % of the range
    k = np.arange(52, 870)
    a = np.dot(u[k], ut[k]) / np.dot(u[k], u[k])
    assert np.max(np.abs(a * u[k] - ut[k])) / ut[869] < 0.01


def test_noisy_clip_after_saturation_is_ignored() -> None:
    """Once a pixel is saturated at an exposure, its samples at longer exposures are dropped
    even when noise put them a little below the clip value."""
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 4000, 1)
    rng = np.random.default_rng(0)
    sat = dn == 1023
    after = np.cumsum(sat, axis=0) > 1  # at a longer exposure than the first saturated one
    dirty = dn.copy()
    dirty[after] = rng.integers(990, 1023, int(after.sum()))
    fit = fit_response(dirty, t, 10)
    assert u_error(fit.inverse_response, sensor.inverse_response()) < 0.008


def test_unobserved_dn_filled_monotonically() -> None:
    """A dim sweep never reaches the upper half of the range: U is extrapolated there."""
    sensor = SensorModel()
    dn, t = make_sweep(sensor, 5, 1.66, 3000, 2, top_x=60.0)
    fit = fit_response(dn, t, 10)
    u, ut = fit.inverse_response, sensor.inverse_response()
    lo, hi = fit.observed_dn
    assert hi < 500
    assert np.all(np.diff(u) >= 0) and np.all(np.isfinite(u)) and u[-1] > u[hi]
    k = np.arange(52, hi + 1)
    a = np.dot(u[k], ut[k]) / np.dot(u[k], u[k])
    assert np.max(np.abs(a * u[k] - ut[k])) / ut[hi] < 0.02
    assert u[511] == pytest.approx(511 - fit.black_level)  # gauge holds through extrapolation


def test_pixel_subsampling_is_seeded() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 12000, 4)
    a = fit_response(dn, t, 10, max_pixels=2000, seed=1)
    b = fit_response(dn, t, 10, max_pixels=2000, seed=1)
    assert np.array_equal(a.inverse_response, b.inverse_response)
    assert a.n_samples <= 2000 * n
    assert a.observed_dn == (int(dn[dn < 1023].min()), int(dn[dn < 1023].max()))
    assert u_error(a.inverse_response, sensor.inverse_response()) < 0.01


# ------------------------------------------------------------------ errors


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_fewer_than_two_exposures() -> None:
    dn, t = make_sweep(SensorModel(), 3, 1.66, 200, 0)
    with pytest.raises(FitError) as err:
        fit_response(dn, np.full(3, t[0]), 10)
    assert "at least 2" in _one_line(err)


@pytest.mark.parametrize("bad", [0.0, -2.0, np.nan])
def test_non_positive_exposure(bad: float) -> None:
    dn, t = make_sweep(SensorModel(), 4, 1.66, 200, 0)
    t[2] = bad
    with pytest.raises(InputError) as err:
        fit_response(dn, t, 10)
    assert "frame 2" in _one_line(err)


def test_all_saturated() -> None:
    with pytest.raises(FitError) as err:
        fit_response(np.full((4, 50), 1023), np.array([1.0, 2.0, 4.0, 8.0]), 10)
    assert "no unsaturated samples" in _one_line(err)


def test_exposure_inconsistent_with_brightness_names_the_frame() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 2000, 0)
    assert check_exposure_consistency(dn, t, 10) == []
    wrong = t.copy()
    wrong[5] *= 4.0  # recorded 4x too long: darker than frames with shorter exposures
    assert check_exposure_consistency(dn, wrong, 10) == [5]
    with pytest.raises(FitError) as err:
        fit_response(dn, wrong, 10)
    assert "frame 5 " in _one_line(err)
    swapped = t.copy()
    swapped[[5, 6]] = swapped[[6, 5]]
    assert check_exposure_consistency(dn, swapped, 10) in ([5], [6])


def test_bad_shapes_values_and_method() -> None:
    dn, t = make_sweep(SensorModel(), 4, 1.66, 200, 0)
    with pytest.raises(InputError):
        fit_response(dn, t[:3], 10)
    with pytest.raises(InputError):
        fit_response(dn[0], t[:1], 10)
    with pytest.raises(InputError) as err:
        fit_response(dn, t, 8)  # 10-bit DN declared as 8-bit
    assert "bit depth" in _one_line(err)
    with pytest.raises(InputError):
        fit_response(dn, t, 10, method="debevec")
    with pytest.raises(InputError):
        fit_response(dn + 0.5, t, 10)


# ------------------------------------------------------------------ prediction through U


def test_predict_dn_inverts_u() -> None:
    u = SensorModel().inverse_response()
    k = np.arange(33, 1024)
    assert np.allclose(predict_dn(u, u[k]), k, atol=1e-9)
    assert predict_dn(u, np.array([0.0]))[0] == pytest.approx(32.0, abs=0.05)  # black level
    assert predict_dn(u, np.array([1e9]))[0] == 1023
    e = np.linspace(0, u[-1], 1000)
    assert np.all(np.diff(predict_dn(u, e)) >= 0)


def test_predict_heldout_rms_with_true_u_is_the_noise() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 4000, 0)
    rms = predict_heldout_rms(sensor.inverse_response(), dn[3], t[3], dn[4], t[4])
    # held-out noise (~5 DN) plus reference noise carried through U (x1.66)
    assert 5.0 < rms < 10.0
    with pytest.raises(FitError):
        predict_heldout_rms(sensor.inverse_response(), np.full(5, 1023), 1.0, np.full(5, 1023), 2.0)


# ------------------------------------------------------------------ 8-bit RGB vs OpenCV Debevec


def rgb_sweep(sensor: SensorModel, n_frames: int, step: float, shape: tuple[int, int],
              seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W, 3) uint8 frames of a static colour scene and exposures (ms)."""
    rng = np.random.default_rng(seed)
    energy = 10 ** rng.uniform(-2.5, 0.0, (3, *shape)) * np.array([1.0, 0.8, 0.6])[:, None, None]
    t = step ** np.arange(n_frames) * 0.15 * float(sensor.x_for_dn(sensor.dn_max))
    frames = np.stack(
        [np.stack([sensor.expose(energy[c], ti, rng) for c in range(3)], axis=-1) for ti in t]
    )
    return frames.astype(np.uint8), t


def heldout_comparison(frames: np.ndarray, t: np.ndarray, held: int) -> dict[str, float]:
    """RMS DN error predicting frame ``held`` from every other frame, per method, with the
    responses fitted on all frames but ``held`` (channels are bands)."""
    fit_idx = [i for i in range(len(t)) if i != held]
    debevec = cv2.createCalibrateDebevec().process(
        [frames[i] for i in fit_idx], (t[fit_idx] / 1000.0).astype(np.float32)
    )  # (256, 1, 3), exposure times in seconds
    errs: dict[str, list[float]] = {"ours": [], "alternating": [], "debevec": [], "true": []}
    for c in range(3):
        dn = frames[fit_idx][..., c].reshape(len(fit_idx), -1)
        us = {
            "ours": fit_response(dn, t[fit_idx], 8).inverse_response,
            "alternating": fit_response(dn, t[fit_idx], 8, method="alternating").inverse_response,
            "debevec": debevec[:, 0, c].astype(np.float64),
            "true": RGB8.inverse_response(),
        }
        for ref in fit_idx:
            for name, u in us.items():
                rms = predict_heldout_rms(
                    u, frames[ref][..., c], t[ref], frames[held][..., c], t[held]
                )
                errs[name].append(rms)
    return {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}


@pytest.mark.parametrize("seed", [0])
def test_rgb8_heldout_prediction_at_least_as_good_as_debevec(seed: int) -> None:
    frames, t = rgb_sweep(RGB8, 7, 2.0, (60, 80), seed)
    rms = heldout_comparison(frames, t, held=3)
    # measured (seeds 0-5): ours 2.105-2.119, Debevec 2.160-2.197, true U 2.091-2.104 DN
    assert rms["ours"] <= rms["debevec"]
    assert rms["ours"] <= 1.02 * rms["true"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_rgb8_heldout_more_seeds(seed: int) -> None:
    frames, t = rgb_sweep(RGB8, 7, 2.0, (60, 80), seed)
    rms = heldout_comparison(frames, t, held=3)
    assert rms["ours"] <= rms["debevec"]


def test_rgb8_response_shape() -> None:
    frames, t = rgb_sweep(RGB8, 6, 2.0, (60, 80), 7)
    fit = fit_response(frames[..., 1].reshape(6, -1), t, 8)
    u = fit.inverse_response
    assert u.shape == (256,) and np.all(np.diff(u) >= 0)
    assert u[127] == pytest.approx(127 - fit.black_level)
    assert u_error(u, RGB8.inverse_response()) < 0.05  # gamma 2.2: U grows 10x from DN 90 to 255


# ------------------------------------------------------------------ speed


@pytest.mark.slow
def test_forward_fit_speed_per_band() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 4000, 9)
    fit_response(dn, t, 10)
    t0 = time.perf_counter()
    fit_response(dn, t, 10)
    assert time.perf_counter() - t0 < 1.0  # target 0.5 s; slack for a shared machine
