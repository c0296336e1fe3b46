#!/usr/bin/env python
"""Light that changes during a flight: how well the same gray panel agrees early and
late in a flight whose light drifts, per interpolation mode, with and without sun-sensor readings.

Usage::

    .venv/bin/python bench/bench_light.py [--seed 0] [--level-end 0.75] [--colour-tilt 0.03]
        [--gradient 1.2] [--images 2] [--size full] [--work DIR]

1. a synthetic session (``write_session(size=--size)``: ``full`` (default) 14 response frames
   and 40 vignetting views, as a user's calibration session; ``small`` 7 and 8, quicker, whose
   vignetting estimate is off by up to 5.5 % rms and shows at the panel's pixels) and
   ``mscal calibrate`` on it, for the response and vignetting (reused from ``--work`` if there);
2. a drifting-light session with the same camera truth (``pipeline.sim.synth.write_light_drift``):
   the light's level goes from 1 to ``--level-end`` and its colour tilts by ``--colour-tilt``
   between 1200 s and 3000 s (linear in time); reflector captured at 1100 s and 3100 s
   (``--images`` images each, light with a ``--gradient``:1 gradient, no shadow); two
   3-frame flights at 1200, 2100, 3000 s: ``drift`` (no clouds, no sun sensor) and
   ``clouds`` (a random cloud factor 0.75-1.15 per frame and a sun-sensor reading);
3. ``mscal fit illumination`` on top of step 1's store, then ``mscal apply
   --illumination linear|nearest`` on both flights;
4. per flight and mode, the 0.5 panel's median reflectance per band in the last and middle
   frame over the first: the largest and the median |ratio - 1| over the 25 bands, corrected,
   and uncorrected (the illumination factors divided out: the first capture's S for every
   frame, as mscal did before it followed the light in time).

Prints a markdown table. Importing this module runs nothing.

``--sun-sensor`` runs the panel + sun-sensor cases instead (no calibration session): synthetic flights
from the real RedEdge capture (``pipeline.sim.sunlight.write_sunlight_flight``: panel at 0 and
``--duration`` s, the sun moving, the direct light fading, a tilted sun sensor with a direct and
a diffuse part and a per-band calibration error), per case and ``--seeds``; the late panel is
predicted from the early one (``pipeline.apply.light_check.panel_prediction``) by the panel alone,
the sun sensor alone (tilt-corrected), panel + raw sensor readings and panel + sensor (the
``panel-dls`` route). Prints the largest |error| over the bands (median and worst over seeds)::

    .venv/bin/python bench/bench_light.py --sun-sensor [--seeds 3] [--duration 2040]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import numpy as np


def panel_medians(out: Path, labels: np.ndarray, corrected: bool, label: int = 4) -> np.ndarray:
    import xarray as xr

    ds = xr.open_zarr(out / "reflectance.zarr")
    refl = ds["reflectance"].values
    if not corrected:
        refl = refl / ds["illumination_scale"].values[:, :, None, None]
    return np.array([[np.nanmedian(refl[f, b][labels[f] == label]) for b in range(refl.shape[1])]
                     for f in range(refl.shape[0])])


#: Synthetic drift cases of ``--sun-sensor``: name, keywords of ``write_sunlight_flight``.
SUN_CASES = (
    ("clear sky (r = 1/6), panel tilt 8 deg, flight 4 deg", {}),
    ("direct light fades to 0.8", {"level_end": 0.8}),
    ("haze builds (diffuse ratio +30 %)", {"haze": 0.3}),
    ("bluer sky (r = 0.12 (550/lambda)^2)", {"r0": 0.12, "r_exponent": 2.0}),
    ("panel tilt 12 deg", {"panel_tilt_deg": 12.0}),
    ("bluer sky, 12 flight captures (ratio fitted per band)", {"r0": 0.12, "r_exponent": 2.0, "n_flight": 12}),
    ("haze builds, 12 flight captures (ratio fitted per band)", {"haze": 0.3, "n_flight": 12}),
)


#: The real RedEdge capture the synthetic flights are built from (``--template``).
TEMPLATE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "micasense-rededge"


def sun_sensor_bench(seeds: int, duration_s: float, work: Path, template: Path = TEMPLATE,
                     cases: tuple[int, ...] | None = None) -> None:
    from pipeline.apply.light_check import panel_prediction
    from pipeline.sim.sunlight import write_sunlight_flight

    methods = ("panel", "sensor", "combined_raw", "combined")
    print(f"\nlate panel ({duration_s:.0f} s after the early one) predicted from the early panel; largest |error| "
          f"over the 5 bands, median / worst over seeds 0-{seeds - 1}\n")
    print("| case | panel alone | sun sensor alone | panel + raw sensor | panel + sensor (panel-dls) |")
    print("|---|---|---|---|---|")
    for case, (name, kw) in enumerate(SUN_CASES):
        if cases is not None and case not in cases:
            continue
        worst: dict[str, list[float]] = {m: [] for m in methods}
        for seed in range(seeds):
            folder = work / f"sun-{case}-{seed}"
            shutil.rmtree(folder, ignore_errors=True)
            truth = write_sunlight_flight(template, folder, seed=seed, duration_s=duration_s, **kw)
            res = panel_prediction(folder, "micasense-rp02-1603036-sc", truth.names[0], truth.names[-1])
            for m in methods:
                worst[m].append(max(abs(v) for v in res[m].values()))
            shutil.rmtree(folder, ignore_errors=True)
        cells = [f"{np.median(worst[m]):.2%} / {max(worst[m]):.2%}" for m in methods]
        print(f"| {name} | " + " | ".join(cells) + " |")


def main() -> None:
    from pipeline.run.cli import main as mscal
    from pipeline.sim.synth import write_light_drift, write_session
    from pipeline.sim.world.scene import LightDrift

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--level-end", type=float, default=0.75)
    ap.add_argument("--colour-tilt", type=float, default=0.03)
    ap.add_argument("--gradient", type=float, default=1.2)
    ap.add_argument("--images", type=int, default=2)
    ap.add_argument("--size", choices=("small", "full"), default="full",
                    help="calibration session of step 1 (its response and vignetting estimates)")
    ap.add_argument("--work", type=Path, default=None, help="work folder (kept; default a temporary one)")
    ap.add_argument("--sun-sensor", action="store_true", help="the panel + sun-sensor cases instead")
    ap.add_argument("--seeds", type=int, default=3, help="--sun-sensor: seeds per case")
    ap.add_argument("--duration", type=float, default=2040.0, help="--sun-sensor: seconds between the panels")
    ap.add_argument("--template", type=Path, default=TEMPLATE, help="--sun-sensor: a RedEdge panel + flight capture")
    ap.add_argument("--cases", default=None, help="--sun-sensor: comma-separated case numbers (default all)")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="mscal-light-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.sun_sensor:
        cases = None if args.cases is None else tuple(int(c) for c in args.cases.split(","))
        sun_sensor_bench(args.seeds, args.duration, work, args.template, cases)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
        return
    calib = work / f"{args.size}-seed{args.seed}.zarr"
    if not calib.exists():
        session = write_session(work / f"{args.size}-seed{args.seed}", seed=args.seed, size=args.size)
        assert mscal(["calibrate", str(session), "-o", str(calib)]) == 0
    drift = LightDrift(1200.0, 3000.0, level_end=args.level_end, colour_tilt_end=args.colour_tilt)
    flight = dict(n_frames=3, time_offset_s=1200.0, frame_interval_s=900.0)
    root = work / "drift"
    truth = write_light_drift(root, drift, seed=args.seed, images_per_capture=args.images,
                              gradient_ratio=args.gradient,
                              flights={"drift": dict(flight, clouds=False),
                                       "clouds": dict(flight, clouds=True, irradiance=True)})
    store = work / "drift.zarr"
    assert mscal(["fit", "illumination", str(root), "-o", str(store), "--calibration", str(calib)]) == 0
    print(f"\nseed {args.seed} ({args.size} calibration session), level 1 -> {args.level_end}, "
          f"colour tilt {args.colour_tilt:.0%}, reflector gradient "
          f"{args.gradient}:1, {args.images} image(s) per capture\n")
    print("| flight | mode | frame | corrected max | corrected median | uncorrected max | uncorrected median |")
    print("|---|---|---|---|---|---|---|")
    for name, fs in truth.items():
        for mode in ("linear", "nearest"):
            out = work / f"out-{name}-{mode}"
            shutil.rmtree(out, ignore_errors=True)
            assert mscal(["apply", str(root / "flights" / name), "--calibration", str(store), "-o", str(out),
                          "--illumination", mode]) == 0
            labels = fs.truth["labels"]
            cor, unc = panel_medians(out, labels, True), panel_medians(out, labels, False)
            for f in (1, 2):
                rc, ru = np.abs(cor[f] / cor[0] - 1.0), np.abs(unc[f] / unc[0] - 1.0)
                print(f"| {name} | {mode} | {f} vs 0 | {rc.max():.2%} | {np.median(rc):.2%} | "
                      f"{ru.max():.2%} | {np.median(ru):.2%} |")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
