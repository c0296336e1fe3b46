"""How well panels and the sun sensor carry the light over time: the late panel of
a folder predicted from its early one, per band and per method. Used by the tests and
``bench/bench_light.py --sun-sensor`` on synthetic flights (:mod:`pipeline.sim.sunlight`) and on
real folders that hold a panel capture before and after a flight."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.apply.captures import capture_times, find_captures
from pipeline.apply.factory_reference import panel_reference
from pipeline.apply.sunlight import panel_sensor_light
from pipeline.ingest.catalog import reflectance_option
from pipeline.ingest.grouping import read_capture_pixels
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.meta import sun_sensor_absolute
from pipeline.ingest.sunsensor import sensor_light


def panel_prediction(folder: str | Path, panel_reflectance: str, early: str, late: str,
                     mode: str = "linear") -> dict[str, Any]:
    """How well the late panel capture is predicted from the early one, per band.

    Each panel capture is fitted on its own (``k = 1 / S``, Eq. 11-14 split, one region for
    all bands); the late panel's reflectance predicted with a factor ``k'`` is
    ``rho k' / k_late``, so the error is ``k' / k_late - 1`` for:

    - ``panel``: the early panel alone, ``k' = k_early``;
    - ``sensor``: the sun sensor alone (tilt-corrected), ``k' = k_sensor(late)`` (absolute
      sensors only; NaN for relative ones), as the ``dls`` route has it: the diffuse ratio the
      clear sky's 1/6 (or a DLS 2's split), never fitted from the folder's captures;
    - ``combined_raw``: the early panel scaled by the sensor's raw readings (no sun position,
      tilt or direct/diffuse split: what mscal did before horizontal levels);
    - ``combined``: the early panel anchoring the sensor (the ``panel-dls`` route with only the
      early panel), ``k' = k_early E^s(early) / E^s(late)``, the diffuse ratio fitted from the
      folder's captures where the route fits it;
    - ``self``: the late panel against itself: its reflectance over its region with the split
      factor, ``k_late,split / k_late,mean - 1``.
    """
    folder = Path(folder)
    camera = identify_camera(folder, None).camera
    caps = find_captures(folder, camera).captures
    names = [c.name for c in caps]
    wl = np.array([m.wavelength_nm for m in caps[0].metas])
    rho = [float(v) for v in reflectance_option(panel_reflectance).at(wl)]
    refs = {}
    for name in (early, late):
        cap = caps[names.index(name)]
        _, dns, ch = read_capture_pixels(cap)
        refs[name] = panel_reference(cap, dns, rho, channels=ch)
    times = capture_times(caps)
    sensor = sensor_light(caps, times)  # panel-dls's
    own = sensor_light(caps, times, fit_ratio=False)  # dls's: each capture on its own
    i_e, i_l = names.index(early), names.index(late)
    k_e, k_l = np.asarray(refs[early].factor_split), np.asarray(refs[late].factor_split)
    combined = panel_sensor_light(k_e[None], [i_e], times, sensor, mode).factor[i_l]
    k_sensor = own.factor[i_l] if sun_sensor_absolute(caps[i_l].metas[0]) else np.full(k_l.shape, np.nan)
    raw = own.factor * own.correction  # the readings' own k, before the turn to horizontal
    bands = list(camera.band_names)

    def per_band(values: np.ndarray) -> dict[str, float]:
        return dict(zip(bands, (float(v) for v in values)))

    return {
        "bands": bands,
        "panel": per_band(k_e / k_l - 1),
        "sensor": per_band(k_sensor / k_l - 1),
        "combined_raw": per_band(k_e * raw[i_l] / raw[i_e] / k_l - 1),
        "combined": per_band(combined / k_l - 1),
        "self": per_band(k_l / np.asarray(refs[late].factor_mean) - 1),
        "region_source": list(refs[late].region_source),
    }
