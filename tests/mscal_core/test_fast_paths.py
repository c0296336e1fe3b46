"""The faster forms of issue 25 give exactly the numbers of the forms they replaced.

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
    """rays_to_plane before issue 25: the rays that meet the plane gathered first."""
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
