"""The apply pass's band geometry step: stored band transforms, --no-align,
--centre-bands, and outputs unchanged for stores without transforms."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import pipeline.apply.bandgrid as bandgrid
import pipeline.apply.flight as apply_mod
from mscal_core.alignment import mosaic_centre_offsets, shift_bands
from pipeline.apply.options import calibration_hash
from pipeline.run.cli import main
from pipeline.storage.store import open_calibration, write_store


def _apply(flight: Path, calib: Path, out: Path, *extra: str) -> int:
    return main(["apply", str(flight), "--calibration", str(calib), "-o", str(out), "--float32", *extra])


def _with_transforms(calib: Path, dst: Path, session_h: np.ndarray, captures: dict[str, np.ndarray]) -> Path:
    ds = open_calibration(calib)
    n, h, w = ds.sizes["band"], ds.sizes["y"], ds.sizes["x"]
    names = list(captures)
    ds["band_transform"] = (("band", "row3", "col3"), session_h)
    if names:
        ds = ds.assign_coords(capture=np.array(names, dtype=object))
        ds["capture_transform"] = (("capture", "band", "row3", "col3"), np.stack([captures[k] for k in names]))
    ds.attrs["registration"] = {"reference_band": str(ds["band_name"].values[0]), "shape": [h, w], "captures": names}
    assert session_h.shape == (n, 3, 3)
    write_store(ds, dst)
    return dst


def _shift(n: int, b: int, dx: float) -> np.ndarray:
    hs = np.tile(np.eye(3), (n, 1, 1))
    hs[b, 0, 2] = dx
    return hs


@pytest.fixture(scope="module")
def plain(small, tmp_path_factory):
    session, calib = small
    out = tmp_path_factory.mktemp("plain") / "out"
    assert _apply(session / "flights" / "field", calib, out) == 0
    return session, calib, out


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes()
            for p in sorted((out / "photogrammetry").glob("*.tif")) + sorted((out / "ndvi").glob("*.tif"))}


def test_no_transforms_leaves_the_pass_untouched(plain, tmp_path, monkeypatch) -> None:
    """A store without transforms never reaches the geometry step, its hash and the run's
    fingerprint are what they were before band alignment (no new keys), and a store whose transforms
    are all the identity gives the same bytes."""
    session, calib, out = plain

    def boom(*a, **k):
        raise AssertionError("geometry step called without transforms")

    monkeypatch.setattr(apply_mod, "geometry_step", boom)
    monkeypatch.setattr(bandgrid, "geometry_step", boom)
    again = tmp_path / "again"
    assert _apply(session / "flights" / "field", calib, again) == 0
    monkeypatch.undo()
    assert _files(out) == _files(again)
    fp = json.loads((out / "run.json").read_text())["fingerprint"]
    assert "align" not in fp["options"] and "centre_bands" not in fp["options"]
    ds = open_calibration(calib)
    import hashlib

    h = hashlib.sha256(str(ds.attrs.get("camera")).encode())
    for name in ("inverse_response", "vignetting", "spectral_factor"):
        arr = np.ascontiguousarray(ds[name].values)
        h.update(name.encode() + str(arr.dtype).encode() + str(arr.shape).encode() + arr.tobytes())
    assert calibration_hash(ds) == h.hexdigest() == fp["calibration_sha256"]
    n = ds.sizes["band"]
    ident = _with_transforms(calib, tmp_path / "ident.zarr", np.tile(np.eye(3), (n, 1, 1)), {})
    out_i = tmp_path / "ident"
    assert _apply(session / "flights" / "field", ident, out_i) == 0
    assert _files(out) == _files(out_i)
    a, b = (xr.open_zarr(p / "reflectance.zarr") for p in (out, out_i))
    np.testing.assert_array_equal(a["reflectance"].values, b["reflectance"].values)


def test_stored_transforms_align_each_frame(plain, tmp_path) -> None:
    """Band 3 shifted by 2 px in the session transform, by 1 px for the registered capture
    IMG_0001: aligned(x) = band(x + dx); --no-align keeps the bands as they are."""
    session, calib, out = plain
    n = open_calibration(calib).sizes["band"]
    store = _with_transforms(calib, tmp_path / "reg.zarr", _shift(n, 3, 2.0), {"IMG_0001": _shift(n, 3, 1.0)})
    aligned = tmp_path / "aligned"
    assert _apply(session / "flights" / "field", store, aligned) == 0
    ref = xr.open_zarr(out / "reflectance.zarr")
    al = xr.open_zarr(aligned / "reflectance.zarr")
    assert al["reflectance"].attrs["aligned_to_band"] == str(ref["band_name"].values[0])
    frames = [str(f) for f in al["frame"].values]
    for f, name in enumerate(frames):
        dx = 1 if name == "IMG_0001" else 2
        r, a = ref["reflectance"].values[f, 3], al["reflectance"].values[f, 3]
        np.testing.assert_allclose(a[:, :-dx - 1], r[:, dx:-1], rtol=1e-6)
        assert np.isnan(a[:, -1]).all()
        np.testing.assert_array_equal(al["reflectance"].values[f, 0], ref["reflectance"].values[f, 0])
    assert "IMG_0001" in frames
    # band 3 is the reference pass's band 3 moved by the frame's own shift (above); every
    # other band is left as it was: the aligned pass differs from the plain one nowhere else
    for b in range(n):
        if b != 3:
            np.testing.assert_array_equal(al["reflectance"].values[:, b], ref["reflectance"].values[:, b])
    raw = tmp_path / "raw"
    assert _apply(session / "flights" / "field", store, raw, "--no-align") == 0
    np.testing.assert_array_equal(xr.open_zarr(raw / "reflectance.zarr")["reflectance"].values, ref["reflectance"].values)
    assert json.loads((raw / "run.json").read_text())["fingerprint"]["options"]["align"] is False


def test_transforms_of_another_image_size_are_refused(plain, tmp_path, capsys) -> None:
    session, calib, _ = plain
    n = open_calibration(calib).sizes["band"]
    store = _with_transforms(calib, tmp_path / "reg.zarr", _shift(n, 3, 2.0), {})
    ds = open_calibration(store)
    ds.attrs["registration"]["shape"] = [960, 1280]
    write_store(ds, tmp_path / "wrong.zarr")
    code = _apply(session / "flights" / "field", tmp_path / "wrong.zarr", tmp_path / "o")
    err = capsys.readouterr().err.strip()
    assert code == 2 and "estimated on 1280x960 images" in err and "--no-align" in err


def test_centre_bands_resamples_to_the_mosaic_centre(plain, tmp_path) -> None:
    session, calib, out = plain
    centred = tmp_path / "centred"
    assert _apply(session / "flights" / "field", calib, centred, "--centre-bands") == 0
    ref = xr.open_zarr(out / "reflectance.zarr")["reflectance"].values[0]
    got = xr.open_zarr(centred / "reflectance.zarr")["reflectance"].values[0]
    want = shift_bands(ref, mosaic_centre_offsets((5, 5)))
    np.testing.assert_allclose(got, want, rtol=1e-5, equal_nan=True)
    np.testing.assert_array_equal(got[12], ref[12])  # the centre band is not moved
    assert not np.allclose(got[0][5:-5, 5:-5], ref[0][5:-5, 5:-5])


def test_registration_option_is_for_factory_calibrations(plain, tmp_path, capsys) -> None:
    session, calib, _ = plain
    code = _apply(session / "flights" / "field", calib, tmp_path / "o", "--registration", str(calib))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "--registration is for --calibration factory" in err
