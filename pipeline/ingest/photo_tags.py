"""What a band file says about its camera's optics, for the per-frame TIFFs.

Photogrammetry software models a camera from the EXIF and XMP tags of the images it is given
(OpenDroneMap's ``opendm/photo.py``: ``compute_focal`` from ``FocalLengthIn35mmFilm``, else
``FocalLength`` over the sensor width from ``FocalPlaneXResolution`` and
``FocalPlaneResolutionUnit``, the projection from XMP ``Camera:ModelType``; Pix4D's camera XMP
specification: ``Camera:PerspectiveFocalLength`` (mm), ``Camera:PrincipalPoint`` (mm from the
image's top-left corner), ``Camera:PerspectiveDistortion`` (R1, R2, R3, T1, T2), the fisheye
model's ``FisheyeAffineMatrix`` / ``FisheyePolynomial``). mscal's TIFFs carry the source
camera's values of these tags (:class:`CameraOptics`), read here from a band file
(:func:`read_optics`: TIFF or JPEG, EXIF with exifread as OpenDroneMap reads it, XMP with
:mod:`pipeline.ingest.xmp`), or derived from a calibration's intrinsics for a camera whose
frames carry none (:func:`optics_from_intrinsics`, the snapshot mosaic camera).

Frames that mscal turns upright (EXIF Orientation 3, Parrot Sequoia) get the principal point
turned with them (``x -> width - x``, ``y -> height - y``) and the tangential distortion
terms negated; mirrored frames (Orientation 2, 4) keep only the EXIF focal tags (a mirrored
image has no pinhole model of the source's handedness).
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from mscal_core.errors import FrameError

from pipeline.ingest.exif import exifread_tags, rational
from pipeline.ingest.xmp import Xmp, jpeg_xmp_packet

__all__ = ["CameraOptics", "XMP_LENS_TAGS", "optics_from_intrinsics", "read_optics"]

#: XMP ``Camera:`` tags of the lens model (Pix4D's camera XMP specification), carried verbatim.
XMP_LENS_TAGS = (
    "ModelType", "PrincipalPoint", "PerspectiveFocalLength", "PerspectiveFocalLengthUnits",
    "PerspectiveDistortion", "FisheyeAffineMatrix", "FisheyeAffineSymmetric", "FisheyePolynomial",
)
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass(frozen=True)
class CameraOptics:
    """The optics of one band's lens, as EXIF and Pix4D XMP state them (None: not known).

    ``focal_plane_resolution``: pixels per ``focal_plane_unit`` (EXIF 2.32 codes: 2 inch,
    3 cm; 4 mm and 5 um as MicaSense and ExifTool use them). ``xmp``: ``(tag, text)`` pairs of
    :data:`XMP_LENS_TAGS` in the ``Camera`` namespace, values as the source wrote them."""

    f_number: float | None = None
    focal_length_mm: float | None = None
    focal_plane_resolution: tuple[float, float] | None = None
    focal_plane_unit: int | None = None
    focal_length_35mm: int | None = None
    xmp: tuple[tuple[str, str], ...] = ()

    def xmp_value(self, tag: str) -> str | None:
        return dict(self.xmp).get(tag)

    def sensor_mm(self, width: int, height: int) -> tuple[float, float] | None:
        """The image's width and height in mm on the sensor, from the focal plane resolution."""
        if self.focal_plane_resolution is None or self.focal_plane_unit not in _MM_PER_UNIT:
            return None
        rx, ry = self.focal_plane_resolution
        if not (rx > 0 and ry > 0):
            return None
        mm = _MM_PER_UNIT[int(self.focal_plane_unit)]
        return width / rx * mm, height / ry * mm

    def upright(self, orientation: int, width: int, height: int) -> "CameraOptics":
        """The optics of the image turned upright from EXIF ``orientation`` (module docstring)."""
        if orientation in (0, 1):
            return self
        if orientation != 3:
            return replace(self, xmp=())
        tags = dict(self.xmp)
        size = self.sensor_mm(width, height)
        pp = _numbers(tags.get("PrincipalPoint"))
        if pp is not None and len(pp) == 2 and size is not None:
            tags["PrincipalPoint"] = f"{_fmt(size[0] - pp[0])},{_fmt(size[1] - pp[1])}"
        elif "PrincipalPoint" in tags:
            del tags["PrincipalPoint"]
        dist = _numbers(tags.get("PerspectiveDistortion"))
        if dist is not None and len(dist) == 5:
            tags["PerspectiveDistortion"] = ",".join(_fmt(v) for v in (*dist[:3], -dist[3], -dist[4]))
        return replace(self, xmp=tuple(tags.items()))


def _numbers(text: str | None) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        out = tuple(float(t) for t in text.replace(",", " ").split())
    except ValueError:
        return None
    return out if all(math.isfinite(v) for v in out) else None


def _fmt(v: float) -> str:
    return repr(float(v)) if not float(v).is_integer() else str(int(v))


def _positive(value: Any) -> float | None:
    try:
        v = rational(value)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def read_optics(path: str | Path) -> CameraOptics:
    """The optics tags of one band file (TIFF or JPEG); empty :class:`CameraOptics` where it
    has none. A TIFF's pixels are not read (its EXIF IFD and tag 700 only)."""
    path = Path(path)
    try:
        if path.suffix.lower() in (".jpg", ".jpeg"):
            data = path.read_bytes()
            packet = jpeg_xmp_packet(data)
        else:
            import tifffile

            with tifffile.TiffFile(path) as tif:
                tag = tif.pages[0].tags.get(700)
                packet = None if tag is None else tag.value
            data = None
        if data is not None:
            exif = exifread_tags(io.BytesIO(data))
        else:
            with path.open("rb") as fh:
                exif = exifread_tags(fh)
    except FrameError:
        raise
    except Exception as exc:  # OSError, tifffile's errors, exifread's zoo on corrupt EXIF
        raise FrameError(f"cannot read the file's tags ({type(exc).__name__}: {str(exc)[:80]})", path=path) from None
    unit = exif.get("EXIF FocalPlaneResolutionUnit")
    rx, ry = _positive(exif.get("EXIF FocalPlaneXResolution")), _positive(exif.get("EXIF FocalPlaneYResolution"))
    f35 = _positive(exif.get("EXIF FocalLengthIn35mmFilm"))
    xmp_pairs: list[tuple[str, str]] = []
    if packet is not None:
        try:
            x = Xmp.parse(packet, path)
        except FrameError:
            x = Xmp.empty(path)
        for name in XMP_LENS_TAGS:
            v = x.raw(name, ("Camera",))
            if v is not None:
                xmp_pairs.append((name, ",".join(v) if isinstance(v, list) else str(v).strip()))
    return CameraOptics(
        f_number=_positive(exif.get("EXIF FNumber")),
        focal_length_mm=_positive(exif.get("EXIF FocalLength")),
        focal_plane_resolution=(rx, ry or rx) if rx is not None else None,
        focal_plane_unit=unit if isinstance(unit, int) and not isinstance(unit, bool) else None,
        focal_length_35mm=None if f35 is None else int(round(f35)),
        xmp=tuple(xmp_pairs),
    )


def optics_from_intrinsics(fx: float, fy: float, cx: float, cy: float, dist: tuple[float, ...],
                           pitch_mm: tuple[float, float], width: int) -> CameraOptics:
    """Optics of a camera known by its pinhole intrinsics (pixels of the output image) and
    the pixel pitch of that image (mm, x and y): the inverse of
    :func:`pipeline.ingest.intrinsics.intrinsics_from_tags` (focal length and principal point
    in mm, distortion from OpenCV's ``k1, k2, p1, p2, k3`` to Pix4D's ``R1, R2, R3, T1, T2``).

    ``FocalLengthIn35mmFilm`` is the focal length scaled to a 36 mm wide frame (width ratio):
    the convention Parrot's Sequoia writes (4.0 mm over a 4.8 mm wide sensor: 30) and
    OpenDroneMap reads (``focal_ratio = FocalLengthIn35mmFilm / 36``). The focal plane
    resolution is in pixels per cm (EXIF unit 3)."""
    px, py = pitch_mm
    if not (px > 0 and py > 0 and fx > 0):
        raise ValueError(f"pixel pitch {pitch_mm} mm and fx {fx} px must be positive")
    f_mm = fx * px
    k = (tuple(dist) + (0.0,) * 5)[:5]
    pix4d = (k[0], k[1], k[4], k[2], k[3])
    xmp = (
        ("ModelType", "perspective"),
        ("PrincipalPoint", f"{_fmt(round(cx * px, 9))},{_fmt(round(cy * py, 9))}"),
        ("PerspectiveFocalLength", _fmt(round(f_mm, 9))),
        ("PerspectiveFocalLengthUnits", "mm"),
        ("PerspectiveDistortion", ",".join(_fmt(round(v, 12)) for v in pix4d)),
    )
    return CameraOptics(
        f_number=None, focal_length_mm=f_mm, focal_plane_resolution=(10.0 / px, 10.0 / py), focal_plane_unit=3,
        focal_length_35mm=int(round(f_mm * 36.0 / (width * px))), xmp=xmp,
    )
