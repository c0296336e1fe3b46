#!/usr/bin/env python
"""Accuracy benchmark: errors against known truth, swept over difficulty.

Usage::

    .venv/bin/python bench/bench_accuracy.py [--quick] [--seed 0] [--out docs/accuracy.md] [--varied N [--no-sweep]]
                                             [--img-dir docs/img]

One synthetic session per point, built from the seeded forward model of
``pipeline.sim.world`` (the camera truth U, V, S is the same at every point of a seed; only
the difficulty changes). The base point is the ``small`` session preset of
``pipeline.sim.synth.write_session`` (10-bit, 7-frame sweep with a 729x exposure span, 8
viewpoints of which 1 without the marker, 2 reflector images, 3 flight frames) with the
default sensor noise and light. Each axis moves one setting away from the base, the others
held at the base:

- ``noise``: read and shot noise multiplied by k (default 1.5 DN read + 9 DN rms shot noise
  at full scale, ``pipeline.sim.world.sensor.SensorModel``);
- ``exposures``: frames in the sweep, same 729x span of exposure times;
- ``views``: vignetting viewpoints (1 without the marker in every case);
- ``light``: non-uniformity ``a`` of the light on the reflector (gradient ``2**a``:1, shadow
  transmission ``(1 - depth)**a``; ``pipeline.sim.world.scene._random_light``).

At each point, against the session's truth (``pipeline.sim.evaluate.evaluate_calibration``):

- (a) mscal's default calibration (``calibrate_session``, response ``forward``);
- (b) the paper's plain alternation of Eq. 6/7 (response ``alternating``; V and S then fitted
  by the same code on that U);
- (c) OpenCV ``CalibrateDebevec`` and ``CalibrateRobertson`` for the response, on the same
  sweep reduced to 8 bits (``DN8 = DN10 >> 2``: what an 8-bit readout of the same sensor
  gives; OpenCV's calibrators take 8-bit images only), beside mscal's two estimators on the
  same 8-bit frames; 5 of the 25 bands (every 6th) to keep the run short;
- (d) Eq. 16 normalisation (divide by the reflector's DN) for the flight figures.

The ``views`` and ``light`` points share the base point's sweep: their response is fitted
once (per estimator), so their response figures repeat the base's.

The markdown section (machine, command, one table per axis, a reading) replaces the text
between ``<!-- bench_accuracy:start -->`` and ``<!-- bench_accuracy:end -->`` of ``--out``;
plots of error vs difficulty (one PNG per axis) go to ``--img-dir``. ``--quick``: two points
(base and 4x noise) into ``build/bench-quick/`` unless ``--out`` is given.

Importing this module runs nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import bench_calibrate as bc  # shared measurement and markdown helpers

SECTION_KEY = "bench_accuracy"
DEFAULT_OUT = ROOT / "docs" / "accuracy.md"
DEFAULT_IMG = ROOT / "docs" / "img"
QUICK_DIR = ROOT / "build" / "bench-quick"

#: Exposure span of the sweep (longest / shortest), the ``small`` preset's 3**6.
SWEEP_SPAN = 3.0**6
#: Bands of the 8-bit response comparison (every 6th of 25).
BANDS_8BIT = (0, 6, 12, 18, 24)


@dataclass(frozen=True)
class Axis:
    key: str
    title: str
    unit: str
    levels: tuple[float, ...]
    base: float


AXES = (
    Axis("noise", "sensor noise", "x default noise (1.5 DN read, 9 DN shot at full scale)", (0.5, 1.0, 2.0, 4.0), 1.0),
    Axis("exposures", "sweep exposures", "frames in the sweep (729x span)", (4, 7, 14), 7),
    Axis("views", "vignetting views", "viewpoints (1 without the marker)", (8, 16, 32), 8),
    Axis("light", "light non-uniformity", "a: gradient 2^a:1, shadow transmission (1-d)^a", (0.0, 1.0, 2.0), 1.0),
)
QUICK_LEVELS = {"noise": (1.0, 4.0), "exposures": (7,), "views": (8,), "light": (1.0,)}

BASE = {"noise": 1.0, "exposures": 7, "views": 8, "light": 1.0}


def axis_points(quick: bool) -> list[tuple[str, float]]:
    """(axis, level) of every point, in order; the base point appears on every axis."""
    return [(a.key, lv) for a in AXES for lv in (QUICK_LEVELS[a.key] if quick else a.levels)]


def point_params(axis: str, level: float) -> dict[str, float]:
    """Session settings of a point: the base with ``axis`` set to ``level``."""
    if axis not in BASE:
        raise ValueError(f"unknown axis {axis!r}; use one of {', '.join(BASE)}")
    p = dict(BASE)
    p[axis] = level
    return p


def params_key(p: dict[str, float]) -> tuple:
    return tuple(sorted(p.items()))


def anchor(axis: str, level: float) -> str:
    """HTML id of a table row: ``acc-<axis>-<level>`` (``.`` as ``p``), stable across runs."""
    return f"acc-{axis}-{level:g}".replace(".", "p")


# --------------------------------------------------------------------------- synthesis


class Synth:
    """Datasets of one seed, cached by the settings they depend on (points share them)."""

    def __init__(self, seed: int):
        self.seed = seed
        self._cache: dict[tuple, Any] = {}

    def _get(self, key: tuple, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def truth(self, noise: float):
        from pipeline.sim.world.scene import make_truth
        from pipeline.sim.world.sensor import SensorModel

        d = SensorModel()
        sensor = SensorModel(read_noise_dn=d.read_noise_dn * noise, shot_noise_dn_at_full=d.shot_noise_dn_at_full * noise)
        return self._get(("truth", noise), lambda: make_truth(self.seed, sensor=sensor))

    def session(self, p: dict[str, float]):
        from pipeline.sim.world.scene import (
            SyntheticSession,
            flight_frames,
            reflector_images,
            response_sweep,
            vignetting_views,
        )

        t = self.truth(p["noise"])
        n = int(p["exposures"])
        step = SWEEP_SPAN ** (1.0 / (n - 1))
        resp = self._get(("resp", p["noise"], n), lambda: response_sweep(t, seed=self.seed, n_frames=n, step=step))
        vig = self._get(("vig", p["noise"], int(p["views"]), p["light"]),
                        lambda: vignetting_views(t, seed=self.seed, n_views=int(p["views"]), n_missing=1,
                                                 light_nonuniformity=p["light"]))
        refl = self._get(("refl", p["noise"], p["light"]),
                         lambda: reflector_images(t, seed=self.seed, n_images=2, light_nonuniformity=p["light"]))
        fl = self._get(("flight", p["noise"]),
                       lambda: flight_frames(t, seed=self.seed, n_frames=3, name="field", time_offset_s=1200.0))
        return SyntheticSession(truth=t, response=resp, vignetting=vig, reflector=refl, flights={"field": fl},
                                size="bench")


def write_synthetic(session, root: Path) -> Path:
    """A session folder as ``pipeline.sim.synth.write_session`` writes it, from a built session."""
    from pipeline.sim.synth import write_synthesized

    if root.exists():
        shutil.rmtree(root)
    return write_synthesized(session, root)


# --------------------------------------------------------------------------- fits


def calibrate(session_dir: Path, out: Path, method: str, response_cache: dict) -> None:
    """``pipeline.calibrate.fit.calibrate_session`` with the response stage cached by sweep."""
    from pipeline.calibrate.fit import observed_vignetting, provenance
    from pipeline.calibrate.illumination_stage import add_illumination, fit_illumination_frames
    from pipeline.calibrate.response_stage import fit_response_frames, response_dataset
    from pipeline.calibrate.vignetting_stage import add_vignetting, fit_vignetting_frames
    from pipeline.ingest.session import load_session
    from pipeline.storage.store import write_store

    session = load_session(session_dir)
    cam = session.camera
    key = (method, response_cache.get("_sweep_key"))
    if key not in response_cache:
        response_cache[key] = fit_response_frames(session.response_dir, cam, method, session.root)
    rfits, rrep = response_cache[key]
    ds = response_dataset(cam, rfits, rrep)
    U, sat = ds["inverse_response"].values, ds["saturation_dn"].values
    vfits, vrep = fit_vignetting_frames(session, U, sat)
    ds = add_vignetting(ds, vfits, vrep)
    ds = add_illumination(ds, fit_illumination_frames(session, U, sat, ds["vignetting"].values,
                                                      vignetting_observed=observed_vignetting(ds)))
    write_store(provenance(ds, session.root), out)


def true_u8(u10):
    """True inverse response of the 8-bit readout ``DN8 = DN10 >> 2``: the mean of the 10-bit
    ``U`` over the four 10-bit codes of each 8-bit code."""
    return u10.reshape(256, 4).mean(axis=1)


def fill_gaps(u):
    """``u`` with its NaN entries linearly interpolated from the finite ones (Robertson leaves
    NaN at codes that never occur in the sweep; mscal's fits interpolate them themselves)."""
    import numpy as np

    u = np.asarray(u, dtype=float)
    ok = np.isfinite(u)
    if ok.all() or not ok.any():
        return u
    k = np.arange(u.size)
    return np.interp(k, k[ok], u[ok])


def response_8bit(dn10, exposure, u10_true, bands: Sequence[int] = BANDS_8BIT) -> dict[str, float]:
    """Worst response error (``mscal_core.metrics.response_error``) over ``bands`` of four
    estimators on the 8-bit sweep ``DN10 >> 2``: OpenCV Debevec, OpenCV Robertson, mscal
    forward, mscal alternating. ``dn10`` (frames, bands, H, W) uint16."""
    import cv2
    import numpy as np

    from mscal_core import metrics, response

    dn8 = (np.asarray(dn10) >> 2).astype(np.uint8)
    times = np.asarray(exposure, np.float32)
    truth = true_u8(np.asarray(u10_true[0], float))
    errs: dict[str, list[float]] = {"debevec": [], "robertson": [], "forward": [], "alternating": []}
    # OpenCV's calibrators on 3-channel images (Robertson on 1-channel images corrupts the heap
    # in OpenCV 5.0.0): the bands in threes, the last three repeated as needed.
    bl = list(bands)
    triples = [bl[i:i + 3] + [bl[-1]] * (3 - len(bl[i:i + 3])) for i in range(0, len(bl), 3)]
    for name, make in (("debevec", cv2.createCalibrateDebevec), ("robertson", cv2.createCalibrateRobertson)):
        seen = set()
        for tri in triples:
            imgs = [np.ascontiguousarray(np.moveaxis(dn8[i, tri], 0, -1)) for i in range(dn8.shape[0])]
            crf = make().process(imgs, times)  # (256, 1, 3): the inverse response, relative
            for c, b in enumerate(tri):
                if b not in seen:
                    seen.add(b)
                    errs[name].append(metrics.response_error(fill_gaps(crf[:, 0, c]), truth))
    n = dn8.shape[0]
    for method in ("forward", "alternating"):
        for b in bands:
            fit = response.fit_response(dn8[:, b].reshape(n, -1), np.asarray(exposure, float), 8, method=method)
            errs[method].append(metrics.response_error(fit.inverse_response, truth))
    return {k: float(max(v)) for k, v in errs.items()}


def light_spread(session) -> float:
    """Max / min of the light's brightness B over the reflector (vignetting views' light)."""
    import numpy as np

    b = np.asarray(session.vignetting.truth["B_plane"], float)
    return float(np.nanmax(b) / np.nanmin(b))


def run_point(synth: Synth, p: dict[str, float], workdir: Path, response_cache: dict, log=print) -> dict[str, Any]:
    """All errors of one point (see the module docstring)."""
    import numpy as np

    from pipeline.sim.evaluate import evaluate_calibration

    t0 = time.perf_counter()
    sess = synth.session(p)
    sdir = write_synthetic(sess, workdir / "session")
    t_synth = time.perf_counter() - t0
    response_cache["_sweep_key"] = (p["noise"], int(p["exposures"]))
    res: dict[str, Any] = {"params": p, "light_spread": light_spread(sess)}
    for method in ("forward", "alternating"):
        out = workdir / f"calib-{method}.zarr"
        calibrate(sdir, out, method, response_cache)
        res[method] = evaluate_calibration(sdir, out)
        shutil.rmtree(out, ignore_errors=True)
    truth = sess.truth
    res["bit8"] = response_8bit(np.stack(sess.response.dn), sess.response.exposure_ms, truth.inverse_response)
    res["seconds"] = {"synthesis": t_synth, "total": time.perf_counter() - t0}
    log(f"  {p}: response {res['forward']['response_max_error']:.4f} / {res['alternating']['response_max_error']:.4f}, "
        f"Debevec-8 {res['bit8']['debevec']:.4f}; {res['seconds']['total']:.0f} s")
    return res


def run_sweep(seed: int, quick: bool, workdir: Path, log=print) -> dict[tuple, dict[str, Any]]:
    synth = Synth(seed)
    cache: dict = {}
    results: dict[tuple, dict[str, Any]] = {}
    for axis, level in axis_points(quick):
        p = point_params(axis, level)
        k = params_key(p)
        if k not in results:
            log(f"point {axis}={level:g}")
            results[k] = run_point(synth, p, workdir, cache, log)
    return results


# --------------------------------------------------------------------------- markdown


def flat(res: dict[str, Any]) -> dict[str, float]:
    """The figures of one point under flat names (``<method>:<metric>``)."""
    nan = float("nan")
    out: dict[str, float] = {}
    for m in ("forward", "alternating"):
        ev = res[m]
        out[f"{m}:response"] = ev["response_max_error"]
        out[f"{m}:vignetting"] = ev.get("vignetting_rms_error", nan)
        out[f"{m}:vignetting_observed"] = ev.get("vignetting_rms_error_observed", nan)
        out[f"{m}:spectral"] = ev.get("spectral_factor_max_error", nan)
        fl = ev.get("flight_field", {}).get("eq15", {})
        out[f"{m}:panel"] = fl.get("panel_abs_error", nan)
        out[f"{m}:ndvi"] = fl.get("vegetation_ndvi_error", nan)
        out[f"{m}:cv"] = fl.get("panel_cv_across_frames", nan)
    e16 = res["forward"].get("flight_field", {}).get("eq16", {})
    out["eq16:panel"] = e16.get("panel_abs_error", nan)
    out["eq16:ndvi"] = e16.get("vegetation_ndvi_error", nan)
    out["eq16:cv"] = e16.get("panel_cv_across_frames", nan)
    for k, v in res["bit8"].items():
        out[f"8bit-{k}:response"] = v
    out["light_spread"] = res.get("light_spread", nan)
    return out


FIT_COLUMNS = (
    ("response, default", "forward:response"),
    ("response, alternating", "alternating:response"),
    ("8-bit: default", "8bit-forward:response"),
    ("8-bit: alternating", "8bit-alternating:response"),
    ("8-bit: OpenCV Debevec", "8bit-debevec:response"),
    ("8-bit: OpenCV Robertson", "8bit-robertson:response"),
    ("V, default", "forward:vignetting"),
    ("V, alternating", "alternating:vignetting"),
    ("V observed px, default", "forward:vignetting_observed"),
    ("S, default", "forward:spectral"),
    ("S, alternating", "alternating:spectral"),
)
FLIGHT_COLUMNS = (
    ("panel, default", "forward:panel"),
    ("panel, alternating", "alternating:panel"),
    ("panel, Eq. 16", "eq16:panel"),
    ("NDVI, default", "forward:ndvi"),
    ("NDVI, alternating", "alternating:ndvi"),
    ("NDVI, Eq. 16", "eq16:ndvi"),
    ("panel CV, default", "forward:cv"),
    ("panel CV, Eq. 16", "eq16:cv"),
)


def _f(v: float) -> str:
    return "nan" if v is None or not math.isfinite(v) else f"{v:.4f}"


def level_label(axis: Axis, level: float, fl: dict[str, float]) -> str:
    s = f"{level:g}"
    if axis.key == "light":
        s += f" (max/min B {fl['light_spread']:.1f})"
    if level == axis.base:
        s += " (base)"
    return s


def axis_tables(axis: Axis, levels: Sequence[float], results: dict[tuple, dict[str, Any]]) -> str:
    parts = []
    for title, cols, suffix in (("calibration fits", FIT_COLUMNS, ""), ("flight", FLIGHT_COLUMNS, "-flight")):
        head = [f"{axis.title} ({axis.unit})"] + [c for c, _ in cols]
        lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * len(cols)) + "|"]
        for lv in levels:
            fl = flat(results[params_key(point_params(axis.key, lv))])
            cell = f'<a id="{anchor(axis.key, lv)}{suffix}"></a>' + level_label(axis, lv, fl)
            lines.append("| " + " | ".join([cell] + [_f(fl[k]) for _, k in cols]) + " |")
        parts += [f"**{axis.title[0].upper() + axis.title[1:]}: {title}**", "", "\n".join(lines), ""]
    return "\n".join(parts)


def reading(results: dict[tuple, dict[str, Any]], quick: bool) -> str:
    base = flat(results[params_key(dict(BASE))])
    lines = [
        f"- Base point: response error {_f(base['forward:response'])} (default) vs {_f(base['alternating:response'])} "
        f"(paper's alternation); on the 8-bit sweep {_f(base['8bit-forward:response'])} (default), "
        f"{_f(base['8bit-debevec:response'])} (OpenCV Debevec), {_f(base['8bit-robertson:response'])} (OpenCV Robertson). "
        f"Panel reflectance error {_f(base['forward:panel'])} with Eq. 15 and the default calibration vs "
        f"{_f(base['eq16:panel'])} with Eq. 16; NDVI error {_f(base['forward:ndvi'])} vs {_f(base['eq16:ndvi'])}.",
    ]
    allp = [flat(r) for r in results.values()]
    for m, label in (("alternating", "the paper's alternation"), ("8bit-debevec", "OpenCV Debevec (8-bit)"),
                     ("8bit-robertson", "OpenCV Robertson (8-bit)")):
        ref = "8bit-forward" if m.startswith("8bit") else "forward"
        ratios = [p[f"{m}:response"] / p[f"{ref}:response"] for p in allp
                  if p[f"{ref}:response"] > 0 and math.isfinite(p[f"{m}:response"])]
        if ratios:
            lines.append(f"- Response error of {label} / mscal default on the same data: "
                         f"{min(ratios):.1f}x to {max(ratios):.1f}x over the {len(ratios)} points.")
    r16 = [p["eq16:panel"] / p["forward:panel"] for p in allp if p["forward:panel"] > 0]
    if r16:
        lines.append(f"- Panel error of Eq. 16 / Eq. 15 with the default calibration: {min(r16):.1f}x to {max(r16):.1f}x.")
    lines.append("- One seed per point (another seed moves each figure too: see the spread over three seeds in the "
                 "calibration benchmark); read the trends, not single differences.")
    if quick:
        lines.append("- Quick smoke run: two points only; the figures are indicative.")
    return "\n".join(lines)


def render(results: dict[tuple, dict[str, Any]], quick: bool, command: str, info: dict[str, str], seed: int,
           started: str, loads: dict[str, str], wall_s: float, img_rel: dict[str, str]) -> str:
    title = "Accuracy vs difficulty" + (" (quick smoke run)" if quick else "")
    parts = [
        '<a id="bench-accuracy"></a>',
        "",
        f"## {title}",
        "",
        f"Produced by `bench/bench_accuracy.py`; a later run replaces this section. Run started {started}, "
        f"{wall_s / 60:.1f} min.",
        "",
        "```",
        command,
        "```",
        "",
        "Machine: " + "; ".join([f"{info['nproc']} CPUs ({info['cpu']})", f"{info['memory']} RAM", info["os"],
                                  f"Python {info['python']}", f"numpy {info['numpy']}", f"OpenCV {info['opencv']}"])
        + f". Code: git {info['git']}. Load (`uptime`): at start `{loads['start']}`; at end `{loads['end']}`.",
        "",
        f"Sessions: seed {seed}, synthesized with `pipeline.sim.world` (same camera truth at every point). Base point: "
        "10-bit sensor, 7-frame sweep spanning 729x in exposure, 8 vignetting viewpoints (1 without the marker), "
        "2 reflector images, 3 flight frames, default noise and light. Each axis changes one setting; the rest stay "
        "at the base. All figures of a row come from the same session. Errors (`pipeline.sim.evaluate`, "
        "`mscal_core.metrics`): response = max |U - U_true| over 5-95 % of the DN range / U_true(95 %) after a "
        "least-squares scale, worst band; V = RMS of V/V_true - 1 over all pixels, worst band (\"observed px\": "
        "pixels some view saw); S = max relative error after a scale; panel = abs error of the gray panels' "
        "reflectance after white-panel normalisation; NDVI = abs error of the vegetation's mean NDVI; panel CV = "
        "the same panel across frames. \"8-bit\": the sweep reduced to 8 bits (`DN8 = DN10 >> 2`, what an 8-bit "
        "readout of the same sensor gives; OpenCV's `CalibrateDebevec` / `CalibrateRobertson` accept only 8-bit "
        "images), bands " + ", ".join(map(str, BANDS_8BIT)) + ", error against the 8-bit true U; OpenCV with its "
        "default parameters (codes absent from the sweep, NaN in Robertson's output, interpolated from their "
        "neighbours). \"alternating\": the paper's plain Eq. 6/7 (`--response-method alternating`), with V "
        "and S then fitted by the same code. Eq. 16: flight DN / the reflector's DN, no calibration.",
        "",
    ]
    for axis in AXES:
        levels = QUICK_LEVELS[axis.key] if quick else axis.levels
        if len(levels) < 2:
            continue
        parts += [f"### {axis.title[0].upper() + axis.title[1:]}", "", axis_tables(axis, levels, results)]
        if axis.key in img_rel:
            parts += [f"![error vs {axis.title}]({img_rel[axis.key]})", ""]
    parts += ["### Reading", "", reading(results, quick), ""]
    return "\n".join(parts)


# --------------------------------------------------------------------------- plots


PLOT_PANELS = (
    ("response (10-bit)", (("default", "forward:response"), ("alternating", "alternating:response"))),
    ("response (8-bit)", (("default", "8bit-forward:response"), ("alternating", "8bit-alternating:response"),
                          ("OpenCV Debevec", "8bit-debevec:response"), ("OpenCV Robertson", "8bit-robertson:response"))),
    ("vignetting RMS", (("default", "forward:vignetting"), ("alternating", "alternating:vignetting"))),
    ("S max rel. error", (("default", "forward:spectral"), ("alternating", "alternating:spectral"))),
    ("panel abs error", (("default", "forward:panel"), ("alternating", "alternating:panel"), ("Eq. 16", "eq16:panel"))),
    ("NDVI abs error", (("default", "forward:ndvi"), ("alternating", "alternating:ndvi"), ("Eq. 16", "eq16:ndvi"))),
)
STYLE = {"default": ("C0", "o"), "alternating": ("C1", "s"), "OpenCV Debevec": ("C2", "^"),
         "OpenCV Robertson": ("C3", "v"), "Eq. 16": ("C4", "D")}


def plot_axis(axis: Axis, levels: Sequence[float], results: dict[tuple, dict[str, Any]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [flat(results[params_key(point_params(axis.key, lv))]) for lv in levels]
    fig, axs = plt.subplots(1, len(PLOT_PANELS), figsize=(3.2 * len(PLOT_PANELS), 3.0), constrained_layout=True)
    for ax, (title, series) in zip(axs, PLOT_PANELS):
        for label, key in series:
            y = [p[key] for p in pts]
            c, mk = STYLE[label]
            ax.plot(levels, y, color=c, marker=mk, label=label)
        ax.set_yscale("log")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(axis.unit if len(axis.unit) < 40 else axis.title, fontsize=8)
        ax.axvline(axis.base, color="0.7", lw=0.8, ls=":")
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    fig.suptitle(f"Error vs {axis.title} (base point at the dotted line)", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- main


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="two points (base, 4x noise); output under build/bench-quick")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="markdown file to update (default docs/accuracy.md; "
                                                          "--quick: build/bench-quick/benchmarks.md)")
    p.add_argument("--img-dir", type=Path, default=None, help="plots (default docs/img; --quick: build/bench-quick/img)")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--json", type=Path, default=None, help="also write the raw figures as JSON")
    p.add_argument("--varied", type=int, default=0, metavar="N",
                   help="also run N varied full-size sessions end to end (calibrate + apply; accuracy_varied.py)")
    p.add_argument("--no-sweep", action="store_true", help="skip the difficulty sweep (with --varied: only those)")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    raw = list(sys.argv[1:] if argv is None else argv)
    a = parse_args(raw)
    sys.path.insert(0, str(ROOT))
    out = a.out or (QUICK_DIR / "benchmarks.md" if a.quick else DEFAULT_OUT)
    img = a.img_dir or (QUICK_DIR / "img" if a.quick else DEFAULT_IMG)
    command = shlex.join([".venv/bin/python", "bench/bench_accuracy.py", *raw])
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    loads = {"start": bc._uptime()}
    info = bc.machine_info()
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="mscal-bench-acc-", dir=a.workdir))
    try:
        if a.varied:
            import accuracy_varied

            varied = accuracy_varied.run(a.varied, work, log=lambda m: print(m, flush=True))
            vmd = accuracy_varied.render(varied, command)
            print(vmd)
            bc.write_section(out, vmd, accuracy_varied.SECTION_KEY)
            print(f"wrote section {accuracy_varied.SECTION_KEY} of {out}")
            if a.no_sweep:
                return 0
        results = run_sweep(a.seed, a.quick, work, log=lambda m: print(m, flush=True))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    loads["end"] = bc._uptime()
    img_rel = {}
    for axis in AXES:
        levels = QUICK_LEVELS[axis.key] if a.quick else axis.levels
        if len(levels) >= 2:
            path = plot_axis(axis, levels, results, img / f"bench_accuracy_{axis.key}.png")
            img_rel[axis.key] = os.path.relpath(path, out.resolve().parent)
    md = render(results, a.quick, command, info, a.seed, started, loads, time.perf_counter() - t0, img_rel)
    print(md)
    if a.json:
        a.json.write_text(json.dumps([{"params": r["params"], **flat(r)} for r in results.values()], indent=2))
    bc.write_section(out, md, SECTION_KEY)
    print(f"wrote section {SECTION_KEY} of {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
