"""The sweep's fits started ahead (pipeline.calibrate.sweep), as ``mscal calibrate`` does."""

from __future__ import annotations

import numpy as np

from pipeline.calibrate.pool import BandPool
from pipeline.calibrate.response_stage import fit_response_frames
from pipeline.calibrate.sweep import start_sweep
from pipeline.ingest.session import load_session


def test_fits_started_ahead_are_the_fits(small) -> None:
    session_dir, _ = small
    session = load_session(session_dir)
    with BandPool(1) as pool:
        plain, plain_rep = fit_response_frames(session.response_dir, session.camera, "forward", session.root, pool)
        sweep = start_sweep(session_dir, "forward", pool)
        assert sweep.is_for(session.response_dir, "forward")
        assert len(sweep.futures) == session.camera.n_bands and all(f.done() for f in sweep.futures)
        ahead, ahead_rep = fit_response_frames(session.response_dir, session.camera, "forward", session.root, pool,
                                               sweep)
    for a, b in zip(plain, ahead):
        np.testing.assert_array_equal(a.inverse_response, b.inverse_response)
    assert ahead_rep.inputs == plain_rep.inputs and ahead_rep.residuals == plain_rep.residuals
    assert ahead_rep.seconds > 0


def test_fits_started_for_another_method_are_not_used(small) -> None:
    """A sweep submitted with one estimator never stands in for another: the stage fits again."""
    session_dir, _ = small
    session = load_session(session_dir)
    with BandPool(1) as pool:
        forward = start_sweep(session_dir, "forward", pool)
        assert not forward.is_for(session.response_dir, "alternating")
        assert not forward.is_for(session.reflector_dir, "forward")
        fits, report = fit_response_frames(session.response_dir, session.camera, "alternating", session.root, pool,
                                           forward)
    assert report.residuals["method"] == "alternating"
    assert {f.method for f in fits} == {"alternating"}
