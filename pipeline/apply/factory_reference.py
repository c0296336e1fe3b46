"""The light reference of a factory-calibrated apply (:mod:`pipeline.apply.factory`): which
route a run takes (``reference_route``: ``panel``, ``panel-dls``, ``dls`` or ``none``), the panel
captures of a panel route and their factors (``reference_panels``: the panel's reflectance from
``--panel-reflectance``, the captures' XMP Albedo or the panel's serial; each capture's
Eq. 11-14 split, :func:`panel_reference`), and what run.json says of it (``reference_record``).

``sun_sensor_missing`` says when no band has a usable sun-sensor reflectance (the ``none``
route, and ``--reference dls`` refused before anything is written).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
from mscal_core.errors import FrameError, InputError
from mscal_core.illumination import fit_illumination
from mscal_core.panel import sample_quad

from pipeline.apply.panel import PanelBand, panel_factors
from pipeline.apply.panel_search import PANEL_SCAN_ALL, PANEL_SEARCH, PanelSerial, panel_candidates
from pipeline.apply.sunlight import readings_missing
from pipeline.ingest.cameras.dispatch import factory_radiance
from pipeline.ingest.catalog import Camera, reflectance_option
from pipeline.ingest.grouping import Capture, read_capture_pixels
from pipeline.ingest.meta import FieldParts, no_reflectance_reason, reflectance_factor
from pipeline.ingest.session import PanelConfig
from pipeline.ingest.sun_scale import sun_scale_record

if TYPE_CHECKING:
    from pipeline.apply.factory import FactoryOptions

PANEL_GRID = 32  # cells per side of the panel grid for the S/B split (Eq. 11-14)
ALBEDO_SOURCE = "XMP Albedo of each panel capture's band files (the camera's reading of the panel's QR code)"


@dataclass(frozen=True)
class PanelReference:
    """Per-band factors from one panel capture: ``k_b = 1/S_b`` (Eq. 11-14 split) beside the
    plain ``rho_b / mean L_b`` and the DLS's ``pi / E_b`` of the same capture."""

    capture: str
    factor_split: tuple[float, ...]
    factor_mean: tuple[float, ...]
    factor_dls: tuple[float | None, ...]
    brightness_p10_p90: tuple[float, float]
    split_residual_rms: float
    region_source: tuple[str, ...]
    reflectance: tuple[float, ...] = ()  # rho_b of the panel used per band


def panel_reference(capture: Capture, dns: Sequence[np.ndarray], rho: Sequence[float],
                    parts: Sequence[FieldParts | None] | None = None, config: PanelConfig | None = None,
                    channels: dict[Path, np.ndarray] | None = None) -> PanelReference:
    """Factors of one panel capture (FrameError naming the file if no panel is found in a band);
    ``parts``: field components per band in place of the factory's; ``config``: session.yaml's
    ``panel`` (marker, polygon); ``channels``: whole images of multi-channel files (Sentera)."""
    parts = list(parts) if parts is not None else [None] * len(capture.metas)
    chans = [(channels or {}).get(m.path) for m in capture.metas]
    bands: list[PanelBand] = panel_factors(capture.metas, dns, rho, parts=parts, config=config, channels=chans)
    rows = []
    for meta, dn, band, part, ch in zip(capture.metas, dns, bands, parts, chans):
        rad = factory_radiance(meta, dn, part, ch)
        if len(band.region.corners) == 4:
            rows.append(sample_quad(rad, band.region.corners, PANEL_GRID).ravel())
    if len(rows) == len(bands):
        fit = fit_illumination(np.array(rows), np.array(rho, dtype=np.float64))
        split = tuple(float(1.0 / s) for s in fit.spectral_factor)
        b = fit.brightness[np.isfinite(fit.brightness)]
        spread = (float(np.percentile(b, 10)), float(np.percentile(b, 90)))
        resid = float(fit.residual_rms)
    else:  # a polygon from the session that is not a quadrilateral: the mean is all there is
        split = tuple(b.factor for b in bands)
        spread, resid = (float("nan"), float("nan")), float("nan")
    dls = tuple(reflectance_factor(m) for m in capture.metas)
    return PanelReference(
        capture=capture.name, factor_split=split, factor_mean=tuple(b.factor for b in bands), factor_dls=dls,
        brightness_p10_p90=spread, split_residual_rms=resid, region_source=tuple(b.region.source for b in bands),
        reflectance=tuple(float(b.reflectance) for b in bands),
    )


def _find_panels(captures: Sequence[Capture], named: Sequence[str], rho: Sequence[float], folder: Path,
                 parts: Sequence[FieldParts | None] | None = None, config: PanelConfig | None = None
                 ) -> list[PanelReference]:
    by_name = {c.name: c for c in captures}
    if named:
        unknown = [n for n in named if n not in by_name]
        if unknown:
            raise InputError(f"--panel names capture(s) {', '.join(unknown)} that are not in the folder", path=folder,
                             hint=f"captures: {', '.join(list(by_name)[:8])}{' ...' if len(by_name) > 8 else ''}")
        refs = []
        for n in named:
            try:
                _, dns, channels = read_capture_pixels(by_name[n])
                refs.append(panel_reference(by_name[n], dns, rho, parts, config, channels))
            except FrameError as exc:
                raise InputError(f"panel capture {n}: {exc.reason}", path=exc.path, hint=exc.hint) from None
        return refs
    refs = []
    for c in panel_candidates(captures):
        try:
            _, dns, channels = read_capture_pixels(c)
            refs.append(panel_reference(c, dns, rho, parts, config, channels))
        except FrameError:
            continue
    if not refs:
        raise InputError(
            f"no reflectance panel found in the captures searched (all of them up to {PANEL_SCAN_ALL}, else the "
            f"first and last {PANEL_SEARCH} and those the camera flagged with XMP ReflectArea)", path=folder,
            hint="name the panel capture with --panel IMG_XXXX, or use --reference dls",
        )
    return refs


def albedo_captures(captures: Sequence[Capture], named: Sequence[str] = ()) -> list[Capture]:
    """Panel captures whose panel reflectance the camera wrote: every reflectance band file
    carries XMP ``Albedo`` (MicaSense: the panel's reflectance in that band, read from its QR
    code) and ``CalibrationPicture`` 2 (Pix4D: a valid panel capture; 1 is an invalid one),
    as MicaSense's own library asks of an automatic panel capture. With ``named``
    (``--panel``) only those captures are looked at."""
    pool = [c for c in captures if c.name in set(named)] if named else list(captures)
    return [c for c in pool if any(m.reflectance_band for m in c.metas)
            and all(m.panel_albedo is not None and m.calibration_picture == 2 for m in c.metas if m.reflectance_band)]


def albedo_reflectance(capture: Capture) -> list[float]:
    """``rho_b`` per band file of an :func:`albedo_captures` capture: its XMP Albedo (a band
    kept out of reflectance, e.g. thermal, takes the others' mean: its factor is never used)."""
    vals = [float(m.panel_albedo) for m in capture.metas if m.reflectance_band and m.panel_albedo is not None]
    fill = float(np.mean(vals))
    return [float(m.panel_albedo) if m.reflectance_band and m.panel_albedo is not None else fill
            for m in capture.metas]


def _albedo_panels(found: Sequence[Capture], named: Sequence[str], folder: Path,
                   parts: Sequence[FieldParts | None] | None = None, config: PanelConfig | None = None
                   ) -> list[PanelReference]:
    """:func:`panel_reference` of every capture ``found`` by :func:`albedo_captures` with its own
    Albedo. A named capture that fails is an error; otherwise failures are skipped unless all fail."""
    missing = [n for n in named if n not in {c.name for c in found}]
    if missing:
        raise InputError(f"--panel capture(s) {', '.join(missing)}: not in the folder, or a band file has no XMP Albedo "
                         "with CalibrationPicture 2 (the panel's reflectance as the camera read it)", path=folder,
                         hint="give the panel's reflectance with --panel-reflectance TARGET")
    refs, failed = [], []
    for c in found:
        try:
            _, dns, channels = read_capture_pixels(c)
            refs.append(panel_reference(c, dns, albedo_reflectance(c), parts, config, channels))
        except FrameError as exc:
            if named:
                raise InputError(f"panel capture {c.name}: {exc.reason}", path=exc.path, hint=exc.hint) from None
            failed.append(exc)
    if not refs:
        exc = failed[0]
        raise InputError(f"no usable panel among the {len(found)} capture(s) with the camera's XMP Albedo: {exc.reason}",
                         path=exc.path, hint=exc.hint or "name a panel capture with --panel and --panel-reflectance")
    return refs


def reference_panels(options: FactoryOptions, reference: str, captures: Sequence[Capture], folder: Path,
                     parts: Sequence[FieldParts | None] | None, config: PanelConfig | None,
                     serial: PanelSerial | None = None) -> tuple[str, list[PanelReference], str | None, str | None]:
    """The panels of a panel route: ``(route, panels, where rho came from, why the camera's own
    panel could not be used)``. rho from ``--panel-reflectance``, else from the panel captures'
    XMP Albedo (:func:`albedo_captures`), else from the target of the panel's ``serial``
    (:func:`pipeline.apply.panel_search.find_panel_serial`); when ``auto`` chose the panel on
    its own and it cannot be used, the route falls back to the sun sensor (or none) with the reason."""
    if reference not in ("panel", "panel-dls"):
        return reference, [], None, None
    fallback = "none" if sun_sensor_missing(captures) is not None else "dls"
    found = [] if options.panel_reflectance is not None else albedo_captures(captures, options.panel_captures)
    if options.panel_reflectance is not None or (not found and serial is not None and serial.target is not None):
        name = options.panel_reflectance or serial.target.name  # type: ignore[union-attr]
        spec = reflectance_option(name)
        rho = [float(r) for r in spec.at(np.array([m.wavelength_nm for m in captures[0].metas]))]
        try:
            return (reference, _find_panels(captures, options.panel_captures, rho, folder, parts, config),
                    f"--panel-reflectance {name}" if options.panel_reflectance else serial.rho_source, None)  # type: ignore[union-attr]
        except InputError as exc:
            if options.panel_reflectance is not None or options.reference != "auto" or options.panel_captures:
                raise
            return fallback, [], None, f"{Path(exc.path).name if exc.path else folder.name}: {exc.reason}"
    if found:  # the camera read the panel's QR code
        try:
            return reference, _albedo_panels(found, options.panel_captures, folder, parts, config), ALBEDO_SOURCE, None
        except InputError as exc:
            if options.reference != "auto" or options.panel_captures:
                raise
            return fallback, [], None, f"{Path(exc.path).name if exc.path else folder.name}: {exc.reason}"
    where = ("the --panel capture(s) do not all carry" if options.panel_captures
             else "no panel capture in the folder carries")
    known = "" if serial is None or serial.serial is None else f"; {serial.where} is in no catalogs/targets file"
    raise InputError(f"--reference {reference} needs --panel-reflectance (a number or a target name); {where} the "
                     f"camera's XMP Albedo with CalibrationPicture 2{known}",
                     hint="e.g. --panel-reflectance micasense-rp02-1603036-sc")


def serial_wanted(options: FactoryOptions, captures: Sequence[Capture]) -> bool:
    """Whether the panel's serial can choose the reference: a panel route (``auto`` included)
    without ``--panel-reflectance`` and no capture with the camera's XMP Albedo."""
    return (options.reference != "dls" and options.panel_reflectance is None
            and not albedo_captures(captures, options.panel_captures))


#: How to get reflectance when the sun sensor gives none: run.json ``reference.hint`` of a run
#: without reflectance (the summary's warning) and, with the radiance-only way out, the error
#: of ``--reference dls``.
PANEL_HINT = ("give --panel-reflectance TARGET (a number, or a target of catalogs/targets) with a panel capture "
              "in the folder (--panel IMG_XXXX names it)")
NO_SUN_SENSOR_HINT = f"{PANEL_HINT}; or leave out --reference dls for radiance only (reflectance NaN)"


def sun_sensor_missing(captures: Sequence[Capture]) -> tuple[Path, str] | None:
    """None when a band of some capture has a usable sun-sensor reflectance factor; else the
    first band file and why it has none (the tag, :func:`pipeline.ingest.meta.
    no_reflectance_reason`): the sun-sensor route would give no reflectance at all."""
    for c in captures:
        if any(reflectance_factor(m) is not None for m in c.metas):
            return None
    if not captures:
        return None
    meta = captures[0].metas[0]
    return meta.path, str(no_reflectance_reason(meta))


def reference_route(options: FactoryOptions, captures: Sequence[Capture], serial: PanelSerial | None = None) -> str:
    """The reference route: as asked, or for ``auto`` the panel when a reflectance is given or
    a panel capture carries the camera's own (:func:`albedo_captures`) or shows a serial of a
    catalog target (``serial``), anchoring the sun sensor (``panel-dls``) when the captures
    have readings; else the sun sensor, else ``none`` (radiance only) when no band of any
    capture has a usable sun-sensor reflectance (Sentera)."""
    if options.reference != "auto":
        return options.reference
    if (options.panel_reflectance is not None or albedo_captures(captures, options.panel_captures)
            or (serial is not None and serial.target is not None)):
        return "panel" if readings_missing(captures) else "panel-dls"
    return "none" if sun_sensor_missing(captures) is not None else "dls"


def reference_record(reference: str, panels: Sequence[PanelReference], factor: tuple[float, ...] | None,
                     camera: Camera, first: Capture | None = None,
                     no_sun: tuple[Path, str] | None = None, rho_source: str | None = None,
                     radiance: bool = True) -> dict[str, Any]:
    """What run.json says of the reference: the route, and for the panel route every panel
    capture's factors beside the DLS's on the same capture (their ratio compares the two);
    for no route (``none``) why the sun sensor gives none (``no_sun``: a band file and its
    reason, :func:`sun_sensor_missing`) and how to get reflectance."""
    rec: dict[str, Any] = {"route": reference}
    meta = first.metas[0] if first is not None else None
    if reference == "none":
        rec["formula"] = "no reflectance (NaN): no panel given and the sun sensor gives no usable reflectance"
        if no_sun is not None:
            rec["reason"] = f"{no_sun[0].name}: {no_sun[1]}"
        rec["hint"] = PANEL_HINT if radiance else f"{PANEL_HINT}; --products radiance writes the radiance"
        return rec
    if reference == "dls":
        return {**rec, **sun_scale_record(meta)}
    rec["formula"] = "R_b = L_b / S_b, S_b from the panel's Eq. 11-14 split (median-lit panel)"
    if reference == "panel-dls":
        rec["formula"] = ("R_b(t) = L_b / E_b(t), E_b(t) = q_b(t) E^s_b(t): the panels' light over the sun sensor's "
                          "(tilt-corrected) per band, interpolated in time, times the capture's own sensor reading")
    rec["factor"] = dict(zip(camera.band_names, factor or ()))
    if rho_source is not None:
        rec["panel_reflectance"] = rho_source
    rec["panels"] = []
    for p in panels:
        ratio = {name: (ks / kd if kd else None) for name, ks, kd in zip(camera.band_names, p.factor_split, p.factor_dls)}
        rec["panels"].append({
            "capture": p.capture,
            "factor_split": dict(zip(camera.band_names, p.factor_split)),
            "factor_mean": dict(zip(camera.band_names, p.factor_mean)),
            "factor_dls": dict(zip(camera.band_names, p.factor_dls)),
            "panel_over_dls": ratio,
            "brightness_p10_p90": list(p.brightness_p10_p90),
            "split_residual_rms": p.split_residual_rms,
            "region_source": list(p.region_source),
            "reflectance": dict(zip(camera.band_names, p.reflectance)),
        })
    return rec
