"""Panels anchored by the sun sensor: warnings with their numbers, the report's
tables, the panel-dls route without readings."""

from __future__ import annotations

import numpy as np

from pipeline.apply.sunlight import RATIO_DRIFT_WARN, PanelSensorLight, light_warnings
from pipeline.storage.run_layout import run_value
from tests.micasense_data import require_data


def test_warnings_carry_numbers_and_thresholds() -> None:
    light = PanelSensorLight(factor=np.ones((3, 2)), sensor_used=np.ones((3, 2), bool), ratio=np.ones((3, 2)),
                             drift=np.array([0.01, 0.08]))
    warns = light_warnings(["A", "B", "C"], ["Red", "NIR"], None, light, ["A", "C"])
    assert [(w["code"], w["band"], w["value"], w["threshold"]) for w in warns] == [
        ("panel_sensor_disagree", "NIR", 0.08, RATIO_DRIFT_WARN)]
    assert "8.0%" in warns[0]["message"]
    assert light_warnings(["A"], ["Red", "NIR"], None, light, ["A"]) == []  # one panel: nothing to disagree


def test_report_shows_the_light_and_its_warnings() -> None:
    from pipeline.products.report.sections import light_tables
    from pipeline.products.report.sections import light_warnings as report_warnings

    run = {"light": {
        "route": "panel-dls", "irradiance_unit": "W m-2 nm-1 (pi / k)",
        "panels_over_time": [{"capture": "A", "panel_irradiance": {"NIR": 0.5, "Red": 0.8},
                              "sensor_irradiance": {"NIR": 0.4, "Red": 1.0}}],
        "panel_sensor_drift": {"NIR": 0.08, "Red": 0.0},
        "frame_irradiance": {"A": {"NIR": 0.5, "Red": 0.8}, "B": {"NIR": 0.45, "Red": 0.7}},
        "sensor_used": {"A": True, "B": True},
        "warnings": [{"code": "panel_sensor_disagree", "band": "NIR", "value": 0.08, "threshold": 0.03,
                      "message": "NIR: disagree by 8.0%"}]}}
    over, frames = light_tables(run, ["Red", "NIR"])
    assert over.rows == [["A", "Red", 0.8, 1.0, 0.8], ["A", "NIR", 0.5, 0.4, 1.25]]
    assert "NIR 8.0%" in over.note
    assert frames.columns == ["frame", "Red", "NIR", "sun sensor used"] and frames.rows[1] == ["B", 0.7, 0.45, True]
    (w,) = report_warnings(run)
    assert (w.code, w.value, w.threshold) == ("panel_sensor_disagree", 0.08, 0.03)
    assert light_tables({}, []) == [] and report_warnings({}) == []


def test_panel_dls_without_readings_exits_2(tmp_path, capsys) -> None:
    from pipeline.run.cli import main
    from tests.camera_files import band_file, drop_element, rewrite

    require_data()
    folder = tmp_path / "noirr"
    folder.mkdir()
    for cap in ("0000", "0001"):
        for b in range(1, 6):
            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif",
                    lambda x: drop_element(drop_element(x, "Camera:Irradiance"), "DLS:SpectralIrradiance"))
    args = ["apply", str(folder), "--calibration", "factory", "--panel-reflectance", "micasense-rp02-1603036-sc"]
    assert main([*args, "-o", str(tmp_path / "o"), "--reference", "panel-dls"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--reference panel-dls: no capture in the folder has a sun-sensor reading" in err and "\n" not in err
    assert main([*args, "-o", str(tmp_path / "auto")]) == 0  # auto: the panel alone
    import json

    assert run_value(json.loads((tmp_path / "auto" / "run.json").read_text()), "reference")["route"] == "panel"
