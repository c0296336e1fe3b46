"""Seeded bracketed 8-bit RGB photographs with a known response (pure arrays, no file I/O).

A stand-in for the exposure brackets an ordinary camera (``generic-rgb8``) produces, with the
effects that make real photographs harder than a clean sweep (Eq. 3-4: ``I = C(t E)``):

- scene: linear radiance over about four decades (sky, sunlit and shaded ground with sharp
  shadow and object edges, multi-scale texture, fine "grass" texture, a dark doorway,
  specular glints), coloured;
- moving things: a wind-blown foliage blob whose texture shifts from frame to frame and a
  walking figure, in a known mask (:attr:`PhotoSet.moving`);
- handheld camera: every frame warped by its own small affine (shift ``shift_px``, rotation
  ``rotation_deg``) with ``cv2.warpAffine``; lens blur (Gaussian PSF);
- sensor: RGGB Bayer mosaic of ``t E``, shot and read noise, raw clipping, 12-bit ADC,
  demosaicking (``cv2`` bilinear or edge-aware);
- camera processing: white balance (fixed per set; ``awb_jitter`` makes it drift per frame
  and per channel), highlights clipped where the first channel clips in raw (blown areas
  neutral; a channel can stop rising before its own clip), colour matrix (channel mixing,
  negatives clipped: saturated colours sit at 0 in some channel), a tone curve with toe
  and shoulder (:class:`ToneCurve`, identical for the three channels), unsharp-mask
  sharpening (halos at edges), 8-bit quantisation with clipping, JPEG compression with 4:2:0
  chroma subsampling (``cv2.imencode``/``imdecode`` in memory);
- exposures: the camera's real shutter times are powers of 2 in third stops (1/64 s) while
  EXIF reports the nominal marking (1/60 s); ``PhotoSet.exposure_ms`` is what a file reports
  (nominal by default), ``PhotoSet.exposure_true_ms`` what the sensor integrated.

Truth: before sharpening/JPEG the DN of channel c is ``255 T(x_c)`` with ``x_c`` the linear
value after white balance and colour matrix, ``x_c = t * E_c`` (E_c constant per scene point,
except where a raw channel clipped or the colour matrix went negative). So the true inverse
response per channel is ``U = T^{-1}`` (:meth:`ToneCurve.inverse_response`,
gauge of docs/architecture.md: ``U[0] = 0``, ``U[127] = 127``). Everything is drawn from
``numpy.random.default_rng(seed)``; the same arguments give the same photographs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from mscal_core.errors import InputError

__all__ = ["NOMINAL_SHUTTER_S", "PhotoSet", "ToneCurve", "bracket", "make_photo_set"]

#: Nominal shutter markings in third stops: index k -> marking of the real time 2**(k/3) s.
NOMINAL_SHUTTER_S: dict[int, float] = {
    -39: 1 / 8000, -38: 1 / 6400, -37: 1 / 5000, -36: 1 / 4000, -35: 1 / 3200, -34: 1 / 2500,
    -33: 1 / 2000, -32: 1 / 1600, -31: 1 / 1250, -30: 1 / 1000, -29: 1 / 800, -28: 1 / 640,
    -27: 1 / 500, -26: 1 / 400, -25: 1 / 320, -24: 1 / 250, -23: 1 / 200, -22: 1 / 160,
    -21: 1 / 125, -20: 1 / 100, -19: 1 / 80, -18: 1 / 60, -17: 1 / 50, -16: 1 / 40,
    -15: 1 / 30, -14: 1 / 25, -13: 1 / 20, -12: 1 / 15, -11: 1 / 13, -10: 1 / 10, -9: 1 / 8,
    -8: 1 / 6, -7: 1 / 5, -6: 1 / 4, -5: 0.3, -4: 0.4, -3: 0.5, -2: 0.6, -1: 0.8, 0: 1.0,
    1: 1.3, 2: 1.6, 3: 2.0, 4: 2.5, 5: 3.2, 6: 4.0,
}


# =============================================================================== tone curve


@dataclass(frozen=True)
class ToneCurve:
    """``T(x)``: linear value -> display value in [0, 1] (DN = 255 T), monotone.

    ``v = srgb(x)`` (linear toe of slope 12.92 below 0.0031308, then ``1.055 x^(1/gamma) -
    0.055``), a soft shoulder ``v_s + h (1 - exp(-(v - v_s)/h))`` above ``knee = v_s``
    (``h = 1.5 (1 - v_s)``, reaching 1 at ``v = v_s + h ln 3``), then a toe ``(1 + tau) v^2 /
    (v + tau)`` that crushes the deepest shadows (slope 0 at black). Each piece has a closed
    inverse.
    """

    gamma: float = 2.4
    knee: float = 0.8
    toe: float = 0.02

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Apply the tone curve to linear values ``x`` (sRGB-like, with knee and toe)."""
        x = np.maximum(np.asarray(x, dtype=np.float32), 0.0)
        lin = x <= 0.0031308
        power = 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / self.gamma) - 0.055
        v = np.where(lin, 12.92 * x, power)
        h = 1.5 * (1.0 - self.knee)
        v = np.where(v <= self.knee, v, self.knee - h * np.expm1(-(v - self.knee) / h))
        return ((1.0 + self.toe) * v * v / (v + self.toe)).astype(np.float32)

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """``T^{-1}(y)`` for ``y`` in [0, 1] (float64)."""
        f = np.clip(np.asarray(y, dtype=np.float64), 0.0, 1.0)
        tau = self.toe
        v = (f + np.sqrt(f * f + 4.0 * (1.0 + tau) * f * tau)) / (2.0 * (1.0 + tau))
        h = 1.5 * (1.0 - self.knee)
        frac = np.clip((v - self.knee) / h, 0.0, 1.0 - 1e-12)
        v = np.where(v <= self.knee, v, self.knee - h * np.log1p(-frac))
        return np.where(v <= 12.92 * 0.0031308, v / 12.92, ((v + 0.055) / 1.055) ** self.gamma)

    def inverse_response(self) -> np.ndarray:
        """Return the true ``U[k]``, k = 0..255, scaled to ``U[127] = 127`` (black level 0)."""
        u = self.inverse(np.arange(256) / 255.0)
        return u * (127.0 / u[127])


# =============================================================================== result


@dataclass(frozen=True)
class PhotoSet:
    """A bracketed set of 8-bit RGB photographs and its truth.

    Attributes
    ----------
    frames : numpy.ndarray
        (n, H, W, 3) uint8, RGB, after JPEG (or before, if ``jpeg_quality=None``).
    exposure_ms : numpy.ndarray
        (n,) as a file reports it (nominal marking by default).
    exposure_true_ms : numpy.ndarray
        (n,) what the sensor integrated.
    tone : ToneCurve
        The camera's tone curve (the truth of U).
    moving : numpy.ndarray
        (H, W) bool: pixels where something moves between frames.
    params : dict
        The arguments of :func:`make_photo_set` and the white balance.
    jpeg : tuple of bytes
        The encoded files (BGR JPEG, as cv2.imencode), if JPEG.
    """

    frames: np.ndarray  # (n, H, W, 3) uint8, RGB, after JPEG (or before, if jpeg_quality=None)
    exposure_ms: np.ndarray  # (n,) as a file reports it (nominal marking by default)
    exposure_true_ms: np.ndarray  # (n,) what the sensor integrated
    tone: ToneCurve
    moving: np.ndarray  # (H, W) bool: pixels where something moves between frames
    params: dict = field(default_factory=dict)
    jpeg: tuple[bytes, ...] = ()  # the encoded files (BGR JPEG, as cv2.imencode), if JPEG

    def file_bytes(self, i: int) -> bytes:
        """Frame ``i`` as a JPEG file's bytes (decodes exactly to ``frames[i]``).

        Raises InputError when the set was made without JPEG.
        """
        if not self.jpeg:
            raise InputError("this photo set was made with jpeg_quality=None: no JPEG bytes")
        return self.jpeg[i]

    @property
    def inverse_response(self) -> np.ndarray:
        """True U per channel, (3, 256) float64 (the same tone curve for R, G, B)."""
        return np.tile(self.tone.inverse_response(), (3, 1))


# =============================================================================== exposures


def bracket(n_frames: int, step_thirds: int, centre_k: int = -21) -> tuple[np.ndarray, np.ndarray]:
    """Return the exposures of a bracket centred on third-stop index ``centre_k`` (default 1/125 s).

    Parameters
    ----------
    n_frames : int
        Frames, >= 2.
    step_thirds : int
        Step in third stops, >= 1.
    centre_k : int
        Third-stop index of the middle frame (``2**(k/3)`` seconds).

    Returns
    -------
    true_s, nominal_s : numpy.ndarray
        True seconds ``2**(k/3)`` and the nominal marking (1/60 for 1/64 s).

    Raises
    ------
    InputError
        For fewer than 2 frames, a step below 1, or a bracket outside 1/8000 .. 4 s.
    """
    if n_frames < 2 or step_thirds < 1:
        raise InputError("a bracket needs >= 2 frames and a step of >= 1 third stop")
    k = centre_k + step_thirds * (np.arange(n_frames) - (n_frames - 1) // 2)
    if k.min() < min(NOMINAL_SHUTTER_S) or k.max() > max(NOMINAL_SHUTTER_S):
        raise InputError("bracket outside 1/8000 .. 4 s; use fewer frames or a smaller step")
    return 2.0 ** (k / 3.0), np.array([NOMINAL_SHUTTER_S[int(i)] for i in k])


# =============================================================================== scene


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Zero-mean, unit-ish smooth random field with features of about ``cell`` pixels."""
    h, w = shape
    gh, gw = max(2, int(np.ceil(h / cell)) + 2), max(2, int(np.ceil(w / cell)) + 2)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(small, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def _fractal(
    rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, ...]
) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for i, c in enumerate(cells):
        out += _smooth_noise(rng, shape, c) * (0.7**i)
    return out


def _polygon(rng: np.random.Generator, cx: float, cy: float, r: float, n: int) -> np.ndarray:
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    rad = r * rng.uniform(0.5, 1.0, n)
    return np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)


def _scene(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, dict]:
    """Draw the static linear radiance (h, w, 3) float32 and the ingredients of the moving parts."""
    s = min(h, w) / 480.0  # feature scale relative to a 480-pixel-high frame
    yy = np.arange(h, dtype=np.float32)[:, None]
    horizon = int(h * rng.uniform(0.25, 0.42))
    # ground: reflectance with multi-scale texture, lit by sun (1) or sky only (shadow)
    refl_log = -1.6 + 0.35 * _fractal(rng, (h, w), (120 * s, 40 * s, 12 * s))
    tint = np.stack([1 + 0.15 * _smooth_noise(rng, (h, w), 150 * s) for _ in range(3)], -1)
    albedo = np.exp(refl_log)[..., None] * tint * np.array([1.0, 1.05, 0.8], np.float32)
    # objects with sharp edges and their own colour (buildings, rocks, boards)
    label = np.zeros((h, w), np.int32)
    n_obj = int(rng.integers(6, 11))
    colours = np.exp(rng.uniform(np.log(0.03), np.log(0.8), (n_obj + 1, 3))).astype(np.float32)
    for j in range(1, n_obj + 1):
        cx, cy = rng.uniform(0, w), rng.uniform(horizon * 0.8, h)
        r = rng.uniform(30, 110) * s
        if rng.random() < 0.5:
            pts = _polygon(rng, cx, cy, r, int(rng.integers(3, 7)))
        else:
            x0, y0 = int(cx - r), int(cy - r * rng.uniform(0.5, 1.5))
            pts = np.array([[x0, y0], [x0 + int(2 * r), y0], [x0 + int(2 * r), int(cy + r)],
                            [x0, int(cy + r)]], np.int32)
        cv2.fillPoly(label, [pts], j)
    obj = label > 0
    obj_tex = np.exp(0.15 * _smooth_noise(rng, (h, w), 6 * s))[..., None]
    albedo = np.where(obj[..., None], colours[label] * obj_tex, albedo)
    # fine grass texture (pixel scale) in part of the ground
    grass = (_smooth_noise(rng, (h, w), 90 * s) > 0.3) & (yy > horizon) & ~obj
    fine = np.exp(0.45 * rng.standard_normal((h, w)).astype(np.float32))
    fine = cv2.GaussianBlur(fine, (0, 0), 0.8)
    grass_tint = np.array([0.7, 1.1, 0.5], np.float32)
    albedo = np.where(grass[..., None], albedo * fine[..., None] * grass_tint, albedo)
    # dark doorway / window
    dx, dy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.55, 0.85) * h
    dw, dh = rng.uniform(25, 60) * s, rng.uniform(40, 90) * s
    door = (np.abs(np.arange(w)[None, :] - dx) < dw) & (np.abs(yy - dy) < dh)
    albedo = np.where(door[..., None], np.float32(0.004), albedo)
    # light: sun with hard shadows of polygons, sky light in shadow
    shadow = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(3, 6))):
        pts = _polygon(rng, rng.uniform(0, w), rng.uniform(horizon, h), rng.uniform(60, 180) * s, 6)
        cv2.fillPoly(shadow, [pts], 1)
    light = np.where(shadow > 0, np.float32(rng.uniform(0.06, 0.15)), np.float32(1.0))
    light = light * np.exp(0.1 * _smooth_noise(rng, (h, w), 200 * s))
    rad = albedo * light[..., None]
    # sky: bright, gradient towards the horizon, soft clouds, bluish
    grad = (1.0 + 1.2 * (yy / max(horizon, 1))).astype(np.float32)
    clouds = np.clip(_fractal(rng, (h, w), (160 * s, 50 * s)), 0, None)
    sky_l = rng.uniform(1.2, 2.5) * grad * (1 + 0.8 * clouds)
    sky = sky_l[..., None] * np.array([0.65, 0.85, 1.25], np.float32)
    skyline = horizon + (18 * s * _smooth_noise(rng, (1, w), 40 * s)).astype(np.int32)
    is_sky = (yy < skyline) & ~(obj & (label > n_obj - 2))  # the last two objects rise into the sky
    rad = np.where(is_sky[..., None], sky, rad)
    # specular glints
    for _ in range(int(rng.integers(5, 15))):
        centre = (int(rng.uniform(0, w)), int(rng.uniform(horizon, h)))
        radius = max(1, int(rng.uniform(1, 4) * s))
        glint = float(rng.uniform(8, 30))
        cv2.circle(rad, centre, radius, (glint, glint, glint), -1)
    # moving parts: foliage blob (texture shifted per frame) and a walking figure
    fol = np.zeros((h, w), np.uint8)
    fx, fy = rng.uniform(0.15, 0.85) * w, rng.uniform(0.2, 0.5) * h
    for _ in range(6):
        cv2.ellipse(fol, (int(fx + rng.normal(0, 40 * s)), int(fy + rng.normal(0, 25 * s))),
                    (int(rng.uniform(30, 70) * s), int(rng.uniform(20, 50) * s)), 0, 0, 360, 1, -1)
    pad = int(40 * s) + 4
    leaves = np.exp(1.2 * _fractal(rng, (h + 2 * pad, w + 2 * pad), (5 * s, 2 * s)))
    leaves = (0.06 * leaves / np.median(leaves)).astype(np.float32)
    moving = dict(foliage=fol.astype(bool), leaves=leaves, pad=pad,
                  leaf_colour=np.array([0.55, 1.0, 0.4], np.float32),
                  person_y=int(rng.uniform(0.6, 0.85) * h), person_x0=rng.uniform(0.1, 0.5) * w,
                  person_dx=rng.uniform(15, 40) * s * rng.choice([-1, 1]), person_r=int(22 * s) + 2,
                  person_colour=np.exp(rng.uniform(np.log(0.05), np.log(0.6), 3))
                  .astype(np.float32))
    return rad.astype(np.float32), moving


def _with_moving(
    rad: np.ndarray, mv: dict, i: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``i``'s radiance: foliage texture shifted by the wind, the figure moved on."""
    h, w = rad.shape[:2]
    out = rad.copy()
    pad = mv["pad"]
    oy, ox = rng.integers(0, 2 * pad + 1, 2)
    tex = mv["leaves"][oy : oy + h, ox : ox + w]
    f = mv["foliage"]
    out[f] = tex[f][:, None] * mv["leaf_colour"]
    person = np.zeros((h, w), np.uint8)
    cx, cy, r = int(mv["person_x0"] + i * mv["person_dx"]), mv["person_y"], mv["person_r"]
    cv2.ellipse(person, (cx, cy), (r, 3 * r), 0, 0, 360, 1, -1)
    cv2.circle(person, (cx, cy - 4 * r), r, 1, -1)
    pm = person.astype(bool)
    out[pm] = mv["person_colour"]
    return out, f | pm


# =============================================================================== camera


_CCM = np.array([[1.55, -0.40, -0.15], [-0.22, 1.45, -0.23], [-0.05, -0.45, 1.50]], np.float32)


def _handheld(scene: np.ndarray, rng: np.random.Generator, shift_px: float,
              rotation_deg: float) -> np.ndarray:
    """Move the scene as a handheld camera would.

    A small random shift and rotation about the centre, then the lens blur.
    """
    h, w = scene.shape[:2]
    ang = rng.uniform(0, 2 * np.pi)
    mag = rng.uniform(shift_px / 3, 2 * shift_px) if shift_px > 0 else 0.0
    rot = rng.normal(0.0, rotation_deg) if rotation_deg > 0 else 0.0
    A = cv2.getRotationMatrix2D((w / 2, h / 2), rot, 1.0)
    A[:, 2] += (mag * np.cos(ang), mag * np.sin(ang))
    if mag > 0 or rot != 0:
        scene = cv2.warpAffine(scene, A, (w, h), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)
    return cv2.GaussianBlur(scene, (0, 0), 0.7)


def _bayer_raw(scene: np.ndarray, sens: np.ndarray, k: np.float32, rng: np.random.Generator,
               full_well_e: float, read_noise_e: float) -> np.ndarray:
    """Expose the scene on the raw sensor.

    RGGB Bayer mosaic of ``scene * sens * k``, shot + read noise, raw clip, 12-bit ADC (uint16).
    """
    h, w = scene.shape[:2]
    mosaic_c = np.zeros((h, w), np.intp)
    mosaic_c[0::2, 1::2] = 1
    mosaic_c[1::2, 0::2] = 1
    mosaic_c[1::2, 1::2] = 2
    yy, xx = np.mgrid[0:h, 0:w]
    e_raw = scene[yy, xx, mosaic_c] * sens[mosaic_c] * k
    e_raw = np.maximum(e_raw, 0.0)
    sd = np.sqrt(e_raw / full_well_e + (read_noise_e / full_well_e) ** 2)
    noisy = e_raw + sd * rng.standard_normal((h, w)).astype(np.float32)
    return np.clip(np.rint(noisy * 4095.0), 0, 4095).astype(np.uint16)


def _develop(rgb: np.ndarray, gains: np.ndarray, tone: ToneCurve, sharpen: float) -> np.ndarray:
    """Demosaiced raw RGB to 8-bit.

    White balance ``gains``, colour matrix, tone curve, unsharp mask.
    """
    # highlights clipped where the first channel clips in raw (neutral blown sky), then the
    # colour matrix (rows sum to 1: neutral stays neutral; saturated colours clip at 0)
    lin = np.minimum(rgb * gains, gains.min())
    lin = np.maximum(lin @ _CCM.T, 0.0)
    v = tone(lin)
    if sharpen > 0:
        v = v + np.float32(sharpen) * (v - cv2.GaussianBlur(v, (0, 0), 1.0))
    return np.clip(np.rint(v * 255.0), 0, 255).astype(np.uint8)


def _jpeg_round_trip(dn: np.ndarray, quality: int) -> tuple[np.ndarray, bytes]:
    """Encode an RGB uint8 frame as JPEG (BGR, as cv2.imencode) and decode it back."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(dn[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise InputError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1], buf.tobytes()


def make_photo_set(
    seed: int,
    *,
    shape: tuple[int, int] = (480, 640),
    n_frames: int = 7,
    step_thirds: int = 3,
    jpeg_quality: int | None = 90,
    shift_px: float = 1.5,
    rotation_deg: float = 0.1,
    moving: bool = True,
    sharpen: float = 0.6,
    demosaic: str = "bilinear",
    awb_jitter: float = 0.0,
    nominal_exposure: bool = True,
    exposure_jitter: float = 0.0,
    full_well_e: float = 12000.0,
    read_noise_e: float = 4.0,
    tone: ToneCurve | None = None,
    exposure_bias_stops: float = 0.0,
) -> PhotoSet:
    """Make a seeded bracket of ``n_frames`` photographs ``step_thirds`` third stops apart.

    Parameters
    ----------
    seed : int
        Seed of every draw.
    shape : tuple of int
        ``(H, W)``, at least 64 x 64.
    n_frames, step_thirds : int
        The bracket (:func:`bracket`).
    jpeg_quality : int or None
        None skips JPEG.
    shift_px : float
        The typical handheld shift between frames (each frame's shift is drawn uniformly in
        ``[shift_px/3, 2 shift_px]`` in a random direction; 0 = tripod).
    rotation_deg : float
        The rms rotation.
    moving : bool
        Adds foliage and a walking figure.
    sharpen : float
        The unsharp-mask amount (0 = none).
    demosaic : {"bilinear", "ea"}
        Bilinear or edge aware.
    awb_jitter : float
        The rms per-frame, per-channel drift of the white balance gains.
    nominal_exposure : bool
        Report EXIF-style markings (1/60 for 1/64 s) instead of the true times.
    exposure_jitter : float
        The rms relative error of the real shutter.
    full_well_e, read_noise_e : float
        The sensor's full well and read noise in electrons.
    tone : ToneCurve, optional
        Defaults to a seeded :class:`ToneCurve`.
    exposure_bias_stops : float
        Shifts the whole bracket (positive = brighter).

    Returns
    -------
    PhotoSet
        The frames and their truth.

    Raises
    ------
    InputError
        For a shape below 64 x 64, an unknown demosaic, a bad bracket or a failed JPEG encoding.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    if h < 64 or w < 64:
        raise InputError("photo shape must be at least 64 x 64")
    if demosaic not in ("bilinear", "ea"):
        raise InputError("demosaic must be 'bilinear' or 'ea'")
    if tone is None:
        tone = ToneCurve(gamma=float(rng.uniform(2.2, 2.6)), knee=float(rng.uniform(0.72, 0.85)),
                         toe=float(rng.uniform(0.01, 0.04)))
    rad, mv = _scene(rng, h, w)
    t_true, t_nom = bracket(n_frames, step_thirds)
    t_true = t_true * np.exp(exposure_jitter * rng.standard_normal(n_frames))
    # exposure scale: the bracket's middle frame puts the scene's 60th percentile at mid-gray
    sens = np.array([0.5, 1.0, 0.7], np.float32)  # filter sensitivities (raw, relative)
    # white balance gains: neutralise the filters, with a per-set tint error
    wb = np.array([rng.uniform(0.9, 1.1), 1.0, rng.uniform(0.9, 1.1)], np.float32) / sens
    raw_white = 0.6  # raw level (1 = raw clip) that maps to linear 1 in the green channel
    mid = np.percentile(rad[..., 1], 60)
    k_scene = 0.18 * raw_white / (mid * t_true[(n_frames - 1) // 2]) * 2.0**exposure_bias_stops
    code = cv2.COLOR_BayerRGGB2RGB_EA if demosaic == "ea" else cv2.COLOR_BayerRGGB2RGB
    frames = np.empty((n_frames, h, w, 3), np.uint8)
    encoded: list[bytes] = []
    moving_any = np.zeros((h, w), bool)
    for i in range(n_frames):
        scene_i = rad
        if moving:
            scene_i, mmask = _with_moving(rad, mv, i, rng)
            moving_any |= mmask
        scene_i = _handheld(scene_i, rng, shift_px, rotation_deg)
        raw = _bayer_raw(scene_i, sens, np.float32(k_scene * t_true[i]), rng, full_well_e, read_noise_e)
        rgb = cv2.cvtColor(raw, code).astype(np.float32) / 4095.0
        # white balance (optionally drifting per frame), colour matrix, tone curve
        gains = wb / raw_white * np.exp(awb_jitter * rng.standard_normal(3)).astype(np.float32)
        dn = _develop(rgb, gains, tone, sharpen)
        if jpeg_quality is not None:
            dn, buf = _jpeg_round_trip(dn, int(jpeg_quality))
            encoded.append(buf)
        frames[i] = dn
    params = dict(seed=seed, shape=shape, n_frames=n_frames, step_thirds=step_thirds,
                  jpeg_quality=jpeg_quality, shift_px=shift_px, rotation_deg=rotation_deg,
                  moving=moving, sharpen=sharpen, demosaic=demosaic, awb_jitter=awb_jitter,
                  nominal_exposure=nominal_exposure, exposure_jitter=exposure_jitter,
                  white_balance=wb.tolist())
    t_true_ms = t_true * 1000.0
    return PhotoSet(
        frames=frames,
        exposure_ms=(t_nom * 1000.0) if nominal_exposure else t_true_ms.copy(),
        exposure_true_ms=t_true_ms,
        tone=tone,
        moving=moving_any,
        params=params,
        jpeg=tuple(encoded),
    )
