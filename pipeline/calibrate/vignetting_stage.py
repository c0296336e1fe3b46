"""The vignetting stage (Eq. 8-10): the optical attenuation V of each band from the marker
views of ``vignetting/``, fitted on the band workers; the screening of views whose marker pose
is wrong (the other IPPE solution tried first) and the stage's part of the calibration store.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import xarray as xr
from mscal_core import geometry, marker, vignetting
from mscal_core.errors import FitError

from pipeline.calibrate.bands import BandViews, band_observations, lens_vignetting_band, vignetting_band
from pipeline.calibrate.intrinsics import with_intrinsics
from pipeline.calibrate.pool import BandPool, pool_or_own
from pipeline.calibrate.stage import StageReport
from pipeline.calibrate.views import (
    FolderFrames,
    View,
    camera_offsets,
    edge_margin,
    exclude_half,
    load_marker_frames,
)
from pipeline.ingest.captures import is_multilens
from pipeline.ingest.session import Session

log = logging.getLogger("mscal.calibrate")

#: Views are only screened for a wrong marker pose when at least this many remain.
MIN_VIEWS_TO_SCREEN = 12

#: Robust loss of the band fits (``robust`` of :func:`mscal_core.vignetting.fit_vignetting`):
#: what still disagrees after the screening (a shadow, a glint, a pose a little off) counts
#: less instead of pulling V; None fits Eq. 8's plain least squares.
ROBUST_LOSS: str | None = "huber"


def fit_vignetting_frames(
    session: Session, inverse_response: np.ndarray, saturation_dn: np.ndarray, pool: BandPool | None = None,
    frames: Callable[[], FolderFrames] | None = None, started: Callable[[], None] | None = None,
) -> tuple[list[vignetting.VignettingFit], StageReport]:
    """Eq. 8-10 per band from the session's ``vignetting/`` views; the bands are fitted on
    ``pool``'s workers (a pool of its own if None). ``frames``: gives the folder already read
    (:func:`pipeline.calibrate.views.read_folder_frames`, e.g. read ahead while the response was fitted); ``started``:
    called once the marker was searched for and the band fits are on the workers (this
    process then only waits for them)."""
    t0 = time.perf_counter()
    camera = session.camera
    report = StageReport("vignetting")
    session, _ = with_intrinsics(session)
    with pool_or_own(pool, camera.n_bands) as p:
        recs, stack, views = load_marker_frames(session, session.vignetting_dir, inverse_response, report,
                                                frames() if frames is not None else None)
        started = started or (lambda: None)
        if is_multilens(camera):
            fits, saturated = _fit_multilens_vignetting(session, stack, views, inverse_response, saturation_dn,
                                                        report, p, started)
            views_used: Any = [sum(v.pose_for(b) is not None for _, v in views) for b in range(camera.n_bands)]
        else:
            fits, saturated, views = _fit_band_vignetting(session, stack, views, inverse_response, saturation_dn,
                                                          report, p, started)
            views_used = len(views)
    report.residuals = {
        **report.residuals,
        "views_used": views_used,
        "views_total": len(recs),
        "residual_rms": [round(float(f.residual_rms), 5) for f in fits],
        "observed_fraction": [round(float(f.observed.mean()), 4) for f in fits],
        "saturated_fraction": [round(saturated.get(b, 0.0), 6) for b in range(camera.n_bands)],
    }
    report.seconds = time.perf_counter() - t0
    return fits, report


#: The reflector's cell boxes (:func:`mscal_core.geometry.reflector_cells`) already projected,
#: by pose (rvec, tvec bytes) and intrinsics: one projection per view serves every band.
CellCache = dict[tuple[bytes, geometry.Intrinsics], "np.ndarray | None"]


def _band_views(session: Session, stack: np.ndarray, b: int, use: Sequence[tuple[int, View]],
                inverse_response: np.ndarray, saturation_dn: np.ndarray, cells: CellCache) -> BandViews:
    """Band ``b``'s vignetting views ``use`` for :func:`pipeline.calibrate.bands.vignetting_band`:
    each view's window of the band (:func:`mscal_core.geometry.reflector_window`)."""
    intr = session.intrinsics_for(b)
    offset = tuple(float(o) for o in camera_offsets(session.camera)[b])
    size = tuple(float(x) for x in np.broadcast_to(np.asarray(session.reflector.size_m, dtype=np.float64), (2,)))
    shape = stack.shape[2:]
    windows = []
    for _, v in use:
        pose = v.pose_for(b)
        key = (np.concatenate([pose.rvec, pose.tvec]).tobytes(), intr)  # type: ignore[union-attr]
        if key not in cells:
            cells[key] = geometry.reflector_cells(pose, intr, size)  # type: ignore[arg-type]
        windows.append(geometry.window_of_cells(cells[key], shape, offset))  # type: ignore[arg-type]
    return BandViews(
        dn=tuple(stack[i, b, rows, cols] for (i, _), (rows, cols) in zip(use, windows)),
        windows=tuple(windows), shape=shape,
        exposures=tuple(v.record.band_exposure(b) for _, v in use),
        poses=tuple(v.pose_for(b) for _, v in use),  # type: ignore[misc]
        inverse_response=inverse_response[b], saturation_dn=int(saturation_dn[b]),
        intrinsics=intr, offset=offset, size_m=size,  # type: ignore[arg-type]
        exclude_half_m=exclude_half(session), edge_margin_m=edge_margin(session),
        grid=vignetting.cell_grid(session.reflector.size_m), robust=ROBUST_LOSS,
    )


def _fit_band_vignetting(session: Session, stack: np.ndarray, views: list[tuple[int, View]],
                         inverse_response: np.ndarray, saturation_dn: np.ndarray, report: StageReport,
                         pool: BandPool, started: Callable[[], None]
                         ) -> tuple[list[vignetting.VignettingFit], dict[int, float], list[tuple[int, View]]]:
    """Eq. 8-10 of a band-grid camera (one pose per view for all bands): the views are
    screened on one band first, then every band is fitted on the views kept, on ``pool``.

    Only the workers that would otherwise idle while the reference band is screened start
    other bands on all views (none with one worker); the rest wait for the screening. A band
    fitted on all views is fitted again if a view is dropped, from its first fit's V (the
    alternation then needs a few sweeps, no log-domain start): a session with a wrong marker
    pose costs a few band fits more, not every band twice."""
    camera = session.camera
    saturated: dict[int, float] = {}  # band -> saturated fraction of its reflector pixels (QA report)
    # Screen the views on one band first: a view whose marker pose is wrong (planar-pose
    # ambiguity, a mis-detected corner) disagrees with all the others and is dropped.
    ref = camera.n_bands // 2
    order = [ref] + [b for b in range(camera.n_bands) if b != ref]
    ahead = order[1:max(1, pool.workers)]  # the workers that would idle during the screening
    cells: CellCache = {}

    def submit(b: int, use: list[tuple[int, View]], screen: bool = False,
               start: np.ndarray | None = None) -> Future:
        return pool.submit(vignetting_band, _band_views(session, stack, b, use, inverse_response, saturation_dn,
                                                        cells), screen, start)

    futures = {b: submit(b, views, b == ref) for b in [ref, *ahead]}
    started()
    ref_fit, saturated[ref], frac, _ = futures[ref].result()
    bad = set(vignetting.inconsistent_views(frac).tolist())
    if bad and len(views) - len(bad) < MIN_VIEWS_TO_SCREEN:
        # With few views the overlap is thin and a sound view that alone covers part of the
        # image also disagrees with the fit (a demo view with a 0.4 deg pose error measured
        # 4-6 %); dropping it costs more coverage than it removes error. Keep all, say so.
        report.residuals["views_not_screened"] = (
            f"{len(bad)} view(s) disagree with the others but only {len(views)} views were usable; "
            f"all kept (screening needs {MIN_VIEWS_TO_SCREEN} views left)"
        )
        bad = set()
    switched = _try_other_solutions(session, stack, views, bad, frac, ref_fit, inverse_response, saturation_dn, cells,
                                    ref, report)
    bad -= set(switched)
    if switched:
        views = [(i, switched.get(k, v)) for k, (i, v) in enumerate(views)]
    if bad or switched:
        med = float(np.nanmedian(frac))
        for k in sorted(bad):
            report.skipped.append({
                "file": views[k][1].record.path.name,
                "reason": f"inconsistent with the other views ({frac[k]:.0%} of its reflector pixels off "
                          f"by >10 %, median view {med:.1%}): marker pose likely wrong"
                          f"{_choice_note(views[k][1].choice)}",
            })
        views = [v for k, v in enumerate(views) if k not in bad]
        futures[ref] = submit(ref, views, start=ref_fit.vignetting)
    for b in order[len(ahead) + 1:]:
        futures[b] = submit(b, views)
    if bad:  # the bands started ahead on all views, again on the views kept
        for b in ahead:
            first = futures[b].result()[0]
            futures[b] = submit(b, views, start=first.vignetting)
    fits, coverage = [], []
    for b in range(camera.n_bands):
        fit, saturated[b], _, cov = futures[b].result()
        fits.append(fit)
        coverage.append(cov)
    report.arrays["coverage"] = np.stack(coverage)
    _record_view_weights(report, [[v.record.path.name for _, v in views]] * camera.n_bands, fits)
    return fits, saturated, views


def _record_view_weights(report: StageReport, names: Sequence[Sequence[str]],
                         fits: Sequence[vignetting.VignettingFit]) -> None:
    """Each view's robust weight per band (``VignettingFit.view_weights``, 1 = a typical view)
    as ``robust_weight`` in its ``marker_poses`` record: None for a band that did not use it."""
    weights: dict[str, list[float | None]] = {}
    for b, (band_names, fit) in enumerate(zip(names, fits)):
        if fit.view_weights is None:
            continue
        for name, w in zip(band_names, fit.view_weights):
            weights.setdefault(name, [None] * len(fits))[b] = round(float(w), 4) if np.isfinite(w) else None
    for rec in report.residuals.get("marker_poses", []):
        if rec.get("file") in weights:
            rec["robust_weight"] = weights[rec["file"]]


def _try_other_solutions(session: Session, stack: np.ndarray, views: list[tuple[int, View]], bad: set[int],
                         frac: np.ndarray, ref_fit: vignetting.VignettingFit, inverse_response: np.ndarray,
                         saturation_dn: np.ndarray, cells: CellCache, ref: int, report: StageReport) -> dict[int, View]:
    """The views screened out (``bad``) that the other IPPE solution of their marker in band
    ``ref`` makes consistent with the other views of that band: each such view taken with that
    pose, by index (of a band-grid camera the pose of every band; of a multi-lens camera that
    lens's own).

    A view disagrees with the band's fit (``ref_fit``) when its pose maps lawn or paper onto
    the reflector; if the mirrored solution (:mod:`mscal_core.marker`) brings its fraction of
    missed observations (:func:`mscal_core.vignetting.view_inconsistency`) under the screening
    limit (:func:`mscal_core.vignetting.inconsistent_views` of all views with its new fraction),
    the view is kept with that pose, and its record in ``marker_poses`` says so."""
    out: dict[int, View] = {}
    for k in sorted(bad):
        i, view = views[k]
        choice = view.choice_for(ref)
        if choice is None or choice.alternative is None:
            continue
        other = view.with_choice(ref, choice.swapped("consistency"))
        obs, _ = band_observations(_band_views(session, stack, ref, [(i, other)], inverse_response, saturation_dn, cells))
        trial = frac.copy()
        trial[k] = vignetting.view_inconsistency(ref_fit, *obs[0])
        if np.isfinite(trial[k]) and k not in set(vignetting.inconsistent_views(trial).tolist()):
            out[k] = other
            log.info("vignetting view %s, band %s: the other IPPE solution agrees with the other views (%.0f%% -> "
                     "%.0f%% of its reflector pixels off)", view.record.path.name, session.camera.bands[ref].name,
                     100 * frac[k], 100 * trial[k])
    _record_choices(report, out.values(), ref)
    return out


def _record_choices(report: StageReport, views: Iterable[View], band: int) -> None:
    """The ``marker_poses`` records of ``views`` with the pose choice now taken (of a
    multi-lens camera: band ``band``'s entry of the record's ``bands``)."""
    for view in views:
        for rec in report.residuals.get("marker_poses", []):
            if "bands" in rec and rec.get("file") == view.record.name:
                rec["bands"][band] = view.choice_for(band).as_record()  # type: ignore[union-attr]
            elif "bands" not in rec and rec.get("file") == view.record.path.name:
                rec.update(view.choice_for(band).as_record())  # type: ignore[union-attr]


def _choice_note(choice: marker.PoseChoice | None) -> str:
    """How a skipped view's pose was chosen between its two IPPE solutions, for its reason."""
    if choice is None:
        return ""
    e0, e1 = choice.reprojection_px
    second = f", {e1:.3f} px" if np.isfinite(e1) else ""
    return f" (IPPE solution {choice.solution} taken by {choice.by}; reprojection {e0:.3f} px{second})"


def _fit_multilens_vignetting(session: Session, stack: np.ndarray, views: list[tuple[int, View]],
                              inverse_response: np.ndarray, saturation_dn: np.ndarray, report: StageReport,
                              pool: BandPool, started: Callable[[], None]
                              ) -> tuple[list[vignetting.VignettingFit], dict[int, float]]:
    """Eq. 8-10 of a multi-lens camera: each lens on the views whose marker it found (its own
    poses), screened on its own fit like the band-grid camera's reference band, on ``pool``; a
    view a lens drops is taken back with the other IPPE solution of that lens's pose when that
    one agrees with the lens's fit (:func:`_try_other_solutions`), and the lens fitted again."""
    camera = session.camera
    uses = [[v for v in views if v[1].pose_for(b) is not None] for b in range(camera.n_bands)]
    for b, use in enumerate(uses):
        if not use:
            raise FitError(f"band {camera.bands[b].name}: the marker was found in none of its vignetting views",
                           hint="check that the marker is in view of every lens and sharp")
    cells: CellCache = {}
    futures = [pool.submit(lens_vignetting_band, _band_views(session, stack, b, uses[b], inverse_response,
                                                             saturation_dn, cells), MIN_VIEWS_TO_SCREEN)
               for b in range(camera.n_bands)]
    started()
    results = [list(f.result()) for f in futures]
    refits: dict[int, Future] = {}
    for b, (fit, _, frac, dropped, _) in enumerate(results):
        # a view the lens dropped may have its other IPPE solution agree with the lens's fit
        # (the band-grid camera's retry, per lens: each lens has its own pose of the marker)
        switched = _try_other_solutions(session, stack, uses[b], set(dropped), frac, fit, inverse_response,
                                        saturation_dn, cells, b, report)
        if switched:
            uses[b] = [(i, switched.get(k, v)) for k, (i, v) in enumerate(uses[b])]
            results[b][3] = [k for k in dropped if k not in switched]
            kept = [v for k, v in enumerate(uses[b]) if k not in results[b][3]]
            refits[b] = pool.submit(vignetting_band, _band_views(session, stack, b, kept, inverse_response,
                                                                 saturation_dn, cells), False, fit.vignetting)
    for b, future in refits.items():  # the lens again on the views it keeps (its saturated share: of all its views)
        results[b][0], _, _, results[b][4] = future.result()
    fits, saturated, names = [], {}, []
    report.arrays["coverage"] = np.stack([r[4] for r in results])
    for b, (fit, saturated[b], frac, dropped, _) in enumerate(results):
        names.append([v.record.name for k, (_, v) in enumerate(uses[b]) if k not in dropped])
        med = float(np.nanmedian(frac)) if dropped else 0.0
        for k in dropped:
            report.skipped.append({
                "file": uses[b][k][1].record.name,
                "reason": f"band {camera.bands[b].name}: inconsistent with the other views ({frac[k]:.0%} of its "
                          f"reflector pixels off by >10 %, median view {med:.1%}): marker pose likely wrong"
                          f"{_choice_note(uses[b][k][1].choice_for(b))}",
            })
        fits.append(fit)
    _record_view_weights(report, names, fits)
    return fits, saturated


def add_vignetting(ds: xr.Dataset, fits: Sequence[vignetting.VignettingFit], report: StageReport) -> xr.Dataset:
    ds = ds.copy()
    ds["vignetting"] = (
        ("band", "y", "x"),
        np.stack([f.vignetting for f in fits]).astype(np.float32),
        {"long_name": "optical attenuation V (Eq. 8-10), max 1 per band"},
    )
    ds["vignetting_count"] = (
        ("band", "y", "x"),
        np.stack([np.minimum(f.count, 65535) for f in fits]).astype(np.uint16),
        {"long_name": "observations per pixel in the vignetting fit"},
    )
    ds["vignetting_observed"] = (
        ("band", "y", "x"),
        np.stack([f.observed for f in fits]).astype(bool),
        {"long_name": "False where V was filled smoothly (too few observations)"},
    )
    coverage = report.arrays.get("coverage")
    if coverage is not None:
        ds["vignetting_coverage"] = (
            ("band", "y", "x"),
            np.asarray(coverage, dtype=np.uint16),
            {"long_name": "vignetting views that observed each pixel (Eq. 8-10)",
             "description": "number of the vignetting views kept for the fit in which the pixel saw the "
                            "reflector (inside its mask: off the marker and the edge margin) unsaturated; "
                            "0: V there is extrapolated, never observed",
             "units": "1"},
        )
    ds.attrs["vignetting"] = report.as_attrs()
    return ds
