"""A flight under drifting light with a tilted sun sensor, written as a real camera's files;
the check run on it (and on real folders) is
:func:`pipeline.apply.light_check.panel_prediction`.

``write_sunlight_flight(template, out)`` takes a MicaSense RedEdge capture folder (a panel
capture ``IMG_0000_*`` and a flight capture ``IMG_0001_*``; ../shared/data/micasense-rededge)
and writes::

    out/IMG_0000_{1..5}.tif              the panel, early (t = 0)
    out/IMG_0001_* ... IMG_000n_*        flight captures between
    out/IMG_000{n+1}_{1..5}.tif          the same panel, late (t = duration_s)

Truth (seeded; :class:`SunlightTruth`): the sun moves (pvlib's position for the template's
time and GPS); the direct light's level drifts linearly to ``level_end``; the diffuse part
``r_b(t) = E_dif / E_dir = r0 (550 / lambda)^r_exponent (1 + haze t / T)`` (default: the
clear sky's 1/6 in every band, constant; ``haze`` > 0 makes it grow over the flight,
``r_exponent`` 2 a bluer sky); the sensor
is tilted (yaw uniform, pitch and roll normal with ``panel_tilt_deg`` during the panel
captures, hand-held, and ``flight_tilt_deg`` in flight) and reads
:func:`mscal_core.sunsensor.sensor_reading` of that light times a per-band calibration error
``1 + gain_spread N(0, 1)`` (unknown to the pipeline) and 0.2 % noise. The pixels are the
template's, their signal above black scaled by the horizontal light ``E_h,b(t)`` relative to
the brightest time (x 0.97, so that no panel pixel saturates), on the template's 16-DN steps.
The XMP ``Irradiance``/``SpectralIrradiance``, ``DLS:Yaw/Pitch/Roll``,
``Camera:IrradianceYaw/Pitch/Roll``, ``CaptureId`` and the EXIF times are rewritten.

The pipeline assumes the clear-sky ratio 1/6 for every band (DLS 1 measures no split): a
bluer or hazier truth is what it cannot know (bench/bench_light.py ``--sun-sensor`` shows by
how much).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mscal_core.sunsensor import sensor_reading

TIME_FMT = "%Y:%m:%d %H:%M:%S"


@dataclass(frozen=True)
class SunlightTruth:
    """Truth of a synthetic sun-sensor flight; arrays (n_captures, n_bands) or (n_captures,)."""

    names: tuple[str, ...]
    kinds: tuple[str, ...]  # "panel" or "flight"
    times: np.ndarray  # datetime64[ns]
    horizontal: np.ndarray  # E_h,b(t) on the template panel's scale, W m-2 nm-1
    diffuse_ratio: np.ndarray
    reading: np.ndarray  # what the sensor writes
    yaw_pitch_roll: np.ndarray  # (n, 3) radians
    sensor_gain: np.ndarray  # (n_bands,) the sensor's calibration error
    scale: np.ndarray  # signal scale applied to the template's pixels


@dataclass(frozen=True)
class _Template:
    """One template capture: its band files' metadata (band order of the file suffix)."""

    metas: tuple[Any, ...]


def _template_light(template: Path, rho: str) -> tuple[list[_Template], np.ndarray, np.ndarray]:
    """The template's two captures (``IMG_0000_*`` panel, ``IMG_0001_*`` flight), the panel
    capture's light ``pi L / rho`` per band (mean factory radiance over the inset of the detected
    panel) and the bands' wavelengths."""
    from mscal_core.factory import polygon_mask
    from mscal_core.panel import DEFAULT_INSET, detect_panel, shrink_polygon

    from pipeline.ingest.camera_meta import read_capture_meta
    from pipeline.ingest.cameras.dispatch import factory_radiance
    from pipeline.ingest.catalog import reflectance_option
    from pipeline.ingest.tiff import read_raw

    caps = []
    for name in ("IMG_0000", "IMG_0001"):
        files = sorted(template.glob(f"{name}_*.tif"), key=lambda f: int(f.stem.rsplit("_", 1)[1]))
        if files:
            caps.append(_Template(tuple(read_capture_meta(f) for f in files)))
    if not caps:
        raise FileNotFoundError(f"no IMG_0000_*.tif panel capture in {template}")
    wl = np.array([m.wavelength_nm for m in caps[0].metas])
    r = np.asarray(reflectance_option(rho).at(wl), dtype=np.float64)
    light = []
    for meta in caps[0].metas:
        dn = read_raw(meta.path)
        found = detect_panel(dn)
        if found is None:
            raise ValueError(f"no panel detected in the template's {meta.path}")
        mask = polygon_mask(dn.shape, shrink_polygon(found.outline, DEFAULT_INSET))
        light.append(float(np.mean(factory_radiance(meta, dn)[mask])))
    return caps, np.pi * np.asarray(light) / r, wl


def sunlight_truth(times: np.ndarray, kinds: tuple[str, ...], lat: float, lon: float, e_template: np.ndarray,
                   wavelengths: np.ndarray, *, seed: int = 0, level_end: float = 0.95, haze: float = 0.0,
                   r0: float = 1.0 / 6.0, r_exponent: float = 0.0, panel_tilt_deg: float = 8.0, flight_tilt_deg: float = 4.0,
                   gain_spread: float = 0.05) -> tuple[np.ndarray, ...]:
    """Light and sensor of each capture (see the module docstring): horizontal E_h, ratio r,
    reading, orientation, sensor gain, pixel scale."""
    from pipeline.ingest.solar import solar_position

    rng = np.random.default_rng(seed)
    t = np.asarray(times, dtype="datetime64[ns]")
    frac = (t - t[0]).astype(np.float64) / max(float((t[-1] - t[0]).astype(np.float64)), 1.0)
    el, az = solar_position(t, lat, lon)
    level = 1.0 + (level_end - 1.0) * frac
    r = r0 * (550.0 / wavelengths[None, :]) ** r_exponent * (1.0 + haze * frac[:, None])
    g = level[:, None] * (np.sin(el)[:, None] + r)  # E_h up to a per-band constant
    scale = 0.97 * g / g.max(axis=0)
    horizontal = scale * e_template[None, :]
    direct = horizontal / (np.sin(el)[:, None] + r)
    tilt = np.where(np.array([k == "panel" for k in kinds]), panel_tilt_deg, flight_tilt_deg)
    ypr = np.stack([rng.uniform(-np.pi, np.pi, t.size), np.radians(rng.normal(0, 1, t.size) * tilt),
                    np.radians(rng.normal(0, 1, t.size) * tilt)], axis=1)
    gain = 1.0 + gain_spread * rng.normal(0, 1, wavelengths.size)
    reading = gain[None, :] * sensor_reading(direct, r * direct, el[:, None], az[:, None], ypr[:, :1], ypr[:, 1:2],
                                             ypr[:, 2:3])
    reading = reading * (1.0 + 0.002 * rng.normal(0, 1, reading.shape))
    return horizontal, r, reading, ypr, gain, scale


def _set(xmp: str, tag: str, value: str) -> str:
    return re.sub(rf"(<{tag}>)[^<]*(</{tag}>)", lambda m: m.group(1) + value + m.group(2), xmp)


def _write_band(src: Path, dst: Path, scale: float, black: float, reading: float, ypr: np.ndarray, capture_id: str,
                when: str, template_when: bytes) -> None:
    import tifffile

    data = src.read_bytes().replace(template_when, when.encode("ascii"))
    dst.write_bytes(data)
    dst.chmod(0o644)
    img = tifffile.memmap(dst, mode="r+")
    signal = (img.astype(np.float64) - black) * scale + black
    img[:] = np.clip(np.round(signal / 16.0) * 16.0, 0, 65520).astype(np.uint16)
    img.flush()
    del img
    with tifffile.TiffFile(dst, mode="r+b") as tif:
        tag = tif.pages[0].tags[700]
        x = tag.value.decode("utf-8")
        for name in ("Camera:Irradiance", "DLS:SpectralIrradiance"):
            x = _set(x, name, repr(float(reading)))
        for name, v in zip(("DLS:Yaw", "DLS:Pitch", "DLS:Roll"), ypr):
            x = _set(x, name, repr(float(v)))
        for name, v in zip(("Camera:IrradianceYaw", "Camera:IrradiancePitch", "Camera:IrradianceRoll"), ypr):
            x = _set(x, name, repr(float(np.degrees(v))))
        x = _set(x, "MicaSense:CaptureId", capture_id)
        tag.overwrite(x.encode("utf-8"))


def write_sunlight_flight(template: str | Path, out: str | Path, *, seed: int = 0, n_flight: int = 2,
                          duration_s: float = 2040.0, rho: str = "micasense-rp02-1603036-sc",
                          **light: float) -> SunlightTruth:
    """Write the flight (module docstring) and return its truth; ``light``: the keywords of
    :func:`sunlight_truth` (level_end, haze, r0, panel_tilt_deg, flight_tilt_deg, gain_spread)."""
    template, out = Path(template), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    caps, e_template, wl = _template_light(template, rho)
    panel_cap, flight_cap = caps[0], caps[min(1, len(caps) - 1)]
    t0 = np.datetime64(panel_cap.metas[0].time.rstrip("Z").split(".")[0], "s")
    n = n_flight + 2
    times = t0 + np.round(np.linspace(0.0, duration_s, n)).astype("timedelta64[s]")
    kinds = tuple("panel" if i in (0, n - 1) else "flight" for i in range(n))
    m0 = panel_cap.metas[0]
    horizontal, r, reading, ypr, gain, scale = sunlight_truth(times, kinds, m0.lat, m0.lon, e_template, wl,
                                                              seed=seed, **light)
    template_when = t0.astype(object).strftime(TIME_FMT).encode("ascii")
    names = []
    for i in range(n):
        src = panel_cap if kinds[i] == "panel" else flight_cap
        when_src = np.datetime64(src.metas[0].time.rstrip("Z").split(".")[0], "s").astype(object).strftime(TIME_FMT).encode()
        name = f"IMG_{i:04d}"
        names.append(name)
        when = times[i].astype("datetime64[s]").astype(object).strftime(TIME_FMT)
        for b, meta in enumerate(src.metas):
            _write_band(meta.path, out / f"{name}_{b + 1}.tif", float(scale[i, b]) * _relight(src, panel_cap, b),
                        meta.black_level, float(reading[i, b]), ypr[i], f"syn{seed:04d}cap{i:04d}sunlight",
                        when, when_src if src is not panel_cap else template_when)
    return SunlightTruth(tuple(names), kinds, times.astype("datetime64[ns]"), horizontal, r, reading, ypr, gain, scale)


def _relight(src: Any, panel_cap: Any, b: int) -> float:
    """A flight template taken under other light than the panel template: its pixels are put
    on the panel template's light first (ratio of the two captures' own DLS readings)."""
    if src is panel_cap:
        return 1.0
    e_src, e_panel = src.metas[b].irradiance, panel_cap.metas[b].irradiance
    return 1.0 if not (e_src and e_panel) else min(1.0, e_panel / e_src)
