"""Written positions that are none (pipeline.ingest.gps): no fix (0/0, GPSStatus V), a jump
the flight could not have made; snapshot frames' frames.csv; the STAC footprint without them
and without the panel captures."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from pipeline.ingest.gps import distance_m, exif_position, unreachable_positions
from pipeline.ingest.session import read_frame_table
from pipeline.products.stac import update_catalog

# 1 degree of latitude on the mean sphere
DEG_M = math.pi / 180 * 6_371_008.8


def test_distance_is_the_great_circle() -> None:
    assert distance_m(45.0, 15.0, 45.0 + 1.0, 15.0) == pytest.approx(DEG_M, rel=1e-12)
    # one degree of longitude at 60 deg north: half of one at the equator (to 0.02 %)
    assert distance_m(60.0, 15.0, 60.0, 16.0) == pytest.approx(DEG_M / 2, rel=2e-4)


def test_a_jump_is_left_out_and_the_flight_kept() -> None:
    """Captures every 2 s along a 10 m/s track; capture 5 is 10 km north: 5000 m/s from 4 and
    from 6. Only 5 is left out (the farther of each pair from the median)."""
    n = 10
    lat = [45.0 + 20.0 * i / DEG_M for i in range(n)]
    lon = [15.0] * n
    lat[5] += 10_000 / DEG_M
    t = [2.0 * i for i in range(n)]
    names = [f"IMG_{i:04d}" for i in range(n)]
    out = unreachable_positions(lat, lon, t, names)
    assert list(out) == [5]
    assert out[5].startswith("10.0")  # the median: 100 m along the track; capture 5: 100 m + 10 km
    assert "5010 m/s from IMG_0004 (2.0 s apart)" in out[5]
    # a flight that moves on 10 km in 200 s (50 m/s) to go on there is kept
    lat_on = [*lat[:5], *(45.0 + (20.0 * i + 10_000) / DEG_M for i in range(5, n))]
    t_on = [*t[:5], *[t[4] + 200.0 + 2.0 * k for k in range(5)]]
    assert unreachable_positions(lat_on, lon, t_on, names) == {}
    # a capture without time, and two captures, are not judged
    assert unreachable_positions(lat, lon, [*t[:5], None, *t[6:]], names) == {}
    assert unreachable_positions(lat[4:6], lon[4:6], t[4:6], names[4:6]) == {}


def test_no_fix_in_a_gps_ifd() -> None:
    from pipeline.ingest.gps import NoPosition

    zero = {"GPSLatitudeRef": "N", "GPSLatitude": (0, 1, 0, 1, 0, 1), "GPSLongitudeRef": "E",
            "GPSLongitude": (0, 1, 0, 1, 0, 1), "GPSAltitude": (5000, 1000)}
    with pytest.raises(NoPosition) as err:
        exif_position(zero)
    assert (err.value.tag, err.value.value) == ("EXIF GPSLatitude/GPSLongitude", "0, 0")
    fix = {**zero, "GPSLatitude": (45, 1, 30, 1, 0, 1), "GPSStatus": "A"}
    assert exif_position(fix) == (45.5, 0.0, 5.0)  # latitude 45.5 on the prime meridian is a position
    with pytest.raises(NoPosition) as err:
        exif_position({**fix, "GPSStatus": "V"})
    assert err.value.tag == "EXIF GPSStatus"


def test_frames_csv_zero_zero_and_a_jump(tmp_path: Path) -> None:
    rows = ["file,exposure_ms,time,lat,lon,alt_m"]
    for i in range(6):
        lat, lon = (0.0, 0.0) if i == 0 else (45.0 + 20.0 * i / DEG_M, 15.0)
        if i == 3:
            lat += 10_000 / DEG_M
        rows.append(f"IMG_{i:04d}.tif,2.0,2026-06-01T10:00:{2 * i:02d}Z,{lat!r},{lon!r},40")
    (tmp_path / "frames.csv").write_text("\n".join(rows) + "\n")
    recs = read_frame_table(tmp_path, require_files=False)
    assert [r.lat is None for r in recs] == [True, False, False, True, False, False]
    assert recs[0].alt_m is None and recs[1].alt_m == 40.0
    assert recs[4].lat == pytest.approx(45.0 + 80.0 / DEG_M, abs=1e-12)


def _flight(out: Path, lat: list[float], lon: list[float], panels: list[str]) -> None:
    import xarray as xr

    n = len(lat)
    t = np.datetime64("2026-06-01T10:00:00") + np.arange(n) * np.timedelta64(2, "s")
    ds = xr.Dataset({"ndvi": (("frame", "y", "x"), np.zeros((n, 2, 2), np.float32))},
                    coords={"frame": [f"IMG_{i:04d}" for i in range(n)], "lat": ("frame", np.array(lat)),
                            "lon": ("frame", np.array(lon)), "time": ("frame", t.astype("datetime64[ns]"))},
                    attrs={"camera": "micasense-rededge-m"})
    out.mkdir(parents=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.to_zarr(out / "reflectance.zarr", mode="w", consolidated=False)
    (out / "run.json").write_text(json.dumps({"frames_in": n, "frames_out": n, "quarantined": [],
                                              "panels": [{"capture": p, "reason": "test"} for p in panels]}))


def _bbox(root: Path) -> list[float]:
    update_catalog(root)
    (item,) = [d for d in (json.loads(p.read_text()) for p in (root / "stac").rglob("*.json"))
               if d.get("type") == "Feature"]
    return item["bbox"]


def test_stac_footprint_without_no_fix_and_without_panels(tmp_path: Path) -> None:
    # frame 0 at (0, 0) (a reflectance.zarr written before positions were checked)
    _flight(tmp_path / "a" / "f", [0.0, 6.10, 6.14], [0.0, 80.05, 80.10], [])
    np.testing.assert_allclose(_bbox(tmp_path / "a"), [80.05, 6.10, 80.10, 6.14])
    # the panel captures IMG_0000 and IMG_0003, on the ground 300 m off the survey
    _flight(tmp_path / "b" / "f", [6.097, 6.10, 6.14, 6.097], [80.05, 80.06, 80.10, 80.05], ["IMG_0000", "IMG_0003"])
    np.testing.assert_allclose(_bbox(tmp_path / "b"), [80.06, 6.10, 80.10, 6.14])
    # a flight of panel captures only keeps them
    _flight(tmp_path / "c" / "f", [6.097, 6.098], [80.05, 80.05], ["IMG_0000", "IMG_0001"])
    np.testing.assert_allclose(_bbox(tmp_path / "c"), [80.05, 6.097, 80.05, 6.098])
