"""Session band co-registration: combination, fallbacks, store, real RedEdge data."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from mscal_core import homography
from mscal_core import registration as reg
from mscal_core.errors import InputError
from pipeline.calibrate.registration import frame_transforms, register_session, with_registration
from pipeline.ingest.catalog import load_camera
from pipeline.run.cli import main
from pipeline.sim.world.multilens import multilens_capture
from pipeline.storage.run_layout import run_value
from pipeline.storage.store import new_dataset, open_calibration, write_store
from tests.micasense_data import band_file

CAMERA = "micasense-rededge"


@pytest.fixture(scope="module")
def session_reg():
    """Three captures of one rig over different ground; in the third the blue band is a
    covered lens (noise): it must fall back to the session transform."""
    camera = load_camera(CAMERA)
    size = (180, 240)  # small: three captures, test time
    first = multilens_capture(10, shape=size)
    truth = first.homographies
    stacks = [("IMG_0010", first.dn), ("IMG_0011", multilens_capture(11, shape=size, homographies=truth).dn)]
    bad = multilens_capture(12, shape=size, homographies=truth).dn.copy()
    bad[0] = np.random.default_rng(0).normal(400, 20, bad[0].shape).clip(0, 4095).astype(np.uint16)
    stacks.append(("IMG_0012", bad))
    return camera, truth, register_session(stacks, camera)


def test_session_transform_and_fallback(session_reg) -> None:
    camera, truth, r = session_reg
    shape = r.shape
    # transforms are rebased onto the rig's middle lens; compare in that frame
    truth_ref = homography.rebase(truth, r.reference)
    for b in range(camera.n_bands):
        d = homography.transform_distance(r.transforms[b], truth_ref[b], shape)
        assert np.sqrt(np.mean(d**2)) < 0.3, (b, d.max())
    assert [f["capture"] for f in r.fallbacks] == ["IMG_0012"]
    assert r.fallbacks[0]["bands"] == ["Blue"] and "gradient correlation" in r.fallbacks[0]["reason"]
    np.testing.assert_allclose(r.capture_transforms[2, 0], r.transforms[0])  # fell back
    assert not np.allclose(r.capture_transforms[0, 0], r.transforms[0], atol=0.0, rtol=0.0)  # its own
    assert np.all(r.spread_px[np.isfinite(r.spread_px)] < 0.3)


def test_store_round_trip_and_old_stores(session_reg, tmp_path) -> None:
    camera, _, r = session_reg
    old = new_dataset(camera)
    write_store(old, tmp_path / "old.zarr")
    assert frame_transforms(open_calibration(tmp_path / "old.zarr", camera), "IMG_0010") is None
    write_store(with_registration(old, r, camera), tmp_path / "reg.zarr")
    ds = open_calibration(tmp_path / "reg.zarr", camera)
    np.testing.assert_allclose(frame_transforms(ds, "IMG_0011"), r.capture_transforms[1])
    np.testing.assert_allclose(frame_transforms(ds, "IMG_9999"), r.transforms)  # not registered: session's
    assert ds["registration_fallback"].sel(capture="IMG_0012").values.tolist() == [True, False, False, False, False]
    assert ds.attrs["registration"]["reference_band"] == camera.band_names[r.reference]
    assert float(ds["registration_ecc"].sel(capture="IMG_0010").min()) > reg.Thresholds().min_ecc


def test_register_refuses_a_snapshot_mosaic(tmp_path, capsys) -> None:
    code = main(["register", str(tmp_path), "--camera", "ximea-mq022hg-sm5x5-nir", "-o", str(tmp_path / "r.zarr")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "snapshot mosaic" in err and len(err.splitlines()) == 1


def _third(path) -> np.ndarray:
    img = tifffile.imread(path).astype(np.float32)
    return cv2.resize(img, (img.shape[1] // 3, img.shape[0] // 3), interpolation=cv2.INTER_AREA)


def _ndvi_edge_energy(ndvi: np.ndarray, mask: np.ndarray) -> float:
    """Mean |grad NDVI| over ``mask``: misaligned bands add false NDVI edges at every edge."""
    v = np.nan_to_num(ndvi.astype(np.float32))
    g = cv2.magnitude(cv2.Sobel(v, cv2.CV_32F, 1, 0), cv2.Sobel(v, cv2.CV_32F, 0, 1))
    return float(g[mask].mean())


@pytest.mark.slow
def test_real_rededge_flight_capture_aligns(tmp_path) -> None:
    """The RedEdge flight capture IMG_0001: registered at a third of its resolution (test
    time; full-resolution figures in docs/benchmarks.md), the transforms scaled to full
    resolution and stored, then ``mscal apply --calibration factory`` with and without
    ``--registration``: band-to-band gradient correlation of the output reflectance and the
    NDVI's false edges."""
    import shutil

    import xarray as xr

    camera = load_camera(CAMERA)
    stack = np.stack([_third(band_file("0001", b)) for b in range(1, 6)])
    r = register_session([("IMG_0001", stack)], camera)
    assert r.fallbacks == () and all(all(c.accepted) for c in r.captures)
    full = [homography.scale_homography(h, 3.0) for h in r.transforms]
    r_full = replace(r, transforms=np.stack(full), capture_transforms=np.stack(full)[None], shape=(960, 1280))
    write_store(with_registration(new_dataset(camera), r_full, camera), tmp_path / "reg.zarr")
    flight = tmp_path / "flight"
    flight.mkdir()
    for b in range(1, 6):
        shutil.copy(band_file("0001", b), flight)
    assert main(["apply", str(flight), "--calibration", "factory", "-o", str(tmp_path / "raw"), "--float32"]) == 0
    assert main(["apply", str(flight), "--calibration", "factory", "-o", str(tmp_path / "al"), "--float32",
                 "--registration", str(tmp_path / "reg.zarr")]) == 0
    raw, al = (xr.open_zarr(tmp_path / d / "reflectance.zarr") for d in ("raw", "al"))
    assert al.attrs["co_registered"] == 1 and raw.attrs["co_registered"] == 0
    # apply measures the bands on the written pixels against the store's reference band
    measured = {d: run_value(json.loads((tmp_path / d / "run.json").read_text()), "coregistration") for d in ("raw", "al")}
    assert measured["al"]["alignment"] == "transforms of the registration store (mscal register)"
    assert measured["raw"]["alignment"] == "none" and measured["al"]["reference_band"] == "Red"  # the store's
    before, after = measured["raw"]["captures"]["IMG_0001"], measured["al"]["captures"]["IMG_0001"]
    assert after["unaligned_px"] == before["residual_px"]
    for name in ("Blue", "Green", "NIR", "Red edge"):  # measured 2.5-14.1 px before, 0.18-0.65 px after
        assert before["residual_px"][name] > 2 and after["residual_px"][name] < 1, name
    ra, rb = raw["reflectance"].values[0], al["reflectance"].values[0]
    ok = cv2.erode(np.isfinite(rb).all(axis=0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert ok.mean() > 0.85
    nir = camera.band_names.index("NIR")
    for b in range(5):
        if b == nir:
            continue
        before = reg.gradient_correlation(np.nan_to_num(ra[nir]), np.nan_to_num(ra[b]), ok)
        after = reg.gradient_correlation(np.nan_to_num(rb[nir]), np.nan_to_num(rb[b]), ok)
        assert after > before + 0.15 and after > 0.35, (b, before, after)
    before = _ndvi_edge_energy(raw["ndvi"].values[0], ok)
    after = _ndvi_edge_energy(al["ndvi"].values[0], ok)
    assert after < 0.7 * before, (before, after)


def test_collect_needs_a_camera_for_a_new_store(tmp_path) -> None:
    """A new store's camera is recognised from the files (as apply does); a folder whose files
    name none asks for --camera."""
    from pipeline.calibrate.registration import register_cli

    with pytest.raises(InputError, match="name it with --camera NAME"):
        register_cli([tmp_path], tmp_path / "r.zarr", None, None)
    with pytest.raises(InputError, match="not found"):
        register_cli([tmp_path / "nowhere"], tmp_path / "r.zarr", None, None)


def test_captures_named_by_folder_or_band_file() -> None:
    from pipeline.calibrate.registration import collect_captures

    camera = load_camera(CAMERA)
    one = band_file("0001", 3)
    caps, problems = collect_captures([one], camera)
    assert [c.name for c in caps] == ["IMG_0001"] and problems == []
    assert [m.band_name for m in caps[0].metas] == list(camera.band_names)
    caps, _ = collect_captures([one.parent], camera)
    assert [c.name for c in caps] == ["IMG_0000", "IMG_0001"]
    with pytest.raises(InputError, match="not found"):
        collect_captures([one.parent / "nope"], camera)


def test_report_shows_the_session_transform_passes_and_fallbacks(session_reg, tmp_path) -> None:
    from pipeline.products.report import (
        REGISTRATION_SPREAD_MAX_PX,
        registration_fallback_table,
        registration_table,
        registration_warnings,
        report_dict,
    )

    camera, truth, r = session_reg
    ds = with_registration(new_dataset(camera), r, camera)
    table = registration_table(ds)
    assert table is not None and len(table.rows) == camera.n_bands
    cols = table.columns
    truth_ref = homography.rebase(truth, r.reference)
    h, w = r.shape
    for b, row in enumerate(table.rows):
        dx, dy, rot, scale = homography.local_motion(truth_ref[b], ((w - 1) / 2, (h - 1) / 2))
        assert abs(row[cols.index("shift x px")] - dx) < 0.3 and abs(row[cols.index("shift y px")] - dy) < 0.3, (b, row)
        assert abs(row[cols.index("rotation deg")] - rot) < 0.05 and abs(row[cols.index("scale")] - scale) < 2e-3
        assert row[cols.index("captures passed")] == ("2/3" if camera.band_names[b] == "Blue" else "3/3")
        assert row[cols.index("spread px")] < 0.3
    ref_row = table.rows[r.reference]
    assert ref_row[0].endswith("(reference)") and ref_row[1:5] == [0.0, 0.0, 0.0, 1.0]
    fb = registration_fallback_table(ds)
    assert fb is not None and [row[:2] for row in fb.rows] == [["IMG_0012", "Blue"]]
    assert "gradient correlation" in fb.rows[0][2]
    assert [x.code for x in registration_warnings(ds)] == ["registration_fallback"]

    # captures that disagree (parallax between altitudes): one more warning, naming the band
    far = ds.copy(deep=True)
    far["registration_spread_px"].values[1] = 4.0
    warns = {x.code: x for x in registration_warnings(far)}
    assert warns["registration_spread"].value == 4.0 and warns["registration_spread"].threshold == REGISTRATION_SPREAD_MAX_PX
    assert camera.band_names[1] in warns["registration_spread"].message

    # through the store and the JSON form of the report: the calibration section carries it
    write_store(ds, tmp_path / "reg.zarr")
    d = report_dict(tmp_path / "reg.zarr")
    sec = d["sections"][0]
    titles = [t["title"] for t in sec["tables"]]
    assert "Band registration" in titles and "Captures that fell back to the session transform" in titles
    assert [x["code"] for x in sec["warnings"] if x["code"].startswith("registration")] == ["registration_fallback"]


def test_report_without_registration_has_no_registration_tables(session_reg) -> None:
    from pipeline.products.report import registration_fallback_table, registration_table, registration_warnings

    camera, _, _ = session_reg
    ds = new_dataset(camera)
    assert registration_table(ds) is None and registration_fallback_table(ds) is None
    assert registration_warnings(ds) == []


SENTERA_NDRE = Path(__file__).resolve().parents[4] / "shared" / "data" / "sentera-d4k" / "NDRE"


def test_register_reads_captures_as_apply_does() -> None:
    """The registration's band reader is apply's (grouping.read_capture_pixels): a
    Sentera JPEG capture is its bands' channels (RedEdge = R, NIR = B), not one 3-channel
    image refused as 'not single-band'."""
    from pipeline.calibrate.registration import collect_captures, read_capture

    if not SENTERA_NDRE.is_dir():
        pytest.skip("no Sentera sample")
    caps, problems = collect_captures([SENTERA_NDRE / "IMG_00006.jpg"], load_camera("sentera-d4k-ndre"))
    assert [c.name for c in caps] == ["IMG_00006"] and problems == []
    stack = read_capture(caps[0])
    rgb = cv2.cvtColor(cv2.imread(str(SENTERA_NDRE / "IMG_00006.jpg"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert stack.shape == (2, 3000, 4000) and stack.dtype == np.float32
    np.testing.assert_array_equal(stack[0], rgb[:, :, 0])
    np.testing.assert_array_equal(stack[1], rgb[:, :, 2])


@pytest.mark.long
def test_register_sentera_jpegs(tmp_path) -> None:
    """`mscal register` on the real Double 4K JPEGs, camera recognised from the files: the two
    bands are channels behind one lens, so the transform is the identity within 1 px
    (measured 0.58 px at most over the image, ECC 0.91)."""
    if not SENTERA_NDRE.is_dir():
        pytest.skip("no Sentera sample")
    out = tmp_path / "reg.zarr"
    assert main(["register", str(SENTERA_NDRE), "-o", str(out), "--max-captures", "1"]) == 0
    ds = open_calibration(out)
    assert ds.attrs["camera"] == "sentera-d4k-ndre" and ds.attrs["registration"]["reference_band"] == "NIR"
    for h in ds["band_transform"].values:
        assert np.max(homography.transform_distance(h, np.eye(3), (3000, 4000))) < 1.0
    assert float(ds["registration_ecc"].values.min()) > 0.8


@pytest.mark.parametrize(("option", "warned"), [("--reference-band", False), ("--reference", True)])
def test_register_reference_band_option(option: str, warned: bool, tmp_path, monkeypatch, capsys) -> None:
    """``--reference-band`` names register's band (``--reference`` is apply's light source);
    the old spelling still reaches the registration and says it is deprecated."""
    import pipeline.calibrate.registration as registration

    seen: list[str | None] = []

    def fake(paths, out, camera, reference, *args, **kwargs):
        seen.append(reference)
        raise InputError("stop here", path=tmp_path)

    monkeypatch.setattr(registration, "register_cli", fake)
    code = main(["register", str(tmp_path), "-o", str(tmp_path / "r.zarr"), option, "Red"])
    err = capsys.readouterr().err
    assert code == 2 and seen == ["Red"]
    assert ("--reference is deprecated, use --reference-band" in err) is warned
