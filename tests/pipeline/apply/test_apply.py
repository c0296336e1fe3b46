"""mscal apply: Eq. 15 over a flight, all outputs, quarantine, re-runs and kills."""

from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import exifread
import numpy as np
import pytest
import rasterio
import tifffile
import xarray as xr

from mscal_core.quality import region_median
from mscal_core.reflectance import eq15
from pipeline.run.cli import main

XIMEA_EXPORT = ["b615", "b670", "b700", "b714", "b739", "b790", "b803", "b857"]


def _flight_copy(session: Path, dst: Path) -> Path:
    shutil.copytree(session / "flights" / "field", dst)
    return dst


def _apply(flight: Path, calib: Path, out: Path, *extra: str) -> int:
    return main(["apply", str(flight), "--calibration", str(calib), "-o", str(out), *extra])


def _rows(flight: Path) -> list[dict[str, str]]:
    return list(csv.DictReader((flight / "frames.csv").open()))


def test_reflectance_store_contract(applied) -> None:
    session, _, out = applied
    ds = xr.open_zarr(out / "reflectance.zarr")
    rows = _rows(session / "flights" / "field")
    assert ds["reflectance"].dims == ("frame", "band", "y", "x")
    assert ds["reflectance"].dtype == np.float32
    assert ds["reflectance"].shape == (len(rows), 25, 217, 409)
    assert ds["ndvi"].dims == ("frame", "y", "x") and ds["ndvi"].dtype == np.float32
    assert list(ds["frame"].values) == [Path(r["file"]).stem for r in rows]
    np.testing.assert_allclose(ds["exposure_ms"].values, [float(r["exposure_ms"]) for r in rows])
    np.testing.assert_allclose(ds["lat"].values, [float(r["lat"]) for r in rows])
    np.testing.assert_allclose(ds["alt_m"].values, [float(r["alt_m"]) for r in rows])
    assert float(ds["wavelength"].sel(band=24)) == 670.0
    assert "time" in ds.coords and "lon" in ds.coords
    r = ds["reflectance"].values
    assert np.nanmin(r) >= 0 and np.all(np.isfinite(r) | np.isnan(r))
    nd = ds["ndvi"].values
    assert np.nanmin(nd) >= -1 and np.nanmax(nd) <= 1
    # the lazily written store equals Eq. 15 computed eagerly, frame by frame, from raw.zarr
    raw = xr.open_zarr(out / "raw.zarr")
    cal = xr.open_zarr(applied[1])
    q = ds["quality"].values  # flagged pixels are NaN (the default)
    assert q.dtype == np.uint8 and q.shape == r.shape
    for f in range(r.shape[0]):
        t = float(raw["exposure_ms"][f] * raw["gain"][f])
        expect = eq15(raw["dn"][f].values, cal["inverse_response"].values, t, cal["vignetting"].values,
                      cal["spectral_factor"].values)
        expect[q[f] != 0] = np.nan
        np.testing.assert_allclose(r[f], expect, rtol=2e-6, equal_nan=True)
    assert ds["vegetation_mask"].dtype == np.uint8


def test_calibrated_reflectance_and_ndvi_match_truth(applied) -> None:
    session, _, out = applied
    ds = xr.open_zarr(out / "reflectance.zarr")
    truth = np.load(session / "truth.npz")
    labels = truth["flight_field_labels"]
    names = list(truth["flight_field_material_names"])
    rho = truth["flight_field_panel_reflectance"]
    white, gray = names.index("panel_0.90"), names.index("panel_0.20")
    veg = names.index("vegetation")
    r = ds["reflectance"].values
    for f in range(r.shape[0]):
        w = labels[f] == white
        k = np.nanmedian(rho.max() / np.nanmedian(r[f][:, w], axis=1))
        g = labels[f] == gray
        if g.sum() > 10:
            np.testing.assert_allclose(np.nanmedian(r[f][:, g], axis=1) * k, 0.20, atol=0.015)
        valued = np.isfinite(ds["ndvi"].values[f])  # flagged pixels have no NDVI
        v = (labels[f] == veg) & valued
        assert abs(np.nanmean(ds["ndvi"].values[f][v]) - np.nanmean(truth["flight_field_ndvi"][f][v])) < 0.01
        mask = ds["vegetation_mask"].values[f]
        assert (mask[v] == 1).mean() > 0.95 and (mask[(labels[f] == names.index("soil")) & valued] == 0).mean() > 0.95


def test_run_json(applied) -> None:
    session, calib, out = applied
    run = json.loads((out / "run.json").read_text())
    n = len(_rows(session / "flights" / "field"))
    assert run["frames_in"] == n and run["frames_out"] == n and run["quarantined"] == []
    assert len(run["calibration_sha256"]) == 64
    assert set(run["versions"]) >= {"mscal", "numpy", "dask", "xarray", "zarr"}
    assert run["saturated_pixels"]["total"] == sum(run["saturated_pixels"]["per_frame"].values())
    assert run["timings_s"]["total"] > 0


def test_photogrammetry_tiffs_carry_exif_and_xmp(applied) -> None:
    session, _, out = applied
    rows = _rows(session / "flights" / "field")
    files = sorted((out / "photogrammetry").glob("*.tif"))
    assert len(files) == len(rows) * len(XIMEA_EXPORT)
    refl = xr.open_zarr(out / "reflectance.zarr")
    uuids = {}
    for row in rows:
        stem = Path(row["file"]).stem
        for rig, band in enumerate(XIMEA_EXPORT):
            p = out / "photogrammetry" / f"{stem}_{band}.tif"
            with p.open("rb") as fh:
                tags = exifread.process_file(fh, details=False)
            lat = tags["GPS GPSLatitude"].values
            lat = sum(float(v.num) / float(v.den) / 60**i for i, v in enumerate(lat))
            assert lat == pytest.approx(abs(float(row["lat"])), abs=1e-6)
            assert str(tags["GPS GPSLatitudeRef"]) == "N"
            assert "EXIF DateTimeOriginal" in tags
            xmp = tifffile.TiffFile(p).pages[0].tags[700].value
            xmp = xmp.decode() if isinstance(xmp, bytes) else xmp
            assert band in xmp and "CaptureUUID" in xmp and "CentralWavelength" in xmp
            assert f"{rig}" in xmp.split("RigCameraIndex")[1][:20]
            uid = xmp.split("CaptureUUID")[1][:60]
            uuids.setdefault(stem, set()).add(uid)
            with rasterio.open(p) as src:
                img = src.read(1)
                assert img.dtype == np.uint16 and img.shape == (217, 409)
            b = refl["band_name"].values.tolist().index(band)
            expect = refl["reflectance"].isel(frame=rows.index(row), band=b).values
            ok = np.isfinite(expect)
            np.testing.assert_allclose(img[ok] / 32768.0, expect[ok], atol=1 / 32768 + 1e-6)
    assert all(len(u) == 1 for u in uuids.values())  # one CaptureUUID per frame, shared by its bands
    assert len({next(iter(u)) for u in uuids.values()}) == len(rows)
    assert len(list((out / "ndvi").glob("*.tif"))) == len(rows)


def test_rerun_changes_nothing(applied, capsys) -> None:
    """A finished run started again writes nothing (its speed is bench_apply's business)."""
    session, calib, out = applied
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    assert _apply(session / "flights" / "field", calib, out) == 0
    assert "up to date" in capsys.readouterr().out
    after = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    assert after == before


def test_bad_frames_are_quarantined_and_the_rest_processed(small, tmp_path, capsys) -> None:
    session, calib = small
    flight = _flight_copy(session, tmp_path / "flight")
    rows = _rows(flight)
    data = (flight / rows[0]["file"]).read_bytes()
    (flight / rows[0]["file"]).write_bytes(data[: len(data) // 2])  # truncated
    rows[1]["exposure_ms"] = "0"
    with (flight / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (flight / "notes.png").write_text("not an image")  # no row, no EXIF, not an image
    out = tmp_path / "out"
    assert _apply(flight, calib, out) == 0
    run = json.loads((out / "run.json").read_text())
    q = {x["file"]: x["reason"] for x in run["quarantined"]}
    assert set(q) == {rows[0]["file"], rows[1]["file"], "notes.png"}
    assert "truncated" in q[rows[0]["file"]] or "unreadable" in q[rows[0]["file"]]
    assert "exposure" in q[rows[1]["file"]]
    assert run["frames_out"] == len(rows) - 2
    err = capsys.readouterr().err
    assert f"quarantined {rows[0]['file']}" in err
    assert _apply(flight, calib, tmp_path / "strict", "--strict") != 0


def test_saturated_pixels_are_nan_and_counted(small, tmp_path) -> None:
    session, calib = small
    flight = _flight_copy(session, tmp_path / "flight")
    first = flight / _rows(flight)[0]["file"]
    raw = tifffile.imread(first)
    raw[500:520, 1000:1050] = 1023  # 20 x 50 sensor pixels at full scale
    tifffile.imwrite(first, raw)
    out = tmp_path / "out"
    assert _apply(flight, calib, out) == 0
    run = json.loads((out / "run.json").read_text())
    n_sat = int((raw >= 1023).sum())
    assert run["saturated_pixels"]["per_frame"][first.stem] == n_sat
    ds = xr.open_zarr(out / "reflectance.zarr")
    r, q = ds["reflectance"].isel(frame=0).values, ds["quality"].isel(frame=0).values
    saturated = (q & 1) != 0  # the quality mask's saturated bit
    assert int(saturated.sum()) == n_sat and np.isnan(r[saturated]).all()
    assert np.array_equal(np.isnan(r), q != 0)
    assert np.isnan(r[:, 100:104, 200:210]).all() and saturated[:, 100:104, 200:210].all()


def test_normalisation_options(small, tmp_path) -> None:
    session, calib = small
    flight = session / "flights" / "field"
    out = tmp_path / "band"
    assert _apply(flight, calib, out, "--normalise", "band:803") == 0
    ds = xr.open_zarr(out / "reflectance.zarr")
    r = ds["reflectance"]
    b = int(np.argmin(np.abs(r["wavelength"].values - 803)))
    # the band's median with its pixels flagged high (the shoulder's: a few of the brightest)
    # counted as above it (mscal_core.quality.region_median) is 1 in every frame
    values = r.isel(band=b).values.reshape(r.sizes["frame"], -1)
    quality = ds["quality"].isel(band=b).values.reshape(values.shape)
    np.testing.assert_allclose(region_median(values, quality), 1.0, rtol=1e-5)
    truth = np.load(session / "truth.npz")
    names = list(truth["flight_field_material_names"])
    lab = truth["flight_field_labels"][1]
    ys, xs = np.nonzero(lab == names.index("panel_0.50"))
    box = f"{xs.min() + 1},{ys.min() + 1},{xs.max()},{ys.max()}"
    frame = str(truth["flight_field_names"][1])
    out = tmp_path / "panel"
    assert _apply(flight, calib, out, "--panel", f"{frame}:{box}", "--panel-reflectance", "0.5") == 0
    r = xr.open_zarr(out / "reflectance.zarr")["reflectance"].isel(frame=1).values
    region = r[:, ys.min() + 1 : ys.max(), xs.min() + 1 : xs.max()]
    assert np.nanmedian(region) == pytest.approx(0.5, abs=0.01)


def test_bad_apply_input_is_one_line(small, tmp_path, capsys) -> None:
    session, calib = small
    flight = session / "flights" / "field"
    for args, expect in [
        ([str(tmp_path / "nope"), "--calibration", str(calib)], "flight folder not found"),
        ([str(flight), "--calibration", str(tmp_path / "none.zarr")], "calibration store not found"),
        ([str(flight), "--calibration", str(calib), "--normalise", "band:999"], "no band within"),
        ([str(flight), "--calibration", str(calib), "--panel", "IMG_0000:1,2", "--panel-reflectance", "0.5"], "is not FRAME:x0,y0,x1,y1"),
        ([str(flight), "--calibration", str(calib), "--export-bands", "b999"], "unknown band(s) b999"),
    ]:
        code = main(["apply", *args, "-o", str(tmp_path / "o")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and expect in err, err


def _outputs(out: Path) -> dict[str, bytes | np.ndarray]:
    res: dict[str, bytes | np.ndarray] = {}
    for p in sorted((out / "photogrammetry").glob("*.tif")) + sorted((out / "ndvi").glob("*.tif")):
        res[str(p.relative_to(out))] = p.read_bytes()
    ds = xr.open_zarr(out / "reflectance.zarr")
    for v in ("reflectance", "ndvi", "vegetation_mask"):
        res[v] = ds[v].values
    return res


# SIGKILL at a random moment, then a restart (two at once): tests/pipeline/apply/test_concurrent.py


@pytest.mark.slow
def test_worker_processes_give_the_same_outputs(small, tmp_path) -> None:
    session, calib = small
    flight = session / "flights" / "field"
    assert _apply(flight, calib, tmp_path / "threads", "--scheduler", "threads") == 0
    assert _apply(flight, calib, tmp_path / "processes", "--scheduler", "processes") == 0
    assert json.loads((tmp_path / "processes" / "run.json").read_text())["execution"]["scheduler"] == "processes"
    _assert_same_outputs(_outputs(tmp_path / "threads"), _outputs(tmp_path / "processes"))


def _assert_same_outputs(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], bytes):
            assert a[key] == b[key], key
        else:
            np.testing.assert_array_equal(a[key], b[key])


def test_single_pass_equals_ingest_then_apply(applied, tmp_path) -> None:
    """A fresh OUT is ingested and calibrated in one pass over the files; an OUT whose raw.zarr
    already holds the frames is calibrated from the cube: the same bytes either way."""
    from pipeline.ingest.catalog import load_camera
    from pipeline.ingest.raw import ingest_flight

    session, calib, out = applied
    assert json.loads((out / "run.json").read_text())["snapshot"]["single_pass"] is True
    cubed = tmp_path / "cubed"
    ingest_flight(session / "flights" / "field", load_camera("ximea-mq022hg-sm5x5-nir"), cubed / "raw.zarr")
    assert _apply(session / "flights" / "field", calib, cubed) == 0
    assert json.loads((cubed / "run.json").read_text())["snapshot"]["single_pass"] is False
    _assert_same_outputs(_outputs(out), _outputs(cubed))
    a, b = (xr.open_zarr(p / "raw.zarr") for p in (out, cubed))
    np.testing.assert_array_equal(a["dn"].values, b["dn"].values)
    assert list(a["sha256"].values) == list(b["sha256"].values)


@pytest.mark.parametrize("scheduler, dup_of", [("threads", 0), ("processes", 4)])
def test_duplicate_frame_in_a_fresh_flight(small, tmp_path, monkeypatch, scheduler: str, dup_of: int) -> None:
    """A duplicate found during the single pass: the frames before it stay, the rest go the
    general way; outputs equal those of the flight without the duplicate. On worker processes
    with a commit every 2 frames the duplicate comes after commits made while the workers
    wrote the frames beyond (``CubeWriter.commit(room=...)``); the pass stops with no task
    left writing, and raw.zarr holds exactly the flight's frames."""
    from pipeline.apply import flight as flight_mod

    monkeypatch.setattr(flight_mod, "FRESH_BATCH", 2)
    session, calib = small
    flight = _flight_copy(session, tmp_path / "flight")
    rows = _rows(flight)
    if scheduler == "processes":  # 9 frames: the 3 of the session, then copies with one DN changed
        for k in range(3, 9):
            dn = tifffile.imread(flight / rows[k % 3]["file"])
            dn[0, k] ^= 1
            tifffile.imwrite(flight / f"IMG_{k:04d}.tif", dn)
            rows.append(dict(rows[k % 3], file=f"IMG_{k:04d}.tif"))
        with (flight / "frames.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    clean = tmp_path / "clean"
    assert _apply(flight, calib, clean, "--scheduler", scheduler) == 0
    name = Path(rows[dup_of]["file"]).stem + "b.tif"  # sorts right after the frame it copies
    dup = dict(rows[dup_of], file=name)
    shutil.copy(flight / rows[dup_of]["file"], flight / name)
    with (flight / "frames.csv").open("a", newline="") as fh:
        csv.DictWriter(fh, fieldnames=list(rows[0])).writerow(dup)
    from pipeline.ingest.raw import CubeWriter

    rooms: list[int] = []
    commit = CubeWriter.commit

    def spy(self, room: int = 0) -> None:
        rooms.append(room)
        commit(self, room)

    monkeypatch.setattr(CubeWriter, "commit", spy)
    out = tmp_path / "out"
    assert _apply(flight, calib, out, "--scheduler", scheduler, "--workers", "2") == 0
    if scheduler == "processes":  # committed twice with frames in flight, then at the duplicate
        assert rooms[:3] == [8, 6, 0]
    run = json.loads((out / "run.json").read_text())
    assert run["execution"]["scheduler"] == scheduler
    assert [q["file"] for q in run["quarantined"]] == [name]
    assert "duplicate" in run["quarantined"][0]["reason"] and run["snapshot"]["single_pass"] is False
    stem = Path(name).stem
    assert not list((out / "photogrammetry").glob(f"{stem}_*")) and not (out / "ndvi" / f"{stem}.tif").exists()
    _assert_same_outputs(_outputs(clean), _outputs(out))
    a, b = xr.open_zarr(clean / "raw.zarr"), xr.open_zarr(out / "raw.zarr")
    np.testing.assert_array_equal(a["dn"].values, b["dn"].values)
    assert sorted(p.name for p in (out / "raw.zarr" / "dn").iterdir() if p.name.startswith("c")) == \
        sorted(p.name for p in (clean / "raw.zarr" / "dn").iterdir() if p.name.startswith("c"))


def eq15_numpy(raw: xr.Dataset, calib: xr.Dataset) -> np.ndarray:
    """Eq. 15 written out here, independently of the apply code: ``R = U(I) / (t V S)`` in
    float64 with t = exposure x gain, NaN from the calibration's lowest saturation DN up."""
    dn = raw["dn"].values.astype(np.int64)
    t = (raw["exposure_ms"] * raw["gain"]).values.astype(np.float64)
    U = calib["inverse_response"].values.astype(np.float64)
    V = calib["vignetting"].values.astype(np.float64)
    S = calib["spectral_factor"].values.astype(np.float64)
    sat = int(calib["saturation_dn"].values.min())
    bands = np.arange(U.shape[0])[None, :, None, None]
    refl = np.maximum(U[bands, dn], 0.0) / (t[:, None, None, None] * V[None] * S[None, :, None, None])
    return np.where(dn >= sat, np.nan, refl)


def test_the_pass_equals_eq15_of_the_cube(applied) -> None:
    """reflectance.zarr is Eq. 15 of raw.zarr's DN, to float32 rounding."""
    from pipeline.storage.store import open_calibration

    _, calib_path, out = applied
    expected = eq15_numpy(xr.open_zarr(out / "raw.zarr"), open_calibration(calib_path))
    ds = xr.open_zarr(out / "reflectance.zarr")
    stored, q = ds["reflectance"].values, ds["quality"].values
    assert stored.dtype == np.float32 and stored.shape == expected.shape == (3, 25, 217, 409)
    assert int(np.isnan(expected).sum()) == 0  # the small flight saturates nowhere ...
    assert not np.any(q & 1) and np.array_equal(np.isnan(stored), q != 0)  # ... NaN only where flagged
    np.testing.assert_allclose(stored[q == 0], expected[q == 0], rtol=2e-6)


def test_each_frame_reads_ahead_a_later_frame(small, tmp_path, monkeypatch) -> None:
    """The single pass asks the kernel to read each file READ_AHEAD frames before its task
    needs it (prefetch_file), and the outputs are those of a pass without read-ahead."""
    import pipeline.apply.executor as executor
    import pipeline.apply.flight as apply_mod

    session, calib = small
    flight = _flight_copy(session, tmp_path / "flight")
    files = sorted(flight / r["file"] for r in _rows(flight))  # frames go in file-name order
    asked: list[Path] = []
    monkeypatch.setattr(executor, "prefetch_file", lambda p: asked.append(Path(p)))
    monkeypatch.setattr(apply_mod, "READ_AHEAD", 2)  # the small flight has 3 frames
    assert _apply(flight, calib, tmp_path / "ahead") == 0
    assert len(files) == 3 and sorted(asked) == files[2:]
    monkeypatch.setattr(apply_mod, "READ_AHEAD", len(files))  # nothing to read ahead
    asked.clear()
    assert _apply(flight, calib, tmp_path / "plain") == 0
    assert asked == []
    _assert_same_outputs(_outputs(tmp_path / "ahead"), _outputs(tmp_path / "plain"))


def test_disk_full_is_one_line_and_the_same_command_then_resumes(small, tmp_path, monkeypatch, capsys) -> None:
    """A full disk mid-run: one line naming the file with what to do, no traceback; once
    there is space the same command finishes with the outputs of an uninterrupted run."""
    import errno

    import pipeline.apply.executor as apply_mod  # the task writes the TIFFs

    session, calib = small
    flight = session / "flights" / "field"
    assert _apply(flight, calib, tmp_path / "clean") == 0
    real = apply_mod.write_tiff_file
    full = tmp_path / "out" / "photogrammetry" / "IMG_0001_b700.tif"

    def disk_full(path, *args, **kwargs):
        if Path(path).name == full.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(apply_mod, "write_tiff_file", disk_full)
    capsys.readouterr()
    assert _apply(flight, calib, tmp_path / "out") == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert err.startswith(f"mscal: error: {full}: No space left on device") and "run the same command again" in err
    monkeypatch.setattr(apply_mod, "write_tiff_file", real)
    assert _apply(flight, calib, tmp_path / "out") == 0
    _assert_same_outputs(_outputs(tmp_path / "clean"), _outputs(tmp_path / "out"))


def test_snapshot_outputs_are_the_kernel_and_the_writers_bit_for_bit(applied, tmp_path) -> None:
    """Locks the snapshot path of the one executor to what it computed before the
    two apply paths were merged: every frame's reflectance is exactly ``eq15_fast`` with the
    store's tables on raw.zarr's DN, and every photogrammetry TIFF is byte for byte what the
    writer makes of it with the frame's tags."""
    import uuid

    from mscal_core.reflectance import eq15_fast, eq15_tables
    from pipeline.apply.flight import catalog_make_model, snapshot_optics
    from pipeline.ingest.catalog import load_camera
    from pipeline.products.writers import BandTags, FrameTags, write_band_tiff

    _, calib, out = applied
    cal = xr.open_zarr(calib, chunks=None).load()
    cam = load_camera(cal.attrs["camera"])
    raw = xr.open_zarr(out / "raw.zarr")
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert "illumination_scale" not in ds.coords and "band_transform" not in cal  # the plain Eq. 15 pass
    lut, inv_v = eq15_tables(cal["inverse_response"].values, cal["vignetting"].values, cal["spectral_factor"].values)
    sat = int(cal["saturation_dn"].values.min()) if "saturation_dn" in cal else cam.dn_max
    export = [cam.band_names.index(n) for n in cam.export_bands]
    make, model = catalog_make_model(cam)
    assert (make, model) == ("XIMEA", "MQ022HG-IM-SM5X5-NIR")
    optics = snapshot_optics(cam, cal, ds["reflectance"].shape[2:])
    assert optics is not None and optics.focal_length_mm == pytest.approx(cal["intrinsics"].values[0, 0] * 0.0275)
    compared = 0
    for f, name in enumerate(raw["frame"].values):
        t = float(raw["exposure_ms"].values[f] * raw["gain"].values[f])
        refl = eq15_fast(raw["dn"][f].values[None], lut, inv_v, t, sat)[0]
        refl[ds["quality"][f].values != 0] = np.nan  # flagged pixels are NaN (the default)
        np.testing.assert_array_equal(ds["reflectance"][f].values, refl)
        tags = FrameTags(
            time=np.datetime_as_string(raw["time"].values[f], unit="ms") + "Z",
            lat=float(raw["lat"].values[f]), lon=float(raw["lon"].values[f]), alt_m=float(raw["alt_m"].values[f]),
            capture_uuid=str(uuid.uuid5(uuid.NAMESPACE_URL, f"mscal:{cam.name}:{raw['sha256'].values[f]}")),
            exposure_ms=float(raw["exposure_ms"].values[f]), camera_make=make, camera_model=model, rig_name=cam.name)
        for i, b in enumerate(export):
            band = cam.bands[b]
            mine = write_band_tiff(tmp_path / f"{name}_{band.name}.tif", refl[b], tags,
                                   BandTags(name=band.name, wavelength_nm=band.wavelength_nm, fwhm_nm=band.fwhm_nm,
                                            rig_camera_index=i, optics=optics))
            assert (out / "photogrammetry" / mine.name).read_bytes() == mine.read_bytes(), mine.name
            compared += 1
    assert compared == 3 * len(export) == 24
