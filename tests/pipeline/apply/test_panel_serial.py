"""``mscal apply --calibration factory`` takes the panel's reflectance from its serial number:
read from the panel's QR code in the pixels (MicaSense's real panel capture IMG_0000 shows
RP02-1603036-SC) or from the band files' XMP PanelSerial, and looked up in catalogs/targets.
Order: the camera's XMP Albedo, else the serial's target, else the sun sensor, else none."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr

from mscal_core.errors import CatalogError
from pipeline.apply.factory import FactoryOptions, apply_factory
from pipeline.ingest import catalog
from pipeline.ingest.targets import target_for_serial
from pipeline.run.cli import main
from pipeline.storage.run_layout import run_value
from tests import camera_files as cf
from tests.micasense_data import BANDS, require_data

TARGET = "micasense-rp02-1603036-sc"
SERIAL = "RP02-1603036-SC"
QR_SOURCE = f"panel serial {SERIAL} (QR code of IMG_0000) -> target {TARGET}"
# x0, y0, x1, y1 around the QR code of IMG_0000 per band (cv2.QRCodeDetector's corners, 12 px more)
QR_BOXES = ((444, 464, 594, 613), (410, 475, 560, 624), (410, 502, 559, 652), (463, 506, 616, 657),
            (446, 485, 594, 633))


def _reflectance(out: Path) -> np.ndarray:
    with xr.open_zarr(out / "reflectance.zarr") as ds:
        return ds["reflectance"].values


def _reference(out: Path) -> dict:
    return run_value(json.loads((out / "run.json").read_text()), "reference")


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    """A folder holding copies of the sample's 10 band files (IMG_0000: panel, IMG_0001: flight)."""
    folder = tmp_path_factory.mktemp("serial") / "in"
    folder.mkdir()
    for f in sorted(require_data().glob("IMG_000[01]_*.tif")):
        shutil.copy(f, folder / f.name)
    return folder


@pytest.fixture(scope="module")
def named_run(sample: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "named"
    apply_factory(sample, out, FactoryOptions(panel_reflectance=TARGET))
    return out


def _with_xmp_serial(folder: Path, serial: str, *, hide_qr: bool = False) -> Path:
    """The sample with ``MicaSense:PanelSerial`` in IMG_0000's band files (as newer firmware
    writes it in panel captures); ``hide_qr``: the QR code's pixels shuffled (unreadable, the
    panel untouched)."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for cap in cf.CAPTURES:
        for b in range(1, 6):
            def edit(x: str, cap: str = cap) -> str:
                tag = f"<MicaSense:PanelSerial>{serial}</MicaSense:PanelSerial>"
                return x.replace("</MicaSense:CaptureId>", "</MicaSense:CaptureId>" + tag) if cap == "0000" else x

            dst = cf.rewrite(cf.band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", edit)
            if hide_qr and cap == "0000":
                x0, y0, x1, y1 = QR_BOXES[b - 1]
                dn = tifffile.memmap(dst, mode="r+")
                dn[y0:y1, x0:x1] = rng.permutation(dn[y0:y1, x0:x1].ravel()).reshape(y1 - y0, x1 - x0)
                dn.flush()
                del dn
    return folder


def test_the_panel_serial_in_its_qr_code_gives_the_reflectance(sample: Path, named_run: Path, tmp_path: Path) -> None:
    """No option: the QR code of IMG_0000 names the panel, its target gives rho, and the
    reflectance is that of the run naming the target (rtol 1e-6); run.json says where rho came
    from and why the camera's Albedo was not used; the panel comes back at its reflectance."""
    out = tmp_path / "auto"
    res = apply_factory(sample, out)
    assert not res.up_to_date
    ref = _reference(out)
    assert ref["route"] in ("panel", "panel-dls") and ref["route"] == _reference(named_run)["route"] == "panel-dls"
    assert ref["panel_reflectance"] == QR_SOURCE
    assert ref["panel_serial"] == {"serial": SERIAL, "capture": "IMG_0000", "source": "QR code", "target": TARGET}
    assert ref["albedo"] == "no capture carries XMP Albedo with CalibrationPicture 2"
    assert "panels_seen" not in ref and "panel_serial_unknown" not in ref
    (panel,) = ref["panels"]
    assert panel["capture"] == "IMG_0000"
    assert panel["reflectance"] == {"Blue": 0.67, "Green": 0.69, "Red": 0.68, "NIR": 0.61, "Red edge": 0.67}
    assert panel["factor_split"] == _reference(named_run)["panels"][0]["factor_split"]
    got, want = _reflectance(out), _reflectance(named_run)
    assert np.isfinite(got).mean() > 0.99
    np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)
    run = json.loads((out / "run.json").read_text())
    assert run_value(run, "panels") == [{"capture": "IMG_0000", "reason": "reflectance panel of the panel route (the panel's serial)"}]
    # the same, up to date
    assert apply_factory(sample, out).up_to_date


def test_a_changed_target_redoes_the_run(sample: Path, tmp_path: Path, monkeypatch) -> None:
    """The serial's target is part of what the run used: editing that catalog file makes the
    next run redo the flight with the new reflectance (here 0.5 in every band)."""
    targets = tmp_path / "catalog" / "targets"
    targets.mkdir(parents=True)
    path = targets / f"{TARGET}.yaml"
    shutil.copy(catalog.CATALOG_ROOT / "targets" / f"{TARGET}.yaml", path)
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path / "catalog"))
    out = tmp_path / "out"
    apply_factory(sample, out)
    first = _reflectance(out)
    assert apply_factory(sample, out).up_to_date
    path.write_text(f"name: {TARGET}\ndescription: edited\nreflectance: 0.5\nserial: {SERIAL.lower()}\n")
    res = apply_factory(sample, out)
    assert not res.up_to_date
    ref = _reference(out)
    assert ref["panels"][0]["reflectance"] == dict.fromkeys(BANDS, 0.5)
    # reflectance scales with the panel's: Red 0.68 -> 0.5
    red = BANDS.index("Red")
    ratio = np.nanmedian(_reflectance(out)[1, red] / first[1, red])
    assert ratio == pytest.approx(0.5 / 0.68, rel=1e-5)


def test_an_unknown_serial_falls_back_to_the_sun_sensor_and_says_why(tmp_path: Path, capsys) -> None:
    """XMP PanelSerial of a panel in no target: the sun sensor, as with --reference dls (same
    reflectance), and run.json says why the panel was not used and how to add it; the summary
    warns (panel_not_used) with that hint. --reference panel asked for stops naming the serial."""
    folder = _with_xmp_serial(tmp_path / "in", " RP99-0000000-XX ")
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(tmp_path / "auto")]) == 0
    text = capsys.readouterr().out
    ref = _reference(tmp_path / "auto")
    assert ref["route"] == "dls" and "panel_reflectance" not in ref
    assert ref["panel_serial"] == {"serial": "RP99-0000000-XX", "capture": "IMG_0000", "source": "XMP PanelSerial",
                                   "target": None}
    assert ref["panel_serial_unknown"] == ("RP99-0000000-XX (XMP PanelSerial of IMG_0000) is in no catalogs/targets "
                                           "file; add one with its per-band reflectance")
    assert ref["albedo"] == "no capture carries XMP Albedo with CalibrationPicture 2"
    assert ref["panels_seen"] == ["IMG_0000"]
    assert "warning panel_not_used: 1 panel capture(s) in the folder (IMG_0000) but reflectance comes from the sun " \
           "sensor (DLS): add catalogs/targets/NAME.yaml with 'serial: RP99-0000000-XX'" in text
    assert main(["apply", str(folder), "--calibration", "factory", "--reference", "dls", "-o",
                 str(tmp_path / "dls")]) == 0
    np.testing.assert_array_equal(_reflectance(tmp_path / "auto"), _reflectance(tmp_path / "dls"))
    capsys.readouterr()
    assert main(["apply", str(folder), "--calibration", "factory", "--reference", "panel", "-o",
                 str(tmp_path / "panel")]) == 2
    err = capsys.readouterr().err
    assert "needs --panel-reflectance" in err and (
        "panel serial RP99-0000000-XX (XMP PanelSerial of IMG_0000) is in no catalogs/targets file") in err
    assert not (tmp_path / "panel").exists()


def test_the_xmp_panel_serial_alone_gives_the_reflectance(tmp_path: Path) -> None:
    """IMG_0000 with its QR code made unreadable and the serial in XMP MicaSense:PanelSerial
    (written in lower case): the panel route from the tag, as naming the target."""
    from mscal_core.panel import qr_serial

    folder = _with_xmp_serial(tmp_path / "in", SERIAL.lower(), hide_qr=True)
    assert qr_serial([tifffile.imread(folder / f"IMG_0000_{b}.tif") for b in range(1, 6)], give_up_after=None) is None
    apply_factory(folder, tmp_path / "auto")
    apply_factory(folder, tmp_path / "named", FactoryOptions(panel_reflectance=TARGET))
    ref = _reference(tmp_path / "auto")
    assert ref["route"] == "panel-dls"
    assert ref["panel_reflectance"] == f"panel serial {SERIAL.lower()} (XMP PanelSerial of IMG_0000) -> target {TARGET}"
    np.testing.assert_allclose(_reflectance(tmp_path / "auto"), _reflectance(tmp_path / "named"), rtol=1e-6,
                               equal_nan=True)


def test_target_for_serial_reads_every_catalog_folder(tmp_path: Path, monkeypatch) -> None:
    """Case and surrounding whitespace do not matter; a serial in no target is None; a target of
    MSCAL_CATALOG_PATH adds serials, and two targets listing one serial are an error."""
    assert target_for_serial(f"  {SERIAL.lower()}\n").name == TARGET
    assert target_for_serial("RP02-1603036") is None and target_for_serial("") is None
    (tmp_path / "targets").mkdir()
    (tmp_path / "targets" / "mine.yaml").write_text(
        "name: mine\ndescription: d\nreflectance: 0.4\nserials: [RP04-1111111-OB, RP04-2222222-OB]\n")
    monkeypatch.setenv("MSCAL_CATALOG_PATH", str(tmp_path))
    assert target_for_serial("rp04-2222222-ob").reflectance.scalar == 0.4
    (tmp_path / "targets" / "twin.yaml").write_text(
        f"name: twin\ndescription: d\nreflectance: 0.4\nserial: {SERIAL}\n")
    with pytest.raises(CatalogError, match=f"panel serial '{SERIAL}' is listed by several targets: "
                                           f"{TARGET}, twin"):
        target_for_serial(SERIAL)


def test_a_known_serial_without_a_panel_in_sight_falls_back_and_says_why(tmp_path: Path) -> None:
    """The flight capture alone with the sample panel's serial in XMP PanelSerial: the target is
    known but no panel is found in the pixels, so auto takes the sun sensor and run.json says why."""
    folder = tmp_path / "in"
    folder.mkdir()
    for b in range(1, 6):
        cf.rewrite(cf.band_file("0001", b), folder / f"IMG_0001_{b}.tif",
                   lambda x: cf.add_camera_element(x, f"<Camera:PanelSerial>{SERIAL}</Camera:PanelSerial>"))
    apply_factory(folder, tmp_path / "out")
    ref = _reference(tmp_path / "out")
    assert ref["route"] == "dls" and "panel_reflectance" not in ref and "albedo_panel_unusable" not in ref
    assert ref["panel_serial"] == {"serial": SERIAL, "capture": "IMG_0001", "source": "XMP PanelSerial",
                                   "target": TARGET}
    assert ref["panel_serial_unusable"].startswith("in: no reflectance panel found in the captures searched")
