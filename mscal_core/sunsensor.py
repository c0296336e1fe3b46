"""Sun sensors: from a tilted sensor's reading to the horizontal irradiance on the ground.

A downwelling light sensor on a drone (MicaSense DLS, Parrot's sunshine sensor, DJI's and
Sentera's) faces up through a diffuser, tilted with the aircraft. Its reading mixes the
direct sunlight, seen at the angle ``theta`` between the sun and the sensor's normal, with
the diffuse skylight. Reflectance needs the irradiance on the horizontal ground instead
(``rho = pi L / E_h``, or, relative, the change of ``E_h`` between a panel and a frame).

Model (isotropic sky, the convention of MicaSense's DLS documentation and of pvlib's
``isotropic`` transposition)::

    E_meas = tau(theta) cos(theta)^+ E_dir + tau_d (1 + cos(tilt)) / 2 * E_dif
    E_h    = E_dir sin(el) + E_dif,          E_dif = r E_dir

``E_dir`` is the direct irradiance on a plane facing the sun, ``E_dif`` the diffuse
irradiance on a horizontal plane, ``r`` their ratio (about 1/6 under a clear sky; near 1 under
thin cloud; measured by a DLS 2 as ScatteredIrradiance / DirectIrradiance), ``tau`` the
diffuser's transmission relative to normal incidence (Fresnel, unpolarised light through air,
polycarbonate and PTFE layers), ``tau_d`` its cosine-weighted mean over the sky hemisphere.
Hence ``E_h = E_meas (sin(el) + r) / (tau cos(theta)^+ + r tau_d (1 + cos tilt) / 2)``.

Angles: the sun by elevation ``el`` and azimuth (clockwise from north) in radians, the sensor
by yaw, pitch, roll (radians, rotation order ZYX from the body frame to North-East-Down, the
convention of MicaSense's DLS, DJI's gimbal and the aerospace norm); the sensor looks along
the body's -z (up when level).

References
----------
MicaSense, "Reading DLS Irradiance Metadata" and the DLS model of micasense/imageprocessing
(``dls.py``: sensor normal, diffuse ratio 6:1 for a clear sky). Hecht, *Optics*, Fresnel
equations. Holmgren, Hansen, Mikofski (2018), pvlib python, the isotropic sky model.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Refractive indices of the layers light crosses into a DLS-style diffuser: air,
#: polycarbonate dome, PTFE diffuser.
DIFFUSER_LAYERS = (1.000277, 1.586, 1.35)
#: Diffuse / direct ratio of a clear sky (MicaSense's DLS 1 assumption, 6:1).
CLEAR_SKY_DIFFUSE_RATIO = 1.0 / 6.0

FloatArray = NDArray[np.float64]


def sun_vector(elevation: ArrayLike, azimuth: ArrayLike) -> FloatArray:
    """Return the unit vector towards the sun in North-East-Down coordinates.

    Parameters
    ----------
    elevation, azimuth : array_like
        Solar elevation above the horizon and azimuth clockwise from north, radians.

    Returns
    -------
    ndarray, shape (..., 3)
        ``(cos az cos el, sin az cos el, -sin el)``: its down component is negative when the
        sun is up.
    """
    el = np.asarray(elevation, np.float64)
    az = np.asarray(azimuth, np.float64)
    return np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), -np.sin(el)], axis=-1)


def sensor_normal(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> FloatArray:
    """Return the sensor's viewing direction in North-East-Down coordinates.

    Parameters
    ----------
    yaw, pitch, roll : array_like
        Orientation of the body, radians, rotation order Z (yaw), Y (pitch), X (roll).

    Returns
    -------
    ndarray, shape (..., 3)
        ``R_z(yaw) R_y(pitch) R_x(roll) (0, 0, -1)``: straight up, ``(0, 0, -1)``, when level.
    """
    y, p, r = (np.asarray(a, np.float64) for a in (yaw, pitch, roll))
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    return -np.stack([cy * sp * cr + sy * sr, sy * sp * cr - cy * sr, cp * cr], axis=-1)


def incidence_angle(sun: ArrayLike, normal: ArrayLike) -> FloatArray:
    """Return the angle between the sun and the sensor's normal, radians, in ``[0, pi]``.

    Parameters
    ----------
    sun : array_like, shape (..., 3)
        Unit vector towards the sun (:func:`sun_vector`).
    normal : array_like, shape (..., 3)
        Unit normal of the sensor (:func:`sensor_normal`).

    Returns
    -------
    ndarray
        ``theta = arccos(sun . normal)`` (the dot product clipped to [-1, 1]).
    """
    c = np.sum(np.asarray(sun, np.float64) * np.asarray(normal, np.float64), axis=-1)
    return np.arccos(np.clip(c, -1.0, 1.0))


def tilt_angle(normal: ArrayLike) -> FloatArray:
    """Return the angle between the sensor's normal and straight up, radians.

    Parameters
    ----------
    normal : array_like, shape (..., 3)
        Unit normal of the sensor in North-East-Down (:func:`sensor_normal`).

    Returns
    -------
    ndarray
        ``arccos(-n_down)`` in ``[0, pi]``: 0 when level.
    """
    return np.arccos(np.clip(-np.asarray(normal, np.float64)[..., 2], -1.0, 1.0))


def fresnel_transmission(theta: ArrayLike, layers: tuple[float, ...] = DIFFUSER_LAYERS) -> FloatArray:
    """Return the fraction of unpolarised light that crosses a stack of plane interfaces.

    Parameters
    ----------
    theta : array_like
        Angle of incidence on the first interface, radians (0 at normal incidence).
    layers : tuple of float
        Refractive indices from outside in.

    Returns
    -------
    ndarray
        ``prod_i (1 - (R_s,i + R_p,i) / 2)`` with the Fresnel reflectances of each interface
        and the angle carried from one layer into the next by Snell's law; 0 at and beyond
        grazing incidence.

    Notes
    -----
    ``R_s = ((n1 cos a - n2 cos b) / (n1 cos a + n2 cos b))^2``,
    ``R_p = ((n1 cos b - n2 cos a) / (n1 cos b + n2 cos a))^2``, ``n1 sin a = n2 sin b``.

    References
    ----------
    E. Hecht, *Optics*: the Fresnel equations.
    """
    a = np.clip(np.abs(np.asarray(theta, np.float64)), 0.0, np.pi / 2)
    t = np.ones_like(a)
    for n1, n2 in zip(layers[:-1], layers[1:]):
        sb = n1 / n2 * np.sin(a)
        ok = sb < 1.0
        b = np.arcsin(np.where(ok, sb, 1.0))
        ca, cb = np.cos(a), np.cos(b)
        with np.errstate(divide="ignore", invalid="ignore"):
            rs = ((n1 * ca - n2 * cb) / (n1 * ca + n2 * cb)) ** 2
            rp = ((n1 * cb - n2 * ca) / (n1 * cb + n2 * ca)) ** 2
        t = t * np.where(ok & (ca > 0), 1.0 - 0.5 * (rs + rp), 0.0)
        a = b
    return np.nan_to_num(t, nan=0.0)


def relative_transmission(theta: ArrayLike, layers: tuple[float, ...] = DIFFUSER_LAYERS) -> FloatArray:
    """Return ``tau(theta) = T(theta) / T(0)``, the diffuser's angular response (1 at normal incidence).

    Parameters
    ----------
    theta : array_like
        Angle of incidence, radians.
    layers : tuple of float
        Refractive indices from outside in (:func:`fresnel_transmission`).

    Returns
    -------
    ndarray
        ``tau(theta)``, 0 at and beyond grazing incidence.
    """
    return fresnel_transmission(theta, layers) / fresnel_transmission(0.0, layers)


def diffuse_transmission(layers: tuple[float, ...] = DIFFUSER_LAYERS, n: int = 2048) -> float:
    """Return ``tau_d``, the diffuser's response to isotropic light.

    Parameters
    ----------
    layers : tuple of float
        Refractive indices from outside in.
    n : int
        Steps of the midpoint rule over ``[0, pi / 2]``.

    Returns
    -------
    float
        ``tau_d = 2 int_0^(pi/2) tau(theta) cos(theta) sin(theta) dtheta``.

    Notes
    -----
    :func:`relative_transmission` averaged over the hemisphere, weighted by ``cos(theta)``.
    Computed once per ``(layers, n)``: every :func:`horizontal_irradiance` needs it, and
    :func:`fit_diffuse_ratio` calls that 82 times per band (0.14 s of a factory apply's five
    bands otherwise).
    """
    return _diffuse_transmission(tuple(float(v) for v in layers), int(n))


@lru_cache(maxsize=32)
def _diffuse_transmission(layers: tuple[float, ...], n: int) -> float:
    h = (np.pi / 2) / n
    th = (np.arange(n) + 0.5) * h
    return float(2.0 * np.sum(relative_transmission(th, layers) * np.cos(th) * np.sin(th)) * h)


@dataclass(frozen=True)
class HorizontalIrradiance:
    """Result of :func:`horizontal_irradiance`; arrays broadcast like the readings.

    Attributes: ``horizontal`` E_h; ``direct`` E_dir (on a plane facing the sun); ``diffuse`` E_dif
    (horizontal); ``factor`` E_h / E_meas; ``incidence`` theta and ``tilt`` of the sensor,
    radians; ``sun_visible`` whether the sun was above the sensor's horizon (cos theta > 0).
    """

    horizontal: FloatArray
    direct: FloatArray
    diffuse: FloatArray
    factor: FloatArray
    incidence: FloatArray
    tilt: FloatArray
    sun_visible: NDArray[np.bool_]


def horizontal_irradiance(reading: ArrayLike, elevation: ArrayLike, azimuth: ArrayLike, yaw: ArrayLike,
                          pitch: ArrayLike, roll: ArrayLike,
                          diffuse_ratio: ArrayLike = CLEAR_SKY_DIFFUSE_RATIO,
                          layers: tuple[float, ...] = DIFFUSER_LAYERS) -> HorizontalIrradiance:
    """Return the horizontal irradiance from a tilted sun sensor's reading (module docstring).

    Parameters
    ----------
    reading : array_like
        The sensor's reading ``E_meas`` (any unit; the result has the same).
    elevation, azimuth : array_like
        The sun's position, radians (azimuth clockwise from north).
    yaw, pitch, roll : array_like
        The sensor's orientation, radians, ZYX to North-East-Down.
    diffuse_ratio : array_like
        ``r = E_dif / E_dir``: measured (a DLS 2's Scattered / Direct), or
        :data:`CLEAR_SKY_DIFFUSE_RATIO`.
    layers : tuple of float
        Refractive indices of the diffuser's layers.

    Returns
    -------
    HorizontalIrradiance
        ``E_h``, ``E_dir``, ``E_dif``, ``E_h / E_meas``, the incidence and tilt angles and
        whether the sun was above the sensor's horizon.

    Notes
    -----
    ``E_h = E_meas (sin el + r) / (tau(theta) max(cos theta, 0) + r tau_d (1 + cos tilt) / 2)``.
    With the sun behind the sensor only the diffuse light reaches it and ``E_h`` rests on
    ``r`` alone: such readings are flagged (``sun_visible`` False) for the caller to weigh.

    References
    ----------
    MicaSense, "Reading DLS Irradiance Metadata" and the DLS model of
    ``micasense/imageprocessing`` (``dls.py``).
    W. F. Holmgren, C. W. Hansen and M. A. Mikofski, "pvlib python: a python package for
    modeling solar energy systems", Journal of Open Source Software 3(29), 2018 (the isotropic
    sky model).
    """
    e = np.asarray(reading, np.float64)
    r = np.asarray(diffuse_ratio, np.float64)
    el = np.asarray(elevation, np.float64)
    n = sensor_normal(yaw, pitch, roll)
    theta = incidence_angle(sun_vector(el, azimuth), n)
    tilt = tilt_angle(n)
    cos_t = np.cos(theta)
    denom = relative_transmission(theta, layers) * np.maximum(cos_t, 0.0) + r * diffuse_transmission(layers) * (1.0 + np.cos(tilt)) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = np.where(denom > 0, e / denom, np.nan)
    diffuse = r * direct
    horizontal = direct * np.maximum(np.sin(el), 0.0) + diffuse
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(e != 0, horizontal / e, np.nan)
    return HorizontalIrradiance(horizontal, direct, diffuse, factor, theta, tilt, cos_t > 0)


def sensor_reading(direct: ArrayLike, diffuse: ArrayLike, elevation: ArrayLike, azimuth: ArrayLike, yaw: ArrayLike,
                   pitch: ArrayLike, roll: ArrayLike, layers: tuple[float, ...] = DIFFUSER_LAYERS) -> FloatArray:
    """Return what a tilted sensor reads: the forward model of :func:`horizontal_irradiance`.

    Used to simulate sun sensors with known truth; :func:`horizontal_irradiance` with
    ``diffuse_ratio = diffuse / direct`` inverts it.

    Parameters
    ----------
    direct : array_like
        ``E_dir``, direct light on a plane facing the sun.
    diffuse : array_like
        ``E_dif``, isotropic diffuse light on a horizontal plane.
    elevation, azimuth : array_like
        The sun's position, radians (azimuth clockwise from north).
    yaw, pitch, roll : array_like
        The sensor's orientation, radians, ZYX to North-East-Down.
    layers : tuple of float
        Refractive indices of the diffuser's layers.

    Returns
    -------
    ndarray
        ``E_meas = tau(theta) max(cos theta, 0) E_dir + tau_d (1 + cos tilt) / 2 E_dif``.

    References
    ----------
    MicaSense, "Reading DLS Irradiance Metadata" and the DLS model of
    ``micasense/imageprocessing`` (``dls.py``).
    W. F. Holmgren, C. W. Hansen and M. A. Mikofski, "pvlib python: a python package for
    modeling solar energy systems", Journal of Open Source Software 3(29), 2018 (the isotropic
    sky model).
    """
    n = sensor_normal(yaw, pitch, roll)
    theta = incidence_angle(sun_vector(elevation, azimuth), n)
    tilt = tilt_angle(n)
    d, s = np.asarray(direct, np.float64), np.asarray(diffuse, np.float64)
    return (relative_transmission(theta, layers) * np.maximum(np.cos(theta), 0.0) * d
            + diffuse_transmission(layers) * (1.0 + np.cos(tilt)) / 2.0 * s)


def dls2_horizontal(direct: ArrayLike, scattered: ArrayLike, elevation: ArrayLike) -> FloatArray:
    """Return the horizontal irradiance from a DLS 2's split of its reading.

    Parameters
    ----------
    direct : array_like
        ``DirectIrradiance``: direct light on a plane facing the sun.
    scattered : array_like
        ``ScatteredIrradiance``: diffuse light on a horizontal plane.
    elevation : array_like
        The sun's elevation, radians (recomputed from time and position: MicaSense's
        ``compute_horizontal_irradiance_dls2`` does so because the camera's own can be wrong).

    Returns
    -------
    ndarray
        ``E_h = E_dir max(sin el, 0) + E_dif`` (the model of the module docstring with the
        split measured instead of assumed).

    References
    ----------
    MicaSense, "Reading DLS Irradiance Metadata" and the DLS model of
    ``micasense/imageprocessing`` (``dls.py``).
    """
    el = np.asarray(elevation, np.float64)
    return np.asarray(direct, np.float64) * np.maximum(np.sin(el), 0.0) + np.asarray(scattered, np.float64)


@dataclass(frozen=True)
class AnchoredLight:
    """Result of :func:`anchored_irradiance`, arrays (n_frames, n_bands).

    ``irradiance`` E_b(tau) on the panel's scale; ``ratio`` the interpolated panel / sensor
    ratio ``q_b(tau)``; ``sensor_used`` whether the frame's own sensor reading carried the light
    (else the panels' interpolated irradiance).
    """

    irradiance: FloatArray
    ratio: FloatArray
    sensor_used: NDArray[np.bool_]


def anchored_irradiance(panel_irradiance: ArrayLike, panel_sensor: ArrayLike, weights: ArrayLike,
                        frame_sensor: ArrayLike) -> AnchoredLight:
    """Return each frame's irradiance per band: panels anchor the scale, the sun sensor the change.

    Parameters
    ----------
    panel_irradiance : array_like, shape (n_panels, n_bands)
        The light measured by each panel capture, ``E^p_{c,b} = pi L_{c,b} / rho_b`` (or any
        quantity proportional to the irradiance per band, e.g. ``1 / k_{c,b}``).
    panel_sensor : array_like, shape (n_panels, n_bands)
        The sun sensor's horizontal irradiance at each panel capture (NaN: none).
    weights : array_like, shape (n_frames, n_panels)
        Interpolation weights in time, rows summing to 1
        (:func:`mscal_core.illumination.capture_weights`, ``nearest`` or ``linear``).
    frame_sensor : array_like, shape (n_frames, n_bands)
        The sun sensor's horizontal irradiance at each frame (NaN: none).

    Returns
    -------
    AnchoredLight
        ``E_b(tau)``, ``q_b(tau)`` and whether the frame's sensor reading was used, each
        (n_frames, n_bands).

    Raises
    ------
    ValueError
        When the shapes disagree.

    Notes
    -----
    Per band ``b`` the ratio ``q_{c,b} = E^p_{c,b} / E^s_{c,b}`` converts the sensor to the
    panel's scale (it absorbs the sensor's calibration and any unit); it is interpolated in
    time, ``q_b(tau) = sum_c w_c(tau) q_{c,b}``, and
    ``E_b(tau) = q_b(tau) E^s_b(tau)``. Between two panels a drift of the sensor's calibration
    is followed linearly; beyond them the nearest panel's ratio holds. A frame (or band)
    without a reading, or a band whose panels have no reading, falls back to the panels'
    interpolated irradiance ``sum_c w_c E^p_{c,b}``.
    """
    ep = np.atleast_2d(np.asarray(panel_irradiance, np.float64))
    es = np.atleast_2d(np.asarray(panel_sensor, np.float64))
    w = np.atleast_2d(np.asarray(weights, np.float64))
    ef = np.atleast_2d(np.asarray(frame_sensor, np.float64))
    if ep.shape != es.shape or w.shape[1] != ep.shape[0] or ef.shape != (w.shape[0], ep.shape[1]):
        raise ValueError(f"shapes disagree: panels {ep.shape}, panel sensor {es.shape}, weights {w.shape}, "
                         f"frame sensor {ef.shape}")
    ok_c = np.isfinite(es) & (es > 0) & np.isfinite(ep)
    band_ok = ok_c.all(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q_c = np.where(ok_c, ep / np.where(ok_c, es, 1.0), 0.0)
    q = w @ q_c
    used = np.isfinite(ef) & (ef > 0) & band_ok[None, :]
    fallback = w @ np.nan_to_num(ep, nan=0.0)
    e = np.where(used, q * np.where(used, ef, 0.0), fallback)
    return AnchoredLight(e, np.where(band_ok[None, :], q, np.nan), used)


def ratio_drift(panel_irradiance: ArrayLike, panel_sensor: ArrayLike) -> FloatArray:
    """Return per band how much the panels and the sun sensor disagree on the light's change.

    Parameters
    ----------
    panel_irradiance, panel_sensor : array_like, shape (n_panels, n_bands)
        As in :func:`anchored_irradiance`.

    Returns
    -------
    ndarray, shape (n_bands,)
        ``max_c q_{c,b} / min_c q_{c,b} - 1``: 0 when the sensor follows the panels exactly
        (one panel: 0; NaN where a reading is missing). A large value means the sensor misreads
        the change (tilt, shade, a diffuse ratio far from the assumed one) or a panel is off.
    """
    ep = np.atleast_2d(np.asarray(panel_irradiance, np.float64))
    es = np.atleast_2d(np.asarray(panel_sensor, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = ep / es
    ok = np.all(np.isfinite(q), axis=0)
    with np.errstate(invalid="ignore"):
        return np.where(ok, np.max(q, axis=0) / np.min(q, axis=0) - 1.0, np.nan)


@dataclass(frozen=True)
class DiffuseFit:
    """Result of :func:`fit_diffuse_ratio`.

    ``ratio`` the ``r`` that makes the horizontal irradiance smoothest; ``roughness`` its
    mean squared log-change between consecutive readings; ``roughness_at`` the same at the
    ratio the caller compares with (``reference``); ``n`` readings used.
    """

    ratio: float
    roughness: float
    roughness_at: float
    n: int


def fit_diffuse_ratio(reading: ArrayLike, elevation: ArrayLike, azimuth: ArrayLike, yaw: ArrayLike,
                      pitch: ArrayLike, roll: ArrayLike, reference: float = CLEAR_SKY_DIFFUSE_RATIO,
                      grid: ArrayLike | None = None, layers: tuple[float, ...] = DIFFUSER_LAYERS) -> DiffuseFit:
    """Estimate the sky's diffuse ratio from a sequence of tilted readings.

    Parameters
    ----------
    reading, elevation, azimuth, yaw, pitch, roll : array_like, shape (n,)
        Consecutive readings of one band in time order, with the sun's position and the
        sensor's orientation (radians) at each; NaN entries are left out.
    reference : float
        The ratio to compare with (the clear-sky 1/6).
    grid : array_like, optional
        Candidate ratios (default 81 values from 0.02 to 2, geometric).
    layers : tuple of float
        Refractive indices of the diffuser's layers.

    Returns
    -------
    DiffuseFit
        The best ratio of the grid, its roughness, the roughness at ``reference`` and the
        readings used; ``reference`` with NaN roughness when fewer than 3 readings are usable.

    Notes
    -----
    The light on the ground changes slowly between consecutive frames, the sensor's
    orientation quickly (the aircraft turns, pitches, rolls): with the right ``r`` the
    horizontal irradiance of :func:`horizontal_irradiance` does not jump with the attitude. The
    estimate minimises ``mean_i (log E_h(t_{i+1}) - log E_h(t_i))^2`` over the grid. It needs
    readings at different incidence angles; a caller keeps ``reference`` unless the fit lowers
    the roughness clearly.
    """
    cols = [np.asarray(a, np.float64).ravel() for a in (reading, elevation, azimuth, yaw, pitch, roll)]
    ok = np.all([np.isfinite(c) for c in cols], axis=0) & (cols[0] > 0)
    e, el, az, y, p, r = (c[ok] for c in cols)
    g = np.geomspace(0.02, 2.0, 81) if grid is None else np.asarray(grid, np.float64).ravel()

    def rough(ratio: float) -> float:
        h = horizontal_irradiance(e, el, az, y, p, r, diffuse_ratio=ratio, layers=layers).horizontal
        d = np.diff(np.log(h[np.isfinite(h) & (h > 0)]))
        return float(np.mean(d ** 2)) if d.size else float("nan")

    if e.size < 3:
        return DiffuseFit(float(reference), float("nan"), float("nan"), int(e.size))
    values = np.array([rough(v) for v in g])
    best = int(np.nanargmin(values))
    return DiffuseFit(float(g[best]), float(values[best]), rough(float(reference)), int(e.size))
