"""Season plots of ``mscal stats`` tables: one series per field and index.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.products.report.sections import Section, Table

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn (0.6 s of every command otherwise)
    from matplotlib.figure import Figure

# --------------------------------------------------------------------------- season


def _stats_table(stats: Any) -> Any:
    if isinstance(stats, (str, Path)):
        from pipeline.products.zonal import read_table

        return read_table(stats)
    return stats


def season_series(table: Any, field_id: str, index: str) -> Any:
    """The rows of one field and index that have numbers and a date, by date: what
    :func:`plot_season` draws (a DataFrame with ``date``, ``flight``, ``mean``, ``median``,
    ``p10``, ``p90``, ``valid_fraction``)."""
    import pandas as pd

    t = table[(table["field_id"] == field_id) & (table["index"] == index) & (table["n_valid"] > 0)]
    t = t[t["date"].notna()].copy()
    t["date"] = pd.to_datetime(t["date"])
    return t.sort_values(["date", "flight"], kind="stable")[
        ["date", "flight", "mean", "median", "p10", "p90", "valid_fraction"]].reset_index(drop=True)


def plot_season(table: Any, field_id: str, index: str) -> Figure:
    """One field through the season: the median of ``index`` per flight (line), the p10-p90
    spread (band) and the mean (dashed), from the ``mscal stats`` table (:func:`season_series`)."""
    t = season_series(table, field_id, index)
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(6.0, 2.6))
    ax = fig.add_subplot(1, 1, 1)
    if len(t):
        x = t["date"].to_numpy()
        ax.fill_between(x, t["p10"].to_numpy(float), t["p90"].to_numpy(float), color="tab:green", alpha=0.25,
                        label="p10-p90", linewidth=0)
        ax.plot(x, t["median"].to_numpy(float), "o-", color="tab:green", label="median", markersize=4)
        ax.plot(x, t["mean"].to_numpy(float), "--", color="k", linewidth=0.8, label="mean")
        ax.legend(fontsize=6, loc="best")
    else:
        ax.text(0.5, 0.5, "no flight with valid pixels and a date", ha="center", va="center", transform=ax.transAxes)
    ax.set_title(f"field {field_id}: {index}", fontsize=8)
    ax.set_ylabel(index, fontsize=7)
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.tick_params(labelsize=6)
    fig.autofmt_xdate()
    fig.tight_layout()
    return fig


def season_sections(stats: Any) -> list[Section]:
    """One section per index of an ``mscal stats`` table: a table of the fields (flights with
    numbers, rows without a date, rows whose status is not ``ok`` with the status) and the
    season plot of each field that has numbers."""
    table = _stats_table(stats)
    out = []
    for index in sorted(set(table["index"])):
        t = table[table["index"] == index]
        rows, figures = [], []
        for fid in dict.fromkeys(t["field_id"]):
            ft = t[t["field_id"] == fid]
            good = ft[ft["n_valid"] > 0]
            undated = int(good["date"].isna().sum())
            problems = sorted({f"{s}" for s in ft["status"] if s != "ok"})
            rows.append([fid, int(len(good)), undated, "; ".join(problems)])
            if len(good) - undated > 0:
                figures.append((f"field {fid}: {index} per flight (median, p10-p90, mean)",
                                lambda fid=fid, index=index: plot_season(table, fid, index)))
        note = ("Rows without a date are in the table but not on the plots. Statuses other than ok: see "
                "'mscal stats' in the README.")
        out.append(Section(f"Season: {index}", f"season-{index}",
                           tables=[Table(f"fields ({index})", ["field", "flights with values", "without date",
                                                               "other statuses"], rows, note)],
                           figures=figures))
    return out


