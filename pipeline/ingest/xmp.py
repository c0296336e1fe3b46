"""XMP metadata the way cameras really write it, for every reader in ``pipeline.ingest``.

One parser for the packets of every maker's files (TIFF tag 700, or the
``http://ns.adobe.com/xap/1.0/`` APP1 segment of a JPEG), pure Python (``xml.etree``):

- a property is found whether it is an attribute of ``rdf:Description``, a child element with
  text, or a child element holding an ``rdf:Seq``/``rdf:Bag``/``rdf:Alt`` of ``rdf:li`` items;
  several ``rdf:Description`` blocks (MicaSense writes one per namespace) are merged;
- namespaces are matched by URI, never by prefix, and a URI with or without its trailing slash
  is the same namespace (RedEdge firmware writes ``http://pix4d.com/camera/1.0`` and
  ``http://pix4d.com/1.0``, Parrot and Sentera ``http://pix4d.com/camera/1.0/``; cameras.md §0,
  ExifTool's Pix4D config);
- a list of numbers may be a sequence of ``rdf:li``, one ``rdf:li`` holding ``622,371,574,...``
  (comma- or space-separated), or a plain comma string (MicaSense PrincipalPoint, Parrot
  SensorModel, DJI VignettingData): :meth:`Xmp.numbers` flattens all of them.

A tag that is present but unreadable raises :class:`TagError` (file, tag, value, why); the
readers turn it into a :class:`TagProblem` that disables only the feature needing the tag.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from mscal_core.errors import FrameError

from pipeline.ingest.cameras import registry

RDF_NS = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"

#: Canonical namespace key -> URIs (compared without a trailing slash) of the schemas every maker
#: may write: Pix4D's camera schema and Adobe's TIFF and EXIF. A maker's own namespaces are
#: declared in its module (:attr:`pipeline.ingest.cameras.registry.Maker.namespaces`) and known to
#: every parse once it is registered (importing :mod:`pipeline.ingest` registers them all).
NAMESPACES: dict[str, tuple[str, ...]] = {
    "Camera": ("http://pix4d.com/camera/1.0", "http://pix4d.com/1.0"),  # Pix4D camera schema, old and new URI
    "tiff": ("http://ns.adobe.com/tiff/1.0",),
    "exif": ("http://ns.adobe.com/exif/1.0",),
}
#: The shared namespace a tag is looked up in when none is named: Pix4D's camera schema; the
#: makers whose files hold its tags in their own namespace too add theirs after it
#: (:func:`default_namespaces`).
SHARED_DEFAULT_NAMESPACES = ("Camera",)
_BY_URI = {uri: key for key, uris in NAMESPACES.items() for uri in uris}
JPEG_XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"


@dataclass(frozen=True)
class TagProblem:
    """A tag that is present but unusable, and the feature it disables (None: the capture)."""

    file: str
    tag: str
    value: str
    reason: str
    feature: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"file": self.file, "tag": self.tag, "value": self.value, "reason": self.reason,
                "feature": self.feature}

    def message(self) -> str:
        what = f"{self.tag} = {self.value!r}: {self.reason}"
        return what + (f" ({self.feature} disabled)" if self.feature else "")


class TagError(FrameError):
    """A present XMP/EXIF tag whose value cannot be used (names the file, tag and value)."""

    def __init__(self, tag: str, value: Any, reason: str, path: str | Path, hint: str | None = None):
        self.tag, self.value = tag, _short(value)
        super().__init__(f"{tag} is {self.value!r}: {reason}", path=path, hint=hint)
        self.why = reason

    def problem(self, feature: str | None) -> TagProblem:
        return TagProblem(str(self.path), self.tag, self.value, self.why, feature)


def _short(value: Any) -> str:
    text = ", ".join(value) if isinstance(value, list) else str(value)
    return text if len(text) <= 160 else text[:157] + "..."


def namespace_key(uri: str) -> str | None:
    """The canonical key of a namespace URI (trailing slash ignored): :data:`NAMESPACES`, else a
    registered maker's own (:data:`pipeline.ingest.cameras.registry.NAMESPACE_KEYS`); None if unknown."""
    uri = uri.rstrip("/")
    return _BY_URI.get(uri) or registry.NAMESPACE_KEYS.get(uri)


def default_namespaces() -> tuple[str, ...]:
    """The namespaces a tag is looked up in, in order, when a reader names none:
    :data:`SHARED_DEFAULT_NAMESPACES`, then the registered makers'
    (:data:`pipeline.ingest.cameras.registry.DEFAULT_NAMESPACE_KEYS`)."""
    return SHARED_DEFAULT_NAMESPACES + registry.DEFAULT_NAMESPACE_KEYS


class Xmp:
    """The properties of one XMP packet, by (namespace key, local name)."""

    def __init__(self, props: dict[tuple[str, str], str | list[str]], path: Path | str):
        self.props = props
        self.path = Path(path)

    # ----------------------------------------------------------------- parsing

    @classmethod
    def parse(cls, packet: bytes | str, path: Path | str) -> "Xmp":
        text = packet.decode("utf-8", errors="replace") if isinstance(packet, (bytes, bytearray)) else packet
        xml = _packet_xml(text)
        if xml is None:
            raise FrameError("the XMP packet has no x:xmpmeta or rdf:RDF element", path=path,
                             hint="the file's XMP metadata is damaged; copy the file again from the camera's card")
        try:
            root = ET.fromstring(xml)
        except (ET.ParseError, ValueError, RecursionError) as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise FrameError(f"the XMP packet is not valid XML ({why})", path=path,
                             hint="the file's XMP metadata is damaged; copy the file again from the camera's card") from None
        props: dict[tuple[str, str], str | list[str]] = {}
        for desc in root.iter(f"{{{RDF_NS}}}Description"):
            for key, value in desc.attrib.items():
                q = _qualified(key)
                if q is not None:
                    props[q] = value.strip()
            for child in desc:
                q = _qualified(child.tag)
                if q is not None:
                    props[q] = _element_value(child)
        return cls(props, path)

    @classmethod
    def empty(cls, path: Path | str) -> "Xmp":
        return cls({}, path)

    # ----------------------------------------------------------------- access

    def raw(self, tag: str, ns: Iterable[str] | None = None) -> str | list[str] | None:
        """The value of ``tag`` in the first of namespaces ``ns`` that has it (None: absent
        or empty); ``ns`` None: :func:`default_namespaces`."""
        for key in default_namespaces() if ns is None else ns:
            v = self.props.get((key, tag))
            if v is not None and v != "" and v != []:
                return v
        return None

    def has(self, tag: str, ns: Iterable[str] | None = None) -> bool:
        return self.raw(tag, ns) is not None

    def text(self, tag: str, ns: Iterable[str] | None = None) -> str | None:
        """A text property; an ``rdf:Seq``/``rdf:Alt`` of one item counts as its item (an Alt
        of several: the first, the default language)."""
        v = self.raw(tag, ns)
        if isinstance(v, list):
            v = v[0] if v else None
        return None if v is None or str(v).strip() == "" else str(v).strip()

    def texts(self, tag: str, ns: Iterable[str] | None = None) -> list[str] | None:
        """A list of texts (an ``rdf:Seq`` per item, or one comma-separated text)."""
        v = self.raw(tag, ns)
        if v is None:
            return None
        if isinstance(v, list) and len(v) > 1:
            return [str(s).strip() for s in v]
        one = v[0] if isinstance(v, list) else v
        return [s.strip() for s in str(one).split(",")]

    def numbers(self, tag: str, ns: Iterable[str] | None = None, count: int | None = None,
                *, allowed: tuple[int, ...] | None = None) -> tuple[float, ...] | None:
        """A tag as finite floats, None when absent; :class:`TagError` when present but not
        ``count`` (or one of ``allowed``) finite numbers. Every list form is flattened."""
        v = self.raw(tag, ns)
        if v is None:
            return None
        out = parse_numbers(v)
        want = f"{count} numbers" if count is not None else (
            f"{' or '.join(map(str, allowed))} numbers" if allowed else "numbers")
        if out is None or not out or (count is not None and len(out) != count) or (allowed and len(out) not in allowed):
            raise TagError(tag, v, f"expected {want}", self.path)
        return out

    def number(self, tag: str, ns: Iterable[str] | None = None) -> float | None:
        n = self.numbers(tag, ns, 1)
        return None if n is None else n[0]

    def angles(self, tags: tuple[str, str, str], ns: Iterable[str], degrees: bool) -> tuple[float, float, float] | None:
        """Three angles (yaw, pitch, roll) in radians from ``tags`` (``degrees``: written in
        degrees), or None unless all three are finite numbers."""
        vals = [self.number(t, ns) for t in tags]
        if any(v is None or not math.isfinite(v) for v in vals):
            return None
        y, p, r = (float(v) for v in vals)  # type: ignore[arg-type]
        return (math.radians(y), math.radians(p), math.radians(r)) if degrees else (y, p, r)


def parse_numbers(value: str | list[str]) -> tuple[float, ...] | None:
    """Numbers of a list value or of a comma/space/semicolon separated text; None if any item
    is not a finite number."""
    items = value if isinstance(value, list) else [value]
    out: list[float] = []
    for item in items:
        for token in str(item).replace(",", " ").replace(";", " ").split():
            try:
                x = float(token)
            except ValueError:
                return None
            if not math.isfinite(x):
                return None
            out.append(x)
    return tuple(out)


_ROOTS = (re.compile(r"<((?:[A-Za-z_][\w.-]*:)?)xmpmeta[\s>/]"), re.compile(r"<((?:[A-Za-z_][\w.-]*:)?)RDF[\s>/]"))


def _packet_xml(text: str) -> str | None:
    """The XML of a packet: its ``x:xmpmeta`` element (any prefix; XMP allows another or
    none), else its ``rdf:RDF`` (the wrapper is optional); None if neither is there."""
    for rx, local in zip(_ROOTS, ("xmpmeta", "RDF")):
        m = rx.search(text)
        if m is not None:
            end = text.rfind(f"</{m[1]}{local}>")
            return text[m.start(): end + len(f"</{m[1]}{local}>")] if end > m.start() else text[m.start():]
    return None


def _qualified(qname: str) -> tuple[str, str] | None:
    if not qname.startswith("{"):
        return None
    uri, _, local = qname[1:].partition("}")
    key = namespace_key(uri)
    return None if key is None else (key, local)


def _element_value(elem: ET.Element) -> str | list[str]:
    for kind in ("Seq", "Bag", "Alt"):
        container = elem.find(f"{{{RDF_NS}}}{kind}")
        if container is not None:
            return [(li.text or "").strip() for li in container.findall(f"{{{RDF_NS}}}li")]
    return (elem.text or "").strip()


# --------------------------------------------------------------------------- packets of files


def jpeg_xmp_packet(data: bytes) -> bytes | None:
    """The XMP packet of a JPEG (its ``http://ns.adobe.com/xap/1.0/`` APP1 segment), None if none."""
    i = 2
    if data[:2] != b"\xff\xd8":
        return None
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no more metadata segments
            return None
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        segment = data[i + 4 : i + 2 + length]
        if marker == 0xE1 and segment.startswith(JPEG_XMP_HEADER):
            return segment[len(JPEG_XMP_HEADER):]
        i += 2 + length
    return None


def xmp_of_bytes(data: bytes, path: Path | str) -> Xmp:
    """The XMP of a JPEG file's bytes (an empty :class:`Xmp` when it has none)."""
    packet = jpeg_xmp_packet(data)
    return Xmp.empty(path) if packet is None else Xmp.parse(packet, path)


def legacy_properties(packet: bytes | str, path: Path | str) -> dict[str, Any]:
    """Properties by local name only (the namespaces of :func:`default_namespaces`), for callers
    of the former ``camera_meta.xmp_properties``."""
    x = Xmp.parse(packet, path)
    keys = default_namespaces()
    out: dict[str, Any] = {}
    for (key, local), value in x.props.items():
        if key in keys:
            out[local] = value
    return out
