"""Adding a camera maker is one module and one catalog file: a toy maker "Acme", written as its
own module file (the public API only) and one catalog YAML in a catalog folder of
``MSCAL_CATALOG_PATH``, is recognised, grouped, read, converted to radiance and reflectance and
applied through the normal path with no other file of mscal edited; and no module outside
``pipeline/ingest/cameras`` branches on a maker's name."""

from __future__ import annotations

import ast
import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from mscal_core.errors import FrameError, InputError
from pipeline.calibrate.library import file_serial
from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import read_file_metas, sun_sensor_xmp
from pipeline.ingest.cameras import registry
from pipeline.ingest.cameras.dispatch import factory_models, factory_radiance, takes_field_parts
from pipeline.ingest.grouping import group_captures
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.intrinsics import intrinsics_from_file
from pipeline.ingest.meta import FieldParts, no_reflectance_reason, reflectance_factor
from pipeline.ingest.sunsensor import sensor_orientation
from pipeline.storage.run_layout import run_value

ROOT = Path(__file__).parents[4]

#: The whole of the Acme maker, as ``pipeline/ingest/cameras/acme.py`` would hold it.
ACME_MODULE = '''
"""Acme Duo (a toy maker): tags XMP Acme:Gain, Acme:Shot, Acme:Utc, Acme:Lens, Acme:Falloff, EXIF
ExposureTime; radiance (DN - black) V / (gain t), V = 1 + falloff r^2 (r from the centre, in
half-diagonals); sun sensor Acme:Sun (W m-2 nm-1) with R = pi L / E and its own
angles Acme:Yaw/Pitch/Roll; quirk: a Dark band read but kept out of reflectance."""
import math

import numpy as np
from mscal_core.geometry import Intrinsics

from pipeline.ingest.cameras.registry import AttitudeSource, Maker, register
from pipeline.ingest.meta import (CaptureMeta, band_of, black_levels, exif_exposure, factory_vignetting, meta_fields,
                                  positive_irradiance)
from pipeline.ingest.sun_scale import SunScale

NS = ("Acme",)


def read(ctx):
    name, wl, fwhm = band_of(ctx)
    return [CaptureMeta(
        path=ctx.path, shape=ctx.shape, bits_per_sample=ctx.bits, band_name=name, wavelength_nm=wl, fwhm_nm=fwhm,
        exposure_s=exif_exposure(ctx.exif, ctx.path), gain=ctx.required("Gain", NS, 1)[0],
        black_levels=black_levels(ctx), irradiance=positive_irradiance(ctx, "Sun", NS), radiometry="acme-dark" if name == "Dark" else "acme",
        maker_tags=(("falloff", ctx.required("Falloff", NS, 1)[0]),), **meta_fields(ctx))]


def radiance(meta, dn, parts, channels, out):
    return (np.asarray(dn, np.float64) - meta.black_level) * factory_vignetting(meta) / (meta.gain * meta.exposure_s)


def vignetting(radiometry, shape, tags):
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return 1.0 + dict(tags.maker)["falloff"] * r2


def lens(x, path):
    v = x.numbers("Lens", NS, 4)
    return None if v is None else Intrinsics(fx=v[0], fy=v[1], cx=v[2], cy=v[3], dist=(0.0,) * 5)


register(Maker(
    name="acme", model="acme", units={"acme": "W m-2 sr-1 nm-1", "acme-dark": "DN"},
    claims=lambda ctx: ctx.xmp.has("Gain", NS), read=read, radiance=radiance,
    vignetting=vignetting, order=40, sun_sensor_tag="XMP Acme:Sun",
    sun_scales={"acme": SunScale(math.pi, "R = pi L / E", "Acme manual (a toy)", True)},
    attitude=(AttitudeSource(35, "Acme:Yaw/Pitch/Roll",
                             lambda x: x.angles(("Yaw", "Pitch", "Roll"), NS, degrees=True)),),
    sun_sensor_xmp=frozenset({"Sun", "Yaw", "Pitch", "Roll"}), kept_out=frozenset({"acme-dark"}),
    capture_id_tags=(("Acme", "Shot"),), time_tags=(("Acme", "Utc"),), intrinsics=lens,
    namespaces={"Acme": ("http://acme.example/camera/1.0/",)}, serial_tags=(("Acme", "Body"),),
    capture_id_output=("Acme", "http://acme.example/camera/1.0/", "Shot"),
))
'''

#: Its one camera, as ``catalogs/cameras/acme-duo.yaml`` would hold it.
ACME_CAMERA = r"""
name: acme-duo
description: Acme Duo, two bands and a dark band, one TIFF per band (ACME_<capture>_<band>.tif)
bit_depth: 12
container_bits: 16
layout: {kind: file_per_band, capture_pattern: '^(?P<capture>ACME_[0-9]{4})_(?P<band>[1-3])\.tif$'}
bands:
  - {name: Green, wavelength_nm: 560, file_suffix: '1'}
  - {name: NIR, wavelength_nm: 840, file_suffix: '2'}
skip_bands: [{name: Dark, file_suffix: '3', reason: the sensor's covered pixels}]
identify: {make: Acme, bands_per_capture: 3}
factory_model: acme
sources: ["Acme Duo manual (a toy)"]
index_bands: {green: 560, nir: 840}
"""

GAIN, EXPOSURE_S, SUN, BLACK, FALLOFF = 2.0, 0.004, 2.0e7, 64, 0.5


def _band_file(path: Path, band: str, wavelength: float, dn: int, capture: int, sun: bool = True) -> Path:
    packet = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description xmlns:Acme="http://acme.example/camera/1.0/" xmlns:Camera="http://pix4d.com/camera/1.0">'
        f"<Camera:BandName>{band}</Camera:BandName><Camera:CentralWavelength>{wavelength}</Camera:CentralWavelength>"
        f"<Acme:Gain>{GAIN}</Acme:Gain><Acme:Shot>shot-{capture}</Acme:Shot><Acme:Body>AC-7</Acme:Body>"
        f"<Acme:Utc>2025:05:20 10:12:54.5</Acme:Utc><Acme:Lens>900,900,32,24</Acme:Lens><Acme:Falloff>{FALLOFF}</Acme:Falloff>"
        + (f"<Acme:Sun>{SUN}</Acme:Sun><Acme:Yaw>90</Acme:Yaw><Acme:Pitch>0</Acme:Pitch><Acme:Roll>0</Acme:Roll>"
           if sun else "")
        + "</rdf:Description></rdf:RDF></x:xmpmeta>").encode()
    exposure = (1, round(1 / EXPOSURE_S))
    tifffile.imwrite(path, np.full((48, 64), dn << 4, np.uint16), photometric="minisblack", metadata=None,
                     extratags=[(271, "s", 0, "Acme", True), (272, "s", 0, "Duo", True),
                                (33434, "2I", 1, exposure, True), (50714, "I", 1, BLACK << 4, True),
                                (700, 1, len(packet), packet, True)])
    return path


@pytest.fixture
def acme(tmp_path, monkeypatch) -> Path:
    """The toy maker's module imported (it registers itself), its catalog file in a catalog
    folder of ``MSCAL_CATALOG_PATH``, and a flight of two captures of its files; the registry
    as it was afterwards."""
    monkeypatch.setattr(registry, "MAKERS", dict(registry.MAKERS))
    monkeypatch.setattr(registry, "NAMESPACE_KEYS", dict(registry.NAMESPACE_KEYS))
    monkeypatch.setattr(registry, "DEFAULT_NAMESPACE_KEYS", registry.DEFAULT_NAMESPACE_KEYS)
    module = tmp_path / "acme.py"
    module.write_text(ACME_MODULE)
    spec = importlib.util.spec_from_file_location("acme_maker_under_test", module)
    assert spec is not None and spec.loader is not None
    spec.loader.exec_module(importlib.util.module_from_spec(spec))
    (tmp_path / "catalog" / "cameras").mkdir(parents=True)
    (tmp_path / "catalog" / "cameras" / "acme-duo.yaml").write_text(ACME_CAMERA)
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path / "catalog"))
    catalog.clear_cache()
    flight = tmp_path / "flight"
    flight.mkdir()
    for c in (1, 2):
        for suffix, (band, wl, dn) in enumerate((("Green", 560, 1064), ("NIR", 840, 2064), ("Dark", 700, 70)), 1):
            _band_file(flight / f"ACME_{c:04d}_{suffix}.tif", band, wl, dn, c)
    yield flight
    catalog.clear_cache()
    sys.modules.pop("acme_maker_under_test", None)


def test_a_new_maker_is_one_module_and_one_catalog_file(acme) -> None:
    """Identified, grouped and read by its own module's tags; radiance, sun-sensor reflectance,
    the kept-out band's and a missing reading's reasons, capture id, time, orientation and
    lens all come from what the module registered."""
    assert "acme" in factory_models()
    ident = identify_camera(acme)
    assert ident.camera.name == "acme-duo" and ident.camera.factory_model == "acme"
    captures, problems = group_captures(acme, ident.camera)
    assert [c.name for c in captures] == ["ACME_0001", "ACME_0002"] and problems == []
    green, nir = read_file_metas(acme / "ACME_0001_1.tif")[0], read_file_metas(acme / "ACME_0001_2.tif")[0]
    assert (green.radiometry, green.band_name, green.gain, green.exposure_s) == ("acme", "Green", GAIN, EXPOSURE_S)
    assert (green.capture_id, green.radiance_unit, green.reflectance_band) == ("shot-1", "W m-2 sr-1 nm-1", True)
    assert green.time is not None and green.time.startswith("2025-05-20T10:12:54.5")
    dn = np.full((48, 64), 2064 << 4, np.uint16)
    # (DN - black) V / (gain t), black = 64 << 4: (33024 - 1024) / (2 x 0.004) = 4.0e6 times V, which is
    # 1 + 0.5 = 1.5 in the corners (its own tag, through CaptureMeta.maker_tags) and about 1 in the middle
    assert nir.maker_tag("falloff") == FALLOFF
    rad = factory_radiance(nir, dn)
    assert rad[0, 0] == pytest.approx(6.0e6, rel=1e-12) and rad[24, 32] == pytest.approx(4.0e6, rel=1e-3)
    assert reflectance_factor(green) == pytest.approx(math.pi / SUN) and no_reflectance_reason(green) is None
    assert green.features()["sun_sensor_absolute"] is True
    kept = sun_sensor_xmp(green)
    assert kept is not None and kept.number("Sun", ("Acme",)) == SUN
    orientation = sensor_orientation(kept)
    assert orientation.source == "Acme:Yaw/Pitch/Roll" and orientation.yaw == pytest.approx(math.pi / 2)
    dark = read_file_metas(acme / "ACME_0001_3.tif")[0]
    assert (dark.radiometry, dark.reflectance_band) == ("acme-dark", False)
    assert no_reflectance_reason(dark) == "a acme-dark band has no sun-sensor reflectance"
    bare = read_file_metas(_band_file(acme.parent / "bare.tif", "Green", 560, 1064, 3, sun=False))[0]
    assert no_reflectance_reason(bare) == "no sun-sensor reading: no XMP Acme:Sun in the file"
    lens = intrinsics_from_file(acme / "ACME_0001_1.tif")
    assert (lens.fx, lens.fy, lens.cx, lens.cy) == (900.0, 900.0, 32.0, 24.0)
    # the camera body's serial from its own XMP tag (no EXIF BodySerialNumber in its files)
    assert file_serial(acme / "ACME_0001_1.tif") == "AC-7"
    # its model takes no field calibration's parts (field_parts left out): refused naming the file
    assert (takes_field_parts("acme"), takes_field_parts("micasense"), takes_field_parts(None)) == (False, True, True)
    with pytest.raises(FrameError, match=r"takes them \(micasense\), not acme's") as err:
        factory_radiance(nir, dn, FieldParts(vignetting=np.ones((48, 64))))
    assert str(err.value.path) == str(nir.path)


def test_a_new_makers_flight_is_applied_with_its_sun_sensor(acme, tmp_path) -> None:
    """``mscal apply FLIGHT --calibration factory`` on the toy maker's files: every capture
    processed with the sun sensor's reflectance R = pi L / E, the dark band skipped; its
    readings checked against the clear sky on the one neutral unit rule (it declares none, so
    no other maker's rules); its capture id in the photogrammetry TIFFs under its own tag."""
    import xarray as xr

    from pipeline.apply.factory import FactoryOptions, apply_factory

    out = tmp_path / "out"
    apply_factory(acme, out, FactoryOptions(reference="dls"))
    run = json.loads((out / "run.json").read_text())
    assert run["camera"] == "acme-duo" and run["frames"] == ["ACME_0001", "ACME_0002"] and run["quarantined"] == []
    assert [b["band"] for b in run_value(run, "skipped_bands")] == ["Dark", "Dark"]
    assert run_value(run, "reference")["sun_sensor_scale"]["source"] == "Acme manual (a toy)"
    assert run_value(run, "sun_sensor_check")["rules"] == {registry.AS_READ_RULE: 4}  # 2 captures x 2 bands
    with tifffile.TiffFile(out / "photogrammetry" / "ACME_0002_NIR.tif") as tif:
        packet = tif.pages[0].tags[700].value.decode()
    assert 'xmlns:Acme="http://acme.example/camera/1.0/"' in packet and "<Acme:Shot>shot-2</Acme:Shot>" in packet
    # its model takes no field calibration's parts: --field-calibration refused before any store is opened
    with pytest.raises(InputError, match=r"takes them \(micasense\); camera acme-duo has the acme model"):
        apply_factory(acme, tmp_path / "field", FactoryOptions(reference="dls", field_calibration="missing.zarr"))
    assert not (tmp_path / "field").exists()
    with xr.open_zarr(out / "reflectance.zarr") as ds:
        assert list(ds["band_name"].values) == ["Green", "NIR"]
        refl = ds["reflectance"].values
    # L = (DN - 64) x 16 V / (2 x 0.004): Green 1000 x 16 / 0.008 = 2e6, NIR 4e6 (x V); R = pi L / 2e7
    np.testing.assert_allclose(refl[:, :, 24, 32], [[0.314159, 0.628319]] * 2, rtol=2e-3)
    np.testing.assert_allclose(refl[:, :, 0, 0], [[0.314159 * 1.5, 0.628319 * 1.5]] * 2, rtol=1e-4)


#: What a module outside pipeline/ingest/cameras may not compare a value with: a maker's name,
#: a camera model, or a radiometry a maker registers.
MAKER_WORDS = ("micasense", "parrot", "sequoia", "dji", "sentera", "rededge", "altum", "mavic", "thermal", "panchro")

#: Branches on a maker outside pipeline/ingest/cameras that are known and not yet moved
#: (modules of other packages): file -> how many. A new one fails the test below.
KNOWN_BRANCHES: dict[str, int] = {}


def _maker_branches(path: Path) -> list[int]:
    """Lines where a comparison (==, !=, in, not in) has a maker's name as a string operand."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            texts = [c.value for o in operands for c in ast.walk(o)
                     if isinstance(c, ast.Constant) and isinstance(c.value, str)]
            if any(t.casefold() in MAKER_WORDS for t in texts):
                lines.append(node.lineno)
    return lines


def test_no_module_outside_the_makers_branches_on_a_maker() -> None:
    """The shared modules ask the registry (kept-out bands, reasons, tags, hooks); a comparison
    with a maker's name elsewhere is a quirk that belongs in that maker's module."""
    found = {}
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(("pipeline/ingest/cameras/", "pipeline/sim/")):  # the makers; the simulator writes their files
            continue
        lines = _maker_branches(path)
        if lines:
            found[rel] = len(lines)
    assert not {k: v for k, v in found.items() if k.startswith("pipeline/ingest/")}
    assert found == KNOWN_BRANCHES


#: The modules of pipeline/ingest/cameras that any module may import: the registry and the
#: dispatcher that asks it. A maker's own module is imported only by the dispatcher's walk.
SHARED_CAMERA_MODULES = {"pipeline.ingest.cameras", "pipeline.ingest.cameras.registry",
                         "pipeline.ingest.cameras.dispatch"}


def test_no_module_outside_the_makers_imports_a_maker_module() -> None:
    """A quirk reached by importing a maker's module from shared code (DJI's band registration,
    Parrot's RGB sibling position) is a hook on its Maker record instead, so that a new maker
    with the same quirk is one module and one catalog file."""
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")) + sorted((ROOT / "flows").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(("pipeline/ingest/cameras/", "pipeline/sim/")):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([node.module or ""] if isinstance(node, ast.ImportFrom)
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            found += [f"{rel}: {n}" for n in names
                      if n.startswith("pipeline.ingest.cameras") and n not in SHARED_CAMERA_MODULES]
    assert found == []


def test_no_module_outside_the_makers_names_a_makers_xmp_namespace() -> None:
    """Each maker declares its own XMP namespaces (:attr:`Maker.namespaces`); the parser knows
    them from the registry, so no shared module lists a maker's namespace URI or key."""
    from pipeline.ingest import xmp

    uris = {uri.rstrip("/") for m in registry.MAKERS.values() for uris in m.namespaces.values() for uri in uris}
    assert {"http://micasense.com/MicaSense/1.0", "http://www.dji.com/drone-dji/1.0"} <= uris  # the walk sees them
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")) + sorted((ROOT / "flows").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if not rel.startswith(("pipeline/ingest/cameras/", "pipeline/sim/")):
            text = path.read_text()
            found += [f"{rel}: {uri}" for uri in sorted(uris) if uri in text]
    assert found == []
    assert set(xmp.NAMESPACES) == {"Camera", "tiff", "exif"}  # the shared schemas only
    assert not {k for m in registry.MAKERS.values() for k in m.namespaces} & set(xmp.NAMESPACES)
    assert xmp.default_namespaces() == ("Camera", "MicaSense")  # MicaSense's own declaration
    packet = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              '<rdf:Description xmlns:ILS="http://sentera.com/ILS/1.0/" ILS:Clear="5644"/></rdf:RDF></x:xmpmeta>')
    assert xmp.Xmp.parse(packet, "a.jpg").number("Clear", ("ILS",)) == 5644  # Sentera's, from its module
