"""Readers of per-frame TIFFs as photogrammetry software reads them (tests only).

OpenDroneMap's ``opendm/photo.py`` (``ODM_Photo.parse_exif_values``) reads EXIF with
``exifread.process_file`` and XMP by cutting ``<x:xmpmeta ... </x:xmpmeta>`` out of the raw
file bytes and parsing it with ``xmltodict`` (qualified names kept as written: attributes
become ``'@Camera:CaptureUUID'``, elements ``'Camera:BandName'`` with an ``rdf:Seq``/``rdf:li``
inside). ``xmltodict`` is not installed here, so :func:`odm_xmp` rebuilds that mapping with
expat (no namespace processing), which is what xmltodict does. :func:`exiftool_tags` runs
ExifTool (Debian ``libimage-exiftool-perl``), the reader Pix4D's and Agisoft's documents refer
to; tests that need it skip when it is absent.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from xml.parsers import expat

import exifread
import pytest


def exif_tags(path: Path, details: bool = False) -> dict:
    with open(path, "rb") as f:
        return exifread.process_file(f, details=details)


def dms_to_decimal(dms_tag, ref_tag) -> float:
    """As ODM_Photo.dms_to_decimal / float_values: Ratio .num/.den, sign from the Ref letter."""
    d, m, s = (float(v.num) / float(v.den) for v in dms_tag.values)
    return (-1 if ref_tag.values[0] in "SWsw" else 1) * (d + m / 60 + s / 3600)


def odm_xmp(path: Path) -> list[dict]:
    """ODM_Photo.get_xmp: the rdf:Description mapping(s), as xmltodict would build them."""
    raw = path.read_bytes()
    start, end = raw.find(b"<x:xmpmeta"), raw.find(b"</x:xmpmeta")
    assert 0 <= start < end
    text = raw[start:end + 12].decode("utf8")

    stack: list[tuple[str, dict, list[str]]] = [("", {}, [])]
    parser = expat.ParserCreate()

    def start_el(name, attrs):
        stack.append((name, {f"@{k}": v for k, v in attrs.items()}, []))

    def end_el(name):
        _, node, texts = stack.pop()
        txt = "".join(texts).strip()
        value: object
        if node:
            if txt:
                node["#text"] = txt
            value = node
        else:
            value = txt or None
        parent = stack[-1][1]
        if name in parent:
            if not isinstance(parent[name], list):
                parent[name] = [parent[name]]
            parent[name].append(value)
        else:
            parent[name] = value

    parser.StartElementHandler = start_el
    parser.EndElementHandler = end_el
    parser.CharacterDataHandler = lambda data: stack[-1][2].append(data)
    parser.Parse(text, True)
    root = stack[0][1]
    desc = root.get("x:xmpmeta", {}).get("rdf:RDF", {}).get("rdf:Description", {})
    return desc if isinstance(desc, list) else [desc]


def odm_get_xmp_tag(xtags: dict, names: list[str]):
    """ODM_Photo.get_xmp_tag: first of ``names`` present; a string, or an rdf:Seq's items."""
    for tag in names:
        if tag in xtags:
            t = xtags[tag]
            if isinstance(t, str):
                return t
            if isinstance(t, dict):
                items = t.get("rdf:Seq", {}).get("rdf:li", {})
                if items:
                    return items if isinstance(items, str) else " ".join(items)
    return None


def odm_float(tag) -> float | None:
    """ODM_Photo.float_value: the first value of an exifread tag as float."""
    v = tag.values[0] if isinstance(tag.values, list) else tag.values
    if isinstance(v, (int, float)):
        return float(v)
    return float(v.num) / float(v.den) if v.den else None


def odm_focal_ratio(path: Path, width: int) -> float | None:
    """ODM_Photo.extract_focal's ratio focal / sensor width from the EXIF tags it uses:
    FocalLengthIn35mmFilm / 36, else FocalLength over FocalPlaneXResolution's sensor width."""
    tags = exif_tags(path, True)
    if "EXIF FocalLengthIn35mmFilm" in tags and odm_float(tags["EXIF FocalLengthIn35mmFilm"]):
        return odm_float(tags["EXIF FocalLengthIn35mmFilm"]) / 36.0
    mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(odm_float(tags["EXIF FocalPlaneResolutionUnit"])))
    sensor_width = width / odm_float(tags["EXIF FocalPlaneXResolution"]) * mm
    return odm_float(tags["EXIF FocalLength"]) / sensor_width


def require_exiftool() -> str:
    """The ExifTool executable; skips the calling test when it is absent."""
    exe = shutil.which("exiftool")
    if exe is None:
        pytest.skip("exiftool is not installed (Debian package libimage-exiftool-perl; .ci/run installs it)")
    return exe


def exiftool_tags(*paths: Path) -> list[dict]:
    """``exiftool -j -n -G1`` of ``paths`` (numbers as numbers); skips the test without ExifTool."""
    exe = require_exiftool()
    out = subprocess.run([exe, "-j", "-n", "-G1", *map(str, paths)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)
