"""Sun-sensor magnitudes against the clear sky: a MicaSense DLS 2 file without
``IrradianceScaleToSIUnits`` is read in the unit whose value fits the sky (MicaSense's library
says uW cm-2 nm-1, x 0.01; some firmware wrote W m-2 nm-1), recorded in run.json
``sun_sensor_check``; a reading no unit rule makes plausible is warned."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.ingest.cameras.micasense import AS_WRITTEN_RULE, LIBRARY_RULE
from pipeline.ingest.clear_sky import choose_capture_rule, choose_rule, clear_sky_spectral, plausible
from pipeline.run.cli import main
from pipeline.run.console import report_warnings
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import require_data

# IMG_0001's DLS 1 readings made horizontal, over the clear sky at its sun (measured on the sample)
SAMPLE_RATIO = {"Blue": 0.8494, "Green": 0.7224, "Red": 0.7445, "NIR": 0.6564, "Red edge": 0.8276}


def test_clear_sky_spectral_irradiance() -> None:
    """SPECTRL2 global horizontal, W m-2 nm-1, on 21 June: 560 nm with the sun 30 degrees high,
    and the blue of a low sun (8.5 degrees) where the RedEdge-M's DLS 2 read 0.20."""
    v = clear_sky_spectral([560.0, 475.0, 840.0, 560.0], [30.0, 8.5, 60.0, 2.0], 172)
    np.testing.assert_allclose(v[:3], [0.745, 0.153, 0.819], rtol=2e-3)
    assert np.isnan(v[3])  # a sun this low: no clear-sky figure


def test_choose_rule_takes_the_unit_that_fits_the_sky() -> None:
    clear = float(clear_sky_spectral(475.0, 8.5, 172))
    # the RedEdge-M firmware 7.4.0 / DLS 2 v1.3.0 file: HorizontalIrradiance 0.20 in W m-2 nm-1
    rule, ratio, ok = choose_rule({LIBRARY_RULE: 0.20 * 0.01, AS_WRITTEN_RULE: 0.20}, clear)
    assert (rule, ok) == (AS_WRITTEN_RULE, True) and ratio == pytest.approx(1.31, abs=0.01)
    # the same light written in uW cm-2 nm-1 (20.0): the library's rule
    rule, ratio, ok = choose_rule({LIBRARY_RULE: 20.0 * 0.01, AS_WRITTEN_RULE: 20.0}, clear)
    assert (rule, ok) == (LIBRARY_RULE, True) and ratio == pytest.approx(1.31, abs=0.01)
    # 50 x the clear sky under its one rule: chosen, but not plausible
    assert choose_rule({"x 1": 50 * clear}, clear) == ("x 1", pytest.approx(50.0), False)
    assert plausible(0.02) and plausible(1.5) and not plausible(0.019) and not plausible(1.51)


def _dls2(folder: Path, unit: float, captures: tuple[str, ...] = ("0001",)) -> Path:
    """IMG_0001 as a DLS 2 writes it without IrradianceScaleToSIUnits: no Camera:Irradiance, the
    DLS's SpectralIrradiance and HorizontalIrradiance (the DLS 1 reading) times ``unit`` (1: W
    m-2 nm-1, 100: uW cm-2 nm-1)."""
    folder.mkdir()

    def edit(x: str) -> str:
        x = cf.drop_element(x, "Camera:Irradiance")
        return re.sub(r"<DLS:SpectralIrradiance>([^<]+)</DLS:SpectralIrradiance>", lambda m: (
            f"<DLS:SpectralIrradiance>{float(m[1]) * unit!r}</DLS:SpectralIrradiance>"
            f"<DLS:HorizontalIrradiance>{float(m[1]) * unit!r}</DLS:HorizontalIrradiance>"), x)

    for cap in captures:
        for b in range(1, 6):
            cf.rewrite(cf.band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", edit)
    return folder


def _apply(folder: Path, out: Path) -> tuple[dict, np.ndarray]:
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--reference", "dls"]) == 0
    return json.loads((out / "run.json").read_text()), xr.open_zarr(out / "reflectance.zarr")["reflectance"].values


def test_a_capture_takes_one_unit_rule_for_all_its_bands() -> None:
    """One sun sensor writes one unit: band by band the rules would differ (band A plausible only
    as written, band B only by the library's x 0.01), the capture takes the one closest to the
    sky over both (as written: |log| 0.22 and 0.88 against 4.38 and 3.73)."""
    a = {LIBRARY_RULE: 0.005, AS_WRITTEN_RULE: 0.5}
    b = {LIBRARY_RULE: 0.012, AS_WRITTEN_RULE: 1.2}
    assert choose_rule(a, 0.4)[0] == AS_WRITTEN_RULE and choose_rule(b, 0.5)[0] == LIBRARY_RULE
    assert choose_capture_rule([a, b], [0.4, 0.5]) == AS_WRITTEN_RULE
    # more bands plausible wins over closeness: a third band plausible only by the library
    c = {LIBRARY_RULE: 0.03, AS_WRITTEN_RULE: 3.0}
    d = {LIBRARY_RULE: 0.04, AS_WRITTEN_RULE: 4.0}
    assert choose_capture_rule([a, b, c, d], [0.4, 0.5, 1.0, 1.0]) == LIBRARY_RULE
    assert choose_capture_rule([a], [float("nan")]) is None


def test_dls2_without_scale_tag_is_read_in_the_unit_that_fits_the_sky(tmp_path) -> None:
    require_data()
    si, si_refl = _apply(_dls2(tmp_path / "si", 1.0), tmp_path / "out_si")
    uw, uw_refl = _apply(_dls2(tmp_path / "uw", 100.0), tmp_path / "out_uw")
    dls1 = tmp_path / "dls1"
    dls1.mkdir()
    for b in range(1, 6):
        cf.rewrite(cf.band_file("0001", b), dls1 / f"IMG_0001_{b}.tif")
    ref, ref_refl = _apply(dls1, tmp_path / "out_dls1")
    # W m-2 nm-1 without a scale tag: taken at scale 1; uW cm-2 nm-1: at MicaSense's 0.01
    assert run_value(si, "sun_sensor_check")["rules"] == {AS_WRITTEN_RULE: 5}
    assert run_value(uw, "sun_sensor_check")["rules"] == {LIBRARY_RULE: 5}
    assert run_value(ref, "sun_sensor_check")["rules"] == {"x 1: W m-2 nm-1 (DLS 1)": 5}
    for run in (si, uw, ref):
        chk = run_value(run, "sun_sensor_check")
        assert chk["implausible"] == 0 and chk["plausible_ratio"] == [0.02, 1.5]
        got = {b: v["ratio"] for b, v in chk["captures"]["IMG_0001"].items()}
        assert got == pytest.approx(SAMPLE_RATIO, abs=2e-4)
        assert not [w for w in run_value(run, "light")["warnings"] if w["code"] == "sun_sensor_implausible"]
    # the same light, so the same reflectance (read x 0.01 the SI file was 100 x too bright)
    np.testing.assert_allclose(si_refl, ref_refl, rtol=1e-6)
    np.testing.assert_allclose(uw_refl, ref_refl, rtol=1e-6)
    assert 0.01 < float(np.nanmedian(si_refl)) < 1.0


def test_a_reading_fifty_times_the_sky_is_warned(tmp_path) -> None:
    require_data()
    folder = tmp_path / "bright"
    folder.mkdir()
    for b in range(1, 6):
        cf.rewrite(cf.band_file("0001", b), folder / f"IMG_0001_{b}.tif", lambda x: re.sub(
            r"<Camera:Irradiance>([^<]+)</Camera:Irradiance>",
            lambda m: f"<Camera:Irradiance>{float(m[1]) * 50}</Camera:Irradiance>", x))
    run, _ = _apply(folder, tmp_path / "out")
    chk = run_value(run, "sun_sensor_check")
    assert chk["implausible"] == 5 and chk["ratio_range"] == pytest.approx([50 * 0.6564, 50 * 0.8494], abs=0.02)
    warns = [w for w in run_value(run, "light")["warnings"] if w["code"] == "sun_sensor_implausible"]
    assert len(warns) == 1 and warns[0]["threshold"] == 1.5
    assert warns[0]["value"] == pytest.approx(50 * 0.8494, abs=0.02) and warns[0]["band"] == "Blue"
    # the QA report (and with it the run's summary) says it
    codes = [w["code"] for w in report_warnings(flights=[tmp_path / "out"])]
    assert "sun_sensor_implausible" in codes


def test_the_panel_compares_with_the_sensor_read_in_the_unit_chosen(tmp_path) -> None:
    """With the panel capture IMG_0000, run.json's panel/DLS factor ratio of a DLS 2 file written
    in W m-2 nm-1 without a scale tag is the DLS 1 file's (0.73 at NIR to 1.01 at Blue with a
    panel of 0.5), not 100 times lower."""
    require_data()
    dls1 = tmp_path / "dls1"
    dls1.mkdir()
    for cap in ("0000", "0001"):
        for b in range(1, 6):
            cf.rewrite(cf.band_file(cap, b), dls1 / f"IMG_{cap}_{b}.tif")
    si = _dls2(tmp_path / "si", 1.0, ("0000", "0001"))
    runs = []
    for folder in (dls1, si):
        out = tmp_path / f"out_{folder.name}"
        assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out), "--panel-reflectance", "0.5",
                     "--panel", "IMG_0000"]) == 0
        runs.append(json.loads((out / "run.json").read_text()))
    ratio = [run_value(r, "reference")["panels"][0]["panel_over_dls"] for r in runs]
    assert ratio[1] == pytest.approx(ratio[0], rel=1e-9)
    assert ratio[0] == pytest.approx({"Blue": 1.0136, "Green": 0.8727, "Red": 0.9037, "NIR": 0.7266,
                                      "Red edge": 0.9380}, abs=2e-4)
    assert run_value(runs[1], "sun_sensor_check")["rules"] == {AS_WRITTEN_RULE: 10}
