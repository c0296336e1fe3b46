"""The sun's position at a frame's time and place, for the sun-sensor model
(:mod:`mscal_core.sunsensor`).

pvlib's implementation of NREL's Solar Position Algorithm (Reda and Andreas 2004; accurate to
0.0003 degrees), with the refraction-corrected (apparent) elevation: the direction the direct
light arrives from. pvlib and pandas stay here; the maths of the sensor is pure numpy.
"""

from __future__ import annotations

import warnings

import numpy as np
from mscal_core.errors import InputError
from numpy.typing import ArrayLike, NDArray


def solar_position(times: ArrayLike, lat: ArrayLike, lon: ArrayLike,
                   alt_m: ArrayLike | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Apparent solar elevation and azimuth (clockwise from north), radians, per time.

    ``times`` are UTC (numpy datetime64 or ISO strings); ``lat``/``lon`` WGS 84 degrees,
    broadcast to the times; ``alt_m`` metres above sea level (0 if unknown). A frame without a
    time or position gets NaN: the caller decides whether it can do without the sun.
    """
    import pandas as pd
    from pvlib.atmosphere import alt2pres
    from pvlib.solarposition import spa_python

    t = np.atleast_1d(np.asarray(times, dtype="datetime64[ns]"))
    la = np.broadcast_to(np.asarray(lat, np.float64), t.shape)
    lo = np.broadcast_to(np.asarray(lon, np.float64), t.shape)
    al = np.zeros(t.shape) if alt_m is None else np.nan_to_num(np.broadcast_to(np.asarray(alt_m, np.float64), t.shape))
    if np.any((np.abs(la) > 90) & np.isfinite(la)) or np.any((np.abs(lo) > 180) & np.isfinite(lo)):
        raise InputError("latitude must lie in [-90, 90] and longitude in [-180, 180] degrees",
                         hint="check the GPS tags or the lat/lon columns of frames.csv")
    el = np.full(t.shape, np.nan)
    az = np.full(t.shape, np.nan)
    ok = ~np.isnat(t) & np.isfinite(la) & np.isfinite(lo)
    if not ok.any():
        return el, az
    # One call for every frame: SPA's numpy steps are element-wise, so a position per time
    # gives each frame's own sun (the same bits as one get_solarposition call per frame, with
    # its pressure from the altitude; 5 ms instead of 10 ms per frame).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        sp = spa_python(pd.DatetimeIndex(t[ok], tz="UTC"), la[ok], lo[ok], altitude=al[ok],
                        pressure=alt2pres(al[ok]), how="numpy")
    el[ok] = np.deg2rad(sp["apparent_elevation"].to_numpy(dtype=np.float64))
    az[ok] = np.deg2rad(sp["azimuth"].to_numpy(dtype=np.float64))
    return el, az
