"""Sentera band files (pipeline.ingest.cameras.sentera): one meta per kept channel of a Double 4K JPEG,
the 6X's band folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.ingest import catalog
from pipeline.ingest.camera_meta import read_file_metas
from tests import camera_files as cf

DATA_ROOT = Path(__file__).parents[4].parent / "shared" / "data"


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


def test_sentera_6x_session_grouping(tmp_path) -> None:
    """A 6X session: the files of one name in the band folders are one capture, each band by
    its XMP BandName, EXIF read from IFD0; a truncated band file quarantines its capture only,
    naming the file; a band in two folders is named too."""
    from pipeline.ingest.grouping import group_captures

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

    from pipeline.ingest.grouping import group_captures

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


def test_sentera_6x_cal_captures_are_captures(tmp_path) -> None:
    """Sentera names the 6X's panel captures CAL_NNNNN.tif (py-radiometric-corrections
    sensor_defs: "calibration images are all named CAL_...tif"): they are captures of the
    session (panel candidates), not files skipped as foreign."""
    from pipeline.ingest.grouping import group_captures

    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    session = cf.sentera_6x(tmp_path / "f")
    for p in session.glob("*/IMG_00006.tif"):
        p.rename(p.with_name("CAL_00006.tif"))
    caps, problems = group_captures(session, catalog.load_camera("sentera-6x"))
    assert problems == [] and [c.name for c in caps] == ["CAL_00006", "IMG_00007"]
    assert len(caps[0].metas) == 5
