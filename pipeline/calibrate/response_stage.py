"""The response stage (Eq. 5-7): the inverse response of each band from the exposure sweep
(``response/``), fitted on the band workers, and its part of the calibration store."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np
import xarray as xr
from mscal_core import response
from mscal_core.errors import FitError

from pipeline.calibrate.pool import BandPool, pool_or_own
from pipeline.calibrate.stage import StageReport, record_files
from pipeline.calibrate.sweep import SweepFits, submit_sweep
from pipeline.ingest.catalog import Camera
from pipeline.storage.store import content_hashes, new_dataset


def fit_response_frames(
    folder: Path, camera: Camera, method: str = "forward", root: Path | None = None, pool: BandPool | None = None,
    sweep: SweepFits | None = None,
) -> tuple[list[response.ResponseFit], StageReport]:
    """Eq. 5-7 per band from an exposure sweep folder (frames.csv + frames); the bands are
    fitted on ``pool``'s workers (a pool of its own if None). ``sweep``: the same folder's fits
    already submitted (:func:`pipeline.calibrate.sweep.submit_sweep`, same method)."""
    t0 = time.perf_counter()
    report = StageReport("response")
    with pool_or_own(pool, camera.n_bands) as p:
        if sweep is None or not sweep.is_for(Path(folder), method):
            sweep = submit_sweep(Path(folder), camera, method, p)
        recs, exposures_b = sweep.records, sweep.exposures
        report.inputs = content_hashes(record_files(recs), root or folder)
        results = [f.result() for f in sweep.futures]
    fits = []
    for b, (bad, fit) in enumerate(results):
        if bad:
            names = ", ".join(f"{recs[i].path.name} ({exposures_b[b][i]:g} ms)" for i in bad[:3])
            raise FitError(
                f"band {camera.bands[b].name}: brightness contradicts exposure for {names}",
                path=folder / "frames.csv",
                hint="check exposure_ms of these frames, or remove frames taken while the scene or light changed",
            )
        fits.append(fit)
    report.residuals = {
        "method": method,
        "residual_rms_dn": [round(f.residual_rms_dn, 4) for f in fits],
        "black_level": [round(f.black_level, 3) for f in fits],
        "observed_dn": [list(map(int, f.observed_dn)) for f in fits],
    }
    report.seconds = time.perf_counter() - min(t0, sweep.started)
    return fits, report


#: What ``response_uncertainty`` is (its attributes in the store).
UNCERTAINTY_ATTRS = {
    "long_name": "relative standard uncertainty of U(k) (Eq. 5-7), a fraction of U(k)",
    "units": "1",
    "description": (
        "sqrt((U'(k) sigma_I(k) / U(k))^2 + s_fit(k)^2): one reading's DN noise through U's slope (U' the "
        "difference quotient of U over k +- sigma_I(k)), "
        "sigma_I(k)^2 = a + b (k - black_level) the response fit's read + shot noise model (per band: "
        "noise_variance [a, b], DN^2 and DN^2 per DN), and s_fit(k) the standard deviation of log U(k) "
        "of the fit itself (its information matrix, every pixel's E marginalised, the prior included: "
        "large where few samples reach, and the step where the top of U was raised for saturated pixels "
        "hidden below the clip). NaN outside response_dn_range; inf where U(k) = 0 (at or below black) and "
        "where k + sigma_I(k) passes the top of response_dn_range (the sweep's data do not determine U there). "
        "Written by the forward response fit only (the plain alternation's bias is not modelled)."
    ),
}


#: What ``response_fit_uncertainty`` is (its attributes in the store).
FIT_UNCERTAINTY_ATTRS = {
    "long_name": "the response fit's own relative standard uncertainty of U(k) (Eq. 5-7), a fraction of U(k)",
    "units": "1",
    "description": (
        "s_fit(k) of response_uncertainty alone: the standard deviation of log U(k) of the fit itself (its "
        "information matrix, every pixel's E marginalised), how far U moves with the smoothness prior "
        f"{response.PRIOR_RELAX:g} times weaker, and the step where the top of U was raised for hidden "
        "saturated pixels, in quadrature. Systematic: the same for every pixel read at k, so a region's mean "
        "keeps it whole while it averages one reading's noise away (apply flags a DN above the one where this "
        "share is least where it passes mscal_core.quality.DEFAULT_FIT_BOUND). NaN where "
        "response_uncertainty is NaN or inf."
    ),
}


def response_dataset(camera: Camera, fits: Sequence[response.ResponseFit], report: StageReport) -> xr.Dataset:
    ds = new_dataset(camera)
    ds["inverse_response"] = (
        ("band", "dn"),
        np.stack([f.inverse_response for f in fits]),
        {"long_name": "inverse camera response U(k) (Eq. 5-7)", "units": "linear DN", "method": fits[0].method},
    )
    ds["black_level"] = ("band", np.array([f.black_level for f in fits]), {"units": "DN"})
    ds["saturation_dn"] = ("band", np.array([f.saturation_dn for f in fits], dtype=np.int32))
    ds.coords["dn"] = np.arange(2**camera.bit_depth, dtype=np.int32)
    if all(f.residual_by_dn is not None for f in fits):
        n_bins = len(fits[0].residual_by_dn)
        ds.coords["dn_bin"] = ("dn_bin", (np.arange(n_bins) + 0.5) * 2**camera.bit_depth / n_bins,
                               {"long_name": "centre of a DN bin of the response residual", "units": "DN"})
        ds["response_residual"] = (("band", "dn_bin"), np.stack([f.residual_by_dn for f in fits]),
                                   {"long_name": "rms of the sweep's fit residual I - C(t E) per DN bin (Eq. 5)",
                                    "units": "DN"})
    if all(f.fitted_dn is not None for f in fits):
        ds.coords["end"] = ("end", np.array(["low", "high"], dtype=object))
        ds["response_dn_range"] = (
            ("band", "end"), np.array([f.fitted_dn for f in fits], dtype=np.int32),
            {"long_name": "lowest and highest DN the response fit has data for: the lowest DN of its sweep "
                          "samples, the high end at most the mean DN of its 10 samples of highest energy (above "
                          "it, on a sweep short of the clip, DN are noise draws); outside it U is extrapolated",
             "units": "DN"})
    if all(f.uncertainty is not None and f.noise_variance is not None for f in fits):
        ds["response_uncertainty"] = (
            ("band", "dn"), np.stack([f.uncertainty for f in fits]).astype(np.float32),
            {**UNCERTAINTY_ATTRS, "noise_variance": [[float(v) for v in f.noise_variance] for f in fits]})
    if all(f.fit_uncertainty is not None for f in fits):
        ds["response_fit_uncertainty"] = (("band", "dn"), np.stack([f.fit_uncertainty for f in fits]).astype(np.float32),
                                          FIT_UNCERTAINTY_ATTRS)
    ds.attrs["response"] = report.as_attrs()
    return ds
