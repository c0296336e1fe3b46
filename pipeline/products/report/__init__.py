"""The QA report: one self-contained HTML page per calibration and its flights.

Every plot is a pure function of stored results -- the calibration store (opened with
:func:`pipeline.storage.store.open_calibration`) or an apply ``OUT`` folder (``run.json``,
``reflectance.zarr``, ``raw.zarr``) -- and returns a :class:`matplotlib.figure.Figure`. Figures
are built without pyplot (no global figure registry, no backend switch in the caller's
process) and rendered with the Agg canvas only.

- :func:`write_report` writes ``report.html`` (PNG plots embedded as base64 data URIs, inline
  CSS, a Content-Security-Policy that forbids every network load) atomically, and
  ``calibration.json`` beside it when a calibration is given.
- :func:`report_markdown` gives the same warnings and tables as markdown (Prefect artifacts);
  :func:`report_dict` the same as a JSON-able dict.
- :func:`calibration_warnings` / :func:`flight_warnings`: :class:`QAWarning` with numbers, each
  against a named threshold of ``thresholds``.

The package, by step: ``thresholds`` (the numbers warnings compare with), ``inputs`` (apply
outputs and calibrations), ``figures`` (helpers), ``calibration`` and ``flight`` (their
plots and warnings), ``sections`` (the report model), ``season`` (``mscal stats`` plots) and
``page`` (HTML, markdown, dict). Everything public is importable from here.
"""

from __future__ import annotations

from pipeline.products.report.calibration import (
    calibration_warnings,
    plot_brightness,
    plot_coverage,
    plot_inverse_response,
    plot_light_over_time,
    plot_reflector_correction,
    plot_spectral_factor,
    plot_vignetting,
    reflector_corrections,
    response_residual_limit,
    sweep_coverage,
)
from pipeline.products.report.figures import (
    figure_png,
)
from pipeline.products.report.flight import (
    dn_outside_sweep,
    flight_warnings,
    frame_levels,
    frame_rows,
    ndvi_pairs,
    plot_histograms,
    plot_ndvi,
    plot_track,
    sample_indices,
)
from pipeline.products.report.inputs import (
    FlightResults,
    open_flight,
)
from pipeline.products.report.page import (
    BROKEN_IMAGES_SCRIPT,
    CSP,
    CSS,
    build_sections,
    calibration_summary,
    report_dict,
    report_markdown,
    sections_html,
    sections_markdown,
    write_report,
    write_report_and_markdown,
    write_report_sections,
    write_season_report,
)
from pipeline.products.report.season import (
    plot_season,
    season_sections,
    season_series,
)
from pipeline.products.report.sections import (
    Section,
    Table,
    band_table,
    calibration_section,
    flight_section,
    reference_table,
    reference_warnings,
    registration_fallback_table,
    registration_table,
    registration_warnings,
    skipped_table,
)
from pipeline.products.report.thresholds import (
    CAPTURE_COLOUR_CHANGE_MAX,
    FLIGHT_DN_OUTSIDE_SWEEP_MAX,
    FRAME_LEVEL_RATIO_MAX,
    HIST_MAX_FRAMES,
    HIST_MAX_PIXELS,
    ILLUMINATION_RESIDUAL_RMS_MAX,
    LEVEL_MAX_FRAMES,
    MARKER_MISSING_FRACTION_MAX,
    MIN_REFLECTOR_PIXELS,
    NDVI_MAX_FRAMES,
    PANEL_DLS_COLOUR_SPREAD_MAX,
    PNG_DPI,
    REFLECTOR_BRIGHTNESS_RATIO_MAX,
    REGISTRATION_SPREAD_MAX_PX,
    RESPONSE_RESIDUAL_RMS_DN_MAX,
    SATURATED_FRACTION_MAX,
    SWEEP_COVERAGE_MIN,
    TABLE_MAX_ROWS,
    VIGNETTING_OBSERVED_MIN,
    VIGNETTING_RESIDUAL_RMS_MAX,
    QAWarning,
)

__all__ = [
    "BROKEN_IMAGES_SCRIPT",
    "CAPTURE_COLOUR_CHANGE_MAX",
    "CSP",
    "CSS",
    "FLIGHT_DN_OUTSIDE_SWEEP_MAX",
    "FRAME_LEVEL_RATIO_MAX",
    "FlightResults",
    "HIST_MAX_FRAMES",
    "HIST_MAX_PIXELS",
    "ILLUMINATION_RESIDUAL_RMS_MAX",
    "LEVEL_MAX_FRAMES",
    "MARKER_MISSING_FRACTION_MAX",
    "MIN_REFLECTOR_PIXELS",
    "NDVI_MAX_FRAMES",
    "PANEL_DLS_COLOUR_SPREAD_MAX",
    "PNG_DPI",
    "QAWarning",
    "REFLECTOR_BRIGHTNESS_RATIO_MAX",
    "REGISTRATION_SPREAD_MAX_PX",
    "RESPONSE_RESIDUAL_RMS_DN_MAX",
    "SATURATED_FRACTION_MAX",
    "SWEEP_COVERAGE_MIN",
    "Section",
    "TABLE_MAX_ROWS",
    "Table",
    "VIGNETTING_OBSERVED_MIN",
    "VIGNETTING_RESIDUAL_RMS_MAX",
    "band_table",
    "build_sections",
    "calibration_section",
    "calibration_summary",
    "calibration_warnings",
    "dn_outside_sweep",
    "figure_png",
    "flight_section",
    "flight_warnings",
    "frame_levels",
    "frame_rows",
    "response_residual_limit",
    "ndvi_pairs",
    "open_flight",
    "plot_brightness",
    "plot_coverage",
    "plot_histograms",
    "plot_inverse_response",
    "plot_light_over_time",
    "plot_ndvi",
    "plot_reflector_correction",
    "plot_season",
    "plot_spectral_factor",
    "plot_track",
    "plot_vignetting",
    "reference_table",
    "reference_warnings",
    "reflector_corrections",
    "registration_fallback_table",
    "registration_table",
    "registration_warnings",
    "report_dict",
    "report_markdown",
    "sample_indices",
    "season_sections",
    "season_series",
    "sections_html",
    "sections_markdown",
    "skipped_table",
    "sweep_coverage",
    "write_report",
    "write_report_and_markdown",
    "write_report_sections",
    "write_season_report",
]
