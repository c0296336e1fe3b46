"""Write a synthetic DJI P4 Multispectral calibration session with known truth.

``write_dji_session(path)`` renders the multi-lens rig of :mod:`pipeline.sim.world.rig` (the
lenses on the P4 Multispectral's bands: Blue 450, Green 560, Red 650, RedEdge 730, NIR 840
nm, the catalog's order) and writes the same datasets as
:func:`pipeline.sim.multilens.write_multilens_session`::

    path/
      session.yaml          camera dji-p4-multispectral, reflector, marker; no intrinsics (the
                            band files' DewarpData carry them, as the camera's do)
      response/  DJI_0001.TIF ... DJI_0075.TIF      exposure sweep (capture 000-007, band 1-5)
      vignetting/ DJI_1001.TIF ...                  reflector + marker, many viewpoints
      reflector/ DJI_2001.TIF ...                   reflector under non-uniform light
      check/     DJI_3001.TIF ...                   gray panels 0.05/0.2/0.5/0.9
      truth.npz             as the RedEdge session's, response and black level in the files' DN

Band files as a P4 Multispectral writes them (catalogs/cameras/dji-p4-multispectral.yaml, DJI's
P4 Multispectral Image Processing Guide; the tag set of ``tests/camera_files.py`` ``dji_xmp``):
``DJI_XXXn.TIF``, ``n`` the band (drone-dji:SensorIndex), 16-bit samples (the catalog's
``bit_depth: 16``: the rig's 12-bit DN scaled to the full 16-bit range by bit replication,
:func:`to_file_dn`, so that a clipped pixel is 65535, the catalog's ``dn_max`` and the full
scale DJI's guide normalises by, p = DN / 65535; black level ~4096 as on the real camera.
Written as 12-bit DN times 16, clipped pixels at 65520, the response fit took them for
saturation hidden below the clip 65535 and raised the top of U about 4-fold, and the
reflector's marker was then found in no frame); EXIF Make ``DJI``, Model ``FC6360``,
``ExposureTime`` (s), ``ISOSpeed`` **200**, ``DateTimeOriginal``, ``BodySerialNumber``,
``BlackLevel``; XMP ``drone-dji:`` attributes ``BandName``, ``CentralWavelength``,
``BandFreq``, ``CaptureUUID``, ``SensorIndex``, ``SensorGain`` **1** (the gain DJI's guide
divides by: ISO 200 is not a gain of 2), ``ExposureTime`` (us), ``BlackLevel``,
``SensorGainAdjustment``, ``Irradiance``, ``CalibratedOpticalCenterX/Y`` (the image centre),
``VignettingData`` (flat: the factory model is no part of a field calibration), ``DewarpData``
(the lens's true intrinsics about the optical centre) and an identity ``CalibratedHMatrix``.
The EXIF tags sit in IFD0.
"""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import numpy as np
import tifffile
import yaml

from pipeline.sim.multilens import SIZES, render_datasets, session_yaml
from pipeline.sim.world.rig import RigFrames, RigTruth, make_rig_truth
from pipeline.sim.world.scene import SESSION_START

CAMERA = "dji-p4-multispectral"
#: Name, centre wavelength (nm), FWHM (nm), file suffix (= drone-dji:SensorIndex) of the P4M's bands.
P4M_BANDS = (("Blue", 450.0, 32.0, "1"), ("Green", 560.0, 32.0, "2"), ("Red", 650.0, 32.0, "3"),
             ("RedEdge", 730.0, 32.0, "4"), ("NIR", 840.0, 52.0, "5"))
SERIAL = "0K8TG0000001"
#: EXIF ISOSpeed of every band file: real P4M files say 200 with drone-dji:SensorGain 1.
ISO = 200
SENSOR_GAIN = 1.0
#: The rig's 12-bit DN are stored about this many times larger (16-bit samples, as the P4M's).
DN_SCALE = 16
#: First capture number of each dataset's files (DJI_0001.TIF: capture 000, band 1).
CAPTURE_BASE = {"response": 0, "vignetting": 100, "reflector": 200, "check": 300}


def _xmp(band: int, truth: RigTruth, capture_uuid: str, exposure_us: float, black: int, irradiance: float,
         sensor_gain: float) -> bytes:
    name, wl, fwhm, suffix = P4M_BANDS[band]
    cam = truth.lenses[band].camera
    h, w = cam.grid_shape
    ox, oy = w / 2.0, h / 2.0
    k1, k2, p1, p2, k3 = cam.dist
    dewarp = "2020-02-04;" + ",".join(repr(float(v)) for v in (cam.fx, cam.fy, cam.cx - ox, cam.cy - oy,
                                                                k1, k2, p1, p2, k3))
    attrs = {
        "BandName": name, "CentralWavelength": f"{wl:g}", "BandFreq": f"{wl:g}(+/-{fwhm / 2:g})nm",
        "CaptureUUID": capture_uuid, "SensorIndex": suffix, "SensorGain": f"{sensor_gain:g}",
        "ExposureTime": f"{exposure_us:.3f}", "BlackLevel": str(black), "SensorGainAdjustment": "1.0",
        "Irradiance": f"{irradiance:.3f}", "CalibratedOpticalCenterX": f"{ox:g}",
        "CalibratedOpticalCenterY": f"{oy:g}", "VignettingData": ", ".join(["0.0"] * 6),
        "DewarpData": dewarp, "CalibratedHMatrix": "1,0,0,0,1,0,0,0,1",
    }
    text = " ".join(f'drone-dji:{k}="{v}"' for k, v in attrs.items())
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
            '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
            f'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" {text}/></rdf:RDF></x:xmpmeta>'
            '<?xpacket end="w"?>').encode("utf-8")


def write_dji_band_file(path: Path, dn12: np.ndarray, *, band: int, truth: RigTruth, capture_uuid: str,
                        exposure_ms: float, time_s: float, serial: str = SERIAL, irradiance: float = 1000.0,
                        sensor_gain: float = SENSOR_GAIN) -> None:
    """One P4 Multispectral band file (module docstring) of the rig's 12-bit DN ``dn12``."""
    black = int(round(truth.lenses[band].sensor.black_level * DN_SCALE))
    xmp = _xmp(band, truth, capture_uuid, exposure_ms * 1000.0, black, irradiance, sensor_gain)
    when = (SESSION_START + dt.timedelta(seconds=float(time_s))).strftime("%Y:%m:%d %H:%M:%S")
    tags = [
        (271, "s", 0, "DJI", True), (272, "s", 0, "FC6360", True),
        (700, "B", len(xmp), xmp, True),
        (33434, "2I", 1, (int(round(exposure_ms * 1e4)), 10_000_000), True),  # ExposureTime, s
        (34867, "I", 1, ISO, True),  # ISOSpeed: 200, not the gain
        (36867, "s", 0, when, True),  # DateTimeOriginal
        (42033, "s", 0, serial, True),  # BodySerialNumber
        (50714, "H", 1, black, True),  # BlackLevel, 16-bit DN
    ]
    tifffile.imwrite(path, to_file_dn(dn12), photometric="minisblack", metadata=None, extratags=tags)


def write_dji_frames(folder: Path, frames: RigFrames, truth: RigTruth, *, base: int, serial: str = SERIAL) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(len(frames.dn)):
        cap = base + k
        for b in range(truth.n_bands):
            write_dji_band_file(folder / f"DJI_{cap:03d}{P4M_BANDS[b][3]}.TIF", frames.dn[k][b], band=b, truth=truth,
                                capture_uuid=f"syn{truth.seed:03d}{frames.kind[:3]}{k:04d}",
                                exposure_ms=float(frames.exposure_ms[k, b]), time_s=frames.times_s[k],
                                serial=serial, irradiance=1000.0 + 10.0 * b)


def to_file_dn(dn12: np.ndarray) -> np.ndarray:
    """12-bit DN as 16-bit samples by bit replication: ``(k << 4) | (k >> 8)`` (0 -> 0,
    4095 -> 65535, ``16 k`` to within 15)."""
    k = np.asarray(dn12).astype(np.uint16)
    return (k << 4) | (k >> 8)


def file_dn_response(u12: np.ndarray) -> np.ndarray:
    """A 12-bit inverse response ``U[k]`` (band, 4096) on the 16-bit samples (band, 65536):
    ``U16[to_file_dn(k)] = U[k]``, linear in between."""
    at = to_file_dn(np.arange(4096)).astype(np.float64)
    k16 = np.arange(2 ** 16, dtype=np.float64)
    return np.stack([np.interp(k16, at, u) for u in np.atleast_2d(u12)])


def write_dji_session(path: str | Path, *, seed: int = 0, size: str = "small", shape: tuple[int, int] = (240, 320),
                      serial: str = SERIAL) -> Path:
    """Render and write a P4 Multispectral session (module docstring); returns its path.
    ``size`` and ``shape`` as :func:`pipeline.sim.multilens.write_multilens_session`."""
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    truth = make_rig_truth(seed, shape=shape, bands=P4M_BANDS)
    data = session_yaml(truth, CAMERA, f"synthetic-dji-p4m-seed{seed}-{size}",
                        "synthetic DJI P4 Multispectral session (pipeline.sim.dji); truth in truth.npz")
    with open(root / "session.yaml", "w") as fh:
        yaml.safe_dump(data, fh, sort_keys=False)
    arrays = {f"camera_{k}": v for k, v in truth.arrays().items()}
    # the calibration sees the files' 16-bit DN: the truth in those units, the sensor's kept beside it
    arrays["sensor_inverse_response"] = arrays["camera_inverse_response"]
    arrays["sensor_black_level"] = arrays["camera_black_level"]
    arrays["camera_inverse_response"] = file_dn_response(arrays["sensor_inverse_response"])
    arrays["camera_black_level"] = arrays["sensor_black_level"] * DN_SCALE  # as BlackLevel (a fraction of a DN off)
    for name, fs in render_datasets(truth, seed, size).items():
        if (root / name).exists():
            shutil.rmtree(root / name)
        write_dji_frames(root / name, fs, truth, base=CAPTURE_BASE[name], serial=serial)
        arrays[f"{name}_exposure_ms"] = fs.exposure_ms
        arrays.update({f"{name}_{k}": v for k, v in fs.truth.items()})
    for key in ("inverse_response", "vignetting", "spectral_factor"):  # the names evaluate_calibration reads
        arrays[key] = arrays[f"camera_{key}"]
    np.savez_compressed(root / "truth.npz", **arrays)
    return root


__all__ = ["CAMERA", "P4M_BANDS", "file_dn_response", "to_file_dn", "write_dji_band_file", "write_dji_session"]
