"""The varied-session generator (pipeline.sim.varied): each parameter changes what it claims,
and the benchmark's generator (write_session) is unchanged by it."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.sim.synth import write_session
from pipeline.sim.varied import VariedParams, draw_params, varied_truth, write_varied_session
from pipeline.sim.world.scene import GradientShadowLight, detect_marker_corners, vignetting_views

#: sha256 over the relative paths and bytes of every file of ``write_session(seed=0,
#: size="small")``, taken before the generator's parameters were threaded through the forward
#: model: the benchmark's sessions must stay byte-identical.
SMALL_SEED0_SHA256 = "23a1c06eafc1b993484d30a9fea3023eab608b79d14ba2cf53274e7fcec0e6ff"


def folder_sha256(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_write_session_is_byte_identical_to_before(tmp_path) -> None:
    session = write_session(tmp_path / "small", seed=0, size="small")
    assert folder_sha256(session) == SMALL_SEED0_SHA256


def test_draw_params_is_seeded_and_within_its_ranges() -> None:
    assert draw_params(3) == draw_params(3)
    drawn = [draw_params(s) for s in range(40)]
    assert len({p.light_nonuniformity for p in drawn}) == 40
    assert len({p.seed for p in drawn}) == 40 and min(p.seed for p in drawn) >= 1000  # not a benchmark seed
    for p in drawn:
        assert 0.3 <= p.light_nonuniformity <= 1.8 and 0.0 <= p.light_gradient_deg < 360.0
        assert 1.0 <= p.read_noise_dn <= 3.0 and 6.0 <= p.shot_noise_dn_at_full <= 14.0
        assert 0.74 <= p.shoulder_start <= 0.92 and 0.02 <= p.curvature <= 0.10
        assert 0.08 <= p.marker_size_m <= 0.14 and 0.02 <= p.marker_border_m <= 0.035
        assert 0.6 <= p.distance_m[0] <= 1.0 and 1.3 <= p.distance_m[1] <= 2.0
        assert 25.0 <= p.max_tilt_deg <= 50.0
        assert 2 <= p.n_missing <= 4 and 0 <= p.n_partial <= 4
        assert 1.5 <= p.sweep_step <= 1.9 and p.sweep_frames == 14 and p.n_views == 40
        assert 0.25 <= p.vignetting_falloff <= 0.38
    assert any(p.n_partial > 0 for p in drawn) and any(p.n_partial == 0 for p in drawn)


def test_stronger_shoulder_flattens_the_response_near_the_clip() -> None:
    """A shoulder starting lower compresses the response near the clip: the forward response's
    slope at 950-1000 DN falls, so the inverse response U rises more steeply there (dU/dI =
    1 / C'), while below the shoulder both are the same near-linear curve."""
    soft, strong = (varied_truth(VariedParams(shoulder_start=s)) for s in (0.92, 0.74))
    dn = np.arange(950, 1001)
    u_slope, c_slope = {}, {}
    for name, t in (("soft", soft), ("strong", strong)):
        u_slope[name] = float(np.mean(np.diff(t.inverse_response[0][dn])))  # U per DN near the clip
        x = t.sensor.x_for_dn(np.array([950.0, 1000.0]))
        c_slope[name] = 50.0 / float(x[1] - x[0])  # the forward response's DN per unit of energy
    # about 1.45 and 2.27 U per DN: U rises ~1.6x as steeply; the response is ~1.6x as flat
    assert u_slope["soft"] == pytest.approx(1.45, abs=0.05)
    assert u_slope["strong"] > 1.5 * u_slope["soft"]
    assert c_slope["strong"] < c_slope["soft"] / 1.5
    # below both shoulders the curves are the same within the curvature's few per cent
    mid = np.arange(200, 600)
    du_soft = np.diff(soft.inverse_response[0][mid]).mean()
    du_strong = np.diff(strong.inverse_response[0][mid]).mean()
    assert du_strong == pytest.approx(du_soft, rel=0.02)


def test_vignetting_strength_and_centre_shift() -> None:
    base = varied_truth(VariedParams(seed=5))
    weak = varied_truth(VariedParams(seed=5, vignetting_falloff=0.25))
    shifted = varied_truth(VariedParams(seed=5, vignetting_shift_px=(10.0, -5.0)))
    corners = (slice(None), [0, 0, -1, -1], [0, -1, 0, -1])
    # mean corner falloff: 37-44 % by default, 25-32 % with the weaker vignetting
    assert 1 - base.vignetting[corners].mean() == pytest.approx(0.40, abs=0.035)
    assert 1 - weak.vignetting[corners].mean() == pytest.approx(0.285, abs=0.035)
    np.testing.assert_allclose(shifted.vignetting_centre - base.vignetting_centre,
                               np.tile([10.0, -5.0], (25, 1)), atol=1e-12)


def test_noise_and_marker_reach_the_truth() -> None:
    t = varied_truth(VariedParams(read_noise_dn=2.5, shot_noise_dn_at_full=13.0, marker_size_m=0.12,
                                  marker_border_m=0.03))
    assert t.sensor.noise_variance(np.array([t.black_level]))[0] == pytest.approx(2.5**2)
    assert t.sensor.noise_variance(np.array([float(t.dn_max)]))[0] == pytest.approx(2.5**2 + 13.0**2)
    assert (t.marker.size_m, t.marker.border_m) == (0.12, 0.03)


def test_light_unevenness_and_direction() -> None:
    """The light of the views: a gradient of 2**a : 1 along the direction asked for, and a
    deeper shadow with a larger ``a``."""
    p = VariedParams(seed=4, light_gradient_deg=120.0)
    truth = varied_truth(p)
    lights = {}
    for a in (0.5, 1.5):
        fs = vignetting_views(truth, seed=p.seed, n_views=1, n_missing=0, light_nonuniformity=a,
                              light_gradient_dir=np.radians(120.0), supersample=1)
        lights[a] = GradientShadowLight.from_params(fs.truth["light"])
    for a, light in lights.items():
        assert light.gradient_ratio == pytest.approx(2.0**a)
        assert light.gradient_dir == pytest.approx(np.radians(120.0))
        c, sn = np.cos(light.gradient_dir), np.sin(light.gradient_dir)
        half = 0.5 * light.extent_m[0] * abs(c) + 0.5 * light.extent_m[1] * abs(sn)  # to the corners
        g = light.gradient(np.array([-half, half]) * c, np.array([-half, half]) * sn)
        assert g[1] / g[0] == pytest.approx(2.0**a, rel=1e-9)
    assert lights[1.5].shadow_depth > lights[0.5].shadow_depth + 0.2


def test_views_with_the_marker_cut_by_the_border(tmp_path) -> None:
    """``n_partial`` views show part of the reflector with the marker cut by the frame's border:
    one to three of its corners in frame, and ArUco does not find it."""
    truth = varied_truth(VariedParams(seed=2))
    fs = vignetting_views(truth, seed=1002, n_views=6, n_missing=1, n_partial=2, supersample=1)
    cut = fs.truth["marker_partial"]
    assert cut.tolist() == [False, True, True, False, False, False]
    assert not fs.truth["marker_in_frame"][cut].any()
    cam, mk = truth.camera, truth.marker
    h, w = cam.grid_shape
    s = 0.5 * mk.size_m
    square = np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]])
    for k in np.flatnonzero(cut):
        R = cv2.Rodrigues(fs.truth["rvec"][k])[0]
        px = cam.project(square @ R.T + fs.truth["tvec"][k])
        inside = (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
        assert 1 <= inside.sum() <= 3
        assert fs.truth["gray_mask"][k].mean() >= 0.03  # the reflector is partly in view
        assert detect_marker_corners(fs.dn[k][0], mk) is None
    full = np.flatnonzero(fs.truth["marker_in_frame"])
    assert full.size == 3 and all(detect_marker_corners(fs.dn[k][0], mk) is not None for k in full)


@pytest.mark.long  # a full-size varied session written, calibrated and scored, ~55 s: make test-long
def test_a_varied_session_is_written_and_scored(tmp_path) -> None:
    """A full-size varied session: params.json, truth.npz, and the evaluation of a calibration
    of it (``mscal calibrate``) gives every figure."""
    from pipeline.run.cli import main
    from pipeline.sim.evaluate import evaluate_calibration

    p = replace(draw_params(0), n_partial=1)
    session = write_varied_session(tmp_path / "v", p)
    assert json.loads((session / "params.json").read_text())["n_partial"] == 1
    assert len(list((session / "vignetting").glob("*.tif"))) == 40
    calib = tmp_path / "cal.zarr"
    assert main(["calibrate", str(session), "-o", str(calib), "-q"]) == 0
    ev = evaluate_calibration(session, calib)
    assert ev["response_max_error"] < 0.02
    assert ev["vignetting_rms_error"] < 0.015
    assert ev["spectral_factor_max_error"] < 0.01
    assert np.isfinite(ev["flight_field"]["eq15"]["panel_abs_error"])
