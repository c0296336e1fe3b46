"""Band co-registration of a run's multi-lens captures, checked on the pixels.

Metadata can be wrong: DJI files of some firmware carry a CalibratedHMatrix that puts the
bands further apart than they were stored. So for every camera with one file per band
(MicaSense, DJI, Sequoia, Sentera 6X; never a single-file camera) apply measures, on the
pixels, the shift each band keeps against a reference band after whatever aligned the bands
(the band files' own registration, a registration store's transforms, or nothing):
:mod:`mscal_core.coregistration` (phase correlation + ECC translation on gradient images in
3 x 3 tiles, decimated to 640 px), on every Nth survey capture, at most
:data:`MAX_MEASURED` per flight (:func:`measured_captures`; the executor measures them as
it writes them, :func:`pipeline.apply.bandgrid.grid_residuals`).

When the bands are put on one grid by the files' own registration (DJI), each capture's is
judged in the pass on the capture's own pixels (:func:`capture_transform`, at :data:`MAX_SIDE`)
against no alignment at all. When it leaves more than :data:`RESIDUAL_MAX_PX` or does worse
than none, the capture's bands are refined by image registration (DJI's Image Processing
Guide, step 4): per band a translation (or affine) from the reference band fitted to that
capture's tiles, on top of the metadata transform, or instead of it when it did worse than
none. So a capture gets the same bands, NaN borders included, alone or in any flight. A capture
with fewer than :data:`OWN_MIN_TILES` textured tiles in a band takes the flight's choice:
before the pass :func:`choose_alignment` does the same on up to :data:`REFINE_CAPTURES`
survey captures with their tiles pooled, which depends on the flight (run.json
``coregistration.per_capture`` lists such captures as not run-invariant). run.json
``band_alignment`` gives the flight's choice and ``coregistration`` holds the measurements
(:func:`coregistration_record`, :func:`refinement_record`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from mscal_core.alignment import align_bands
from mscal_core.coregistration import (
    MAX_SIDE,
    BandResidual,
    pooled_affines,
    pooled_translations,
    sample_every,
    stack_residuals,
    translation_transforms,
)

from pipeline.ingest.cameras.dispatch import align_by_files
from pipeline.ingest.catalog import Camera
from pipeline.ingest.grouping import Capture, read_capture_pixels

MAX_MEASURED = 24  # captures measured per flight (every Nth)
REFINE_CAPTURES = 4  # captures the metadata alignment is judged and refined on (pooled)
REFINE_MAX_SIDE = 1600  # px on the long side for the refinement's estimate (sub-pixel at full resolution)
RESIDUAL_MAX_PX = 1.0  # a band further than this from the reference band is misregistered
METHOD = ("per band against the reference band: phase correlation refined by ECC (MOTION_TRANSLATION) on "
          "gradient-magnitude images in 3 x 3 tiles inside a 5 % border, tiles without texture or correlation "
          "left out; median shift magnitude over the tiles, in full-resolution px")
METADATA = "factory metadata"
REFINED = "factory metadata + image registration"
INSTEAD = "image registration (metadata alignment was worse than none)"
ARTICLE = {"translation": "a", "affine": "an"}


def multi_lens(camera: Camera, captures: Sequence[Capture]) -> bool:
    """Whether the run's captures are one file per band (several lenses) with several bands."""
    return camera.n_bands > 1 and bool(captures) and len({m.path for m in captures[0].metas}) > 1


def reference_band(camera: Camera, registered: int | None = None) -> int:
    """The band residual shifts are measured against: a registration's reference band, else
    the band of the median wavelength (the middle of the spectrum correlates best with both ends)."""
    if registered is not None:
        return registered
    return int(np.argsort(camera.wavelengths, kind="stable")[(camera.n_bands - 1) // 2])


def measured_captures(captures: Sequence[Capture], panels: Sequence[str] | set[str]) -> tuple[list[str], int]:
    """Names of the survey captures (panel captures left out, unless there is nothing else)
    measured: every Nth, at most :data:`MAX_MEASURED`; and N."""
    survey = [c.name for c in captures if c.name not in panels] or [c.name for c in captures]
    step = sample_every(len(survey), MAX_MEASURED)
    return survey[::step], step


@dataclass(frozen=True)
class AlignmentChoice:
    """How the pass puts the bands on one grid: the files' own registration or not, and the
    image registration on top (``refine``, band x 9 flattened transforms), with what was measured."""

    factory_alignment: bool
    refine: tuple[float, ...] | None = None
    label: str | None = None  # run.json band_alignment when changed
    record: dict[str, Any] = field(default_factory=dict)


def choose_alignment(camera: Camera, captures: Sequence[Capture], reference: int,
                     panels: Sequence[str] | set[str]) -> AlignmentChoice:
    """Judge the band files' own registration (DJI) on up to :data:`REFINE_CAPTURES` survey
    captures against no alignment, and refine it by image registration when it leaves more
    than :data:`RESIDUAL_MAX_PX` or does worse than none (the module docstring)."""
    names, _ = measured_captures(captures, panels)
    spread = np.unique(np.linspace(0, len(names) - 1, min(len(names), REFINE_CAPTURES)).round().astype(int))
    picks = [names[k] for k in spread]
    by_name = {c.name: c for c in captures}
    stacks, none_res, meta_res, used = [], [], [], []
    for name in picks:
        cap = by_name[name]
        try:
            stack = np.stack(read_capture_pixels(cap)[1]).astype(np.float32)
        except Exception:  # an unreadable capture is quarantined by the pass, with its reason
            continue
        if stack.shape[0] != camera.n_bands:
            continue
        aligned = align_by_files(cap.metas, stack)
        stacks.append((stack, aligned))
        used.append(name)
        none_res.append(stack_residuals(stack, reference, max_side=REFINE_MAX_SIDE))
        meta_res.append(stack_residuals(aligned, reference, max_side=REFINE_MAX_SIDE))
    if not stacks:
        return AlignmentChoice(True)
    bands = camera.band_names
    none_px, meta_px = _band_px(none_res), _band_px(meta_res)
    others = [b for b in range(len(bands)) if b != reference]
    rec: dict[str, Any] = {"captures": used,
                           "max_side_px": REFINE_MAX_SIDE,
                           "unaligned_px": _named(bands, none_px), "metadata_px": _named(bands, meta_px)}
    if not np.isfinite(meta_px[others]).any():
        return AlignmentChoice(True, record={**rec, "decision": "factory metadata kept, not judged: no tile with "
                                             "texture where the bands correlate"})
    worse = _mean(meta_px[others]) > _mean(none_px[others])
    worst = float(np.nanmax(meta_px[others]))
    if not (worse or worst > RESIDUAL_MAX_PX):
        return AlignmentChoice(True, record={**rec, "decision": "factory metadata kept: within "
                                             f"{RESIDUAL_MAX_PX:g} px and better than no alignment"})
    best, tried = _best_refinement(stacks, meta_res, none_res, worse, reference, REFINE_MAX_SIDE, bands)
    before = min(_mean(meta_px[others]), _mean(none_px[others]))
    rec["refinements_px"] = tried
    if best is None or not best[0] < before:  # no better: the files' own registration stays
        return AlignmentChoice(True, record={**rec, "decision": "image registration did not improve on the "
                                             "factory metadata: metadata kept"})
    _, on_meta, model, h, px = best
    label = REFINED if on_meta else INSTEAD
    why = ("the metadata alignment left the bands further apart than no alignment" if worse else
           f"the metadata alignment left up to {worst:.2f} px (> {RESIDUAL_MAX_PX:g} px)")
    rec.update({"model": model, "refined_px": _named(bands, px),
                "transforms": {bands[b]: [round(float(v), 6) for v in h[b].ravel()] for b in range(len(bands))}})
    return AlignmentChoice(on_meta, tuple(float(v) for v in h.ravel()), label,
                           {**rec, "decision": f"{label}: {why}; per band {ARTICLE[model]} {model} from the reference "
                                               f"band, estimated on {len(stacks)} capture(s) (tiles pooled)"})


Best = tuple[float, bool, str, np.ndarray, np.ndarray]  # score, on the metadata's alignment, model, transforms, px


def _best_refinement(stacks: Sequence[tuple[np.ndarray, np.ndarray]], meta_res: Sequence[Sequence[BandResidual]],
                     none_res: Sequence[Sequence[BandResidual]], worse: bool, reference: int, max_side: int,
                     bands: Sequence[str]) -> tuple[Best | None, dict[str, dict[str, float | None]]]:
    """Image registration on top of the metadata's alignment, and (when that did worse than
    none) instead of it; a translation per band, and an affine where the tiles allow one; each
    estimated from the tiles of ``stacks`` (unaligned, aligned) pooled and judged on them again:
    the one with the lowest mean residual over the other bands, and what each left."""
    others = [b for b in range(len(bands)) if b != reference]
    best: Best | None = None
    tried: dict[str, dict[str, float | None]] = {}
    for on_meta in (True, False) if worse else (True,):
        res = meta_res if on_meta else none_res
        base = [a if on_meta else u for u, a in stacks]
        models = {"translation": translation_transforms(pooled_translations(res))}
        affine = pooled_affines(res)
        if affine is not None:
            models["affine"] = affine
        for model, h in models.items():
            px = _band_px([stack_residuals(align_bands(b, h), reference, max_side=max_side) for b in base])
            key = f"{'metadata' if on_meta else 'none'} + {model}"
            tried[key] = _named(bands, px)
            score = _mean(px[others])
            if np.isfinite(score) and (best is None or score < best[0]):
                best = (score, on_meta, model, h, px)
    return best, tried


OWN_MIN_TILES = 3  # tiles in every band a capture needs to be judged and refined on its own pixels
OWN = "own pixels"
RULE = (f"each capture judged and refined on its own pixels (tiles at {MAX_SIDE} px on the long side; metadata kept "
        f"within {RESIDUAL_MAX_PX:g} px), so it gets the same band alignment in any flight; a capture with fewer than "
        f"{OWN_MIN_TILES} textured tiles in a band takes the flight's choice (metadata_check), which depends on the "
        "flight: not run-invariant")


@dataclass(frozen=True)
class Refinement:
    """``Plan.refine``: how the pass puts each capture's bands on one grid after the files' own
    registration (:func:`capture_transform`); the flight's choice for captures without texture."""

    reference: int
    bands: tuple[str, ...]
    flight_on_meta: bool = True
    flight: tuple[float, ...] | None = None  # (band x 9) transforms of the flight's choice, None: metadata kept
    flight_label: str = METADATA


def capture_transform(unaligned: np.ndarray, aligned: np.ndarray, plan: Refinement
                      ) -> tuple[bool, np.ndarray | None, dict[str, Any]]:
    """How one capture's bands go on one grid, judged on its own pixels (``unaligned`` as
    stored, ``aligned`` by the files' own registration), like :func:`choose_alignment` on one
    capture, at :data:`MAX_SIDE`; with fewer than :data:`OWN_MIN_TILES` tiles in a band, the
    flight's choice (``plan``). Returns whether it starts from the files' own registration
    (else from the bands as stored), the per band transforms applied on top ((band, 3, 3),
    None: none) and the run.json record; :func:`pipeline.apply.bandgrid.one_grid` applies
    them, and replays the same warp on the capture's quality mask."""
    ref, bands = plan.reference, plan.bands
    others = [b for b in range(len(bands)) if b != ref]
    meta = stack_residuals(aligned, ref)
    tiles = min(meta[b].n_tiles for b in others)
    if tiles < OWN_MIN_TILES:
        h = None if plan.flight is None else np.asarray(plan.flight, np.float64).reshape(-1, 3, 3)
        return plan.flight_on_meta, h, {
            "from": f"flight (fewest textured tiles in a band: {tiles} < {OWN_MIN_TILES})", "run_invariant": False,
            "alignment": plan.flight_label}
    meta_px = np.array([r.median_px for r in meta])
    rec: dict[str, Any] = {"from": OWN, "run_invariant": True, "alignment": METADATA,
                           "metadata_px": _named(bands, meta_px)}
    if float(np.max(meta_px[others])) <= RESIDUAL_MAX_PX:
        return True, None, rec
    none = stack_residuals(unaligned, ref)
    none_px = np.array([r.median_px for r in none])
    worse = _mean(meta_px[others]) > _mean(none_px[others])
    best, _ = _best_refinement([(unaligned, aligned)], [meta], [none], worse, ref, MAX_SIDE, bands)
    if best is None or not best[0] < min(_mean(meta_px[others]), _mean(none_px[others])):
        return True, None, {**rec, "note": "image registration did not improve on the metadata"}
    _, on_meta, model, h, px = best
    rec.update({"alignment": REFINED if on_meta else INSTEAD, "model": model, "refined_px": _named(bands, px)})
    return on_meta, h, rec


def refinement_record(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """run.json ``coregistration.per_capture``: the rule, each capture's alignment and where it
    came from, and the captures that took the flight's (not run-invariant)."""
    flight = sorted(n for n, r in results.items() if not r["run_invariant"])
    return {"rule": RULE, "own_pixels": len(results) - len(flight), "from_flight": len(flight),
            "not_run_invariant": flight, "captures": results}


def _band_px(per_capture: Sequence[Sequence[BandResidual]]) -> np.ndarray:
    """Per band the median over captures of the median residual (NaN when none measured)."""
    a = np.array([[r.median_px for r in cap] for cap in per_capture], dtype=np.float64)
    out = np.full(a.shape[1], np.nan)
    for b in range(a.shape[1]):
        v = a[:, b][np.isfinite(a[:, b])]
        if v.size:
            out[b] = np.median(v)
    return out


def _mean(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def _named(bands: Sequence[str], px: np.ndarray) -> dict[str, float | None]:
    return {b: (round(float(v), 3) if np.isfinite(v) else None) for b, v in zip(bands, px)}


def coregistration_record(camera: Camera, reference: int, alignment: str, step: int, n_captures: int,
                          measured: dict[str, dict[str, Any]], choice: AlignmentChoice | None) -> dict[str, Any]:
    """run.json ``coregistration``: the method, the sample, per measured capture and band the
    residual (px) after the alignment (and without it), per flight and band the median and
    the max, the worst band, and the decision on refining the metadata alignment."""
    bands = camera.band_names
    flight: dict[str, dict[str, Any]] = {}
    for b in bands:
        if b == bands[reference]:
            continue
        row: dict[str, Any] = {}
        for key, out in (("residual_px", ""), ("unaligned_px", "unaligned_")):
            vals = [m[key][b] for m in measured.values() if m.get(key, {}).get(b) is not None]
            if vals:
                row[f"{out}median_px"] = round(float(np.median(vals)), 3)
                row[f"{out}max_px"] = round(float(np.max(vals)), 3)
        row["captures"] = sum(1 for m in measured.values() if (m.get("residual_px") or {}).get(b) is not None)
        row["tiles"] = int(sum((m.get("tiles") or {}).get(b, 0) for m in measured.values()))
        flight[b] = row
    medians = [r["median_px"] for r in flight.values() if "median_px" in r]
    rec: dict[str, Any] = {
        "alignment": alignment, "reference_band": bands[reference], "method": METHOD,
        "threshold_px": RESIDUAL_MAX_PX,
        "sample": {"every": step, "captures": len(measured), "of": n_captures, "max_side_px": MAX_SIDE,
                   "note": "survey captures only (panel captures left out)"},
        "flight": flight, "worst_median_px": round(max(medians), 3) if medians else None,
        "captures": measured,
    }
    if choice is not None and choice.record:
        rec["metadata_check"] = choice.record
    return rec


@dataclass(frozen=True)
class RunCoregistration:
    """What a pass over captures does about co-registration (:func:`prepare`): the captures
    it measures, against which band, and the alignment chosen before it."""

    reference: int | None = None  # None: not measured (a single-file camera)
    measured: frozenset[str] = frozenset()
    step: int = 1
    n_captures: int = 0
    alignment: str = "none"
    choice: AlignmentChoice | None = None

    def record(self, camera: Camera, results: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """run.json keys of the pass: ``coregistration`` and, when the alignment was changed,
        ``band_alignment``."""
        if self.reference is None:
            return {}
        own = {n: r["refinement"] for n, r in results.items() if "refinement" in r}
        measured = {n: {k: v for k, v in r.items() if k != "refinement"} for n, r in results.items()
                    if set(r) - {"refinement"}}
        out: dict[str, Any] = {"coregistration": coregistration_record(
            camera, self.reference, self.alignment, self.step, self.n_captures, measured, self.choice)}
        if own:
            out["coregistration"]["per_capture"] = refinement_record(own)
        if self.choice is not None and self.choice.label is not None:
            out["band_alignment"] = self.choice.record.get("decision", self.choice.label)
        return out


def prepare(camera: Camera, captures: Sequence[Capture], factory_alignment: bool, transforms: bool,
            registered_reference: int | None, panels: Sequence[str] | set[str]) -> RunCoregistration:
    """The co-registration of a pass: for a multi-lens camera the sampled captures and the
    reference band, and, when the files' own registration aligns the bands, whether image
    registration refines it (:func:`choose_alignment`)."""
    if not multi_lens(camera, captures):
        return RunCoregistration()
    reference = reference_band(camera, registered_reference if transforms else None)
    names, step = measured_captures(captures, panels)
    choice = choose_alignment(camera, captures, reference, panels) if factory_alignment and not transforms else None
    if choice is not None and choice.label is not None:
        alignment = choice.label
    elif factory_alignment:
        alignment = METADATA
    else:
        alignment = "transforms of the registration store (mscal register)" if transforms else "none"
    return RunCoregistration(reference, frozenset(names), step, len(captures), alignment, choice)


#: In every apply's fingerprint: an output written before the bands were checked on the pixels
#: (no run.json ``coregistration``, a DJI metadata alignment never refined, or refined by the
#: flight's pooled transform for every capture) is not up to date.
COREGISTRATION_CHECK = ("bands measured on the pixels; DJI metadata alignment judged and refined by image "
                        "registration on each capture's own pixels")
