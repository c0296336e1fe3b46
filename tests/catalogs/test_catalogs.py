"""Every catalog file loads, validates, and says what it must; bad entries are rejected."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from mscal_core.errors import CatalogError
from pipeline.ingest import catalog

ROOT = catalog.CATALOG_ROOT


@pytest.mark.parametrize("path", sorted((ROOT / "cameras").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_camera_file_loads(path: Path) -> None:
    cam = catalog.load_camera(path.stem)
    assert cam.name == path.stem
    assert cam.n_bands >= 1
    for role, wl in cam.index_bands.items():
        assert abs(cam.bands[cam.band_for_wavelength(wl)].wavelength_nm - wl) <= 10


@pytest.mark.parametrize("path", sorted((ROOT / "targets").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_target_file_loads(path: Path) -> None:
    from pipeline.ingest.targets import target_for_serial

    t = catalog.load_target(path.stem)
    rho = t.reflectance.at(np.array([450.0, 650.0, 850.0]))
    assert np.all((rho > 0) & (rho <= 1))
    for serial in t.serials:  # each serial finds this target and no other
        assert target_for_serial(serial) == t and t.name == path.stem


def test_the_micasense_panel_target_carries_its_serial() -> None:
    from pipeline.ingest.targets import serial_targets, target_for_serial

    t = catalog.load_target("micasense-rp02-1603036-sc")
    assert t.serials == ("RP02-1603036-SC",)
    assert target_for_serial(" rp02-1603036-sc ") == t and target_for_serial("RP02-1603036") is None
    assert [x.name for x in serial_targets()] == ["micasense-rp02-1603036-sc"]
    assert catalog.load_target("gray-50").serials == ()


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"serial": 1603036}, "serial must be text, not empty, got 1603036 (quote a serial YAML reads as a number)"),
        ({"serial": " "}, "serial must be text, not empty, got ' '"),
        ({"serials": "RP02-1"}, "serials must be a list of serial numbers (text, not empty), got 'RP02-1'"),
        ({"serials": ["RP02-1", None]}, "serials must be a list of serial numbers (text, not empty), got ['RP02-1', None]"),
        ({"serial": "RP02-1", "name": "other"}, "name 'other' must match the file name 't-x'"),
        ({"serail": "RP02-1"}, "unknown key(s) serail"),
    ],
)
def test_bad_target_serial_rejected_naming_file(tmp_path, monkeypatch, extra, message) -> None:
    (tmp_path / "targets").mkdir()
    p = tmp_path / "targets" / "t-x.yaml"
    p.write_text(yaml.safe_dump({"name": "t-x", "description": "d", "reflectance": 0.5} | extra))
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    with pytest.raises(CatalogError) as err:
        catalog.load_target("t-x")
    assert message in str(err.value) and str(p) in str(err.value)


def test_target_serials_are_stripped_and_kept_once() -> None:
    data = {"name": "t", "description": "d", "reflectance": 0.5, "serial": " A-1 ", "serials": ["a-1", "B-2"]}
    assert catalog.parse_target(data, Path("t.yaml")).serials == ("A-1", "B-2")


@pytest.mark.parametrize("path", sorted((ROOT / "indices").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_index_file_loads_and_evaluates(path: Path) -> None:
    idx = catalog.load_index(path.stem)
    vals = {k: np.array([0.1, 0.5, 0.0]) for k in idx.inputs}
    vals["nir"] = np.array([0.5, 0.5, 0.0])
    out = idx.evaluate(vals)
    assert out.dtype == np.float32
    assert np.isnan(out[2])  # 0/0 is NaN, never inf


def test_ximea_matches_spec() -> None:
    cam = catalog.load_camera("ximea-mq022hg-sm5x5-nir")
    assert cam.sensor == (1088, 2048)
    assert cam.bit_depth == 10 and cam.dn_max == 1023
    assert cam.layout.kind == "mosaic"
    assert cam.layout.pattern == (5, 5) and cam.layout.origin == (0, 0) and cam.layout.grid == (217, 409)
    spec = [
        [615, 623, 608, 790, 686],
        [816, 828, 803, 791, 700],
        [765, 778, 752, 739, 714],
        [653, 662, 645, 636, 678],
        [867, 864, 857, 845, 670],
    ]
    wl = cam.wavelengths.reshape(5, 5)
    np.testing.assert_array_equal(wl, np.array(spec, dtype=float))
    assert cam.bands[cam.band_for_wavelength(670)].mosaic == (4, 4)
    assert cam.bands[cam.band_for_wavelength(803)].mosaic == (1, 2)
    assert cam.index_bands["red"] == 670 and cam.index_bands["nir"] == 803
    assert len(cam.export_bands) <= 8


def test_ximea_exif_names_the_camera_and_its_pixel_pitch() -> None:
    cam = catalog.load_camera("ximea-mq022hg-sm5x5-nir")
    assert (cam.exif.make, cam.exif.model, cam.exif.pixel_um) == ("XIMEA", "MQ022HG-IM-SM5X5-NIR", 5.5)
    assert catalog.load_camera("micasense-rededge").exif is None  # its files carry their own EXIF


def test_generic_rgb8() -> None:
    cam = catalog.load_camera("generic-rgb8")
    assert cam.bit_depth == 8 and cam.layout.kind == "multichannel" and cam.layout.channels == 3
    assert [b.channel for b in cam.bands] == [0, 1, 2]
    assert cam.wavelengths[0] > cam.wavelengths[1] > cam.wavelengths[2]  # R, G, B


def test_ndvi_value() -> None:
    ndvi = catalog.load_index("ndvi")
    out = ndvi.evaluate({"red": np.array([0.05]), "nir": np.array([0.45])})
    assert out[0] == pytest.approx(0.8, abs=1e-6)


def test_micasense_cameras_store_12_bit_dn_in_16_bit_samples() -> None:
    for name, n_bands in (("micasense-rededge", 5), ("micasense-rededge-mx-dual", 10)):
        cam = catalog.load_camera(name)
        assert cam.layout.kind == "file_per_band" and cam.n_bands == n_bands
        assert (cam.bit_depth, cam.container_bits, cam.dn_shift, cam.dn_max) == (12, 16, 4, 4095)
        assert [b.file_suffix for b in cam.bands] == [str(i) for i in range(1, n_bands + 1)]
    dual = catalog.load_camera("micasense-rededge-mx-dual")
    assert sorted(dual.wavelengths) == [444, 475, 531, 560, 650, 668, 705, 717, 740, 842]
    assert dual.bands[dual.band_for_wavelength(705)].name == "Red edge-705"
    assert catalog.load_camera("generic-rgb8").dn_shift == 0


def test_target_table_interpolates() -> None:
    t = catalog.load_target("micasense-rp02-1603036-sc")
    assert t.reflectance.at(np.array([668.0]))[0] == pytest.approx(0.68)
    assert t.reflectance.at(np.array([840.0]))[0] == pytest.approx(0.61)


def test_reflectance_option_takes_a_number_or_a_target_name() -> None:
    assert catalog.reflectance_option("0.5").at(np.array([550.0]))[0] == pytest.approx(0.5)
    table = catalog.reflectance_option("micasense-rp02-1603036-sc")
    assert table.at(np.array([668.0]))[0] == pytest.approx(0.68)
    with pytest.raises(CatalogError, match=r"--panel-reflectance must be in \(0, 1\], got 1.5"):
        catalog.reflectance_option("1.5")
    with pytest.raises(CatalogError, match=r"^--panel-reflectance: --panel-reflectance 'nope': unknown target 'nope'"):
        catalog.reflectance_option("nope")
    with pytest.raises(CatalogError) as err:
        catalog.parse_reflectance({"x": 1}, Path("s.yaml"), "reflector.reflectance")
    assert str(err.value) == ("s.yaml: reflector.reflectance must be a number, a table of [wavelength_nm, reflectance] "
                              "rows or a target name, got {'x': 1}")


def _write_camera(tmp_path: Path, data: dict) -> Path:
    d = tmp_path / "cameras"
    d.mkdir(exist_ok=True)
    p = d / f"{data['name']}.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _base_camera() -> dict:
    return yaml.safe_load((ROOT / "cameras" / "generic-rgb8.yaml").read_text()) | {"name": "cam-x"}


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.update(colour="blue"), "unknown key(s) colour"),
        (lambda d: d["bands"][0].update(wavelenght_nm=1), "unknown key(s) wavelenght_nm"),
        (lambda d: d.update(bit_depth=33), "bit_depth"),
        (lambda d: d["layout"].update(kind="hexagon"), "layout.kind"),
        (lambda d: d.pop("bands"), "missing key(s) bands"),
        (lambda d: d["bands"][1].update(channel=0), "one band per channel"),
        (lambda d: d.update(export_bands=["uv"]), "unknown band(s) uv"),
        (lambda d: d.update(container_bits=4), "container_bits must be an integer from bit_depth (8) to 16"),
        (lambda d: d.update(exif={"make": "X", "model": "Y", "pixel_um": -5.5}), "exif.pixel_um"),
        (lambda d: d.update(exif={"make": "X", "model": "Y", "lens": 5}), "unknown key(s) lens"),
        (lambda d: d.update(exif={"make": "X"}), "missing key(s) model"),
        # unknown keys (the allowed ones said), of any YAML type
        (lambda d: d.update(colour="blue"), "camera: unknown key(s) colour (allowed keys: bands, bit_depth,"),
        (lambda d: d.update({1: 2}), "camera: unknown key(s) 1 (allowed keys:"),
        (lambda d: d["layout"].update(grid=[1, 2]), "layout (kind multichannel): unknown key(s) grid "
                                                    "(allowed keys: channels, kind)"),
        (lambda d: d.update(sensor={"width": 10, "height": 5, "depth": 3}), "sensor: unknown key(s) depth"),
        # missing keys
        (lambda d: d["layout"].pop("channels"), "layout (kind multichannel): missing key(s) channels"),
        (lambda d: d["bands"][2].pop("wavelength_nm"), "bands[2]: missing key(s) wavelength_nm"),
        (lambda d: d.update(skip_bands=[{"name": "x"}]), "skip_bands[0]: missing key(s) reason"),
        # wrong types
        (lambda d: d.update(bit_depth="8"), "bit_depth must be an integer 1..16, got '8'"),
        (lambda d: d.update(bands="rgb"), "bands must be a list, got 'rgb'"),
        (lambda d: d.update(layout=5), "layout must be a mapping, got 5"),
        (lambda d: d["bands"].__setitem__(1, "green"), "bands[1] must be a mapping, got 'green'"),
        (lambda d: d.update(index_bands={"red": "x"}), "index_bands.red must be a positive number, got 'x'"),
        (lambda d: d.update(identify={"make": "X", "models": "A"}), "identify.models must be a list of strings, got 'A'"),
        (lambda d: d.update(export_bands="Red"), "export_bands must be a list of band names, got 'Red'"),
        (lambda d: d["layout"].update(kind=None), "layout.kind must be one of mosaic, multichannel, file_per_band"),
        # out of range
        (lambda d: d["bands"][0].update(wavelength_nm=-5), "bands[0].wavelength_nm must be a positive number, got -5"),
        (lambda d: d["bands"][0].update(wavelength_nm=float("nan")), "bands[0].wavelength_nm must be a positive number"),
        (lambda d: d["bands"][0].update(channel=5000), "bands[0].channel must be an integer 0..1023, got 5000"),
        (lambda d: d["layout"].update(channels=0), "layout.channels must be a positive integer, got 0"),
        (lambda d: d.update(sensor={"width": 0, "height": 5}), "sensor.width must be an integer 1..100000 (pixels), got 0"),
        (lambda d: d.update(bands=[]), "bands must have at least 1 item(s), got []"),
    ],
)
def test_bad_camera_rejected_naming_file(tmp_path, monkeypatch, mutate, message) -> None:
    data = _base_camera()
    mutate(data)
    p = _write_camera(tmp_path, data)
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    catalog.clear_cache()
    try:
        with pytest.raises(CatalogError) as err:
            catalog.load_camera("cam-x")
    finally:
        catalog.clear_cache()
    assert message in str(err.value)
    assert str(err.value).startswith(f"{p}: ") and "\n" not in str(err.value)


@pytest.mark.parametrize(
    "kind, data, message",
    [
        ("targets", {"name": "t-x", "description": "d"}, "target: missing key(s) reflectance (allowed keys:"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": 1.5}, "reflectance must be in (0, 1], got 1.5"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": [[400, 0.5], [500, "x"]]},
         "reflectance[1] must be [wavelength_nm, reflectance]: finite numbers, nm > 0, 0 < reflectance <= 1, "
         "got [500, 'x']"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": [[500, 0.5], [400, 0.5]]},
         "reflectance must list its wavelengths strictly increasing, got [[500, 0.5], [400, 0.5]]"),
        ("targets", ["t-x"], "must be a YAML mapping of keys to values, got ['t-x']"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": "gray-50"},
         "reflectance must be a number or a table of [wavelength_nm, reflectance] rows, got 'gray-50'"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": []},
         "reflectance must have at least 1 item(s), got []"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": True},
         "reflectance must be a number or a table of [wavelength_nm, reflectance] rows, got True"),
        ("targets", {"name": "t-x", "description": "d", "reflectance": [[400, 0.5], [400, 0.6]]},
         "reflectance must list its wavelengths strictly increasing, got [[400, 0.5], [400, 0.6]]"),
        ("indices", {"name": "t-x", "description": "d"}, "index: missing key(s) expression"),
        ("indices", {"name": "t-x", "description": "d", "expression": "nir", "scale": 2},
         "index: unknown key(s) scale (allowed keys: description, expression, name, valid_range)"),
        ("indices", {"name": "t-x", "description": "d", "expression": "nir", "valid_range": [1, -1]},
         "valid_range must be [low, high] (finite numbers, low < high), got [1, -1]"),
        ("indices", {"name": "t-x", "description": "d", "expression": "nir", "valid_range": "all"},
         "valid_range must be [low, high]"),
    ],
)
def test_bad_target_or_index_rejected_naming_file_and_key(tmp_path, monkeypatch, kind, data, message) -> None:
    (tmp_path / kind).mkdir()
    p = tmp_path / kind / "t-x.yaml"
    p.write_text(yaml.safe_dump(data))
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    catalog.clear_cache()
    try:
        with pytest.raises(CatalogError) as err:
            (catalog.load_target if kind == "targets" else catalog.load_index)("t-x")
    finally:
        catalog.clear_cache()
    assert str(err.value).startswith(f"{p}: {message}") and "\n" not in str(err.value)


def test_unknown_camera_lists_known() -> None:
    with pytest.raises(CatalogError, match="unknown camera 'nope'.*ximea-mq022hg-sm5x5-nir"):
        catalog.load_camera("nope")


def test_index_expression_is_sandboxed(tmp_path, monkeypatch) -> None:
    (tmp_path / "indices").mkdir()
    (tmp_path / "indices" / "evil.yaml").write_text(
        "name: evil\ndescription: x\nexpression: __import__('os').system('true')\n"
    )
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    catalog.clear_cache()
    try:
        with pytest.raises(CatalogError, match="uses Attribute, Call"):
            catalog.load_index("evil")
    finally:
        catalog.clear_cache()


def test_cache_sees_an_edited_and_a_new_file(tmp_path, monkeypatch) -> None:
    """A long-running process (mscal serve) sees catalog edits: the cache is keyed on the
    file's path, mtime and size."""
    import os

    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    (tmp_path / "indices").mkdir()
    f = tmp_path / "indices" / "ratio.yaml"
    f.write_text("name: ratio\ndescription: first\nexpression: nir / red\n")
    first = catalog.load_index("ratio")
    assert first.description == "first" and catalog.load_index("ratio") is first  # cached
    f.write_text("name: ratio\ndescription: second\nexpression: nir / red + 1\n")
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # a later mtime even on coarse clocks
    second = catalog.load_index("ratio")
    assert second.description == "second" and second.expression == "nir / red + 1"
    # a file added under the extra path shadows the shipped one at the next call
    shipped = catalog.load_index("ndvi")
    assert shipped.description.startswith("Normalised difference")
    (tmp_path / "indices" / "ndvi.yaml").write_text("name: ndvi\ndescription: local\nexpression: nir - red\n")
    assert catalog.load_index("ndvi").description == "local"
    monkeypatch.delenv("MSCAL_CATALOG_PATH")
    assert catalog.load_index("ndvi") is shipped


def test_catalog_search_path_parameter_and_its_default(tmp_path, monkeypatch) -> None:
    """``search_path`` given: its folders, then the shipped catalogs; None: MSCAL_CATALOG_PATH's."""
    import os

    a, b = tmp_path / "a", tmp_path / "b"
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(b))
    assert catalog.catalog_dirs("cameras", f"{a}{os.pathsep}{b}") == [a / "cameras", b / "cameras",
                                                                         catalog.CATALOG_ROOT / "cameras"]
    assert catalog.catalog_dirs("targets", "") == [catalog.CATALOG_ROOT / "targets"]
    assert catalog.catalog_dirs("indices") == [b / "indices", catalog.CATALOG_ROOT / "indices"]
    monkeypatch.delenv("MSCAL_CATALOG_PATH")
    assert catalog.catalog_dirs("indices") == [catalog.CATALOG_ROOT / "indices"]


def test_catalog_root_is_the_catalogs_package() -> None:
    import catalogs

    assert ROOT == Path(catalogs.__file__).parent
    assert {"cameras", "targets", "indices"} <= {p.name for p in ROOT.iterdir() if p.is_dir()}


def test_skip_bands_need_a_file_suffix_only_where_files_are_numbered(tmp_path) -> None:
    """A one-file-per-band camera's skipped band is found by its file number (it may be
    unreadable); a folder-per-band camera's by its XMP BandName, so no file_suffix there."""
    data = yaml.safe_load((ROOT / "cameras" / "micasense-altum.yaml").read_text())
    del data["skip_bands"][0]["file_suffix"]
    with pytest.raises(CatalogError, match="need their file_suffix"):
        catalog.parse_camera(data, tmp_path / "micasense-altum.yaml")
    six = catalog.load_camera("sentera-6x")
    assert [(s.name, s.file_suffix) for s in six.skip_bands] == [("LWIR", None)]
