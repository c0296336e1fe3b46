"""Property-based fuzzing of the files a user hands mscal: session.yaml, frames.csv,
catalog YAML and XMP packets.

Every strategy starts from a real, valid document (the small synthetic session, the shipped
catalogs, the packets of the real camera files in ../shared/data) and breaks it the ways files
get broken: keys dropped or added, wrong types, random unicode, huge numbers, NaN/inf, negative
values, duplicate keys, truncated text, wrong XML, other namespace prefixes, rdf:Seq/Bag/Alt
forms, comma/space separated lists. The property, for each reader: it returns a valid object
or raises an :class:`~mscal_core.errors.MscalError` (exit status 2) whose message is one line
naming the file; never another exception. A few end-to-end runs of the command line check the
same on stderr, and that an output already written is left untouched.

The short, seeded version runs in ``make test``; the ``long``-marked twins (``make test-long``)
draw many more examples (profiles in tests/conftest.py).
"""

from __future__ import annotations

import copy
import csv
import hashlib
import io
import math
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

from mscal_core.errors import MscalError
from pipeline.ingest.camera_meta import meta_from_tags, read_file_metas
from pipeline.ingest.catalog import (
    CATALOG_ROOT,
    Camera,
    Index,
    Target,
    clear_cache,
    load_camera,
    load_index,
    load_target,
)
from pipeline.ingest.exif import time_ns
from pipeline.ingest.intrinsics import intrinsics_from_tags, tiff_tags
from pipeline.ingest.meta import factory_vignetting
from pipeline.ingest.session import Session, load_session, read_frame_table
from pipeline.ingest.xmp import RDF_NS, Xmp, jpeg_xmp_packet
from tests.camera_files import dji_xmp, jpeg_segments

DATA = Path(__file__).parents[3].parent / "shared" / "data"
ROOT = Path(__file__).parents[3]


# --------------------------------------------------------------------------- the property


def assert_clean_error(exc: BaseException, *names: str) -> None:
    """An error a user can act on: mscal's, exit status 2, one line, naming the file."""
    assert isinstance(exc, MscalError), f"{type(exc).__name__} escaped: {exc!r}"
    assert exc.exit_code == 2, exc
    text = str(exc)
    assert len(text.splitlines()) == 1, f"not one line: {text!r}"
    assert any(n in text for n in names), f"does not name {names}: {text!r}"


def read_or_error(read, *names: str):
    """``read()``'s value, or None after checking the error it raised."""
    try:
        return read()
    except Exception as exc:  # the property is about which exceptions
        assert_clean_error(exc, *names)
        return None


def finite(*values: float) -> bool:
    return all(math.isfinite(float(v)) for v in values)


# --------------------------------------------------------------------------- YAML strategies

WEIRD_TEXT = ["", " ", "-1", "0", "1e999", "-1e999", "nan", ".nan", ".inf", "9" * 400, "a" * 300, "\x00",
              "a\nb", "a: b", "../../../etc/passwd", "/etc/passwd", "DICT_4X4_50", "gray-50", "ndvi", "ü€𝔘",
              "\u2028", "{", "[", "'", "null", "~", "2017-06-14", "(?P<capture>.+)", "(?P<x", "a{99999999999}"]
SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 30), st.integers(),
    st.sampled_from([10**400, -(10**400), 2**63, -(2**63) - 1, 2**64]),
    st.floats(), st.sampled_from([math.nan, math.inf, -math.inf, -0.0, 5e-324, 1.7e308]),
    st.text(max_size=12), st.sampled_from(WEIRD_TEXT),
)
KEYS = st.one_of(st.text(max_size=8), st.sampled_from(["a\nb", "fx", "kind", "name", "id"]), st.integers(), st.none())
VALUES = st.recursive(SCALARS, lambda c: st.lists(c, max_size=4) | st.dictionaries(KEYS, c, max_size=3), max_leaves=8)


def _paths(node, path=()):
    yield path
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*path, i))


def _mutate_at(doc, path, op, draw):
    """``doc`` with the node at ``path`` changed by ``op``."""
    if not path:
        parent, key, node = None, None, doc
    else:
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        key, node = path[-1], parent[path[-1]]
    number = isinstance(node, (int, float)) and not isinstance(node, bool)
    if op == "delete" and parent is not None:
        del parent[key]
        return doc
    if op == "add_key" and isinstance(node, dict):
        node[draw(KEYS)] = draw(VALUES)
        return doc
    if op == "negate" and number:
        new = -node
    elif op == "scale" and number:
        factor = draw(st.sampled_from([0, 10**6, 10**30, 1e300, 1e-300, math.inf, math.nan]))
        try:
            new = node * factor
        except OverflowError:  # a huge int times a float: the document gets inf, as YAML would read it
            new = math.inf
    elif op == "wrap":
        new = [node]
    elif op == "stringify":
        new = str(node)
    elif op == "shrink" and isinstance(node, list) and node:
        new = node[: draw(st.integers(0, len(node) - 1))]
    else:
        new = draw(VALUES)
    if parent is None:
        return new
    parent[key] = new
    return doc


OPS = ["replace", "delete", "add_key", "negate", "scale", "wrap", "stringify", "shrink"]


@st.composite
def mutated_tree(draw, doc):
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(0, 3))):
        path = draw(st.sampled_from(list(_paths(doc))))
        doc = _mutate_at(doc, path, draw(st.sampled_from(OPS)), draw)
    return doc


@st.composite
def mutated_text(draw, text: str) -> str:
    """Text-level breakage: truncation, a duplicated line (a duplicate key in YAML), a span
    deleted, random unicode inserted, a tab for an indent."""
    for _ in range(draw(st.integers(0, 2))):
        op = draw(st.sampled_from(["truncate", "dup_line", "delete", "insert", "tab"]))
        n = len(text)
        i = draw(st.integers(0, n))
        if op == "truncate":
            text = text[:i]
        elif op == "dup_line":
            lines = text.splitlines(keepends=True)
            if lines:
                j = draw(st.integers(0, len(lines) - 1))
                lines.insert(draw(st.integers(0, len(lines))), lines[j])
                text = "".join(lines)
        elif op == "delete":
            text = text[:i] + text[i + draw(st.integers(1, 20)):]
        elif op == "insert":
            text = text[:i] + draw(st.text(min_size=1, max_size=8) | st.sampled_from(WEIRD_TEXT)) + text[i:]
        else:
            text = text.replace("\n  ", "\n\t", 1)
    return text


@st.composite
def yaml_texts(draw, seeds):
    doc = draw(mutated_tree(draw(st.sampled_from(seeds))))
    text = yaml.safe_dump(doc, sort_keys=False, allow_unicode=draw(st.booleans()))
    return draw(mutated_text(text))


# --------------------------------------------------------------------------- session.yaml


@pytest.fixture(scope="module")
def synth(small) -> Path:
    """The small synthetic session (the demo's: write_session(seed=0, size="small")), read only;
    the one the other tests of the process calibrate, so that make test writes it once."""
    return small[0]


@pytest.fixture(scope="module")
def session_seeds(synth) -> list:
    base = yaml.safe_load((synth / "session.yaml").read_text())
    with_panel = copy.deepcopy(base)
    with_panel["panel"] = {"marker": {"dictionary": "DICT_APRILTAG_36h11", "id": 7, "size_m": 0.06},
                           "size_m": [0.15, 0.15], "offset_m": [0.12, 0.0]}
    with_panel["reflector"]["reflectance"] = "gray-50"
    with_table = copy.deepcopy(base)
    with_table["panel"] = {"polygon": [[646, 454], [808, 452], [809, 613], [648, 615]]}
    with_table["reflector"]["reflectance"] = [[400, 0.5], [700, 0.52], [900, 0.55]]
    return [base, with_panel, with_table]


def check_session(root: Path, text: str) -> Session | None:
    (root / "session.yaml").write_text(text, encoding="utf-8")
    s = read_or_error(lambda: load_session(root), "session.yaml")
    if s is not None:
        assert finite(*s.reflector.size_m, s.marker.size_m, s.marker.border_m)
        assert s.reflector.size_m[0] > 0 and s.marker.size_m > 0
        assert np.all(np.isfinite(s.reflector.reflectance.at(s.camera.wavelengths)))
        for i in ((s.intrinsics,) if s.intrinsics else ()) + (s.band_intrinsics or ()):
            assert finite(i.fx, i.fy, i.cx, i.cy, *i.dist)
    return s


def test_session_yaml_fuzz(session_seeds, fuzz_settings, tmp_path):
    root = tmp_path / "session"
    root.mkdir()
    assert check_session(root, yaml.safe_dump(session_seeds[0])) is not None  # the seeds are valid

    @settings(fuzz_settings)
    @given(text=yaml_texts(session_seeds))
    def fuzz(text):
        check_session(root, text)

    fuzz()


# --------------------------------------------------------------------------- frames.csv

CELLS = st.one_of(
    st.sampled_from(WEIRD_TEXT),
    st.sampled_from(["inf", "-inf", "NaN", "1e-320", "1_000", "１２", "0x10", " 3 ", "1,5", "-0", "+2",
                     "2017-06-14T09:50:00Z", "2017-06-14", "0001-01-01T00:00:00+01:00",
                     "9999-12-31T23:59:59-01:00", "2017-06-14T25:00:00", "IMG_0000.tif", "sweep_00.tif",
                     "../field/IMG_0000.tif", "IMG_0000.tif/", "img_0000.TIF", "a" * 5000]),
    st.floats().map(repr), st.integers().map(str), st.text(max_size=10),
)


@st.composite
def csv_bytes(draw, seeds: list[str]) -> bytes:
    rows = list(csv.reader(io.StringIO(draw(st.sampled_from(seeds)))))
    for _ in range(draw(st.integers(0, 4))):
        op = draw(st.sampled_from(["cell", "cell", "cell", "drop_col", "drop_row", "dup_row", "add_col",
                                   "header", "ragged"]))
        r = draw(st.integers(0, len(rows) - 1)) if rows else 0
        width = max((len(x) for x in rows), default=0)
        c = draw(st.integers(0, max(width - 1, 0)))
        if op == "cell" and rows and c < len(rows[r]):
            rows[r][c] = draw(CELLS)
        elif op == "drop_col":
            rows = [x[:c] + x[c + 1:] for x in rows]
        elif op == "drop_row" and rows:
            del rows[r]
        elif op == "dup_row" and rows:
            rows.insert(draw(st.integers(0, len(rows))), list(rows[r]))
        elif op == "add_col":
            name = draw(st.sampled_from(["irradiance", "gain", "time", "lat", "file", "exposure_ms"]) | CELLS)
            rows = [x + [name if k == 0 else draw(CELLS)] for k, x in enumerate(rows)]
        elif op == "header" and rows and c < len(rows[0]):
            rows[0][c] = draw(st.sampled_from(["File", " file ", "exposure", "", "\ufefffile"]) | CELLS)
        elif op == "ragged" and rows:
            rows[r] = rows[r][:c] if draw(st.booleans()) else rows[r] + [draw(CELLS)]
    out = io.StringIO()
    csv.writer(out, lineterminator=draw(st.sampled_from(["\n", "\r\n", "\r"]))).writerows(rows)
    data = draw(mutated_text(out.getvalue())).encode(draw(st.sampled_from(["utf-8", "utf-8-sig"])))
    op = draw(st.sampled_from(["none", "none", "nul", "latin1", "truncate"]))
    i = draw(st.integers(0, len(data)))
    if op == "nul":
        data = data[:i] + b"\x00" + data[i:]
    elif op == "latin1":
        data = data[:i] + b"\xff\xfe" + data[i:]
    elif op == "truncate":
        data = data[:i]
    return data


@pytest.fixture(scope="module")
def frame_folders(synth, tmp_path_factory) -> dict[str, tuple[Path, str]]:
    """A copy of the small session's flight and response folders' frames (symbolic links) with
    their frames.csv text, by name."""
    out = {}
    for name, src in (("flight", synth / "flights" / "field"), ("response", synth / "response")):
        d = tmp_path_factory.mktemp(f"fuzz_{name}")
        for f in src.glob("*.tif"):
            (d / f.name).symlink_to(f)
        out[name] = (d, (src / "frames.csv").read_text())
    return out


def check_frame_table(folder: Path, data: bytes) -> None:
    (folder / "frames.csv").write_bytes(data)
    names = ("frames.csv", str(folder))
    recs = read_or_error(lambda: read_frame_table(folder), *names)
    reported: list[tuple[str, MscalError]] = []
    lenient = read_or_error(lambda: read_frame_table(folder, on_frame_error=lambda n, e: reported.append((n, e))),
                            *names)
    for name, exc in reported:
        assert_clean_error(exc, "frames.csv", name)
    for rec in (recs or []) + (lenient or []):
        assert rec.path.parent == folder and rec.path.is_file(), rec.path
        assert finite(rec.exposure_ms, rec.gain) and rec.exposure_ms > 0 and rec.gain > 0
        assert rec.irradiance is None or (finite(rec.irradiance) and rec.irradiance > 0)
        assert rec.lat is None or -90 <= rec.lat <= 90
        assert rec.lon is None or -180 <= rec.lon <= 180
        assert rec.alt_m is None or finite(rec.alt_m)
        if rec.time:
            time_ns(rec.time)  # the datacube's time coordinate takes it


@pytest.mark.parametrize("which", ["flight", "response"])
def test_frames_csv_fuzz(frame_folders, which, fuzz_settings):
    folder, seed = frame_folders[which]
    check_frame_table(folder, seed.encode())
    assert len(read_frame_table(folder)) >= 3  # the seed is valid

    @settings(fuzz_settings)
    @given(data=csv_bytes([seed]))
    def fuzz(data):
        check_frame_table(folder, data)

    fuzz()


# --------------------------------------------------------------------------- catalog YAML

CATALOG_SEEDS = [(p.parent.name, p.stem, yaml.safe_load(p.read_text(encoding="utf-8")))
                 for p in sorted(CATALOG_ROOT.glob("*/*.yaml"))]
LOADERS = {"cameras": load_camera, "targets": load_target, "indices": load_index}


@st.composite
def catalog_files(draw):
    kind, stem, doc = draw(st.sampled_from(CATALOG_SEEDS))
    text = yaml.safe_dump(draw(mutated_tree(doc)), sort_keys=False, allow_unicode=True)
    return kind, stem, draw(mutated_text(text))


def check_catalog(root: Path, kind: str, stem: str, text: str) -> None:
    path = root / kind / f"{stem}.yaml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text, encoding="utf-8")
    old = os.environ.get("MSCAL_CATALOG_PATH")
    os.environ["MSCAL_CATALOG_PATH"] = str(root)
    clear_cache()
    try:
        entry = read_or_error(lambda: LOADERS[kind](stem), str(path))
    finally:
        path.unlink()
        clear_cache()
        if old is None:
            del os.environ["MSCAL_CATALOG_PATH"]
        else:
            os.environ["MSCAL_CATALOG_PATH"] = old
    if isinstance(entry, Camera):
        assert 1 <= entry.bit_depth <= 16 and entry.n_bands >= 1
        assert np.all(np.isfinite(entry.wavelengths)) and np.all(entry.wavelengths > 0)
        assert entry.sensor is None or min(entry.sensor) > 0
        assert all(finite(v) for v in entry.index_bands.values())
    elif isinstance(entry, Target):
        rho = entry.reflectance.at(np.array([350.0, 550.0, 1000.0]))
        assert np.all(np.isfinite(rho)) and np.all((rho > 0) & (rho <= 1))
    elif isinstance(entry, Index):
        assert entry.valid_range is None or (finite(*entry.valid_range) and entry.valid_range[0] < entry.valid_range[1])


def test_catalog_yaml_fuzz(fuzz_settings, tmp_path):
    for kind, stem, doc in CATALOG_SEEDS:  # the seeds are valid
        check_catalog(tmp_path, kind, stem, yaml.safe_dump(doc))

    @settings(fuzz_settings)
    @given(f=catalog_files())
    def fuzz(f):
        check_catalog(tmp_path, *f)

    fuzz()


# --------------------------------------------------------------------------- XMP packets

XMP_VALUES = st.one_of(
    st.sampled_from(["", " ", "nan", "NaN", "inf", "-inf", "-1", "0", "1e999", "1e308", "-1e308", "5e-324",
                     "1,2", "1, 2", "1 2 3", "1;2", "a", "１２３", "1_000", "0x10", " 7 ", "9" * 400,
                     "2020-02-04;1,2,3", "2020-02-04;a,b,c,d,e,f,g,h,i", "840(+/-26)nm", "1.2.3nm",
                     "...nm", ".(+/-.)nm", "LWIR", "Panchro", "Garbage", "Blue", "NIR", "AAAA", "AA==",
                     "1,2,3,4,5,6,7,8,9", "0,0,0,0", "-5,-5,10,10", "1e5,1e5,1,1", "<", "&amp;", "]]>"]),
    st.floats().map(repr), st.integers().map(str), st.text(max_size=12),
    st.lists(st.floats(allow_nan=False, allow_infinity=False, width=32).map(repr), min_size=1, max_size=12)
    .map(", ".join),
)
OTHER_URIS = ["http://pix4d.com/camera/1.0/", "http://pix4d.com/camera/1.0", "http://pix4d.com/1.0",
              "http://micasense.com/MicaSense/1.0/", "http://www.dji.com/drone-dji/1.0/", "http://example.com/x/"]


def _props(root: ET.Element) -> list[tuple[ET.Element, str, ET.Element | None]]:
    """Every property: (its rdf:Description, its qualified name, its element or None for an
    attribute)."""
    out = []
    for desc in root.iter(f"{{{RDF_NS}}}Description"):
        out += [(desc, k, None) for k in desc.attrib if not k.startswith(f"{{{RDF_NS}}}")]
        out += [(desc, c.tag, c) for c in desc]
    return out


NUMBER_TOKEN = re.compile(r"[-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?")
NASTY_NUMBERS = ["nan", "inf", "-inf", "-1", "0", "-0", "1e999", "1e308", "5e-324", "9" * 400, "1.2.3", ".", "-",
                 "1e", "0x1F", "１２", "1_0", "2**8"]


@st.composite
def perturbed(draw, text: str) -> str:
    """``text`` changed a little: a number in it replaced, a separator or letter inserted, a
    character deleted, an item appended, or cut short."""
    op = draw(st.sampled_from(["number", "number", "insert", "delete", "append", "cut"]))
    i = draw(st.integers(0, len(text)))
    numbers = list(NUMBER_TOKEN.finditer(text))
    if op == "number" and numbers:
        m = draw(st.sampled_from(numbers))
        return text[: m.start()] + draw(st.sampled_from(NASTY_NUMBERS)) + text[m.end():]
    if op == "insert":
        return text[:i] + draw(st.sampled_from(list(".,;- a()+/e") + ["\n", "  "])) + text[i:]
    if op == "delete" and text:
        return text[:i] + text[i + 1:]
    if op == "append":
        return text + draw(st.sampled_from([",1", ", 2.5", " 3", ";4", ",", ",nan"]))
    return text[:i]


def _set(desc: ET.Element, name: str, elem: ET.Element | None, value: str) -> None:
    if elem is None:
        desc.set(name, value)
    else:
        for c in list(elem):
            elem.remove(c)
        elem.text = value


@st.composite
def xmp_packets(draw, seeds: list[str]) -> str:
    text = draw(st.sampled_from(seeds))
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>") + len("</x:xmpmeta>")
    root = ET.fromstring(text[start:end])
    for _ in range(draw(st.integers(1, 4))):
        props = _props(root)
        if not props:
            break
        desc, name, elem = draw(st.sampled_from(props))
        current = desc.get(name) if elem is None else (elem.text or "")
        op = draw(st.sampled_from(["value", "perturb", "perturb", "perturb", "delete", "to_element", "to_list",
                                   "flatten", "namespace", "duplicate"]))
        if op == "value":
            _set(desc, name, elem, draw(XMP_VALUES))
        elif op == "perturb":
            lis = [] if elem is None else list(elem.iter(f"{{{RDF_NS}}}li"))
            if lis:  # one item of an rdf list
                li = draw(st.sampled_from(lis))
                li.text = draw(perturbed(li.text or ""))
            else:
                _set(desc, name, elem, draw(perturbed(current)))
        elif op == "delete":
            desc.attrib.pop(name, None) if elem is None else desc.remove(elem)
        elif op == "to_element" and elem is None:
            del desc.attrib[name]
            ET.SubElement(desc, name).text = current
        elif op == "to_list":  # text -> rdf:Seq/Bag/Alt of its items (or of the one text)
            items = current.replace(",", " ").split() if draw(st.booleans()) else [current]
            if elem is None:
                del desc.attrib[name]
                elem = ET.SubElement(desc, name)
            _set(desc, name, elem, "")
            container = ET.SubElement(elem, f"{{{RDF_NS}}}{draw(st.sampled_from(['Seq', 'Bag', 'Alt']))}")
            for item in items:
                ET.SubElement(container, f"{{{RDF_NS}}}li").text = item
        elif op == "flatten" and elem is not None:  # rdf list -> one comma or space separated text
            items = [(li.text or "") for li in elem.iter(f"{{{RDF_NS}}}li")]
            _set(desc, name, elem, draw(st.sampled_from([",", ", ", " "])).join(items))
        elif op == "namespace":
            local = name.partition("}")[2]
            new = f"{{{draw(st.sampled_from(OTHER_URIS))}}}{local}"
            if elem is None:
                desc.set(new, desc.attrib.pop(name))
            else:
                elem.tag = new
        elif op == "duplicate" and elem is not None:
            desc.append(copy.deepcopy(elem))
    packet = ET.tostring(root, encoding="unicode")  # other prefixes: ns0, ns1, ...
    meta = re.search(r'xmlns:(\w+)="adobe:ns:meta/"', packet)
    if meta and draw(st.booleans()):  # the usual x: for the packet's root, half of the time
        packet = re.sub(rf"\b{meta[1]}:", "x:", packet)
    packet = '<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?>' + packet + '<?xpacket end="w"?>'
    return draw(mutated_text(packet)) if draw(st.booleans()) else packet


def _tiff(path: Path) -> tuple[dict, tuple[int, int], int]:
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        return ({t.code: t.value for t in page.tags.values()}, (int(page.imagelength), int(page.imagewidth)),
                int(page.bitspersample))


@pytest.fixture(scope="module")
def xmp_sources() -> dict:
    """Per camera: the tags of a real band file and the packets to start from."""
    mica = DATA / "micasense-rededge" / "IMG_0000_1.tif"
    seq = DATA / "parrot-sequoia" / "IMG_180413_080658_0000_GRE.TIF"
    if not (mica.is_file() and seq.is_file()):
        pytest.skip("real camera files of ../shared/data are not here")
    out = {}
    for name, path, packets in (("micasense", mica, None), ("sequoia", seq, None),
                                ("dji", mica, [dji_xmp(1, "abc"), dji_xmp(5, "abc", band_freq=True)])):
        tags, shape, bits = _tiff(path)
        if packets is None:
            packets = [tags[700].decode("utf-8") if isinstance(tags[700], bytes) else tags[700]]
        out[name] = (path, tags, shape, bits, tiff_tags(path), packets)
    return out


def check_tiff_meta(path: Path, tags: dict, shape, bits: int, itags: dict, packet: str) -> None:
    data = packet.encode("utf-8")
    meta = read_or_error(lambda: meta_from_tags(path, {**tags, 700: data}, shape, bits), path.name)
    if meta is not None:
        assert meta.shape == shape
        if meta.reflectance_band:
            lo, hi = 300.0, 1100.0
            assert lo <= meta.wavelength_nm <= hi and 0 < meta.exposure_s <= 1
            assert finite(meta.gain, meta.black_level) and meta.gain > 0
            v = read_or_error(lambda: factory_vignetting(meta), path.name)
            assert v is None or v.shape == shape
        meta.features()
    intr = read_or_error(lambda: intrinsics_from_tags({**itags, 700: data}, path), path.name)
    if intr is not None:
        assert finite(intr.fx, intr.fy, intr.cx, intr.cy, *intr.dist)
    x = read_or_error(lambda: Xmp.parse(data, path), path.name)
    if x is not None:
        for tag in ("CentralWavelength", "VignettingPolynomial", "Irradiance"):
            read_or_error(lambda: x.numbers(tag), path.name)


@pytest.mark.parametrize("camera", ["micasense", "sequoia", "dji"])
def test_xmp_tiff_fuzz(xmp_sources, camera, fuzz_settings):
    path, tags, shape, bits, itags, packets = xmp_sources[camera]
    for p in packets:  # the seeds are read
        assert meta_from_tags(path, {**tags, 700: p.encode()}, shape, bits).wavelength_nm > 0

    @settings(fuzz_settings)
    @given(packet=xmp_packets(packets))
    def fuzz(packet):
        check_tiff_meta(path, tags, shape, bits, itags, packet)

    fuzz()


def with_xmp(jpeg: bytes, packet: bytes) -> bytes:
    """``jpeg`` with its XMP APP1 segment's packet replaced (the other segments kept)."""
    header = b"http://ns.adobe.com/xap/1.0/\x00"
    out, i = [jpeg[:2]], 2
    for seg in jpeg_segments(jpeg):
        i += len(seg)
        if seg[1] == 0xE1 and seg[4:].startswith(header):
            body = header + packet[:65000]
            seg = seg[:2] + (len(body) + 2).to_bytes(2, "big") + body
        out.append(seg)
    return b"".join(out) + jpeg[i:]


def test_xmp_jpeg_fuzz(fuzz_settings, tmp_path):
    src = DATA / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if not src.is_file():
        pytest.skip("real camera files of ../shared/data are not here")
    jpeg = src.read_bytes()
    packet = jpeg_xmp_packet(jpeg)
    path = tmp_path / "IMG_00006.jpg"
    path.write_bytes(with_xmp(jpeg, packet))
    assert len(read_file_metas(path)) >= 2  # the seed (rebuilt) is read

    @settings(fuzz_settings)
    @given(packet=xmp_packets([packet.decode("utf-8")]))
    def fuzz(packet):
        path.write_bytes(with_xmp(jpeg, packet.encode("utf-8")))
        metas = read_or_error(lambda: read_file_metas(path), path.name) or []
        for m in metas:
            assert 300 <= m.wavelength_nm <= 1100 and 0 < m.exposure_s <= 1 and m.gain > 0

    fuzz()


# --------------------------------------------------------------------------- the command line


def snapshot(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (the files that were there before a run)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def run_cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    e = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-m", "pipeline.run.cli", *args], capture_output=True, text=True,
                          env=e, timeout=600)


def assert_cli_refused(res: subprocess.CompletedProcess, name: str) -> None:
    assert res.returncode == 2, (res.returncode, res.stderr[-3000:])
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mscal: error: ") and name in lines[0], res.stderr


def unchanged(before: dict[str, str], folder: Path) -> None:
    after = snapshot(folder)
    assert {k: after.get(k) for k in before} == before  # nothing written before is lost or changed


@pytest.fixture(scope="module")
def cli_session(small, tmp_path_factory) -> tuple[Path, Path]:
    """A copy of the small session (frames as symbolic links) and a copy of its store."""
    root = tmp_path_factory.mktemp("fuzz_cli")
    session = root / "session"
    for src in small[0].rglob("*"):
        dst = session / src.relative_to(small[0])
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        elif src.suffix == ".tif":
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(src)
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
    store = root / "calib.zarr"
    shutil.copytree(small[1], store)
    return session, store


# Two examples each, not shrunk (every example is a process start); the first that the reader
# rejects is the one run.
E2E = settings(max_examples=2, derandomize=True, database=None, deadline=None,
               phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))


def test_cli_fuzzed_session_yaml(cli_session, session_seeds, tmp_path):
    """``mscal calibrate`` on a broken session.yaml over an existing store: one line, exit 2,
    the store untouched."""
    session, store = cli_session
    good = (session / "session.yaml").read_text()
    before = snapshot(store)

    @E2E
    @given(text=yaml_texts(session_seeds))
    def fuzz(text):
        probe = tmp_path / "probe"
        probe.mkdir(exist_ok=True)
        (probe / "session.yaml").write_text(text, encoding="utf-8")
        try:
            load_session(probe)
        except MscalError:
            pass
        else:
            assume(False)  # a valid session: a minute of fitting, not what this test is about
        (session / "session.yaml").write_text(text, encoding="utf-8")
        try:
            res = run_cli("calibrate", str(session), "-o", str(store))
        finally:
            (session / "session.yaml").write_text(good)
        assert_cli_refused(res, "session.yaml")
        unchanged(before, store)

    fuzz()


def test_cli_fuzzed_frames_csv(cli_session, frame_folders, tmp_path):
    """``mscal calibrate`` with a broken response/frames.csv, and ``mscal apply`` with a flight
    frames.csv that cannot be read as a table: one line, exit 2, existing outputs untouched."""
    session, store = cli_session
    out = tmp_path / "out"
    (out / "flights" / "earlier").mkdir(parents=True)
    (out / "notes.txt").write_text("the user's notes\n")
    (out / "flights" / "earlier" / "reflectance.bin").write_bytes(bytes(range(256)))
    before_store, before_out = snapshot(store), snapshot(out)
    folder, seed = frame_folders["response"]
    target = session / "response" / "frames.csv"
    good = target.read_bytes()

    @E2E
    @given(data=csv_bytes([seed]))
    def calibrate(data):
        (folder / "frames.csv").write_bytes(data)
        try:
            read_frame_table(folder)
        except MscalError:
            pass
        else:
            assume(False)
        target.write_bytes(data)
        try:
            res = run_cli("calibrate", str(session), "-o", str(store))
        finally:
            target.write_bytes(good)
        assert_cli_refused(res, "frames.csv")
        unchanged(before_store, store)

    calibrate()
    flight = session / "flights" / "field"
    good = (flight / "frames.csv").read_bytes()
    for data in (good.replace(b"exposure_ms", b"exposure"), b"\xff\xfe" + good):  # no exposure column; not UTF-8
        (flight / "frames.csv").write_bytes(data)
        try:
            res = run_cli("apply", str(flight), "--calibration", str(store), "-o", str(out))
        finally:
            (flight / "frames.csv").write_bytes(good)
        assert_cli_refused(res, "frames.csv")
        unchanged(before_out, out)
        unchanged(before_store, store)


def test_cli_fuzzed_camera_catalog(cli_session, tmp_path):
    """``mscal calibrate`` with a broken camera entry (MSCAL_CATALOG_PATH first): one line
    naming the catalog file, exit 2, the store untouched."""
    session, store = cli_session
    name = yaml.safe_load((session / "session.yaml").read_text())["camera"]
    doc = yaml.safe_load((CATALOG_ROOT / "cameras" / f"{name}.yaml").read_text())
    before = snapshot(store)
    cat = tmp_path / "catalogs"
    (cat / "cameras").mkdir(parents=True)
    path = cat / "cameras" / f"{name}.yaml"

    @E2E
    @given(doc=mutated_tree(doc))
    def fuzz(doc):
        text = yaml.safe_dump(doc)
        assume(text != yaml.safe_dump(yaml.safe_load((CATALOG_ROOT / "cameras" / f"{name}.yaml").read_text())))
        path.write_text(text)
        os.environ["MSCAL_CATALOG_PATH"] = str(cat)
        clear_cache()
        try:
            load_camera(name)
        except MscalError:
            pass
        else:
            assume(False)
        finally:
            del os.environ["MSCAL_CATALOG_PATH"]
            clear_cache()
        res = run_cli("calibrate", str(session), "-o", str(store), env={"MSCAL_CATALOG_PATH": str(cat)})
        assert_cli_refused(res, f"{name}.yaml")
        unchanged(before, store)

    fuzz()
