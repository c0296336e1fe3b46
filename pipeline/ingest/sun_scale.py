"""The one fixed reflectance scale of each camera model's sun sensor: ``R = c L / E`` with the
radiance ``L`` and the sun-sensor reading ``E`` of the band file, and ``c`` a constant of the
camera model, never chosen from the data of a run (SPEC: the same capture gives the same
reflectance alone, in any flight, on any day).

- **MicaSense** (``c = pi``): ``R = pi L / E`` with ``L`` in W m-2 sr-1 nm-1 and ``E`` in W m-2
  nm-1 (micasense/imageprocessing ``image.py`` ``reflectance()``; MicaSense "Tutorial 3 - DLS
  Sensor Basic Usage"): absolute.
- **DJI** P4 Multispectral and Mavic 3M (``c = 1``): the guides' reflectance of a band is the
  camera value times ``pCam`` over the sunlight sensor's value, ``X pCam / (X_LS pLS)``, with
  ``pCam`` = ``drone-dji:SensorGainAdjustment`` (already in the camera value,
  :func:`mscal_core.vendors.dji_camera_value`) and ``X_LS pLS`` = ``drone-dji:Irradiance``
  ("calibrated sunlight sensor value"; DJI, P4 Multispectral Image Processing Guide v1.0,
  2020.07, and Mavic 3M Image Processing Guide v1.0, 2023.08, the NDVI section). The guides
  write no further constant (no pi, no panel): their reflectance is used as written, ``c = 1``.
  Neither guide says whether that ratio is absolute (its NDVI needs only ratios of bands):
  absolute values need a panel.
- **Parrot Sequoia** (``c = 5e-4``): Parrot's sensor model gives the irradiance on the imager
  ``I`` (SEQ AN 01, :func:`mscal_core.vendors.sequoia_irradiance`) and on the sunshine sensor
  ``E`` (:func:`mscal_core.vendors.sunshine_irradiance`), both "homogeneous to SI units but with
  an arbitrary scaling factor"; reflectance is ``R = K I / E`` with ``K`` a constant of the
  sensors' responses (Parrot developer forum, "Reflectance estimation" and "About radiometric
  calibration": "K is a constant that depends on sensors responses", found once with a target of
  known reflectance). Parrot publishes no K: mscal fixes ``K = 5e-4`` for the camera model,
  chosen once (2026-12) so that the one real capture in ../shared/data lies in the uint16
  TIFFs' range (its band medians 0.15 .. 0.41, NIR 99th percentile 1.2): the same for every
  Sequoia and run; absolute values need a panel.

Sentera's ILS counts have no published conversion (no entry: reflectance only from a panel).
The uint16 photogrammetry TIFFs store ``round(R * 32768)`` for every camera
(:data:`pipeline.products.writers.REFLECTANCE_SCALE`): fixed too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

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


DJI_GUIDES = ("DJI, P4 Multispectral Image Processing Guide v1.0 (2020.07) and Mavic 3M Image Processing Guide v1.0 "
              "(2023.08): reflectance = camera value x pCam (drone-dji:SensorGainAdjustment) / (X_LS x pLS) = "
              "drone-dji:Irradiance; the guides write no further constant (no pi): 1")

#: Per radiance model (``CaptureMeta.radiometry``), the camera model's one sun-sensor scale.
SUN_SENSOR_SCALES: dict[str, SunScale] = {
    "micasense": SunScale(math.pi, "R = pi L / E (L W m-2 sr-1 nm-1, E W m-2 nm-1)",
                          "MicaSense, micasense/imageprocessing image.py reflectance() and Tutorial 3 (DLS): pi", True),
    "dji": SunScale(1.0, "R = X pCam / Irradiance (X pCam: the camera value, Irradiance: drone-dji:Irradiance)",
                    DJI_GUIDES, False),
    "sequoia": SunScale(5e-4, "R = K I / E, K = 5e-4 (I: SEQ AN 01 irradiance on the imager, E: sunshine sensor "
                              "CH0 / (gain x ms x golden sensitivity))",
                        "Parrot SEQ AN 01 and developer forum ('Reflectance estimation', 'About radiometric "
                        "calibration': R = K I / E, K a constant of the sensors' responses); Parrot publishes no K: "
                        "mscal fixes K = 5e-4 for the camera model (chosen once so that the real sample capture "
                        "lies in 0..2), never from a run's data", False),
}


def sun_scale(radiometry: str) -> SunScale | None:
    """The fixed sun-sensor scale of a radiance model, None when its sun sensor gives no
    reflectance (Sentera, thermal, panchromatic)."""
    return SUN_SENSOR_SCALES.get(radiometry)


def sun_scale_constant(meta: CaptureMeta | None) -> float:
    """The band file's fixed scale ``c`` (1 without one): ``c / k`` is its sun sensor's reading."""
    scale = None if meta is None else sun_scale(meta.radiometry)
    return 1.0 if scale is None else scale.constant


def sun_scale_record(meta: CaptureMeta | None) -> dict[str, Any]:
    """run.json ``reference`` of the sun-sensor route: the formula, and the camera model's fixed
    scale with its source (``sun_sensor_scale``); ``scale`` says when it is not absolute."""
    scale = sun_scale("micasense" if meta is None else meta.radiometry) or SUN_SENSOR_SCALES["micasense"]
    rec: dict[str, Any] = {
        "formula": f"{scale.formula}; E the capture's sun sensor reading turned horizontal (sun position, sensor "
                   "tilt, direct/diffuse split: run.json sun_sensor)",
        "sun_sensor_scale": scale.record(),
    }
    if not scale.absolute:
        rec["scale"] = "fixed per camera model, not absolute (absolute values need a panel)"
    return rec


__all__ = ["SUN_SENSOR_SCALES", "SunScale", "sun_scale", "sun_scale_constant", "sun_scale_record"]
