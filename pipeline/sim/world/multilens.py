"""Seeded synthetic captures of a multi-lens camera with known band transforms.

Seeded synthetic captures of a multi-lens camera (one lens per band) with known band transforms,
for band co-registration. Pure arrays, no I/O.

Scene: a ground plane of soil and crop rows (with gaps, weeds and brightness texture, as
:class:`~pipeline.sim.world.scene.FieldScene`), a few bushes that stand above the ground, and
gray panels. Reflectance per band from :func:`~pipeline.sim.world.scene.vegetation_reflectance`
and :func:`~pipeline.sim.world.scene.soil_reflectance`: vegetation is dark in red and bright in
NIR, soil the other way round, so the bands' edges have opposite signs.

Geometry: band b sees the ground through the homography ``H_b`` (reference pixels -> band
pixels, the convention of :mod:`mscal_core.registration`): a shift of several to tens of
pixels, a rotation of up to a degree, a scale change of up to 1 % and a small perspective
term. Parallax: a bush point of relative height ``h`` (0-1) is displaced in band b by
``parallax_px * h`` pixels along that band's baseline direction (a random unit vector per
band), which no homography captures. Each band gets its own radial vignetting,
gain, shot and read noise and 12-bit quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import PeriodicNoise, soil_reflectance, vegetation_reflectance

# MicaSense RedEdge band centres (nm), file order: blue, green, red, NIR, red edge
REDEDGE_WAVELENGTHS_NM = (475.0, 560.0, 668.0, 840.0, 717.0)


@dataclass(frozen=True)
class MultiLensCapture:
    """One synthetic capture of a multi-lens camera and its truth.

    Attributes
    ----------
    dn : numpy.ndarray
        (band, H, W) uint16 (12-bit values).
    homographies : numpy.ndarray
        (band, 3, 3) the true reference -> band transforms of the ground plane (identity for
        ``reference``).
    reflectance : numpy.ndarray
        (band, H, W) float32 the true ground reflectance on the reference grid (what an aligned
        band shows, before vignetting and noise).
    height : numpy.ndarray
        (H, W) float32 the bushes' relative height (0-1, parallax ``parallax_px * height``) on
        the reference grid.
    reference : int
        The reference band.
    wavelengths_nm : tuple of float
        (band,).
    """

    dn: np.ndarray
    homographies: np.ndarray
    reflectance: np.ndarray
    height: np.ndarray
    reference: int
    wavelengths_nm: tuple[float, ...]


def random_homographies(rng: np.random.Generator, n_bands: int, reference: int, shape: tuple[int, int], *,
                        max_shift_px: float = 20.0, max_rotation_deg: float = 1.0, max_scale: float = 0.01,
                        max_perspective: float = 2e-6) -> np.ndarray:
    """Draw reference -> band homographies.

    Parameters
    ----------
    rng : numpy.random.Generator
        The random stream.
    n_bands, reference : int
        Number of bands and the reference band (identity).
    shape : tuple of int
        ``(H, W)`` of the bands.
    max_shift_px, max_rotation_deg, max_scale, max_perspective : float
        Each term is drawn uniformly up to its maximum.

    Returns
    -------
    numpy.ndarray
        (n_bands, 3, 3): rotation and scale about the image centre, a shift and a perspective
        term.
    """
    h, w = shape
    c = np.array([[1.0, 0.0, (w - 1) / 2], [0.0, 1.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    out = np.tile(np.eye(3), (n_bands, 1, 1))
    for b in range(n_bands):
        if b == reference:
            continue
        a = np.deg2rad(rng.uniform(-max_rotation_deg, max_rotation_deg))
        s = 1.0 + rng.uniform(-max_scale, max_scale)
        rot = np.array([[s * np.cos(a), -s * np.sin(a), 0.0], [s * np.sin(a), s * np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        dx, dy = rng.uniform(-max_shift_px, max_shift_px, 2)
        persp = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [*rng.uniform(-max_perspective, max_perspective, 2), 1.0]])
        m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]) @ c @ persp @ rot @ np.linalg.inv(c)
        out[b] = m / m[2, 2]
    return out


class _Field:
    """The ground's textures (one set per capture, drawn from ``rng``)."""

    def __init__(self, rng: np.random.Generator, texture: float):
        self.width = PeriodicNoise(rng, 0.05, 4.0)
        self.gaps = PeriodicNoise(rng, 0.10, 3.0)
        self.weeds = PeriodicNoise(rng, 0.02, 2.5)
        self.tex = PeriodicNoise(rng, 0.01, 2.0)
        self.bushes = PeriodicNoise(rng, 0.15, 2.0)
        self.texture = float(texture)

    def bush(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Relative height of the bushes (0 on the ground, up to 1)."""
        return np.clip((self.bushes(u, v) - 1.6) / 0.6, 0.0, 1.0).astype(np.float32)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vegetation cover (0-1) and brightness texture at ground points (u, v) metres."""
        sp = np.float32(0.75)
        f = u / sp
        f -= np.floor(f)
        d = np.abs(f - np.float32(0.5)) * sp
        hw = 0.17 * (1.0 + 0.3 * self.width(u, v)) * np.clip(1.6 + 0.9 * self.gaps(u, v), 0, 1)
        rows = np.clip(0.5 + (hw - d) / 0.02, 0.0, 1.0)
        weed = np.clip(0.5 + (self.weeds(u, v) - 2.2) / 0.15, 0.0, 1.0)
        cover = np.maximum(np.maximum(rows, weed), self.bush(u, v))
        brightness = 1.0 + self.texture * self.tex(u, v)
        return cover.astype(np.float32), brightness.astype(np.float32)


def multilens_capture(seed: int = 0, *, shape: tuple[int, int] = (240, 320), reference: int = 3,
                      wavelengths_nm: tuple[float, ...] = REDEDGE_WAVELENGTHS_NM, gsd_m: float = 0.02,
                      max_shift_px: float = 20.0, max_rotation_deg: float = 1.0, parallax_px: float = 0.5,
                      texture: float = 0.12, homographies: np.ndarray | None = None,
                      full_well_dn: float = 2500.0, read_noise_dn: float = 3.0) -> MultiLensCapture:
    """Render one capture of a multi-lens camera over the synthetic field (see the module docstring).

    Parameters
    ----------
    seed : int
        Every draw from ``numpy.random.default_rng(seed)``.
    shape : tuple of int
        ``(H, W)`` of the bands.
    reference : int
        The reference band.
    wavelengths_nm : tuple of float
        Band wavelengths.
    gsd_m : float
        Ground sample distance of the reference band.
    max_shift_px, max_rotation_deg : float
        Ranges of the drawn band transforms (:func:`random_homographies`).
    parallax_px : float
        Parallax of the bushes' tops.
    texture : float
        The relative brightness texture of soil and leaves (0 for a low-texture scene: only
        the crop rows' edges remain).
    homographies : numpy.ndarray, optional
        Fixes the band transforms (else drawn).
    full_well_dn : float
        The mean DN of a white ground (sets the shot noise).
    read_noise_dn : float
        Read noise in DN.

    Returns
    -------
    MultiLensCapture
        The DN and their truth.
    """
    rng = np.random.default_rng([seed, 9])
    n = len(wavelengths_nm)
    h, w = shape
    hom = (random_homographies(rng, n, reference, shape, max_shift_px=max_shift_px,
                               max_rotation_deg=max_rotation_deg)
           if homographies is None else np.asarray(homographies, dtype=np.float64))
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    r_veg, r_soil = vegetation_reflectance(wl), soil_reflectance(wl)
    origin = rng.uniform(0, 50, 2)
    field = _Field(np.random.default_rng(int(rng.integers(2**31))), texture)
    directions = rng.normal(size=(n, 2))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)])
    dn = np.empty((n, h, w), dtype=np.uint16)
    refl_ref = np.empty((n, h, w), dtype=np.float32)
    height_ref = None
    for b in range(n):
        # band pixel -> reference pixel (ground plane), sampled 2x2 per pixel (pixel footprint)
        inv = np.linalg.inv(hom[b])
        acc = np.zeros((h, w), dtype=np.float64)
        for oy in (-0.25, 0.25):
            for ox in (-0.25, 0.25):
                q = inv @ (pts + np.array([[ox], [oy], [0.0]]))
                xr, yr = (q[0] / q[2]).reshape(h, w), (q[1] / q[2]).reshape(h, w)
                # bushes stand up: their points appear displaced along the band's baseline;
                # find the ground point seen at this pixel from the displacement at the
                # undisplaced point (one fixed-point step is enough for sub-pixel parallax)
                u = (origin[0] + xr * gsd_m).astype(np.float32)
                v = (origin[1] + yr * gsd_m).astype(np.float32)
                if b != reference and parallax_px > 0:
                    shift = parallax_px * field.bush(u, v)
                    u = (u - directions[b, 0] * shift * gsd_m).astype(np.float32)
                    v = (v - directions[b, 1] * shift * gsd_m).astype(np.float32)
                cover, bright = field(u, v)
                acc += bright * (cover * r_veg[b] + (1.0 - cover) * r_soil[b])
        refl = acc / 4.0
        cx, cy = (w - 1) / 2 + rng.normal(0, 10), (h - 1) / 2 + rng.normal(0, 10)
        r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / (0.5 * (h**2 + w**2))
        vign = 1.0 / (1.0 + 0.35 * r2 + 0.2 * r2**2)
        gain = rng.uniform(0.8, 1.2)
        mean_dn = full_well_dn * gain * vign * refl / max(float(r_veg.max()), float(r_soil.max()))
        noisy = rng.poisson(np.clip(mean_dn, 0, None)) + rng.normal(0.0, read_noise_dn, mean_dn.shape)
        dn[b] = np.clip(np.round(noisy + 100.0), 0, 4095).astype(np.uint16)
        # truth on the reference grid (no parallax: the reference lens's own view)
        u = (origin[0] + xs * gsd_m).astype(np.float32)
        v = (origin[1] + ys * gsd_m).astype(np.float32)
        cover, bright = field(u, v)
        refl_ref[b] = bright * (cover * r_veg[b] + (1.0 - cover) * r_soil[b])
        height_ref = field.bush(u, v)
    assert height_ref is not None
    return MultiLensCapture(dn=dn, homographies=hom, reflectance=refl_ref, height=height_ref,
                            reference=reference, wavelengths_nm=tuple(float(x) for x in wavelengths_nm))
