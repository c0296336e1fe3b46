"""pipeline.ingest.exif: the one copy of the RATIONAL / DMS / time codecs, read both ways
(tifffile's flat tuples, exifread's Ratio objects) and written back."""

from __future__ import annotations

import math
from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.ingest.exif import (
    NAT,
    degrees_to_dms,
    dms_to_degrees,
    exif_time_utc,
    exposure_time,
    parse_iso,
    rational,
    signed_gps,
    time_ns,
    to_rational,
    utc_naive,
)


class Ratio(SimpleNamespace):  # what exifread gives: .num and .den
    pass


def test_rational_reads_every_form() -> None:
    assert rational((1, 400)) == 0.0025
    assert rational(Ratio(num=1, den=400)) == 0.0025
    assert rational(SimpleNamespace(values=[Ratio(num=3, den=2)])) == 1.5  # an exifread tag
    assert rational((7,)) == 7.0 and rational(2) == 2.0
    assert math.isnan(rational((0, 0)))


def test_dms_round_trip_tifffile_and_exifread_forms() -> None:
    deg = 52.123456789
    dms = degrees_to_dms(-deg)  # the sign goes to the reference tag
    assert dms == [(52, 1), (7, 1), (24444440, 1_000_000)]
    flat = tuple(x for pair in dms for x in pair)
    assert dms_to_degrees(flat) == pytest.approx(deg, abs=1e-9)
    tag = SimpleNamespace(values=[Ratio(num=n, den=d) for n, d in dms])
    assert dms_to_degrees(tag) == dms_to_degrees(flat) == dms_to_degrees(dms)
    # exact carry: 59.9999999 s rounds up into the next minute, not to 60 s
    assert degrees_to_dms(1 + 59.99999999 / 3600) == [(1, 1), (1, 1), (0, 1_000_000)]
    assert signed_gps(1.0, "S", 2.0, "W ", 3.0, True) == (-1.0, -2.0, -3.0)
    assert signed_gps(1.0, "N", 2.0, None, None, False) == (1.0, 2.0, None)


def test_to_rational_fits_32_bits() -> None:
    assert to_rational(0.5) == (1, 2) and to_rational((72, 1)) == (72, 1)
    n, d = to_rational(math.pi)
    assert n <= 2**32 - 1 and d <= 2**32 - 1 and abs(n / d - math.pi) < 1e-9
    with pytest.raises(ValueError, match="RATIONAL"):
        to_rational(-1.0)
    assert to_rational(Fraction(3, 4)) == (3, 4)


def test_exif_datetime_and_iso_times() -> None:
    assert exif_time_utc("2024:06:01 10:30:00") == "2024-06-01T10:30:00"
    assert exif_time_utc(b"2024:06:01 10:30:00".decode(), "123") == "2024-06-01T10:30:00.123"
    assert exif_time_utc("2024:06:01 10:30:00", " ") == "2024-06-01T10:30:00"
    assert exif_time_utc("    :  :     :  :  ") is None and exif_time_utc(None) is None
    t, zoned = utc_naive(parse_iso("2024-06-01T12:30:00+02:00"))
    assert zoned and t.isoformat() == "2024-06-01T10:30:00"
    assert utc_naive(parse_iso("2024-06-01T10:30:00")) == (parse_iso("2024-06-01T10:30:00"), False)
    assert time_ns("2024-06-01T10:30:00Z") == time_ns("2024-06-01T12:30:00+02:00") == int(
        np.datetime64("2024-06-01T10:30:00", "ns").astype(np.int64))
    assert time_ns(None) == time_ns("") == NAT
    with pytest.raises(ValueError):
        parse_iso("yesterday")


def test_exposure_times_in_utc_when_the_zone_is_known() -> None:
    """EXIF 2.31 OffsetTimeOriginal gives DateTimeOriginal's zone: UTC with Z, across a day;
    no usable offset: as written; a clock that was never set (zeros, spaces): no time; DJI's
    UTCAtExposure (with its fraction) wins over the local DateTimeOriginal unless unreadable."""
    assert exif_time_utc("2025:05:20 10:12:34", None, "+08:00") == "2025-05-20T02:12:34Z"
    assert exif_time_utc("2025:01:01 03:00:00", "5", "+08:00") == "2024-12-31T19:00:00.5Z"
    assert exif_time_utc("2025:01:01 22:00:00", None, "-05:30") == "2025-01-02T03:30:00Z"
    assert exif_time_utc("2025:05:20 10:12:34", "123", None) == "2025-05-20T10:12:34.123"
    for offset in ("", "   ", "+8", "+24:00", "+08:60", "Z"):
        assert exif_time_utc("2025:05:20 10:12:34", None, offset) == "2025-05-20T10:12:34", offset
    for never in ("0000:00:00 00:00:00", "    :  :     :  :  ", "2025:13:01 10:00:00", "2025:05:20 10:12", None):
        assert exif_time_utc(never, None, "+01:00") is None and exif_time_utc(never) is None, never
    assert exif_time_utc("0001:01:01 00:30:00", None, "+01:00") is None  # before year 1 in UTC
    assert exif_time_utc("0999:01:01 00:30:00") == "0999-01-01T00:30:00"
    assert exposure_time("2025:05:20 10:12:34", None, None, "2025:05:20 02:12:54.019996") == "2025-05-20T02:12:54.019996Z"
    assert exposure_time("2025:05:20 10:12:34", "7", "+08:00", "garbled") == "2025-05-20T02:12:34.7Z"
    assert exposure_time("2025:05:20 10:12:34", "7") == "2025-05-20T10:12:34.7"
    assert time_ns(exposure_time("2025:05:20 10:12:34", None, "+08:00")) == time_ns("2025-05-20T02:12:34")
