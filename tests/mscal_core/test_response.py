"""Inverse response from an exposure sweep (Eq. 5-7), on the synthetic sensor.

Accuracy is the max |U error| over 5-95 % of the DN range, relative to U at 95 %, after a
least-squares scale alignment of the estimate on the truth (U is known up to scale).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import pytest

from mscal_core.errors import FitError, InputError
from mscal_core.response import (
    ResponseFit,
    check_exposure_consistency,
    exposure_period,
    fit_response,
    fit_response_alternating,
    predict_dn,
    predict_heldout_rms,
)
from pipeline.sim.world.photo import PhotoSet, make_photo_set
from pipeline.sim.world.sensor import SensorModel

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
    assert err <= 0.008  # measured 0.09-0.47 % over seeds 0-7 (previous estimator: 0.09-0.63 %)
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
    # measured (seeds 0-5): ours 2.103-2.114, Debevec 2.160-2.197, true U 2.091-2.104 DN
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


# ------------------------------------------------------------------ harder conditions
# Real photographs are not clean sweeps: values stuck below the clip (a colour channel clipped
# before the camera's colour matrix), pixels that change between frames (moving things,
# a handheld camera), pixels that never leave 0 or dn_max. Measured with the previous
# estimator (plain weighted least squares, only samples >= dn_max treated as saturated):
# stuck 36-97 % max U error, movers 10-43 %.


def _stuck_below_clip(dn: np.ndarray, rng: np.random.Generator, frac: float = 0.1,
                      level: int = 800) -> np.ndarray:
    """``frac`` of the pixels stop rising once they reach ``level``: later samples repeat that
    value minus 0-14 DN (never the clip value, so not flagged as saturated)."""
    out = dn.copy()
    n = dn.shape[0]
    for c in rng.choice(dn.shape[1], int(frac * dn.shape[1]), replace=False):
        above = np.flatnonzero(dn[:, c] >= level)
        if above.size:
            i = above[0]
            out[i:, c] = np.clip(dn[i, c] - rng.integers(0, 15, n - i), 0, 1022)
    return out


def _movers(dn: np.ndarray, rng: np.random.Generator, frac: float = 0.1, n_bad: int = 3
            ) -> np.ndarray:
    """``frac`` of the pixels show something else (uniform DN 40..999) in ``n_bad`` frames."""
    out = dn.copy()
    for c in rng.choice(dn.shape[1], int(frac * dn.shape[1]), replace=False):
        rows = rng.choice(dn.shape[0], n_bad, replace=False)
        out[rows, c] = rng.integers(40, 1000, n_bad)
    return out


@pytest.mark.parametrize("setting", ["14x1.66", "7x3"])
def test_values_stuck_below_the_clip_are_treated_as_saturated(setting: str) -> None:
    sensor, n, step = SETTINGS[setting]
    dn, t = make_sweep(sensor, n, step, 4000, 0)
    fit = fit_response(_stuck_below_clip(dn, np.random.default_rng(0)), t, 10)
    # measured 0.11-0.65 % over seeds 0-3
    assert u_error(fit.inverse_response, sensor.inverse_response()) < 0.008


@pytest.mark.parametrize("setting", ["14x1.66", "7x3"])
def test_pixels_that_change_between_frames_are_outliers(setting: str) -> None:
    sensor, n, step = SETTINGS[setting]
    dn, t = make_sweep(sensor, n, step, 4000, 1)
    fit = fit_response(_movers(dn, np.random.default_rng(1)), t, 10)
    # measured 0.15-0.37 % over seeds 0-3
    assert u_error(fit.inverse_response, sensor.inverse_response()) < 0.008


def test_pixels_always_clipped_are_ignored() -> None:
    sensor, n, step = SETTINGS["14x1.66"]
    dn, t = make_sweep(sensor, n, step, 4000, 2)
    dn[:, :600] = 0
    dn[:, 600:1200] = 1023
    fit = fit_response(dn, t, 10)
    assert u_error(fit.inverse_response, sensor.inverse_response()) < 0.008
    assert fit.n_samples <= 14 * 2800


def test_large_band_is_not_copied() -> None:
    """The pipeline passes every pixel of a band (9 frames x 6 Mpx x 3 bands): the fit works on
    a seeded subset of candidates and must not make full-size temporaries (int32 / float64
    copies, per-pixel float masks)."""
    import tracemalloc

    sensor, n, step = SETTINGS["7x3"]
    dn_small, t = make_sweep(sensor, n, step, 20000, 3)
    dn = np.tile(dn_small, (1, 150))  # (7, 3 000 000) uint16: 42 MB
    tracemalloc.start()
    try:
        fit_response(dn, t, 10)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 0.5 * dn.nbytes  # measured 15 MB for this 42 MB band


def test_exposure_period_of_geometric_brackets() -> None:
    stop = np.log(2.0)
    assert exposure_period(2.0 ** np.arange(7)) == pytest.approx(stop)
    # nominal markings of third-stop shutter times (1/1000 1/500 1/250 1/125 1/60 1/30)
    nominal = 1.0 / np.array([1000, 500, 250, 125, 60, 30])
    assert exposure_period(nominal) / stop == pytest.approx(1.0, abs=0.1)
    # the middle frame of a 2-stop bracket held out: one 4-stop step
    assert exposure_period(np.array([1.0, 16.0])) == pytest.approx(4 * stop)
    assert exposure_period(np.array([1.0, 4.0, 16.0, 32.0])) == pytest.approx(stop)


# ------------------------------------------------------------------ photographs (8-bit brackets)


def photo_heldout(ps: PhotoSet, held: int) -> dict[str, float]:
    """Held-out RMS DN predicting frame ``held`` from every other frame (responses fitted on
    all frames but ``held``), per method: ours, OpenCV Debevec, the true response."""
    fr, t = ps.frames, ps.exposure_ms
    idx = [i for i in range(len(t)) if i != held]
    debevec = cv2.createCalibrateDebevec().process(
        [fr[i] for i in idx], (t[idx] / 1000.0).astype(np.float32)
    )
    errs: dict[str, list[float]] = {"ours": [], "debevec": [], "true": []}
    for c in range(3):
        us = {
            "ours": fit_response(fr[idx][..., c].reshape(len(idx), -1), t[idx], 8).inverse_response,
            "debevec": debevec[:, 0, c].astype(np.float64),
            "true": ps.inverse_response[c],
        }
        for ref in idx:
            for name, u in us.items():
                errs[name].append(
                    predict_heldout_rms(u, fr[ref][..., c], t[ref], fr[held][..., c], t[held])
                )
    return {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}


PHOTO = dict(shape=(240, 320), n_frames=7, step_thirds=3)
PHOTO_SETTINGS = {
    # JPEG q90, 0.5-3 px handheld shifts, foliage + walking figure, sharpening, 1/60-style EXIF
    "handheld": PHOTO,
    "tripod-jpeg": PHOTO | dict(shift_px=0.0, rotation_deg=0.0, moving=False),
    "tripod-raw-tone": PHOTO | dict(shift_px=0.0, rotation_deg=0.0, moving=False,
                                    jpeg_quality=None, sharpen=0.0),
}


@pytest.mark.parametrize("setting", list(PHOTO_SETTINGS))
def test_photo_bracket_heldout_at_least_as_good_as_debevec(setting: str) -> None:
    ps = make_photo_set(31, **PHOTO_SETTINGS[setting])
    rms = photo_heldout(ps, held=4)  # a bright frame: toe and shoulder of U both matter
    # measured (seeds 31, 41, 51): ours / Debevec 0.89-0.98, ours / true U 0.89-1.02
    assert rms["ours"] <= rms["debevec"]
    assert rms["ours"] <= 1.05 * rms["true"]


def test_photo_two_frames_four_stops_apart() -> None:
    """A 3-frame bracket 2 stops apart with its middle frame held out: 2 frames 16x apart
    determine U only up to a factor periodic in log exposure; the adaptive log-log prior
    resolves it (Debevec: 1.4-1.7x the error of the true U on these sets)."""
    ps = make_photo_set(32, shape=(240, 320), n_frames=3, step_thirds=6)
    rms = photo_heldout(ps, held=1)
    assert rms["ours"] <= 0.85 * rms["debevec"]  # measured 0.51-0.80 (seeds 32, 42, 52)
    assert rms["ours"] <= 1.3 * rms["true"]  # measured 1.05-1.22


def test_photo_response_close_to_truth() -> None:
    """On a tripod bracket without JPEG the fitted U follows the camera's tone curve (toe,
    sRGB-like gamma, shoulder) within a few percent over DN 5..250."""
    ps = make_photo_set(33, **PHOTO_SETTINGS["tripod-raw-tone"])
    k = np.arange(5, 251)
    for c in range(3):
        u = fit_response(ps.frames[..., c].reshape(7, -1), ps.exposure_ms, 8).inverse_response
        r = np.log(u[k] / ps.inverse_response[c][k])
        assert np.all(np.diff(u) >= 0)
        assert np.sqrt(np.mean((r - r.mean()) ** 2)) < 0.06  # measured 0.017-0.047 (rms log)


def test_dn0_and_first_saturated_samples_are_censored_not_dropped() -> None:
    """Dark frames of a photograph are mostly 0-5 DN. Dropping the DN-0 samples keeps only
    the noise draws above 0: the black level came out 1.2-2.0 DN and U(2) was 0 (seeds 33,
    43, 53, ``censored=False``); as censored terms the black level stays near 0."""
    ps = make_photo_set(43, **PHOTO_SETTINGS["tripod-raw-tone"])
    k = np.arange(2, 251)
    for c in range(3):
        fit = fit_response(ps.frames[..., c].reshape(7, -1), ps.exposure_ms, 8)
        u = fit.inverse_response
        assert -1.5 < fit.black_level < 1.0  # measured -1.4 .. 0.6
        assert u[2] > 0
        r = np.log(u[k] / ps.inverse_response[c][k])
        assert np.max(np.abs(r[:4] - np.median(r))) < 0.8  # DN 2-5; measured 0.09-0.77
    dropped = [fit_response(ps.frames[..., c].reshape(7, -1), ps.exposure_ms, 8,
                            censored=False).black_level for c in range(3)]
    assert max(dropped) > 1.5


def test_residual_profile_per_dn_bin_adds_up_to_the_rms() -> None:
    from mscal_core.response import residual_profile

    rng = np.random.default_rng(3)
    d = rng.integers(0, 1024, size=(4, 500)).astype(np.float64)
    mu = d + rng.normal(0.0, 1.0 + d / 512.0)  # noise growing with DN
    used = d < 1000
    prof = residual_profile(d, mu, used, bits=10, n_bins=8)
    k = np.clip((d[used] * 8 / 1024).astype(int), 0, 7)
    counts = np.bincount(k, minlength=8)
    total = np.sqrt(np.sum(counts * prof**2) / counts.sum())
    assert total == pytest.approx(np.sqrt(np.mean((d - mu)[used] ** 2)), rel=1e-12)
    assert prof[7] > 1.5 * prof[0]  # the noise model's growth shows per bin
    assert np.isnan(residual_profile(d, mu, d < 100, bits=10, n_bins=8)[5])
