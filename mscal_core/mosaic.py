"""Band layouts: snapshot filter mosaics and multi-channel images (no I/O).

A snapshot mosaic camera with an ``R x C`` filter pattern starting at sensor pixel
``origin = (r0, c0)`` samples the band at mosaic position (r, c) at sensor pixels
``(r0 + R*i + r, c0 + C*j + c)``; band index is ``r*C + c`` (row-major).
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


def demosaic(
    raw: np.ndarray,
    pattern_shape: tuple[int, int],
    origin: tuple[int, int] = (0, 0),
    grid_shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Split a raw mosaic ``(H_sensor, W_sensor)`` into a band stack ``(R*C, H, W)``.

    Parameters
    ----------
    raw : numpy.ndarray
        The raw sensor frame.
    pattern_shape : tuple of int
        ``(R, C)`` of the filter pattern.
    origin : tuple of int
        ``(r0, c0)``, the sensor pixel where the pattern starts.
    grid_shape : tuple of int, optional
        ``(H, W)`` of every band (default: the largest grid every band fills).

    Returns
    -------
    numpy.ndarray
        ``(R*C, H, W)``: band ``r*C + c`` is ``raw[r0 + r :: R, c0 + c :: C]`` cropped to
        ``grid_shape``. No interpolation: each band keeps its own sampling positions (see
        :func:`band_offsets`).

    Raises
    ------
    InputError
        On a frame that is not single-channel or smaller than the mosaic needs.
    """
    if raw.ndim != 2:
        raise InputError(
            f"a mosaic frame must be a single-channel image, got shape {raw.shape}",
            hint="check the camera's layout in its catalog entry",
        )
    rows, cols = pattern_shape
    r0, c0 = origin
    if grid_shape is None:
        grid_shape = ((raw.shape[0] - r0) // rows, (raw.shape[1] - c0) // cols)
    h, w = grid_shape
    need_h, need_w = r0 + rows * h, c0 + cols * w
    if raw.shape[0] < need_h or raw.shape[1] < need_w:
        raise InputError(
            f"frame is {raw.shape[1]}x{raw.shape[0]} pixels but the camera's mosaic needs at "
            f"least {need_w}x{need_h}",
            hint="is this the right camera for the session?",
        )
    out = np.empty((rows * cols, h, w), dtype=raw.dtype)
    for r in range(rows):
        for c in range(cols):
            out[r * cols + c] = raw[r0 + r : need_h : rows, c0 + c : need_w : cols][:h, :w]
    return out


def remosaic(
    bands: np.ndarray, pattern_shape: tuple[int, int], sensor_shape: tuple[int, int],
    origin: tuple[int, int] = (0, 0), fill: int = 0,
) -> np.ndarray:
    """Interleave a band stack into a raw sensor frame, the inverse of :func:`demosaic`.

    Parameters
    ----------
    bands : numpy.ndarray
        ``(R*C, H, W)`` band stack.
    pattern_shape : tuple of int
        ``(R, C)`` of the filter pattern.
    sensor_shape : tuple of int
        ``(H_sensor, W_sensor)`` of the frame.
    origin : tuple of int
        ``(r0, c0)``, the sensor pixel where the pattern starts.
    fill : int
        Value of the sensor pixels no band covers.

    Returns
    -------
    numpy.ndarray
        The raw frame, dtype of ``bands``.

    Raises
    ------
    InputError
        When the number of bands does not fill the pattern.
    """
    rows, cols = pattern_shape
    r0, c0 = origin
    n, h, w = bands.shape
    if n != rows * cols:
        raise InputError(f"{n} bands do not fill a {rows}x{cols} mosaic")
    raw = np.full(sensor_shape, fill, dtype=bands.dtype)
    for r in range(rows):
        for c in range(cols):
            raw[r0 + r : r0 + r + rows * h : rows, c0 + c : c0 + c + cols * w : cols] = bands[
                r * cols + c
            ]
    return raw


def band_offsets(pattern_shape: tuple[int, int]) -> np.ndarray:
    """Return the sub-pixel offsets ``(dx, dy)`` of each band's samples on the band grid.

    Parameters
    ----------
    pattern_shape : tuple of int
        ``(R, C)`` of the filter pattern.

    Returns
    -------
    numpy.ndarray
        ``(R*C, 2)`` float64 ``(c/C, r/R)`` in band-index order: band (r, c) pixel (i, j) lies at
        band-grid point ``(j + c/C, i + r/R)``.
    """
    rows, cols = pattern_shape
    rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return np.stack([cc.ravel() / cols, rr.ravel() / rows], axis=1).astype(np.float64)
