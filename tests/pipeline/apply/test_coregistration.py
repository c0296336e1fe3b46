"""Band co-registration checked on the pixels of every multi-lens capture (run.json
``coregistration``, the report's table and ``band_misregistration`` warning), and a DJI
metadata alignment that leaves the bands apart refined by image registration."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
import xarray as xr

from pipeline.products.report import report_dict
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import DATA, require_data

#: CalibratedHMatrix written wrong by these translations (px on the designed plane) in four of
#: the five bands; Red (band 3) is the band the residuals are measured against.
H_ERRORS = {1: (12.0, -6.0), 2: (-15.0, 4.0), 4: (10.0, 10.0), 5: (18.0, -3.0)}


def _apply(folder: Path, out: Path, *extra: str) -> dict:
    assert main(["-q", "apply", str(folder), "--calibration", "factory", "-o", str(out), "--products", "radiance", *extra]) == 0
    return json.loads((out / "run.json").read_text())


def _section(out: Path) -> dict:
    (sec,) = [s for s in report_dict(None, [out])["sections"] if s["title"].startswith("Flight")]
    return sec


def _table(sec: dict) -> dict[str, list]:
    (table,) = [t for t in sec["tables"] if t["title"].startswith("Band co-registration")]
    assert table["columns"] == ["band", "residual median", "residual max", "without alignment", "metadata alone",
                                "captures", "tiles"]
    return {row[0]: row[1:] for row in table["rows"]}


def _scene_shift(scene: np.ndarray, band: np.ndarray) -> float:
    """Worst displacement (px) of a written band against the scene over five 192 px tiles
    (centre and corners; phase correlation, Hanning window): an independent check."""
    worst = 0.0
    for y, x in ((160, 200), (160, 1080), (800, 200), (800, 1080), (480, 640)):
        sl = (slice(y - 96, y + 96), slice(x - 96, x + 96))
        ref, t = scene[sl] / scene[sl].mean(), band[sl].astype(np.float64)
        t = np.where(np.isfinite(t), t, np.nanmedian(t))
        (dx, dy), _ = cv2.phaseCorrelate(ref, t / t.mean(), cv2.createHanningWindow(ref.shape[::-1], cv2.CV_64F))
        worst = max(worst, math.hypot(dx, dy))
    return worst


def test_a_wrong_dji_h_matrix_is_measured_and_refined_by_image_registration(tmp_path) -> None:
    """DJI bands whose H matrix is off by 10-20 px, written with firmware v01.17's spelling
    drone-dji:DewarpHMatrix: the metadata alignment alone leaves each band its error against
    Red (measured 13.4-18.2 px, > 10 px); apply sees it on the pixels and refines the alignment
    by image registration: <= 0.5 px left (measured 0.02-0.03 px), in run.json, the report and
    the written radiance itself."""
    require_data()
    built = cf.dji_p4m_warped(tmp_path / "built", H_ERRORS)
    folder = tmp_path / "wrong"
    folder.mkdir()
    for path in sorted(built.glob("*.TIF")):
        cf.rewrite(path, folder / path.name, lambda x: x.replace("drone-dji:CalibratedHMatrix=", "drone-dji:DewarpHMatrix="))
        assert b"DewarpHMatrix" in (folder / path.name).read_bytes()
    out = tmp_path / "out"
    run = _apply(folder, out)
    assert run_value(run, "band_alignment").startswith("factory metadata + image registration: the metadata alignment left ")
    co = run_value(run, "coregistration")
    assert co["alignment"] == "factory metadata + image registration" and co["reference_band"] == "Red"
    # before: the metadata alone, on the same captures, against no alignment at all
    check = co["metadata_check"]
    assert check["captures"] == ["002"]  # 001 is the panel capture
    for b, (dx, dy) in H_ERRORS.items():
        name = cf.DJI_BANDS[b - 1][0]
        assert check["metadata_px"][name] == pytest.approx(math.hypot(dx, dy), abs=0.2)
        assert check["metadata_px"][name] > 10
        assert check["unaligned_px"][name] < 5  # the bands as stored were closer: the matrix made it worse
    # after: measured on the written capture
    assert co["sample"] == {"every": 1, "captures": 1, "of": 2, "max_side_px": 640,
                            "note": "survey captures only (panel captures left out)"}
    assert set(co["captures"]) == {"002"}
    for name in ("Blue", "Green", "RedEdge", "NIR"):
        assert co["flight"][name]["median_px"] <= 0.5 and co["flight"][name]["max_px"] <= 0.5
        assert co["flight"][name]["tiles"] == 9
        assert co["captures"]["002"]["residual_px"][name] <= 0.5
    assert co["worst_median_px"] <= 0.5
    # the quality mask's not_coregistered: checked on the sampled capture (002) and, by the
    # image registration that judged it on its own pixels, on the panel capture (001)
    checks = run["quality"]["coregistration"]
    assert (checks["measured"], checks["own_pixels"], checks["not_checked"]) == (["002"], ["001"], [])
    assert "not_coregistered" in run["quality"]["checked"]
    assert not any("not_coregistered" in flags for flags in run["quality"]["totals"].values())  # all within 0.5 px
    ds = xr.open_zarr(out / "reflectance.zarr")
    assert ds.attrs["co_registered"] == 1 and ds.attrs["registration"] == "factory metadata + image registration"
    # the written radiance is on the scene's grid (the builders' scene: the RedEdge NIR frame)
    for f, cap in enumerate(cf.CAPTURES):
        scene = tifffile.imread(cf.band_file(cap, 4)).astype(np.float64)
        for b in range(5):
            assert _scene_shift(scene, ds["radiance"].isel(frame=f, band=b).values) < 0.5, (cap, b)
    # the report: the numbers before and after, no warning left
    sec = _section(out)
    rows = _table(sec)
    assert list(rows) == ["Blue", "Green", "RedEdge", "NIR"]
    for name, row in rows.items():
        assert float(row[0]) <= 0.5 and float(row[3]) > 10
    assert not [w for w in sec["warnings"] if w["code"] == "band_misregistration"]
    # without the refinement the bands would be off by the matrix's errors: the numbers say so
    _apply(folder, tmp_path / "plain", "--no-align")
    plain = run_value(json.loads((tmp_path / "plain" / "run.json").read_text()), "coregistration")
    assert plain["alignment"] == "none" and plain["worst_median_px"] > 1


def test_a_right_dji_h_matrix_is_kept_and_the_outputs_do_not_change(tmp_path, monkeypatch) -> None:
    """Correct DewarpData and CalibratedHMatrix: within 1 px (measured 0.01 px), so the metadata
    alignment is kept and nothing is warped again: the TIFFs are byte for byte those of a pass
    that neither measures nor refines."""
    import pipeline.apply.captures as captures_mod
    from pipeline.apply.coregistration import RunCoregistration

    require_data()
    folder = cf.dji_p4m_warped(tmp_path / "right")
    run = _apply(folder, tmp_path / "out")
    co = run_value(run, "coregistration")
    assert run_value(run, "band_alignment").startswith("factory metadata: each band's") and co["alignment"] == "factory metadata"
    assert co["metadata_check"]["decision"].startswith("factory metadata kept")
    assert co["worst_median_px"] < 0.1
    assert all(co["flight"][name]["unaligned_median_px"] > 1 for name in ("Blue", "Green", "RedEdge", "NIR"))
    assert "refined_px" not in co["metadata_check"] and _table(_section(tmp_path / "out"))["NIR"][0] == "0.011"
    assert xr.open_zarr(tmp_path / "out" / "reflectance.zarr").attrs["registration"] == "factory metadata"
    monkeypatch.setattr(captures_mod, "prepare", lambda *args: RunCoregistration())
    assert "coregistration" not in _apply(folder, tmp_path / "unmeasured")
    tiffs = sorted(p.relative_to(tmp_path / "out") for p in (tmp_path / "out").rglob("*.tif"))
    assert len(tiffs) == 11  # 2 captures x 5 bands, the survey capture's NDVI
    for rel in tiffs:
        assert (tmp_path / "out" / rel).read_bytes() == (tmp_path / "unmeasured" / rel).read_bytes(), rel


def test_micasense_bands_are_measured_and_warned_of(tmp_path) -> None:
    """The real RedEdge sample: MicaSense writes no alignment, so the bands keep their own
    grids; on the flight capture (the panel capture is left out) they are 2.5-14 px from Red,
    and the summary and report warn (band_misregistration, with mscal register as the way)."""
    require_data()
    out = tmp_path / "out"
    run = _apply(DATA, out)
    assert run_value(run, "band_alignment") == "none: each band keeps its own pixel grid"
    co = run_value(run, "coregistration")
    assert co["alignment"] == "none" and co["reference_band"] == "Red" and "metadata_check" not in co
    assert list(co["captures"]) == ["IMG_0001"] and co["sample"]["of"] == 2
    measured = co["captures"]["IMG_0001"]["residual_px"]
    expected = {"Blue": 10.29, "Green": 2.51, "Red": 0.0, "NIR": 14.06, "Red edge": 13.69}
    assert measured == pytest.approx(expected, abs=0.05)
    assert co["flight"]["NIR"] == {"median_px": pytest.approx(14.06, abs=0.05), "max_px": pytest.approx(14.06, abs=0.05),
                                   "captures": 1, "tiles": 9}
    sec = _section(out)
    (warn,) = [w for w in sec["warnings"] if w["code"] == "band_misregistration"]
    assert warn["value"] == pytest.approx(14.06, abs=0.05) and warn["threshold"] == 1.0
    assert "NIR 14.1 px, Red edge 13.7 px, Blue 10.3 px, Green 2.5 px" in warn["message"]
    assert "mscal register" in warn["message"]
    rows = _table(sec)
    assert rows["NIR"][0] == rows["NIR"][2] == "14.06"  # without alignment: the same numbers
    # bands left on their own grids make no claim to fail: not_coregistered not checked
    assert "not_coregistered" not in run["quality"]["checked"] and "coregistration" not in run["quality"]


def test_single_file_cameras_are_not_measured(tmp_path) -> None:
    """A Sentera Double 4K JPEG holds its bands in one file (one lens per JPEG): nothing to measure."""
    if not cf.SENTERA_D4K.is_dir():
        pytest.skip("no Sentera sample")
    run = _apply(cf.SENTERA_D4K / "NDRE", tmp_path / "out")
    assert run_value(run, "coregistration") is None


def test_a_metadata_alignment_worse_than_none_is_replaced_by_image_registration(monkeypatch) -> None:
    """Bands stored a few pixels apart (3.6-5.8 px) that the files' own registration bends
    radially by up to 16 px at the corners (a wrong distortion: neither a translation nor an
    affine undoes it): the metadata alignment does worse than none, image registration on top
    of it cannot straighten the bend, so the bands are registered from the stored grids instead
    (< 0.1 px left)."""
    from types import SimpleNamespace

    import pipeline.apply.coregistration as coreg
    from pipeline.ingest.catalog import load_camera

    rng = np.random.default_rng(5)
    shape = (480, 640)
    offsets = [(3.0, -2.0), (-4.0, 1.5), (0.0, 0.0), (5.0, 3.0), (-2.5, -4.0)]  # Red (index 2) the reference
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)

    def stored(seed: int) -> list[np.ndarray]:
        scene = sum(w * cv2.GaussianBlur(np.random.default_rng(seed).random((560, 720)).astype(np.float32), (0, 0), s)
                    for s, w in ((2.0, 1.0), (6.0, 2.0)))
        return [cv2.remap(scene, xx + 40 + dx, yy + 40 + dy, cv2.INTER_CUBIC) for dx, dy in offsets]

    cx, cy = (shape[1] - 1) / 2, (shape[0] - 1) / 2
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / 266.0**2  # 1 at the corner tiles' centres

    def bend(metas, stack):  # the "metadata" alignment: band b bent radially, 8 |b - 2| px at the corner tiles
        out = np.empty(stack.shape, np.float32)
        for b in range(stack.shape[0]):
            k = 8.0 * abs(b - 2) / 266.0
            out[b] = cv2.remap(stack[b], cx + (xx - cx) * (1 + k * r2), cy + (yy - cy) * (1 + k * r2),
                               cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return out

    pixels = {f"{k:03d}": stored(int(rng.integers(1 << 30))) for k in range(3)}
    monkeypatch.setattr(coreg, "read_capture_pixels", lambda cap: ("", pixels[cap.name], {}))
    monkeypatch.setattr(coreg, "align_by_files", bend)
    camera = load_camera("dji-p4-multispectral")
    captures = [SimpleNamespace(name=n, metas=[SimpleNamespace(path=Path(f"{n}_{b}.TIF")) for b in range(5)])
                for n in pixels]
    run = coreg.prepare(camera, captures, True, False, None, set())
    choice = run.choice
    assert run.reference == 2 and run.alignment == coreg.INSTEAD and choice is not None
    assert choice.factory_alignment is False and choice.label == coreg.INSTEAD
    rec = choice.record
    assert rec["captures"] == ["000", "001", "002"]
    assert rec["metadata_px"]["NIR"] > rec["unaligned_px"]["NIR"]  # worse than none
    assert rec["decision"].startswith("image registration (metadata alignment was worse than none): ")
    for name, (dx, dy) in zip(camera.band_names, offsets):
        assert rec["unaligned_px"][name] == pytest.approx(math.hypot(dx - offsets[2][0], dy - offsets[2][1]), abs=0.1)
        assert rec["refined_px"][name] < 0.1
    on_meta = rec["refinements_px"]["metadata + affine"]  # a bend is not an affine: measured 0.27-1.13 px left
    assert min(v for name, v in on_meta.items() if name != "Red") > 0.2
    h = np.asarray(choice.refine).reshape(5, 3, 3)
    assert h[0, :2, 2] == pytest.approx([-3.0, 2.0], abs=0.1)  # Blue, stored at scene(x + (3, -2)): band(x - (3, -2)) ~ Red(x)


def test_flat_captures_leave_the_metadata_alignment_unjudged(monkeypatch) -> None:
    """Captures without texture (a flat field of view): nothing to measure, so the files' own
    registration is kept and run.json says it was not judged."""
    from types import SimpleNamespace

    import pipeline.apply.coregistration as coreg
    from pipeline.ingest.catalog import load_camera

    monkeypatch.setattr(coreg, "read_capture_pixels", lambda cap: ("", [np.full((480, 640), 900.0)] * 5, {}))
    monkeypatch.setattr(coreg, "align_by_files", lambda metas, stack: stack.copy())
    camera = load_camera("dji-p4-multispectral")
    caps = [SimpleNamespace(name="001", metas=[SimpleNamespace(path=Path(f"DJI_001{b}.TIF")) for b in range(5)])]
    run = coreg.prepare(camera, caps, True, False, None, set())
    assert run.alignment == coreg.METADATA and run.choice is not None and run.choice.refine is None
    assert run.choice.factory_alignment and run.choice.record["decision"].startswith("factory metadata kept, not judged")
    assert run.choice.record["metadata_px"]["NIR"] is None


def test_every_nth_survey_capture_is_measured() -> None:
    """A 100-capture flight with two panel captures: every 5th of the 98 survey captures (20 <= 24)."""
    from types import SimpleNamespace

    from pipeline.apply.coregistration import measured_captures

    caps = [SimpleNamespace(name=f"IMG_{k:04d}") for k in range(100)]
    names, step = measured_captures(caps, {"IMG_0000", "IMG_0099"})
    assert step == 5 and len(names) == 20 and names[:3] == ["IMG_0001", "IMG_0006", "IMG_0011"]
    assert measured_captures(caps[:1], {"IMG_0000"}) == (["IMG_0000"], 1)  # only a panel: measured all the same


def test_a_capture_without_texture_takes_the_flights_alignment_and_is_marked() -> None:
    """Per capture: a flat capture (no tile with texture) cannot be judged on its own pixels, so
    it takes the flight's choice (here a 3 px translation of Blue) and run.json lists it as not
    run-invariant; a textured capture whose bands the metadata left 4-5 px apart is refined on
    its own pixels (< 0.3 px left at 640 px) whatever the flight's choice."""
    from mscal_core.alignment import align_bands
    from pipeline.apply.coregistration import REFINED, Refinement, capture_transform, refinement_record
    from pipeline.ingest.catalog import load_camera

    bands = tuple(load_camera("dji-p4-multispectral").band_names)
    flight = np.tile(np.eye(3), (5, 1, 1))
    flight[0, 0, 2] = 3.0
    plan = Refinement(2, bands, True, tuple(flight.ravel()), REFINED)
    flat = np.full((5, 480, 640), 900.0, np.float32)
    def capture_alignment(stack: np.ndarray) -> tuple[np.ndarray, dict]:  # as bandgrid.one_grid applies it
        on_meta, h, record = capture_transform(stack, stack, plan)
        assert on_meta  # the files' own registration is the stack itself here
        return (stack if h is None else align_bands(stack, h)), record

    out, rec = capture_alignment(flat)
    assert rec == {"from": "flight (fewest textured tiles in a band: 0 < 3)", "run_invariant": False,
                   "alignment": REFINED}
    assert np.isnan(out[0][:, -3:]).all() and not np.isnan(out[0][:, :-4]).any() and not np.isnan(out[1:]).any()
    rng = np.random.default_rng(3)
    scene = sum(w * cv2.GaussianBlur(rng.random((560, 720)).astype(np.float32), (0, 0), s)
                for s, w in ((2.0, 1.0), (6.0, 2.0)))
    offsets = [(4.0, -2.0), (-3.0, 3.0), (0.0, 0.0), (2.5, 4.0), (-4.0, -1.0)]
    yy, xx = np.mgrid[0:480, 0:640].astype(np.float32)
    stack = np.stack([cv2.remap(scene, xx + 40 + dx, yy + 40 + dy, cv2.INTER_CUBIC) for dx, dy in offsets])
    out, own = capture_alignment(stack)
    assert own["from"] == "own pixels" and own["run_invariant"] and own["alignment"] == REFINED
    assert own["model"] in ("translation", "affine") and min(v for v in own["metadata_px"].values() if v) > 3.5
    assert max(own["refined_px"].values()) < 0.3
    record = refinement_record({"001": rec, "002": own})
    assert (record["own_pixels"], record["from_flight"], record["not_run_invariant"]) == (1, 1, ["001"])
