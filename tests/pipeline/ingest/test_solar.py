"""pipeline.ingest.solar: the sun's position from time and GPS (pvlib's SPA)."""

import numpy as np
import pytest

from mscal_core.errors import InputError
from pipeline.ingest.solar import solar_position


def test_known_positions() -> None:
    # equinox noon on the equator at Greenwich: the sun nearly overhead; solstice noon at
    # 45 N: elevation 90 - 45 + 23.44 = 68.4 deg, due south
    el, az = solar_position(["2026-03-20T12:07:00", "2026-06-21T12:02:00"], [0.0, 45.0], [0.0, 0.0])
    assert np.rad2deg(el[0]) == pytest.approx(90, abs=0.6)
    assert np.rad2deg(el[1]) == pytest.approx(68.44, abs=0.1)
    assert np.rad2deg(az[1]) == pytest.approx(180, abs=1.0)


def test_real_micasense_capture_time_and_place() -> None:
    """The RedEdge sample (EXIF DateTimeOriginal 2017:10:19 20:40:39 UTC, 36.576 N 119.435 W):
    about an hour after solar noon (~19:43 UTC there), noon elevation 90 - 36.6 - 10.1 (the
    declination) = 43.3 deg: a little lower now, a little west of south."""
    el, az = solar_position(np.array(["2017-10-19T20:40:39"], "datetime64[ns]"), 36.576, -119.435, 101.9)
    assert 40.0 < np.rad2deg(el[0]) < 42.5 and 195 < np.rad2deg(az[0]) < 203


def test_missing_time_or_position_gives_nan_and_bad_position_is_an_error() -> None:
    el, az = solar_position(np.array(["NaT", "2026-06-21T12:00:00"], "datetime64[ns]"), [45.0, np.nan], [0.0, 0.0])
    assert np.isnan(el).all() and np.isnan(az).all()
    with pytest.raises(InputError, match="latitude"):
        solar_position(["2026-06-21T12:00:00"], 95.0, 0.0)


def test_one_call_for_all_frames_gives_each_frame_its_own_sun() -> None:
    """Frames at different times and places in one call: the same bits as pvlib's
    get_solarposition called once per frame (with its pressure from the altitude)."""
    import warnings

    import pandas as pd
    from pvlib.solarposition import get_solarposition

    rng = np.random.default_rng(3)
    n = 40
    t = (np.datetime64("2026-06-01T06:00", "ns") + rng.integers(0, 12 * 3600, n) * np.timedelta64(1, "s"))
    t[5] = np.datetime64("NaT")
    lat, lon, alt = rng.uniform(-60, 60, n), rng.uniform(-179, 179, n), rng.uniform(0, 3000, n)
    lat[7] = np.nan
    el, az = solar_position(t, lat, lon, alt)
    assert np.isnan(el[[5, 7]]).all() and np.isnan(az[[5, 7]]).all()
    for i in (0, 1, 13, n - 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            sp = get_solarposition(pd.DatetimeIndex([t[i]], tz="UTC"), lat[i], lon[i], altitude=alt[i])
        assert el[i] == np.deg2rad(float(sp["apparent_elevation"].iloc[0]))
        assert az[i] == np.deg2rad(float(sp["azimuth"].iloc[0]))
    assert np.ptp(el[np.isfinite(el)]) > 0.5  # frames really differ
