"""The layout of an apply's ``OUT/run.json``: which keys sit at the top and which under the key
of one kind of input, and reading a key from either layout.

At the top: what every apply records, the same in name and meaning for every camera (SPEC.md,
"Outputs of apply": frames in and out, ``quarantined``, saturated pixels, the calibration's hash,
versions, timings, ``outputs_manifest``; and ``fingerprint``, ``products``, ``quality``,
``illumination``, the light at each frame's time, which every kind of input records). Under
:data:`CAPTURES` the keys of a folder of captures (any chain), under :data:`FACTORY` those of
the factory chain; a snapshot flight's own keys were under ``snapshot`` already.
:func:`group_parts` nests a source's keys when the record is built, so producers write flat
dicts; :func:`run_value` reads a key from a record of this layout or of the flat one that mscal
wrote before (every key at the top), so a run folder made before still reports.
"""
from __future__ import annotations

from typing import Any, Mapping

#: run.json key of the keys of a folder of captures (any chain).
CAPTURES = "captures"
#: run.json key of the keys of the factory chain (``--calibration factory``).
FACTORY = "factory"

#: Per group, the keys a source's record puts under it.
GROUPS: dict[str, tuple[str, ...]] = {
    CAPTURES: ("inputs_listing", "skipped", "skipped_bands", "orientation", "capture_times", "panels",
               "coregistration", "thermal"),
    FACTORY: ("components", "reference", "camera_identification", "radiance_unit", "radiance_factor",
              "band_alignment", "light", "sun_sensor", "sun_sensor_check", "reflectance_missing"),
}
_GROUP_OF = {key: group for group, keys in GROUPS.items() for key in keys}


def group_parts(parts: Mapping[str, Any]) -> dict[str, Any]:
    """A source's run.json keys (``parts``, flat) in this layout: each key of :data:`GROUPS`
    under its group (in the order the source gave them), the others (``illumination``,
    ``snapshot``) as they are."""
    out: dict[str, Any] = {}
    for key, value in parts.items():
        group = _GROUP_OF.get(key)
        if group is None:
            out[key] = value
        else:
            out.setdefault(group, {})[key] = value
    return out


def run_value(run: Mapping[str, Any], key: str, default: Any = None) -> Any:
    """``key`` of an apply's run.json ``run``: under its group (:data:`GROUPS`) in this layout,
    at the top in the flat one of earlier runs; ``default`` when the run has none."""
    group = _GROUP_OF.get(key)
    if group is not None:
        nested = run.get(group)
        if isinstance(nested, Mapping) and key in nested:
            return nested[key]
    return run.get(key, default)


__all__ = ["CAPTURES", "FACTORY", "GROUPS", "group_parts", "run_value"]
