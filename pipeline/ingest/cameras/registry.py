"""The camera makers mscal reads factory metadata of: each maker's module registers one
:class:`Maker` here (its tag reading, radiance model, vignetting, sun-sensor tag and the
units of its radiance); :mod:`pipeline.ingest.cameras` picks one by a file's tags or by a
band's ``CaptureMeta.radiometry``.

This module imports no other module of mscal at run time, so that the shared modules
(:mod:`pipeline.ingest.meta`) can look up what a maker registered without a cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import numpy as np

    from pipeline.ingest.meta import CaptureMeta, FieldParts, TagContext, VignettingTags

#: ``radiance(meta, dn, parts, channels, out)``: a band's radiance from its stored DN
#: (:func:`pipeline.ingest.cameras.factory_radiance` checks the shapes and field parts first).
Radiance = Callable[["CaptureMeta", "np.ndarray", "FieldParts | None", "np.ndarray | None", "np.ndarray | None"],
                    "np.ndarray"]


@dataclass(frozen=True)
class Maker:
    """One camera maker's factory model.

    ``claims(ctx)`` says whether a file's tags are this maker's (tried in ``order``, lowest
    first; the ``fallback`` maker reads every file no other claims); ``read(ctx)`` gives the
    file's bands' :class:`~pipeline.ingest.meta.CaptureMeta`, each with a ``radiometry`` of
    ``units``; ``radiance`` computes a band's radiance for those radiometries and
    ``vignetting(radiometry, shape, tags)`` its factory vignetting correction (``(H, W)``, >= 1, multiplies DN).
    ``model`` is the catalog's ``factory_model`` name of the maker's cameras, ``sun_sensor_tag``
    the tag its sun-sensor reading comes from (named when a band has none), and
    ``companion_images`` the catalog cameras' images saved beside the band files that are no
    band files (camera name: (file-name pattern with group ``capture``, why it is left out)).
    """

    name: str
    model: str
    units: dict[str, str]
    claims: Callable[["TagContext"], bool]
    read: Callable[["TagContext"], "list[CaptureMeta]"]
    radiance: Radiance
    vignetting: Callable[[str, tuple[int, int], "VignettingTags"], "np.ndarray"]
    order: int = 50
    fallback: bool = False
    sun_sensor_tag: str | None = None
    companion_images: dict[str, tuple[str, str]] = field(default_factory=dict)


MAKERS: dict[str, Maker] = {}


def register(maker: Maker) -> Maker:
    """Add ``maker`` (called once by its module when imported); a second maker of one name,
    catalog model or radiometry is a programming error."""
    if maker.name in MAKERS:
        raise ValueError(f"camera maker {maker.name!r} registered twice")
    for other in MAKERS.values():
        if other.model == maker.model or set(other.units) & set(maker.units):
            raise ValueError(f"camera makers {other.name!r} and {maker.name!r} claim one model or radiometry")
        if other.fallback and maker.fallback:
            raise ValueError(f"camera makers {other.name!r} and {maker.name!r} are both the fallback")
    MAKERS[maker.name] = maker
    return maker


def by_order() -> list[Maker]:
    """The registered makers in the order their ``claims`` are tried."""
    return sorted(MAKERS.values(), key=lambda m: (m.order, m.name))


def maker_of(radiometry: str) -> Maker:
    """The maker whose bands have ``radiometry`` (``CaptureMeta.radiometry``)."""
    for maker in MAKERS.values():
        if radiometry in maker.units:
            return maker
    raise KeyError(radiometry)


def radiance_unit(radiometry: str) -> str:
    """The unit of a band's radiance of ``radiometry``."""
    return maker_of(radiometry).units[radiometry]


def sun_sensor_tag(radiometry: str) -> str | None:
    """The sun-sensor tag the maker of ``radiometry`` reads, None if it names none."""
    try:
        return maker_of(radiometry).sun_sensor_tag
    except KeyError:
        return None
