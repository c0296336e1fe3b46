"""``mscal fit response`` on bracketed 8-bit JPEG photographs, scored like the acceptance check.

The photographs come from ``pipeline.sim.world.photo`` (handheld shifts, a moving region, JPEG,
sharpening, tone curve with toe and shoulder, nominal EXIF-style exposures such as 1/60 s for
a real 1/64 s). One interior frame is held out: the response is fitted through the command
line on the other files, OpenCV's ``CalibrateDebevec`` on the same files, and both predict
the held-out frame's DN from every fitted frame (``predict_heldout_rms``).

EXIF: ``piexif`` and Pillow are not installed, so the EXIF variant writes a minimal EXIF APP1
segment (ExposureTime only) itself; ``exifread`` reads it in ``pipeline.ingest.session``.
"""

from __future__ import annotations

import struct
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
import xarray as xr

from mscal_core.response import predict_heldout_rms
from pipeline.run.cli import main
from pipeline.sim.world.photo import PhotoSet, make_photo_set

#: A handheld bracket: JPEG q90, 0.5-3 px shifts, small rotation, foliage and a walking
#: figure, unsharp mask, nominal exposures (the generator's defaults).
HANDHELD = dict(shape=(300, 400), n_frames=7, step_thirds=3)


# --------------------------------------------------------------------------- helpers


def exif_app1(exposure_s: float) -> bytes:
    """A minimal EXIF APP1 segment: IFD0 -> Exif IFD -> ExposureTime (0x829A, RATIONAL)."""
    fr = Fraction(exposure_s).limit_denominator(1_000_000)
    tiff = b"II*\x00" + struct.pack("<I", 8)
    tiff += struct.pack("<H", 1) + struct.pack("<HHII", 0x8769, 4, 1, 26) + struct.pack("<I", 0)
    tiff += struct.pack("<H", 1) + struct.pack("<HHII", 0x829A, 5, 1, 44) + struct.pack("<I", 0)
    tiff += struct.pack("<II", fr.numerator, fr.denominator)
    payload = b"Exif\x00\x00" + tiff
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


def write_bracket(
    ps: PhotoSet, folder: Path, frames: list[int], *, exif: bool = False
) -> list[Path]:
    """JPEG files of ``frames``; exposures in frames.csv, or (``exif``) in each file's EXIF."""
    folder.mkdir(parents=True)
    paths, rows = [], ["file,exposure_ms"]
    for i in frames:
        data = ps.file_bytes(i)
        if exif:
            assert data[:2] == b"\xff\xd8"
            data = data[:2] + exif_app1(ps.exposure_ms[i] / 1000.0) + data[2:]
        path = folder / f"IMG_{i:04d}.jpg"
        path.write_bytes(data)
        paths.append(path)
        rows.append(f"{path.name},{ps.exposure_ms[i]:.9g}")
    if not exif:
        (folder / "frames.csv").write_text("\n".join(rows) + "\n")
    return paths


def read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def heldout_rms(u: np.ndarray, refs: list[np.ndarray], t_refs: np.ndarray,
                held: np.ndarray, t_held: float) -> float:
    """RMS over channels and reference frames of predict_heldout_rms (u: (3, 256))."""
    errs = [
        predict_heldout_rms(u[c], ref[..., c], t_ref, held[..., c], t_held)
        for c in range(3)
        for ref, t_ref in zip(refs, t_refs)
    ]
    return float(np.sqrt(np.mean(np.square(errs))))


def fit_cli(folder: Path, out: Path) -> np.ndarray:
    assert main(["fit", "response", str(folder), "--camera", "generic-rgb8", "-o", str(out)]) == 0
    ds = xr.open_zarr(out)
    u = ds["inverse_response"].values
    assert ds["inverse_response"].dims == ("band", "dn") and u.shape == (3, 256)
    assert list(ds["band_name"].values) == ["red", "green", "blue"]  # channel order R, G, B
    return u


def compare(ps: PhotoSet, root: Path, held: int, *, exif: bool = False) -> dict[str, float]:
    """Fit through the CLI without frame ``held``; held-out RMS of ours, Debevec, truth."""
    fit_idx = [i for i in range(len(ps.exposure_ms)) if i != held]
    paths = write_bracket(ps, root / "bracket", fit_idx, exif=exif)
    u = fit_cli(root / "bracket", root / "U.zarr")
    assert np.all(np.isfinite(u)) and np.all(np.diff(u, axis=1) >= 0)  # monotone per channel
    assert np.all(u[:, -1] > u[:, 128])
    refs = [read_rgb(p) for p in paths]
    t = ps.exposure_ms[fit_idx]
    held_img = ps.frames[held]
    debevec = cv2.createCalibrateDebevec().process(refs, (t / 1000.0).astype(np.float32))
    return {
        "ours": heldout_rms(u, refs, t, held_img, ps.exposure_ms[held]),
        "debevec": heldout_rms(debevec[:, 0, :].T.astype(np.float64), refs, t, held_img,
                               ps.exposure_ms[held]),
        "true": heldout_rms(ps.inverse_response, refs, t, held_img, ps.exposure_ms[held]),
    }


# --------------------------------------------------------------------------- tests


def test_exif_segment_is_read_by_the_session_reader(tmp_path) -> None:
    from pipeline.ingest.session import read_frame_table

    ps = make_photo_set(0, shape=(64, 96), n_frames=3, moving=False)
    write_bracket(ps, tmp_path / "b", [0, 1, 2], exif=True)
    recs = read_frame_table(tmp_path / "b")
    assert [r.exposure_ms for r in recs] == pytest.approx(list(ps.exposure_ms), rel=1e-6)
    assert ps.exposure_ms[2] == pytest.approx(1000 / 60)  # nominal marking of a real 1/64 s
    assert ps.exposure_true_ms[2] == pytest.approx(1000 / 64)


def test_handheld_jpeg_bracket_predicts_heldout_at_least_as_well_as_debevec(tmp_path) -> None:
    ps = make_photo_set(11, **HANDHELD)
    rms = compare(ps, tmp_path, held=3)
    # measured (seeds 11-16): ours / Debevec 0.89-0.99, ours / true U 0.97-0.99
    assert rms["ours"] <= rms["debevec"]
    assert rms["ours"] <= 1.05 * rms["true"]


def test_exif_exposures_without_frames_csv(tmp_path) -> None:
    ps = make_photo_set(12, **HANDHELD)
    rms = compare(ps, tmp_path, held=2, exif=True)
    assert not (tmp_path / "bracket" / "frames.csv").exists()
    assert rms["ours"] <= rms["debevec"]  # measured (seeds 11-16): 0.87-0.98 x Debevec


def test_tripod_jpeg_bracket_bright_frame_held_out(tmp_path) -> None:
    """No motion: JPEG ringing around blown highlights (245-254 inside saturated areas) is
    what separates the methods when a bright frame is predicted."""
    ps = make_photo_set(14, **HANDHELD | dict(shift_px=0.0, rotation_deg=0.0, moving=False))
    rms = compare(ps, tmp_path, held=4)
    assert rms["ours"] <= rms["debevec"]  # measured (seeds 11-16): 0.75-1.00 x Debevec


def test_few_frames_two_stops_apart(tmp_path) -> None:
    ps = make_photo_set(13, shape=(300, 400), n_frames=5, step_thirds=6)
    rms = compare(ps, tmp_path, held=2)
    # measured (seeds 11-16): 0.92-1.002 x Debevec (seed 14: 38.94 vs 38.87, a tie)
    assert rms["ours"] <= rms["debevec"]


@pytest.mark.slow
# seed 21 in make test; the second seed under make test-long (make test stays under 10 min)
@pytest.mark.parametrize("seed", [21, pytest.param(23, marks=pytest.mark.long)])
@pytest.mark.parametrize("setting", [pytest.param("handheld", marks=pytest.mark.long), "tripod",
                                     pytest.param("9x2/3", marks=pytest.mark.long), "5x2"])
def test_each_interior_frame_held_out(tmp_path, seed: int, setting: str) -> None:
    kw = {
        "handheld": HANDHELD,
        "tripod": HANDHELD | dict(shift_px=0.0, rotation_deg=0.0, moving=False),
        "9x2/3": HANDHELD | dict(n_frames=9, step_thirds=2),
        "5x2": HANDHELD | dict(n_frames=5, step_thirds=6),
    }[setting]
    ps = make_photo_set(seed, **kw)
    ours, debevec = [], []
    for held in range(1, len(ps.exposure_ms) - 1):
        rms = compare(ps, tmp_path / f"h{held}", held)
        ours.append(rms["ours"])
        debevec.append(rms["debevec"])
        assert rms["ours"] <= 1.03 * rms["debevec"], (held, rms)
    assert np.mean(ours) <= np.mean(debevec)
