"""How far U can be trusted at each DN: its relative standard uncertainty over the fitted DN range."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._curve import Curve, ramp_basis


def response_uncertainty(
    inverse_response: np.ndarray,
    black_level: float,
    noise_variance: tuple[float, float],
    dn_range: tuple[int, int],
    fit_std: np.ndarray | None = None,
) -> np.ndarray:
    """Return U's relative standard uncertainty at every DN.

    Two parts combined in quadrature, each relative to ``U(k)``:

    - the DN noise of one reading through the slope of U, ``U'(k) sigma_I(k) / U(k)``, with
      ``sigma_I(k)^2 = a + b (k - black)`` the fit's read + shot noise model;
    - how well the sweep determines U at ``k``, ``fit_std[k]`` (e.g. the linearised standard
      deviation of ``log U(k)`` of the fit, large where few samples reach, such as near the top).

    Parameters
    ----------
    inverse_response : numpy.ndarray
        U on every DN, ``(2**bits,)``, monotone.
    black_level : float
        DN where U = 0.
    noise_variance : tuple of float
        ``(a, b)`` of the DN noise variance ``a + b (k - black)`` (DN^2, DN^2 per DN).
    dn_range : tuple of int
        Lowest and highest DN the fit had data for.
    fit_std : numpy.ndarray, optional
        ``(2**bits,)`` relative standard uncertainty of U from the fit itself (0 if None).

    Returns
    -------
    numpy.ndarray
        ``(2**bits,)`` float64: a fraction of ``U(k)``; NaN outside ``dn_range``, ``inf`` inside
        it where ``U(k) = 0`` (at or below black: no relative uncertainty is defined) and where
        the noise's reach ``k + sigma_I(k)`` passes the top of ``dn_range`` (U not determined).

    Raises
    ------
    InputError
        On a ``fit_std`` of another length than U, a negative noise variance or a
        ``dn_range`` outside ``0 .. len(U) - 1`` or reversed.

    Notes
    -----
    Eq. 4 linearises a reading ``I`` as ``U(I) = t E``; a reading's noise ``sigma_I`` moves it
    by ``U'(I) sigma_I`` (first order), and the fit of U by Eq. 5 [1]_ is itself uncertain by
    ``fit_std``. ``U'(k)`` is the difference quotient of U (linearly interpolated) over
    ``k +- sigma_I(k)`` (clipped to the table): the derivative where U is smooth on the scale of
    the noise, and a step or plateau of U within the noise's reach is not missed.

    Where ``k + sigma_I(k)`` passes the top ``h`` of ``dn_range`` the data do not determine U at
    ``k``: a reading there is the DN of energies up to beyond those the sweep reached, and the
    sweep's own samples near ``h`` (blurred by the same noise) constrain C there from below
    only, so a shoulder that steepens within ``sigma_I`` of ``h`` is not resolved (on harsh
    shoulders U there was 3-10 % off while ``U' sigma_I / U`` said 1.5-2.4 %). The
    uncertainty is ``inf`` there, not a number that would understate it.

    References
    ----------
    .. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
           for Multispectral Cameras", IEEE International Conference on Robotics and
           Automation (ICRA), 2017.
    """
    U = np.asarray(inverse_response, dtype=np.float64)
    n = U.size
    lo, hi = int(dn_range[0]), int(dn_range[1])
    if not 0 <= lo <= hi < n:
        raise InputError(f"dn_range must satisfy 0 <= low <= high < {n}, got {dn_range}")
    a, b = float(noise_variance[0]), float(noise_variance[1])
    if not (a >= 0 and b >= 0):
        raise InputError(f"noise variance terms must be >= 0, got a={a:g}, b={b:g}")
    fs = np.zeros(n) if fit_std is None else np.asarray(fit_std, dtype=np.float64)
    if fs.shape != (n,):
        raise InputError(f"fit_std must have the length of U ({n}), got shape {fs.shape}")
    k = np.arange(n, dtype=np.float64)
    sigma = np.sqrt(a + b * np.maximum(k - black_level, 0.0))
    # U' over the noise's own span: a step or a plateau of U within +-sigma counts
    k_lo, k_hi = np.maximum(k - sigma, 0.0), np.minimum(k + sigma, n - 1.0)
    span = np.maximum(k_hi - k_lo, 1e-12)
    slope = (np.interp(k_hi, k, U) - np.interp(k_lo, k, U)) / span
    with np.errstate(divide="ignore", invalid="ignore"):
        noise_rel = slope * sigma / U
    out = np.sqrt(noise_rel**2 + fs**2)
    out[U <= 0] = np.inf
    out[k + sigma > hi] = np.inf  # the noise's reach passes the data's top: U not determined
    out[:lo] = np.nan
    out[hi + 1:] = np.nan
    return out


def fit_log_std(curve: Curve, info: np.ndarray, dn: np.ndarray, k_ref: int) -> np.ndarray:
    """Return the standard deviation of ``log U(k)`` at the DN ``dn`` from C's information matrix.

    In the package's gauge ``U(k) = (k_ref - C(0)) x_k / x_ref`` with ``x_k = C^{-1}(k)``;
    to first order ``d x_k = -phi(x_k)' d theta / C'(x_k)`` (:func:`ramp_basis`), so
    ``d log U(k) = g_k' d theta``,
    ``g_k = -phi(x_k) / (C'(x_k) x_k) + phi(x_ref) / (C'(x_ref) x_ref) - e_0 / (k_ref - C(0))``,
    and ``var = g_k' info^+ g_k``. NaN where ``x_k <= 0`` (at or below black).
    """
    dn = np.asarray(dn, dtype=np.float64)
    x = curve.inverse(np.concatenate([dn, [float(k_ref)]]))
    _, s = curve(x)
    black = float(curve.c[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        g = ramp_basis(x, curve.xk) / (s * x)[:, None]
    g = g[:-1] - g[-1]  # -g_k (the sign does not change the variance)
    g[:, 0] += 1.0 / max(k_ref - black, 1e-9)
    cov = np.linalg.pinv(info, hermitian=True, rcond=1e-13)
    var = ((g @ cov) * g).sum(axis=1)
    out = np.sqrt(np.maximum(var, 0.0))
    out[~(x[:-1] > 0)] = np.nan
    return out
