"""XMP read the way cameras write it (pipeline.ingest.xmp), cameras recognised from
their files (pipeline.ingest.identify), the camera catalog entries, and ``mscal cameras``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mscal_core.errors import CatalogError, InputError
from mscal_core.factory import sunshine_irradiance, thermal_kelvin, upright
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import factory_radiance, no_reflectance_reason, read_capture_meta, read_file_metas
from pipeline.ingest.identify import identify_camera
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


def test_sequoia_reader() -> None:
    path = DATA_ROOT / "parrot-sequoia" / "IMG_180413_080658_0000_NIR.TIF"
    if not path.is_file():
        pytest.skip("no Sequoia sample")
    m = read_capture_meta(path)
    assert (m.make, m.model, m.radiometry, m.band_name, m.wavelength_nm) == ("Parrot", "Sequoia", "sequoia", "NIR", 790)
    assert m.sensor_model == (271665.8, 5008.3, 2581.1)  # one rdf:li of three comma-separated numbers
    assert m.iso == 621 and m.exposure_s == pytest.approx(0.003, rel=1e-6) and m.f_number == pytest.approx(2.2, rel=1e-6)
    assert m.orientation == 3 and m.rig_camera_index == 3 and m.capture_id == "BE5AB0ABA969E1CB424A394AA2FD3208"
    assert len(m.vignetting_polynomial_2d) == 15 and len(m.vignetting_polynomial_2d_exponents) == 30
    # sunshine: 10 records CH0 = 14 at gain index 1, 100 ms; golden CH0 sensitivity 656.1082
    assert m.irradiance == pytest.approx(14 / 100 / 656.1082, rel=1e-9)
    assert m.lat is None and m.features()["position"] is False


def test_sequoia_without_golden_sensitivities_has_radiance_but_no_sun_sensor_reading(tmp_path) -> None:
    """Firmware that wrote no Camera:IrradianceSensitivitiesGolden: the radiance model is the
    same, the sunshine reading is none (the bands' readings cannot be put on one scale) and
    the reason names the tag; the intact file keeps its reading."""
    if not cf.SEQUOIA.is_dir():
        pytest.skip("no Sequoia sample")
    folder = cf.sequoia_without_golden(tmp_path / "old")
    name = "IMG_180413_080658_0000_NIR.TIF"
    m, intact = read_capture_meta(folder / name), read_capture_meta(cf.SEQUOIA / name)
    assert m.sensor_model == intact.sensor_model == (271665.8, 5008.3, 2581.1)
    dn = np.full(m.shape, 20000, np.uint16)
    np.testing.assert_array_equal(factory_radiance(m, dn), factory_radiance(intact, dn))
    assert m.irradiance is None and intact.irradiance == pytest.approx(14 / 100 / 656.1082, rel=1e-9)
    (problem,) = m.problems
    assert (problem.tag, problem.value, problem.feature) == ("XMP IrradianceSensitivitiesGolden", "(missing)", "sun_sensor")
    assert problem.file == str(folder / name)
    why = no_reflectance_reason(m)
    assert why.startswith("XMP IrradianceSensitivitiesGolden = '(missing)': not in the file") and "one scale" in why
    assert no_reflectance_reason(intact) is None and m.features()["sun_sensor_reading"] is False


def test_no_reflectance_reason_names_the_missing_tag(tmp_path) -> None:
    require_data()
    path = cf.rewrite(cf.band_file("0000", 1), tmp_path / "IMG_0000_1.tif",
                      lambda x: cf.drop_element(cf.drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance"))
    assert no_reflectance_reason(read_capture_meta(path)) == (
        "no sun-sensor reading: no XMP Camera:Irradiance (DLS 1) or DLS:HorizontalIrradiance (DLS 2) in the file")
    sentera = DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if sentera.is_file():  # a reading, but no published conversion
        assert "no published conversion" in no_reflectance_reason(read_file_metas(sentera)[0])


def test_sentera_reader_one_meta_per_kept_channel() -> None:
    path = DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    if not path.is_file():
        pytest.skip("no Sentera sample")
    metas = read_file_metas(path)
    assert [(m.band_name, m.channel, m.wavelength_nm) for m in metas] == [("RedEdge", 0, 720), ("NIR", 2, 840)]
    m = metas[0]
    assert m.radiometry == "sentera" and m.gain == pytest.approx(3.47) and m.exposure_s == pytest.approx(1 / 609)
    assert m.irradiance == pytest.approx(3124.34) and m.lat == pytest.approx(35 + 49 / 60 + 16083 / 400 / 3600)
    assert m.time == "2020-09-15T04:37:17.991974"
    assert m.features()["sun_sensor_reading"] and not m.features()["sun_sensor_reflectance"]


def test_thermal_and_pan_bands_are_read_not_used(tmp_path) -> None:
    require_data()
    folder = cf.rededge_p(tmp_path / "apt", altum_pt=True)
    lwir = read_capture_meta(folder / "IMG_0000_7.tif")
    pan = read_capture_meta(folder / "IMG_0000_6.tif")
    assert (lwir.radiometry, lwir.shape, lwir.reflectance_band) == ("thermal", (120, 160), False)
    assert (pan.radiometry, pan.shape, pan.reflectance_band) == ("panchro", (1200, 1600), False)
    assert factory_radiance(lwir, np.full((120, 160), 29315, np.uint16))[0, 0] == pytest.approx(293.15)
    assert thermal_kelvin(np.array([27315]))[0] == pytest.approx(273.15)


def test_dls2_horizontal_irradiance_and_its_scale() -> None:
    """DLS 2 firmware: HorizontalIrradiance x IrradianceScaleToSIUnits (0.01 when the scale tag
    is missing, as micasense/imageprocessing metadata.py assumes)."""
    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    path = cf.band_file("0000", 2)
    tags = {}
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    x = tags[700].decode()
    x = cf.drop_element(x, "Camera:Irradiance")
    tags[700] = cf.add_camera_element(x, "<Camera:HorizontalIrradiance>123.0</Camera:HorizontalIrradiance>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(1.23)
    tags[700] = cf.add_camera_element(tags[700].decode(), "<Camera:IrradianceScaleToSIUnits>0.001</Camera:IrradianceScaleToSIUnits>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(0.123)


def test_dls2_legacy_irradiance_takes_the_files_scale() -> None:
    """DLS 2 firmware also writes the legacy ``Camera:Irradiance`` beside HorizontalIrradiance,
    in the same uW cm-2 nm-1 ("DLS2 irradiance units",
    https://github.com/micasense/imageprocessing/issues/47): it is scaled like the other
    irradiance tags of the file (0.01 without IrradianceScaleToSIUnits), not read as W m-2 nm-1.
    A DLS 1 file (the sample: no HorizontalIrradiance) keeps its reading as it is."""
    from pipeline.ingest.camera_meta import meta_from_tags

    require_data()
    path = cf.band_file("0000", 2)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    dls1 = meta_from_tags(path, tags, (960, 1280), 16).irradiance
    x = cf.drop_element(tags[700].decode(), "Camera:Irradiance")
    x = cf.add_camera_element(x, "<Camera:Irradiance>95.74</Camera:Irradiance>")
    x = cf.add_camera_element(x, "<Camera:HorizontalIrradiance>88.5</Camera:HorizontalIrradiance>")
    tags[700] = x.encode()
    m = meta_from_tags(path, tags, (960, 1280), 16)
    assert m.irradiance == pytest.approx(0.9574) and not m.problems
    tags[700] = cf.add_camera_element(x, "<Camera:IrradianceScaleToSIUnits>0.001</Camera:IrradianceScaleToSIUnits>").encode()
    assert meta_from_tags(path, tags, (960, 1280), 16).irradiance == pytest.approx(0.09574)
    tags[700] = cf.add_camera_element(x, "<Camera:IrradianceScaleToSIUnits>-1</Camera:IrradianceScaleToSIUnits>").encode()
    bad = meta_from_tags(path, tags, (960, 1280), 16)
    assert bad.irradiance is None and any("IrradianceScaleToSIUnits" in str(p) for p in bad.problems)
    assert 0.5 < dls1 < 2.0  # the sample's DLS 1 reading, W m-2 nm-1, unscaled


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
    from pipeline.ingest.camera_meta import group_captures

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


def test_sunshine_gain_from_calibration_table() -> None:
    # table: gain index 1 reads 737 counts in 600 ms, index 2 reads 12340 (16.7x the gain)
    cal = {1: 737 / 600, 2: 12340 / 600}
    e1 = sunshine_irradiance([100], [1], [100], cal)
    e2 = sunshine_irradiance([100 * 12340 / 737], [2], [100], cal)
    assert e1 == pytest.approx(1.0) and e2 == pytest.approx(1.0)
    with pytest.raises(ValueError):
        sunshine_irradiance([65535], [1], [100], cal)


def test_rededge_12bit_band_file_is_read_and_clips_at_4095(tmp_path) -> None:
    """A RedEdge band file saved as a packed 12-bit TIFF (BitsPerSample 12, uncompressed; MicaSense's
    "12-bit or 16-bit format") decodes to the sensor's DN, the 16-bit file's >> 4; its factory
    radiance is the 16-bit file's wherever neither is clipped, and it clips at 4095 (its own
    depth's top), the 16-bit file at the catalog's 65520."""
    from pipeline.apply.factory import camera_clip_dn
    from pipeline.ingest.session import plain_tiff_pixels, read_raw

    require_data()
    src = cf.band_file("0001", 1)
    dst = cf.rededge_12bit(src, tmp_path / "IMG_0001_1.tif")
    m16, m12 = read_capture_meta(src), read_capture_meta(dst)
    assert (m16.bits_per_sample, m12.bits_per_sample) == (16, 12)
    assert (m16.black_level, m12.black_level) == (4800.0, 300.0)
    assert plain_tiff_pixels(dst.read_bytes()) is None  # the strip reader leaves 12-bit to tifffile
    dn16, dn12 = read_raw(src), read_raw(dst)
    assert dn12.dtype == np.uint16 and int(dn12.max()) == 4095
    np.testing.assert_array_equal(dn12, dn16 >> 4)
    sat = camera_clip_dn(catalog.load_camera("micasense-rededge"))
    assert (sat, m16.clipped_from(sat), m12.clipped_from(sat)) == (65520, 65520, 4095)
    clipped16, clipped12 = dn16 >= m16.clipped_from(sat), dn12 >= m12.clipped_from(sat)
    assert int(clipped12.sum()) == int(clipped16.sum()) == 1829  # IMG_0001 Blue: sky glint
    np.testing.assert_array_equal(clipped12, clipped16)
    r16, r12 = factory_radiance(m16, dn16), factory_radiance(m12, dn12)
    np.testing.assert_allclose(r12[~clipped12], r16[~clipped16], rtol=1e-12, atol=0)
    assert float(np.median(r12[~clipped12])) == pytest.approx(float(np.median(r16[~clipped16])), rel=1e-12)


def test_sentera_6x_session_grouping(tmp_path) -> None:
    """A 6X session: the files of one name in the band folders are one capture, each band by
    its XMP BandName, EXIF read from IFD0; a truncated band file quarantines its capture only,
    naming the file; a band in two folders is named too."""
    from pipeline.ingest.camera_meta import group_captures

    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    session = cf.sentera_6x(tmp_path / "f")
    camera = catalog.load_camera("sentera-6x")
    caps, problems = group_captures(session, camera)
    assert [c.name for c in caps] == ["IMG_00006", "IMG_00007"] and problems == []
    m = caps[0].metas
    assert [x.band_name for x in m] == ["Blue", "Green", "Red", "RedEdge", "NIR"]
    assert [x.path.parent.name for x in m] == ["blue_475", "green_550", "red_670", "rededge_715", "nir_840"]
    assert caps[0].capture_id == "2020-09-15_04-37-17_1" and m[0].time.startswith("2020-09-15T04:37:17")
    for x in m:  # EXIF ExposureTime and ISOSpeedRatings from IFD0: the D4K capture's they were built from
        p = cf.PARAMS[str(x.path)]
        assert x.exposure_s == pytest.approx(p["exposure"][0] / p["exposure"][1]) and x.gain == pytest.approx(p["iso"] / 100)
    assert m[4].gain == pytest.approx(3.47) and m[4].exposure_s == pytest.approx(1 / 609)  # NDRE IMG_00006
    bad = session / "nir_840" / "IMG_00007.tif"
    bad.write_bytes(bad.read_bytes()[:400])
    caps, problems = group_captures(session, camera)
    assert [c.name for c in caps] == ["IMG_00006"]
    assert problems[0]["file"] == str(bad) and "IMG_00007" in problems[0]["reason"]
    twin = session / "nir_840_copy"
    twin.mkdir()
    (twin / "IMG_00006.tif").write_bytes((session / "nir_840" / "IMG_00006.tif").read_bytes())
    caps, problems = group_captures(session, camera)
    assert caps == [] and any("band NIR also in" in p["reason"] for p in problems)


def test_sentera_6x_thermal_folder_is_named_and_kept_out(tmp_path) -> None:
    """A 6X Thermal session holds a sixth imager folder (LWIR, kelvin x 100: Sentera 6X "Data
    Import"): its files are named in Capture.skipped, the five reflectance bands make the
    capture, instead of every capture being quarantined for an unexpected band."""
    import tifffile

    from pipeline.ingest.camera_meta import group_captures

    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    session = cf.sentera_6x(tmp_path / "f")
    (session / "lwir").mkdir()
    for src in sorted((session / "nir_840").glob("*.tif")):
        with tifffile.TiffFile(src) as tif:
            page = tif.pages[0]
            dn, tags = page.asarray(), {t.code: (t.dtype, t.count, t.value) for t in page.tags.values()}
        xmp = cf.set_element(tags[700][2].decode(), "Camera:BandName", cf.seq("LWIR"))
        xmp = cf.set_element(xmp, "Camera:CentralWavelength", cf.seq(11000)).encode()
        keep = [(c, d, n, v, True) for c, (d, n, v) in tags.items() if c in (271, 272, 42016, 33434, 34855, 36867)]
        tifffile.imwrite(session / "lwir" / src.name, (dn // 16 + 29315).astype(np.uint16), photometric="minisblack",
                         metadata=None, extratags=[*keep, (700, 1, len(xmp), xmp, True)])
    caps, problems = group_captures(session, catalog.load_camera("sentera-6x"))
    assert problems == [] and [c.name for c in caps] == ["IMG_00006", "IMG_00007"]
    assert [x.band_name for x in caps[0].metas] == ["Blue", "Green", "Red", "RedEdge", "NIR"]
    assert [(Path(s["file"]).parent.name, s["band"]) for s in caps[1].skipped] == [("lwir", "LWIR")]


def _dji_tags(packet: str) -> tuple[Path, dict]:
    """The tags of a real band file with a DJI XMP packet and DJI's EXIF black level (4096)."""
    import tifffile

    require_data()
    path = cf.band_file("0000", 2)
    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    tags.update({700: packet.encode(), 271: "DJI", 272: "M3M", 50714: (4096,)})
    return path, tags


def test_dji_band_from_the_mavic_3m_manuals_spellings() -> None:
    """The Mavic 3M User Manual ("Photo File") writes BandFreq ``560(±16)nm`` and
    ``drone-dji:CentralWavelength``; the P4 Multispectral guide ``840(+/-26)nm``. Each names the
    band; drone-dji:CentralWavelength wins over BandFreq's centre."""
    from pipeline.ingest.camera_meta import meta_from_tags

    base = cf.dji_xmp(2, "abc", band_freq=True)  # BandFreq 560(+/-16)nm, no Camera: band tags
    for freq, extra, want in (("560(+/-16)nm", "", (560.0, 32.0)), ("560(\u00b116)nm", "", (560.0, 32.0)),
                              ("560 (\u00b1 16) nm", "", (560.0, 32.0)),
                              ("garbled", 'drone-dji:CentralWavelength="561" ', (561.0, None)),
                              ("560(\u00b116)nm", 'drone-dji:CentralWavelength="561" ', (561.0, 32.0))):
        packet = base.replace('drone-dji:BandFreq="560(+/-16)nm"', f'{extra}drone-dji:BandFreq="{freq}"')
        assert freq in packet
        m = meta_from_tags(*_dji_tags(packet), (960, 1280), 16)
        assert (m.band_name, m.wavelength_nm, m.fwhm_nm) == ("Green", *want), freq
    with pytest.raises(Exception, match="drone-dji:CentralWavelength"):
        meta_from_tags(*_dji_tags(base.replace("560(+/-16)nm", "garbled")), (960, 1280), 16)


def test_exposure_time_in_utc_when_the_file_says_its_zone() -> None:
    """drone-dji:UTCAtExposure (UTC) wins over a DJI file's local DateTimeOriginal; EXIF 2.31
    OffsetTimeOriginal turns DateTimeOriginal into UTC; without either the time is as written
    (zone unknown: MicaSense's, which its own library reads as UTC). A garbled UTCAtExposure
    or offset leaves the time as written."""
    from pipeline.ingest.camera_meta import meta_from_tags

    packet = cf.dji_xmp(2, "abc")
    path, tags = _dji_tags(packet)
    assert meta_from_tags(path, tags, (960, 1280), 16).time == "2017-10-19T20:40:39.200173789"
    for stamp, want in (("2017:10:20 03:40:39.25", "2017-10-20T03:40:39.25Z"), ("2017:10:20 03:40:39", "2017-10-20T03:40:39Z"),
                        ("garbled", "2017-10-19T20:40:39.200173789")):
        p = packet.replace("drone-dji:SensorIndex=", f'drone-dji:UTCAtExposure="{stamp}" drone-dji:SensorIndex=')
        assert meta_from_tags(*_dji_tags(p), (960, 1280), 16).time == want, stamp
    for offset, want in (("-07:00", "2017-10-20T03:40:39.200173789Z"), ("+09:30", "2017-10-19T11:10:39.200173789Z"),
                         ("+00:00", "2017-10-19T20:40:39.200173789Z"), ("   ", "2017-10-19T20:40:39.200173789"),
                         ("+7", "2017-10-19T20:40:39.200173789")):
        exif = {**tags[34665], "OffsetTimeOriginal": offset}
        assert meta_from_tags(path, {**tags, 34665: exif}, (960, 1280), 16).time == want, offset


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


def test_dji_black_level_from_exif_xmp_or_the_manuals_black_current() -> None:
    """EXIF BlackLevel first (P4 Multispectral guide), else drone-dji:BlackLevel (Mavic 3M
    guide), else drone-dji:BlackCurrent (the Mavic 3M User Manual's name for it)."""
    from pipeline.ingest.camera_meta import meta_from_tags

    packet = cf.dji_xmp(2, "abc", band_freq=True)
    path, tags = _dji_tags(packet)
    assert meta_from_tags(path, tags, (960, 1280), 16).black_levels == (4096.0,)
    del tags[50714]
    for attr, want in (('drone-dji:BlackLevel="3200" ', (3200.0,)), ('drone-dji:BlackCurrent="3200" ', (3200.0,)),
                       ('drone-dji:BlackLevel="3100" drone-dji:BlackCurrent="3200" ', (3100.0,))):
        tags[700] = packet.replace("drone-dji:SensorGain=", attr + "drone-dji:SensorGain=").encode()
        assert meta_from_tags(path, tags, (960, 1280), 16).black_levels == want, attr
    tags[700] = packet.encode()
    with pytest.raises(Exception, match="BlackLevel"):
        meta_from_tags(path, tags, (960, 1280), 16)


def test_legacy_rededge_exposure_is_corrected_as_micasense_does() -> None:
    """Some legacy RedEdge firmware wrote ExposureTime 1/6329 s for an exposure of 0.274 ms
    (micasense/imageprocessing metadata.py ``exposure()``, every model but Altum): radiance
    would be 1.73x too high. Other exposures, and Altum's 1/6329 s, are kept."""
    from pipeline.ingest.camera_meta import meta_from_tags, micasense_exposure

    require_data()
    path = cf.band_file("0000", 2)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    exif = dict(tags[34665])
    own = meta_from_tags(path, tags, (960, 1280), 16).exposure_s
    assert own != pytest.approx(0.000274, abs=1e-6)
    exif["ExposureTime"] = (1, 6329)
    tags[34665] = exif
    assert meta_from_tags(path, tags, (960, 1280), 16).exposure_s == 0.000274
    assert micasense_exposure(1 / 6329, "Altum") == pytest.approx(1 / 6329)
    assert micasense_exposure(1 / 6000, "RedEdge") == pytest.approx(1 / 6000)


def _sequoia_with_rgb(folder: Path, gps: dict | None) -> Path:
    """The real Sequoia capture (its TIFFs: GPSStatus V, no position) and beside it the
    capture's ``_RGB.JPG`` with ``gps`` (PIL's GPS IFD keys) or without a GPS IFD."""
    from PIL import Image

    src = DATA_ROOT / "parrot-sequoia"
    if not src.is_dir():
        pytest.skip("no Sequoia sample")
    folder.mkdir(parents=True)
    for p in src.glob("*.TIF"):
        (folder / p.name).write_bytes(p.read_bytes())
    ex = Image.Exif()
    ex[0x010F], ex[0x0110] = "Parrot", "Sequoia"
    if gps is not None:
        ex.get_ifd(0x8825).update(gps)
    Image.new("RGB", (64, 48), (120, 130, 140)).save(folder / "IMG_180413_080658_0000_RGB.JPG", exif=ex)
    return folder


def test_sequoia_position_from_the_captures_rgb_jpeg(tmp_path) -> None:
    """Sequoia writes GPS only into the capture's RGB JPEG (OpenDroneMap contrib/sequoia): the
    band files, which have none, take its position; without a fix there, they stay unplaced."""
    from pipeline.ingest.camera_meta import group_captures

    camera = catalog.load_camera("parrot-sequoia")
    folder = _sequoia_with_rgb(tmp_path / "a", {1: "S", 2: (47.0, 30.0, 0.0), 3: "W", 4: (7.0, 36.0, 0.0), 5: 0, 6: 420.0})
    caps, problems = group_captures(folder, camera)
    assert problems == [] and len(caps) == 1 and len(caps[0].metas) == 4
    assert [(m.lat, m.lon, m.alt_m) for m in caps[0].metas] == [(pytest.approx(-47.5), pytest.approx(-7.6), 420.0)] * 4
    caps, _ = group_captures(_sequoia_with_rgb(tmp_path / "b", None), camera)
    assert all(m.lat is None and m.lon is None for m in caps[0].metas)


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


def test_sentera_6x_cal_captures_are_captures(tmp_path) -> None:
    """Sentera names the 6X's panel captures CAL_NNNNN.tif (py-radiometric-corrections
    sensor_defs: "calibration images are all named CAL_...tif"): they are captures of the
    session (panel candidates), not files skipped as foreign."""
    from pipeline.ingest.camera_meta import group_captures

    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    session = cf.sentera_6x(tmp_path / "f")
    for p in session.glob("*/IMG_00006.tif"):
        p.rename(p.with_name("CAL_00006.tif"))
    caps, problems = group_captures(session, catalog.load_camera("sentera-6x"))
    assert problems == [] and [c.name for c in caps] == ["CAL_00006", "IMG_00007"]
    assert len(caps[0].metas) == 5


def test_rededge_12bit_files_reach_the_field_fits_in_sensor_dn(tmp_path) -> None:
    """Calibration's reads (read_bands, stored_bands from bytes, as ingest reads them) shift each
    band file by what it stores: a 16-bit RedEdge file by the catalog's 4, a packed 12-bit one
    not at all; both give the same sensor DN. Shifting the 12-bit file by 4 too (the catalog's
    shift for every file) gave DN / 16, silently: a 4095 highlight became 255."""
    from pipeline.ingest.session import FrameRecord, read_bands, sample_bits, stored_bands

    require_data()
    cam = catalog.load_camera("micasense-rededge")
    assert (cam.shift_for(None), cam.shift_for(16), cam.shift_for(12), cam.shift_for(14)) == (4, 4, 0, 2)
    assert catalog.load_camera("generic-rgb8").shift_for(16) == 0
    src16 = [cf.band_file("0001", b) for b in range(1, 6)]
    src12 = [cf.rededge_12bit(p, tmp_path / p.name) for p in src16]
    assert [sample_bits(p) for p in (src16[0], src12[0])] == [16, 12]
    assert sample_bits(src12[0].read_bytes()) == 12 and sample_bits(b"\xff\xd8\xff\xe0") is None
    rec16, rec12 = (FrameRecord(path=f[0], exposure_ms=1.0, band_files=tuple(f), capture="IMG_0001")
                    for f in (src16, src12))
    b16, b12 = read_bands(rec16, cam), read_bands(rec12, cam)
    assert b12.shape == (5, 960, 1280) and int(b12.max()) == 4095
    np.testing.assert_array_equal(b12, b16)
    for p16, p12 in zip(src16, src12):
        np.testing.assert_array_equal(stored_bands(p12.read_bytes(), p12, cam), stored_bands(p16.read_bytes(), p16, cam))
    mixed = FrameRecord(path=src12[0], exposure_ms=1.0, band_files=(src12[0], *src16[1:]), capture="IMG_0001")
    np.testing.assert_array_equal(read_bands(mixed, cam), b16)
