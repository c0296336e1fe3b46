"""Run invariance of the sun-sensor reflectance (SPEC: one fixed scale per camera model, never a
constant chosen from the data of a run): a capture's reflectance is bit-identical processed
alone, within its flight, or within another flight, for every camera kind with a sun sensor
(MicaSense, DJI, Sequoia) and every light route without panels (``dls``; ``none``: radiance
only), and so is a Sentera capture's radiance (no sun-sensor route) and a snapshot frame's
field-calibrated reflectance (Eq. 15). With panels only the interpolation in time may change it, by the
amount the panels' light over the sensor's changes.

Before the fixed scales, DJI and Sequoia divided by a constant that put the run's first
capture's brightest band median at 0.5: a DJI capture processed alone and after another
differed by 14.9 % in every band.

On flights of at least :data:`pipeline.ingest.sunsensor.FIT_MIN_CAPTURES` captures at changing
attitudes the diffuse ratio of the tilt model (MicaSense DLS 1, Sequoia) could be fitted from
the flight: the dls route does not fit it (the clear sky's 1/6), so a long flight keeps the
invariance (:func:`test_long_flight_dls_reflectance_is_the_capture_alone`); the panel routes
do, as part of the light's interpolation between panels.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import xarray as xr

from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import DATA, require_data

SEQUOIA = DATA.parent / "parrot-sequoia"
SEQ = "IMG_180413_080658_0000"


def _apply(folder: Path, out: Path, *extra: str) -> tuple[dict, xr.Dataset]:
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--products", "radiance", *extra]) == 0
    return json.loads((out / "run.json").read_text()), xr.open_zarr(out / "reflectance.zarr")


def _frame(run: dict, ds: xr.Dataset, name: str, var: str = "reflectance") -> np.ndarray:
    return ds[var].isel(frame=run["frames"].index(name)).values


# --------------------------------------------------------------------------- capture builders
# Each writes one capture into ``folder``: ``slot`` names it (its place in the flight's order),
# ``source`` picks the real pixels, ``variant`` 0 is the capture under test, 1 another capture
# (other light on the sun sensor, other id); ``sun`` False strips the sun-sensor tags.


def _micasense(folder: Path, slot: str, source: str, variant: int, sun: bool) -> str:
    ident = cf.capture_id(source)

    def edit(x: str) -> str:
        if variant:
            x = x.replace(ident, f"{ident[:-3]}v{slot[-2:]}")
            x = re.sub(r"<Camera:Irradiance>([^<]+)</Camera:Irradiance>",
                       lambda m: f"<Camera:Irradiance>{float(m[1]) * 1.7}</Camera:Irradiance>", x)
        if not sun:
            x = cf.drop_element(cf.drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance")
        return x

    for b in range(1, 6):
        cf.rewrite(cf.band_file(source, b), folder / f"IMG_{slot}_{b}.tif", edit)
    return f"IMG_{slot}"


def _dji(folder: Path, slot: str, source: str, variant: int, sun: bool) -> str:
    for b in range(1, 6):
        packet = cf.dji_xmp(b, f"dji-capture-{slot}-{variant}", band_freq=b == 5)
        if variant:
            packet = re.sub(r'drone-dji:Irradiance="([^"]+)"',
                            lambda m: f'drone-dji:Irradiance="{float(m[1]) * 1.7}"', packet)
        if not sun:
            packet = re.sub(r'\s*drone-dji:Irradiance="[^"]+"', "", packet)
        cf.rewrite(cf.band_file(source, b), folder / f"DJI_00{slot}{b}.TIF", lambda _x, p=packet: p, make="DJI",
                   model="FC6360", black=(int(cf.DJI["black"]),))
    return f"00{slot}"


def _sequoia(folder: Path, slot: str, source: str, variant: int, sun: bool) -> str:
    name = SEQ if not variant else SEQ.replace("080658", f"0806{slot}")

    def edit(x: str) -> str:
        if variant:  # another capture: its own id, a less sensitive imager (darker radiance)
            x = re.sub(r'Camera:CaptureUUID="[^"]*"', f'Camera:CaptureUUID="BE5AB0ABA969E1CB424A394AA2FD3{variant}{slot}"', x)
            x = re.sub(r"(<Camera:SensorModel>\s*<rdf:Seq>\s*<rdf:li>)([-0-9.eE+]+)",
                       lambda m: f"{m[1]}{float(m[2]) * (1 + variant)}", x)
        if not sun:
            x, n = re.subn(r'\s+Camera:IrradianceSensitivitiesGolden="[^"]*"', "", x)
            assert n == 1
        return x

    for band in cf.SEQUOIA_BANDS:
        cf.rewrite(SEQUOIA / f"{SEQ}_{band}.TIF", folder / f"{name}_{band}.TIF", edit)
    return name


def _require(kind: str) -> None:
    require_data()
    if kind == "sequoia" and not SEQUOIA.is_dir():
        pytest.skip("no Sequoia sample")


Builder = Callable[[Path, str, str, int, bool], str]
# kind -> (builder, slots (other capture first in the order, the capture under test last), pixels of each)
KINDS: dict[str, tuple[Builder, tuple[str, str], tuple[str, str]]] = {
    "micasense": (_micasense, ("0001", "0002"), ("0000", "0001")),
    "dji": (_dji, ("1", "2"), ("0000", "0001")),
    "sequoia": (_sequoia, ("00", "58"), ("", "")),
}


def _flights(tmp_path: Path, kind: str, sun: bool) -> tuple[dict[str, Path], str]:
    """The capture under test alone, after the other capture of its flight, and after a capture
    of another flight (another light on the sun sensor)."""
    build, (first, last), (src_first, src_last) = KINDS[kind]
    folders = {k: tmp_path / k for k in ("alone", "flight", "other_flight")}
    for f in folders.values():
        f.mkdir()
    name = build(folders["alone"], last, src_last, 0, sun)
    assert build(folders["flight"], last, src_last, 0, sun) == name
    # without a sun sensor, no panel in the pixels either (auto would take the panel's QR code)
    build(folders["flight"], first, src_first if sun else src_last, 0 if kind != "sequoia" and sun else 2, sun)
    assert build(folders["other_flight"], last, src_last, 0, sun) == name
    build(folders["other_flight"], first, src_last, 1, sun)
    return folders, name


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_sun_sensor_reflectance_is_the_same_alone_in_its_flight_and_in_another(tmp_path, kind) -> None:
    _require(kind)
    folders, name = _flights(tmp_path, kind, sun=True)
    # --no-align: each band on its own grid, so that only the light is compared (the band
    # alignment's invariance: test_dji_refined_band_alignment_is_the_same_alone_and_in_a_flight)
    out = {k: _apply(f, tmp_path / f"out_{k}", "--reference", "dls", "--no-align") for k, f in folders.items()}
    alone = _frame(*out["alone"], name)
    assert len(out["flight"][0]["frames"]) == 2 and out["flight"][0]["frames"][-1] == name
    assert np.isfinite(alone).mean() > 0.9 and 0.01 < float(np.nanmedian(alone)) < 2.0  # on the TIFFs' scale
    for k in ("flight", "other_flight"):
        np.testing.assert_array_equal(_frame(*out[k], name), alone)
        assert "relative_scale" not in run_value(out[k][0], "reference")
        assert run_value(out[k][0], "reference")["sun_sensor_scale"] == run_value(out["alone"][0], "reference")["sun_sensor_scale"]
    # the photogrammetry TIFFs (uint16 x 32768 for every camera) of the capture: the same bytes
    for tif in sorted((tmp_path / "out_alone" / "photogrammetry").glob(f"{name}_*.tif")):
        for k in ("flight", "other_flight"):
            assert (tmp_path / f"out_{k}" / "photogrammetry" / tif.name).read_bytes() == tif.read_bytes()


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_radiance_only_route_is_the_same_alone_in_its_flight_and_in_another(tmp_path, kind) -> None:
    _require(kind)
    folders, name = _flights(tmp_path, kind, sun=False)
    out = {k: _apply(f, tmp_path / f"out_{k}", "--no-align") for k, f in folders.items()}
    alone = _frame(*out["alone"], name, "radiance")
    assert run_value(out["alone"][0], "reference")["route"] == "none" and np.isnan(_frame(*out["alone"], name)).all()
    for k in ("flight", "other_flight"):
        assert run_value(out[k][0], "reference")["route"] == "none"
        np.testing.assert_array_equal(_frame(*out[k], name, "radiance"), alone)
        assert np.isnan(_frame(*out[k], name)).all()


def test_with_panels_only_the_interpolation_in_time_changes_a_capture(tmp_path) -> None:
    """IMG_0001 with the panel capture IMG_0000 before it (panel-dls: the panel's light over the
    sensor's, q, carried by the sensor), then with a second panel 181 s after IMG_0000 whose sun
    sensor reads 10 % more: q is interpolated in time, so IMG_0001 (91 s after the first panel,
    weight 0.503 on the second) changes by q_before / q(t) = 1 / (0.497 + 0.503 q_after / q_before):
    4.7 %, the same in every pixel of a band."""
    require_data()
    one, two = tmp_path / "one", tmp_path / "two"
    for folder in (one, two):
        folder.mkdir()
        for cap in ("0000", "0001"):
            for b in range(1, 6):
                shutil.copyfile(cf.band_file(cap, b), folder / f"IMG_{cap}_{b}.tif")
    ident = cf.capture_id("0000")
    for b in range(1, 6):
        dst = cf.rewrite(cf.band_file("0000", b), two / f"IMG_0002_{b}.tif", lambda x: re.sub(
            r"<Camera:Irradiance>([^<]+)</Camera:Irradiance>",
            lambda m: f"<Camera:Irradiance>{float(m[1]) * 1.1}</Camera:Irradiance>", x.replace(ident, ident[:-3] + "two")))
        dst.write_bytes(dst.read_bytes().replace(b"2017:10:19 20:40:39", b"2017:10:19 20:43:40"))
    run1, ds1 = _apply(one, tmp_path / "o1", "--panel-reflectance", "0.5", "--panel", "IMG_0000")
    run2, ds2 = _apply(two, tmp_path / "o2", "--panel-reflectance", "0.5", "--panel", "IMG_0000,IMG_0002")
    assert run_value(run1, "reference")["route"] == run_value(run2, "reference")["route"] == "panel-dls"
    ratio = _frame(run2, ds2, "IMG_0001") / _frame(run1, ds1, "IMG_0001")
    per_band = np.nanmedian(ratio, axis=(1, 2))
    # the same factor on every pixel of a band (only the light changed, not the pixels' model)
    np.testing.assert_allclose(np.nanmax(ratio, axis=(1, 2)), per_band, rtol=1e-5)
    np.testing.assert_allclose(np.nanmin(ratio, axis=(1, 2)), per_band, rtol=1e-5)
    # by how much: the interpolation of q between the panels, from run.json's light record
    panels = {p["capture"]: p for p in run_value(run2, "light")["panels_over_time"]}
    w_after = 91.0 / 181.0  # IMG_0001 at 20:42:10.2, panels at 20:40:39.2 and 20:43:40.2
    for b, band in enumerate(ds2["band_name"].values):
        q = {c: panels[c]["panel_irradiance"][band] / panels[c]["sensor_irradiance"][band]
             for c in ("IMG_0000", "IMG_0002")}
        expected = 1.0 / ((1 - w_after) + w_after * q["IMG_0002"] / q["IMG_0000"])
        assert per_band[b] == pytest.approx(expected, rel=1e-4)
    np.testing.assert_allclose(per_band, 1 / (1 - w_after + w_after / 1.1), rtol=3e-3)  # ~ +4.7 %


# --------------------------------------------------------------------------- long flights
# A flight of more captures than FIT_MIN_CAPTURES at changing attitudes under a sky bluer than
# the clear sky's 1/6: the sun sensor's diffuse ratio could be fitted from the flight's readings
# (it lowers the roughness of the horizontal light), but on the dls route it is not.

LONG = 12
SKY_RATIO = 0.12 * (550.0 / np.array([475.0, 560.0, 668.0, 840.0, 717.0])) ** 2  # IMG_0001's bands, in file order


def _long_flight(folder: Path, seed: int = 0) -> list[str]:
    """``LONG`` copies of IMG_0001 (its pixels, time and position), each its own capture with a
    sun sensor tilted 10 deg rms at a random yaw, reading the light of a bluer sky through
    MicaSense's DLS model (:func:`mscal_core.sunsensor.sensor_reading`, direct light such that
    the level sensor would read IMG_0001's own readings)."""
    from mscal_core.sunsensor import sensor_reading
    from pipeline.ingest.solar import solar_position

    folder.mkdir()
    when = np.array(["2017-10-19T20:42:10.200159489"], dtype="datetime64[ns]")
    el, az = (float(v[0]) for v in solar_position(when, np.array([36.5760815]), np.array([-119.4352604]),
                                                   np.array([174.527])))
    own = np.array([0.9574306607246399, 0.7664443850517273, 0.6869884729385376, 0.41153082251548767,
                    0.631069004535675])
    level = sensor_reading(1.0, SKY_RATIO, el, az, 0.0, 0.0, 0.0)  # a level sensor, direct light 1
    rng = np.random.default_rng(seed)
    ident = cf.capture_id("0001")
    names = []
    for i in range(LONG):
        ypr = (rng.uniform(-np.pi, np.pi), *np.radians(rng.normal(0.0, 10.0, 2)))
        reading = sensor_reading(own / level, SKY_RATIO * own / level, el, az, *ypr)
        name = f"IMG_{i + 2:04d}"

        def edit(x: str, b: int, ypr=ypr, reading=reading, i=i) -> str:
            x = x.replace(ident, f"{ident[:-4]}L{i:03d}")
            x = cf.set_element(x, "Camera:Irradiance", repr(float(reading[b])))
            for tag, v in zip(("Yaw", "Pitch", "Roll"), ypr):
                x = cf.set_element(x, f"DLS:{tag}", repr(float(v)))
                x = cf.set_element(x, f"Camera:Irradiance{tag}", repr(float(np.degrees(v))))
            return x

        for b in range(5):
            cf.rewrite(cf.band_file("0001", b + 1), folder / f"{name}_{b + 1}.tif", lambda x, b=b: edit(x, b))
        names.append(name)
    return names


def test_long_flight_dls_reflectance_is_the_capture_alone(tmp_path) -> None:
    """On the dls route the diffuse ratio is the clear sky's 1/6 however long the flight: the
    last capture of a 12-capture flight gets the reflectance it gets alone, bit for bit. The
    flight's readings do let the ratio be fitted (every band, within 3 % of the truth 0.05-0.16,
    roughness 2-7000x lower than at 1/6): when the dls route fitted it, the capture's median
    reflectance in the flight was 0.09 % (Blue) to 1.6 % (NIR) above the capture's alone."""
    require_data()
    from pipeline.apply.captures import capture_times, find_captures
    from pipeline.ingest.identify import identify_camera
    from pipeline.ingest.sunsensor import sensor_light

    names = _long_flight(tmp_path / "flight")
    x = names[-1]
    (tmp_path / "alone").mkdir()
    for b in range(1, 6):
        shutil.copyfile(tmp_path / "flight" / f"{x}_{b}.tif", tmp_path / "alone" / f"{x}_{b}.tif")
    # the flight does let the ratio be fitted (what the panel routes use)
    caps = find_captures(tmp_path / "flight", identify_camera(tmp_path / "flight", None).camera).captures
    fitted = sensor_light(caps, capture_times(caps))
    assert [c.name for c in caps] == names
    fit_bands = [b for b, src in enumerate(fitted.ratio_source) if "fitted" in src]
    assert len(fit_bands) >= 3, fitted.ratio_source
    for b in fit_bands:
        assert abs(fitted.diffuse_ratio[b] / SKY_RATIO[b] - 1) < 0.3
    run_f, ds_f = _apply(tmp_path / "flight", tmp_path / "out_flight", "--reference", "dls", "--no-align")
    run_a, ds_a = _apply(tmp_path / "alone", tmp_path / "out_alone", "--reference", "dls", "--no-align")
    in_flight, alone = _frame(run_f, ds_f, x), _frame(run_a, ds_a, x)
    assert len(run_f["frames"]) == LONG and np.isfinite(alone).mean() > 0.9
    np.testing.assert_array_equal(in_flight, alone)
    for run in (run_f, run_a):
        ratios = run_value(run, "sun_sensor")["diffuse_ratio"]
        assert {r["source"] for r in ratios.values()} == {"clear-sky diffuse ratio 1/6"}
        assert all(r["ratio"] == pytest.approx(1 / 6, abs=1e-6) for r in ratios.values())
        assert run_value(run, "sun_sensor")["diffuse_ratio_rule"].startswith("clear-sky 1/6 (or a DLS 2's measured split), never")


# --------------------------------------------------------------------------- band alignment
def test_dji_refined_band_alignment_is_the_same_alone_and_in_a_flight(tmp_path) -> None:
    """DJI captures whose H matrix is 10-20 px wrong (test_coregistration's errors), with the
    default alignment: every capture's refinement is judged and estimated on its own pixels, so
    capture 003 gets the same bands, NaN borders included, alone and after two other survey
    captures (other scenes: IMG_0001's NIR frame rolled, and turned upside down). The flight's
    own pooled estimate (its three captures' tiles; what every capture got before) differs from
    003's alone by up to 0.014 px (transforms in run.json ``metadata_check``): with it, 80 % of
    003's pixels differed (by up to 1.3 %) and 163 of its NaN border's. Each capture: 13.3-18.1
    px left by the metadata, 0.08-0.15 px after its own refinement (measured at 640 px)."""
    import tifffile

    from pipeline.apply.coregistration import REFINED
    from tests.pipeline.apply.test_coregistration import H_ERRORS

    require_data()
    x = tifffile.imread(cf.band_file("0001", 4))
    cf.dji_p4m_warped(tmp_path / "flight", H_ERRORS, [np.roll(x, (97, 211), axis=(0, 1)), x[::-1].copy(), x])
    (tmp_path / "alone").mkdir()
    for b in range(1, 6):
        shutil.copyfile(tmp_path / "flight" / f"DJI_003{b}.TIF", tmp_path / "alone" / f"DJI_003{b}.TIF")
    out = {k: _apply(tmp_path / k, tmp_path / f"out_{k}", "--reference", "dls") for k in ("alone", "flight")}
    (run_a, ds_a), (run_f, ds_f) = out["alone"], out["flight"]
    assert run_f["frames"] == ["001", "002", "003"]
    alone, in_flight = _frame(run_a, ds_a, "003"), _frame(run_f, ds_f, "003")
    assert 0.005 < np.isnan(alone).mean() < 0.1  # the bands, moved, leave NaN where they do not cover (1.4 %)
    np.testing.assert_array_equal(in_flight, alone)
    for tif in sorted((tmp_path / "out_alone" / "photogrammetry").glob("003_*.tif")):
        assert (tmp_path / "out_flight" / "photogrammetry" / tif.name).read_bytes() == tif.read_bytes()
    # where each capture's alignment came from, and what it left
    for run, names in ((run_a, ["003"]), (run_f, ["001", "002", "003"])):
        per = run_value(run, "coregistration")["per_capture"]
        assert per["own_pixels"] == len(names) and per["not_run_invariant"] == [] and list(per["captures"]) == names
        for name in names:
            rec = per["captures"][name]
            assert rec["from"] == "own pixels" and rec["run_invariant"] and rec["alignment"] == REFINED
            assert min(v for v in rec["metadata_px"].values() if v) > 10
            assert max(rec["refined_px"].values()) <= 0.5
    assert run_value(run_a, "coregistration")["per_capture"]["captures"]["003"] == \
        run_value(run_f, "coregistration")["per_capture"]["captures"]["003"]
    # the flight's pooled transforms (the fallback) are not 003's own
    pooled = {k: np.array(list(run_value(r, "coregistration")["metadata_check"]["transforms"].values()))
              for k, r in (("alone", run_a), ("flight", run_f))}
    assert run_value(run_f, "coregistration")["metadata_check"]["captures"] == ["001", "002", "003"]
    shift = np.abs(pooled["flight"][:, [2, 5]] - pooled["alone"][:, [2, 5]]).max()
    assert 0.005 < shift < 0.5


# --------------------------------------------------------------------------- cameras without a sun-sensor route


def test_sentera_radiance_is_the_capture_alone(tmp_path) -> None:
    """Sentera Double 4K (route none: radiance only, its sun sensor has no published
    conversion): a capture's radiance alone equals it within its flight."""
    src = DATA.parent / "sentera-d4k" / "NDRE"
    if not src.is_dir():
        pytest.skip(f"no Sentera sample at {src}")
    flight, alone = tmp_path / "flight", tmp_path / "alone"
    shutil.copytree(src, flight)
    alone.mkdir()
    shutil.copy(src / "IMG_00007.jpg", alone / "IMG_00007.jpg")
    run_f, ds_f = _apply(flight, tmp_path / "out-flight")
    run_a, ds_a = _apply(alone, tmp_path / "out-alone")
    assert run_value(run_f, "reference")["route"] == run_value(run_a, "reference")["route"] == "none"
    np.testing.assert_array_equal(_frame(run_f, ds_f, "IMG_00007", "radiance"), _frame(run_a, ds_a, "IMG_00007", "radiance"))


def test_snapshot_field_reflectance_is_the_frame_alone(small, tmp_path) -> None:
    """A snapshot camera's frame with a field calibration (Eq. 15, relative): its reflectance
    alone equals it within its flight."""
    session, calib = small
    src = session / "flights" / "field"
    rows = (src / "frames.csv").read_text().splitlines()
    alone = tmp_path / "alone"
    alone.mkdir()
    name = rows[2].split(",")[0]
    shutil.copy(src / name, alone / name)
    (alone / "frames.csv").write_text("\n".join([rows[0], rows[2]]) + "\n")
    outs = {}
    for key, folder in (("flight", src), ("alone", alone)):
        assert main(["apply", str(folder), "--calibration", str(calib), "-o", str(tmp_path / key)]) == 0
        outs[key] = xr.open_zarr(tmp_path / key / "reflectance.zarr")
    stem = Path(name).stem
    np.testing.assert_array_equal(outs["flight"]["reflectance"].sel(frame=stem).values,
                                  outs["alone"]["reflectance"].sel(frame=stem).values)
