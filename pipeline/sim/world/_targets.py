"""Targets of the synthetic scenes: materials, the gray reflector with its marker, the crop field."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from ._light import UniformLight


class PeriodicNoise:
    """Smooth, zero-mean, unit-variance periodic noise on the plane (bilinear, seeded)."""

    def __init__(self, rng: np.random.Generator, cell_m: float, corr_cells: float, n: int = 256):
        white = rng.standard_normal((n, n))
        k = np.fft.fftfreq(n)
        kk = k[:, None] ** 2 + k[None, :] ** 2
        filt = np.exp(-0.5 * (2.0 * np.pi * corr_cells) ** 2 * kk)
        field_ = np.real(np.fft.ifft2(np.fft.fft2(white) * filt))
        field_ = (field_ - field_.mean()) / field_.std()
        self.table = field_.astype(np.float32)
        self.cell_m = float(cell_m)
        self.n = n

    def _coords(self, u) -> np.ndarray:
        a = np.asarray(u, dtype=np.float32) * np.float32(1.0 / (self.n * self.cell_m))
        a -= np.floor(a)  # periodic: fraction of the table's period, in [0, 1)
        a *= np.float32(self.n)
        return a

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Evaluate the periodic noise at plane points ``(u, v)``."""
        mx, my = self._coords(u), self._coords(v)
        shape = mx.shape
        if mx.ndim == 2 and max(shape) < 32000:
            return cv2.remap(self.table, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        size = mx.size
        width = 1024
        rows = -(-size // width)
        pad = rows * width - size
        mx = np.pad(mx.ravel(), (0, pad)).reshape(rows, width)
        my = np.pad(my.ravel(), (0, pad)).reshape(rows, width)
        out = np.concatenate([
            cv2.remap(self.table, mx[r0:r0 + 16000], my[r0:r0 + 16000], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_WRAP).ravel()
            for r0 in range(0, rows, 16000)
        ])
        return out[:size].reshape(shape)


def vegetation_reflectance(wavelength_nm) -> np.ndarray:
    """Green leaf canopy: chlorophyll absorption at ~670 nm, red edge at ~717 nm, NIR plateau.

    About 0.04 at 670 nm and 0.49 at 803 nm (NDVI ~0.86).
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    edge = 1.0 / (1.0 + np.exp(-(wl - 717.0) / 11.0))
    return 0.05 + 0.44 * edge - 0.018 * np.exp(-(((wl - 672.0) / 16.0) ** 2))


def soil_reflectance(wavelength_nm) -> np.ndarray:
    """Dry loam: slowly rising with wavelength, 0.14 at 600 nm to 0.24 at 875 nm."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return 0.14 + 0.10 * (wl - 600.0) / 275.0


@dataclass(frozen=True)
class MarkerSpec:
    """ArUco marker printed on white paper at the centre of the gray reflector."""

    dictionary: str = "DICT_4X4_50"
    id: int = 3
    size_m: float = 0.10
    border_m: float = 0.025
    paper_reflectance: float = 0.85
    ink_reflectance: float = 0.04
    #: session.yaml ``marker.type``.
    kind: ClassVar[str] = "aruco"

    def half_extent(self) -> tuple[float, float]:
        """Half width and half height of the black square (metres)."""
        return 0.5 * self.size_m, 0.5 * self.size_m

    def bits(self) -> np.ndarray:
        """(n, n) cells incl. the black border, 1 = white, row 0 at the top (+y) as printed."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        n = d.markerSize + 2
        img = cv2.aruco.generateImageMarker(d, self.id, n)
        return (img > 127).astype(np.uint8)


@dataclass(frozen=True)
class CharucoBoardSpec:
    """ChArUco board printed on white paper at the centre of the gray reflector, in place of
    the single marker (``mscal_core.charuco``'s board frame: the board's centre at the origin,
    ``u`` right, ``v`` up as printed, OpenCV's top-left square at ``(-W/2, +H/2)``).

    ``squares_x x squares_y`` squares of ``square_m``, markers of ``marker_m`` in the white
    squares, ``border_m`` of white paper around the board. The default, 4 x 4 squares of 60 mm
    with 45 mm markers (7.5 mm cells of ``DICT_4X4_50``), fits on an A3 sheet (260 mm with its
    border) and keeps >= 2 band-grid pixels per marker cell up to ~1.6 m from the Ximea's
    band grid (fx 436 px); its 9 inner corners clear ``mscal_core.charuco.MIN_CORNERS``.
    """

    squares_x: int = 4
    squares_y: int = 4
    square_m: float = 0.06
    marker_m: float = 0.045
    dictionary: str = "DICT_4X4_50"
    border_m: float = 0.01
    paper_reflectance: float = 0.85
    ink_reflectance: float = 0.04
    #: session.yaml ``marker.type``.
    kind: ClassVar[str] = "charuco"
    #: Printed image resolution (pixels per square) the renderer looks the ink up in.
    px_per_square: ClassVar[int] = 240

    @property
    def board_size_m(self) -> tuple[float, float]:
        """``(W, H)`` of the board (metres, without its paper border)."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def size_m(self) -> float:
        """The board's larger side: calibrate excludes a square of this side (plus the
        border) around the reflector's centre, as for a single marker of this size."""
        return max(self.board_size_m)

    def half_extent(self) -> tuple[float, float]:
        """Half width and half height of the board (metres)."""
        w, h = self.board_size_m
        return 0.5 * w, 0.5 * h

    def board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

    def image(self) -> np.ndarray:
        """The printed board (uint8, 255 white, row 0 at the top (+v)), ``px_per_square``
        pixels per square (``CharucoBoard.generateImage``, no margin)."""
        n = self.px_per_square
        return self.board().generateImage((self.squares_x * n, self.squares_y * n), marginSize=0, borderBits=1)

    def corners_m(self) -> np.ndarray:
        """(N, 3) inner chessboard corners in the plane frame (OpenCV's corner order)."""
        xyz = np.asarray(self.board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        w, h = self.board_size_m
        return np.stack([xyz[:, 0] - w / 2, h / 2 - xyz[:, 1], np.zeros(len(xyz))], axis=1)


class ReflectorScene:
    """Gray reflector with the ArUco marker (or ChArUco board), lying on a lawn.

    Gray reflector (``size_m``, reflectance ``rho``) with the marker (a :class:`MarkerSpec` or
    a :class:`CharucoBoardSpec`) on white paper at its centre, lying on a lawn (grass/soil mix)
    in the plane z = 0, lit by ``light``.

    Hard labels (for edge supersampling and pure-pixel masks): 0 ground, 1 gray reflector,
    2 white paper, 3 black ink.
    """

    material_names = ("soil", "vegetation", "gray_reflector", "white_paper", "black_ink")
    GROUND, GRAY, PAPER, INK = 0, 1, 2, 3

    def __init__(self, wavelengths, reflector_reflectance, size_m, marker: MarkerSpec | CharucoBoardSpec, light,
                 ground_seed: int):
        wl = np.asarray(wavelengths, dtype=np.float64)
        n = wl.size
        rho = np.broadcast_to(np.asarray(reflector_reflectance, dtype=np.float64), (n,))
        self.reflectance = np.stack([
            soil_reflectance(wl), vegetation_reflectance(wl), rho,
            np.full(n, marker.paper_reflectance), np.full(n, marker.ink_reflectance),
        ])
        self.size_m = (float(size_m[0]), float(size_m[1]))
        self.marker = marker
        self.light = light
        self._board = marker.image() if isinstance(marker, CharucoBoardSpec) else None
        self._bits = marker.bits() if self._board is None else None
        rng = np.random.default_rng([ground_seed, 7])
        self._cover = PeriodicNoise(rng, 0.01, 3.0)
        self._tex_v = PeriodicNoise(rng, 0.005, 2.0)
        self._tex_s = PeriodicNoise(rng, 0.01, 2.0)

    def evaluate(self, u: np.ndarray, v: np.ndarray):
        """Return material weights and labels of plane points.

        (u, v) plane points (N,) -> weights (K, N) float32 (``B`` x area of each material,
        ground texture included) and hard labels (N,) uint8.
        """
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        B = self.light(u, v)
        au, av = np.abs(u), np.abs(v)
        lab = ((au <= 0.5 * self.size_m[0]) & (av <= 0.5 * self.size_m[1])).astype(np.uint8)
        if self._board is not None:
            self._paint_board(u, v, au, av, lab)
        else:
            s = self.marker.size_m
            half_p = 0.5 * s + self.marker.border_m
            idx = np.flatnonzero((au <= half_p) & (av <= half_p))  # paper: a small subset
            if idx.size:
                pu, pv = u.ravel()[idx], v.ravel()[idx]
                sub = np.full(idx.size, self.PAPER, dtype=np.uint8)
                in_mark = (np.abs(pu) < 0.5 * s) & (np.abs(pv) < 0.5 * s)
                nb = self._bits.shape[0]
                col = np.clip(np.floor((pu + 0.5 * s) / s * nb), 0, nb - 1).astype(np.intp)
                row = np.clip(np.floor((0.5 * s - pv) / s * nb), 0, nb - 1).astype(np.intp)
                sub[in_mark & (self._bits[row, col] == 0)] = self.INK
                lab.ravel()[idx] = sub
        ground = lab == self.GROUND
        cover = np.clip(0.6 + 0.45 * self._cover(u, v), 0.0, 1.0)
        w = np.zeros((5,) + u.shape, dtype=np.float32)
        gB = np.where(ground, B, np.float32(0.0))
        w[0] = gB * (1.0 - cover) * (1.0 + 0.12 * self._tex_s(u, v))
        w[1] = gB * cover * (1.0 + 0.15 * self._tex_v(u, v))
        for k in (self.GRAY, self.PAPER, self.INK):
            w[k + 1] = np.where(lab == k, B, np.float32(0.0))
        return w, lab

    def _paint_board(self, u, v, au, av, lab) -> None:
        """Label the ChArUco board's paper and ink in ``lab`` (in place): the printed image
        looked up at each plane point (nearest pixel, 0.25 mm for 60 mm squares)."""
        hu, hv = self.marker.half_extent()
        border = self.marker.border_m
        idx = np.flatnonzero((au <= hu + border) & (av <= hv + border))
        if not idx.size:
            return
        pu, pv = u.ravel()[idx], v.ravel()[idx]
        sub = np.full(idx.size, self.PAPER, dtype=np.uint8)
        inside = (np.abs(pu) < hu) & (np.abs(pv) < hv)
        rows, cols = self._board.shape
        col = np.clip(np.floor((pu + hu) / (2 * hu) * cols), 0, cols - 1).astype(np.intp)
        row = np.clip(np.floor((hv - pv) / (2 * hv) * rows), 0, rows - 1).astype(np.intp)
        sub[inside & (self._board[row, col] < 128)] = self.INK
        lab.ravel()[idx] = sub


@dataclass(frozen=True)
class Panel:
    """A square gray panel of the field: centre and side (metres) and flat reflectance."""

    centre_m: tuple[float, float]
    size_m: float
    reflectance: float


class FieldScene:
    """Crop field (rows of a green crop on soil) with flat gray panels, lit uniformly.

    Ground plane z = 0, u east, v north (metres). Hard labels: 0 ground, 1 + k panel k.
    Materials: soil, vegetation, then one per panel.
    """

    def __init__(self, wavelengths, panels: Sequence[Panel], sun: float, field_seed: int,
                 row_spacing_m: float = 0.75):
        wl = np.asarray(wavelengths, dtype=np.float64)
        n = wl.size
        self.panels = tuple(panels)
        self.material_names = ("soil", "vegetation") + tuple(
            f"panel_{p.reflectance:.2f}" for p in self.panels
        )
        self.reflectance = np.stack(
            [soil_reflectance(wl), vegetation_reflectance(wl)]
            + [np.full(n, p.reflectance) for p in self.panels]
        )
        self.light = UniformLight(float(sun))
        self.row_spacing_m = row_spacing_m
        rng = np.random.default_rng([field_seed, 11])
        self._width = PeriodicNoise(rng, 0.05, 4.0)
        self._gaps = PeriodicNoise(rng, 0.10, 3.0)
        self._weeds = PeriodicNoise(rng, 0.02, 2.5)
        self._tex_v = PeriodicNoise(rng, 0.01, 2.0)
        self._tex_s = PeriodicNoise(rng, 0.02, 2.0)
        self.soft_m = 0.01

    def vegetation_cover(self, u, v) -> np.ndarray:
        """Return the vegetation cover (0..1) at plane points ``(u, v)``."""
        sp = np.float32(self.row_spacing_m)
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        f = u / sp
        f -= np.floor(f)
        d = np.abs(f - np.float32(0.5)) * sp  # distance to the nearest row centre
        hw = 0.17 * (1.0 + 0.3 * self._width(u, v)) * np.clip(1.6 + 0.9 * self._gaps(u, v), 0, 1)
        rows = np.clip(0.5 + (hw - d) / self.soft_m, 0.0, 1.0)
        weeds = np.clip(0.5 + (self._weeds(u, v) - 2.2) / 0.15, 0.0, 1.0)
        return np.maximum(rows, weeds)

    def evaluate(self, u: np.ndarray, v: np.ndarray):
        """Return the material weights and labels at plane points ``(u, v)``."""
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        B = self.light(u, v)
        lab = np.zeros(u.shape, dtype=np.uint8)
        for k, p in enumerate(self.panels):
            inside = (np.abs(u - p.centre_m[0]) <= 0.5 * p.size_m) & (
                np.abs(v - p.centre_m[1]) <= 0.5 * p.size_m)
            lab[inside] = 1 + k
        ground = lab == 0
        cover = self.vegetation_cover(u, v)
        w = np.zeros((2 + len(self.panels),) + u.shape, dtype=np.float32)
        gB = np.where(ground, B, np.float32(0.0))
        w[0] = gB * (1.0 - cover) * (1.0 + 0.10 * self._tex_s(u, v))
        w[1] = gB * cover * (1.0 + 0.12 * self._tex_v(u, v))
        for k in range(len(self.panels)):
            w[2 + k] = np.where(lab == 1 + k, B, np.float32(0.0))
        return w, lab
