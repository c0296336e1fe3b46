"""Write a synthetic multi-lens (MicaSense RedEdge-style) calibration session with known truth.

``write_multilens_session(path)`` renders :mod:`pipeline.sim.world.rig` and writes::

    path/
      session.yaml          camera micasense-rededge, reflector, marker; no intrinsics (the
                            band files carry them, as the camera's do)
      response/  IMG_0000_1.tif ... IMG_0011_5.tif   exposure sweep (one exposure for all lenses)
      vignetting/ IMG_1000_1.tif ...                 reflector + marker, many viewpoints
      reflector/ IMG_2000_1.tif ...                  reflector under non-uniform light
      check/     IMG_3000_1.tif ...                  gray panels 0.05/0.2/0.5/0.9 (Eq. 15 check)
      intrinsics/ IMG_4000_1.tif ... + board.yaml    ChArUco board captures (optional)
      truth.npz             per lens U, V, S, intrinsics, rig pose; per dataset its truth

Band files as a RedEdge writes them: 12-bit DN in the high bits of 16-bit samples, XMP
(Pix4D ``Camera:`` namespace) ``BandName``, ``CentralWavelength``, ``WavelengthFWHM``,
``CaptureId``, ``RigCameraIndex``, ``PerspectiveFocalLength`` (pixels, no unit tag, as
RedEdge 3), ``PrincipalPoint`` ("x,y" mm), ``PerspectiveDistortion`` ``[k1, k2, k3, p1, p2]``;
``ExposureTime`` (s, rational), ``ISOSpeed`` (100: gain 1), ``DateTimeOriginal``,
``FocalPlaneX/YResolution`` (px/mm, unit 4), ``BodySerialNumber`` (``serial``: sessions of
two serials are two camera bodies). The EXIF tags sit in IFD0 (tifffile writes no EXIF
sub-IFD); mscal's readers look in both places. No frames.csv unless ``frames_csv``.
"""

from __future__ import annotations

import csv
import datetime as dt
import shutil
from pathlib import Path

import numpy as np
import tifffile
import yaml

from pipeline.sim.world.rig import (
    REDEDGE_BANDS,
    REDEDGE_PX_PER_MM,
    REDEDGE_SHAPE,
    RigFrames,
    RigTruth,
    make_rig_truth,
    marker_views,
    panel_captures,
    response_sweep,
)
from pipeline.sim.world.scene import SESSION_START

CAMERA = "micasense-rededge"
#: The serial number the synthetic camera writes unless told another.
SERIAL = "RE0000001"
PIX4D_NS = "http://pix4d.com/camera/1.0/"
SIZES = {
    "small": dict(n_response=8, step=2.2, n_vignetting=14, n_reflector=2, n_check=2),
    "full": dict(n_response=12, step=1.7, n_vignetting=28, n_reflector=3, n_check=3),
}


#: ``factory_tags``: the MicaSense factory model written into the band files (``Make``/``Model``,
#: EXIF BlackLevel = the lens's true black level, XMP RadiometricCalibration with this a1 and no
#: row-gradient terms, a flat vignetting polynomial). It is *not* the rig's truth (no
#: non-linearity, no vignetting): a camera's factory model is an approximation, which a field
#: calibration's response and vignetting replace (``mscal apply --field-calibration``).
FACTORY_A1 = 1.0e-4


def _factory_xmp(truth: RigTruth, band: int) -> str:
    h, w = truth.lenses[band].camera.grid_shape
    seq = lambda tag, vals: (f"<Camera:{tag}><rdf:Seq>" + "".join(f"<rdf:li>{v!r}</rdf:li>" for v in vals)
                             + f"</rdf:Seq></Camera:{tag}>")
    return (seq("RadiometricCalibration", (FACTORY_A1, 0.0, 0.0)) + seq("VignettingCenter", (w / 2.0, h / 2.0))
            + seq("VignettingPolynomial", (0.0,)))


def _xmp(band: int, truth: RigTruth, capture_id: str, factory_tags: bool = False) -> bytes:
    name, wl, fwhm, _ = REDEDGE_BANDS[band]
    cam = truth.lenses[band].camera
    res = REDEDGE_PX_PER_MM * cam.grid_shape[1] / REDEDGE_SHAPE[1]
    k1, k2, p1, p2, k3 = cam.dist
    seq = lambda tag, vals: (f"<Camera:{tag}><rdf:Seq>" + "".join(f"<rdf:li>{v!r}</rdf:li>" for v in vals)
                             + f"</rdf:Seq></Camera:{tag}>")
    text = (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        f'<rdf:Description rdf:about="Pix4D Camera Information" xmlns:Camera="{PIX4D_NS}">'
        f"<Camera:BandName>{name}</Camera:BandName><Camera:CentralWavelength>{wl:g}</Camera:CentralWavelength>"
        f"<Camera:WavelengthFWHM>{fwhm:g}</Camera:WavelengthFWHM><Camera:CaptureId>{capture_id}</Camera:CaptureId>"
        f"<Camera:RigCameraIndex>{band}</Camera:RigCameraIndex>"
        f"<Camera:PerspectiveFocalLength>{cam.fx!r}</Camera:PerspectiveFocalLength>"
        f"<Camera:PrincipalPoint>{cam.cx / res!r},{cam.cy / res!r}</Camera:PrincipalPoint>"
        + seq("PerspectiveDistortion", (k1, k2, k3, p1, p2))
        + (_factory_xmp(truth, band) if factory_tags else "")
        + "</rdf:Description>"
        + ('<rdf:Description rdf:about="" xmlns:MicaSense="http://micasense.com/MicaSense/1.0/">'
           f"<MicaSense:CaptureId>{capture_id}</MicaSense:CaptureId></rdf:Description>" if factory_tags else "")
        + "</rdf:RDF></x:xmpmeta><?xpacket end=\"w\"?>"
    )
    return text.encode("utf-8")


def write_band_file(path: Path, dn12: np.ndarray, *, band: int, truth: RigTruth, capture_id: str,
                    exposure_ms: float, time_s: float, serial: str = SERIAL, factory_tags: bool = False) -> None:
    """One RedEdge-style band file (see the module docstring; ``factory_tags``: :data:`FACTORY_A1`)."""
    res = REDEDGE_PX_PER_MM * dn12.shape[1] / REDEDGE_SHAPE[1]
    xmp = _xmp(band, truth, capture_id, factory_tags)
    when = (SESSION_START + dt.timedelta(seconds=float(time_s))).strftime("%Y:%m:%d %H:%M:%S")
    res_q = (int(round(res * 1e6)), 1_000_000)
    tags = [
        (700, "B", len(xmp), xmp, True),
        (33434, "2I", 1, (int(round(exposure_ms * 1e4)), 10_000_000), True),  # ExposureTime, s
        (34867, "I", 1, 100, True),  # ISOSpeed: gain 1
        (36867, "s", 0, when, True),  # DateTimeOriginal
        (41486, "2I", 1, res_q, True), (41487, "2I", 1, res_q, True), (41488, "H", 1, 4, True),  # px per mm
        (42033, "s", 0, serial, True),  # BodySerialNumber
    ]
    if factory_tags:  # stored units: the 12-bit DN in the high bits of 16-bit samples
        black = int(round(truth.lenses[band].sensor.black_level * 16))
        tags += [(271, "s", 0, "MicaSense", True), (272, "s", 0, "RedEdge", True),
                 (50714, "H", 4, (black,) * 4, True)]
    tifffile.imwrite(path, (dn12.astype(np.uint16) << 4), photometric="minisblack", extratags=tags)


def write_frames(folder: Path, frames: RigFrames, truth: RigTruth, *, frames_csv: bool = False,
                 serial: str = SERIAL, factory_tags: bool = False) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(frames.names):
        cid = f"syn{truth.seed:03d}{frames.kind[:3]}{k:04d}"
        for b in range(truth.n_bands):
            write_band_file(folder / f"{name}_{REDEDGE_BANDS[b][3]}.tif", frames.dn[k][b], band=b, truth=truth,
                            capture_id=cid, exposure_ms=float(frames.exposure_ms[k, b]), time_s=frames.times_s[k],
                            serial=serial, factory_tags=factory_tags)
    if frames_csv:  # one row per band file: the lenses are exposed separately
        with open(folder / "frames.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["file", "exposure_ms", "gain", "time"])
            for k, name in enumerate(frames.names):
                t = (SESSION_START + dt.timedelta(seconds=frames.times_s[k])).isoformat().replace("+00:00", "Z")
                for b in range(truth.n_bands):
                    w.writerow([f"{name}_{REDEDGE_BANDS[b][3]}.tif", repr(float(frames.exposure_ms[k, b])), "1", t])


#: The ChArUco board of the synthetic ``intrinsics/`` folder (board.yaml of ``mscal fit intrinsics``).
BOARD = {"kind": "charuco", "squares": [7, 5], "square_m": 0.06, "marker_m": 0.045, "dictionary": "DICT_4X4_50"}


def write_board_images(folder: str | Path, truth: RigTruth, *, seed: int = 0, n_views: int = 12,
                       serial: str = SERIAL) -> Path:
    """``folder/`` with ChArUco board captures of the rig (:func:`pipeline.sim.world.rig.board_views`)
    and its ``board.yaml``."""
    from mscal_core.intrinsics import Board

    from pipeline.sim.world.rig import board_views

    folder = Path(folder)
    board = Board(BOARD["kind"], tuple(BOARD["squares"]), BOARD["square_m"], BOARD["marker_m"], BOARD["dictionary"])
    px = 120  # texture pixels per square
    img = board.charuco().generateImage((board.squares[0] * px, board.squares[1] * px), marginSize=0)
    size = (board.squares[0] * board.square_m, board.squares[1] * board.square_m)
    fs = board_views(truth, img, size, seed=seed, n_views=n_views)
    write_frames(folder, fs, truth, serial=serial)
    with open(folder / "board.yaml", "w") as fh:
        yaml.safe_dump(BOARD, fh, sort_keys=False)
    return folder


def render_datasets(truth: RigTruth, seed: int, size: str) -> dict[str, RigFrames]:
    """The session's datasets of ``size`` (:data:`SIZES`) rendered through the rig: response,
    vignetting, reflector, check."""
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    cfg = SIZES[size]
    return {
        "response": response_sweep(truth, seed=seed, n_frames=cfg["n_response"], step=cfg["step"]),
        "vignetting": marker_views(truth, seed=seed, kind="vignetting", n_views=cfg["n_vignetting"]),
        "reflector": marker_views(truth, seed=seed, kind="reflector", n_views=cfg["n_reflector"], fixed_light=False,
                                  time0_s=900.0),
        "check": panel_captures(truth, seed=seed, n_frames=cfg["n_check"]),
    }


def session_yaml(truth: RigTruth, camera: str, name: str, notes: str) -> dict:
    """session.yaml of a synthetic rig session: the camera, the rig's reflector and marker."""
    return {
        "camera": camera, "name": name, "notes": notes,
        "reflector": {"reflectance": float(truth.reflector_reflectance[0]), "size_m": list(truth.reflector_size_m)},
        "marker": {"dictionary": truth.marker.dictionary, "id": int(truth.marker.id),
                   "size_m": float(truth.marker.size_m), "border_m": float(truth.marker.border_m)},
    }


def write_multilens_session(path: str | Path, *, seed: int = 0, size: str = "small",
                            shape: tuple[int, int] = (240, 320), frames_csv: bool = False,
                            intrinsics_in_yaml: bool = False, board_views: int = 0,
                            board_folder: str = "intrinsics", serial: str = SERIAL,
                            factory_tags: bool = False) -> Path:
    """Render and write a multi-lens session (module docstring); returns its path.
    ``size``: ``small`` (8-frame sweep x2.2, 14 views, 2 reflector and 2 check captures) or
    ``full`` (12 x1.7, 28, 3, 3). ``shape`` (H, W) of every band image (RedEdge: 960 x 1280).
    ``intrinsics_in_yaml`` writes the true intrinsics per band into session.yaml;
    ``board_views`` > 0 writes that many ChArUco board captures into ``board_folder``
    (``intrinsics/``: the calibration then takes the intrinsics from them). ``serial``: the
    camera's serial number in every band file (EXIF BodySerialNumber). ``factory_tags``: the
    files also carry Make/Model and a MicaSense factory model (:data:`FACTORY_A1`), as a camera's
    card does."""
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    truth = make_rig_truth(seed, shape=shape)
    data = session_yaml(truth, CAMERA, f"synthetic-multilens-seed{seed}-{size}",
                        "synthetic multi-lens session (pipeline.sim.multilens); truth in truth.npz")
    if intrinsics_in_yaml:
        data["intrinsics"] = {
            REDEDGE_BANDS[b][0]: {"fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy),
                                  "dist": [float(d) for d in c.dist]}
            for b, c in enumerate(ln.camera for ln in truth.lenses)
        }
    with open(root / "session.yaml", "w") as fh:
        yaml.safe_dump(data, fh, sort_keys=False)
    sets = render_datasets(truth, seed, size)
    arrays = {f"camera_{k}": v for k, v in truth.arrays().items()}
    for name, fs in sets.items():
        if (root / name).exists():
            shutil.rmtree(root / name)
        write_frames(root / name, fs, truth, frames_csv=frames_csv, serial=serial, factory_tags=factory_tags)
        arrays[f"{name}_exposure_ms"] = fs.exposure_ms
        arrays.update({f"{name}_{k}": v for k, v in fs.truth.items()})
    if board_views:
        if (root / board_folder).exists():
            shutil.rmtree(root / board_folder)
        write_board_images(root / board_folder, truth, seed=seed, n_views=board_views, serial=serial)
    # the names evaluate_calibration (pipeline.sim.evaluate) reads
    for key in ("inverse_response", "vignetting", "spectral_factor"):
        arrays[key] = arrays[f"camera_{key}"]
    np.savez_compressed(root / "truth.npz", **arrays)
    return root


def evaluate_multilens(session_dir: str | Path, calibration) -> dict:
    """Errors of a multi-lens calibration against the session's truth: those of
    :func:`pipeline.sim.evaluate.evaluate_calibration` (U, V, S per lens) plus the Eq. 15
    check on ``check/``: per capture and band ``R = U(I) / (t V S)`` on each gray panel's pure
    pixels (median), one scalar per capture from the white panel (median over bands), and
    ``panel_abs_error`` the largest ``|R - rho|`` over panels, bands and captures;
    ``panel_abs_error_uncalibrated`` the same with raw DN above black / t instead of Eq. 15.
    The camera is session.yaml's; truth.npz's response and black level are in the files' DN."""
    import xarray as xr

    from pipeline.calibrate.sweep import read_stack
    from pipeline.ingest.captures import read_capture_table
    from pipeline.ingest.catalog import load_camera
    from pipeline.sim.evaluate import evaluate_calibration

    root = Path(session_dir)
    ds = calibration if isinstance(calibration, xr.Dataset) else xr.open_zarr(calibration).load()
    out = evaluate_calibration(root, ds)
    truth = np.load(root / "truth.npz")
    cam = load_camera(yaml.safe_load((root / "session.yaml").read_text())["camera"])  # RedEdge or DJI (pipeline.sim.dji)
    recs = read_capture_table(root / "check", cam)
    dn = read_stack(recs, cam)
    labels, rho = truth["check_labels"], truth["check_panel_reflectance"]
    U, V, S = ds["inverse_response"].values, ds["vignetting"].values, ds["spectral_factor"].values
    black = truth["camera_black_level"]
    white = int(np.argmax(rho))

    def score(calibrated: bool) -> float:
        worst = 0.0
        for f, rec in enumerate(recs):
            vals = np.full((len(rho), cam.n_bands), np.nan)
            for b in range(cam.n_bands):
                t = rec.band_exposure(b)
                r = U[b][dn[f, b]] / (t * V[b] * S[b]) if calibrated else (dn[f, b] - black[b]) / t
                for p in range(len(rho)):
                    m = labels[f, b] == p
                    if m.sum() >= 20:
                        vals[p, b] = np.median(r[m])
            k = np.nanmedian(rho[white] / vals[white])
            worst = max(worst, float(np.nanmax(np.abs(k * vals - rho[:, None]))))
        return worst

    out["check"] = {"captures": len(recs), "panel_abs_error": score(True), "panel_abs_error_uncalibrated": score(False)}
    return out


__all__ = ["BOARD", "write_board_images", "evaluate_multilens", "write_band_file", "write_multilens_session"]
