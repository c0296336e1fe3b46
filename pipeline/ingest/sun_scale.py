"""The one fixed reflectance scale of each camera model's sun sensor: ``R = c L / E`` with the
radiance ``L`` and the sun-sensor reading ``E`` of the band file, and ``c`` a constant of the
camera model, never chosen from the data of a run (SPEC: the same capture gives the same
reflectance alone, in any flight, on any day).

Each camera maker's module keeps its own constants with their sources
(``Maker.sun_scales``, by radiometry: :mod:`pipeline.ingest.cameras.micasense` pi,
:mod:`pipeline.ingest.cameras.dji` 1, :mod:`pipeline.ingest.cameras.parrot` 5e-4;
:mod:`pipeline.ingest.cameras.sentera` none: reflectance only from a panel); this module looks
them up and says what run.json records of them. The uint16 photogrammetry TIFFs store
``round(R * 32768)`` for every camera (:data:`pipeline.products.writers.REFLECTANCE_SCALE`):
fixed too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pipeline.ingest.cameras.registry import by_order, fallback

if TYPE_CHECKING:
    from pipeline.ingest.meta import CaptureMeta


@dataclass(frozen=True)
class SunScale:
    """The sun-sensor reflectance ``R = constant L / E`` of one radiance model."""

    constant: float
    formula: str
    source: str
    absolute: bool

    def record(self) -> dict[str, Any]:
        """run.json ``reference.sun_sensor_scale``."""
        return {"constant": self.constant, "formula": self.formula, "absolute": self.absolute, "source": self.source}


def sun_sensor_scales() -> dict[str, SunScale]:
    """Every registered maker's fixed sun-sensor scales, by radiance model (``CaptureMeta.radiometry``)."""
    return {radiometry: scale for maker in by_order() for radiometry, scale in maker.sun_scales.items()}


def sun_scale(radiometry: str) -> SunScale | None:
    """The fixed sun-sensor scale of a radiance model, None when its sun sensor gives no
    reflectance (Sentera, thermal, panchromatic)."""
    for maker in by_order():
        if radiometry in maker.sun_scales:
            return maker.sun_scales[radiometry]
    return None


def sun_scale_constant(meta: CaptureMeta | None) -> float:
    """The band file's fixed scale ``c`` (1 without one): ``c / k`` is its sun sensor's reading."""
    scale = None if meta is None else sun_scale(meta.radiometry)
    return 1.0 if scale is None else scale.constant


def sun_scale_record(meta: CaptureMeta | None) -> dict[str, Any]:
    """run.json ``reference`` of the sun-sensor route: the formula, and the camera model's fixed
    scale with its source (``sun_sensor_scale``); ``scale`` says when it is not absolute. Without
    a band, or for one whose sensor has no scale, the fallback maker's first scale (MicaSense's)."""
    default = next(iter(fallback().sun_scales.values()))
    scale = (None if meta is None else sun_scale(meta.radiometry)) or default
    rec: dict[str, Any] = {
        "formula": f"{scale.formula}; E the capture's sun sensor reading turned horizontal (sun position, sensor "
                   "tilt, direct/diffuse split: run.json sun_sensor)",
        "sun_sensor_scale": scale.record(),
    }
    if not scale.absolute:
        rec["scale"] = "fixed per camera model, not absolute (absolute values need a panel)"
    return rec


__all__ = ["SunScale", "sun_scale", "sun_scale_constant", "sun_scale_record", "sun_sensor_scales"]
