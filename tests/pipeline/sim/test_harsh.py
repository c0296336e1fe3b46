"""harsh_params: sessions hard where the flight reads the response (a steep shoulder, a sweep
that ends near or short of the top, flights exposed onto the shoulder), without changing what
the default parameters write."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.quality import dn_flag_table
from pipeline.calibrate.bands import response_band
from pipeline.sim.varied import VariedParams, draw_params, harsh_params, params_record, varied_truth
from pipeline.sim.world.scene import response_sweep
from pipeline.sim.world.sensor import SensorModel


def test_params_json_lists_the_new_fields_only_away_from_their_defaults() -> None:
    assert set(params_record(draw_params(3))) == set(params_record(VariedParams()))
    assert not {"shoulder_headroom", "sweep_stop", "n_reflector", "flight_exposure"} & set(params_record(draw_params(3)))
    rec = params_record(harsh_params(3))
    assert rec["flight_exposure"] == [0.96, 0.99] or rec["flight_exposure"] == (0.96, 0.99)
    assert 1.002 <= rec["shoulder_headroom"] <= 1.05 and 0.88 <= rec["sweep_stop"] <= 0.995
    assert rec["n_reflector"] == 2 and rec["sweep_frames"] == 7
    full = harsh_params(3, size="full")
    assert full.sweep_frames == draw_params(3).sweep_frames and full.n_reflector == 3
    with pytest.raises(ValueError):
        harsh_params(3, size="tiny")


@pytest.mark.parametrize("seed", range(5))
def test_the_harsh_shoulder_compresses_a_wide_energy_range_near_the_clip(seed) -> None:
    p = harsh_params(seed)
    U = varied_truth(p).inverse_response[0]
    knee = int(np.ceil(p.shoulder_start * 1023))
    assert 1.15 < U[1022] / U[knee] < 2.3  # U at the clip 1.15-2.3 x U at the knee ...
    assert (1022 - knee) / 1023 < 0.16  # ... in the last 5-15 % of the DN
    default = varied_truth(draw_params(seed)).inverse_response[0]
    assert U[1022] / U[1000] - 1 > 2 * (default[1022] / default[1000] - 1)  # steeper at the top than ours


def test_a_headroom_that_never_reaches_the_clip_is_refused() -> None:
    with pytest.raises(InputError, match="shoulder_headroom"):
        SensorModel(shoulder_headroom=1.0)


def test_the_sweep_ends_where_stop_fraction_puts_it() -> None:
    p = harsh_params(0)
    truth = varied_truth(p)
    fs = response_sweep(truth, seed=p.seed, n_frames=7, step=3.0, stop_fraction=0.9)
    last = fs.dn[-1].astype(float)
    # the 99.5 % quantile of the energy at 0.9 of the range: that share of the DN of the longest
    # frame is below ~0.9 x 1023 (noise), the rest above; the shortest exposure ~0.3 ms
    assert 0.97 < np.mean(last < 0.9 * 1023 + 15) and np.mean(last > 0.9 * 1023 - 15) < 0.03
    assert fs.exposure_ms[0] == pytest.approx(0.3, rel=0.01)
    assert fs.exposure_ms[-1] / fs.exposure_ms[0] == pytest.approx(3.0**6, rel=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [4, 5, pytest.param(6, marks=pytest.mark.long), pytest.param(7, marks=pytest.mark.long)])
def test_no_dn_above_the_knee_left_unflagged_is_far_off(seed) -> None:
    """The response fit of a harsh sweep, every other band: where the flags (bound 0.03, the
    fitted range) leave a DN above the knee unflagged, U is within 0.04 of the truth (up to
    U's scale). Measured on harsh sessions 0-11, every band: up to 0.096 (3-4 times the
    uncertainty) while the uncertainty was ``U' sigma_I / U`` up to the data's top; at most
    0.037 (1.2-1.3 times it, inside the shoulder) once it is inf within a reading's noise of the
    top."""
    p = harsh_params(seed)
    truth = varied_truth(p)
    fs = response_sweep(truth, seed=p.seed, n_frames=p.sweep_frames, step=p.sweep_step,
                        start_fraction=p.sweep_start, stop_fraction=p.sweep_stop)
    dn, ex = np.asarray(fs.dn), np.asarray(fs.exposure_ms, dtype=float)
    knee = int(np.ceil(p.shoulder_start * 1023))
    worst, unflagged = 0.0, 0
    bands = range((seed + 1) % 2, dn.shape[1], 2)
    for b in bands:
        _, fit = response_band(dn[:, b], ex[:, b] if ex.ndim == 2 else ex, 10, "forward")
        U, Ut = fit.inverse_response, truth.inverse_response[b]
        k = np.arange(51, knee)
        s = float(U[k] @ Ut[k] / (U[k] @ U[k]))
        flags = dn_flag_table(1, 1024, fit.saturation_dn, fit.uncertainty[None], 0.03, np.array([fit.fitted_dn]))[0]
        ok = np.flatnonzero(flags[knee:] == 0) + knee
        unflagged += ok.size
        if ok.size:
            worst = max(worst, float(np.max(np.abs(s * U[ok] / Ut[ok] - 1))))
    assert unflagged > 20 * len(bands)  # the flags still leave most of the shoulder
    assert worst < 0.04
