"""pipeline.sim.evaluate.score_flight on small hand-made flights: the per-frame panel
normalisation, NaN (flagged) pixels left out, and the figures it reports."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mscal_core.quality import FLAGS
from pipeline.sim.evaluate import FlightScene, calibration_cv, panel_value, score_flight


def _scene(n_frames: int = 3) -> tuple[FlightScene, np.ndarray]:
    """Two gray panels (rho 0.9 and 0.3) and vegetation in a 3-band, 6x6 frame; the truth
    reflectance of every frame (frame, band, y, x) with the light ``sun`` in it."""
    labels = np.zeros((n_frames, 6, 8), np.int32)
    labels[:, :, :2] = 1  # panel 0.9
    labels[:, :, 2:4] = 2  # panel 0.3
    labels[:, :, 4:] = 3  # vegetation
    sun = np.linspace(1.0, 1.4, n_frames)
    rho = {1: 0.9, 2: 0.3}
    veg = np.array([0.05, 0.08, 0.5])  # red = band 1, nir = band 2
    r = np.zeros((n_frames, 3, 6, 8), np.float32)
    for f in range(n_frames):
        for p, v in rho.items():
            r[f][:, labels[f] == p] = v * sun[f]
        r[f][:, labels[f] == 3] = (veg * sun[f])[:, None]
    true_ndvi = np.full((n_frames, 6, 8), (0.5 - 0.08) / (0.5 + 0.08))
    scene = FlightScene(labels=labels, panels=[1, 2], panel_rho=np.array([0.9, 0.3]), sun=sun, vegetation=3,
                        ndvi=true_ndvi, red=1, nir=2)
    return scene, r


def test_exact_reflectance_scores_zero_and_a_biased_band_shows() -> None:
    scene, r = _scene()
    s = score_flight(r, scene)
    assert s["panel_abs_error"] < 1e-6 and s["panel_cv_across_frames"] < 1e-6 and s["vegetation_ndvi_error"] < 1e-6
    r2 = r.copy()
    r2[1, 0] *= 1.05  # band 0 of frame 1 reads 5 % high: the median over bands normalises it away
    s2 = score_flight(r2, scene)
    # frame 1's scalar is the median over bands (1 / sun): the 0.9 panel in band 0 reads 0.9 x 1.05
    assert s2["panel_abs_error"] == pytest.approx(0.9 * 0.05, rel=1e-4)
    assert s2["panel_cv_across_frames"] > 0.02


def test_flagged_white_panel_falls_back_to_the_next_panel_and_nan_pixels_do_not_count() -> None:
    scene, r = _scene()
    r2 = r.copy()
    r2[0][:, scene.labels[0] == 1] = np.nan  # the white panel flagged in frame 0
    r2[1][0, 0, 4] = 50.0  # one vegetation pixel far off ...
    r2[1][0, 1, 4] = np.nan  # ... and one flagged
    s = score_flight(r2, scene)
    assert s["panel_abs_error"] < 1e-6  # frame 0 normalised by the 0.3 panel, still exact
    assert s["panel_cv_across_frames"] < 1e-6
    assert s["vegetation_ndvi_error"] < 1e-6  # band 0 is neither red nor NIR
    r3 = r.copy()
    r3[:, :, :, 4:] = np.nan  # no vegetation pixel left
    assert np.isnan(score_flight(r3, scene)["vegetation_ndvi_error"])


def test_a_panel_with_too_few_finite_pixels_is_left_out_of_its_frame() -> None:
    scene, r = _scene()
    r2 = r.copy()
    keep = np.zeros((6, 8), bool)
    keep[0, :2] = True  # 2 finite pixels of the 0.3 panel's 12 ... (panel 2 is columns 2-3)
    m = (scene.labels[2] == 2) & ~np.roll(keep, 2, axis=1)
    r2[2][:, m] = np.nan
    r2[2][:, (scene.labels[2] == 2) & np.roll(keep, 2, axis=1)] = 7.0  # ... and those wrong
    s = score_flight(r2, scene)
    assert s["panel_abs_error"] < 1e-6


def test_a_panel_cut_by_the_frame_to_a_few_pixels_is_left_out() -> None:
    """A panel with less than half its pixels in a frame measures those pixels' noise: left out
    of that frame, it changes neither the error nor the cross-frame CV."""
    scene, r = _scene()
    labels = scene.labels.copy()
    labels[0][:, 2:4] = 0  # the 0.3 panel cut to 5 of its 12 pixels in frame 0 ...
    labels[0][:5, 2] = 2
    r2 = r.copy()
    r2[0][:, labels[0] == 2] *= 1.2  # ... where they read 20 % high
    s = score_flight(r2, replace(scene, labels=labels))
    assert s["panel_abs_error"] < 1e-6 and s["panel_cv_across_frames"] < 1e-6
    labels[0][:, 2] = 2  # 6 of 12: half of it, counted
    labels[0][:, 3] = 0
    r3 = r.copy()
    r3[0][:, labels[0] == 2] *= 1.2
    assert score_flight(r3, replace(scene, labels=labels))["panel_abs_error"] == pytest.approx(0.3 * 0.2, rel=1e-4)


def test_a_panel_partly_flagged_high_is_scored_on_its_censored_median_and_counted() -> None:
    """The 0.9 panel's 12 pixels per band read 0.9 x (1 + 0.01 k), k = -5..6, in frame 1; the
    brightest is flagged on the shoulder (NaN; one of 12, under the tenth from which a panel
    is flagged as a whole). The valid 11 alone have a median 0.5 % low; with the one counted
    as above it the median is that of all 12 (0.9 x 1.005). A third flagged: not scored."""
    scene, r = _scene()
    panel = scene.labels[1] == 1
    spread = 1 + 0.01 * np.arange(-5, 7)
    r2, q = r.copy(), np.zeros(r.shape, np.uint8)
    r2[1][:, panel] = (0.9 * scene.sun[1] * spread)[None, :]
    q[1][:, panel] = np.where(spread > 1.055, np.uint8(FLAGS["response_shoulder"]), np.uint8(0))[None, :]
    r2[q != 0] = np.nan
    s = score_flight(r2, scene, q)
    # frame 1 normalised on this panel: median 0.9 x 1.005 -> k = 1 / (1.005 sun); the 0.3 panel 0.3 / 1.005
    assert s["panel_abs_error"] == pytest.approx(0.3 * (1 - 1 / 1.005), rel=1e-4)
    assert s["panels_censored"] == 3.0 and s["panels_flagged"] == 0.0  # one panel in one frame, 3 bands
    # without the mask the valid 11 alone: median 0.9 x 1.000, 0.5 % below the censored one
    plain = score_flight(r2, scene)
    assert plain["panel_abs_error"] < 1e-6  # float32 reflectance
    assert plain["panels_censored"] == 0.0
    q[1][:, panel] = np.where(spread > 1.025, np.uint8(FLAGS["response_shoulder"]), np.uint8(0))[None, :]  # 4 of 12
    s2 = score_flight(r2, scene, q)
    assert s2["panels_flagged"] == 3.0 and s2["panels_censored"] == 0.0
    q[1][:, panel] = np.where(spread > 0.995, np.uint8(FLAGS["response_shoulder"]), np.uint8(0))[None, :]  # 6 of 12
    s3 = score_flight(r2, scene, q)
    assert s3["panels_flagged"] == 3.0 and s3["panels_censored"] == 0.0
    assert s3["panel_abs_error"] < 1e-6  # frame 1 normalised by the 0.3 panel, the 0.9 one not scored there
    # flagged in band 0 only; in bands 1 and 2 the NaN pixel without a flag is left out (not
    # censored): scored there on the mean of the 11 others, 0.9 x 1.000; with the 4 brightest
    # NaN, the mean of the 8 others would read 0.9 x 0.985, but a third of the panel without a
    # value flags it in every band
    q[1][1:, panel] = 0
    s4 = score_flight(r2, scene, q)
    assert s4["panels_flagged"] == 1.0 and s4["panels_censored"] == 0.0
    assert s4["panel_abs_error"] < 1e-6
    r2[1][:, panel & (r2[1][0] > 0.9 * scene.sun[1] * 1.025)] = np.nan
    assert score_flight(r2, scene, q)["panels_flagged"] == 3.0


def test_panel_value_spread_is_the_pixel_noise_over_root_n() -> None:
    """A gray panel of 300 pixels with 8.5 % Gaussian pixel noise (the 0.05 panel ~30 DN above
    black of the varied sessions): over 4000 draws the mean's spread is sigma / sqrt(N) and,
    with 3 pixels per draw flagged high, the censored median's is sqrt(pi / 2) times that."""
    rng = np.random.default_rng(7)
    n, draws, rho, rel = 300, 4000, 0.05, 0.085
    v = rho * (1 + rel * rng.standard_normal((draws, n)))  # one row per draw, as bands
    val, state = panel_value(v, np.zeros(v.shape, np.uint8))
    assert (state == 0).all()
    theory = rel / np.sqrt(n)
    # the spread of 4000 draws is itself known to 1 / sqrt(2 x 4000) = 1.1 %: 5 % is 4 of those
    assert np.std(val / rho) == pytest.approx(theory, rel=0.05)
    assert np.mean(val / rho) == pytest.approx(1.0, abs=4 * theory / np.sqrt(draws))
    q = np.zeros(v.shape, np.uint8)
    top = np.argsort(v, axis=1)[:, -3:]  # the 3 brightest read on the shoulder ...
    np.put_along_axis(q, top, np.uint8(FLAGS["response_shoulder"]), axis=1)
    cen, cstate = panel_value(np.where(q != 0, np.nan, v), q)  # ... and carry no value
    assert (cstate == 1).all()
    assert np.std(cen / rho) == pytest.approx(np.sqrt(np.pi / 2) * theory, rel=0.06)
    assert np.mean(cen / rho) == pytest.approx(1.0, abs=4 * 1.26 * theory / np.sqrt(draws))
    half = q.copy()
    half[:, : n // 2] = FLAGS["vignetting_unobserved"]  # half of the panel flagged: not scored
    assert np.isnan(panel_value(v, half)[0]).all() and (panel_value(v, half)[1] == 2).all()


def test_panel_value_of_integer_dn_does_not_depend_on_where_the_level_falls_between_dn_steps() -> None:
    """A dark panel reads integer DN: at 30.0, 30.3 and 30.5 DN with 2.6 DN of noise (300
    pixels, 2000 draws) the mean's spread is sqrt(2.6^2 + 1/12) / sqrt(300) = 0.151 DN at each
    level; the median sticks to the DN levels, its spread 0.05 DN at 30.0 and 0.49 DN at 30.5
    (the continuous theory, 1.25 x 0.150 = 0.188 DN, holds at neither)."""
    rng = np.random.default_rng(3)
    theory = np.sqrt(2.6**2 + 1 / 12) / np.sqrt(300)
    spread_median = {}
    for mu in (30.0, 30.3, 30.5):
        dn = np.rint(mu + 2.6 * rng.standard_normal((2000, 300)))
        val, _ = panel_value(dn, np.zeros(dn.shape, np.uint8))
        assert np.std(val) == pytest.approx(theory, rel=0.07)  # 2000 draws: spread known to 1.6 %
        assert np.mean(val) == pytest.approx(mu, abs=4 * theory / np.sqrt(2000))
        spread_median[mu] = float(np.std(np.median(dn, axis=1)))
    assert spread_median[30.0] < 0.5 * theory and spread_median[30.5] > 2.5 * theory


def test_score_flight_takes_a_panel_without_flags_on_its_mean() -> None:
    """One of the 0.3 panel's 12 pixels reads 12 % high in frame 1: its mean, 1 % high, is
    the panel's value there (its median would not move)."""
    scene, r = _scene()
    r2 = r.copy()
    y, x = np.nonzero(scene.labels[1] == 2)
    r2[1][:, y[0], x[0]] *= 1.12
    s = score_flight(r2, scene)
    assert s["panel_abs_error"] == pytest.approx(0.3 * 0.01, rel=1e-3)
    assert s["panels_censored"] == 0.0


def test_calibration_cv_cancels_the_pixel_noise_and_keeps_what_the_calibration_moves() -> None:
    """Pixels with 10 % noise read through a calibration 2 % high in frame 1's band 2 only: the
    panels' cross-frame CV is mostly the noise, the calibration's share is that of (1, 1.02, 1)."""
    scene, r = _scene()
    rng = np.random.default_rng(5)
    exact = (r * (1 + 0.1 * rng.standard_normal(r.shape))).astype(np.float32)
    fitted = exact * 1.3  # U's scale is free: the ratio's level does not count
    fitted[1, 2] *= 1.02
    assert score_flight(fitted, scene)["panel_cv_across_frames"] > 0.01
    want = np.std([1, 1.02, 1]) / np.mean([1, 1.02, 1])
    assert calibration_cv(fitted, exact, scene) == pytest.approx(want, rel=1e-4)
    assert calibration_cv(exact * 1.3, exact, scene) < 1e-6


def test_censor_bounds_are_eq15_of_the_trusted_dn_under_each_reading_on_the_outputs_scale() -> None:
    """A 2-band calibration with a linear U, the sweep up to DN 99: a reading of 120 flagged
    above the sweep gets Eq. 15 of DN 99 at its pixel (its V), times the output's scale over
    Eq. 15 on the valid pixels (2 here); unflagged pixels and readings under the sweep get none."""
    import xarray as xr

    from pipeline.sim.evaluate import censor_bounds

    u = np.tile(np.arange(256, dtype=np.float64) * 0.01, (2, 1))
    v = np.ones((2, 2, 3))
    v[:, 0, 0] = 0.5
    ds = xr.Dataset({"inverse_response": (("band", "dn"), u), "vignetting": (("band", "y", "x"), v),
                     "spectral_factor": (("band",), np.array([1.0, 2.0])),
                     "saturation_dn": (("band",), np.array([250, 250])),
                     "response_dn_range": (("band", "end"), np.array([[10, 99], [10, 99]]))},
                    coords={"end": ["low", "high"]})
    dn = np.full((1, 2, 2, 3), 50, np.uint16)
    dn[0, :, 0, 0] = 120  # above the sweep, at the pixel of V 0.5
    dn[0, :, 1, 2] = 5  # under the sweep
    own = u[0][dn[0]] / v / np.array([1.0, 2.0])[:, None, None]
    refl = (2.0 * own)[None].astype(np.float32)
    q = np.zeros(dn.shape, np.uint8)
    q[0, :, 0, 0] = FLAGS["outside_sweep"]
    q[0, :, 1, 2] = FLAGS["outside_sweep"] | FLAGS["below_sweep"]
    refl[q != 0] = np.nan
    b = censor_bounds(dn, np.array([1.0]), ds, refl, q)
    np.testing.assert_allclose(b[0, :, 0, 0], [2.0 * 0.99 / 0.5 / 1.0, 2.0 * 0.99 / 0.5 / 2.0], rtol=1e-6)
    assert np.isnan(b[0][:, 1, 2]).all() and np.isnan(b[0][:, 0, 1:]).all()


def test_panel_value_with_bounds_is_not_biased_by_a_cut_where_v_is_high() -> None:
    """A uniform 0.9 panel over a 20 % V gradient cut at one DN in 30 % of its pixels: with each
    cut pixel's bound its product-limit median is the panel's; counted above, it reads high."""
    rng = np.random.default_rng(4)
    v = rng.uniform(0.8, 1.0, 3000)
    truth = 0.9 * (1.0 + 0.015 * rng.standard_normal(3000))
    cut = float(np.quantile(truth * v, 0.7))
    q = np.where(truth * v > cut, np.uint8(FLAGS["response_shoulder"]), np.uint8(0))[None]
    vals = np.where(q == 0, truth, np.nan)
    bounded, state = panel_value(vals, q, (cut / v)[None], max_flagged_share=0.5)
    above, _ = panel_value(vals, q, max_flagged_share=0.5)
    assert state[0] == 1 and abs(bounded[0] - np.median(truth)) < 0.001
    assert above[0] - np.median(truth) > 0.004
    assert np.isnan(panel_value(vals, q, (cut / v)[None])[0][0])  # a tenth flagged or more: not scored by default
