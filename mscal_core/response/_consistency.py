"""Consistency of a sweep: frames whose brightness contradicts their exposure, and the checks run before a fit."""

from __future__ import annotations

import numpy as np

from ..errors import FitError
from ._common import pava, validate_samples

#: Frames larger than this are subsampled (evenly strided) for the per-frame median of
#: :func:`check_exposure_consistency`.
_MEDIAN_PIXELS = 1 << 18


def check_exposure_consistency(dn: np.ndarray, exposure: np.ndarray, bits: int) -> list[int]:
    """Find the frames whose brightness contradicts their exposure.

    Parameters
    ----------
    dn : numpy.ndarray
        ``(n_frames, n_pixels)`` integer samples of a static scene.
    exposure : numpy.ndarray
        ``(n_frames,)`` effective exposures, positive.
    bits : int
        Bit depth of the camera.

    Returns
    -------
    list of int
        Indices of the removed frames, sorted (empty for a consistent sweep).

    Raises
    ------
    InputError
        On bad shapes, non-positive exposures or DN outside the bit depth.

    Notes
    -----
    For every pair of frames with exposures ``t_a >= 1.25 t_b`` the longer frame must not be
    darker: its median DN may not fall below the shorter one's by more than
    ``max(1, 0.5 % of dn_max)``. Offending frames are removed greedily (the frame in most
    contradictions first; ties go to the frame farthest from a monotone fit of median DN on
    exposure) until none is left. The response fit (Eq. 5-7 of [1]_) assumes a static scene
    under constant light; a frame that breaks this would bend U.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    dn, t = validate_samples(dn, exposure, bits)
    dn_max = 2**bits - 1
    med = _frame_medians(dn)
    tol = max(1.0, 0.005 * dn_max)
    longer = t[:, None] >= 1.25 * t[None, :]  # [a, b]: a clearly longer than b
    bad = longer & (med[:, None] < med[None, :] - tol)
    order = np.argsort(t, kind="stable")
    alive = np.ones(t.size, dtype=bool)
    removed: list[int] = []
    while True:
        live = bad & alive[:, None] & alive[None, :]
        counts = live.sum(axis=0) + live.sum(axis=1)
        if counts.max() == 0:
            return sorted(removed)
        idx = order[alive[order]]
        fitted = np.empty(t.size)
        fitted[idx] = pava(med[idx], np.ones(idx.size))
        dev = np.abs(med - fitted)
        cand = np.flatnonzero(counts == counts.max())
        worst = int(cand[np.argmax(dev[cand])])
        alive[worst] = False
        removed.append(worst)


def _frame_medians(dn: np.ndarray) -> np.ndarray:
    """Median DN of every frame.

    On an evenly strided subsample of at most about ``_MEDIAN_PIXELS`` pixels for large frames
    (no sorted copy of a whole band).
    """
    step = max(1, -(-dn.shape[1] // _MEDIAN_PIXELS))
    return np.median(dn[:, ::step], axis=1).astype(np.float64)


def check_sweep(d: np.ndarray, t: np.ndarray, bits: int) -> None:
    n_t = np.unique(t).size
    if n_t < 2:
        raise FitError(
            f"the sweep has {n_t} distinct exposure(s); the response fit needs at least 2",
            hint="capture the static scene at several exposure times",
        )
    bad = check_exposure_consistency(d, t, bits)
    if bad:
        names = ", ".join(f"frame {i} (exposure {t[i]:g})" for i in bad)
        raise FitError(
            f"brightness contradicts exposure for {names}",
            hint="fix their exposure times or drop frames taken while the scene or light changed",
        )
