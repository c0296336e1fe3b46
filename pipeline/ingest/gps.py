"""Positions of frames and captures, and when a written position is no position.

A camera writes GPS tags whether or not its receiver has a fix. Three kinds of written
position are missing positions here (the frame keeps no latitude, longitude or altitude, and
the reason is named):

* latitude 0 and longitude 0: what a MicaSense RedEdge, a DJI and others write before the
  first fix (a panel capture taken on the ground at power-on);
* EXIF ``GPSStatus`` ``V`` (EXIF: A = measurement in progress, V = measurement
  interoperability; the receiver's NMEA status "void", no valid fix);
* a position far from the rest of the flight with no time to get there
  (:func:`unreachable_positions`: faster than :data:`MAX_SPEED_M_S` from the capture before or
  after it in time, and the farther of the two from the flight's median position).

Left out of the track plot, the STAC footprint and the per-frame TIFFs' GPS tags, such
positions would put a flight at (0, 0) or stretch it over kilometres it never flew.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from pipeline.ingest.exif import NAT, dms_to_degrees, rational, signed_gps, time_ns

if TYPE_CHECKING:
    from pipeline.ingest.grouping import Capture

#: A survey UAV flies at 10-30 m/s; a position reached faster than this from the capture
#: before or after it is a receiver's jump, not a flight.
MAX_SPEED_M_S = 100.0
#: Capture times are written to the second by some cameras: two captures are at least this
#: far apart in time when their speed is judged.
MIN_INTERVAL_S = 1.0
EARTH_RADIUS_M = 6_371_008.8  # mean radius (IUGG)
#: A flight needs this many positioned captures to have a median position to judge against
#: (with two, neither is the odd one out).
MIN_CAPTURES = 3


class NoPosition(ValueError):
    """GPS tags that are written but are not a position (no fix): the tag, its value and why."""

    def __init__(self, tag: str, value: str, reason: str):
        super().__init__(reason)
        self.tag, self.value = tag, value


def no_fix_reason(lat: float | None, lon: float | None, status: Any = None) -> tuple[str, str, str] | None:
    """``(tag, value, reason)`` when a written position is no position (latitude and longitude
    both 0, or GPSStatus V), else None."""
    text = status.decode("ascii", "replace") if isinstance(status, bytes) else str(status or "")
    if text.strip("\x00 ").upper().startswith("V"):
        return ("EXIF GPSStatus", "V", "GPS status void (no fix when the image was taken): position left out")
    if lat == 0 and lon == 0:
        return ("EXIF GPSLatitude/GPSLongitude", "0, 0",
                "latitude 0 and longitude 0: written before the GPS had a fix; position left out")
    return None


def exif_position(gps: dict[str, Any]) -> tuple[float | None, float | None, float | None]:
    """``(lat, lon, alt_m)`` of a GPS IFD (tag names as tifffile gives them; None: not
    written); ``ValueError`` when a latitude or longitude is written but is not a number (a
    zero denominator: NaN), :class:`NoPosition` when it is no position (:func:`no_fix_reason`).
    An altitude that is not a number is left out."""
    has_pos = "GPSLatitude" in gps and "GPSLongitude" in gps
    lat, lon, alt = signed_gps(
        dms_to_degrees(gps["GPSLatitude"]) if has_pos else None, gps.get("GPSLatitudeRef"),
        dms_to_degrees(gps["GPSLongitude"]) if has_pos else None, gps.get("GPSLongitudeRef"),
        rational(gps["GPSAltitude"]) if "GPSAltitude" in gps else None,
        gps.get("GPSAltitudeRef") in (1, b"\x01", "1"),
    )
    if has_pos and not (lat is not None and lon is not None and math.isfinite(lat) and math.isfinite(lon)):
        raise ValueError("GPSLatitude/GPSLongitude is not a number (a zero denominator?)")
    status = gps.get("GPSStatus")
    if hasattr(status, "values"):  # an exifread tag
        status = status.values
    why = no_fix_reason(lat, lon, status) if has_pos else None
    if why is not None:
        raise NoPosition(*why)
    return lat, lon, alt if alt is not None and math.isfinite(alt) else None


def distance_m(lat1: Any, lon1: Any, lat2: Any, lon2: Any) -> Any:
    """Great-circle distance (haversine, metres) between WGS84 degrees."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dp, dl = p2 - p1, np.radians(np.asarray(lon2) - np.asarray(lon1))
    a = np.sin(dp / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(a, 0.0, 1.0)))


def unreachable_positions(lat: Sequence[float | None], lon: Sequence[float | None], seconds: Sequence[float | None],
                          names: Sequence[str], max_speed: float = MAX_SPEED_M_S) -> dict[int, str]:
    """Frames (by index) whose position could not have been reached: the reason of each.

    The frames with a position and a time, in time order: where two consecutive ones are
    further apart than ``max_speed`` allows in the time between them (at least
    :data:`MIN_INTERVAL_S`), the one farther from the flight's median position is left out
    (the farthest of all such first) and the check is redone without it. Frames without a
    time are not judged; fewer than :data:`MIN_CAPTURES` positioned frames are not judged
    either (no median to tell the odd one out)."""
    idx = [i for i in range(len(names)) if lat[i] is not None and lon[i] is not None and seconds[i] is not None
           and math.isfinite(float(lat[i])) and math.isfinite(float(lon[i])) and math.isfinite(float(seconds[i]))]
    if len(idx) < MIN_CAPTURES:
        return {}
    la = np.array([float(lat[i]) for i in idx])
    lo = np.array([float(lon[i]) for i in idx])
    t = np.array([float(seconds[i]) for i in idx])
    from_median = distance_m(la, lo, float(np.median(la)), float(np.median(lo)))
    live = sorted(range(len(idx)), key=lambda k: (t[k], k))
    out: dict[int, str] = {}
    while len(live) >= 2:
        worst: tuple[float, int, int, float, float] | None = None  # (from median, k, other, speed, dt)
        for a, b in zip(live, live[1:]):
            dt = max(t[b] - t[a], MIN_INTERVAL_S)
            speed = float(distance_m(la[a], lo[a], la[b], lo[b])) / dt
            if speed > max_speed:
                k, other = (a, b) if from_median[a] > from_median[b] else (b, a)
                if worst is None or from_median[k] > worst[0]:
                    worst = (float(from_median[k]), k, other, speed, float(t[b] - t[a]))
        if worst is None:
            break
        far, k, other, speed, dt = worst
        out[idx[k]] = (f"{far / 1000:.2f} km from the flight's median position and {speed:.0f} m/s from "
                       f"{names[idx[other]]} ({abs(dt):.1f} s apart): faster than {max_speed:.0f} m/s, no time to "
                       "get there; position left out")
        live.remove(k)
    return out


def seconds_of(times: Sequence[str | None]) -> list[float | None]:
    """Seconds since the epoch of ISO 8601 times as frames carry them (``Z`` or as written:
    one clock per flight), None where a time is missing or unreadable."""
    out: list[float | None] = []
    for text in times:
        try:
            ns = time_ns(text)
        except (ValueError, OverflowError):
            ns = NAT
        out.append(None if ns == NAT else ns / 1e9)
    return out


def without_unreachable(captures: Sequence["Capture"]) -> list["Capture"]:
    """``captures`` with the positions :func:`unreachable_positions` finds left out: every band
    file's latitude, longitude and altitude None, the reason a ``position`` problem of the
    capture's first file (run.json ``metadata_problems``)."""
    from dataclasses import replace

    from pipeline.ingest.xmp import TagProblem

    firsts = [c.metas[0] for c in captures]
    far = unreachable_positions([m.lat for m in firsts], [m.lon for m in firsts], seconds_of([m.time for m in firsts]),
                                [c.name for c in captures])
    out = list(captures)
    for i, why in far.items():
        m = firsts[i]
        problem = TagProblem(str(m.path), "EXIF GPSLatitude/GPSLongitude", f"{m.lat:.7f}, {m.lon:.7f}", why, "position")
        metas = tuple(replace(x, lat=None, lon=None, alt_m=None, problems=(*x.problems, problem) if b == 0
                              else x.problems) for b, x in enumerate(captures[i].metas))
        out[i] = replace(captures[i], metas=metas)
    return out


def placed_records(records: Sequence[Any], on_problem: Callable[[Any], None] | None = None) -> list[Any]:
    """Frame records (:class:`pipeline.ingest.session.FrameRecord`: ``path``, ``lat``, ``lon``,
    ``alt_m``, ``time``, ``gps_status``) with the positions that are none left out: no fix
    (:func:`no_fix_reason`) and the positions :func:`unreachable_positions` finds. Each is
    given to ``on_problem`` as a ``position`` :class:`pipeline.ingest.xmp.TagProblem` naming
    the frame's file (run.json ``metadata_problems``)."""
    from dataclasses import replace

    from pipeline.ingest.xmp import TagProblem

    def drop(r: Any, tag: str, value: str, why: str) -> Any:
        if on_problem is not None:
            on_problem(TagProblem(r.path.name, tag, value, why, "position"))
        return replace(r, lat=None, lon=None, alt_m=None)

    out = []
    for r in records:
        why = no_fix_reason(r.lat, r.lon, r.gps_status) if r.lat is not None and r.lon is not None else None
        out.append(r if why is None else drop(r, *why))
    far = unreachable_positions([r.lat for r in out], [r.lon for r in out], seconds_of([r.time for r in out]),
                                [r.path.name for r in out])
    return [drop(r, "GPS latitude/longitude", f"{r.lat:.7f}, {r.lon:.7f}", far[i]) if i in far else r
            for i, r in enumerate(out)]
