"""The command line follows conventions: --version, -v/-q/--json on every command,
short help never cut, help on every option, one name per option, a summary with the QA
report's own warnings (one JSON document with --json), the panel a factory apply saw but did
not use, index without rasterio's NotGeoreferencedWarning, progress bars on stderr."""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import json
import logging
import shutil
import sys
import warnings
from pathlib import Path

import click
import numpy as np
import pytest

from pipeline.products.report import report_dict
from pipeline.run.cli import cli, main
from pipeline.storage.run_layout import GROUPS, run_value
from tests.micasense_data import DATA as MICASENSE
from tests.micasense_data import band_file, require_data

DATA = MICASENSE.parent
PANEL = "micasense-rp02-1603036-sc"


def _run(argv: list) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def _commands(group: click.Group = cli, path: tuple[str, ...] = ()):
    for name, cmd in sorted(group.commands.items()):
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def _report_warnings(calibration=None, flights=()) -> list[dict]:
    return [w for s in report_dict(calibration, flights)["sections"] for w in s["warnings"]]


def _codes_values(ws: list[dict]) -> list[tuple[str, float, float]]:
    return [(w["code"], round(w["value"], 9), round(w["threshold"], 9)) for w in ws]


# --------------------------------------------------------------------------- options and help


def test_version() -> None:
    code, out, _ = _run(["--version"])
    assert code == 0 and out == f"mscal {importlib.metadata.version('mscal')}\n"


def test_every_command_takes_v_q_json_and_documents_them() -> None:
    names = []
    for path, _ in _commands():
        code, out, _ = _run([*path, "--help"])
        assert code == 0, path
        for opt in ("-v, --verbose", "-q, --quiet", "--json"):
            assert opt in out, (path, opt)
        names.append(" ".join(path))
    assert len(names) == 15  # 11 commands + fit's 4


def test_v_and_q_before_or_after_the_command_name() -> None:
    folder = DATA / "parrot-sequoia"
    if not folder.is_dir():
        pytest.skip("no shared data")
    root = logging.getLogger()
    level = root.level
    try:
        for argv, want in ((["-v", "cameras", folder], logging.INFO), (["cameras", folder, "-v"], logging.INFO),
                           (["-q", "cameras", folder], logging.ERROR), (["cameras", "-q", folder], logging.ERROR)):
            code, out, _ = _run(argv)
            assert code == 0 and "camera: parrot-sequoia" in out
            assert root.level == want, argv
        code, _, err = _run(["-v", "cameras", folder, "-q"])
        assert code == 2 and "give -v or -q, not both" in err
    finally:
        root.setLevel(level)
    a = json.loads(_run(["--json", "cameras", folder])[1])
    b = json.loads(_run(["cameras", folder, "--json"])[1])
    assert a == b and a["counts"] == {"folders": 1}
    assert any("camera: parrot-sequoia" in line for line in a["folders"][str(folder)])


def test_short_help_is_whole_and_listed_uncut() -> None:
    _, top, _ = _run(["--help"])
    _, fit, _ = _run(["fit", "--help"])
    for path, cmd in [((n,), c) for n, c in cli.commands.items()] + list(_commands()):
        text = cmd.get_short_help_str(limit=45)
        assert text == cmd.short_help and text.endswith(".") and "..." not in text, path
        listing = fit if path[0] == "fit" and len(path) > 1 else top
        assert any(line.split(None, 1)[1:] == [text] for line in listing.splitlines()
                   if line.strip().startswith(path[-1] + " ")), (path, text)


def test_every_option_has_help_and_one_name() -> None:
    names: dict[str, set[str]] = {}
    for path, cmd in _commands():
        for p in cmd.params:
            if isinstance(p, click.Option) and not p.hidden:
                assert p.help, (path, p.opts)
                names.setdefault(p.name, set()).add(tuple(sorted(p.opts)))
    assert names["response_method"] == {("--response-method",)}
    assert names["out"] == {("--output", "-o")}
    for path in (("calibrate",), ("fit", "response"), ("run",), ("serve",)):
        _, out, _ = _run([*path, "--help"])
        assert "--response-method" in out and "--method " not in out, path


def test_fit_response_method_is_a_deprecated_alias(small, tmp_path: Path, monkeypatch) -> None:
    from pipeline.calibrate import fit
    from pipeline.storage.store import open_calibration

    session, calib = small
    seen = []

    def fake(directory, out, camera, method):  # the fit is tested elsewhere
        seen.append(method)
        return open_calibration(calib)

    monkeypatch.setattr(fit, "fit_response_cli", fake)
    code, out, err = _run(["fit", "response", session, "-o", calib, "--method", "alternating", "--json"])
    assert code == 0 and seen == ["alternating"]
    assert "--method is deprecated, use --response-method" in err
    assert json.loads(out)["command"] == "fit response"
    code, _, err = _run(["fit", "response", session, "-o", calib, "--response-method", "alternating"])
    assert code == 0 and seen[-1] == "alternating" and "deprecated" not in err
    assert _run(["fit", "response", session, "-o", calib])[0] == 0 and seen[-1] == "forward"


# --------------------------------------------------------------------------- summaries


@pytest.fixture(scope="module")
def micasense(tmp_path_factory) -> Path:
    require_data()
    folder = tmp_path_factory.mktemp("rededge") / "flight"
    folder.mkdir()
    for cap in ("0000", "0001"):
        for b in range(1, 6):
            shutil.copy(band_file(cap, b), folder)
    return folder


def test_factory_apply_says_a_panel_was_seen_and_how_to_use_it(micasense: Path, tmp_path: Path, monkeypatch) -> None:
    """The panel's serial (its QR code) is in no target here (the shipped target is shadowed by
    one without it): the sun sensor gives reflectance and the summary says how to use the panel."""
    (tmp_path / "catalog" / "targets").mkdir(parents=True)
    (tmp_path / "catalog" / "targets" / f"{PANEL}.yaml").write_text(
        f"name: {PANEL}\ndescription: the panel without its serial\nreflectance: 0.5\n")
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path / "catalog"))
    out = tmp_path / "dls"
    code, text, _ = _run(["apply", micasense, "--calibration", "factory", "-o", out])
    assert code == 0
    lines = text.splitlines()
    assert lines[0].startswith(f"wrote {out} (2 frames, 0 quarantined;")
    assert f"  run record: {out / 'run.json'}" in lines
    # the bands' own grids, measured on the flight capture's pixels: MicaSense writes no alignment
    warn, misreg = [ln for ln in lines if ln.startswith("  warning ")]
    assert misreg.startswith("  warning band_misregistration: bands are off band Red after alignment 'none' by "
                             "NIR 14.1 px, Red edge 13.7 px, Blue 10.3 px, Green 2.5 px (median over 1 measured")
    assert warn.startswith("  warning panel_not_used: 1 panel capture(s) in the folder (IMG_0000) but reflectance "
                           "comes from the sun sensor (DLS): add catalogs/targets/NAME.yaml with 'serial: "
                           "RP02-1603036-SC' and the panel's per-band reflectance")
    assert "or give --panel-reflectance TARGET; --panel IMG_0000 chooses the capture" in warn
    assert warn.endswith("(value 1, threshold 0)")
    run = json.loads((out / "run.json").read_text())
    assert run_value(run, "reference")["route"] == "dls" and run_value(run, "reference")["panels_seen"] == ["IMG_0000"]
    assert run_value(run, "reference")["panel_serial_unknown"].startswith("RP02-1603036-SC (QR code of IMG_0000) is in no")
    # --json: one document and nothing else on stdout (the second run is up to date)
    code, text, _ = _run(["apply", micasense, "--calibration", "factory", "-o", out, "--json"])
    doc = json.loads(text)
    assert code == 0 and doc["up_to_date"] is True and doc["counts"]["frames_out"] == 2
    assert doc["counts"]["saturated_pixels"] == 7268
    assert _codes_values(doc["warnings"]) == _codes_values(_report_warnings(flights=[out])) == [
        ("panel_not_used", 1.0, 0.0), ("band_misregistration", 14.062, 1.0)]


def test_factory_apply_without_any_reflectance_warns_why_and_how(tmp_path: Path) -> None:
    """--reference auto on a Sequoia capture without Camera:IrradianceSensitivitiesGolden: no
    panel, no usable sun sensor, so radiance only; the summary (and report.html) says so, with
    the file, the tag and the fix, instead of looking like a success."""
    from tests import camera_files as cf

    if not cf.SEQUOIA.is_dir():
        pytest.skip("no Sequoia sample")
    folder = cf.sequoia_without_golden(tmp_path / "old")
    out = tmp_path / "out"
    code, text, _ = _run(["apply", folder, "--calibration", "factory", "-o", out])
    assert code == 0
    lines = text.splitlines()
    assert lines[0].startswith(f"wrote {out} (1 frames, 0 quarantined;")
    assert "  2 quality warning(s) (as in report.html):" in lines
    warn, misreg = [ln for ln in lines if ln.startswith("  warning ")]
    assert misreg.startswith("  warning band_misregistration: bands are off band Red after alignment 'none' by "
                             "Red edge 82.0 px, NIR 50.5 px, Green 41.0 px")  # Sequoia writes no alignment
    assert warn == (
        "  warning no_reflectance: reflectance and indices are NaN in all 1 frame(s), radiance only: no panel given "
        "and the sun sensor gives no usable reflectance (IMG_180413_080658_0000_GRE.TIF: XMP "
        "IrradianceSensitivitiesGolden = '(missing)': not in the file (older firmware?): the bands' sunshine readings "
        "cannot be put on one scale without it (sun_sensor disabled)): give --panel-reflectance TARGET (a number, or "
        "a target of catalogs/targets) with a panel capture in the folder (--panel IMG_XXXX names it); "
        "--products radiance writes the radiance (value 1, threshold 0)")
    assert _codes_values(_report_warnings(flights=[out])) == [("no_reflectance", 1.0, 0.0),
                                                              ("band_misregistration", 82.028, 1.0)]
    code, text, _ = _run(["apply", folder, "--calibration", "factory", "-o", out, "--json"])  # up to date
    doc = json.loads(text)
    assert code == 0 and doc["up_to_date"] is True and doc["reference"]["route"] == "none"
    assert _codes_values(doc["warnings"]) == [("no_reflectance", 1.0, 0.0), ("band_misregistration", 82.028, 1.0)]


def test_factory_apply_with_the_panel_reports_its_colour_disagreement(micasense: Path, tmp_path: Path) -> None:
    out = tmp_path / "panel"
    code, text, err = _run(["apply", micasense, "--calibration", "factory", "-o", out, "--panel-reflectance", PANEL,
                            "--json"])
    doc = json.loads(text)
    assert code == 0 and doc["command"] == "apply" and doc["reference"]["route"] == "panel-dls"  # the default with a panel and sun-sensor readings
    w, misreg = doc["warnings"]
    assert misreg["code"] == "band_misregistration" and misreg["value"] == pytest.approx(14.06, abs=0.01)
    assert w["code"] == "panel_dls_colour" and w["threshold"] == 0.05
    assert w["value"] == pytest.approx(0.532, abs=0.01)
    assert _codes_values(doc["warnings"]) == _codes_values(_report_warnings(flights=[out]))
    assert err == ""  # the flight folder holds only captures: no notes
    # -q keeps the summary's first line and the warning, not the outputs
    code, text, _ = _run(["-q", "apply", micasense, "--calibration", "factory", "-o", out, "--panel-reflectance",
                          PANEL])
    lines = text.splitlines()
    assert code == 0 and lines[0].endswith("up to date)") and len(lines) == 4
    assert lines[2].startswith("  warning panel_dls_colour: panel IMG_0000: panel and sun sensor disagree in colour "
                               "by 53%") and lines[2].endswith("(value 0.5322, threshold 0.05)")  # one panel region for all bands



def test_a_run_folder_of_the_flat_run_json_layout_is_up_to_date_and_reports_the_same(micasense: Path,
                                                                                     tmp_path: Path) -> None:
    """A run.json written before the keys of a kind of input moved under ``captures`` and
    ``factory`` (every key at the top): the same apply finds it up to date (the fingerprint did
    not change shape) and the summary and the report read its keys as they read the new layout's."""
    out = tmp_path / "out"
    args = ["apply", micasense, "--calibration", "factory", "-o", out, "--panel-reflectance", PANEL, "--json"]
    code, text, _ = _run(args)
    new, report = json.loads(text), report_dict(None, [out])
    run = json.loads((out / "run.json").read_text())
    common = {"flight", "camera", "calibration", "calibration_sha256", "frames_in", "frames_out", "frames",
              "frames_sha256", "quarantined", "metadata_problems", "saturated_pixels", "quality", "outputs", "products",
              "export_bands", "versions", "scheduler", "execution", "timings_s", "fingerprint", "outputs_manifest",
              "illumination"}
    assert set(run) - common == {"captures", "factory"}  # every other key under its kind of input
    code, text, _ = _run(args)  # the new layout's record is up to date (its inputs_listing found under captures)
    assert code == 0 and json.loads(text)["up_to_date"] is True
    flat = {k: v for k, v in run.items() if k not in GROUPS}
    for group in GROUPS:
        flat.update(run[group])
    assert set(flat) > {"reference", "light", "sun_sensor", "panels", "inputs_listing", "coregistration"}
    (out / "run.json").write_text(json.dumps(flat))
    code, text, _ = _run(args)
    doc = json.loads(text)
    assert code == 0 and doc["up_to_date"] is True and json.loads((out / "run.json").read_text()) == flat
    assert doc["reference"] == new["reference"] and doc["reference"]["route"] == "panel-dls"
    assert doc["warnings"] == new["warnings"] and [w["code"] for w in doc["warnings"]] == [
        "panel_dls_colour", "band_misregistration"]
    assert report_dict(None, [out]) == report


def test_a_folder_without_a_panel_gets_no_panel_warning(tmp_path: Path) -> None:
    require_data()
    folder = tmp_path / "flight"
    folder.mkdir()
    for b in range(1, 6):
        shutil.copy(band_file("0001", b), folder)
    code, text, _ = _run(["apply", folder, "--calibration", "factory", "-o", tmp_path / "out", "--json"])
    doc = json.loads(text)
    assert code == 0 and "panels_seen" not in doc["reference"]
    assert [w["code"] for w in doc["warnings"]] == ["band_misregistration"]  # MicaSense writes no alignment


def _fake_tty(monkeypatch) -> io.StringIO:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    return err


def _main_tty(argv: list, monkeypatch) -> tuple[int, str, str]:
    out = io.StringIO()
    err = _fake_tty(monkeypatch)
    with contextlib.redirect_stdout(out):
        code = main([str(a) for a in argv])
    monkeypatch.undo()
    return code, out.getvalue(), err.getvalue()


def test_report_progress_bar_summary_and_json(small, tmp_path: Path, monkeypatch) -> None:
    _, calib = small
    code, out, err = _main_tty(["report", "--calibration", calib, "-o", tmp_path / "r.html", "--json"], monkeypatch)
    doc = json.loads(out)
    assert code == 0 and "report" in err and "100%" in err
    assert doc["counts"]["figures"] >= 5 and doc["outputs"]["QA report"] == str(tmp_path / "r.html")
    assert _codes_values(doc["warnings"]) == _codes_values(_report_warnings(calib))
    assert ("vignetting_coverage", pytest.approx(0.22, abs=0.01)) in [(w["code"], w["value"]) for w in doc["warnings"]]
    code, _, err = _main_tty(["report", "--calibration", calib, "-o", tmp_path / "r.html", "-q"], monkeypatch)
    assert code == 0 and err == ""  # -q: no bar
    code, _, err = _run(["report", "--calibration", calib, "-o", tmp_path / "r.html"])
    assert code == 0 and "100%" not in err  # not a terminal: no bar


def test_calibrate_progress_bar_and_summary(small, tmp_path: Path, monkeypatch) -> None:
    """The command's wiring (the fits themselves are tested elsewhere): four steps on the
    bar, the summary's warnings those of the store written."""
    from pipeline.calibrate import fit
    from pipeline.storage.store import open_calibration

    session, calib = small
    steps = []

    def fake(session_dir, out, *, response_method, calibration, advance, pool, sweep):
        # the band workers and the sweep's fits were started before the fit module was used
        assert pool.workers >= 1 and sweep.method == response_method and len(sweep.futures) == 25
        for _ in range(fit.CALIBRATE_STEPS):
            advance()
            steps.append(1)
        return open_calibration(calib)

    monkeypatch.setattr(fit, "calibrate_session", fake)
    monkeypatch.setenv("MSCAL_CACHE_DIR", str(tmp_path / "cache"))
    code, out, err = _main_tty(["calibrate", session, "-o", calib, "--json"], monkeypatch)
    doc = json.loads(out)
    assert code == 0 and len(steps) == 4 and "calibrate" in err and "100%" in err
    assert doc["counts"]["bands"] == 25 and doc["counts"]["frames_skipped"]["vignetting"] == 1
    assert _codes_values(doc["warnings"]) == _codes_values(_report_warnings(calib))
    # the store is recorded in the calibration library of the cache folder (the snapshot
    # session's frames carry no serial number: filed under unknown)
    index = json.loads((tmp_path / "cache" / "library" / "index.json").read_text())
    (entry,) = index["entries"]
    assert doc["library"] == doc["outputs"]["calibration library"] == str(tmp_path / "cache" / "library" / entry["store"])
    assert entry["store"].startswith("ximea-mq022hg-sm5x5-nir/unknown/") and entry["session"] == str(Path(session).resolve())


def test_register_progress_bar_and_spread_warning(micasense: Path, tmp_path: Path, monkeypatch) -> None:
    """Registered at a third of the resolution (test time): the panel capture (at 1 m) and the
    flight capture disagree by several pixels; the summary has the report's warning."""
    from pipeline.calibrate import registration

    read = registration.read_capture
    monkeypatch.setattr(registration, "read_capture", lambda c: read(c)[:, ::3, ::3])
    with monkeypatch.context() as m:
        out = io.StringIO()
        err = _fake_tty(m)
        with contextlib.redirect_stdout(out):
            code = main(["register", str(micasense), "--camera", "micasense-rededge", "-o", str(tmp_path / "reg.zarr"),
                         "--json"])
    doc = json.loads(out.getvalue())
    assert code == 0 and "register" in err.getvalue() and "100%" in err.getvalue()
    assert doc["counts"]["captures_registered"] == 2
    spread = doc["registration_spread_px"]
    (w,) = [w for w in doc["warnings"] if w["code"] == "registration_spread"]
    assert w["value"] == pytest.approx(max(spread.values())) and w["value"] > 1.0 and w["threshold"] == 1.0
    assert _codes_values(doc["warnings"]) == _codes_values(_report_warnings(tmp_path / "reg.zarr"))


# --------------------------------------------------------------------------- index


def _raster(path: Path, georeferenced: bool) -> Path:
    import rasterio
    from rasterio.transform import Affine

    data = np.stack([np.full((32, 48), v, dtype=np.float32) for v in (0.1, 0.5)])
    profile = {"driver": "GTiff", "width": 48, "height": 32, "count": 2, "dtype": "float32"}
    if georeferenced:
        profile.update(crs="EPSG:32633", transform=Affine(0.1, 0.0, 500000.0, 0.0, -0.1, 4000000.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(data)
    return path


@pytest.mark.parametrize("geo", [False, True])
def test_index_says_once_that_the_input_is_not_georeferenced(tmp_path: Path, geo: bool) -> None:
    src = _raster(tmp_path / "in.tif", geo)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, out, err = _run(["index", src, "--bands", "red=1,nir=2", "-o", tmp_path / "ndvi.tif", "--json"])
    assert code == 0
    assert not [w for w in caught if "NotGeoreferenced" in type(w.message).__name__ + str(w.category)]
    doc = json.loads(out)
    assert doc["georeferenced"] is geo and doc["outputs"]["index map"] == str(tmp_path / "ndvi.tif")
    assert err.count("has no georeferencing") == (0 if geo else 1)
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(tmp_path / "ndvi.tif") as ds:
            assert ds.read(1)[0, 0] == pytest.approx((0.5 - 0.1) / (0.5 + 0.1), abs=1e-6)
            assert (ds.crs is not None) is geo


def test_demo_prints_plain_lines_or_one_json_document(tmp_path: Path, monkeypatch) -> None:
    """The demo's printing (its flow is tested in tests/flows): plain lines without JSON, or
    with --json one document and nothing else."""
    from pipeline.run import cli as cli_mod
    from pipeline.run import demo

    out = tmp_path / "demo"

    def fake(o, *, flow, size, seed):
        out.mkdir(exist_ok=True)
        (out / "run.json").write_text(json.dumps({"flights": {"field": {}}}))
        return {"session": str(out / "session"), "outputs": str(out), "run_json": str(out / "run.json"),
                "report": None, "calibration_cached": False, "flights": {"field": f"{out}/flights/field (3 frames)"},
                "errors_vs_truth": {"response_max_error": 0.0031, "flight_field": {"ndvi": 0.01}}}

    monkeypatch.setattr(demo, "run_demo", fake)
    monkeypatch.setattr(cli_mod, "_flow", lambda name: None)
    code, text, _ = _run(["demo", "-o", out])
    lines = text.splitlines()
    assert code == 0 and lines[0] == f"wrote {out} (demo session, 1 flight(s); calibration fitted)"
    assert f"  run record: {out / 'run.json'}" in lines and "  error vs truth: response_max_error: 0.0031" in lines
    assert not any(ln.lstrip().startswith(("{", "}", '"')) for ln in lines)
    code, text, _ = _run(["demo", "-o", out, "--json"])
    doc = json.loads(text)
    assert code == 0 and doc["demo"]["errors_vs_truth"]["flight_field"] == {"ndvi": 0.01}


def test_the_executable_is_script_main_and_exits_with_main_status(tmp_path):
    """The installed ``mscal`` runs :func:`pipeline.run.cli.script_main`: main's exit status
    (2 and the one-line reason on bad input, 0 on success), with the garbage collector's
    objects frozen before the shutdown and the exit handlers (logging's) still run."""
    import subprocess

    eps = [ep for ep in importlib.metadata.entry_points(group="console_scripts") if ep.name == "mscal"]
    assert [ep.value for ep in eps] == ["pipeline.run.cli:script_main"]
    probe = (
        "import atexit, gc, sys\n"
        "from pipeline.run import cli\n"
        "atexit.register(lambda: print('frozen', gc.get_freeze_count() > 1000, flush=True))\n"
        "sys.argv = ['mscal', *sys.argv[1:]]\n"
        "cli.script_main()\n"
    )
    bad = subprocess.run([sys.executable, "-c", probe, "calibrate", str(tmp_path / "none"), "-o", str(tmp_path / "c.zarr")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert "mscal: error:" in bad.stderr and "session folder not found" in bad.stderr
    assert bad.stdout.strip() == "frozen True"
    ok = subprocess.run([sys.executable, "-c", probe, "--version"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and ok.stdout.splitlines()[-1] == "frozen True"
    assert not (tmp_path / "c.zarr").exists()


def test_apply_summary_warns_from_the_calibration_apply_read(small, tmp_path: Path, monkeypatch) -> None:
    """The summary's warnings come from the calibration store apply has in memory (the report
    does not read it a second time) and are those of the report of the same store and OUT."""
    from pipeline.products.report import inputs

    session, calib = small
    read = []
    opened = inputs.open_calibration
    monkeypatch.setattr(inputs, "open_calibration", lambda path, *a, **k: read.append(path) or opened(path, *a, **k))
    out = tmp_path / "out"
    code, text, _ = _run(["apply", session / "flights" / "field", "--calibration", calib, "-o", out, "--json"])
    doc = json.loads(text)
    assert code == 0 and doc["counts"]["frames_out"] >= 3
    assert read == []
    want = _report_warnings(calib, [out])
    assert read == [calib]
    assert "vignetting_coverage" in [w["code"] for w in want]  # the calibration's section is in both
    assert _codes_values(doc["warnings"]) == _codes_values(want)
