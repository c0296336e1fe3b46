"""A whole synthetic session: the truth and its four datasets."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ._flight import flight_frames
from ._reflector import reflector_images, vignetting_views
from ._sweep import response_sweep
from ._targets import CharucoBoardSpec, MarkerSpec
from ._truth import FrameSet, SyntheticTruth, make_truth

SIZES = {
    # response frames, response step, vignetting views, missing-marker views, reflector
    # images, flight frames
    "full": dict(n_response=14, step=1.66, n_views=40, n_missing=2, n_reflector=3, n_flight=8),
    "small": dict(n_response=7, step=3.0, n_views=8, n_missing=1, n_reflector=2, n_flight=3),
}


@dataclass
class SyntheticSession:
    """All four datasets of a session plus the camera truth.

    Attributes
    ----------
    truth : SyntheticTruth
        The camera truth.
    response, vignetting, reflector : FrameSet
        The sweep (Eq. 5-7), the reflector views (Eq. 8-10) and the reflector images
        (Eq. 11-14).
    flights : dict of str to FrameSet
        Survey flights by name (Eq. 15).
    size : str
        ``"full"`` or ``"small"`` (``SIZES``).
    """

    truth: SyntheticTruth
    response: FrameSet
    vignetting: FrameSet
    reflector: FrameSet
    flights: dict[str, FrameSet] = field(default_factory=dict)
    size: str = "full"

    def truth_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict of truth arrays (what ``truth.npz`` holds).

        Camera: ``wavelength_nm`` (n_bands,), ``inverse_response`` (n_bands, 2**bits),
        ``black_level``, ``bits``, ``vignetting`` (n_bands, H, W) float32,
        ``vignetting_centre`` (n_bands, 2), ``spectral_factor`` (n_bands,),
        ``reflector_reflectance`` (n_bands,), ``intrinsics`` (fx, fy, cx, cy),
        ``dist`` (5,), ``seed``. Per dataset, its FrameSet truth with a prefix ``response_``,
        ``vignetting_``, ``reflector_``, ``flight_<name>_``, plus ``<prefix>exposure_ms``.
        """
        t = self.truth
        cam = t.camera
        out: dict[str, np.ndarray] = {
            "seed": np.array(t.seed),
            "size": np.array(self.size),
            "wavelength_nm": cam.wavelengths,
            "bits": np.array(cam.bits),
            "black_level": np.array(t.black_level),
            "inverse_response": t.inverse_response,
            "vignetting": t.vignetting.astype(np.float32),
            "vignetting_centre": t.vignetting_centre,
            "spectral_factor": t.spectral_factor,
            "reflector_reflectance": t.reflector_reflectance,
            "reflector_size_m": np.array(t.reflector_size_m),
            "intrinsics": np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            "dist": cam.dist_coeffs,
            "sun_brightness": np.array(t.sun_brightness),
        }
        sets = [("response_", self.response), ("vignetting_", self.vignetting),
                ("reflector_", self.reflector)]
        sets += [(f"flight_{name}_", fs) for name, fs in self.flights.items()]
        for prefix, fs in sets:
            out[prefix + "exposure_ms"] = fs.exposure_ms
            out[prefix + "names"] = np.array(fs.names)
            for key, val in fs.truth.items():
                out[prefix + key] = np.asarray(val)
        return out


def synthesize_session(seed: int = 0, *, size: str = "full", n_flight_frames: int | None = None,
                       flights: Sequence[str] = ("field",),
                       reflector_reflectance: float | Sequence[float] = 0.5,
                       marker: MarkerSpec | CharucoBoardSpec | None = None) -> SyntheticSession:
    """Render all datasets of a session.

    Parameters
    ----------
    seed : int
        Seed of the session.
    size : {"full", "small"}
        Dataset sizes (``SIZES``).
    n_flight_frames : int, optional
        Frames per flight (default from ``SIZES``).
    flights : sequence of str
        Names of the flights.
    reflector_reflectance : float or sequence of float
        R_s of the reflector.
    marker : MarkerSpec or CharucoBoardSpec, optional
        What is printed at the reflector's centre (default the ArUco ``MarkerSpec()``).

    Returns
    -------
    SyntheticSession
        The truth and its datasets.
    """
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    cfg = SIZES[size]
    truth = make_truth(seed, reflector_reflectance=reflector_reflectance, marker=marker)
    resp = response_sweep(truth, seed=seed, n_frames=cfg["n_response"], step=cfg["step"])
    vig = vignetting_views(truth, seed=seed, n_views=cfg["n_views"], n_missing=cfg["n_missing"])
    refl = reflector_images(truth, seed=seed, n_images=cfg["n_reflector"])
    nf = cfg["n_flight"] if n_flight_frames is None else int(n_flight_frames)
    fl = {
        name: flight_frames(truth, seed=seed, n_frames=nf, name=name,
                            time_offset_s=1200.0 + 900.0 * i)
        for i, name in enumerate(flights)
    }
    return SyntheticSession(truth=truth, response=resp, vignetting=vig, reflector=refl,
                            flights=fl, size=size)
