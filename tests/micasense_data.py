"""Where the real MicaSense RedEdge sample files live, and what MicaSense publishes about them.

The folder is ``../shared/data/micasense-rededge/`` beside the repository (see its README).
Tests that need it call :func:`require_data`, which skips with the reason when it is absent.
"""

from __future__ import annotations

from pathlib import Path

import pytest

# This file is tests/micasense_data.py: parents[1] is the repository, its parent holds shared/
# (the same folder as ``Path(test_file).parents[2].parent`` from tests/<package>/test_*.py).
DATA = Path(__file__).parents[1].parent / "shared" / "data" / "micasense-rededge"

BANDS = ("Blue", "Green", "Red", "NIR", "Red edge")  # by file suffix 1..5
WAVELENGTHS_NM = (475.0, 560.0, 668.0, 840.0, 717.0)
FWHM_NM = (20.0, 20.0, 10.0, 40.0, 10.0)

# Panel corners (x, y) per band of IMG_0000, as MicaSense's tutorials publish them for use
# without a QR reader; band 1 is the README's (+-3 px).
PANEL_CORNERS = (
    ((809, 613), (648, 615), (646, 454), (808, 452)),
    ((772, 623), (613, 625), (610, 464), (770, 462)),
    ((771, 651), (611, 653), (610, 492), (770, 490)),
    ((829, 658), (668, 659), (668, 496), (829, 496)),
    ((807, 632), (648, 634), (645, 473), (805, 471)),
)
PANEL_RAW_DN = (45406.753893482026, 46924.919447148139, 53240.810340812051, 56187.417482757308, 54479.170371812339)
PANEL_RADIANCE = (0.17028382320603955, 0.17940027272297152, 0.1622172746785481, 0.10647021248769974, 0.13081077851565506)


def require_data() -> Path:
    """The sample folder; skips the calling test when it is absent."""
    if not (DATA / "IMG_0000_1.tif").is_file():
        pytest.skip(f"MicaSense RedEdge sample files not found in {DATA}")
    return DATA


def band_file(capture: str, band: int) -> Path:
    """``IMG_<capture>_<band>.tif`` in the sample folder (band 1..5); skips if absent."""
    return require_data() / f"IMG_{capture}_{band}.tif"


# A marker painted beside the sample panel (tests of the marker route): 1 mm per pixel
# at the panel; the panel's bright surface is about 0.215 m (its published corners are the
# inner 75 %), the marker's centre 0.19 m left of the panel's.
MARKER = {"dictionary": "DICT_APRILTAG_36h11", "id": 7, "size_m": 0.08}
MARKER_PANEL = {"marker": MARKER, "size_m": [0.215, 0.215], "offset_m": [0.19, 0.0]}


def paint_marker(dn, band: int) -> None:
    """Paint :data:`MARKER` (with a white quiet zone) into band ``band`` (1..5) of IMG_0000 in
    place, 190 px left of the panel's centre, upright: :data:`MARKER_PANEL` then describes the
    panel (its ``offset_m`` is the panel centre from the marker's)."""
    import cv2
    import numpy as np

    side, quiet = 80, 14
    img = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
                                        MARKER["id"], side)
    img = cv2.copyMakeBorder(img, quiet, quiet, quiet, quiet, cv2.BORDER_CONSTANT, value=255)
    cx, cy = np.mean(np.asarray(PANEL_CORNERS[band - 1], dtype=float), axis=0)
    x0, y0 = int(round(cx - 190 - img.shape[1] / 2)), int(round(cy - img.shape[0] / 2))
    dn[y0:y0 + img.shape[0], x0:x0 + img.shape[1]] = np.where(img > 127, 40000, 3000).astype(dn.dtype)


def factory_store(out, capture: str = "IMG_0000"):
    """A calibration store for the MicaSense bands built from the factory model of one capture
    (tests of the field chain on multi-lens flights): U linear in the stored DN above
    the black level, V the inverse of the factory vignetting polynomial scaled to max 1, and
    S such that Eq. 15 gives the factory radiance without its row-gradient term:
    ``R = L / R(y)`` with ``R(y)`` of :func:`mscal_core.factory.row_gradient`."""
    import numpy as np

    from mscal_core.factory import vignetting_map
    from pipeline.ingest.camera_meta import read_capture_meta
    from pipeline.ingest.catalog import load_camera
    from pipeline.storage.store import new_dataset, write_store

    cam = load_camera("micasense-rededge")
    metas = [read_capture_meta(require_data() / f"{capture}_{b.file_suffix}.tif") for b in cam.bands]
    ds = new_dataset(cam)
    k = np.arange(2 ** cam.bit_depth, dtype=np.float64)
    U = np.stack([np.maximum(k * 2 ** cam.dn_shift - m.black_level, 0.0) for m in metas])
    V, S = [], []
    for m in metas:
        inv = 1.0 / vignetting_map(m.shape, m.vignetting_center, m.vignetting_polynomial)
        V.append(inv / inv.max())
        S.append(inv.max() * 2.0 ** m.bits_per_sample / (1e3 * m.radiometric_calibration[0]))
    ds["inverse_response"] = (("band", "dn"), U)
    ds["vignetting"] = (("band", "y", "x"), np.stack(V).astype(np.float32))
    ds["spectral_factor"] = (("band",), np.array(S))
    return write_store(ds, out)
