"""Varied synthetic sessions: the forward model of :mod:`pipeline.sim.synth` with what changes
from one field session to the next drawn from a seed instead of fixed.

:func:`write_session` in :mod:`pipeline.sim.synth` renders every session with the same light
(a 2:1 gradient, a 35-50 % shadow), the same sensor, the same marker and the same distribution
of viewpoints; only the random draws inside those settings change with the seed. A calibration
tuned and timed on those sessions may behave differently on a session taken on another day
with another reflector. :class:`VariedParams` names each setting; :func:`draw_params` draws a
set from a seed over the ranges a real field session shows (defended in its docstring);
:func:`write_varied_session` writes a full-size session (14-frame sweep, 40 viewpoints, 3
reflector images, one 8-frame flight) with them, plus ``truth.npz`` in the layout
:func:`pipeline.sim.evaluate.evaluate_calibration` scores, plus ``params.json`` (the set).

Every parameter at its default reproduces the forward model of ``write_session`` (same draws,
other seed stream: see :func:`synthesize_varied`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from pipeline.sim.world.scene import (
    CharucoBoardSpec,
    MarkerSpec,
    SyntheticSession,
    SyntheticTruth,
    flight_frames,
    make_truth,
    reflector_images,
    response_sweep,
    vignetting_views,
)
from pipeline.sim.world.sensor import SensorModel

from .synth import session_marker, write_synthesized

__all__ = ["VariedParams", "draw_params", "harsh_params", "params_record", "synthesize_varied", "varied_truth",
           "write_varied_session"]

#: Seed streams of :func:`draw_params` start here, apart from the seeds of ``write_session``
#: (0, 1, 2 in the benchmark), so a varied session never repeats a benchmark session's draws.
SEED_BASE = 1000


@dataclass(frozen=True)
class VariedParams:
    """What varies from one field session to the next. Defaults: the fixed settings of
    :func:`pipeline.sim.synth.write_session` (``size="full"``).

    Attributes
    ----------
    seed : int
        Seed of every random draw inside the datasets (poses, noise, textures).
    light_nonuniformity : float
        ``a`` of :func:`pipeline.sim.world._reflector.random_light`: gradient ``2**a`` : 1
        across the reflector and a shadow ``1 - (1 - d)**a`` deep (d 35-50 %); 0 is uniform.
    light_gradient_deg : float or None
        Direction of the gradient on the reflector (degrees; None: drawn per light).
    read_noise_dn, shot_noise_dn_at_full : float
        Sensor noise, DN rms (read; shot noise at full scale).
    shoulder_start : float
        Fraction of the DN range where the response's soft shoulder begins: the lower, the
        stronger the shoulder (the flatter the response, the steeper U near the clip).
    curvature : float
        Mild compression of the linear part (``SensorModel.curvature``).
    marker_size_m, marker_border_m : float
        Side of the ArUco marker and the white paper around it.
    distance_m : tuple of float
        Range of the marker's distance in the vignetting views.
    max_tilt_deg : float
        Largest tilt of the camera from the reflector's normal (obliqueness).
    n_views, n_missing, n_partial : int
        Vignetting views, of which ``n_missing`` with the marker out of frame and
        ``n_partial`` with the marker cut by the frame's border.
    view_exposure : tuple of float
        Share of the DN range the brightest gray-reflector pixel gets (vignetting views and
        reflector images).
    sweep_frames, sweep_step : int, float
        Exposures of the sweep and the ratio between neighbours.
    sweep_start : tuple of float
        Share of the DN range of the brightest sweep pixel in the shortest exposure.
    vignetting_falloff : float
        Smallest mean corner falloff of V over the bands (bands span it to +0.07).
    vignetting_shift_px : tuple of float
        Common shift (x, y) of the vignetting centres, band-grid pixels.
    marker : str or CharucoBoardSpec
        ``"aruco"``: the single marker of ``marker_size_m``; ``"charuco"`` (or a
        ``CharucoBoardSpec``): a ChArUco board in its place (default 4 x 4 squares of 60 mm,
        ``marker_size_m`` and ``marker_border_m`` unused). ``params.json`` lists it only when
        it is not ``"aruco"``.
    shoulder_headroom : float
        ``SensorModel.shoulder_headroom``: close to 1, a harsh shoulder (a wide energy range
        in the last DN below the clip).
    sweep_stop : float or None
        The sweep's brightest pixel's share of the DN range in its *longest* exposure (the
        sweep ends there, sparse near it; below ~0.95 the flight can read DN above the sweep);
        None: ``sweep_start`` sets the exposures.
    n_reflector : int
        Reflector images.
    flight_exposure : tuple of float
        Range of the flight frames' brightest pixel's share of the DN range (auto exposure;
        near 1 the bright panel lies on the shoulder).

    The last four are listed in ``params.json`` only when not at their defaults (the
    sessions' files as before they existed).
    """

    seed: int = 0
    light_nonuniformity: float = 1.0
    light_gradient_deg: float | None = None
    read_noise_dn: float = 1.5
    shot_noise_dn_at_full: float = 9.0
    shoulder_start: float = 0.85
    curvature: float = 0.05
    marker_size_m: float = 0.10
    marker_border_m: float = 0.025
    distance_m: tuple[float, float] = (0.8, 1.6)
    max_tilt_deg: float = 35.0
    n_views: int = 40
    n_missing: int = 2
    n_partial: int = 0
    view_exposure: tuple[float, float] = (0.70, 0.85)
    sweep_frames: int = 14
    sweep_step: float = 1.66
    sweep_start: tuple[float, float] = (0.30, 0.40)
    vignetting_falloff: float = 0.37
    vignetting_shift_px: tuple[float, float] = (0.0, 0.0)
    marker: str | CharucoBoardSpec = "aruco"
    shoulder_headroom: float = 1.5
    sweep_stop: float | None = None
    n_reflector: int = 3
    flight_exposure: tuple[float, float] = (0.72, 0.82)


#: Fields of :class:`VariedParams` that ``params.json`` lists only away from their defaults.
_OPTIONAL = ("marker", "shoulder_headroom", "sweep_stop", "n_reflector", "flight_exposure")

#: Seed streams of :func:`harsh_params` (apart from those of :func:`draw_params`).
HARSH_SEED_BASE = 2000


def draw_params(seed: int) -> VariedParams:
    """Draw a varied parameter set for session ``seed`` (its own stream, ``SEED_BASE + seed``).

    Ranges, and why a field session shows them:

    - **Light**: ``light_nonuniformity`` 0.3-1.8 (gradient 1.2:1 to 3.5:1 across a 0.5 m
      reflector, shadow 12-70 % deep): from an overcast sky over a clean board to low sun with
      the operator's body or the tripod shading part of it; the gradient's direction uniform
      (the sun's azimuth relative to the reflector is arbitrary).
    - **Noise**: read 1.0-3.0 DN rms, shot 6-14 DN rms at full scale on the 10-bit sensor
      (full-well capacities of ~5-25 ke- for small-pixel CMOS; read noise of machine-vision
      sensors at unity gain up to a warmer sensor in the sun).
    - **Response**: shoulder from 0.74 to 0.92 of the DN range (a sensor with little headroom to
      one whose compression starts a quarter below the clip), curvature 0.02-0.10.
    - **Marker**: side 0.08-0.14 m with a 0.02-0.035 m paper border (what fits on an A4 sheet in
      the middle of the board).
    - **Viewpoints**: nearest distance 0.6-1.0 m and farthest 1.3-2.0 m (an arm's length to a
      step back), largest tilt 25-50 deg (hand-held views get oblique towards the image
      corners, where the planar pose becomes ambiguous), 2-4 views with the marker out of
      frame and 0-4 with the marker cut by the border (the operator sweeping the reflector to
      the image edges).
    - **Exposures**: views at 55-90 % of the range (auto exposure with another metering), the
      sweep's shortest frame at 20-45 % with a step of 1.5-1.9 (the sweep's span from 2.4 to 4.5
      decades over its 14 frames).
    - **Vignetting**: corner falloff from 25-45 % (a wide or a long lens), centres shifted by
      up to 12 x 6 band-grid pixels (a lens mounted off the sensor's centre).
    """
    rng = np.random.default_rng(SEED_BASE + int(seed))
    near = float(rng.uniform(0.6, 1.0))
    far = float(rng.uniform(1.3, 2.0))
    vx = float(rng.uniform(0.55, 0.75))
    sx = float(rng.uniform(0.20, 0.45))
    return VariedParams(
        seed=SEED_BASE + int(seed),
        light_nonuniformity=round(float(rng.uniform(0.3, 1.8)), 3),
        light_gradient_deg=round(float(rng.uniform(0.0, 360.0)), 1),
        read_noise_dn=round(float(rng.uniform(1.0, 3.0)), 2),
        shot_noise_dn_at_full=round(float(rng.uniform(6.0, 14.0)), 2),
        shoulder_start=round(float(rng.uniform(0.74, 0.92)), 3),
        curvature=round(float(rng.uniform(0.02, 0.10)), 3),
        marker_size_m=round(float(rng.uniform(0.08, 0.14)), 3),
        marker_border_m=round(float(rng.uniform(0.02, 0.035)), 3),
        distance_m=(round(near, 3), round(far, 3)),
        max_tilt_deg=round(float(rng.uniform(25.0, 50.0)), 1),
        n_missing=int(rng.integers(2, 5)),
        n_partial=int(rng.integers(0, 5)),
        view_exposure=(round(vx, 3), round(vx + 0.15, 3)),
        sweep_step=round(float(rng.uniform(1.5, 1.9)), 3),
        sweep_start=(round(sx, 3), round(sx + 0.1, 3)),
        vignetting_falloff=round(float(rng.uniform(0.25, 0.38)), 3),
        vignetting_shift_px=(round(float(rng.uniform(-12, 12)), 1), round(float(rng.uniform(-6, 6)), 1)),
    )


def harsh_params(seed: int, *, size: str = "small") -> VariedParams:
    """Draw a session whose response is hard to fit where the flight reads it: the settings of
    :func:`draw_params` with a harsh shoulder, a sweep that ends near or short of the top and
    flights exposed onto the shoulder.

    - **Shoulder**: starts at 0.85-0.95 of the DN range with a headroom of 1.002-1.05 (slope
      1/500 to 1/21 of the linear one at the clip): the last 5-15 % of the DN span an energy
      3-6 times their width, U at the clip 1.15-2.2 times U at the knee (a sensor whose full
      well compresses hard, or a sensor read through an in-camera knee).
    - **Sweep**: its longest exposure puts the brightest pixel at 0.88-0.995 of the range (an
      operator who stops the sweep before the clip): few samples, or none, on the shoulder.
    - **Flight**: brightest pixel at 0.96-0.99 (auto exposure metered on the dark crop), so the
      0.9 panel lies on the shoulder, or above the sweep.

    ``size="small"``: a 7-frame sweep in steps of 3, 8 views (1 without the marker), 2
    reflector images (``write_varied_session(..., n_flight_frames=3)`` for a small flight);
    ``"full"``: the sizes of :func:`draw_params`.
    """
    rng = np.random.default_rng(HARSH_SEED_BASE + int(seed))
    p = replace(draw_params(seed),
                shoulder_start=round(float(rng.uniform(0.85, 0.95)), 3),
                shoulder_headroom=round(float(rng.uniform(1.002, 1.05)), 4),
                sweep_stop=round(float(rng.uniform(0.88, 0.995)), 3),
                flight_exposure=(0.96, 0.99))
    if size == "small":
        p = replace(p, sweep_frames=7, sweep_step=3.0, n_views=8, n_missing=1, n_partial=0, n_reflector=2)
    elif size != "full":
        raise ValueError(f"size must be 'small' or 'full', got {size!r}")
    return p


def varied_truth(params: VariedParams) -> SyntheticTruth:
    """The camera truth of ``params``: its sensor (noise, response shape), marker and
    vignetting (no rendering)."""
    p = params
    sensor = SensorModel(read_noise_dn=p.read_noise_dn, shot_noise_dn_at_full=p.shot_noise_dn_at_full,
                         shoulder_start=p.shoulder_start, curvature=p.curvature,
                         shoulder_headroom=p.shoulder_headroom)
    board = session_marker(p.marker)
    marker = MarkerSpec(size_m=p.marker_size_m, border_m=p.marker_border_m) if board is None else board
    return make_truth(p.seed, sensor=sensor, marker=marker, vignetting_falloff=p.vignetting_falloff,
                      vignetting_shift_px=p.vignetting_shift_px)


def synthesize_varied(params: VariedParams, *, n_flight_frames: int = 8,
                      flight: str = "field") -> SyntheticSession:
    """Render a full-size session with ``params`` (no I/O): the truth and its four datasets,
    drawn as :func:`pipeline.sim.world.scene.synthesize_session` draws them."""
    p = params
    truth = varied_truth(p)
    gdir = None if p.light_gradient_deg is None else math.radians(p.light_gradient_deg)
    resp = response_sweep(truth, seed=p.seed, n_frames=p.sweep_frames, step=p.sweep_step,
                          start_fraction=p.sweep_start, stop_fraction=p.sweep_stop)
    vig = vignetting_views(truth, seed=p.seed, n_views=p.n_views, n_missing=p.n_missing,
                           n_partial=p.n_partial, max_tilt_deg=p.max_tilt_deg, distance_m=p.distance_m,
                           light_nonuniformity=p.light_nonuniformity, light_gradient_dir=gdir,
                           exposure_fraction=p.view_exposure)
    refl = reflector_images(truth, seed=p.seed, n_images=p.n_reflector, light_nonuniformity=p.light_nonuniformity,
                            light_gradient_dir=gdir, exposure_fraction=p.view_exposure)
    fl = {flight: flight_frames(truth, seed=p.seed, n_frames=n_flight_frames, name=flight,
                                exposure_fraction=p.flight_exposure)}
    return SyntheticSession(truth=truth, response=resp, vignetting=vig, reflector=refl, flights=fl,
                            size="full")


def write_varied_session(path: str | Path, params: VariedParams | int, *,
                         n_flight_frames: int = 8) -> Path:
    """Write a varied full-size session folder (``params``, or :func:`draw_params` of an int
    seed) with ``truth.npz`` and ``params.json``; returns its path."""
    p = draw_params(params) if isinstance(params, int) else params
    root = write_synthesized(synthesize_varied(p, n_flight_frames=n_flight_frames), Path(path))
    (root / "params.json").write_text(json.dumps(params_record(p), indent=1) + "\n")
    return root


def params_record(params: VariedParams) -> dict:
    """``params.json`` of a varied session: the fields of ``params``, those of ``_OPTIONAL``
    (``marker``, ...) only away from their defaults (the files as before the fields existed)."""
    record = asdict(params)
    defaults = {f.name: f.default for f in fields(VariedParams)}
    for name in _OPTIONAL:
        if getattr(params, name) == defaults[name]:
            del record[name]
    return record
