"""Which pixels of reflectance to trust: ``reflectance.zarr``'s ``quality`` mask, written by
the apply pass with each frame, and run.json ``quality``.

A bit per reason (:data:`mscal_core.quality.FLAGS`): ``saturated`` (DN at or above the clip),
``response_shoulder`` (the calibration's ``response_uncertainty`` of U at the DN above the
bound), ``outside_sweep`` (DN outside its ``response_dn_range``), ``vignetting_unobserved``
(its ``vignetting_coverage`` is 0), ``not_coregistered`` (the band failed the co-registration
check of a checked capture: :mod:`pipeline.apply.coregistration`; run.json
``quality.coregistration`` names the captures checked and not, :func:`coregistration_checks`),
``no_value`` (NaN for any other reason). The three store variables are optional: a store without them is applied as
before and run.json ``quality.checked`` lists the flags that were checked. The factory chain
checks ``saturated``, ``not_coregistered`` and ``no_value`` (the others need a field store).

Flagged pixels are NaN unless the run keeps them (``--keep-flagged``, session.yaml
``products: {keep_flagged: true}``); saturated pixels are NaN either way (no value to keep).
The field chain folds the flags into its Eq. 15 tables
(:func:`pipeline.apply.stores.calibration_tables`): no extra float work per pixel; the mask
itself is one uint8 lookup per pixel (:func:`mscal_core.quality.frame_flags`) on the sensor
grid, carried onto the outputs' grid by the same warps as the reflectance (:func:`on_grid`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np
from mscal_core.quality import DEFAULT_BOUND, DEFAULT_FIT_BOUND, FLAGS, SPARSE, flag_counts, frame_flags

from pipeline.apply.coregistration import INSTEAD, OWN, REFINED, RESIDUAL_MAX_PX
from pipeline.apply.stores import pixel_flag_sets, quality_checks, quality_tables

if TYPE_CHECKING:
    from pipeline.apply.executor import Plan

#: Flags the factory chain can check (no field store: no U uncertainty, sweep or V coverage).
FACTORY_CHECKS = ("saturated", "not_coregistered", "no_value")
#: ``reflectance.zarr/quality``'s attributes (CF flag conventions).
ATTRS = {
    "long_name": "quality of reflectance: 0 trusted, else the OR of the flags",
    "units": "1",
    "flag_masks": list(FLAGS.values()),
    "flag_meanings": " ".join(FLAGS),
    "description": "bits: 1 DN at or above the clip; 2 relative uncertainty of the response U at the DN above the "
                   "bound (run.json quality.bound), or the fit's own share of it above quality.fit_bound; 4 DN outside the response sweep's range; 8 vignetting observed "
                   "by no view; 16 the band failed the co-registration check of a checked capture (run.json "
                   "quality.coregistration names the captures checked and not); 32 NaN for any other reason; 64 (with 4) DN "
                   "below the sweep's range. "
                   "Flagged pixels are NaN in reflectance unless the run kept them (run.json quality.keep_flagged); "
                   "run.json quality.checked lists the flags checked",
}


@dataclass(frozen=True)
class Flagging:
    """The quality mask of a run: the bound on U's relative uncertainty, whether flagged
    values are kept, and the flags that can be checked."""

    bound: float = DEFAULT_BOUND
    keep_flagged: bool = False
    checked: tuple[str, ...] = FACTORY_CHECKS
    #: The image registration that refines each capture's alignment judges it on its own pixels
    #: and nothing moves the bands after it: its residuals check the capture
    #: (:func:`coregistration_residuals`).
    own_pixels: bool = False

    def record(self) -> dict[str, Any]:
        """run.json ``quality``'s keys of the run (:func:`quality_record` adds the counts); the
        shoulder's bounds only where the shoulder is checked (a field store with U's uncertainty)."""
        bounds = ({"bound": self.bound, "fit_bound": DEFAULT_FIT_BOUND} if "response_shoulder" in self.checked
                  else {})
        return {**bounds, "keep_flagged": self.keep_flagged, "checked": list(self.checked), "flags": dict(FLAGS)}


def run_flagging(products: Any, calib: Any = None) -> Flagging:
    """The quality mask of a run of ``products`` (:class:`pipeline.ingest.products.Products`:
    ``keep_flagged``, ``shoulder_bound``) with the field calibration ``calib`` (the flags its
    optional variables let one check, :func:`pipeline.apply.stores.quality_checks`), or
    without (None: the factory chain's flags)."""
    checked = FACTORY_CHECKS if calib is None else quality_checks(calib)
    return Flagging(float(products.shoulder_bound), bool(products.keep_flagged), checked)


def sensor_flags(flagging: Flagging, calibration: Path, sat: int, dn: np.ndarray, refl: np.ndarray) -> np.ndarray:
    """A capture's mask on its sensor grid from its sensor DN (band, y, x) with the tables of a
    field ``calibration`` (:func:`pipeline.apply.stores.quality_tables`); ``refl``: its Eq. 15
    reflectance, NaN wherever a flag is set unless flagged values are kept (then only its NaN
    pixels are looked up). The factory chain's mask is its saturated pixels
    (:func:`pipeline.apply.executor.radiometry`).

    The same mask as :func:`mscal_core.quality.frame_flags`, faster where it can be: a band
    whose NaN pixels are exactly those the calibration's pixel table flags (a flagged pixel is
    NaN: the tables are :func:`mscal_core.quality.mask_tables`') has its DN flags looked up at
    those pixels, whose positions are found once per calibration, not per frame (a 25-band
    217x409 snapshot frame with 8.5 % of its pixels flagged: 1.99 -> 1.22 ms of CPU); any other
    band goes through ``frame_flags``."""
    dn_flags, pixel, _ = quality_tables(str(calibration), int(sat), flagging.bound)
    d = np.asarray(dn)
    if (flagging.keep_flagged or pixel is None or d.ndim != 3 or d.dtype.kind != "u" or d.shape != pixel.shape
            or np.shape(refl) != d.shape or int(d.max(initial=0)) >= dn_flags.shape[1]):
        return frame_flags(dn, dn_flags, pixel, reflectance=None if flagging.keep_flagged else refl)
    out = np.empty(d.shape, np.uint8)
    sets = pixel_flag_sets(str(calibration), int(sat), flagging.bound)
    assert sets is not None  # the store has a pixel table (pixel above)
    for b, (at, flags) in enumerate(sets):
        nan = np.isnan(refl[b])
        if np.count_nonzero(nan) == len(at) and (not len(at) or nan.ravel()[at].all()):
            # NaN exactly at the pixels the pixel table flags: the DN flags only there
            # (frame_flags' sparse lookup, without finding the NaN pixels first)
            out[b] = 0
            if len(at):
                out[b].ravel()[at] = np.take(dn_flags[b], d[b].ravel()[at]) | flags
        else:
            frame_flags(d[b:b + 1], dn_flags[b:b + 1], pixel[b:b + 1], out=out[b:b + 1], reflectance=refl[b:b + 1])
    return out


def on_grid(q: np.ndarray, warp: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
    """The mask of a capture's stored grid on the outputs' grid: each bit carried by the warp
    the reflectance took (``warp``: :func:`pipeline.apply.bandgrid.one_grid`'s, the capture's
    own image registration included, so each bit lands where its pixel's value did; None: no
    step moved the bands), a pixel flagged where a flagged pixel contributes to it (as NaN
    does)."""
    if warp is None or not q.any():
        return q
    return warp_bits(q, warp)


def warp_bits(q: np.ndarray, warp: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """A quality mask (band, y, x) through ``warp`` (any resampling of a float32 stack the
    reflectance takes): each bit's image (0 or the bit's value) warped, set where a flagged pixel contributes
    (above 1e-3), so a pixel is flagged where NaN would reach it. A mask without bits is warped
    as zeros (the shape may change, e.g. an upright rotation)."""
    out: np.ndarray | None = None
    for bit in FLAGS.values():
        has = np.bitwise_and(q, bit)
        if not has.any():
            continue
        with np.errstate(invalid="ignore"):
            moved = warp(has.astype(np.float32)) > 1e-3 * bit
        if out is None:
            out = np.zeros(moved.shape, np.uint8)
        out[moved] |= bit
    if out is None:
        out = np.zeros(warp(np.zeros(q.shape, np.float32)).shape, np.uint8)
    return out


def coregistration_checked(plan: Plan) -> bool:
    """Whether the pass checks its bands' co-registration: a multi-lens camera's captures
    measured (``plan.coreg_reference``) whose bands the run puts on one grid (a registration
    store, the files' own registration, image registration). Bands left on their own grids
    (no alignment: ``--no-align``, or nothing to align with) make no claim to fail, and a
    single-file camera is not measured."""
    return plan.coreg_reference is not None and (plan.transforms is not None or plan.factory_alignment
                                                 or plan.refine is not None)


def checked(flagging: Flagging, plan: Plan) -> Flagging:
    """``flagging`` with ``not_coregistered`` left out of its checked flags when the pass does
    not check it (:func:`coregistration_checked`): run.json ``quality.checked``."""
    if coregistration_checked(plan):
        return replace(flagging, own_pixels=_own_pixels(plan))
    return replace(flagging, checked=tuple(f for f in flagging.checked if f != "not_coregistered"))


def _own_pixels(plan: Plan) -> bool:
    """Whether a capture's own-pixel judgement (:func:`pipeline.apply.coregistration.capture_transform`)
    measures its bands as written: image registration refines the files' own alignment and no
    band transforms or shift move them after it."""
    return plan.refine is not None and plan.transforms is None and plan.band_shift is None


def coregistration_residuals(residuals: Mapping[str, Any] | None, own_pixels: bool
                             ) -> tuple[str, Mapping[str, float | None]] | None:
    """How a capture's co-registration was checked and per band the residual (px) against the
    reference band that check left after the alignment; None when it was not checked.

    ``("measured", ...)``: a capture of the every-Nth sample (run.json
    ``coregistration.captures``, :func:`pipeline.apply.bandgrid.grid_residuals`).
    ``("own pixels", ...)``: with ``own_pixels`` (:attr:`Flagging.own_pixels`), a capture whose
    alignment image registration judged on its own textured tiles (run.json
    ``coregistration.per_capture``): the residuals of the alignment it was given (the
    metadata's, or the refinement's). A capture that took the flight's alignment (too few
    textured tiles) was not checked. Measuring every capture was measured and not taken: on a
    5-band 1280 x 960 MicaSense capture the check costs 180-220 ms of CPU (75 ms decimated to
    320 px), the whole factory apply of a capture 68 ms."""
    r = residuals or {}
    if r.get("residual_px"):
        return "measured", r["residual_px"]
    own = r.get("refinement") or {}
    if own_pixels and own.get("from") == OWN:
        px = own.get("refined_px") if own.get("alignment") in (REFINED, INSTEAD) else own.get("metadata_px")
        if px:
            return "own pixels", px
    return None


def not_coregistered(plan: Plan, residuals: Mapping[str, Any] | None) -> list[int]:
    """The bands of a checked capture (:func:`coregistration_residuals`) further than the
    co-registration threshold from the reference band after the alignment; none when the pass
    does not check (:func:`coregistration_checked`) or did not check this capture."""
    if not coregistration_checked(plan):
        return []
    found = coregistration_residuals(residuals, _own_pixels(plan))
    if found is None:
        return []
    names = [b.name for b in plan.camera.bands]
    return [names.index(n) for n, px in found[1].items() if px is not None and px > RESIDUAL_MAX_PX and n in names]


def coregistration_checks(flagging: Flagging, residuals: Mapping[str, Mapping[str, Any] | None]
                          ) -> dict[str, Any] | None:
    """run.json ``quality.coregistration``: which captures the ``not_coregistered`` flag was
    checked on (by the sample, or on their own pixels) and which it was not (their mask's bit
    16 is 0 because nothing measured them, not because they passed); None when the pass does
    not check the flag. ``residuals``: each capture's run.json ``coregistration`` entry."""
    if "not_coregistered" not in flagging.checked:
        return None
    how: dict[str, list[str]] = {"measured": [], "own pixels": []}
    unchecked = []
    for name, r in residuals.items():
        found = coregistration_residuals(r, flagging.own_pixels)
        if found is None:
            unchecked.append(name)
        else:
            how[found[0]].append(name)
    return {"rule": CHECK_RULE, "measured": how["measured"], "own_pixels": how["own pixels"],
            "not_checked": unchecked}


#: run.json ``quality.coregistration.rule``.
CHECK_RULE = ("not_coregistered is set on the bands of a checked capture whose residual against the reference band "
              f"passes {RESIDUAL_MAX_PX:g} px: every Nth survey capture is measured (run.json coregistration.sample), "
              "and a capture whose alignment image registration judged on its own pixels is checked by that "
              "judgement; the captures under not_checked were not measured: their bit 16 is 0 unchecked, not passed")


def finish(flagging: Flagging, q: np.ndarray, refl: np.ndarray, bad_bands: Sequence[int], moved: bool
           ) -> np.ndarray:
    """The frame's mask with ``not_coregistered`` on ``bad_bands`` and ``no_value`` where the
    reflectance is NaN and nothing else is flagged; unless flagged values are kept, every
    flagged pixel of ``refl`` NaN (in place; already so for the field chain's flags unless the
    grid ``moved`` them)."""
    _flag_bands_and_moved(flagging, q, refl, bad_bands, moved)
    return _finish_tail(q, refl)


def _flag_bands_and_moved(flagging: Flagging, q: np.ndarray, refl: np.ndarray, bad_bands: Sequence[int],
                          moved: bool) -> None:
    for b in bad_bands:
        q[b] |= FLAGS["not_coregistered"]
        if not flagging.keep_flagged:
            refl[b] = np.nan
    if moved and not flagging.keep_flagged and q.any():
        refl[q != 0] = np.nan


def finish_counted(flagging: Flagging, q: np.ndarray, refl: np.ndarray, bad_bands: Sequence[int], moved: bool,
                   band_names: Sequence[str]) -> tuple[np.ndarray, dict[str, dict[str, int]]]:
    """:func:`finish`, and :func:`counts` of its mask: the same mask and counts.

    Unless flagged values are kept, a flagged pixel is NaN, so after :func:`finish` the flagged
    pixels are exactly the NaN ones: their flags are gathered at those positions once
    (``no_value`` set where a NaN pixel has none) and counted there, per band, instead of a
    pass over the whole mask for ``no_value`` and a histogram of every band's whole mask. Kept
    flagged values, a mask with a flag on a pixel that is not NaN, or NaN on more than
    one pixel in :data:`mscal_core.quality.SPARSE`: the two passes as before. CPU per frame
    (medians over real frames, old and new interleaved): a 25-band 217x409 snapshot frame with
    8.5 % of its pixels flagged 1.95 -> 1.57 ms, a 5-band 1280x960 MicaSense capture (0.1 %
    saturated) 3.19 -> 2.00 ms.
    """
    _flag_bands_and_moved(flagging, q, refl, bad_bands, moved)
    flat = q.reshape(-1)
    if flagging.keep_flagged or not flat.flags.c_contiguous:
        return _finish_tail(q, refl), counts(q, band_names)
    at = np.flatnonzero(np.isnan(refl))
    if len(at) * SPARSE >= flat.size:
        return _finish_tail(q, refl), counts(q, band_names)
    codes = flat[at]
    n_flagged = np.count_nonzero(codes)
    if n_flagged != np.count_nonzero(flat):  # a flagged pixel that is not NaN: not this shortcut's case
        return _finish_tail(q, refl), counts(q, band_names)
    if n_flagged < len(codes):
        none = codes == 0
        codes[none] = FLAGS["no_value"]
        flat[at[none]] = FLAGS["no_value"]
    plane = flat.size // max(1, q.shape[0])
    bounds = np.searchsorted(at, np.arange(q.shape[0] + 1, dtype=np.int64) * plane)
    out: dict[str, dict[str, int]] = {}
    for b, name in enumerate(band_names):
        if bounds[b + 1] == bounds[b]:
            continue
        hist = np.bincount(codes[bounds[b]:bounds[b + 1]], minlength=256)
        c = _hist_counts(hist)
        if c:
            out[name] = c
    return q, out


def _hist_counts(hist: np.ndarray) -> dict[str, int]:
    """``{flag: pixels}`` of one band from the histogram of its mask values (flags of no pixel
    left out), as :func:`mscal_core.quality.flag_counts` counts a band."""
    per_flag = dict.fromkeys(FLAGS, 0)
    for code in np.flatnonzero(hist).tolist():  # a few codes: plain Python beats numpy calls per flag
        n = int(hist[code])
        for name, bit in FLAGS.items():
            if code & bit:
                per_flag[name] += n
    return {k: v for k, v in per_flag.items() if v}


def _finish_tail(q: np.ndarray, refl: np.ndarray) -> np.ndarray:
    nan = np.isnan(refl)
    if nan.any():
        nan &= q == 0
        q[nan] = FLAGS["no_value"]
    return q


def counts(q: np.ndarray, band_names: Sequence[str]) -> dict[str, dict[str, int]]:
    """Per band the pixels of each flag, bands and flags without any left out (an Outcome's)."""
    return {n: c for n, c in zip(band_names, flag_counts(q)) if c}


def quality_record(flagging: Flagging, frames: Mapping[str, Mapping[str, Mapping[str, int]]],
                   coregistration: Mapping[str, Mapping[str, Any] | None] | None = None) -> dict[str, Any]:
    """run.json ``quality``: the run's keys (:meth:`Flagging.record`), the totals per band and
    flag, per frame the counts of its flagged bands (zero counts left out) and, when the pass
    checks ``not_coregistered``, the captures it checked it on (:func:`coregistration_checks`
    of ``coregistration``, each frame's run.json ``coregistration`` entry)."""
    totals: dict[str, dict[str, int]] = {}
    for bands in frames.values():
        for band, flags in bands.items():
            row = totals.setdefault(band, {})
            for flag, n in flags.items():
                row[flag] = row.get(flag, 0) + int(n)
    out = {**flagging.record(), "totals": totals,
           "frames": {f: {b: dict(c) for b, c in bands.items()} for f, bands in frames.items() if bands}}
    checks = None if coregistration is None else coregistration_checks(flagging, coregistration)
    if checks is not None:
        out["coregistration"] = checks
    return out
