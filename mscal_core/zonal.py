"""Per-field (zonal) statistics of an index map: the maths, no I/O.

A field's statistics are computed from the index values of the pixels of one mosaic whose
centres fall inside the field (GDAL's rasterisation rule, ``all_touched=False``):

- ``n_pixels``  = pixel centres of the mosaic's grid inside the field, *including* those
  beyond the mosaic's edge (so a field half off the mosaic has ``valid_fraction`` <= 0.5);
- ``n_valid``   = those with a finite index value (not nodata, not masked, not NaN);
- ``valid_fraction = n_valid / n_pixels``;
- ``mean = sum(v) / n``, ``std = sqrt(sum((v - mean)^2) / n)`` (population, ddof = 0);
- ``median``, ``p10``, ``p90``: quantiles of the valid values by linear interpolation between
  order statistics, ``q(p) = v_(k) + (h - k) (v_(k+1) - v_(k))`` with ``h = (n - 1) p``,
  ``k = floor(h)`` (Hyndman & Fan type 7, numpy's default ``method="linear"``).

Everything is computed in float64 from the values as stored (float32 index maps). These need
every valid value of a field at once (exact order statistics); see ``pipeline/products/zonal.py`` for
how the memory is bounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["QUANTILES", "ZonalStats", "zonal_statistics"]

#: The quantiles reported besides the median, as fractions (p10, p90).
QUANTILES: tuple[float, float] = (0.10, 0.90)


@dataclass(frozen=True)
class ZonalStats:
    """Statistics of one field on one index map (NaN where no pixel is valid).

    Attributes
    ----------
    n_pixels : int
        Pixel centres of the mosaic inside the field.
    n_valid : int
        Of those, pixels with a finite index value.
    valid_fraction : float
        ``n_valid / n_pixels`` (NaN when ``n_pixels == 0``).
    mean, median, std, p10, p90 : float
        Mean, population std (ddof 0) and the type-7 quantiles 0.5, 0.1, 0.9 of the valid
        values (module docstring).
    """

    n_pixels: int
    n_valid: int
    valid_fraction: float
    mean: float
    median: float
    std: float
    p10: float
    p90: float


def zonal_statistics(values: np.ndarray, n_pixels: int) -> ZonalStats:
    """Compute the statistics of the finite entries of ``values``, ``n_pixels`` pixels in the field.

    Parameters
    ----------
    values : numpy.ndarray
        Index values of the field's pixels (any shape); non-finite entries are not valid.
    n_pixels : int
        Pixels in the field; must be >= the number of finite values.

    Returns
    -------
    ZonalStats
        ``valid_fraction = n_valid / n_pixels`` (NaN when ``n_pixels == 0``); mean, population
        std (ddof 0), and the type-7 quantiles 0.5, 0.1, 0.9 (module docstring), in float64.

    Raises
    ------
    ValueError
        When ``n_pixels`` is smaller than the number of finite values.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n_pixels < n:
        raise ValueError(f"n_pixels {n_pixels} is smaller than the {n} valid values")
    frac = float(n / n_pixels) if n_pixels > 0 else float("nan")
    if n == 0:
        nan = float("nan")
        return ZonalStats(int(n_pixels), 0, frac, nan, nan, nan, nan, nan)
    mean = float(v.mean())
    std = float(np.sqrt(np.mean((v - mean) ** 2)))
    q = np.quantile(v, [0.5, *QUANTILES], method="linear")
    return ZonalStats(int(n_pixels), n, frac, mean, float(q[0]), std, float(q[1]), float(q[2]))
