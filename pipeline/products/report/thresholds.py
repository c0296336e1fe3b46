"""The QA report's thresholds (each warning is a number compared with one of these) and the
bounds on how much data its plots sample; :class:`QAWarning`.
"""

from __future__ import annotations

from dataclasses import dataclass

# --------------------------------------------------------------------------- thresholds

#: Saturated pixels carry no radiometry (Eq. 15 gives NaN). Above 1 % of the reflector pixels
#: of a calibration dataset, or of a flight's pixels, the exposure was too long.
SATURATED_FRACTION_MAX = 0.01
#: The sweep should observe at least 80 % of the usable DN range [black level, saturation):
#: outside what it saw, U is extrapolated, not measured (Eq. 6 has no samples there).
SWEEP_COVERAGE_MIN = 0.8
#: Flight DN above the highest DN the sweep observed use the extrapolated part of U; more
#: than 0.1 % of the flight's pixels there means the sweep missed the bright end.
FLIGHT_DN_OUTSIDE_SWEEP_MAX = 0.001
#: More than a fifth of the marker views without the marker means the geometry coverage of
#: the vignetting fit is thinner than planned (check marker id, focus, framing).
MARKER_MISSING_FRACTION_MAX = 0.2
#: The illumination fit (Eq. 13) averages over the reflector pixels; below 10 000 pixels
#: (about 100 x 100, a twelfth of the Ximea band grid) B(x) covers too little to judge the light.
MIN_REFLECTOR_PIXELS = 10_000
#: Below half of the band grid observed, V is mostly the smooth radial fill, not measured.
VIGNETTING_OBSERVED_MIN = 0.5
#: Residuals: about 3x what the fits reach on sound data (synthetic demo session: response
#: 3.0 DN rms = the sensor noise, vignetting 0.8-1.0 %, illumination 1.5 %). Above them the
#: scene moved during the sweep, a marker pose is wrong, or the light changed between images.
RESPONSE_RESIDUAL_RMS_DN_MAX = 9.0  # for 10-bit DN; x 2^(bits - 10) for deeper sensors (response_residual_limit)
VIGNETTING_RESIDUAL_RMS_MAX = 0.03
ILLUMINATION_RESIDUAL_RMS_MAX = 0.05
#: Reflector images taken minutes apart under the same sky differ in median brightness by a
#: few per cent (demo: 1.06 vs 0.90); a factor 1.5 points to a wrong exposure_ms or gain.
REFLECTOR_BRIGHTNESS_RATIO_MAX = 1.5
#: A flight frame whose exposure-normalised level (median (DN - black) / t) is more than a
#: factor 2 off the flight's median: clouds change the light by less over one flight, a
#: wrong exposure_ms or gain by more.
FRAME_LEVEL_RATIO_MAX = 2.0
#: The light's colour (S with its level removed, ``mscal_core.illumination.colour_change``)
#: may change by at most 2 % in any band between consecutive reflector captures. The light
#: is interpolated between captures; if a change was not linear in time, the
#: interpolated colour can be off by up to about half of it mid-way, and mscal aims at 1 %.
#: Above it, capture the reflector more often or re-fly in steadier light.
CAPTURE_COLOUR_CHANGE_MAX = 0.02
#: Panel and sun sensor (DLS) on the same capture (factory apply): their factor ratio
#: carries the DLS's tilt and cosine error, one number for all bands; its spread across bands
#: (max/min - 1) is a disagreement in colour that goes straight into every index. Above 5 %
#: the two references give NDVI differing by more than about 0.02 on vegetation: keep the panel.
PANEL_DLS_COLOUR_SPREAD_MAX = 0.05
#: Band registration: the median distance of the registered captures' transforms
#: to the session transform of a band. Captures of one flight at one altitude agree to a few
#: tenths of a pixel (synthetic rigs: < 0.3 px); above 1 px the captures saw the rig from
#: different distances (parallax: a panel capture at 1 m beside flight captures) or one
#: registration went wrong, and frames that were not registered themselves take a median
#: that fits none of them.
REGISTRATION_SPREAD_MAX_PX = 1.0
#: Band co-registration measured on a flight's pixels (run.json ``coregistration``): the median
#: residual shift of a band against the reference band after the run's alignment. Above 1 px
#: per-pixel indices mix neighbouring ground points at every edge.
BAND_MISREGISTRATION_MAX_PX = 1.0

# --------------------------------------------------------------------------- sampling bounds

#: Frames read for histograms and DN coverage (evenly spaced over the flight).
HIST_MAX_FRAMES = 12
#: Pixels per band per frame in histograms (a regular stride over the band grid).
HIST_MAX_PIXELS = 20_000
#: Frames read for the exposure-consistency check (one chunk read per frame).
LEVEL_MAX_FRAMES = 400
#: Frames shown as NDVI quick-looks.
NDVI_MAX_FRAMES = 3
#: Rows of the HTML/markdown frame table (quarantined frames are always listed).
TABLE_MAX_ROWS = 300

PNG_DPI = 80


@dataclass(frozen=True)
class QAWarning:
    """One finding with its number: ``value`` compared with ``threshold`` (same unit).

    (Not called ``Warning``: that would shadow the builtin warning category in this module.)
    """

    code: str
    message: str
    value: float
    threshold: float


