"""A sun sensor's magnitude against the sky: the clear-sky spectral irradiance on horizontal
ground at a band's wavelength and the sun's elevation, and whether a reading is plausible.

The clear sky is NREL's SPECTRL2 (Bird and Riordan 1984, pvlib ``spectrum.spectrl2``): global
horizontal spectral irradiance, W m-2 nm-1, with a mid-latitude atmosphere (sea-level
pressure, 1.42 cm of precipitable water, 0.344 atm-cm of ozone, aerosol optical depth 0.1 at
500 nm, ground albedo 0.2; Kasten's relative air mass). A reading in W m-2 nm-1 is compared as
the ratio ``reading / clear sky``: clouds lower the light, nothing raises it ten times above a
clear sky, so a reading is plausible within :data:`PLAUSIBLE_RATIO`. Where the maker's documented
unit rules disagree (MicaSense DLS 2 files without ``IrradianceScaleToSIUnits``), the rule whose
value is plausible and closest to the clear sky in log ratio is taken (:func:`choose_rule`).

pvlib stays in ``pipeline``; the functions take and return plain numbers and arrays.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Readings within these ratios of the clear sky are plausible: overcast down to 2 %, and up to
#: 1.5x for a sensor tilted towards the sun, clouds' edges reflecting extra light and the
#: model's own atmosphere.
PLAUSIBLE_RATIO = (0.02, 1.5)
#: Below this sun elevation (degrees) the clear-sky model is not used (air mass beyond ~20).
MIN_ELEVATION_DEG = 3.0
#: A day of the year at which the sun is at its mean distance (1 AU).
MEAN_DISTANCE_DAY = 93.0
#: The atmosphere of :func:`clear_sky_spectral` (pvlib spectrl2's arguments).
ATMOSPHERE = {"surface_pressure": 101325.0, "precipitable_water": 1.42, "ozone": 0.344,
              "aerosol_turbidity_500nm": 0.1, "ground_albedo": 0.2}
MODEL = ("SPECTRL2 clear sky (pvlib spectrum.spectrl2), global horizontal, W m-2 nm-1: sea-level pressure, "
         "1.42 cm water, 0.344 atm-cm ozone, aerosol optical depth 0.1 at 500 nm")


def clear_sky_spectral(wavelength_nm: ArrayLike, elevation_deg: ArrayLike,
                       day_of_year: ArrayLike | None = None) -> NDArray[np.float64]:
    """Clear-sky global horizontal spectral irradiance, W m-2 nm-1, at each (wavelength, sun
    elevation) pair (broadcast); NaN where the sun is below :data:`MIN_ELEVATION_DEG` or
    unknown. ``day_of_year`` corrects the sun's distance (None or NaN: day 93, the mean
    distance of 1 AU)."""
    from pvlib.atmosphere import get_relative_airmass
    from pvlib.spectrum import spectrl2

    wl, el = np.broadcast_arrays(np.asarray(wavelength_nm, np.float64), np.asarray(elevation_deg, np.float64))
    doy = np.full(wl.shape, np.nan) if day_of_year is None else np.broadcast_to(
        np.asarray(day_of_year, np.float64), wl.shape)
    out = np.full(wl.shape, np.nan)
    ok = np.isfinite(wl) & np.isfinite(el) & (el >= MIN_ELEVATION_DEG)
    if not ok.any():
        return out
    # one vectorised call per day (the sun's distance), every elevation of that day at once
    for day in np.unique(doy[ok]):
        sel = ok & ((doy == day) if np.isfinite(day) else ~np.isfinite(doy))
        zenith = 90.0 - el[sel]
        spec = spectrl2(apparent_zenith=zenith, aoi=zenith, surface_tilt=0.0,
                        relative_airmass=np.asarray(get_relative_airmass(zenith, "kasten1966"), np.float64),
                        dayofyear=float(day) if np.isfinite(day) else MEAN_DISTANCE_DAY, **ATMOSPHERE)
        grid = np.asarray(spec["wavelength"], np.float64)
        g = np.asarray(spec["poa_global"], np.float64).reshape(grid.size, -1)
        out[sel] = [float(np.interp(w, grid, g[:, i])) for i, w in enumerate(wl[sel])]
    return out


def plausible(ratio: float) -> bool:
    """Whether ``reading / clear sky`` lies in :data:`PLAUSIBLE_RATIO`."""
    return math.isfinite(ratio) and PLAUSIBLE_RATIO[0] <= ratio <= PLAUSIBLE_RATIO[1]


def choose_rule(readings: Mapping[str, float], clear_sky: float) -> tuple[str, float, bool]:
    """Of one reading taken by several unit rules (``{rule: W m-2 nm-1}``), the rule whose value
    is plausible against ``clear_sky`` and closest to it in ``|log(ratio)|``; when none is
    plausible, the closest one. Returns ``(rule, ratio, plausible)``; with no clear sky
    (NaN), the first rule and a NaN ratio (plausible: not known, True)."""
    rules = list(readings)
    if not rules:
        raise ValueError("no unit rule to choose from")
    if not (math.isfinite(clear_sky) and clear_sky > 0):
        return rules[0], float("nan"), True
    ratios = {r: readings[r] / clear_sky for r in rules}
    dist = {r: abs(math.log(v)) if v > 0 and math.isfinite(v) else math.inf for r, v in ratios.items()}
    ok = [r for r in rules if plausible(ratios[r])]
    best = min(ok or rules, key=lambda r: dist[r])
    return best, ratios[best], bool(ok)


def choose_capture_rule(readings: Sequence[Mapping[str, float]], clear_sky: Sequence[float]) -> str | None:
    """One unit rule for all band readings of a capture (one sun sensor writes one unit): of
    the rules every band offers, the one that makes the most bands plausible against their
    clear sky, then the one closest to it in mean ``|log(ratio)|``. None when no band has a
    clear sky to compare with (each band then keeps :func:`choose_rule`'s first rule)."""
    pairs = [(r, c) for r, c in zip(readings, clear_sky) if r and math.isfinite(c) and c > 0]
    if not pairs:
        return None
    common = [k for k in pairs[0][0] if all(k in r for r, _ in pairs)]
    if not common:
        return None

    def score(rule: str) -> tuple[int, float]:
        ratios = [r[rule] / c for r, c in pairs]
        logs = [abs(math.log(v)) if v > 0 and math.isfinite(v) else math.inf for v in ratios]
        return sum(plausible(v) for v in ratios), -sum(logs) / len(logs)

    return max(common, key=score)


__all__ = ["ATMOSPHERE", "MIN_ELEVATION_DEG", "MODEL", "PLAUSIBLE_RATIO", "choose_capture_rule", "choose_rule",
           "clear_sky_spectral", "plausible"]
