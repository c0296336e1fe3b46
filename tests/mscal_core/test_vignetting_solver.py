"""Tests of mscal_core.vignetting_solver: the log-domain start of the Eq. 8-10 fit solves its
least-squares problem, with the plane cells eliminated exactly."""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.vignetting_solver import alternate, compact, incidence, informative, log_init


def problem(seed: int = 3, n_pix: int = 300, n_cells: int = 60, n_obs: int = 4000, noise: float = 0.02):
    rng = np.random.default_rng(seed)
    pix = rng.integers(0, n_pix, n_obs)
    cell = rng.integers(0, n_cells, n_obs)
    v = rng.uniform(0.5, 1.0, n_pix)
    lum = rng.uniform(50.0, 200.0, n_cells)
    y = v[pix] * lum[cell] * np.exp(noise * rng.standard_normal(n_obs))
    return pix, cell, y, n_pix, n_cells


def dense_log_solution(pix, cell, y, n_pix, n_cells):
    """log V, log L of ``log y = log V + log L`` by a dense least-squares solve (gauge max log V = 0)."""
    a = np.zeros((pix.size, n_pix + n_cells))
    a[np.arange(pix.size), pix] = 1.0
    a[np.arange(pix.size), n_pix + cell] = 1.0
    x = np.linalg.lstsq(a, np.log(y), rcond=None)[0]
    lv, ll = x[:n_pix], x[n_pix:]
    off = lv.max()
    return lv - off, ll + off


def test_log_init_solves_the_log_least_squares() -> None:
    pix, cell, y, n_pix, n_cells = problem()
    structure = incidence(pix, cell, n_pix, n_cells)
    v, lum = log_init(pix, cell, y, n_pix, n_cells, 200, structure)
    lv, ll = dense_log_solution(pix, cell, y, n_pix, n_cells)
    # CG stops when the preconditioned residual has fallen by 1e-7 (measured: 4e-8 here)
    np.testing.assert_allclose(np.log(v), lv, atol=1e-6)
    np.testing.assert_allclose(np.log(lum), ll, atol=1e-6)


def test_log_init_converges_in_few_iterations() -> None:
    """Eliminating the cells leaves a well-conditioned pixel system: 10 CG iterations already
    give log V to 1e-5 on 300 pixels and 60 cells."""
    pix, cell, y, n_pix, n_cells = problem()
    structure = incidence(pix, cell, n_pix, n_cells)
    lv, _ = dense_log_solution(pix, cell, y, n_pix, n_cells)
    v10, _ = log_init(pix, cell, y, n_pix, n_cells, 10, structure)
    v2, _ = log_init(pix, cell, y, n_pix, n_cells, 2, structure)
    assert np.max(np.abs(np.log(v10) - lv)) < 1e-5
    assert np.max(np.abs(np.log(v2) - lv)) > 1e-4  # not solved by the first step alone


def test_alternate_from_log_init_fits_v_and_l() -> None:
    pix, cell, y, n_pix, n_cells = problem(noise=0.0)
    structure = incidence(pix, cell, n_pix, n_cells)
    v0, _ = log_init(pix, cell, y, n_pix, n_cells, 200, structure)
    v, lum, sweeps, converged = alternate(y, np.ones_like(y), v0, n_cells, 50, 1e-10, structure)
    assert converged and sweeps <= 10  # noise-free: the log start is the solution to ~1e-7
    np.testing.assert_allclose(v[pix] * lum[cell], y, rtol=1e-8)


def test_informative_and_compact() -> None:
    # cell 0 seen by pixels 0 and 1, cell 3 by pixels 0, 5 and 6: one connected part; cell 1
    # only by pixel 2 (uninformative); cell 2 by pixels 3 and 4, a smaller part of its own
    pix = np.array([0, 1, 0, 2, 2, 3, 4, 5, 5, 6])
    cell = np.array([0, 0, 3, 1, 1, 2, 2, 3, 3, 3])
    use = informative(pix, cell, 7, 4)
    assert use.tolist() == [True, True, True, False, False, False, False, True, True, True]
    active, pos = compact(np.array([5, 2, 5, 9]), 10)
    assert active.tolist() == [2, 5, 9] and pos.tolist() == [1, 0, 1, 2]


def test_weighted_log_init_starts_next_to_the_least_squares_of_y() -> None:
    """Weighted by y^2, the log fit's minimum is Eq. 8's (least squares in y) to first order:
    with 10 % noise the weighted start is closer to the alternation's end than the unweighted."""
    pix, cell, y, n_pix, n_cells = problem(noise=0.10, seed=8)
    structure = incidence(pix, cell, n_pix, n_cells)
    plain, _ = log_init(pix, cell, y, n_pix, n_cells, 200, structure)
    weighted, _ = log_init(pix, cell, y, n_pix, n_cells, 200, structure, (y / np.median(y)) ** 2)
    end, _, _, converged = alternate(y, np.ones_like(y), plain, n_cells, 500, 1e-12, structure)
    assert converged
    gap = lambda v: float(np.max(np.abs(np.log(v / end) - np.median(np.log(v / end)))))
    assert gap(weighted) < 0.5 * gap(plain)


def test_log_init_without_iterations_starts_flat() -> None:
    pix, cell, y, n_pix, n_cells = problem()
    v, _ = log_init(pix, cell, y, n_pix, n_cells, 0, incidence(pix, cell, n_pix, n_cells))
    assert v == pytest.approx(np.ones(n_pix))


def test_robust_weights_and_scale() -> None:
    """Huber: weight 1 within k = 1.345 scales, k s / |r| beyond; Cauchy: 1 / (1 + (r / 2.385 s)^2);
    the scale is 1.4826 x the median |r| (the standard deviation of Gaussian residuals)."""
    from mscal_core.vignetting_solver import robust_scale, robust_weights

    r = np.array([0.0, 0.01, -0.0134, 0.02, -0.1])
    np.testing.assert_allclose(robust_weights(r, "huber", 0.01), [1.0, 1.0, 1.0, 0.6725, 0.1345])
    np.testing.assert_allclose(robust_weights(r, "cauchy", 0.01),
                               1.0 / (1.0 + (r / 0.023849) ** 2))
    noise = np.random.default_rng(0).normal(0.0, 0.02, 200000)
    noise[:20000] = 0.5  # a tenth gross outliers barely move the MAD scale
    assert robust_scale(noise) == pytest.approx(0.0225, abs=0.0008)
    assert robust_scale(np.zeros(100)) == 1e-3  # floor: noise-free data keep weight 1


def test_a_view_offset_by_more_than_the_noise_is_down_weighted() -> None:
    """Views whose mean residual is within k s keep weight 1 (whatever their noise); a view
    3 % off with 1 % noise per pixel gets Huber's k s / |m| with m its mean residual clipped
    to 3 s (2.6 %: 0.51); a tenth of gross outliers in a view move its clipped mean by 0.3 %
    only."""
    from mscal_core.vignetting_solver import view_offset_weights

    rng = np.random.default_rng(2)
    view = np.repeat(np.arange(5), 1000)
    resid = rng.normal(0.0, 0.01, view.size)
    resid[view == 1] *= 2.0  # noisier, not offset
    resid[view == 2] += 0.03  # offset
    resid[(view == 3) & (np.arange(view.size) % 10 == 0)] = 0.5  # a tenth gross outliers
    w = view_offset_weights(resid, view, np.ones(view.size), 0.01)
    np.testing.assert_array_equal(w[[0, 1, 4]], 1.0)
    m = np.mean(np.clip(resid[view == 2], -0.03, 0.03))
    assert m == pytest.approx(0.026, abs=0.001)
    assert w[2] == pytest.approx(1.345 * 0.01 / m, rel=1e-9)
    assert w[3] == 1.0  # 0.1 x 0.03 = 0.3 % < 1.345 %
