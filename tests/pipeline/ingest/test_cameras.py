"""XMP read the way cameras write it (pipeline.ingest.xmp), cameras recognised from
their files (pipeline.ingest.identify), the camera catalog entries, and ``mscal cameras``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mscal_core.errors import CatalogError, InputError
from mscal_core.factory import upright
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import read_capture_meta, read_file_metas
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.meta import no_reflectance_reason
from pipeline.ingest.xmp import TagError, Xmp, jpeg_xmp_packet, parse_numbers
from pipeline.run.cli import main
from tests import camera_files as cf
from tests.micasense_data import require_data

DATA_ROOT = Path(__file__).parents[3].parent / "shared" / "data"
RDF = 'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"'


def _packet(body: str, ns: str = 'xmlns:C="http://pix4d.com/camera/1.0"') -> str:
    return f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF {RDF}><rdf:Description {ns} {body}</rdf:Description></rdf:RDF></x:xmpmeta>'


def test_every_serialisation_form_reads_the_same_numbers() -> None:
    forms = {
        "attribute": _packet('C:ReflectArea="622,371,574,368">'),
        "element": _packet("><C:ReflectArea>622, 371, 574, 368</C:ReflectArea>"),
        "seq": _packet("><C:ReflectArea><rdf:Seq><rdf:li>622</rdf:li><rdf:li>371</rdf:li><rdf:li>574</rdf:li>"
                       "<rdf:li>368</rdf:li></rdf:Seq></C:ReflectArea>"),
        "bag": _packet("><C:ReflectArea><rdf:Bag><rdf:li>622 371</rdf:li><rdf:li>574 368</rdf:li></rdf:Bag></C:ReflectArea>"),
        "one li": _packet("><C:ReflectArea><rdf:Seq><rdf:li>622,371,574,368</rdf:li></rdf:Seq></C:ReflectArea>"),
        "alt": _packet("><C:ReflectArea><rdf:Alt><rdf:li>622;371;574;368</rdf:li></rdf:Alt></C:ReflectArea>"),
    }
    for form, packet in forms.items():
        assert Xmp.parse(packet, "f.tif").numbers("ReflectArea", allowed=(4, 8)) == (622, 371, 574, 368), form


@pytest.mark.parametrize("uri", ["http://pix4d.com/camera/1.0", "http://pix4d.com/camera/1.0/", "http://pix4d.com/1.0",
                                 "http://pix4d.com/1.0/"])
def test_namespace_by_uri_not_prefix(uri: str) -> None:
    packet = _packet('Pix:BandName="NIR" Other:BandName="no">', f'xmlns:Pix="{uri}" xmlns:Other="http://example.com/x/"')
    assert Xmp.parse(packet, "f.tif").text("BandName") == "NIR"
    wrong = _packet('Camera:BandName="NIR">', 'xmlns:Camera="http://example.com/camera/1.0/"')
    assert Xmp.parse(wrong, "f.tif").text("BandName") is None  # the prefix alone means nothing


def test_unreadable_value_names_tag_value_and_file() -> None:
    x = Xmp.parse(_packet("><C:VignettingCenter><rdf:Seq><rdf:li>676.7</rdf:li><rdf:li>nan</rdf:li></rdf:Seq>"
                          "</C:VignettingCenter>"), "/d/IMG_1.tif")
    with pytest.raises(TagError) as err:
        x.numbers("VignettingCenter", count=2)
    assert "/d/IMG_1.tif" in str(err.value) and "VignettingCenter" in str(err.value) and "676.7, nan" in str(err.value)
    assert parse_numbers("1e-4, 2.5 3") == (1e-4, 2.5, 3.0) and parse_numbers("1,x") is None


def test_jpeg_xmp_segment() -> None:
    path = DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if not path.is_file():
        pytest.skip("no Sentera sample")
    x = Xmp.parse(jpeg_xmp_packet(path.read_bytes()), path)
    assert x.texts("BandName") == ["RedEdge", "Garbage", "NIR"] and x.text("RigName") == "21022-01"
    assert x.numbers("ColorTransform", count=9)[:3] == (2.7, 0.0, -2.581)
    assert x.number("Clear", ("ILS",)) == 5644


# --------------------------------------------------------------------------- readers of real files


def test_no_reflectance_reason_names_the_missing_tag(tmp_path) -> None:
    require_data()
    path = cf.rewrite(cf.band_file("0000", 1), tmp_path / "IMG_0000_1.tif",
                      lambda x: cf.drop_element(cf.drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance"))
    assert no_reflectance_reason(read_capture_meta(path)) == (
        "no sun-sensor reading: no XMP Camera:Irradiance (DLS 1) or DLS:HorizontalIrradiance (DLS 2) in the file")
    sentera = DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if sentera.is_file():  # a reading, but no published conversion
        assert "no published conversion" in no_reflectance_reason(read_file_metas(sentera)[0])


# --------------------------------------------------------------------------- identification


def test_identify_real_folders() -> None:
    cases = {"micasense-rededge": "micasense-rededge", "parrot-sequoia": "parrot-sequoia",
             "sentera-d4k/NDRE": "sentera-d4k-ndre", "sentera-d4k/nRGB": "sentera-d4k-nrgb"}
    for folder, name in cases.items():
        if not (DATA_ROOT / folder).is_dir():
            pytest.skip(f"no {folder} sample")
        ident = identify_camera(DATA_ROOT / folder)
        assert ident.camera.name == name, folder
    ident = identify_camera(DATA_ROOT / "micasense-rededge")
    assert "Model 'RedEdge'" in ident.evidence and "5 band(s) per capture" in ident.evidence


def test_dual_is_not_taken_for_a_rededge_from_one_file(tmp_path) -> None:
    """The first file of a Dual capture (IMG_0000_1.tif, Blue) is exactly a RedEdge-MX's; the
    ten band files under one CaptureId decide."""
    require_data()
    folder = cf.rededge_mx_dual(tmp_path / "dual")
    assert identify_camera(folder).camera.name == "micasense-rededge-mx-dual"
    five = tmp_path / "five"
    five.mkdir()
    for p in folder.glob("IMG_*_[1-5].tif"):
        (five / p.name).write_bytes(p.read_bytes())
    assert identify_camera(five).camera.name == "micasense-rededge-mx"  # Model RedEdge-MX, 5 bands
    assert identify_camera(five, "micasense-rededge").camera.name == "micasense-rededge"  # --camera overrides


def test_altum_family_by_model_and_band_count(tmp_path) -> None:
    require_data()
    from pipeline.ingest.grouping import group_captures

    ident = identify_camera(cf.altum(tmp_path / "altum"))
    assert ident.camera.name == "micasense-altum" and "6 band(s) per capture" in ident.evidence
    caps, problems = group_captures(tmp_path / "altum", ident.camera)
    assert problems == [] and [s["band"] for s in caps[0].skipped] == ["LWIR"] and len(caps[0].metas) == 5
    assert identify_camera(cf.rededge_p(tmp_path / "apt", altum_pt=True)).camera.name == "micasense-altum-pt"
    assert identify_camera(cf.rededge_p(tmp_path / "p")).camera.name == "micasense-rededge-p"


def test_unknown_camera_is_named(tmp_path) -> None:
    require_data()
    cf.rewrite(cf.band_file("0000", 1), tmp_path / "IMG_0000_1.tif", make="Acme", model="Spectro 9")
    with pytest.raises(InputError, match="no catalog camera matches Make 'Acme', Model 'Spectro 9'"):
        identify_camera(tmp_path)


# --------------------------------------------------------------------------- catalog and CLI


def test_every_factory_camera_cites_its_sources_and_validates() -> None:
    names = catalog.list_entries("cameras")
    factory = [catalog.load_camera(n) for n in names if catalog.load_camera(n).factory_model]
    assert {c.name for c in factory} >= {
        "micasense-rededge", "micasense-rededge-m", "micasense-rededge-mx", "micasense-rededge-mx-dual",
        "micasense-rededge-p", "micasense-altum", "micasense-altum-pt", "parrot-sequoia", "dji-p4-multispectral",
        "dji-mavic-3m", "sentera-d4k-ndre", "sentera-d4k-nrgb"}
    for cam in factory:
        assert cam.sources and cam.identify is not None
    dual = catalog.load_camera("micasense-rededge-mx-dual")
    assert dual.n_bands == 10 and dual.identify.bands_per_capture == 10
    assert [s.name for s in catalog.load_camera("micasense-altum-pt").skip_bands] == ["Panchro", "LWIR"]


def test_catalog_refuses_a_factory_camera_without_sources(tmp_path) -> None:
    data = {"name": "x", "description": "x", "bit_depth": 12, "layout": {"kind": "file_per_band",
            "capture_pattern": r"^(?P<capture>.+)_(?P<band>[0-9]+)\.tif$"},
            "bands": [{"name": "NIR", "wavelength_nm": 840, "file_suffix": "1"}], "factory_model": "micasense",
            "identify": {"make": "X"}}
    with pytest.raises(CatalogError, match="must cite the manufacturer's documents"):
        catalog.parse_camera(data, tmp_path / "x.yaml")
    data["factory_model"] = "acme"
    with pytest.raises(CatalogError, match="factory_model must be one of"):
        catalog.parse_camera(data, tmp_path / "x.yaml")


def test_mscal_cameras_on_the_shared_data(capsys) -> None:
    if not DATA_ROOT.is_dir():
        pytest.skip("no shared data")
    assert main(["cameras", str(DATA_ROOT)]) == 0
    out = capsys.readouterr().out
    for name in ("micasense-rededge", "parrot-sequoia", "sentera-d4k-ndre", "sentera-d4k-nrgb"):
        assert f"camera: {name} " in out
    assert "captures: 2 complete, 0 quarantined" in out and "captures: 1 complete, 0 quarantined" in out
    assert "stored with EXIF Orientation 3" in out and "sun_sensor_absolute yes" in out


def test_upright() -> None:
    a = np.arange(6).reshape(2, 3)
    assert upright(a, 3).tolist() == [[5, 4, 3], [2, 1, 0]] and upright(a, 1) is a
    with pytest.raises(ValueError, match="90 degree"):
        upright(a, 6)


def test_calibration_and_apply_read_the_same_exposure_time(tmp_path) -> None:
    """A session's band files (captures.band_file_record: reflector captures, frames of mscal
    calibrate) and apply's (camera_meta) give one time: DJI's UTCAtExposure, not the local
    DateTimeOriginal, so a store's reflector times and a flight's are on one clock; a RedEdge
    file without a zone keeps its time as written in both."""
    from pipeline.ingest.captures import band_file_record

    require_data()
    local = cf.dji_p4m(tmp_path / "local")
    path = local / "DJI_0012.TIF"
    path.write_bytes(path.read_bytes().replace(b"2017:10:19 20:40:39", b"2017:10:19 13:40:39"))  # UTC-7
    utc = cf.rewrite(path, tmp_path / "DJI_0012.TIF", lambda x: x.replace(
        "drone-dji:SensorIndex=", 'drone-dji:UTCAtExposure="2017:10:19 20:40:39.200173" drone-dji:SensorIndex='))
    assert band_file_record(path).time == read_capture_meta(path).time == "2017-10-19T13:40:39.200173789"
    assert band_file_record(utc).time == read_capture_meta(utc).time == "2017-10-19T20:40:39.200173Z"
    src = cf.band_file("0000", 1)
    assert band_file_record(src).time == read_capture_meta(src).time == "2017-10-19T20:40:39.200173789"


def test_a_folder_of_two_cameras_is_refused_naming_both(tmp_path) -> None:
    """A Sentera Double 4K card's NDRE/ and nRGB/ folders given as one flight: each complete
    capture names its camera; two cameras in one tree are an input error naming both and their
    folders (before: one sensor applied, the other's captures quarantined as incomplete, exit
    0). Each folder alone, or --camera, still works."""
    src = DATA_ROOT / "sentera-d4k"
    if not src.is_dir():
        pytest.skip("no Sentera sample")
    for sub in ("NDRE", "nRGB"):
        (tmp_path / "card" / sub).mkdir(parents=True)
        for p in (src / sub).glob("*.jpg"):
            (tmp_path / "card" / sub / p.name).write_bytes(p.read_bytes())
    with pytest.raises(InputError, match=r"2 cameras \(sentera-d4k-ndre in NDRE; sentera-d4k-nrgb in nRGB\)"):
        identify_camera(tmp_path / "card")
    assert identify_camera(tmp_path / "card" / "NDRE").camera.name == "sentera-d4k-ndre"
    assert identify_camera(tmp_path / "card", "sentera-d4k-nrgb").camera.name == "sentera-d4k-nrgb"
    assert main(["apply", str(tmp_path / "card"), "--calibration", "factory", "-o", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out").exists()


