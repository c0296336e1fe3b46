"""--normalise panel (pipeline.apply.options.normalisation): the panel's median per band, with
the pixels its quality mask flags high counted as above it when the mask is given."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mscal_core.errors import InputError
from mscal_core.quality import FLAGS
from pipeline.apply.options import ApplyOptions, PanelSpec, normalisation


def _panel() -> tuple[np.ndarray, np.ndarray, ApplyOptions, SimpleNamespace]:
    """Two bands, a 4 x 3 panel at x 1-4, y 0-3 of frame B reading 0.45 x (1 + 0.01 k),
    k = -5..6; its 4 brightest pixels flagged on the shoulder (NaN)."""
    r = np.full((2, 5, 6), 0.2, np.float32)
    spread = 1 + 0.01 * np.arange(-5, 7)
    r[:, 0:3, 1:5] = (0.45 * spread).reshape(3, 4)[None]
    q = np.zeros(r.shape, np.uint8)
    q[:, 0:3, 1:5] = np.where(spread > 1.025, FLAGS["response_shoulder"], 0).reshape(3, 4)[None]
    r[q != 0] = np.nan
    opts = ApplyOptions(normalise="panel", panel=PanelSpec.parse("B:1,0,5,3", "0.9"))
    return r, q, opts, SimpleNamespace(wavelengths=np.array([550.0, 800.0]))


def test_the_panel_median_counts_the_pixels_flagged_high() -> None:
    r, q, opts, cam = _panel()
    kind, k = normalisation(opts, cam, ["A", "B"], lambda f: (r, q))
    # the median of all 12 readings, 0.45 x 1.005, not of the 8 valid ones (0.45 x 0.985)
    assert kind == "scalar" and k == pytest.approx(0.9 / (0.45 * 1.005), rel=1e-6)
    _, plain = normalisation(opts, cam, ["A", "B"], lambda f: (r, None))
    assert plain == pytest.approx(0.9 / (0.45 * 0.985), rel=1e-6)


def test_a_panel_half_flagged_has_no_median() -> None:
    r, q, opts, cam = _panel()
    q[:, 0:3, 1:5] = FLAGS["response_shoulder"] * (np.arange(12).reshape(3, 4) >= 6)[None]
    with pytest.raises(InputError, match="no valid pixels"):
        normalisation(opts, cam, ["A", "B"], lambda f: (r, q))


def test_the_panel_median_takes_each_flagged_pixels_own_bound() -> None:
    """The same panel with each flagged pixel's bound (``PanelPixels.censor_at``): a bound
    below the valid values (a pixel flagged for its high V, not its value) pulls the median
    down to the product-limit median; a reading under the sweep counts below."""
    from pipeline.apply.options import PanelPixels

    r, q, opts, cam = _panel()
    bounds = np.full(r.shape, np.inf)
    _, high = normalisation(opts, cam, ["A", "B"], lambda f: PanelPixels(r, q, bounds))
    assert high == pytest.approx(0.9 / (0.45 * 1.005), rel=1e-6)  # every bound above: as counted above
    bounds[q != 0] = 0.0  # known only to be above 0: they leave the count at once
    _, low = normalisation(opts, cam, ["A", "B"], lambda f: PanelPixels(r, q, bounds))
    assert low == pytest.approx(0.9 / (0.45 * 0.985), rel=1e-6)  # the 8 valid values' median
    q[q != 0] = FLAGS["outside_sweep"] | FLAGS["below_sweep"]
    _, under = normalisation(opts, cam, ["A", "B"], lambda f: PanelPixels(r, q, bounds))
    # 4 below the 8 valid (0.45 x 0.95 .. 1.02): the 6th and 7th of 12 are the 2nd and 3rd valid
    assert under == pytest.approx(0.9 / (0.45 * 0.965), rel=1e-6)
