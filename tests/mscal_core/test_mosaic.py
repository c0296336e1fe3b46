import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.mosaic import band_offsets, demosaic, remosaic


def test_demosaic_samples_spec_positions() -> None:
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 1024, size=(1088, 2048), dtype=np.uint16)
    bands = demosaic(raw, (5, 5), (0, 0), (217, 409))
    assert bands.shape == (25, 217, 409)
    # band at mosaic row r, column c is sampled at sensor pixels (5i + r, 5j + c)
    for r, c, i, j in [(0, 0, 0, 0), (4, 4, 216, 408), (1, 2, 100, 7), (3, 0, 5, 300)]:
        assert bands[r * 5 + c, i, j] == raw[5 * i + r, 5 * j + c]


def test_remosaic_inverts_demosaic() -> None:
    rng = np.random.default_rng(1)
    bands = rng.integers(0, 1024, size=(25, 217, 409), dtype=np.uint16)
    raw = remosaic(bands, (5, 5), (1088, 2048))
    np.testing.assert_array_equal(demosaic(raw, (5, 5), (0, 0), (217, 409)), bands)


def test_offsets() -> None:
    off = band_offsets((5, 5))
    assert off.shape == (25, 2)
    np.testing.assert_allclose(off[7], [0.4, 0.2])  # band (1, 2): dx = c/5, dy = r/5


def test_too_small_frame_is_named() -> None:
    with pytest.raises(InputError, match="mosaic needs at least 2045x1085"):
        demosaic(np.zeros((100, 100), np.uint16), (5, 5), (0, 0), (217, 409))
