"""Scene part of the seeded synthetic forward model: camera, targets, light, datasets.

Physics (equation numbers of Khanna et al., ICRA 2017, summarised in ``PAPER.md``), per band
(wavelength) ``lambda`` and pixel ``x``:

- (1)  ``L(x) = J(x) R(x)``: Lambertian radiance = incident light x reflectance.
- (11) ``J_lambda(p) = S(lambda) B(p)``: the light's colour ``S`` is the same everywhere, only
  its brightness ``B`` varies over the scene (gradient, soft shadow, clouds between frames).
  ``S`` also absorbs the filter sensitivity of each band.
- (2)  ``E(x) = V(x) L(x)``: optical attenuation (vignetting) of the lens per band and pixel.
- (3, 4) ``I(x) = C(t E(x))``, ``U(I) = t E``: the sensor integrates ``E`` over the exposure
  ``t`` and maps it through its response ``C`` (``SensorModel``, with shot and read noise and
  quantisation).

Units: the energy rate ``E = V S B R`` is in "linear DN per millisecond" (the U gauge of
``docs/architecture.md``: ``U(I) ~ I - black`` in the linear part), so ``t E`` is the linear DN
the sensor integrates during ``t`` ms. ``S`` (1.5-2.5) and ``B`` (a few hundred in reflector
scenes) are stored in those units: ``E = V * S * B * R`` holds exactly for every rendered pixel.
``S`` and ``B`` are a product, so a fit recovers them up to one common scalar; ``V`` is
normalised to max 1 per band.

Geometry: a distorted pinhole (OpenCV model, intrinsics of the 217 x 409 band grid) looking at
a plane ``z = 0`` (marker frame of ``docs/architecture.md``: x right, y up as printed, plane
normal towards the camera; ``X_cam = R X_plane + t`` as in ``cv2.solvePnP``). Band (r, c) of
the 5 x 5 snapshot mosaic samples its pixel (i, j) at band-grid point ``(j + c/5, i + r/5)``,
i.e. at sensor pixel ``(5i + r, 5j + c)``. The renderer works on the sensor grid: every sensor
pixel centre is back-projected (own iterative inversion of the distortion, independent of the
fitting code), intersected with the plane and the scene evaluated there; pixels on a hard edge
(reflector edge, paper, marker cells, panels) are supersampled over the sensor pixel's footprint
and a small Gaussian lens PSF is applied before the bands are split.

Nothing here reads or writes files; ``pipeline/sim/synth.py`` writes a session folder.

Layout: this module gathers the public names of the private modules that hold them, one per
part of the model or per dataset of a session:

- ``_camera`` (:class:`SnapshotCamera`, :class:`Pose`), ``_light`` (:class:`UniformLight`,
  :class:`GradientShadowLight`, :class:`LightDrift`), ``_targets`` (materials,
  :class:`ReflectorScene` with its :class:`MarkerSpec` or :class:`CharucoBoardSpec`,
  :class:`FieldScene`), ``_render`` (:func:`render`, the marker or board read back);
- ``_truth`` (:class:`SyntheticTruth`, :func:`make_truth`, :class:`FrameSet`);
- the datasets: ``_sweep`` (:func:`response_sweep`), ``_reflector``
  (:func:`vignetting_views`, :func:`reflector_images`), ``_flight`` (:func:`flight_frames`);
- ``_session`` (:class:`SyntheticSession`, :func:`synthesize_session`).

References
----------
.. [1] R. Khanna, I. Sa, J. Nieto and R. Siegwart, "On Field Radiometric Calibration
       for Multispectral Cameras", IEEE International Conference on Robotics and
       Automation (ICRA), 2017.
"""

from ._camera import CAMERA_NAME, FRONTAL, XIMEA_WAVELENGTHS_NM, Pose, SnapshotCamera, rot
from ._flight import DEFAULT_PANELS, FIELD_GROUND_ALT_M, FIELD_LAT_LON, NDVI_NIR_NM, NDVI_RED_NM, flight_frames
from ._light import GradientShadowLight, LightDrift, UniformLight
from ._reflector import frame_marker_ok, pose_through, random_light, random_tilt, reflector_images, vignetting_views
from ._render import Render, detect_board_corners, detect_marker_corners, marker_pose_from_image, pose_error, render
from ._session import SIZES, SyntheticSession, synthesize_session
from ._sweep import response_sweep
from ._targets import (
    CharucoBoardSpec,
    FieldScene,
    MarkerSpec,
    Panel,
    PeriodicNoise,
    ReflectorScene,
    soil_reflectance,
    vegetation_reflectance,
)
from ._truth import SESSION_START, FrameSet, SyntheticTruth, expose_frame, exposure_for, make_truth

#: Helpers of the datasets that tests/mscal_core/test_synth_scene.py checks directly; not part
#: of ``__all__``.
TESTED_HELPERS = (FRONTAL, rot, expose_frame, exposure_for, frame_marker_ok, pose_through, random_light)
#: Helpers the multi-lens rig (``rig.py``) builds its views with; not part of ``__all__``.
RIG_HELPERS = (random_tilt,)

__all__ = [
    "CAMERA_NAME",
    "CharucoBoardSpec",
    "XIMEA_WAVELENGTHS_NM",
    "DEFAULT_PANELS",
    "FIELD_GROUND_ALT_M",
    "FIELD_LAT_LON",
    "NDVI_NIR_NM",
    "NDVI_RED_NM",
    "SESSION_START",
    "SIZES",
    "FieldScene",
    "FrameSet",
    "GradientShadowLight",
    "LightDrift",
    "MarkerSpec",
    "Panel",
    "PeriodicNoise",
    "Pose",
    "ReflectorScene",
    "Render",
    "SnapshotCamera",
    "SyntheticSession",
    "SyntheticTruth",
    "UniformLight",
    "detect_board_corners",
    "detect_marker_corners",
    "marker_pose_from_image",
    "pose_error",
    "flight_frames",
    "make_truth",
    "reflector_images",
    "render",
    "response_sweep",
    "soil_reflectance",
    "synthesize_session",
    "vegetation_reflectance",
    "vignetting_views",
]
