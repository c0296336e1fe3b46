"""Reflectance targets by the serial number of the panel they describe.

A calibrated panel carries its serial number (MicaSense: printed and in its QR code, e.g.
``RP02-1603036-SC``); a target file of ``catalogs/targets`` lists the serials of the panels
whose reflectance it gives (``serial: TEXT`` or ``serials: [TEXT, ...]``,
:func:`pipeline.ingest.catalog.parse_target`). A panel capture's serial
(:mod:`pipeline.apply.panel_search`) is looked up here.
"""

from __future__ import annotations

import hashlib

from mscal_core.errors import CatalogError

from pipeline.ingest.catalog import Target, list_entries, load_target


def normalise_serial(serial: str) -> str:
    """A serial number as compared: surrounding whitespace dropped, case folded."""
    return serial.strip().casefold()


def serial_targets() -> list[Target]:
    """Every reflectance target that lists a serial, by name, over every catalog folder
    (:func:`pipeline.ingest.catalog.catalog_dirs`: a file in a folder of ``MSCAL_CATALOG_PATH``
    shadows the shipped file of its name)."""
    return [t for t in (load_target(n) for n in list_entries("targets")) if t.serials]


def target_for_serial(serial: str) -> Target | None:
    """The target of :func:`serial_targets` that lists ``serial`` (compared by
    :func:`normalise_serial`), or None. Two targets listing it: :class:`CatalogError` naming
    both (which reflectance is the panel's?)."""
    key = normalise_serial(serial)
    found = [t for t in serial_targets() if key and key in map(normalise_serial, t.serials)]
    if len(found) > 1:
        raise CatalogError(f"panel serial {serial.strip()!r} is listed by several targets: "
                           f"{', '.join(t.name for t in found)}", hint="keep it in one catalogs/targets file")
    return found[0] if found else None


def serial_targets_digest() -> str:
    """SHA-256 of what :func:`target_for_serial` can answer (every serial target's name,
    serials and reflectance): a run that took its reflectance from a panel's serial is redone
    when this changes."""
    return hashlib.sha256(repr([(t.name, t.serials, t.reflectance) for t in serial_targets()]).encode()).hexdigest()
