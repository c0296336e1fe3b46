"""A field calibration of a DJI P4 Multispectral, end to end: a synthetic session written as
the camera writes its band files (pipeline.sim.dji: ``DJI_XXXn.TIF``, 16-bit samples, EXIF
ISOSpeed 200 beside XMP drone-dji:SensorGain 1, ExposureTime in us, DewarpData intrinsics,
factory vignetting and CalibratedHMatrix), fitted by ``mscal calibrate``, applied by ``mscal
apply --calibration STORE`` to the gray-panel captures and checked against the truth.

The point is the exposure: calibrate and apply must take one effective exposure per band file
(``t x SensorGain``; DJI's ISO 200 is no gain of 2). Read by the EXIF rule (ISO / 100) in
calibrate alone, the session's S B come out half as large and apply's reflectance twice the
truth, which ``test_the_exif_iso_rule_in_calibrate_alone_doubles_the_reflectance`` measures.

No pipeline change was needed: the field apply of DJI captures takes the store's response,
vignetting and S, leaves DJI's factory band alignment out (``alignment 'none'`` in run.json:
the field chain does not warp the bands), and the factory reader accepts the built files.
One assumption matters: the files' full scale is 65535 (the catalog's 16 bits, DJI's p = DN /
65535). Files whose clipped pixels sat at 65520 (12-bit DN times 16) would need the catalog to
say so (bit_depth 12, container_bits 16): against a dn_max of 65535 the response fit takes them
for hidden saturation and raises the top of U (pipeline.sim.dji's docstring).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import xarray as xr

from pipeline.ingest import captures
from pipeline.ingest.camera_meta import read_file_metas
from pipeline.ingest.captures import band_file_record, exif_band_record, read_capture_table
from pipeline.ingest.catalog import load_camera
from pipeline.run.cli import main
from pipeline.sim.dji import CAMERA, P4M_BANDS, file_dn_response, to_file_dn, write_dji_session
from pipeline.sim.multilens import evaluate_multilens
from pipeline.storage.run_layout import run_value

pytestmark = pytest.mark.slow  # ~20 s on 2 cores: two calibrations and three applies of 240 x 320 lenses


@pytest.fixture(scope="module")
def dji(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A small P4M session (5 lenses of 240 x 320, 8-frame sweep, 14 views, 2 reflector and 2
    panel captures), its calibration by `mscal calibrate` and the apply of its check captures."""
    root = tmp_path_factory.mktemp("dji")
    session = write_dji_session(root / "session", seed=0, size="small", shape=(240, 320))
    calib, out = root / "calib.zarr", root / "out"
    assert main(["calibrate", str(session), "-o", str(calib)]) == 0
    # the chain's numbers, not the flags: where U's fit share passes its bound (an 8-frame sweep)
    # a few pixels of the brightest panel are flagged, and kept here
    assert main(["apply", str(session / "check"), "--calibration", str(calib), "-o", str(out), "--keep-flagged"]) == 0
    return session, calib, out


def _reflectance(out: Path) -> np.ndarray:
    with xr.open_zarr(out / "reflectance.zarr") as ds:
        return ds["reflectance"].values


def _panel_values(refl: np.ndarray, labels: np.ndarray, n_panels: int) -> np.ndarray:
    """Median reflectance of each panel's pure pixels, (capture, panel, band)."""
    return np.array([[[np.median(refl[f, b][labels[f, b] == p]) for b in range(refl.shape[1])]
                      for p in range(n_panels)] for f in range(refl.shape[0])])


def test_the_session_is_written_as_a_p4_multispectral_writes_it(dji) -> None:
    session, _, _ = dji
    names = sorted(p.name for p in (session / "check").iterdir())
    assert names == [f"DJI_{c}{b}.TIF" for c in (300, 301) for b in range(1, 6)]
    path = session / "check" / "DJI_3004.TIF"
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        tags = {t.code: t.value for t in page.tags.values()}
        dn = page.asarray()
    assert page.bitspersample == 16 and dn.dtype == np.uint16 and dn.max() <= 65535
    assert (tags[271], tags[272], tags[34867]) == ("DJI", "FC6360", 200)  # Make, Model, EXIF ISOSpeed 200
    xmp = tags[700].decode()
    assert 'drone-dji:SensorGain="1"' in xmp and 'drone-dji:BandName="RedEdge"' in xmp
    meta = read_file_metas(path)[0]
    assert (meta.radiometry, meta.band_name, meta.wavelength_nm, meta.gain) == ("dji", "RedEdge", 730.0, 1.0)
    assert meta.problems == ()
    # the rig's 12-bit DN over the full 16-bit range (0 -> 0, 4095 -> 65535), truth U on those DN
    assert to_file_dn(np.array([0, 1, 256, 4095])).tolist() == [0, 16, 4097, 65535]
    u = file_dn_response(np.arange(4096.0)[None])[0]
    assert u[65535] == 4095 and u[4097] == 256 and u[16] == 1
    assert [b[0] for b in P4M_BANDS] == [b.name for b in load_camera(CAMERA).bands]


def test_dji_session_round_trip(dji) -> None:
    """The RedEdge-style session's small-session targets (test_multilens), on the DJI files:
    measured response 0.0034, vignetting 0.010 (observed pixels), S 0.0023, panels 0.0046 with
    Eq. 15 against 0.28 raw."""
    session, calib, _ = dji
    err = evaluate_multilens(session, calib)
    assert err["response_max_error"] < 0.02
    assert err["vignetting_rms_error_observed"] < 0.02
    assert err["spectral_factor_max_error"] < 0.02
    assert err["check"]["captures"] == 2
    assert err["check"]["panel_abs_error"] < 0.015
    assert err["check"]["panel_abs_error_uncalibrated"] > 3 * err["check"]["panel_abs_error"]
    ds = xr.open_zarr(calib).load()
    assert ds["inverse_response"].shape == (5, 65536)  # the catalog's 16 bits: U on the files' DN
    assert ds["intrinsics"].attrs["source"].startswith("metadata of ")  # DewarpData
    truth = np.load(session / "truth.npz")
    np.testing.assert_allclose(ds["intrinsics"].values[:, :4], truth["camera_intrinsics"], rtol=1e-9)


def test_apply_gives_the_gray_panels_reflectance(dji) -> None:
    """`mscal apply --calibration STORE` on the panel captures: each panel's reflectance after
    one scale per capture (the white panel's, median over bands, as evaluate_multilens's
    check) within 0.015 of the truth (measured 0.0046), the five bands agreeing on each panel;
    and the same numbers as Eq. 15 with the store on the raw DN (apply adds only one factor per
    capture, the light level)."""
    session, calib, out = dji
    truth = np.load(session / "truth.npz")
    labels, rho = truth["check_labels"], truth["check_panel_reflectance"]
    run = json.loads((out / "run.json").read_text())
    assert (run["camera"], run["frames_out"], run_value(run, "coregistration")["alignment"]) == (CAMERA, 2, "none")
    vals = _panel_values(_reflectance(out), labels, len(rho))
    white = int(np.argmax(rho))
    worst = 0.0
    for f in range(vals.shape[0]):
        k = np.median(rho[white] / vals[f, white])
        worst = max(worst, float(np.max(np.abs(k * vals[f] - rho[:, None]))))
    assert worst < 0.015
    err = evaluate_multilens(session, calib)["check"]
    assert worst == pytest.approx(err["panel_abs_error"], abs=0.003)
    assert err["panel_abs_error_uncalibrated"] > 10 * worst

    ds = xr.open_zarr(calib).load()
    U, V, S = ds["inverse_response"].values, ds["vignetting"].values, ds["spectral_factor"].values
    recs = read_capture_table(session / "check", load_camera(CAMERA))
    for f, rec in enumerate(recs):
        eq15 = np.stack([U[b][tifffile.imread(rec.band_files[b])] / (rec.band_exposure(b) * V[b] * S[b])
                         for b in range(5)])
        ratio = vals[f] / _panel_values(eq15[None], labels[f:f + 1], len(rho))[0]
        assert np.ptp(ratio[1:]) / np.median(ratio) < 2e-3  # one factor per capture: no band, no panel apart


def test_calibrate_and_apply_take_one_exposure_per_band_file(dji) -> None:
    """The effective exposure calibrate reads for every band file (read_capture_table) is the
    one apply reads (read_file_metas: XMP ExposureTime x SensorGain) and the one the files were
    exposed with; the EXIF rule (ExposureTime x ISO / 100) would say twice as long."""
    session, _, out = dji
    truth = np.load(session / "truth.npz")
    cam = load_camera(CAMERA)
    for folder in ("response", "reflector", "check"):
        for f, rec in enumerate(read_capture_table(session / folder, cam)):
            for b, path in enumerate(rec.band_files):
                meta = read_file_metas(path)[0]
                applied = meta.exposure_s * 1000.0 * meta.gain
                assert rec.band_exposure(b) == pytest.approx(applied, rel=1e-12)
                assert applied == pytest.approx(truth[f"{folder}_exposure_ms"][f, b], rel=1e-6)
                assert band_file_record(path).effective_exposure == pytest.approx(applied, rel=1e-12)
                assert exif_band_record(path).effective_exposure == pytest.approx(2 * applied, rel=1e-6)
    with xr.open_zarr(out / "reflectance.zarr") as ds:
        np.testing.assert_allclose(ds["band_exposure_ms"].values * ds["gain"].values[:, None],
                                   truth["check_exposure_ms"], rtol=1e-6)


def test_the_exif_iso_rule_in_calibrate_alone_doubles_the_reflectance(dji, tmp_path, monkeypatch) -> None:
    """The review's finding, reproduced: calibrate reading each band file by the EXIF rule (ISO
    200 / 100 = gain 2) while apply reads SensorGain 1 gives reflectance 2x the consistent
    calibration's (measured 2.000 on every panel and band, S 0.500 of the consistent fit's);
    and apply on the same captures with
    SensorGain rewritten to 2 gives half (the effective exposure is what apply divides by)."""
    session, calib, out = dji
    truth = np.load(session / "truth.npz")
    labels, rho = truth["check_labels"], truth["check_panel_reflectance"]
    base = _panel_values(_reflectance(out), labels, len(rho))

    with monkeypatch.context() as m:  # calibrate as before: every band file by its EXIF
        m.setattr(captures, "band_file_record", exif_band_record)
        old = tmp_path / "old.zarr"
        assert main(["calibrate", str(session), "-o", str(old)]) == 0
    assert main(["apply", str(session / "check"), "--calibration", str(old), "-o", str(tmp_path / "o1"),
                 "--keep-flagged"]) == 0
    ratio = _panel_values(_reflectance(tmp_path / "o1"), labels, len(rho)) / base
    np.testing.assert_allclose(ratio, 2.0, rtol=1e-4)
    # the fit itself is the same but for the factor: S half as large, U and V unchanged
    a, b = xr.open_zarr(old).load(), xr.open_zarr(calib).load()
    np.testing.assert_allclose(a["spectral_factor"].values / b["spectral_factor"].values, 0.5, rtol=1e-6)
    np.testing.assert_allclose(a["inverse_response"].values, b["inverse_response"].values, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a["vignetting"].values, b["vignetting"].values, atol=1e-5)

    gain2 = tmp_path / "gain2"
    shutil.copytree(session / "check", gain2)
    for p in sorted(gain2.glob("*.TIF")):
        with tifffile.TiffFile(p, mode="r+b") as tif:
            tag = tif.pages[0].tags[700]
            xmp, n = re.subn(r'drone-dji:SensorGain="1"', 'drone-dji:SensorGain="2"', tag.value.decode())
            assert n == 1
            tag.overwrite(xmp.encode())
    assert read_file_metas(gain2 / "DJI_3001.TIF")[0].gain == 2.0
    assert main(["apply", str(gain2), "--calibration", str(calib), "-o", str(tmp_path / "o2"), "--keep-flagged"]) == 0
    half = _panel_values(_reflectance(tmp_path / "o2"), labels, len(rho)) / base
    np.testing.assert_allclose(half, 0.5, rtol=1e-4)
