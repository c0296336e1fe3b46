"""Which captures of a factory apply show a reflectance panel, and which panel it is.

- :func:`panel_candidates`: the captures searched for a panel when none is named;
- :func:`panels_seen`: panel captures a run does not use (exported, and named in the summary);
- :func:`find_panel_serial`: the panel's serial number, from the band files' XMP
  ``PanelSerial`` (MicaSense firmware writes it in its panel captures; no pixels read), else
  from the panel's QR code in the pixels (:func:`mscal_core.panel.qr_serial`), looked up in
  the reflectance targets (:func:`pipeline.ingest.targets.target_for_serial`). With
  ``--reference auto`` and no ``--panel-reflectance``, a panel whose serial has a target gives
  reflectance when the camera wrote no XMP Albedo (:mod:`pipeline.apply.factory`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

from mscal_core.errors import FrameError

from pipeline.ingest.catalog import Target
from pipeline.ingest.grouping import Capture, read_capture_pixels
from pipeline.ingest.sunsensor import file_xmp
from pipeline.ingest.targets import target_for_serial

PANEL_SEARCH = 3  # captures at each end of the folder searched for a panel when none is named
PANEL_SCAN_ALL = 50  # folders of at most this many captures are searched whole (panels mixed with the flight)
PANEL_SEEN_SIDE = 1280  # px: panels_seen searches bigger images decimated to this (RedEdge size)
XMP_SERIAL = "XMP PanelSerial"
QR_SERIAL = "QR code"


def panel_candidates(captures: Sequence[Capture]) -> list[Capture]:
    """Captures searched for a panel when none is named, in folder order: all of them in a
    folder of at most :data:`PANEL_SCAN_ALL` captures (panels before, during and after the
    flight, mixed with it); else the first and last :data:`PANEL_SEARCH` and every capture the
    camera flagged as a panel capture (an XMP ``ReflectArea`` in one of its bands)."""
    if len(captures) <= PANEL_SCAN_ALL:
        return list(captures)
    ends = {c.name for c in list(captures[:PANEL_SEARCH]) + list(captures[-PANEL_SEARCH:])}
    return [c for c in captures if c.name in ends or any(m.reflect_area for m in c.metas)]


def panels_seen(captures: Sequence[Capture], named: Sequence[str] = ()) -> list[str]:
    """Captures that show a reflectance panel, for a run that does not use one (exported to
    ``OUT/panels/``, and named in the summary's hint):
    those named with ``--panel``, else among the folder's first and last
    :data:`PANEL_SEARCH` captures those with an XMP ReflectArea, or where a panel is detected
    (:func:`mscal_core.panel.detect_panel`) in both the first and the last band (one band
    alone finds a bright roof now and then), decimated to at most :data:`PANEL_SEEN_SIDE`
    pixels a side. About 0.3 s per capture searched."""
    from mscal_core.panel import detect_panel

    if named:
        return list(named)
    ends = list(captures[:PANEL_SEARCH]) + [c for c in captures[-PANEL_SEARCH:] if c not in captures[:PANEL_SEARCH]]
    seen = []
    for c in ends:
        if any(m.reflect_area for m in c.metas):
            seen.append(c.name)
            continue
        try:
            _, dns, _ = read_capture_pixels(c)
        except FrameError:
            continue
        k = max(1, math.ceil(max(dns[0].shape[:2]) / PANEL_SEEN_SIDE))  # big images: searched decimated
        if detect_panel(dns[0][::k, ::k]) is not None and (len(dns) == 1 or detect_panel(dns[-1][::k, ::k]) is not None):
            seen.append(c.name)
    return seen


def seen_record(seen: Sequence[str]) -> dict[str, Any]:
    """run.json ``reference.panels_seen``: panel captures in the folder that the run did not
    use, and how to use them (the QA report and the command's summary warn of them)."""
    if not seen:
        return {}
    return {"panels_seen": list(seen),
            "panel_hint": "give --panel-reflectance TARGET (a number, or a target of catalogs/targets such as "
                          f"micasense-rp02-1603036-sc) to take the reflectance from the panel; --panel {seen[0]} "
                          "chooses the capture"}


# --------------------------------------------------------------------------- the panel's serial


@dataclass(frozen=True)
class PanelSerial:
    """What the search for the panel's serial found: ``serial`` None when no capture of the
    ``searched`` ones carries one; else the first capture showing it, how it was read
    (:data:`XMP_SERIAL` or :data:`QR_SERIAL`) and its catalog target (None: in no target)."""

    searched: int
    serial: str | None = None
    capture: str | None = None
    source: str | None = None
    target: Target | None = None

    @property
    def where(self) -> str:
        return f"panel serial {self.serial} ({self.source} of {self.capture})"

    @property
    def rho_source(self) -> str:
        """run.json ``reference.panel_reflectance`` of a run that used it."""
        return f"{self.where} -> target {self.target.name if self.target else None}"

    def record(self, used: bool, unusable: str | None = None) -> dict[str, Any]:
        """run.json ``reference`` entries saying what the search found and, when the run did
        not use it (``used`` False), why: no serial read, a serial in no target, or a panel
        that could not be measured (``unusable``, the reason)."""
        if self.serial is None:
            return {"panel_serial_none": f"no XMP PanelSerial and no readable QR code in the {self.searched} "
                                         "capture(s) searched for a panel"}
        rec: dict[str, Any] = {"panel_serial": {"serial": self.serial, "capture": self.capture, "source": self.source,
                                                "target": self.target.name if self.target else None}}
        if self.target is None:
            rec["panel_serial_unknown"] = (f"{self.serial} ({self.source} of {self.capture}) is in no catalogs/targets "
                                           "file; add one with its per-band reflectance")
            rec["panel_hint"] = (f"add catalogs/targets/NAME.yaml with 'serial: {self.serial}' and the panel's per-band "
                                 "reflectance (or a folder of them in MSCAL_CATALOG_PATH), or give --panel-reflectance "
                                 f"TARGET; --panel {self.capture} chooses the capture")
        elif not used and unusable:
            rec["panel_serial_unusable"] = unusable
        return rec


def capture_xmp_serial(capture: Capture) -> str | None:
    """The XMP ``PanelSerial`` (the shared Camera schema, then the makers' default namespaces:
    :func:`pipeline.ingest.xmp.default_namespaces`) of the capture's first band file that has
    one (the tag only: no pixels are read)."""
    for path in capture.files:
        text = file_xmp(path).text("PanelSerial")
        if text and text.strip():
            return text.strip()
    return None


def capture_qr_serial(capture: Capture) -> str | None:
    """The text of the QR code in the capture's band images (:func:`mscal_core.panel.qr_serial`),
    None when none is read or the pixels cannot be read."""
    from mscal_core.panel import qr_serial

    try:
        _, dns, _ = read_capture_pixels(capture)
    except FrameError:
        return None
    return qr_serial(dns)


def find_panel_serial(captures: Sequence[Capture], named: Sequence[str] = ()) -> PanelSerial:
    """The serial of the first panel among the ``named`` captures (``--panel``), else among
    :func:`panel_candidates`: XMP ``PanelSerial`` of every capture first (cheap), then the QR
    code in the pixels (about 0.1 s per capture without one, 0.3 s with one), stopping at the
    first found; its target by :func:`pipeline.ingest.targets.target_for_serial`."""
    pool = [c for c in captures if c.name in set(named)] if named else panel_candidates(captures)
    for source, read in ((XMP_SERIAL, capture_xmp_serial), (QR_SERIAL, capture_qr_serial)):
        for c in pool:
            serial = read(c)
            if serial:
                return PanelSerial(len(pool), serial, c.name, source, target_for_serial(serial))
    return PanelSerial(len(pool))
