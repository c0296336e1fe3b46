"""Figure helpers: panel grids, titles and ticks, and PNG rendering on the Agg canvas
(no pyplot: no global figure registry, no backend switch in the caller's process).
"""

from __future__ import annotations

import io
import math
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import xarray as xr

from pipeline.products.report.thresholds import PNG_DPI

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- figure helpers


def _grid(n: int) -> tuple[int, int]:
    cols = math.ceil(math.sqrt(n))
    return math.ceil(n / cols), cols


def panel_figure(n: int, panel_in: float = 2.0, extra_w: float = 0.0) -> tuple[Figure, list[Any]]:
    """A figure with ``n`` panels on a near-square grid; unused grid cells are not created."""
    rows, cols = _grid(n)
    w, h = cols * panel_in + extra_w, rows * panel_in * 0.8 + 0.6
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h))
    # A fixed layout: the constrained layout engine costs seconds on 25 panels.
    fig.subplots_adjust(left=0.03, right=1 - (extra_w + 0.1) / w, bottom=0.04, top=1 - 0.55 / h,
                        wspace=0.25, hspace=0.45)
    axes = [fig.add_subplot(rows, cols, k + 1) for k in range(n)]
    return fig, axes


def band_titles(ds: xr.Dataset) -> list[str]:
    wl = ds["wavelength"].values if "wavelength" in ds.coords else np.arange(ds.sizes["band"])
    return [f"{float(w):g} nm" for w in wl]


def few_ticks(ax: Any, xticks: Sequence[float] | None = None) -> None:
    """Three ticks per axis at most: tick objects are most of the rendering time of a
    25-panel figure."""
    from matplotlib.ticker import MaxNLocator

    if xticks is not None:
        ax.set_xticks(list(xticks))
    else:
        ax.xaxis.set_major_locator(MaxNLocator(3))
    ax.yaxis.set_major_locator(MaxNLocator(3))
    ax.tick_params(labelsize=6)


def image_axes(ax: Any) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def figure_png(fig: Figure) -> bytes:
    """PNG bytes of ``fig`` (Agg canvas); the figure is cleared afterwards."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    fig.clear()
    return buf.getvalue()


