"""The median stored DN of each band of a frame, kept beside its dn chunk in raw.zarr
(:data:`DN_MEDIAN`), and the counting median of unsigned DN that computes it
(:func:`median_uint16`: ``np.median``'s value for a fraction of its CPU).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

#: Variable of raw.zarr (frame, band): the median stored DN of each band of each frame, written
#: by whoever writes the frame's dn chunk (snapshot flights and capture folders). The report's
#: exposure-normalised frame levels read it instead of decoding every frame again (5 s of a
#: 150-capture factory apply's summary, on the main process after the pass).
DN_MEDIAN = "dn_median"
DN_MEDIAN_ATTRS = {"long_name": "median stored DN of each band", "units": "1"}


#: Below this many values OpenCV's histogram counts them exactly (float32 counts: integers
#: up to 2**24 are exact); larger arrays are counted by ``np.bincount``.
_EXACT_HISTOGRAM = 2**24


def _counts(values: np.ndarray, largest: int | None = None) -> np.ndarray:
    """How many of ``values`` (unsigned, up to 16 bits) equal 0, 1, ... max: ``cv2.calcHist``
    with one unit-wide bin per value (exact below :data:`_EXACT_HISTOGRAM` values; a tenth of
    ``np.bincount``'s CPU on a 10-bit band, which first copies every value to int64).
    ``largest``: their maximum, when the caller has it."""
    v = np.asarray(values)
    if v.size == 0 or v.size >= _EXACT_HISTOGRAM or v.dtype not in (np.uint8, np.uint16):
        return np.bincount(v.ravel())
    top = (int(v.max()) if largest is None else largest) + 1
    return cv2.calcHist([_as_image(v)], [0], None, [top], [0, top]).ravel().astype(np.int64)


def _as_image(v: np.ndarray) -> np.ndarray:
    """``v`` as a C-contiguous 2-D image for OpenCV's histogram (rows of its last axis)."""
    return np.ascontiguousarray(v.reshape(-1, v.shape[-1]) if v.ndim >= 2 else v.reshape(1, -1))


#: From this largest value on, :func:`median_uint16` counts in two steps (:func:`_ranked_wide`):
#: one unit-wide bin per value scatters its counts over a table too large for the fastest cache
#: (a 16-bit MicaSense band: 1.9 ms for 65,536 bins against 0.5 ms for 4,096).
_WIDE_HISTOGRAM = 4096


def _ranked_wide(image: np.ndarray, ranks: Sequence[int]) -> list[int]:
    """The values of ``image`` (2-D uint16, C-contiguous, fewer than :data:`_EXACT_HISTOGRAM`
    values) at each 0-based rank of its sorted values, counted in two steps: the high bytes
    (256 bins), then the low bytes of the values whose high byte holds the rank. Exact, as
    one count per value."""

    high = (image >> 8).astype(np.uint8)
    cum = np.cumsum(cv2.calcHist([high], [0], None, [256], [0, 256]).ravel().astype(np.int64))
    low_cum: dict[int, np.ndarray] = {}
    out = []
    for r in ranks:
        k = int(np.searchsorted(cum, r, side="right"))
        if k not in low_cum:
            low = (image[high == k] & 0xFF).astype(np.uint8).reshape(1, -1)
            low_cum[k] = np.cumsum(cv2.calcHist([low], [0], None, [256], [0, 256]).ravel().astype(np.int64))
        below = int(cum[k - 1]) if k else 0
        out.append(k * 256 + int(np.searchsorted(low_cum[k], r - below, side="right")))
    return out


def _zero_low_bits(v: np.ndarray) -> int:
    """How many low bits are 0 in every one of ``v`` (unsigned, not all 0): 4 for the 12-bit
    DN a 16-bit MicaSense band file stores shifted up."""
    bits = int(np.bitwise_or.reduce(v, axis=None))
    return (bits & -bits).bit_length() - 1


def median_uint16(values: np.ndarray) -> float:
    """``np.median`` of unsigned integers of up to 16 bits, by counting: the middle value, or
    the float64 mean of the middle two (as ``np.median`` takes it), for a fraction of its CPU
    on a full-resolution band (no partition of a copy; :func:`_counts`, or in two steps for
    values past :data:`_WIDE_HISTOGRAM`: :func:`_ranked_wide`). Values past it whose low bits
    are all 0 (:func:`_zero_low_bits`) are counted shifted down, when that brings them below
    it: the same ranks, in one count (0.8 -> 0.5 ms a 1280 x 960 MicaSense band)."""
    v = np.asarray(values)
    shift = 0
    largest = None
    if v.dtype == np.uint16 and 0 < v.size < _EXACT_HISTOGRAM:
        largest = int(v.max())
        if largest >= _WIDE_HISTOGRAM:
            shift = _zero_low_bits(v)
            largest >>= shift
            if largest >= _WIDE_HISTOGRAM:
                n = v.size
                lo, hi = _ranked_wide(_as_image(v), ((n - 1) // 2, n // 2))
                return (lo + hi) / 2
            v = np.right_shift(v, shift)
    counts = np.cumsum(_counts(v, largest))
    n = int(counts[-1])
    lo = int(np.searchsorted(counts, (n - 1) // 2, side="right")) << shift
    hi = int(np.searchsorted(counts, n // 2, side="right")) << shift
    return (lo + hi) / 2  # np.median's float64 mean of the two: their sum, below 2**17, is exact


def kept_medians(cube: Path) -> Path | None:
    """The :data:`DN_MEDIAN` array of the raw cube at ``cube``; None for cubes written before
    it was kept (their frames' medians are computed from the frames when needed)."""
    path = Path(cube) / DN_MEDIAN
    return path if path.is_dir() else None


def band_medians(dn: np.ndarray) -> np.ndarray:
    """``(band,)`` float64: the median of each band of a ``(band, y, x)`` frame as stored
    (:data:`DN_MEDIAN`); NaN for an empty band."""
    out = np.full(dn.shape[0], np.nan)
    for b in range(dn.shape[0]):
        if dn[b].size:
            out[b] = median_uint16(dn[b]) if dn.dtype.kind == "u" and dn.dtype.itemsize <= 2 else float(np.median(dn[b]))
    return out
