"""Flight discovery and ingest into OUT/raw.zarr (docs/architecture.md, "Flights").

Layout, coordinates and CF attributes of the cube; every kind of bad frame quarantined with a
reason naming the file while the rest go on; incremental and idempotent re-runs (nothing
already ingested is decoded again); changed files; EXIF fallback; SIGKILL at many points of
an ingest followed by a re-run gives the cube of one uninterrupted run.

Most tests use a tiny 2x2-mosaic test camera (catalog written to a temporary folder) so that
ingests take milliseconds; layout and EXIF tests use the paper's Ximea camera at full size.
"""

from __future__ import annotations

import csv
import hashlib
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr
import zarr

import mscal_core
import pipeline.ingest.raw as ingest_mod
import pipeline.ingest.session as session_mod
from mscal_core.errors import InputError, SessionError
from pipeline.ingest.catalog import load_camera
from pipeline.ingest.discover import discover_flight
from pipeline.ingest.medians import DN_MEDIAN
from pipeline.ingest.raw import cube_lock, ingest_flight
from pipeline.ingest.session import exif_record, read_bands
from pipeline.ingest.tiff import decode_frame, decode_raw
from tests.pipeline.ingest.kill_points import KILL_CODE, arm

ROOT = Path(__file__).resolve().parents[3]
MICASENSE = ROOT.parent / "shared" / "data" / "micasense-rededge"
XIMEA = "ximea-mq022hg-sm5x5-nir"
TINY = "tiny-mosaic-test"
TINY_YAML = """\
name: tiny-mosaic-test
description: 2x2 mosaic test camera (ingest tests)
bit_depth: 10
sensor: {width: 40, height: 30}
layout: {kind: mosaic, pattern: [2, 2], grid: [15, 20]}
bands:
  - {name: b600, wavelength_nm: 600, mosaic: [0, 0]}
  - {name: b650, wavelength_nm: 650, mosaic: [0, 1]}
  - {name: b700, wavelength_nm: 700, mosaic: [1, 0]}
  - {name: b800, wavelength_nm: 800, mosaic: [1, 1]}
"""
MICA1 = """\
name: mica-band1-test
description: one band of a MicaSense RedEdge as a 1x1 "mosaic" (EXIF fallback test)
bit_depth: 16  # the files hold 12-bit DN in the high bits
sensor: {width: 1280, height: 960}
layout: {kind: mosaic, pattern: [1, 1], grid: [960, 1280]}
bands:
  - {name: Blue, wavelength_nm: 475, mosaic: [0, 0]}
"""
COLUMNS = ("file", "exposure_ms", "gain", "time", "lat", "lon", "alt_m")


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> str:
    root = tmp_path_factory.mktemp("catalog")
    (root / "cameras").mkdir()
    (root / "cameras" / f"{TINY}.yaml").write_text(TINY_YAML)
    (root / "cameras" / "mica-band1-test.yaml").write_text(MICA1)
    old = os.environ.get("MSCAL_CATALOG_PATH")
    os.environ["MSCAL_CATALOG_PATH"] = str(root) + (os.pathsep + old if old else "")
    yield str(root)
    if old is None:
        os.environ.pop("MSCAL_CATALOG_PATH", None)
    else:
        os.environ["MSCAL_CATALOG_PATH"] = old


def _mosaic(seed: int, shape=(30, 40), top: int = 1023) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, top + 1, shape, dtype=np.uint16)


def _row(name: str, exposure="2.5", gain="1", time="2026-05-01T10:00:00Z", lat="47.1", lon="8.5", alt="120"):
    return {"file": name, "exposure_ms": exposure, "gain": gain, "time": time, "lat": lat, "lon": lon, "alt_m": alt}


def _write_csv(folder: Path, rows: list[dict]) -> None:
    with (folder / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)


def _flight(folder: Path, n: int, *, shape=(30, 40), start: int = 0, prefix: str = "IMG_", seed: int = 0) -> Path:
    """``n`` frames with rows in frames.csv (appended to an existing frames.csv)."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = list(csv.DictReader((folder / "frames.csv").open())) if (folder / "frames.csv").exists() else []
    for i in range(start, start + n):
        name = f"{prefix}{i:04d}.tif"
        tifffile.imwrite(folder / name, _mosaic(seed * 1000 + i, shape), photometric="minisblack")
        rows.append(_row(name, exposure=f"{1 + i * 0.5:g}", time=f"2026-05-01T10:00:{i % 60:02d}Z", lat=f"{47 + i * 1e-5:.6f}"))
    _write_csv(folder, rows)
    return folder


def _snapshot(path: Path) -> dict:
    """Everything a reader sees in the cube."""
    ds = xr.open_zarr(path).load()
    return {
        "dn": ds["dn"].values.copy(),
        "coords": {k: ds[k].values.copy() for k in ds.coords},
        "attrs": dict(ds.attrs),
        "var_attrs": {k: dict(ds[k].attrs) for k in ds.variables},
    }


def _assert_same(a: dict, b: dict) -> None:
    assert a["dn"].dtype == b["dn"].dtype == np.uint16
    np.testing.assert_array_equal(a["dn"], b["dn"])
    assert a["coords"].keys() == b["coords"].keys()
    for k in a["coords"]:
        va, vb = a["coords"][k], b["coords"][k]
        if va.dtype.kind in "fM":
            np.testing.assert_array_equal(va, vb)
        else:
            assert [str(x) for x in va] == [str(x) for x in vb], k
    assert a["attrs"] == b["attrs"]
    assert a["var_attrs"] == b["var_attrs"]


class _Spy:
    """Records which files ingest decodes (decode_frame runs in worker threads)."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, data, path):
        with self.lock:
            self.names.append(Path(path).name)
        return decode_frame(data, path)


@pytest.fixture
def spy(monkeypatch) -> _Spy:
    s = _Spy()
    monkeypatch.setattr(session_mod, "decode_frame", s)  # ingest decodes through session.stored_bands
    return s


# --------------------------------------------------------------------------- layout


def test_cube_layout_coordinates_and_cf_attributes(tmp_path) -> None:
    cam = load_camera(XIMEA)
    d = tmp_path / "flight"
    d.mkdir()
    for i, name in enumerate(["c.tif", "a.tif", "b.tif"]):
        tifffile.imwrite(d / name, _mosaic(i, (1088, 2048)), photometric="minisblack")
    _write_csv(d, [
        _row("a.tif", exposure="2.5", gain="2", time="2026-05-01T10:00:00Z", lat="47.1", lon="8.5", alt="120"),
        _row("b.tif", exposure="5", time="2026-05-01T12:00:01.250+02:00", lat="", lon="", alt=""),
        _row("c.tif", exposure="1.25", time="", lat="-33.5", lon="-70.25", alt="-3"),
    ])
    out = tmp_path / "out" / "raw.zarr"
    res = ingest_flight(d, cam, out)
    assert (res.frames_added, res.frames_already_present, res.n_frames, res.quarantined) == (3, 0, 3, [])
    assert res.added == ["a", "b", "c"]

    ds = xr.open_zarr(out)
    assert ds["dn"].dims == ("frame", "band", "y", "x")
    assert ds["dn"].dtype == np.uint16
    assert ds["dn"].shape == (3, 25, 217, 409)
    assert ds["dn"].encoding["chunks"] == (1, 25, 217, 409)  # storage chunk = one frame
    assert ds["dn"].chunks == ((1, 1, 1), (25,), (217,), (409,))  # dask chunk = storage chunk
    for k, name in enumerate(["a", "b", "c"]):
        np.testing.assert_array_equal(ds["dn"][k].values, read_bands(d / f"{name}.tif", cam))

    assert list(ds["frame"].values) == ["a", "b", "c"]
    np.testing.assert_array_equal(ds["exposure_ms"].values, [2.5, 5, 1.25])
    np.testing.assert_array_equal(ds["gain"].values, [2, 1, 1])
    assert ds["time"].dtype == np.dtype("datetime64[ns]")
    np.testing.assert_array_equal(
        ds["time"].values,
        np.array(["2026-05-01T10:00:00", "2026-05-01T10:00:01.250", "NaT"], dtype="datetime64[ns]"),
    )
    np.testing.assert_array_equal(ds["lat"].values, [47.1, np.nan, -33.5])
    np.testing.assert_array_equal(ds["lon"].values, [8.5, np.nan, -70.25])
    np.testing.assert_array_equal(ds["alt_m"].values, [120, np.nan, -3])
    assert list(ds["source_file"].values) == ["a.tif", "b.tif", "c.tif"]
    assert list(ds["sha256"].values) == [hashlib.sha256((d / f"{n}.tif").read_bytes()).hexdigest() for n in "abc"]
    for k in ("exposure_ms", "gain", "time", "lat", "lon", "alt_m", "source_file", "sha256"):
        assert ds[k].dims == ("frame",)
    np.testing.assert_array_equal(ds["band"].values, np.arange(25))
    assert list(ds["band_name"].values) == cam.band_names
    np.testing.assert_array_equal(ds["wavelength"].values, cam.wavelengths)

    assert ds.attrs["Conventions"].startswith("CF-")
    assert ds.attrs["camera"] == XIMEA
    assert ds.attrs["mscal_version"] == mscal_core.__version__
    assert ds.attrs["frames_committed"] == 3
    assert ds["lat"].attrs["units"] == "degrees_north"
    assert ds["lon"].attrs["units"] == "degrees_east"
    assert ds["alt_m"].attrs["units"] == "m"
    assert ds["exposure_ms"].attrs["units"] == "ms"
    assert ds["wavelength"].attrs["units"] == "nm"
    for k in ("dn", "exposure_ms", "gain", "time", "lat", "lon", "alt_m", "wavelength", "sha256"):
        assert ds[k].attrs.get("long_name"), k
    assert not list(out.parent.glob(".*tmp-*")) and not list(out.rglob("*.partial"))


# --------------------------------------------------------------------------- quarantine


def test_every_bad_frame_kind_is_quarantined_naming_the_file(tmp_path, catalog) -> None:
    d = _flight(tmp_path / "flight", 3)  # IMG_0000..0002 are good
    rows = list(csv.DictReader((d / "frames.csv").open()))
    tifffile.imwrite(d / "zero.tif", _mosaic(10))
    tifffile.imwrite(d / "negative.tif", _mosaic(11))
    tifffile.imwrite(d / "norow.tif", _mosaic(12))  # no row, no EXIF
    tifffile.imwrite(d / "twice.tif", _mosaic(13))
    (d / "notes.txt").write_text("pilot notes")
    (d / "text.tif").write_text("this is not a TIFF")
    tifffile.imwrite(d / "cut.tif", _mosaic(14))
    raw = (d / "cut.tif").read_bytes()
    (d / "cut.tif").write_bytes(raw[: int(len(raw) * 0.9)])
    tifffile.imwrite(d / "small.tif", _mosaic(15, (20, 30)))
    tifffile.imwrite(d / "bright.tif", np.full((30, 40), 4000, np.uint16))
    shutil.copy(d / "IMG_0001.tif", d / "copy.tif")
    tifffile.imwrite(d / "rgb.tif", np.zeros((30, 40, 3), np.uint16))
    rows += [
        _row("missing.tif"),
        _row("zero.tif", exposure="0"),
        _row("negative.tif", exposure="-2"),
        _row("twice.tif", exposure="1"),
        _row("twice.tif", exposure="2"),
        _row("notes.txt"),
        _row("text.tif"),
        _row("cut.tif"),
        _row("small.tif"),
        _row("bright.tif"),
        _row("copy.tif"),
        _row("rgb.tif"),
    ]
    _write_csv(d, rows)
    res = ingest_flight(d, TINY, tmp_path / "raw.zarr")
    assert res.added == ["IMG_0000", "IMG_0001", "IMG_0002"] and res.n_frames == 3
    reasons = {q["file"]: q["reason"] for q in res.quarantined}
    expected = {
        "missing.tif": "listed but the file does not exist",
        "zero.tif": "exposure_ms 0; it must be positive",
        "negative.tif": "exposure_ms -2; it must be positive",
        "norow.tif": "no exposure time",
        "twice.tif": "listed twice",
        "notes.txt": "not an image file",
        "text.tif": "unreadable or truncated image",
        "cut.tif": "unreadable or truncated image",
        "small.tif": "frame is 30x20 but camera tiny-mosaic-test has a 40x30 sensor",
        "bright.tif": "DN 4000 exceed the 10-bit range",
        "copy.tif": "same content as frame IMG_0001",
        "rgb.tif": "expected a single-channel mosaic",
    }
    assert set(reasons) == set(expected)
    for f, text in expected.items():
        assert text in reasons[f], (f, reasons[f])
        assert f in reasons[f], f"reason does not name the file: {reasons[f]}"
    assert [q["file"] for q in res.quarantined] == sorted(reasons)  # deterministic order
    ds = xr.open_zarr(tmp_path / "raw.zarr")
    assert list(ds["frame"].values) == ["IMG_0000", "IMG_0001", "IMG_0002"]


def test_discovery_alone_and_unreadable_table(tmp_path, catalog) -> None:
    cam = load_camera(TINY)
    d = _flight(tmp_path / "f", 2)
    tifffile.imwrite(d / "IMG_0000.png", _mosaic(3))  # same frame name as IMG_0000.tif
    rows = list(csv.DictReader((d / "frames.csv").open())) + [_row("IMG_0000.png")]
    _write_csv(d, rows)
    found = discover_flight(d, cam)
    assert [r.path.name for r in found.frames] == ["IMG_0001.tif"]
    assert {q["file"] for q in found.quarantined} == {"IMG_0000.tif", "IMG_0000.png"}
    assert all("used by several files" in q["reason"] for q in found.quarantined)

    (d / "frames.csv").write_text("file,exposure\nIMG_0001.tif,1\n")
    with pytest.raises(SessionError, match="frames.csv: column 'exposure_ms' is missing"):
        ingest_flight(d, cam, tmp_path / "raw.zarr")
    with pytest.raises(SessionError, match="frame folder not found"):
        discover_flight(tmp_path / "nowhere", cam)
    with pytest.raises(InputError, match="one file per band"):
        discover_flight(d, load_camera("micasense-rededge"))


def test_all_frames_bad_gives_an_empty_cube(tmp_path, catalog) -> None:
    d = tmp_path / "f"
    d.mkdir()
    (d / "a.tif").write_text("garbage")
    _write_csv(d, [_row("a.tif")])
    res = ingest_flight(d, TINY, tmp_path / "raw.zarr")
    assert res.n_frames == 0 and [q["file"] for q in res.quarantined] == ["a.tif"]
    ds = xr.open_zarr(tmp_path / "raw.zarr")
    assert ds.sizes["frame"] == 0 and ds.sizes["band"] == 4


def test_camera_without_fixed_size_takes_it_from_the_first_frame(tmp_path) -> None:
    import cv2

    d = tmp_path / "f"
    d.mkdir()
    rng = np.random.default_rng(0)
    for name, shape in [("a.png", (4, 5, 3)), ("b.png", (4, 5, 3)), ("c.png", (6, 5, 3))]:
        cv2.imwrite(str(d / name), rng.integers(0, 256, shape, dtype=np.uint8))
    _write_csv(d, [_row("a.png"), _row("b.png"), _row("c.png")])
    res = ingest_flight(d, "generic-rgb8", tmp_path / "raw.zarr")
    assert res.added == ["a", "b"]
    assert [q["file"] for q in res.quarantined] == ["c.png"]
    assert "band stack is 3x6x5 but the datacube's is 3x4x5" in res.quarantined[0]["reason"]
    ds = xr.open_zarr(tmp_path / "raw.zarr")
    assert ds["dn"].shape == (2, 3, 4, 5) and ds["dn"].dtype == np.uint16
    assert list(ds["band_name"].values) == ["red", "green", "blue"]


# --------------------------------------------------------------------------- incremental


def test_rerun_decodes_nothing_and_changes_nothing(tmp_path, catalog, spy) -> None:
    d = _flight(tmp_path / "f", 5)
    out = tmp_path / "raw.zarr"
    first = ingest_flight(d, TINY, out, commit_every=2)
    assert first.frames_added == 5 and sorted(spy.names) == [f"IMG_{i:04d}.tif" for i in range(5)]
    before = _snapshot(out)
    spy.names.clear()
    again = ingest_flight(d, TINY, out, commit_every=2)
    assert spy.names == []  # nothing already in the cube is decoded again
    assert (again.frames_added, again.frames_already_present, again.n_frames, again.quarantined) == (0, 5, 5, [])
    _assert_same(before, _snapshot(out))


def test_new_frames_are_appended_in_name_order(tmp_path, catalog, spy) -> None:
    d = _flight(tmp_path / "f", 3, prefix="M_")
    out = tmp_path / "raw.zarr"
    ingest_flight(d, TINY, out)
    before = _snapshot(out)
    _flight(d, 1, prefix="Z_", start=7, seed=1)
    _flight(d, 1, prefix="A_", start=9, seed=2)  # sorts before the frames already there
    spy.names.clear()
    res = ingest_flight(d, TINY, out)
    assert sorted(spy.names) == ["A_0009.tif", "Z_0007.tif"]
    assert res.added == ["A_0009", "Z_0007"] and res.frames_already_present == 3 and res.n_frames == 5
    after = _snapshot(out)
    assert list(after["coords"]["frame"]) == ["M_0000", "M_0001", "M_0002", "A_0009", "Z_0007"]
    np.testing.assert_array_equal(after["dn"][:3], before["dn"])
    cam = load_camera(TINY)
    np.testing.assert_array_equal(after["dn"][3], read_bands(d / "A_0009.tif", cam))
    np.testing.assert_array_equal(after["dn"][4], read_bands(d / "Z_0007.tif", cam))


def test_band_medians_are_kept_with_each_frame_and_older_cubes_still_append(tmp_path, catalog) -> None:
    """raw.zarr keeps each frame's band medians (dn_median, for the report's frame levels),
    appended frames included; a cube written before it existed takes new frames without it."""
    d = _flight(tmp_path / "f", 3)
    out = tmp_path / "raw.zarr"
    ingest_flight(d, TINY, out, commit_every=2)
    _flight(d, 2, start=3, seed=1)
    ingest_flight(d, TINY, out)
    ds = xr.open_zarr(out).load()
    assert ds[DN_MEDIAN].dims == ("frame", "band") and ds[DN_MEDIAN].shape == (5, ds.sizes["band"])
    np.testing.assert_array_equal(ds[DN_MEDIAN].values, np.median(ds["dn"].values.astype(np.float64), axis=(2, 3)))
    assert len(np.unique(ds[DN_MEDIAN].values[:, 0])) == 5  # each frame its own medians

    older = tmp_path / "older.zarr"
    d2 = _flight(tmp_path / "g", 2, seed=3)
    ingest_flight(d2, TINY, older)
    g = zarr.open_group(str(older), mode="r+")
    del g[DN_MEDIAN]
    zarr.consolidate_metadata(str(older))
    _flight(d2, 1, start=2, seed=4)
    res = ingest_flight(d2, TINY, older)
    assert res.added == ["IMG_0002"] and res.n_frames == 3
    ds = xr.open_zarr(older).load()
    assert DN_MEDIAN not in ds and ds.sizes["frame"] == 3
    np.testing.assert_array_equal(ds["dn"].values[2], read_bands(d2 / "IMG_0002.tif", load_camera(TINY)))


def test_changed_file_is_quarantined_and_the_cube_kept(tmp_path, catalog, spy) -> None:
    d = _flight(tmp_path / "f", 3)
    out = tmp_path / "raw.zarr"
    ingest_flight(d, TINY, out)
    before = _snapshot(out)
    tifffile.imwrite(d / "IMG_0001.tif", _mosaic(99), photometric="minisblack")
    spy.names.clear()
    res = ingest_flight(d, TINY, out)
    assert spy.names == []
    assert res.frames_already_present == 2 and res.frames_added == 0
    assert [q["file"] for q in res.quarantined] == ["IMG_0001.tif"]
    assert "changed since ingest" in res.quarantined[0]["reason"]
    assert "IMG_0001.tif" in res.quarantined[0]["reason"]
    _assert_same(before, _snapshot(out))


def test_output_checks(tmp_path, catalog) -> None:
    d = _flight(tmp_path / "f", 1)
    out = tmp_path / "raw.zarr"
    ingest_flight(d, TINY, out)
    with pytest.raises(InputError, match="holds frames of camera 'tiny-mosaic-test'"):
        ingest_flight(d, XIMEA, out)
    (tmp_path / "junk.zarr").mkdir()
    (tmp_path / "junk.zarr" / "zarr.json").write_text("{}")
    with pytest.raises(InputError, match="not an mscal raw datacube"):
        ingest_flight(d, TINY, tmp_path / "junk.zarr")
    with cube_lock(out):  # another process ingesting into the cube: refused at once, named
        code = (
            "import sys\nfrom pipeline.ingest.raw import ingest_flight\n"
            "try:\n    ingest_flight(sys.argv[1], sys.argv[2], sys.argv[3])\n"
            "except Exception as e:\n    print(type(e).__name__, e)\n"
        )
        p = subprocess.run([sys.executable, "-c", code, str(d), TINY, str(out)], cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
        assert p.stdout.startswith(f"LockedError {out}: another mscal process is writing here: "
                                   f"pid {os.getpid()} on "), (p.stdout, p.stderr)
    assert not (tmp_path / ".raw.zarr.lock").exists()


# --------------------------------------------------------------------------- EXIF fallback


def _tiff_with_exif(path: Path, img: np.ndarray, exposure_s: tuple[int, int]) -> None:
    """A TIFF whose IFD0 points to an EXIF IFD holding ExposureTime (tifffile cannot write one:
    it is written with a private placeholder tag that is then turned into the ExifIFD pointer)."""
    tifffile.imwrite(path, img, photometric="minisblack", extratags=[(65000, "I", 1, 0, True)])
    with tifffile.TiffFile(path) as tf:
        assert tf.byteorder == "<" and not tf.is_bigtiff
        tag = tf.pages[0].tags[65000]
        entry, value = tag.offset, tag.valueoffset
    data = bytearray(path.read_bytes())
    data += b"\0" * (len(data) % 2)
    ifd = len(data)
    data += struct.pack("<H", 1) + struct.pack("<HHII", 33434, 5, 1, ifd + 18) + struct.pack("<I", 0)
    data += struct.pack("<II", *exposure_s)
    data[entry : entry + 2] = struct.pack("<H", 34665)  # ExifIFD (tags stay in ascending order)
    data[value : value + 4] = struct.pack("<I", ifd)
    path.write_bytes(bytes(data))


def test_exif_fallback_for_a_frame_without_a_row(tmp_path) -> None:
    d = tmp_path / "f"
    d.mkdir()
    tifffile.imwrite(d / "a.tif", _mosaic(1, (1088, 2048)), photometric="minisblack")
    _tiff_with_exif(d / "b.tif", _mosaic(2, (1088, 2048)), (1, 400))  # 2.5 ms, no row
    _write_csv(d, [_row("a.tif")])
    assert exif_record(d / "b.tif").exposure_ms == pytest.approx(2.5)
    res = ingest_flight(d, XIMEA, tmp_path / "raw.zarr")
    assert res.added == ["a", "b"] and res.quarantined == []
    ds = xr.open_zarr(tmp_path / "raw.zarr")
    assert ds["exposure_ms"].values[1] == pytest.approx(2.5)
    assert np.isnat(ds["time"].values[1]) and np.isnan(ds["lat"].values[1])


@pytest.mark.skipif(not (MICASENSE / "IMG_0001_1.tif").is_file(), reason="shared data not present")
def test_exif_fallback_with_gps_on_a_real_file(tmp_path, catalog) -> None:
    d = tmp_path / "f"
    d.mkdir()
    shutil.copy(MICASENSE / "IMG_0001_1.tif", d / "IMG_0001_1.tif")  # no frames.csv at all
    rec = exif_record(d / "IMG_0001_1.tif")
    res = ingest_flight(d, "mica-band1-test", tmp_path / "raw.zarr")
    assert res.added == ["IMG_0001_1"] and res.quarantined == []
    ds = xr.open_zarr(tmp_path / "raw.zarr")
    assert ds["dn"].shape == (1, 1, 960, 1280)
    assert ds["exposure_ms"].values[0] == pytest.approx(rec.exposure_ms)
    assert ds["lat"].values[0] == pytest.approx(rec.lat) and ds["lon"].values[0] == pytest.approx(rec.lon)
    assert ds["alt_m"].values[0] == pytest.approx(rec.alt_m)
    assert ds["time"].values[0] == np.datetime64(rec.time, "ns")


# --------------------------------------------------------------------------- SIGKILL


INGEST_CODE = (
    "import sys\nfrom pipeline.ingest.raw import ingest_flight\n"
    "ingest_flight(sys.argv[1], sys.argv[2], sys.argv[3], commit_every=int(sys.argv[4]))\n"
)
COMMIT_EVERY = 3


def _child(flight: str, camera: str, out: str, point: str) -> None:
    arm(point)  # this forked process only
    ingest_flight(flight, camera, out, commit_every=COMMIT_EVERY)


def _killed_run(flight: Path, out: Path, point: str, camera: str = TINY, *, fresh: bool = False) -> None:
    """Run an ingest in another process that SIGKILLs itself at ``point``.

    ``fresh``: a new interpreter (slow to start); otherwise a fork of this one (zarr resets
    its event loop after a fork; the child uses no dask).
    """
    if fresh:
        p = subprocess.run([sys.executable, "-c", KILL_CODE, str(flight), camera, str(out), str(COMMIT_EVERY), point],
                           cwd=ROOT, capture_output=True, text=True, timeout=300)
        rc, err = p.returncode, p.stderr[-800:]
    else:
        import multiprocessing

        proc = multiprocessing.get_context("fork").Process(target=_child, args=(str(flight), camera, str(out), point))
        proc.start()
        proc.join(300)
        rc, err = proc.exitcode, ""
    assert rc == -signal.SIGKILL, f"kill point {point} not reached (exit {rc}): {err}"


@pytest.fixture(scope="module")
def kill_flight(tmp_path_factory, catalog):
    """7 frames (commits after 3, 6 and 7) and the cube of one uninterrupted run."""
    root = tmp_path_factory.mktemp("kill")
    d = _flight(root / "flight", 7)
    ref = root / "ref" / "raw.zarr"
    ingest_flight(d, TINY, ref, commit_every=COMMIT_EVERY)
    return d, _snapshot(ref)


@pytest.mark.parametrize(
    "point, committed",
    [
        ("create", None),  # cube built under its temporary name, not yet renamed
        ("frame:2", 0),  # chunks of an uncommitted batch written
        ("coords:1", 0),  # chunks and coordinates written, not consolidated
        ("consolidated:1", 0),  # consolidated, commit counter not yet bumped
        ("commit:1", 3),  # right after the first commit
        ("frame:5", 3),  # in the middle of the second batch
        ("consolidated:3", 6),  # the last (partial) batch
    ],
)
def test_sigkill_then_rerun_equals_an_uninterrupted_run(tmp_path, kill_flight, point, committed, spy) -> None:
    flight, reference = kill_flight
    out = tmp_path / "raw.zarr"
    _killed_run(flight, out, point)
    if committed is None:
        assert not out.exists() and list(tmp_path.glob(".raw.zarr.tmp-*"))
    else:
        import zarr

        assert zarr.open_group(str(out), mode="r", use_consolidated=False).attrs["frames_committed"] == committed
    res = ingest_flight(flight, TINY, out, commit_every=COMMIT_EVERY)
    assert res.frames_already_present == (committed or 0)
    assert len(spy.names) == 7 - (committed or 0)  # only uncommitted frames are decoded again
    _assert_same(reference, _snapshot(out))
    assert not list(tmp_path.glob(".raw.zarr.tmp-*")) and not list(out.rglob("*.partial"))


def test_sigkill_during_recovery_then_rerun(tmp_path, kill_flight) -> None:
    flight, reference = kill_flight
    out = tmp_path / "raw.zarr"
    _killed_run(flight, out, "frame:5", fresh=True)  # leaves frames beyond the committed 3
    _killed_run(flight, out, "recover")  # killed after cutting them off, before re-consolidating
    _killed_run(flight, out, "frame:2")  # 2nd new frame of this run (the 5th of the flight)
    ingest_flight(flight, TINY, out, commit_every=COMMIT_EVERY)
    _assert_same(reference, _snapshot(out))


def _first_frames(flight: Path, dst: Path, n: int) -> Path:
    """A flight folder of the first ``n`` frames of ``flight`` (hard links, its table cut)."""
    dst.mkdir()
    rows = list(csv.DictReader((flight / "frames.csv").open()))[:n]
    for r in rows:
        os.link(flight / r["file"], dst / r["file"])
    _write_csv(dst, rows)
    return dst


def test_stale_consolidated_metadata_is_repaired_without_new_frames(tmp_path, kill_flight) -> None:
    flight, reference = kill_flight
    out = tmp_path / "raw.zarr"
    _killed_run(flight, out, "consolidated:2")  # readers would see 6 frames, 3 are committed
    _killed_run(flight, out, "recover")  # cut back to 3, killed before re-consolidating
    only3 = _first_frames(flight, tmp_path / "only3", 3)
    res = ingest_flight(only3, TINY, out)  # nothing new to append
    assert (res.frames_added, res.frames_already_present) == (0, 3)
    snap = _snapshot(out)
    assert snap["dn"].shape[0] == 3 and all(len(v) == 3 for k, v in snap["coords"].items() if k not in ("band", "band_name", "wavelength"))
    np.testing.assert_array_equal(snap["dn"], reference["dn"][:3])


def test_chunks_beyond_the_shape_left_by_a_commit_with_frames_in_flight_are_dropped(tmp_path, kill_flight) -> None:
    """``CubeWriter.commit(room=...)`` (apply's single pass commits while its workers write
    the frames after) shrinks ``dn`` without deleting their chunks, then grows it back. A run
    killed in between leaves chunks beyond the array's shape; the next open drops them with
    the rest of the uncommitted frames."""
    import zarr
    from zarr.core.sync import sync

    flight, reference = kill_flight
    out = tmp_path / "raw.zarr"
    ingest_flight(flight, TINY, out, commit_every=COMMIT_EVERY)
    for name in ("dn", "dn_median"):  # the state of a kill inside the commit of frame 5
        arr = zarr.open_array(str(out / name), mode="r+")
        sync(arr.async_array.resize((5, *arr.shape[1:]), delete_outside_chunks=False))
    zarr.open_group(str(out), mode="r+", use_consolidated=False).attrs.update({"frames_committed": 3})
    assert sorted(p.name for p in (out / "dn").glob("c.*")) == [f"c.{k}.0.0.0" for k in range(7)]
    only3 = _first_frames(flight, tmp_path / "only3", 3)
    res = ingest_flight(only3, TINY, out)
    assert (res.frames_added, res.frames_already_present) == (0, 3)
    assert sorted(p.name for p in (out / "dn").glob("c.*")) == [f"c.{k}.0.0.0" for k in range(3)]
    assert sorted(p.name for p in (out / "dn_median").glob("c.*")) == [f"c.{k}.0" for k in range(3)]
    snap = _snapshot(out)
    assert snap["dn"].shape[0] == 3
    np.testing.assert_array_equal(snap["dn"], reference["dn"][:3])


# --------------------------------------------------------------------------- full size (slow)


@pytest.mark.long  # the small-frame SIGKILL tests run in make test; this one at full size: make test-long
def test_sigkill_at_random_times_full_size(tmp_path) -> None:
    d = _flight(tmp_path / "f", 24, shape=(1088, 2048))
    ref = tmp_path / "ref.zarr"
    ingest_flight(d, XIMEA, ref, commit_every=COMMIT_EVERY)
    reference = _snapshot(ref)
    out = tmp_path / "raw.zarr"
    import zarr

    rng = np.random.default_rng(0)
    mid_run = []
    for _ in range(10):
        code = INGEST_CODE.replace("ingest_flight(sys.argv[1]", "print('ready', flush=True)\ningest_flight(sys.argv[1]")
        p = subprocess.Popen([sys.executable, "-c", code, str(d), XIMEA, str(out), str(COMMIT_EVERY)], cwd=ROOT,
                             stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "ready"  # imports done: the ingest starts now
        time.sleep(rng.uniform(0.05, 1.0))
        if p.poll() is None:
            p.send_signal(signal.SIGKILL)
        p.wait()
        p.stdout.close()
        if p.returncode == -signal.SIGKILL:  # killed while ingesting
            mid_run.append(
                zarr.open_group(str(out), mode="r", use_consolidated=False).attrs["frames_committed"]
                if out.exists() else None
            )
        if out.exists():  # start again from scratch now and then, so early kills happen too
            if rng.uniform() < 0.3:
                shutil.rmtree(out)
    assert len(mid_run) >= 5, mid_run
    print("frames committed when killed:", mid_run)
    ingest_flight(d, XIMEA, out, commit_every=COMMIT_EVERY)
    _assert_same(reference, _snapshot(out))


@pytest.mark.slow
def test_throughput_and_flat_memory_full_size(tmp_path) -> None:
    import tracemalloc

    d = _flight(tmp_path / "f", 48, shape=(1088, 2048))
    peaks = {}
    for n in (8, 48):
        sub = tmp_path / f"f{n}"
        sub.mkdir()
        rows = list(csv.DictReader((d / "frames.csv").open()))[:n]
        for r in rows:
            os.link(d / r["file"], sub / r["file"])
        _write_csv(sub, rows)
        ingest_flight(sub, XIMEA, tmp_path / f"warm{n}.zarr")  # imports, page cache
        tracemalloc.start()
        t0 = time.perf_counter()
        res = ingest_flight(sub, XIMEA, tmp_path / f"o{n}.zarr")
        dt = time.perf_counter() - t0
        peaks[n] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert res.frames_added == n
        print(f"{n} frames: {n / dt:.1f} frames/s, traced peak {peaks[n] / 2**20:.0f} MiB")
    frame_bytes = 1088 * 2048 * 2
    assert peaks[48] < peaks[8] + 4 * frame_bytes  # flat: not proportional to the flight


def test_prefetch_file_asks_for_the_whole_file_and_never_fails(tmp_path, monkeypatch) -> None:
    calls: list[tuple[int, int, int]] = []
    opened: list[str] = []
    real_open = os.open

    def recording_open(path, flags, *args):
        opened.append(str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(ingest_mod.os, "posix_fadvise", lambda fd, off, n, advice: calls.append((off, n, advice)))
    monkeypatch.setattr(ingest_mod.os, "open", recording_open)
    f = tmp_path / "IMG_0001.tif"
    f.write_bytes(b"x" * 10_000)
    ingest_mod.prefetch_file(f)
    assert opened == [str(f)] and calls == [(0, 0, os.POSIX_FADV_WILLNEED)]
    ingest_mod.prefetch_file(tmp_path / "missing.tif")  # its own task reports it
    assert calls == [(0, 0, os.POSIX_FADV_WILLNEED)]


def test_read_frame_reads_once_same_hash_and_bands_as_from_the_file(tmp_path, catalog, monkeypatch) -> None:
    """read_frame hashes and decodes a frame from one read into the thread's buffer: the sha256
    of the file's bytes and the bands decoded from the file itself, frame after frame (the
    buffer reused, a larger frame growing it); a frame over the size limit takes the stream
    hash and the file decode; a file that ends before its size is refused, naming it."""
    from pipeline.ingest.raw import read_frame
    from pipeline.ingest.session import FrameRecord, to_bands
    from pipeline.storage.store import file_sha256

    cam = load_camera(TINY)
    small = [tmp_path / "a.tif", tmp_path / "b.tif"]
    tifffile.imwrite(small[0], _mosaic(1), photometric="minisblack")  # tifffile's shape description
    tifffile.imwrite(small[1], _mosaic(2), photometric="minisblack", metadata=None, description="free text")
    big = tmp_path / "c.tif"
    tifffile.imwrite(big, _mosaic(3), photometric="minisblack", extratags=[(65000, "B", 5000, bytes(5000), False)])
    for path in (*small, big, small[0]):
        sha, bands = read_frame(FrameRecord(path, 2.0), cam)
        assert sha == file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()
        np.testing.assert_array_equal(bands, to_bands(decode_raw(path, path), cam, path))
    monkeypatch.setattr(ingest_mod, "READ_ONCE_MAX_BYTES", 100)
    seen: list = []
    monkeypatch.setattr(ingest_mod, "read_whole", lambda *a: seen.append(a))
    sha, bands = read_frame(FrameRecord(small[0], 2.0), cam)
    assert not seen and sha == file_sha256(small[0])
    np.testing.assert_array_equal(bands, to_bands(decode_raw(small[0], small[0]), cam, small[0]))
    monkeypatch.undo()

    real_stat = Path.stat
    shrunk = tmp_path / "shrunk.tif"
    shutil.copy(small[0], shrunk)

    def larger(self, *a, **k):  # the size seen before the read: the copy was still growing
        st = real_stat(self, *a, **k)
        return os.stat_result((*st[:6], st.st_size + 100, *st[7:])) if self == shrunk else st

    monkeypatch.setattr(Path, "stat", larger)
    with pytest.raises(ingest_mod.FrameError, match="changed while it was being read") as err:
        read_frame(FrameRecord(shrunk, 2.0), cam)
    assert "shrunk.tif" in str(err.value)
