"""mscal_core.panel: automatic panel detection on rendered images (not tuned to one capture), and
the panel's QR code (its serial) read on rendered images and on MicaSense's real panel capture."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mscal_core.panel import detect_panel, order_corners, polygon_iou, qr_serial, sample_quad, shrink_polygon


def _render(angle_deg: float, seed: int, *, panel: bool = True, distractor: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A 480 x 640 16-bit frame: textured dark ground, a bright textured (checker) patch as a
    QR-sticker-like distractor, and a uniform bright square panel rotated by ``angle_deg``."""
    rng = np.random.default_rng(seed)
    h, w = 480, 640
    ground = cv2.GaussianBlur(rng.normal(9000, 2500, (h, w)), (0, 0), 6)
    img = ground + rng.normal(0, 300, (h, w))
    if distractor:
        checker = ((np.indices((80, 80)) // 10).sum(axis=0) % 2) * 30000 + 20000
        img[60:140, 60:140] = checker
    corners = np.zeros((4, 2))
    if panel:
        c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        half = np.array([[-60, -60], [60, -60], [60, 60], [-60, 60]], dtype=np.float64)
        corners = half @ np.array([[c, s], [-s, c]]) + [400, 260]
        mask = np.zeros((h, w), np.uint8)
        cv2.fillPoly(mask, [np.round(corners).astype(np.int32)], 1)
        img = np.where(mask > 0, 45000 + rng.normal(0, 600, (h, w)), img)
    return np.clip(img, 0, 65535).astype(np.uint16), corners


@pytest.mark.parametrize("angle", [0.0, 17.0, 38.0])
def test_finds_rotated_noisy_panel_and_ignores_textured_bright_patch(angle: float) -> None:
    img, truth = _render(angle, seed=int(angle))
    found = detect_panel(img)
    assert found is not None
    assert polygon_iou(img.shape, found.outline, truth) > 0.95
    assert np.abs(order_corners(truth) - found.outline).max() < 3.0  # px
    assert found.cv < 0.02


def test_no_panel_gives_none() -> None:
    img, _ = _render(0.0, seed=5, panel=False)
    assert detect_panel(img) is None


def test_corner_order_shrink_and_iou() -> None:
    sq = [(0, 0), (10, 0), (10, 10), (0, 10)]
    assert order_corners(sq).tolist() == [[10, 10], [0, 10], [0, 0], [10, 0]]
    assert shrink_polygon(sq, 0.5).tolist() == [[2.5, 2.5], [7.5, 2.5], [7.5, 7.5], [2.5, 7.5]]
    assert polygon_iou((20, 20), sq, sq) == 1.0
    assert polygon_iou((20, 20), sq, [(20, 20), (19, 20), (19, 19), (20, 19)]) == 0.0
    with pytest.raises(ValueError, match="shrink factor"):
        shrink_polygon(sq, 0.0)


def test_sample_quad_maps_the_same_panel_spot_in_shifted_bands() -> None:
    y, x = np.mgrid[0:100, 0:120].astype(np.float64)
    image = x + 1000 * y  # value encodes the position
    quad = [(20, 10), (80, 10), (80, 70), (20, 70)]
    shifted = np.roll(image, (5, 7), axis=(0, 1))  # the same scene 7 px right, 5 px down
    a = sample_quad(image, quad, 7)
    b = sample_quad(shifted, [(qx + 7, qy + 5) for qx, qy in quad], 7)
    assert np.allclose(a, b)
    assert a[0, 0] == pytest.approx(20 + 1000 * 10) and a[-1, -1] == pytest.approx(80 + 1000 * 70)


def test_panel_from_marker_maps_the_plane_rectangle_through_the_marker_homography() -> None:
    from mscal_core.panel import panel_from_marker

    # a known plane-to-image homography (tilted view), the marker's and the panel's corners through it
    H = np.array([[900.0, 120.0, 640.0], [-60.0, -820.0, 480.0], [0.15, -0.2, 1.0]])

    def project(uv: np.ndarray) -> np.ndarray:
        p = np.c_[uv, np.ones(len(uv))] @ H.T
        return p[:, :2] / p[:, 2:]

    s = 0.08
    marker = project(np.array([[-s / 2, s / 2], [s / 2, s / 2], [s / 2, -s / 2], [-s / 2, -s / 2]]))
    got = panel_from_marker(marker, s, (0.15, 0.10), (0.14, -0.02))
    want = order_corners(project(np.array([[0.065, 0.03], [0.215, 0.03], [0.215, -0.07], [0.065, -0.07]])))
    np.testing.assert_allclose(got, want, atol=1e-6)


# --------------------------------------------------------------------------- the panel's QR code

SAMPLE_SERIAL = "RP02-1603036-SC"  # printed on MicaSense's sample panel (IMG_0000) and in its QR code


def _qr_band(text: str | None, seed: int, module: int = 4) -> np.ndarray:
    """A 480 x 640 band as a RedEdge stores it (12-bit DN in the high bits of 16): textured dark
    ground and, unless ``text`` is None, a QR code of ``text`` with ``module`` px per module."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.normal(6000, 1500, (480, 640)), (0, 0), 4) + rng.normal(0, 200, (480, 640))
    if text is not None:
        code = cv2.QRCodeEncoder.create().encode(text)
        code = cv2.resize(code, None, fx=module, fy=module, interpolation=cv2.INTER_NEAREST)
        code = cv2.copyMakeBorder(code, 16, 16, 16, 16, cv2.BORDER_CONSTANT, value=255)
        h, w = code.shape
        img[100:100 + h, 200:200 + w] = np.where(code > 127, 40000, 4000)
    return (np.clip(img, 0, 65535).astype(np.uint16) >> 4) << 4


def test_qr_serial_majority_of_the_bands() -> None:
    """The text read in most bands; a tie between two texts is no answer; no code is None."""
    assert qr_serial([_qr_band(SAMPLE_SERIAL, s) for s in range(5)]) == SAMPLE_SERIAL
    assert qr_serial([_qr_band("AAA-1", 0), _qr_band("BBB-2", 1), _qr_band("AAA-1", 2)]) == "AAA-1"
    assert qr_serial([_qr_band("AAA-1", 0), _qr_band("BBB-2", 1)]) is None
    assert qr_serial([_qr_band(None, s) for s in range(5)]) is None
    assert qr_serial([]) is None and qr_serial([np.zeros((8, 8), np.uint16)]) is None
    # a capture stops after give_up_after bands in a row without a code located
    late = [_qr_band(None, 1), _qr_band(None, 2), _qr_band(None, 3), _qr_band(SAMPLE_SERIAL, 0)]
    assert qr_serial(late) is None and qr_serial(late, give_up_after=None) == SAMPLE_SERIAL


def test_qr_serial_of_the_real_micasense_panel_capture() -> None:
    """IMG_0000 (the panel) gives the panel's serial, in every band alone too (band 2 only
    through the 2x enlargement: its code is located but not read at full size); IMG_0001 (the
    flight) gives None."""
    import tifffile

    from tests.micasense_data import band_file

    panel = [tifffile.imread(band_file("0000", b)) for b in range(1, 6)]
    assert qr_serial(panel) == SAMPLE_SERIAL
    assert [qr_serial([band], give_up_after=None) for band in panel] == [SAMPLE_SERIAL] * 5
    assert qr_serial([tifffile.imread(band_file("0001", b)) for b in range(1, 6)]) is None
