"""The faster forms give exactly the numbers of the forms they replaced.

Each reference below is the code as it was before (a sort where a count now does, a boolean
gather where a masked expression now does); the new form must match it bit for bit, ties,
empty bins, NaN and missed rays included.
"""

from __future__ import annotations

import numpy as np
import pytest

from mscal_core.geometry import Pose, rays_to_plane

# the helpers themselves are pinned here, against the code they replaced
from mscal_core.response._noise import _bin_order_stats  # noqa: PLC2701
from mscal_core.vignetting import _compact  # noqa: PLC2701


def _lexsort_order_stats(values: np.ndarray, k: np.ndarray, cnt: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    srt = np.lexsort((values, k))
    starts = np.concatenate([[0], np.cumsum(cnt)])[:-1]
    return values[srt][np.minimum(starts + ranks, values.size - 1)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bin_order_stats_match_a_full_sort(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, n_bins = 5000, 16
    values = np.round(rng.random(n) ** 3, 3)  # many ties
    values[rng.integers(0, n, 20)] = np.nan
    k = rng.integers(0, n_bins, n)
    k[k == 5] = 6  # an empty bin
    cnt = np.bincount(k, minlength=n_bins)
    for ranks in (cnt // 2, (cnt - 1) // 2, np.zeros_like(cnt), cnt - 1):
        got = _bin_order_stats(values, k, cnt, ranks)
        want = _lexsort_order_stats(values, k, cnt, ranks)
        ok = cnt > 0
        np.testing.assert_array_equal(got[ok], want[ok])
        assert got[5] == 0.0


def test_compact_matches_unique_and_searchsorted() -> None:
    rng = np.random.default_rng(3)
    idx = rng.integers(0, 5000, 40000) * 3  # gaps: most indices unused
    active, pos = _compact(idx, 15000)
    np.testing.assert_array_equal(active, np.unique(idx))
    np.testing.assert_array_equal(pos, np.searchsorted(np.unique(idx), idx))
    assert np.array_equal(active[pos], idx)


def _rays_to_plane_gather(rays: np.ndarray, pose: Pose) -> np.ndarray:
    """rays_to_plane before its faster form: the rays that meet the plane gathered first."""
    norm = np.asarray(rays, dtype=np.float64).reshape(-1, 2)
    out = np.full(norm.shape, np.nan)
    rot, t = pose.rotation, pose.tvec
    normal = rot[:, 2]
    num = float(normal @ t)
    den = norm[:, 0] * normal[0] + norm[:, 1] * normal[1] + normal[2]
    ray_len = np.sqrt(norm[:, 0] ** 2 + norm[:, 1] ** 2 + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / den
    ok = np.isfinite(s) & (np.abs(den) > 1e-9 * ray_len) & (s > 0)
    ok &= np.all(np.isfinite(norm), axis=1)
    sx, sy, sz = s[ok] * norm[ok, 0] - t[0], s[ok] * norm[ok, 1] - t[1], s[ok] - t[2]
    out[ok, 0] = rot[0, 0] * sx + rot[1, 0] * sy + rot[2, 0] * sz
    out[ok, 1] = rot[0, 1] * sx + rot[1, 1] * sy + rot[2, 1] * sz
    return out


def test_rays_to_plane_matches_the_gathering_form() -> None:
    rng = np.random.default_rng(4)
    rays = rng.uniform(-1.5, 1.5, (20000, 2))
    rays[:50] = np.nan
    rays[50:60, 0] = np.inf
    pose = Pose(rvec=np.array([1.2, -0.3, 0.2]), tvec=np.array([0.05, -0.02, 1.3]))  # steep: many rays miss
    got = rays_to_plane(rays, pose)
    want = _rays_to_plane_gather(rays, pose)
    missed = np.isnan(want[:, 0])
    assert 100 < missed.sum() < rays.shape[0] - 100  # both kinds of ray are tested
    np.testing.assert_array_equal(got, want)


def test_bin_order_stats_several_ranks_at_once() -> None:
    rng = np.random.default_rng(5)
    values = rng.random(3000)
    k = rng.integers(0, 16, 3000)
    cnt = np.bincount(k, minlength=16)
    lo, hi = _bin_order_stats(values, k, cnt, (cnt - 1) // 2, cnt // 2)
    np.testing.assert_array_equal(lo, _lexsort_order_stats(values, k, cnt, (cnt - 1) // 2))
    np.testing.assert_array_equal(hi, _lexsort_order_stats(values, k, cnt, cnt // 2))


def _noise_model_each_time(r, mu, lev, floor, robust, offset=None):
    """_noise_model before the residuals and bins were made once per noise_update."""
    from scipy.optimize import lsq_linear

    keep = lev < 0.9
    r2 = r[keep] ** 2 / (1.0 - lev[keep])
    if offset is not None:
        r2 = np.maximum(r2 - offset[keep], 0.0)
    mu = mu[keep]
    if r2.size < 10:
        return max(float(np.mean(r ** 2)) if r.size else 1.0, floor), 0.0
    edges = np.unique(np.quantile(mu, np.linspace(0, 1, 17)))
    if edges.size < 3:
        return max(float(r2.mean()), floor), 0.0
    k = np.clip(np.searchsorted(edges, mu, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1).astype(np.float64)
    ok = cnt > 0
    if robust:
        n_bin = cnt.astype(np.intp)
        lo_v, hi_v = _bin_order_stats(r2, k, n_bin, (n_bin - 1) // 2, n_bin // 2)
        mv = np.where(ok, 0.5 * (lo_v + hi_v), 0.0)[ok] / 0.4549
    else:
        mv = np.bincount(k, r2, edges.size - 1)[ok] / cnt[ok]
    mm = np.bincount(k, mu, edges.size - 1)[ok] / cnt[ok]
    X = np.stack([np.ones_like(mm), mm], 1)
    sw = np.sqrt(cnt[ok]) / np.maximum(mv, floor)
    sol = np.array([max(float(np.mean(mv)), floor), 0.0])
    for _ in range(2):
        trial = lsq_linear(X * sw[:, None], mv * sw, bounds=([floor, 0.0], [np.inf, np.inf])).x
        if not np.all(np.isfinite(trial)):
            break
        sol = trial
        sw = np.sqrt(cnt[ok]) / np.maximum(X @ sol, floor)
    return float(sol[0]), float(sol[1])


def _gradient_noise_each_time(r, lev, base, g2):
    keep = lev < 0.9
    r2 = r[keep] ** 2 / (1.0 - lev[keep])
    g2, base = g2[keep], base[keep]
    edges = np.unique(np.quantile(g2, np.linspace(0, 1, 9)))
    if edges.size < 3 or r2.size < 64:
        return 0.0
    k = np.clip(np.searchsorted(edges, g2, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    ok = cnt > 0
    med = _bin_order_stats(r2, k, cnt, cnt // 2) / 0.4549
    gmean = np.bincount(k, g2, edges.size - 1)[ok] / cnt[ok]
    excess = med[ok] - np.bincount(k, base, edges.size - 1)[ok] / cnt[ok]
    wts = cnt[ok] / np.maximum(med[ok], 1e-6) ** 2
    return max(float(np.sum(wts * gmean * excess) / max(float(np.sum(wts * gmean * gmean)), 1e-300)), 0.0)


@pytest.mark.parametrize("robust", [False, True])
def test_noise_update_matches_refitting_the_bins_each_time(robust: bool) -> None:
    from mscal_core.response._curve import Curve  # noqa: PLC2701
    from mscal_core.response._noise import _leverage, noise_update  # noqa: PLC2701

    rng = np.random.default_rng(6)
    n_frames, n_pix = 9, 3000
    t = np.geomspace(1.0, 16.0, n_frames)
    e = rng.uniform(2.0, 60.0, n_pix)
    xk = np.linspace(0.0, 1000.0, 17)
    curve = Curve(xk=xk, c=20.0 + 900.0 * np.sqrt(xk / 1000.0) + 0.1 * xk)
    mu, _ = curve(t[:, None] * e[None, :])
    g2 = rng.gamma(0.5, 40.0, (n_frames, n_pix))
    g2[:, :200] = 0.0  # flat pixels
    d = np.round(mu + rng.normal(0.0, 1.0, mu.shape) * np.sqrt(2.0 + 0.05 * (mu - 20.0) + 1.0 * g2))
    m = (d > 0) & (d < 1000)
    m[:, rng.integers(0, n_pix, 40)] = False
    w = m / (2.0 + 0.05 * np.maximum(mu - 20.0, 0.0))
    got = noise_update(d, m, w, t, e, curve, robust, g2)
    # the loop of noise_update as it was: everything made again in each pass
    mu, s = curve(t[:, None] * e[None, :])
    lev = _leverage(w, t, s)
    r, above = (d - mu)[m], np.maximum(mu - curve.c[0], 0.0)[m]
    a, b, c = 1.0, 0.0, 0.0
    for _ in range(2):
        a, b = _noise_model_each_time(r, above, lev[m], 1 / 12, robust, offset=c * g2[m])
        c = _gradient_noise_each_time(r, lev[m], a + b * above, g2[m])
    assert c > 0.1  # the gradient term is exercised (1.0 in the simulated noise)
    assert got == (a, b, c)
    # without g2: the noise model alone
    a0, b0, c0 = noise_update(d, m, w, t, e, curve, robust)
    assert (a0, b0, c0) == (*_noise_model_each_time(r, above, lev[m], 1 / 12, robust), 0.0)


def test_curve_at_remembers_the_last_exposures_and_energies() -> None:
    """Curve.at gives C(t E) of __call__ bit for bit, the same arrays again for the same t and
    E objects (the fit asks several times per iteration), read-only so no caller can change
    what the next one gets, and a new result for a new E."""
    from mscal_core.response._curve import Curve  # noqa: PLC2701

    rng = np.random.default_rng(8)
    xk = np.linspace(0.0, 500.0, 9)
    curve = Curve(xk=xk, c=10.0 + 700.0 * np.sqrt(xk / 500.0) + 0.2 * xk)
    t = np.array([1.0, 2.0, 4.5])
    e = rng.uniform(0.0, 150.0, 1000)
    mu, s = curve.at(t, e)
    want_mu, want_s = curve(t[:, None] * e[None, :])
    np.testing.assert_array_equal(mu, want_mu)
    np.testing.assert_array_equal(s, want_s)
    again = curve.at(t, e)
    assert again[0] is mu and again[1] is s
    with pytest.raises(ValueError, match="read-only"):
        mu[0, 0] = 0.0
    e2 = e * 1.01
    mu2, _ = curve.at(t, e2)
    assert mu2 is not mu
    np.testing.assert_array_equal(mu2, curve(t[:, None] * e2[None, :])[0])
    # an equal but different E array is evaluated again, not taken for the last one
    assert curve.at(t, e.copy())[0] is not mu
