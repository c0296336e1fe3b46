"""Reflectance panel of a one-file-per-band capture, and reflectance from it or from the DLS.

Panel region of one band file, first that applies:

1. XMP ``ReflectArea`` written by the camera: 8 numbers are four (x, y) corners, 4 numbers
   an axis-aligned ``x, y, width, height`` box (used whole: the camera chose it);
1b. an ArUco/AprilTag marker in the panel's plane, when session.yaml ``panel.marker`` names one
   and the band shows it: the configured rectangle through the marker's homography
   (:func:`mscal_core.panel.panel_from_marker`), shrunk to its inner ``inset`` like a detection;
2. automatic detection (:func:`mscal_core.panel.detect_panel`), shrunk to its inner
   ``inset`` (linear, default 0.75) to keep the blurred, shadowed edges out;
3. the polygon from session.yaml ``panel: {polygon: [[x, y], ...]}``
   (:func:`pipeline.ingest.session.parse_panel_polygon`), if given.

Otherwise :class:`FrameError` "no reflectance panel found" naming the file.

A panel capture's bands share one region (:func:`common_regions`): when every band
detects the panel, the region is chosen once in the panel's own coordinates (the camera's
ReflectArea of one band, else the centred inset) and mapped into each band through its own
detection of the same square, so that every band samples the same spot of the panel.

Reflectance of a capture (bands are *not* co-registered: every band uses its own pixel grid,
its own panel polygon, and per-pixel indices mix neighbouring ground points near edges):

- panel route: ``k_b = rho_b / mean factory radiance over the panel`` in the panel capture,
  ``R_b = k_b L_b`` in the flight capture;
- sun-sensor route: ``R_b = pi L_b / E_b`` with ``E_b`` the XMP ``Irradiance`` of the
  flight capture's own band file, in W m-2 nm-1 (MicaSense's unit for the DLS spectral
  irradiance, the same per-nm unit as the radiance). It is the raw DLS reading: no
  correction for the DLS's tilt against the sun is applied here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from mscal_core.errors import FrameError
from mscal_core.factory import panel_stats, polygon_mask
from mscal_core.geometry import detect_marker
from mscal_core.illumination import IlluminationFit, fit_illumination
from mscal_core.panel import (
    DEFAULT_INSET,
    detect_panel,
    from_panel_coords,
    inset_square,
    panel_from_marker,
    sample_quad,
    shrink_polygon,
    to_panel_coords,
)
from mscal_core.reflectance import ndvi

from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.meta import CaptureMeta, FieldParts
from pipeline.ingest.session import PanelConfig

SATURATION_DN = 65000  # 16-bit container: above this a RedEdge pixel is clipped


@dataclass(frozen=True)
class PanelRegion:
    """Panel polygon of one band file: ``corners`` (n, 2) (x, y) and where it came from
    (``"xmp"``, ``"marker"``, ``"detected"`` or ``"session"``)."""

    corners: np.ndarray
    source: str


def reflect_area_polygon(meta: CaptureMeta) -> np.ndarray | None:
    """The panel polygon written in the file's XMP ReflectArea, or None if there is none."""
    area = meta.reflect_area
    if not area:
        return None
    if len(area) == 8:
        corners = np.asarray(area, dtype=np.float64).reshape(4, 2)
    elif len(area) == 4:
        x, y, w, h = area
        if w <= 0 or h <= 0:
            raise FrameError(f"XMP ReflectArea {area!r} has a non-positive width or height", path=meta.path)
        corners = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], dtype=np.float64)
    else:
        raise FrameError(
            f"XMP ReflectArea has {len(area)} numbers, expected 4 (x, y, width, height) or 8 (four x, y corners)",
            path=meta.path,
        )
    _check_inside(corners, meta, "XMP ReflectArea")
    return corners


def _check_inside(corners: np.ndarray, meta: CaptureMeta, what: str) -> None:
    h, w = meta.shape
    if corners.min() < 0 or corners[:, 0].max() > w - 1 or corners[:, 1].max() > h - 1:
        raise FrameError(f"{what} {corners.tolist()} lies outside the {w} x {h} image", path=meta.path)


def panel_region(
    meta: CaptureMeta,
    dn: np.ndarray,
    *,
    session_polygon: Sequence[Sequence[float]] | None = None,
    inset: float = DEFAULT_INSET,
    config: PanelConfig | None = None,
) -> PanelRegion:
    """The panel polygon of one band file: XMP ReflectArea, else through the session's panel
    marker if this band shows it, else detected, else session.yaml's polygon (``config``'s, or
    ``session_polygon``)."""
    corners = reflect_area_polygon(meta)
    if corners is not None:
        return PanelRegion(corners, "xmp")
    if config is not None and config.marker is not None:
        mk = config.marker
        found_marker = detect_marker(dn, mk.dictionary, mk.id)
        if found_marker is not None:
            quad = shrink_polygon(panel_from_marker(found_marker, mk.size_m, mk.panel_size_m, mk.offset_m), inset)
            _check_inside(quad, meta, f"the panel placed by marker {mk.id}")
            return PanelRegion(quad, "marker")
    if session_polygon is None and config is not None:
        session_polygon = config.polygon
    found = detect_panel(dn)
    if found is not None:
        return PanelRegion(shrink_polygon(found.outline, inset), "detected")
    if session_polygon is not None:
        corners = np.asarray(session_polygon, dtype=np.float64)
        _check_inside(corners, meta, "session.yaml panel.polygon")
        return PanelRegion(corners, "session")
    raise FrameError(
        "no reflectance panel found (no XMP ReflectArea, no panel marker, no bright uniform quadrilateral in the image)",
        path=meta.path,
        hint="photograph the panel filling more of the frame, or say where it is in session.yaml: "
             "panel: {polygon: [[x, y], ...]} or panel: {marker: {dictionary, id, size_m}, size_m, offset_m}",
    )


def common_regions(
    metas: Sequence[CaptureMeta],
    dns: Sequence[np.ndarray],
    *,
    session_polygon: Sequence[Sequence[float]] | None = None,
    inset: float = DEFAULT_INSET,
    config: PanelConfig | None = None,
) -> list[PanelRegion]:
    """One panel region for all bands of a capture: the same physical spot of the
    panel in every band, so that the panel's colour is not biased by where each band looked.

    When every band shows the panel (:func:`mscal_core.panel.detect_panel`), the region is
    chosen once in the panel's own coordinates (:func:`mscal_core.panel.to_panel_coords`): the
    camera's XMP ReflectArea of the first band that has a four-corner one, else the centred
    ``inset`` square; and mapped into each band through that band's detection of the same
    square (source ``"detected"``, or ``"xmp:BAND"`` for the camera's area carried over).
    Otherwise, when every band has its ReflectArea, those (``"xmp"``, the camera's choice);
    else each band's own region (:func:`panel_region`: marker, detection, session polygon).
    A session panel marker keeps the per-band route (the marker places the same rectangle in
    every band already).
    """
    if config is None or config.marker is None:
        areas = [reflect_area_polygon(m) for m in metas]
        found = []
        for dn in dns:  # stop at the first band without a panel: most captures of a flight have none
            found.append(detect_panel(dn))
            if found[-1] is None:
                break
        if found and len(found) == len(dns) and all(f is not None for f in found):
            ref = next((b for b, a in enumerate(areas) if a is not None and len(a) == 4), None)
            if ref is None:
                uv, source = inset_square(inset), "detected"
            else:
                uv, source = to_panel_coords(found[ref].outline, areas[ref]), f"xmp:{metas[ref].band_name}"
            out = []
            for meta, f in zip(metas, found):
                quad = from_panel_coords(f.outline, uv)
                _check_inside(quad, meta, "the panel region mapped from the common panel coordinates")
                out.append(PanelRegion(quad, source))
            return out
        if areas and all(a is not None for a in areas):
            return [PanelRegion(a, "xmp") for a in areas]  # type: ignore[arg-type]
    return [panel_region(m, dn, session_polygon=session_polygon, inset=inset, config=config)
            for m, dn in zip(metas, dns)]


@dataclass(frozen=True)
class PanelBand:
    """One band of a panel capture: its region, mean radiance on it and the factor ``k_b``."""

    region: PanelRegion
    radiance: float  # mean factory radiance over the region, W m-2 sr-1 nm-1
    radiance_std: float
    reflectance: float  # rho_b of the panel
    factor: float  # k_b = rho_b / radiance, sr nm m2 W-1
    irradiance: float | None  # the panel capture's DLS irradiance, W m-2 nm-1


def panel_factors(
    metas: Sequence[CaptureMeta],
    dns: Sequence[np.ndarray],
    rho: Sequence[float],
    *,
    session_polygon: Sequence[Sequence[float]] | None = None,
    parts: Sequence[FieldParts | None] | None = None,
    config: PanelConfig | None = None,
    channels: Sequence[np.ndarray | None] | None = None,
) -> list[PanelBand]:
    """Per band of a panel capture: ``k_b = rho_b / mean factory radiance on the panel``
    (``parts``: field components per band in place of the factory's, see :func:`factory_radiance`;
    ``channels``: per band, the whole image of a multi-channel file, for Sentera's colour transform).

    Saturated panel pixels make the factor meaningless: FrameError naming the file.
    """
    if not len(metas) == len(dns) == len(rho):
        raise ValueError(f"{len(metas)} band files, {len(dns)} images and {len(rho)} reflectances differ")
    out = []
    parts = list(parts) if parts is not None else [None] * len(metas)
    chans = list(channels) if channels is not None else [None] * len(metas)
    regions = common_regions(metas, dns, session_polygon=session_polygon, config=config)
    for meta, dn, rho_b, part, ch, region in zip(metas, dns, rho, parts, chans, regions):
        mask = polygon_mask(dn.shape, region.corners)
        sat = SATURATION_DN if meta.bits_per_sample >= 16 else 2**meta.bits_per_sample - 2  # JPEG: 255 is clipped
        raw = panel_stats(dn, mask, saturation=sat)
        if raw.saturated:
            raise FrameError(
                f"{raw.saturated} of {raw.count} panel pixels are saturated",
                path=meta.path,
                hint="take the panel capture with a shorter exposure",
            )
        rad = panel_stats(factory_radiance(meta, dn, part, ch), mask)
        out.append(
            PanelBand(region, rad.mean, rad.std, float(rho_b), float(rho_b) / rad.mean, meta.irradiance)
        )
    return out


def panel_reflectance(meta: CaptureMeta, dn: np.ndarray, band: PanelBand) -> np.ndarray:
    """Reflectance ``k_b L_b`` of one band file with the panel capture's factor (float32)."""
    return (band.factor * factory_radiance(meta, dn)).astype(np.float32)


def dls_reflectance(meta: CaptureMeta, dn: np.ndarray) -> np.ndarray:
    """Reflectance ``pi L_b / E_b`` of one band file with its own DLS irradiance (float32)."""
    e = meta.irradiance
    if e is None or not math.isfinite(e) or e <= 0:
        raise FrameError(
            f"no usable DLS irradiance (XMP Irradiance = {e!r})",
            path=meta.path,
            hint="use the panel route, or a camera with a downwelling light sensor",
        )
    return (math.pi / e * factory_radiance(meta, dn)).astype(np.float32)


def capture_ndvi(red: np.ndarray, nir: np.ndarray) -> np.ndarray:
    """Per-pixel NDVI of two band reflectances on their *own* grids (not co-registered:
    objects are shifted by tens of pixels between bands, so edges mix neighbours)."""
    if red.shape != nir.shape:
        raise ValueError(f"red {red.shape} and NIR {nir.shape} images differ in shape")
    return ndvi(red, nir)


def panel_illumination(
    metas: Sequence[CaptureMeta], dns: Sequence[np.ndarray], bands: Sequence[PanelBand], *, grid: int = 32
) -> IlluminationFit:
    """Split the panel's radiance into colour S(lambda) and brightness B(x) (Eq. 11-14).

    The bands are not co-registered, so each band's radiance is resampled on a ``grid x
    grid`` lattice spanning *its own* four-corner panel region (:func:`sample_quad`): cell x
    is the same spot of the panel in every band. ``B`` (grid * grid,) has median 1; its
    spread is the light's non-uniformity over the panel (shadow, tilt, sky), which a mean
    over the panel would fold into every band's factor alike.
    """
    rows = []
    for meta, dn, band in zip(metas, dns, bands):
        if len(band.region.corners) != 4:
            raise FrameError(
                f"the B(x)/S(lambda) split needs a four-corner panel region, got {len(band.region.corners)} corners",
                path=meta.path,
            )
        rows.append(sample_quad(factory_radiance(meta, dn), band.region.corners, grid).ravel())
    return fit_illumination(np.array(rows), np.array([b.reflectance for b in bands]))
