"""What an apply computes, shared by every camera's path (:mod:`pipeline.apply.flight` for
snapshot frames, :mod:`pipeline.apply.captures` for capture folders): the options and their
parsing, the bands exported and the index roles, the normalisation, the pass geometry, the
calibration's clip level and content hash, and the result an apply returns."""
from __future__ import annotations

import hashlib
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import xarray as xr
from mscal_core.alignment import mosaic_centre_offsets
from mscal_core.errors import InputError
from mscal_core.quality import region_median

from pipeline.apply.execution import Execution
from pipeline.apply.light import DEFAULT_MODE, varies_in_time
from pipeline.ingest.catalog import Camera, Index, reflectance_option
from pipeline.ingest.products import Products

MAX_EXPORT_BANDS = 8


@dataclass(frozen=True)
class PanelSpec:
    """A region of known reflectance in one frame: ``FRAME:x0,y0,x1,y1`` (band-grid pixels)."""

    frame: str
    box: tuple[int, int, int, int]
    reflectance: Any  # catalog.ReflectanceSpec

    @staticmethod
    def parse(text: str, reflectance: str) -> "PanelSpec":
        m = re.fullmatch(r"\s*([^:]+):\s*(\d+),\s*(\d+),\s*(\d+),\s*(\d+)\s*", text or "")
        if not m:
            raise InputError(
                f"--panel {text!r} is not FRAME:x0,y0,x1,y1",
                hint="e.g. --panel IMG_0003:120,80,140,95 (band-grid pixel columns and rows, end exclusive)",
            )
        x0, y0, x1, y1 = (int(m[i]) for i in range(2, 6))
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"--panel {text!r}: empty box (need x1 > x0 and y1 > y0)")
        return PanelSpec(m[1], (x0, y0, x1, y1), reflectance_option(reflectance))


@dataclass(frozen=True)
class ApplyOptions:
    normalise: str = "relative"  # relative | band:<name or nm> | panel
    panel: PanelSpec | None = None
    tiff_dtype: str = "uint16"
    export_bands: tuple[str, ...] | None = None
    products: Products = Products()  # what is written beyond raw.zarr and reflectance (pipeline.ingest.products)
    strict: bool = False
    illumination: str = DEFAULT_MODE  # nearest | linear: light between reflector captures
    align: bool = True  # align bands with the store's band_transform, if it has one
    centre_bands: bool = False  # snapshot mosaics: resample every band to the mosaic's centre position
    execution: Execution = Execution()  # how the pass runs (not what it computes: not fingerprinted)
    captures: tuple[str, ...] = ()  # one-file-per-band cameras: only these captures of the folder (one flight)

    def fingerprint(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("strict")
        d.pop("execution")
        if not d["captures"]:  # the default: earlier runs stay up to date
            d.pop("captures")
        d.pop("illumination")  # in the fingerprint only when the light varies (see run_fingerprint)
        for key, default in (("align", True), ("centre_bands", False)):  # runs before band alignment stay up to date
            if d[key] == default:
                d.pop(key)
        d["products"] = self.products.fingerprint()
        if self.panel is not None:
            d["panel"] = {"frame": self.panel.frame, "box": list(self.panel.box), "reflectance": repr(self.panel.reflectance)}
        return d


@dataclass
class ApplyResult:
    """What one apply did: ``run`` is ``OUT/run.json``'s record. ``calibration``: the
    calibration store as apply read it (in memory), for the caller's summary to use instead of
    reading the store again; None for ``--calibration factory``."""

    out: Path
    run: dict[str, Any]
    up_to_date: bool = False
    quarantined: list[dict[str, str]] = field(default_factory=list)
    calibration: xr.Dataset | None = field(default=None, repr=False, compare=False)


def calibration_hash(ds: xr.Dataset) -> str:
    """sha256 of the calibration's arrays (U, V, S) and camera: what Eq. 15 depends on; with
    light that varies in time also the captures' S, level, time and irradiance."""
    h = hashlib.sha256(str(ds.attrs.get("camera")).encode())
    names = ["inverse_response", "vignetting", "spectral_factor"]
    if varies_in_time(ds):
        names += ["capture_spectral_factor", "capture_level", "capture_time", "capture_irradiance"]
    names += [n for n in ("band_transform", "capture_transform") if n in ds]  # only stores that have them
    for name in names:
        arr = np.ascontiguousarray(ds[name].values)
        h.update(name.encode())
        h.update(str(arr.dtype).encode() + str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def calibration_clip_dn(calib: xr.Dataset, camera: Camera) -> int:
    """DN from which pixels are saturated (NaN in reflectance): the calibration's lowest, else
    the camera's full scale."""
    return int(calib["saturation_dn"].values.min()) if "saturation_dn" in calib else camera.dn_max


def export_band_indices(camera: Camera, names: Sequence[str] | None) -> list[int]:
    names = list(names) if names else list(camera.export_bands) or camera.band_names[:MAX_EXPORT_BANDS]
    unknown = [n for n in names if n not in camera.band_names]
    if unknown:
        raise InputError(
            f"--export-bands names unknown band(s) {', '.join(unknown)}",
            hint=f"bands of {camera.name}: {', '.join(camera.band_names)}",
        )
    return [camera.band_names.index(n) for n in names]


def band_index(camera: Camera, text: str) -> int:
    if text in camera.band_names:
        return camera.band_names.index(text)
    try:
        return camera.band_for_wavelength(float(text))
    except ValueError:
        raise InputError(f"--normalise band:{text}: no such band name or wavelength",
                         hint=f"bands: {', '.join(camera.band_names)}") from None


def index_roles(camera: Camera, index: Index) -> dict[str, int]:
    missing = [r for r in index.inputs if r not in camera.index_bands]
    if missing:
        raise InputError(
            f"index {index.name} needs band role(s) {', '.join(missing)} that camera {camera.name} does not define",
            hint=f"add them under index_bands in {camera.source}",
        )
    return {r: camera.band_for_wavelength(camera.index_bands[r]) for r in index.inputs}


class PanelPixels(NamedTuple):
    """A frame's pixels for a panel's median (:func:`normalisation`), all (band, y, x) on the
    outputs' grid: Eq. 15 reflectance; its quality mask (None: the run has none); and each
    pixel's bound if censored high (:func:`mscal_core.quality.region_median`'s ``censor_at``;
    None: not known, each counts above every valid value)."""

    reflectance: np.ndarray
    quality: np.ndarray | None = None
    censor_at: np.ndarray | None = None


#: ``panel_reflectance(f)`` of :func:`normalisation`: the pixels of frame ``f``
#: (:class:`PanelPixels`, or a tuple of its first fields).
PanelReflectance = Callable[[int], "PanelPixels | tuple[np.ndarray, np.ndarray | None]"]


def normalisation(
    options: ApplyOptions, camera: Camera, frames: Sequence[str],
    panel_reflectance: PanelReflectance,
) -> tuple[str, float | int | None]:
    """How relative reflectance is scaled: ``("none", None)``, ``("band", b)`` (per frame,
    that band's median becomes 1) or ``("scalar", k)`` (one factor from a panel of known
    reflectance, for every frame: Eq. 15's R is relative up to one scalar).

    ``panel_reflectance(f)`` gives Eq. 15 reflectance (band, y, x) of frame ``f`` and its
    quality mask or None (:data:`PanelReflectance`); with a mask the panel's median per band
    counts the pixels flagged high (shoulder, saturated, above the sweep) as above it, each
    above its own bound where the pixels carry one (the product-limit median: a shoulder cut
    flags a panel's highest-V pixels, not its highest values), and a band half flagged or more
    has none (:func:`mscal_core.quality.region_median`; the valid pixels alone of a panel the
    shoulder flag cuts read low). Without the mask, the median of the finite pixels."""
    mode = options.normalise
    if mode == "relative":
        return "none", None
    if mode.startswith("band:"):
        return "band", band_index(camera, mode.split(":", 1)[1])
    if mode == "panel":
        p = options.panel
        if p is None:
            raise InputError("--normalise panel needs --panel FRAME:x0,y0,x1,y1 and --panel-reflectance")
        frames = list(frames)
        if p.frame not in frames:
            raise InputError(f"--panel frame {p.frame!r} is not in the flight", hint=f"frames: {', '.join(frames[:5])}, ...")
        x0, y0, x1, y1 = p.box
        pixels = PanelPixels(*panel_reflectance(frames.index(p.frame)))
        refl, quality = pixels.reflectance, pixels.quality
        region = refl[:, y0:y1, x0:x1]
        rho = p.reflectance.at(camera.wavelengths)
        flat = region.reshape(region.shape[0], -1)
        if not region.size:
            med = np.array([np.nan])
        elif quality is None:
            med = np.nanmedian(flat, axis=1)
        else:
            def box(a: np.ndarray | None) -> np.ndarray | None:
                return None if a is None else a[:, y0:y1, x0:x1].reshape(flat.shape)

            med = region_median(flat, box(quality), censor_at=box(pixels.censor_at))
        if not np.any(np.isfinite(med) & (med > 0)):
            raise InputError(f"--panel region of {p.frame} has no valid pixels (saturated, flagged, or outside the frame)")
        return "scalar", float(np.nanmedian(rho / med))
    raise InputError(f"--normalise {mode!r}: use relative, band:<name or nm>, or panel")


def pass_geometry(calib: xr.Dataset, camera: Camera, options: ApplyOptions
              ) -> tuple[bool, tuple[tuple[float, float], ...] | None, str | None]:
    """``(align, band_shift, reference band)`` of the pass (``geometry_step``)."""
    align = bool(options.align and "band_transform" in calib)
    reference = (calib.attrs.get("registration") or {}).get("reference_band") if align else None
    band_shift = None
    if options.centre_bands:
        if camera.layout.kind != "mosaic" or camera.layout.pattern is None:
            raise InputError(f"--centre-bands is for snapshot mosaic cameras; {camera.name} is {camera.layout.kind}",
                             hint="multi-lens cameras are aligned with 'mscal register' transforms instead")
        band_shift = tuple((float(dx), float(dy)) for dx, dy in mosaic_centre_offsets(camera.layout.pattern))
    return align, band_shift, reference
