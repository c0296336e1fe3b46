"""The per-frame TIFFs read back as photogrammetry software reads them, one test per
camera kind: the snapshot mosaic camera (synthetic session, its catalog's camera and the
calibration's intrinsics), and the real MicaSense RedEdge, Parrot Sequoia and Sentera Double
4K captures (../shared/data) through the factory chain.

Readers: exifread and the XMP packet cut out of the file bytes as OpenDroneMap's
``opendm/photo.py`` does (:mod:`tests.photo_readers`), and ExifTool (skipped without it).
Every value is compared with the source file's own, read by the same reader.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr

from pipeline.products.writers import SOFTWARE
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests.photo_readers import (
    dms_to_decimal,
    exif_tags,
    exiftool_tags,
    odm_focal_ratio,
    odm_get_xmp_tag,
    odm_xmp,
    require_exiftool,
)

DATA = Path(__file__).parents[3].parent / "shared" / "data"
CAPTURE_ID_TAGS = ["@drone-dji:CaptureUUID", "MicaSense:CaptureId", "@Camera:ImageUniqueID", "@Camera:CaptureUUID"]
BAND_TAGS = ["Camera:BandName", "@Camera:BandName", "FLIR:BandName"]


def _data(name: str) -> Path:
    folder = DATA / name
    if not folder.is_dir():
        pytest.skip(f"sample captures not found in {folder}")
    return folder


def _factory(folder: Path, out: Path, *extra: str) -> Path:
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), *extra]) == 0
    return out


@pytest.fixture(scope="module")
def micasense(tmp_path_factory) -> Path:
    return _factory(_data("micasense-rededge"), tmp_path_factory.mktemp("rb") / "micasense",
                    "--panel-reflectance", "micasense-rp02-1603036-sc", "--products", "radiance")


@pytest.fixture(scope="module")
def sequoia(tmp_path_factory) -> Path:
    return _factory(_data("parrot-sequoia"), tmp_path_factory.mktemp("rb") / "sequoia")


@pytest.fixture(scope="module")
def sentera(tmp_path_factory) -> Path:
    return _factory(_data("sentera-d4k") / "NDRE", tmp_path_factory.mktemp("rb") / "sentera")


@pytest.fixture(scope="module")
def snapshot(small, tmp_path_factory) -> tuple[Path, Path, Path]:
    session, calib = small
    out = tmp_path_factory.mktemp("rb") / "snapshot"
    assert main(["apply", str(session / "flights" / "field"), "--calibration", str(calib), "-o", str(out)]) == 0
    return session, calib, out


# --------------------------------------------------------------------------- helpers


def _f(tag) -> float:
    v = tag.values[0] if isinstance(tag.values, list) else tag.values
    return float(v) if isinstance(v, (int, float)) else float(v.num) / float(v.den)


def _position(tags: dict) -> tuple[float, float, float] | None:
    if "GPS GPSLatitude" not in tags:
        return None
    alt = _f(tags["GPS GPSAltitude"]) * (-1 if tags["GPS GPSAltitudeRef"].values[0] else 1)
    return (dms_to_decimal(tags["GPS GPSLatitude"], tags["GPS GPSLatitudeRef"]),
            dms_to_decimal(tags["GPS GPSLongitude"], tags["GPS GPSLongitudeRef"]), alt)


def _odm_calibrates(tags: dict, xt: dict) -> bool:
    """OpenDroneMap's ``dn_to_radiance`` changes the values only with a1
    (MicaSense:RadiometricCalibration) or a photometric exposure (ExposureTime and FNumber)."""
    a1 = odm_get_xmp_tag(xt, ["MicaSense:RadiometricCalibration"])
    return a1 is not None or ("EXIF ExposureTime" in tags and "EXIF FNumber" in tags)


def _check_marker(tags: dict, xt: dict) -> None:
    """The reflectance marker (pipeline.products.writers): ODM keeps the values in every
    --radiometric-calibration mode (no radiance model, pi L / E with E = pi), and says so."""
    assert not _odm_calibrates(tags, xt)
    assert float(odm_get_xmp_tag(xt, ["Camera:HorizontalIrradiance"])) == pytest.approx(math.pi, rel=1e-15)
    for raw_tag in ("Camera:Irradiance", "Camera:SunSensor", "Camera:VignettingPolynomial", "Camera:BandSensitivity"):
        assert raw_tag not in xt
    assert "Image BlackLevel" not in tags and "EXIF ISOSpeed" not in tags and "EXIF ISOSpeedRatings" not in tags
    assert xt["@mscal:Quantity"] == "reflectance"
    assert "already reflectance" in tags["Image ImageDescription"].values


def _check_against_source(out_tif: Path, source: Path, band: str) -> tuple[dict, dict]:
    """Camera model, lens, time and position of ``out_tif`` equal ``source``'s (same readers)."""
    tags, src = exif_tags(out_tif, True), exif_tags(source, True)
    (xt,) = odm_xmp(out_tif)
    assert tags["Image Make"].values.strip() == src["Image Make"].values.strip()
    assert tags["Image Model"].values.strip() == src["Image Model"].values.strip()
    assert tags["Image Software"].values == SOFTWARE and SOFTWARE.startswith("mscal ")
    for name in ("EXIF FNumber", "EXIF FocalLength", "EXIF FocalPlaneXResolution", "EXIF FocalPlaneYResolution"):
        assert _f(tags[name]) == pytest.approx(_f(src[name]), rel=1e-7), name
    assert tags["EXIF FocalPlaneResolutionUnit"].values == src["EXIF FocalPlaneResolutionUnit"].values
    if "EXIF FocalLengthIn35mmFilm" in src:
        assert tags["EXIF FocalLengthIn35mmFilm"].values == src["EXIF FocalLengthIn35mmFilm"].values
    width = int(str(tags["Image ImageWidth"]))
    assert odm_focal_ratio(out_tif, width) == pytest.approx(odm_focal_ratio(source, width), rel=1e-7)
    assert tags["EXIF DateTimeOriginal"].values == src["EXIF DateTimeOriginal"].values
    pos, src_pos = _position(tags), _position(src)
    if src_pos is None:
        assert pos is None
    else:
        assert pos[:2] == pytest.approx(src_pos[:2], abs=1e-8) and pos[2] == pytest.approx(src_pos[2], abs=1e-3)
    assert odm_get_xmp_tag(xt, BAND_TAGS) == band
    _check_marker(tags, xt)
    return tags, xt


def _source_xmp(source: Path) -> dict:
    (sx,) = odm_xmp(source) if source.suffix.lower() != ".tif" else [_merged(source)]
    return sx


def _merged(source: Path) -> dict:
    """MicaSense writes one rdf:Description per namespace: merged, as ODM iterates them."""
    out: dict = {}
    for d in odm_xmp(source):
        out.update(d)
    return out


# --------------------------------------------------------------------------- tests


def test_micasense_tiffs_carry_the_rededge_camera_and_its_capture_id(micasense) -> None:
    data = _data("micasense-rededge")
    run = json.loads((micasense / "run.json").read_text())
    assert run_value(run, "panels") == [{"capture": "IMG_0000", "reason": "reflectance panel of the panel route "
                                                                "(--panel-reflectance)"}]
    assert sorted(p.name for p in (micasense / "photogrammetry").iterdir()) == [
        f"IMG_0001_{b}.tif" for b in ("Blue", "Green", "NIR", "Red", "RedEdge")]
    assert sorted(p.name for p in (micasense / "panels").iterdir()) == [
        f"IMG_0000_{b}.tif" for b in ("Blue", "Green", "NIR", "Red", "RedEdge")]
    assert [p.name for p in (micasense / "ndvi").iterdir()] == ["IMG_0001.tif"]
    refl = xr.open_zarr(micasense / "reflectance.zarr")
    for suffix, band, file_band in ((5, "Red edge", "RedEdge"), (1, "Blue", "Blue")):
        source = data / f"IMG_0001_{suffix}.tif"
        out = micasense / "photogrammetry" / f"IMG_0001_{file_band}.tif"
        _, xt = _check_against_source(out, source, band)
        sx = _merged(source)
        assert odm_get_xmp_tag(xt, CAPTURE_ID_TAGS) == odm_get_xmp_tag(sx, CAPTURE_ID_TAGS) == "g2R43Qr5m7EeTFGbkh1W"
        assert odm_get_xmp_tag(xt, ["DLS:SensorId", "@Camera:RigCameraIndex"]) == str(suffix - 1)
        for tag in ("Camera:PerspectiveFocalLength", "Camera:PrincipalPoint", "Camera:ModelType"):
            assert odm_get_xmp_tag(xt, [tag]) == odm_get_xmp_tag(sx, [tag]), tag
        assert [float(v) for v in xt["Camera:PerspectiveDistortion"].split(",")] == [
            float(v) for v in odm_get_xmp_tag(sx, ["Camera:PerspectiveDistortion"]).replace(",", " ").split()]
        assert xt["Camera:RigName"] == "RedEdge"
        expect = refl["reflectance"].sel(frame="IMG_0001").isel(band=suffix - 1).values
        img = tifffile.imread(out)
        ok = np.isfinite(expect)
        np.testing.assert_allclose(img[ok] / 32768.0, np.clip(expect[ok], 0, 65534 / 32768), atol=0.5 / 32768 + 1e-7)
        assert np.all(img[~ok] == 65535)
    # the panel capture carries its own capture id, apart from the survey frames
    (px,) = odm_xmp(micasense / "panels" / "IMG_0000_Blue.tif")
    assert odm_get_xmp_tag(px, CAPTURE_ID_TAGS) == odm_get_xmp_tag(_merged(data / "IMG_0000_1.tif"), CAPTURE_ID_TAGS)


def test_sequoia_tiffs_keep_the_capture_uuid_and_turn_the_principal_point_upright(sequoia) -> None:
    data = _data("parrot-sequoia")
    out = sorted((sequoia / "photogrammetry").iterdir())
    assert [p.name for p in out] == [f"IMG_180413_080658_0000_{b}.tif" for b in ("Green", "NIR", "Red", "RedEdge")]
    assert list((sequoia / "panels").iterdir()) == []
    first = data / "IMG_180413_080658_0000_GRE.TIF"  # the capture's time and position are its first band's
    source = data / "IMG_180413_080658_0000_REG.TIF"
    tags, xt = _check_against_source(sequoia / "photogrammetry" / "IMG_180413_080658_0000_RedEdge.tif", source,
                                      "Red edge")
    assert exif_tags(first)["EXIF SubSecTimeOriginal"].values.startswith(tags["EXIF SubSecTimeOriginal"].values)
    sx = odm_xmp(source)[0]
    assert odm_get_xmp_tag(xt, CAPTURE_ID_TAGS) == odm_get_xmp_tag(sx, CAPTURE_ID_TAGS) == \
        "BE5AB0ABA969E1CB424A394AA2FD3208"
    assert xt["Camera:RigName"] == odm_get_xmp_tag(sx, ["Camera:RigName", "@Camera:RigName"]) == "Sequoia"
    assert odm_get_xmp_tag(xt, ["@Camera:ModelType", "Camera:ModelType"]) == "fisheye"
    for tag in ("Camera:FisheyeAffineMatrix", "Camera:FisheyePolynomial"):
        assert xt[tag].split(",") == odm_get_xmp_tag(sx, [tag, "@" + tag]).replace(" ", ",").split(",")
    # stored rotated 180 degrees (EXIF Orientation 3), written upright: the principal point turns too
    assert tags["Image Orientation"].values == [1] and exif_tags(source)["Image Orientation"].values == [3]
    cx, cy = (float(v) for v in odm_get_xmp_tag(sx, ["Camera:PrincipalPoint", "@Camera:PrincipalPoint"]).split(","))
    mm = 1280 / (_f(tags["EXIF FocalPlaneXResolution"])), 960 / _f(tags["EXIF FocalPlaneYResolution"])
    assert [float(v) for v in xt["Camera:PrincipalPoint"].split(",")] == pytest.approx([mm[0] - cx, mm[1] - cy])


def test_sentera_tiffs_carry_the_d4k_camera_per_channel(sentera) -> None:
    data = _data("sentera-d4k") / "NDRE"
    names = sorted(p.name for p in (sentera / "photogrammetry").iterdir())
    assert names == ["IMG_00006_NIR.tif", "IMG_00006_RedEdge.tif", "IMG_00007_NIR.tif", "IMG_00007_RedEdge.tif"]
    ids = {}
    for cap in ("IMG_00006", "IMG_00007"):
        for band, file_band in (("NIR", "NIR"), ("RedEdge", "RedEdge")):
            _, xt = _check_against_source(sentera / "photogrammetry" / f"{cap}_{file_band}.tif", data / f"{cap}.jpg",
                                          band)
            sx = odm_xmp(data / f"{cap}.jpg")[0]
            for tag in ("Camera:PerspectiveFocalLength", "Camera:PrincipalPoint", "Camera:PerspectiveDistortion",
                        "Camera:RigName", "Camera:ModelType"):
                assert odm_get_xmp_tag(xt, [tag]) == odm_get_xmp_tag(sx, [tag, "@" + tag]), tag
            ids.setdefault(cap, set()).add(odm_get_xmp_tag(xt, CAPTURE_ID_TAGS))
    # no capture id in the source: one derived per capture, shared by its bands, distinct between captures
    assert all(len(v) == 1 for v in ids.values()) and len(set.union(*ids.values())) == 2


def test_snapshot_tiffs_carry_the_catalog_camera_and_the_calibration_intrinsics(snapshot) -> None:
    session, calib, out = snapshot
    intr = xr.open_zarr(calib)["intrinsics"].values[0]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr
    pitch_mm = 5.5e-3 * 5  # catalog exif.pixel_um times the 5x5 mosaic
    with (session / "flights" / "field" / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        stem = Path(row["file"]).stem
        p = out / "photogrammetry" / f"{stem}_b670.tif"
        tags = exif_tags(p, True)
        (xt,) = odm_xmp(p)
        assert (tags["Image Make"].values, tags["Image Model"].values) == ("XIMEA", "MQ022HG-IM-SM5X5-NIR")
        assert _f(tags["EXIF FocalLength"]) == pytest.approx(fx * pitch_mm, rel=1e-7)
        assert _f(tags["EXIF FocalPlaneXResolution"]) == pytest.approx(10 / pitch_mm, rel=1e-7)
        assert tags["EXIF FocalPlaneResolutionUnit"].values == [3]
        assert odm_focal_ratio(p, 409) == pytest.approx(fx / 409, rel=0.02)  # 35 mm equivalent is a whole mm
        assert float(xt["Camera:PerspectiveFocalLength"]) == pytest.approx(fx * pitch_mm, rel=1e-7)
        assert xt["Camera:PerspectiveFocalLengthUnits"] == "mm"
        assert [float(v) for v in xt["Camera:PrincipalPoint"].split(",")] == pytest.approx(
            [cx * pitch_mm, cy * pitch_mm])
        assert [float(v) for v in xt["Camera:PerspectiveDistortion"].split(",")] == pytest.approx([k1, k2, k3, p1, p2])
        assert odm_get_xmp_tag(xt, BAND_TAGS) == "b670"
        assert xt["Camera:RigName"] == "ximea-mq022hg-sm5x5-nir"
        lat, lon, alt = _position(tags)
        assert (lat, lon, alt) == pytest.approx((float(row["lat"]), float(row["lon"]), float(row["alt_m"])), abs=1e-6)
        assert len(odm_get_xmp_tag(xt, CAPTURE_ID_TAGS)) == 36
        _check_marker(tags, xt)


@pytest.mark.parametrize("kind", ["micasense", "sequoia", "sentera", "snapshot"])
def test_exiftool_reads_camera_band_capture_and_marker(kind, request) -> None:
    """ExifTool (the reader Pix4D's and Agisoft's documents point to) finds the same tags."""
    require_exiftool()  # skips here when ExifTool is absent, before any apply runs
    run = request.getfixturevalue(kind)
    out = run[2] if kind == "snapshot" else run
    cases = {
        "micasense": ("IMG_0001_RedEdge.tif", _data("micasense-rededge") / "IMG_0001_5.tif", "Red edge"),
        "sequoia": ("IMG_180413_080658_0000_RedEdge.tif", _data("parrot-sequoia") / "IMG_180413_080658_0000_REG.TIF",
                    "Red edge"),
        "sentera": ("IMG_00006_NIR.tif", _data("sentera-d4k") / "NDRE" / "IMG_00006.jpg", "NIR"),
        "snapshot": (None, None, "b670"),
    }
    name, source, band = cases[kind]
    tif = out / "photogrammetry" / name if name else sorted((out / "photogrammetry").glob("*_b670.tif"))[0]
    got, *src = exiftool_tags(tif, *([source] if source else []))
    assert got["XMP-Camera:BandName"] == band
    assert got["IFD0:Software"] == SOFTWARE
    assert got["XMP-Camera:HorizontalIrradiance"] == pytest.approx(math.pi)
    assert got["XMP-mscal:Quantity"] == "reflectance" and "ExifIFD:ExposureTime" not in got
    assert got["XMP-Camera:CaptureUUID"]
    if source is None:
        assert (got["IFD0:Make"], got["IFD0:Model"]) == ("XIMEA", "MQ022HG-IM-SM5X5-NIR")
        assert got["ExifIFD:FocalLength"] > 0 and got["Composite:GPSLatitude"] > 0
        return
    (s,) = src
    for key in ("IFD0:Make", "IFD0:Model", "ExifIFD:FocalLength", "ExifIFD:FNumber", "ExifIFD:FocalPlaneXResolution",
                "ExifIFD:DateTimeOriginal"):
        assert got[key] == pytest.approx(s[key], rel=1e-7) if isinstance(s[key], float) else got[key] == s[key], key
    for key in ("Composite:GPSLatitude", "Composite:GPSLongitude"):
        assert (key in got) == (key in s)
        if key in s:
            assert got[key] == pytest.approx(s[key], abs=1e-8)
    ids = [s.get(k) for k in ("XMP-MicaSense:CaptureId", "XMP-Camera:CaptureUUID") if s.get(k)]
    if ids:
        assert ids[0] in (got.get("XMP-MicaSense:CaptureId"), got["XMP-Camera:CaptureUUID"])


def _numeric(v: xr.Variable) -> bool:
    return v.dtype.kind in "biuf"


def test_stores_carry_units_everywhere_and_one_cf_set_on_both_apply_paths(micasense, snapshot) -> None:
    """Every numeric variable of the calibration store, raw.zarr and reflectance.zarr (field
    and factory path) has units; lat, lon and time carry the same CF attributes on both."""
    _, calib, field = snapshot
    stores = {"calibration": calib, "field reflectance": field / "reflectance.zarr", "field raw": field / "raw.zarr",
              "factory reflectance": micasense / "reflectance.zarr", "factory raw": micasense / "raw.zarr"}
    missing = {}
    for what, path in stores.items():
        ds = xr.open_zarr(path)
        assert ds.attrs["Conventions"] == "CF-1.10", what
        missing[what] = sorted(n for n, v in ds.variables.items() if _numeric(v) and "units" not in v.attrs)
    assert missing == {what: [] for what in stores}
    f, g = xr.open_zarr(field / "reflectance.zarr"), xr.open_zarr(micasense / "reflectance.zarr")
    for name in ("lat", "lon", "time", "alt_m", "band", "wavelength"):
        assert f[name].attrs == g[name].attrs, name
    assert f["exposure_ms"].attrs["units"] == g["exposure_ms"].attrs["units"] == "ms"  # a capture's: the median
    assert (f["lat"].attrs["standard_name"], f["lon"].attrs["units"], g["time"].attrs["standard_name"]) == (
        "latitude", "degrees_east", "time")
    assert g["reflectance"].attrs["units"] == "1" and g["radiance"].attrs["units"] == "W m-2 sr-1 nm-1"
    assert f["ndvi"].attrs["units"] == g["ndvi"].attrs["units"] == "1"
