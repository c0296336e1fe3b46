"""A DJI P4 Multispectral card as the drone writes it: each capture's RGB camera JPEG
(``DJI_XXX0.JPG``, EXIF with a thumbnail) beside its five band files (tests/camera_files.py
``dji_card``). The JPEG's EXIF is read in every form a camera writes its tags (thumbnail bytes,
maker notes, undefined bytes, zero denominators, empty fields); identification ignores the RGB
images; the card's captures are all processed, the RGB images named as skipped."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import exifread
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mscal_core.errors import FrameError, MscalError
from pipeline.apply.captures import find_captures
from pipeline.apply.factory import FactoryOptions, apply_factory
from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.cameras.parrot import sibling_position
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.exif import jpeg_exif
from pipeline.ingest.gps import exif_position
from pipeline.ingest.grouping import COMPANION_IMAGES
from pipeline.ingest.identify import describe_folders, identify_camera, probe_folder
from pipeline.ingest.intrinsics import intrinsics_from_file
from pipeline.ingest.photo_tags import read_optics
from pipeline.ingest.session import exif_record
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import require_data

RGB_REASON = COMPANION_IMAGES["dji-p4-multispectral"][1]


def _exifread(path: Path) -> dict:
    with path.open("rb") as f:
        return exifread.process_file(f, details=False)


# --------------------------------------------------------------------------- the RGB JPEG


def test_rgb_jpeg_exif_with_thumbnail_and_maker_note(tmp_path) -> None:
    """The FC6360's JPEG: exifread gives its thumbnail as bytes (``JPEGThumbnail``); the
    reader takes Make, Model, time and position and leaves the thumbnail out."""
    path = cf.dji_rgb_jpeg(tmp_path / "DJI_0010.JPG")
    raw = _exifread(path)
    assert isinstance(raw["JPEGThumbnail"], bytes) and raw["JPEGThumbnail"][:2] == b"\xff\xd8"
    with path.open("rb") as f:  # the maker note is there (exifread leaves it out without details)
        assert "EXIF MakerNote" in exifread.process_file(f, details=True)
    exif, gps = jpeg_exif(path.read_bytes())
    assert exif["Make"] == "DJI" and exif["Model"] == "FC6360" and exif["DateTimeOriginal"] == "2024:05:20 10:12:34"
    assert exif["ExifImageWidth"] == 64 and exif["ExifImageLength"] == 48 and exif["ExifVersion"] == b"0230"
    assert not any(k.endswith("Thumbnail") or k == "MakerNote" for k in exif)
    lat, lon, alt = exif_position(gps)
    assert (lat, lon, alt) == pytest.approx((cf.DJI_RGB["lat"], cf.DJI_RGB["lon"], cf.DJI_RGB["alt_m"]), abs=1e-6)
    # not a band file: a clean error naming the file, not a crash
    with pytest.raises(FrameError, match="DJI_0010.JPG"):
        read_file_metas(path)
    # the same JPEG as a Sequoia-style <capture>_RGB.JPG positions its capture's band files
    shutil.copyfile(path, tmp_path / "IMG_0000_RGB.JPG")
    assert sibling_position(tmp_path, "IMG_0000") == pytest.approx((47.3769, 8.5417, 512.25), abs=1e-6)


def test_zero_denominators_and_empty_fields_are_left_out(tmp_path) -> None:
    """``0/0`` (firmware's "unknown"), a zero denominator in GPS, an empty SHORT and an empty
    text are no values: left out, so no position instead of a NaN one."""
    path = cf.dji_rgb_jpeg(tmp_path / "DJI_0010.JPG", exif_extra=[
        (0x829D, "RATIONAL", (0, 0)), (0x829A, "RATIONAL", (1, 0)), (0x8827, "SHORT", []),
        (0x9290, "ASCII", ""), (0xA002, "LONG", []), (0x9286, "UNDEFINED", b"ASCII\x00\x00\x00hello")])
    exif, _ = jpeg_exif(path.read_bytes())
    assert {"FNumber", "ExposureTime", "ISOSpeedRatings", "SubsecTime", "ExifImageWidth"}.isdisjoint(exif)
    assert exif["Make"] == "DJI" and exif["ExifImageLength"] == 48
    # a GPS latitude with a zero denominator: the tag is dropped, the position unknown
    app1 = cf.exif_app1([(0x010F, "ASCII", "DJI")], [(0x9003, "ASCII", "2024:05:20 10:12:34")],
                        [(0x0001, "ASCII", "N"), (0x0002, "RATIONAL", [(47, 1), (22, 0), (0, 0)]),
                         (0x0003, "ASCII", "E"), (0x0004, "RATIONAL", [(8, 1), (32, 1), (3, 1)])])
    _, gps = jpeg_exif(cf.with_app1(cf.encode_jpeg(np.zeros((8, 8, 3), np.uint8)), app1))
    assert "GPSLatitude" not in gps and gps["GPSLongitude"] and exif_position(gps) == (None, None, None)


# forms an EXIF field takes in the wild, for a tag whose proper type is ``kind``
def _forms(kind: str, proper: object) -> st.SearchStrategy:
    return st.one_of(
        st.just((kind, proper)),
        st.sampled_from([("RATIONAL", (0, 0)), ("RATIONAL", (7, 0)), ("RATIONAL", [(1, 1), (0, 0), (5, 1)]),
                         ("SRATIONAL", (-3, 2)), ("SHORT", []), ("LONG", []), ("RATIONAL", []),
                         ("ASCII", ""), ("ASCII", "abc"), ("ASCII", b"\xff\xfe\x80"), ("DOUBLE", 2.5),
                         ("DOUBLE", [1.0, 2.0]), ("SHORT", [1, 2, 3]), ("BYTE", b"\x01"), ("UNDEFINED", b"")]),
        st.tuples(st.just("UNDEFINED"), st.binary(max_size=40)),
        st.tuples(st.just("UNDEFINED"), st.binary(min_size=1000, max_size=1100)),  # exifread: an empty list
        st.tuples(st.just("LONG"), st.integers(0, 2**32 - 1)),
        st.tuples(st.just("RATIONAL"), st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 3))),
    )


_IFD0 = {0x010F: ("ASCII", "DJI"), 0x0110: ("ASCII", "FC6360"), 0x0112: ("SHORT", 1), 0x0131: ("ASCII", "v01.02")}
_EXIF = {0x829A: ("RATIONAL", (1, 1000)), 0x829D: ("RATIONAL", (22, 10)), 0x8827: ("SHORT", 100),
         0x9003: ("ASCII", "2024:05:20 10:12:34"), 0x9291: ("ASCII", "123"), 0xA002: ("LONG", 64),
         0xA003: ("LONG", 48), 0xA431: ("ASCII", "SN1"), 0x920A: ("RATIONAL", (5, 1)),
         0xA20E: ("RATIONAL", (4000, 1)), 0xA20F: ("RATIONAL", (4000, 1)), 0xA210: ("SHORT", 3)}
_GPS = {0x0001: ("ASCII", "N"), 0x0002: ("RATIONAL", [(47, 1), (22, 1), (3, 1)]), 0x0003: ("ASCII", "E"),
        0x0004: ("RATIONAL", [(8, 1), (32, 1), (3, 1)]), 0x0005: ("BYTE", b"\x00"), 0x0006: ("RATIONAL", (500, 1))}
# XMP of the RGB camera (no band: not a band file) or of a three-band JPEG camera (Sentera
# Double 4K: its EXIF ExposureTime and ISO are the radiance's), so both readers' paths run
_SENTERA_XMP = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
                '<rdf:Description xmlns:Camera="http://pix4d.com/camera/1.0/">'
                + "".join(f"<Camera:{t}>{cf.seq(*v)}</Camera:{t}>" for t, v in (
                    ("BandName", ("Red", "Green", "NIR")), ("CentralWavelength", (650, 550, 850)),
                    ("ColorTransform", (1, 0, 0, 0, 1, 0, 0, 0, 1))))
                + "</rdf:Description></rdf:RDF></x:xmpmeta>")


@st.composite
def exif_jpegs(draw) -> tuple[bytes, str]:
    """A small JPEG whose EXIF tags mscal reads each take a drawn form, with or without a
    thumbnail (a JPEG, or bytes that are none), a maker note of random bytes, and the XMP of
    the DJI RGB camera or of a Sentera-like three-band camera."""
    def ifd(table: dict) -> list:
        out = []
        for tag, (kind, proper) in table.items():
            choice = draw(st.sampled_from(["proper", "proper", "drawn", "absent"]))
            if choice == "absent":
                continue
            out.append((tag, *((kind, proper) if choice == "proper" else draw(_forms(kind, proper)))))
        return out

    ifd0 = ifd(_IFD0)
    exif = ifd(_EXIF)
    if draw(st.booleans()):
        exif.append((0x927C, "UNDEFINED", draw(st.binary(min_size=1, max_size=3000))))
    thumbnail = draw(st.sampled_from([None, cf.encode_jpeg(np.full((6, 8, 3), 90, np.uint8))]) | st.binary(max_size=64))
    app1 = cf.exif_app1(ifd0, exif, ifd(_GPS), thumbnail)
    sentera = draw(st.booleans())
    packet = _SENTERA_XMP if sentera else cf.dji_rgb_xmp()
    img = cf.encode_jpeg(np.full((48, 64, 3), 120, np.uint8))
    return cf.with_app1(img, app1, cf.xmp_app1(packet)), "IMG_0000_RGB.JPG"


def _clean_or_value(read, name: str):
    try:
        return read()
    except Exception as exc:  # the property is about which exceptions
        assert isinstance(exc, MscalError), f"{type(exc).__name__} escaped: {exc!r}"
        assert exc.exit_code == 2 and len(str(exc).splitlines()) == 1 and name in str(exc), exc
        return None


def test_jpeg_exif_fuzz(fuzz_settings, tmp_path) -> None:
    """Every reader of a JPEG's EXIF (band metadata, the sibling position, the lens, a session
    frame's record) returns a value or a clean error naming the file, whatever form each tag
    takes: thumbnails, maker notes, undefined bytes, zero denominators, empty fields, text or
    floats where numbers belong."""
    @settings(fuzz_settings)
    @given(drawn=exif_jpegs())
    def fuzz(drawn):
        data, name = drawn
        path = tmp_path / name
        path.write_bytes(data)
        exif, gps = jpeg_exif(data)
        for value in (*exif.values(), *gps.values()):
            assert value is not None and value != [] and value != ""
            assert not hasattr(value, "values")  # no exifread tag
            for v in value if isinstance(value, list) else [value]:
                assert not (hasattr(v, "den") and v.den == 0)
        assert "JPEGThumbnail" not in exif and "MakerNote" not in exif
        for m in _clean_or_value(lambda: read_file_metas(path), name) or []:
            assert 0 < m.exposure_s <= 1 and m.gain > 0 and 300 <= m.wavelength_nm <= 1100
            assert m.lat is None or (math.isfinite(m.lat) and math.isfinite(m.lon))
            assert m.alt_m is None or math.isfinite(m.alt_m)
        pos = sibling_position(tmp_path, "IMG_0000")
        assert pos is None or all(v is None or math.isfinite(v) for v in pos)
        _clean_or_value(lambda: read_optics(path), name)
        _clean_or_value(lambda: intrinsics_from_file(path), name)
        _clean_or_value(lambda: exif_record(path), name)

    fuzz()


# --------------------------------------------------------------------------- the card


@pytest.fixture(scope="module")
def card(tmp_path_factory) -> Path:
    require_data()
    return cf.dji_card(tmp_path_factory.mktemp("dji") / "card")


def test_card_is_a_p4_multispectral(card) -> None:
    """With the RGB JPEGs (Make DJI, Model FC6360) among the band files, the camera is still
    recognised from the band files; the JPEGs are named, not read."""
    media = card / "DCIM" / "100MEDIA"
    assert sorted(p.name for p in media.iterdir()) == [
        "DJI_0010.JPG", "DJI_0011.TIF", "DJI_0012.TIF", "DJI_0013.TIF", "DJI_0014.TIF", "DJI_0015.TIF",
        "DJI_0020.JPG", "DJI_0021.TIF", "DJI_0022.TIF", "DJI_0023.TIF", "DJI_0024.TIF", "DJI_0025.TIF"]
    assert "JPEGThumbnail" in _exifread(media / "DJI_0010.JPG")
    for folder in (card, media):
        ident = identify_camera(folder)
        assert ident.camera.name == "dji-p4-multispectral", ident.evidence
        assert ident.probe["bands_per_capture"] == 5
    probe = probe_folder(card)
    assert [(p.name, why) for p, why in probe.skipped] == [("DJI_0010.JPG", RGB_REASON), ("DJI_0020.JPG", RGB_REASON)]
    assert probe.unreadable == []
    lines = describe_folders(card)  # mscal cameras CARD
    assert lines[0] == f"{media}:" and "camera: dji-p4-multispectral" in lines[1]
    assert f"  skipped 2 file(s), {RGB_REASON}: DJI_0010.JPG, DJI_0020.JPG" in lines


def test_card_captures_and_what_is_skipped(card, tmp_path) -> None:
    """The card's two captures; each RGB JPEG skipped as the camera's RGB image. A JPEG only
    named like one (no band file of its capture beside it) is skipped as any other file."""
    camera = load_camera("dji-p4-multispectral")
    found = find_captures(card, camera)
    assert [c.name for c in found.captures] == ["001", "002"] and found.quarantined == []
    assert found.skipped == [{"file": f"DCIM/100MEDIA/DJI_00{c}0.JPG", "reason": RGB_REASON} for c in (1, 2)]
    other = tmp_path / "other"
    shutil.copytree(card / "DCIM" / "100MEDIA", other)
    shutil.copyfile(other / "DJI_0010.JPG", other / "DJI_0030.JPG")
    skipped = {s["file"]: s["reason"] for s in find_captures(other, camera).skipped}
    assert skipped["DJI_0010.JPG"] == RGB_REASON and skipped["DJI_0030.JPG"].startswith("not a capture file")


def test_apply_factory_on_the_card(card, tmp_path) -> None:
    """``mscal apply CARD --calibration factory``: both captures processed, the RGB JPEGs in
    run.json ``skipped`` with the reason, nothing quarantined."""
    apply_factory(card, tmp_path / "out", FactoryOptions())
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["camera"] == "dji-p4-multispectral"
    assert run["frames_out"] == 2 and run["frames"] == ["001", "002"] and run["quarantined"] == []
    assert run_value(run, "skipped") == [{"file": f"DCIM/100MEDIA/DJI_00{c}0.JPG", "reason": RGB_REASON} for c in (1, 2)]


def test_band_file_tags_in_odd_forms() -> None:
    """A band file's own tags (tifffile) in the forms firmware writes: a GPS position with a
    zero denominator (no position, a problem naming the tag, not NaN degrees), an EXIF IFD
    tifffile could not follow (its offset, an int), an Orientation of two values."""
    import tifffile

    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    path = cf.band_file("0000", 2)
    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    tags.update({700: cf.dji_xmp(2, "abc").encode(), 271: "DJI", 272: "FC6360", 50714: (4096,)})
    gps = dict(tags[34853])
    gps.update(GPSLatitude=(47, 1, 22, 0, 0, 0), GPSAltitude=(0, 0))
    m = meta_from_tags(path, {**tags, 34853: gps}, (960, 1280), 16)
    assert m.lat is None and m.lon is None and m.alt_m is None and not m.features()["position"]
    assert [(p.tag, p.feature) for p in m.problems] == [("EXIF GPS", "position")]
    gps = dict(tags[34853])
    gps["GPSAltitude"] = (5, 0)  # an altitude that is no number: left out, the position kept
    m = meta_from_tags(path, {**tags, 34853: gps}, (960, 1280), 16)
    assert m.lat is not None and math.isfinite(m.lat) and m.alt_m is None and m.problems == ()
    m = meta_from_tags(path, {**tags, 34665: 1234, 274: (3, 3)}, (960, 1280), 16)
    assert m.radiometry == "dji" and m.orientation == 1 and m.exposure_s == pytest.approx(472.5e-6)
