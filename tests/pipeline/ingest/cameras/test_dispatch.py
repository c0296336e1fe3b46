"""The camera makers' registry and dispatcher (pipeline.ingest.cameras): every maker registers
itself, a file goes to the maker its tags name, a band's radiance to the maker of its
radiometry, and a new maker is one more registered module."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml

from mscal_core.vendors import sentera_relative_radiance
from pipeline.ingest.camera_meta import meta_from_tags, read_capture_meta, read_file_metas
from pipeline.ingest.cameras import registry
from pipeline.ingest.cameras.dispatch import factory_models, factory_radiance, maker_for_model
from pipeline.ingest.cameras.registry import Maker, maker_of, radiance_unit, register
from pipeline.ingest.meta import CaptureMeta, TagContext, factory_vignetting
from tests.micasense_data import require_data

DATA_ROOT = Path(__file__).parents[4].parent / "shared" / "data"
CATALOG = Path(__file__).parents[4] / "catalogs" / "cameras"


def test_every_maker_is_registered_with_the_catalogs_models() -> None:
    """The four makers are registered; the catalog's factory_model names are exactly theirs."""
    assert sorted(registry.MAKERS) == ["dji", "micasense", "parrot", "sentera"]
    used = {yaml.safe_load(p.read_text()).get("factory_model") for p in CATALOG.glob("*.yaml")} - {None}
    assert used == set(factory_models()) == {"micasense", "sequoia", "dji", "sentera"}
    assert maker_for_model("sequoia").name == "parrot"
    assert {r: maker_of(r).name for r in ("micasense", "thermal", "panchro", "sequoia", "dji", "sentera")} == {
        "micasense": "micasense", "thermal": "micasense", "panchro": "micasense", "sequoia": "parrot",
        "dji": "dji", "sentera": "sentera"}
    assert radiance_unit("thermal") == "K"


def test_real_files_go_to_their_makers() -> None:
    require_data()
    assert read_capture_meta(DATA_ROOT / "micasense-rededge" / "IMG_0000_1.tif").radiometry == "micasense"
    assert read_capture_meta(DATA_ROOT / "parrot-sequoia" / "IMG_180413_080658_0000_NIR.TIF").radiometry == "sequoia"
    metas = read_file_metas(DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg")
    assert [m.radiometry for m in metas] == ["sentera"] * len(metas) and len(metas) == 2


def test_sentera_radiance_is_the_pure_formula() -> None:
    """The Sentera module's radiance is mscal_core's formula on the band's tags (bit for bit)."""
    require_data()
    path = DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg"
    import cv2

    rgb = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
    for meta in read_file_metas(path):
        got = factory_radiance(meta, rgb[:, :, meta.channel], channels=rgb)
        want = sentera_relative_radiance(rgb[:, :, meta.channel], black_level=meta.black_level, gain=meta.gain,
                                         exposure_s=meta.exposure_s, bits_per_sample=8, channels=rgb,
                                         matrix=meta.maker_tag("channel_mix"), channel=meta.channel)
        np.testing.assert_array_equal(got, want)
        assert np.isfinite(got).mean() > 0.9


def _tags(path: Path) -> dict:
    with tifffile.TiffFile(path) as tif:
        return {t.code: t.value for t in tif.pages[0].tags.values()}


def test_a_new_maker_is_one_registered_module(monkeypatch) -> None:
    """A maker registered like the four (here in the test, as its own module would at import)
    reads the files its tags claim, before the MicaSense fallback, and computes its bands'
    radiance and vignetting."""
    require_data()
    path = DATA_ROOT / "micasense-rededge" / "IMG_0000_1.tif"
    tags = _tags(path)
    base = meta_from_tags(path, tags, (960, 1280), 16)

    def read(ctx: TagContext) -> list[CaptureMeta]:
        return [replace(base, radiometry="acme", make=ctx.make)]

    acme = Maker(name="acme", model="acme", units={"acme": "1 (twice the DN)"},
                 claims=lambda ctx: ctx.make == "Acme", read=read,
                 radiance=lambda meta, dn, parts, channels, out: 2.0 * np.asarray(dn, np.float64),
                 vignetting=lambda radiometry, shape, vtags: np.full(shape, 1.5), order=5)
    monkeypatch.setattr(registry, "MAKERS", dict(registry.MAKERS))
    register(acme)
    assert "acme" in factory_models()
    assert meta_from_tags(path, tags, (960, 1280), 16).radiometry == "micasense"  # Make MicaSense: not Acme's
    meta = meta_from_tags(path, {**tags, 271: "Acme"}, (960, 1280), 16)
    assert (meta.radiometry, meta.make, meta.radiance_unit) == ("acme", "Acme", "1 (twice the DN)")
    dn = np.full((960, 1280), 1000, np.uint16)
    assert factory_radiance(meta, dn)[5, 7] == 2000.0
    assert factory_vignetting(replace(meta, shape=(3, 4)))[2, 3] == 1.5
    with pytest.raises(ValueError, match="registered twice"):
        register(acme)
    with pytest.raises(ValueError, match="claim one model or radiometry"):
        register(replace(acme, name="acme2"))


def test_each_makers_sun_sensor_is_registered_with_it(monkeypatch) -> None:
    """The sun sensor's maker-specific parts live in the makers' modules: the fixed scales (pi
    MicaSense, 1 DJI, 5e-4 Sequoia, none for Sentera, whose ILS reading is only proportional to
    the light), the attitude tags in the order they are tried, and for a new maker its own
    scale, attitude and self-compensated reading are what sun_scale and sunsensor use."""
    import math

    from pipeline.ingest.cameras.registry import AttitudeSource, attitude_sources
    from pipeline.ingest.sun_scale import SunScale, sun_scale, sun_scale_record, sun_sensor_scales
    from pipeline.ingest.sunsensor import band_correction, band_factor, compensated_model, sensor_orientation
    from pipeline.ingest.xmp import Xmp

    assert {r: s.constant for r, s in sun_sensor_scales().items()} == pytest.approx(
        {"micasense": math.pi, "dji": 1.0, "sequoia": 5e-4})
    assert sun_scale("sentera") is None and sun_scale("thermal") is None
    assert sun_scale_record(None)["sun_sensor_scale"]["constant"] == pytest.approx(math.pi)  # the fallback maker's
    assert [a.name for a in attitude_sources()] == [
        "DLS:Yaw/Pitch/Roll", "Camera:IrradianceYaw/Pitch/Roll", "Camera:IrradianceList (sunshine sensor)",
        "drone-dji:FlightYaw/Pitch/RollDegree"]
    require_data()
    sentera = read_file_metas(DATA_ROOT / "sentera-d4k" / "NDRE" / "IMG_00006.jpg")[0]
    assert sentera.radiometry == "sentera"
    assert band_factor(replace(sentera, irradiance=250.0)) == pytest.approx(1 / 250.0)  # its maker's sun_factor
    assert band_factor(replace(sentera, irradiance=None)) is None

    acme = Maker(name="acme", model="acme", units={"acme": "1"}, claims=lambda ctx: False, read=lambda ctx: [],
                 radiance=lambda meta, dn, parts, channels, out: dn,
                 vignetting=lambda radiometry, shape, vtags: np.ones(shape),
                 sun_scales={"acme": SunScale(2.0, "R = 2 L / E", "a test maker", False)},
                 attitude=(AttitudeSource(25, "Acme:Y/P/R", lambda x: x.angles(("Y", "P", "R"), ("Acme",), True)),),
                 compensated=lambda x: x.has("Done", ("Acme",)), compensated_model="Acme reading as written")
    monkeypatch.setattr(registry, "MAKERS", dict(registry.MAKERS))
    register(acme)
    assert sun_scale("acme").constant == 2.0 and sun_sensor_scales()["acme"].source == "a test maker"
    aircraft = {("Camera", "Yaw"): "10", ("Camera", "Pitch"): "1", ("Camera", "Roll"): "2"}
    assert sensor_orientation(Xmp(aircraft, "a.tif")).source == "Camera:Yaw/Pitch/Roll"  # the shared fallback
    o = sensor_orientation(Xmp({**aircraft, ("Acme", "Y"): "90", ("Acme", "P"): "0", ("Acme", "R"): "0"}, "a.tif"))
    assert o.source == "Acme:Y/P/R" and o.yaw == pytest.approx(math.pi / 2)  # rank 25: before the aircraft's 90
    o = sensor_orientation(Xmp({("Acme", "Y"): "90", ("Acme", "P"): "0", ("Acme", "R"): "0",
                                ("DLS", "Yaw"): "0.5", ("DLS", "Pitch"): "0", ("DLS", "Roll"): "0"}, "a.tif"))
    assert o.source == "DLS:Yaw/Pitch/Roll" and o.yaw == 0.5  # MicaSense's rank 10 first
    done = Xmp({("Acme", "Done"): "1"}, "a.tif")
    assert compensated_model(done) == "Acme reading as written"
    corr, tilt, inc, model = band_correction(done, 0.6, 1.0, sensor_orientation(done))
    assert (corr, model) == (1.0, "Acme reading as written") and math.isnan(tilt) and math.isnan(inc)
