"""Error measures of a calibration against a known truth (synthetic sessions, benchmarks).

Pure functions; each states the gauge alignment it applies, because U, V and S are each only
known up to a scale (Eq. 5, 8 and 12 are invariant to it).
"""

from __future__ import annotations

import numpy as np


def response_error(u_est: np.ndarray, u_true: np.ndarray, lo_frac: float = 0.05, hi_frac: float = 0.95) -> float:
    """Return the worst error of an estimated U against the truth, relative to ``U_true(hi)``.

    Parameters
    ----------
    u_est, u_true : numpy.ndarray
        U on every DN, same length.
    lo_frac, hi_frac : float
        The DN range ``[lo, hi]`` compared, as fractions of ``dn_max``.

    Returns
    -------
    float
        Max ``|s U_est(k) - U_true(k)|`` over ``k`` in ``[lo, hi]``, divided by ``U_true(hi)``;
        ``s`` is the least-squares scale aligning the two over that range (U is known up to a
        scale: Eq. 5 is invariant to it).

    Notes
    -----
    ``s = sum U_est U_true / sum U_est^2`` over ``[lo, hi]``: the scale of Eq. 5-7 of [1]_ fixed
    the way the truth fixes it.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    n = u_true.shape[-1]
    dn_max = n - 1
    k = np.arange(int(np.ceil(lo_frac * dn_max)), int(np.floor(hi_frac * dn_max)) + 1)
    a, b = np.asarray(u_est, float)[k], np.asarray(u_true, float)[k]
    s = float(a @ b / (a @ a)) if a @ a > 0 else 1.0
    return float(np.max(np.abs(s * a - b)) / b[-1])


def vignetting_rms(v_est: np.ndarray, v_true: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Return the RMS of ``V_est / V_true - 1`` over ``mask``.

    Parameters
    ----------
    v_est, v_true : numpy.ndarray
        V of one band, both max-1 normalised (no extra alignment).
    mask : numpy.ndarray, optional
        Pixels compared (default all).

    Returns
    -------
    float
        The relative RMS error.

    Notes
    -----
    ``sqrt(mean((V_est / V_true - 1)^2))`` over the finite ratios of ``mask``; both ``V`` carry the
    max-1 scale of Eq. 8-10 of [1]_.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    r = np.asarray(v_est, float) / np.asarray(v_true, float) - 1.0
    if mask is not None:
        r = r[mask]
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r**2)))


def spectral_factor_error(s_est: np.ndarray, s_true: np.ndarray) -> float:
    """Return the max relative error of ``S`` after the least-squares scale alignment.

    Parameters
    ----------
    s_est, s_true : numpy.ndarray
        (n_bands,) spectral factors; S is relative (Eq. 12 is invariant to a common scale).

    Returns
    -------
    float
        Max over bands of ``|a S_est / S_true - 1|``, ``a`` the least-squares scale.

    Notes
    -----
    ``a = sum S_est S_true / sum S_est^2``: ``S`` of Eq. 12-13 of [1]_ is known up to a common
    scale (it trades with ``B``).

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    a, b = np.asarray(s_est, float), np.asarray(s_true, float)
    s = float(a @ b / (a @ a))
    return float(np.max(np.abs(s * a / b - 1.0)))


def coefficient_of_variation(values: np.ndarray) -> float:
    """Return ``std / mean`` of the finite values (population std).

    Parameters
    ----------
    values : numpy.ndarray
        Any shape; non-finite entries are ignored.

    Returns
    -------
    float
        The coefficient of variation.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.std(v) / np.mean(v))
