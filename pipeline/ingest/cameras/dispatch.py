"""The small dispatcher that picks a camera maker's module.

Each maker's module (``micasense``, ``parrot``, ``dji``, ``sentera``, ...) holds that maker's
tag reading (which XMP/EXIF tags, how they become :class:`~pipeline.ingest.meta.CaptureMeta`
fields), its radiance model (calling the pure formulas of :mod:`mscal_core.factory`), its
sun-sensor reading and its quirks, and registers itself with
:func:`pipeline.ingest.cameras.registry.register`. Every module of this package is imported
here, so adding a camera maker is adding one module (and its cameras' catalog files).

A file's maker is the first whose ``claims`` its tags satisfy (MicaSense's when none does);
a band's radiance model is the maker of its ``CaptureMeta.radiometry``; a catalog camera's
``factory_model`` names the maker its files follow (:func:`factory_models`).
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Sequence

import numpy as np
from mscal_core.errors import FrameError

import pipeline.ingest.cameras as _cameras
from pipeline.ingest.cameras.registry import FileRegistration, Maker, by_order, maker_of, radiance_unit
from pipeline.ingest.meta import CaptureMeta, FieldParts, TagContext

for _module in pkgutil.iter_modules(_cameras.__path__):
    if _module.name not in ("registry", "dispatch"):
        importlib.import_module(f"{_cameras.__name__}.{_module.name}")


def factory_models() -> tuple[str, ...]:
    """The catalog ``factory_model`` names of the registered makers."""
    return tuple(m.model for m in by_order())


def maker_for_model(model: str) -> Maker:
    """The maker of a catalog camera's ``factory_model``."""
    for maker in by_order():
        if maker.model == model:
            return maker
    raise KeyError(model)


def takes_field_parts(model: str | None) -> bool:
    """Whether the radiance model of a catalog camera's ``factory_model`` takes a field
    calibration's parts (:attr:`Maker.field_parts`); a camera without one (None) has no
    factory model to replace parts of: its radiance is the field calibration's whole."""
    if model is None:
        return True
    try:
        return maker_for_model(model).field_parts
    except KeyError:
        return False


def read_tags(ctx: TagContext) -> list[CaptureMeta]:
    """The bands of one file, read by the maker whose tags the file carries."""
    makers = by_order()
    for maker in makers:
        if maker.claims(ctx):
            return maker.read(ctx)
    return next(m for m in makers if m.fallback).read(ctx)


def maker_of_band(meta: CaptureMeta) -> Maker | None:
    """The maker of a band file's radiometry, or None when no registered maker has it."""
    try:
        return maker_of(meta.radiometry)
    except KeyError:
        return None


def file_registration(meta: CaptureMeta) -> FileRegistration | None:
    """The band file's maker's own registration onto the camera's common image plane
    (:attr:`Maker.file_registration`), or None when its maker writes none."""
    maker = maker_of_band(meta)
    return None if maker is None else maker.file_registration


def has_file_registration(meta: CaptureMeta) -> bool:
    """Whether the band file carries its maker's registration to the common image plane."""
    reg = file_registration(meta)
    return reg is not None and reg.has(meta)


def align_by_files(metas: Sequence[CaptureMeta], stack: np.ndarray) -> np.ndarray:
    """Bands ``(band, H, W)`` of one capture (stored orientation) on the camera's common image
    plane with each band file's own registration (:attr:`Maker.file_registration`);
    FrameError naming the first band file without one."""
    reg = file_registration(metas[0])
    if reg is None:
        raise FrameError("no band registration in the file's metadata", path=metas[0].path,
                         hint="align the bands with 'mscal register' and --registration, or apply with --no-align")
    return reg.align(metas, stack)


def file_registration_note(metas: Sequence[CaptureMeta]) -> str:
    """What the band files' own registration is (:attr:`FileRegistration.note`), for run.json."""
    notes = {reg.note for m in metas if (reg := file_registration(m)) is not None}
    return "; ".join(sorted(notes))


def sibling_position(meta: CaptureMeta, capture: str) -> tuple[float, float, float | None] | None:
    """``(lat, lon, alt_m)`` of capture ``capture`` from a file its maker saves beside the band
    file ``meta`` (:attr:`Maker.sibling_position`), or None (no such file, or no such maker)."""
    maker = maker_of_band(meta)
    find = None if maker is None else maker.sibling_position
    return None if find is None else find(meta.path.parent, capture)


def is_temperature(meta: CaptureMeta) -> bool:
    """Whether the band file's factory model gives temperature in kelvin (a thermal band:
    its maker's unit for the band's radiometry is ``K``, :func:`~pipeline.ingest.cameras.registry.radiance_unit`), not radiance."""
    return maker_of_band(meta) is not None and radiance_unit(meta.radiometry) == "K"


def companion_image_patterns() -> dict[str, tuple[str, str]]:
    """Every maker's images saved beside band files that are no band files, by catalog camera
    (:attr:`Maker.companion_images`)."""
    out: dict[str, tuple[str, str]] = {}
    for maker in by_order():
        out.update(maker.companion_images)
    return out


def factory_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None = None,
                     channels: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Radiance of one band's DN with its maker's factory model (unit: ``meta.radiance_unit``;
    kelvin for a thermal band), or with the field-fitted ``parts`` in place of the factory's
    response and/or vignetting (a maker whose model takes them, :attr:`Maker.field_parts`). ``channels``: the whole ``(H, W, C)``
    image of a multi-channel file (Sentera), which the colour transform needs. The result is
    in the stored orientation (see :func:`pipeline.ingest.meta.upright_meta`); with ``out``
    (e.g. a float32 band of the capture's cube) it is written there and ``out`` returned."""
    if dn.shape != meta.shape:
        raise FrameError(f"image {dn.shape} does not match its metadata {meta.shape}", path=meta.path)
    maker = maker_of(meta.radiometry)
    if parts is not None and (parts.vignetting is not None or parts.inverse_response is not None) and \
            not (maker.field_parts and meta.radiometry not in maker.kept_out):
        takes = ", ".join(m.model for m in by_order() if m.field_parts) or "none"
        raise FrameError(f"field components replace parts of a factory radiance model that takes them ({takes}), "
                         f"not {meta.radiometry}'s", path=meta.path, hint="leave out --field-calibration for this camera")
    rad = maker.radiance(meta, dn, parts, channels, out)
    if out is not None and rad is not out:
        out[...] = rad
        return out
    return rad
