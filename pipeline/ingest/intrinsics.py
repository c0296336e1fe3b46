"""Camera intrinsics per band: from session.yaml, from a band file's own metadata, or as
the calibration store keeps them.

A multi-lens camera (one lens per band: MicaSense, DJI multispectral, Sequoia) is several
cameras, each with its own focal length, principal point and distortion; the snapshot
camera's bands share one lens on the band grid. Every route here gives one
:class:`~mscal_core.geometry.Intrinsics` per band (band order of the camera's catalog entry).

Metadata (MicaSense RedEdge/Altum, see /tmp/research/cameras.md 1.5 and MicaSense's
"Image Processing" tutorial, ``micasense/imageprocessing`` ``metadata.py``):

- XMP ``Camera:PerspectiveFocalLength`` in mm when ``Camera:PerspectiveFocalLengthUnits`` is
  ``mm``, else in pixels (RedEdge 3 writes pixels and no unit) unless it is the EXIF
  FocalLength in mm (Sentera Double 4K writes 5.4 and no unit: Pix4D's camera schema says mm);
- XMP ``Camera:PrincipalPoint`` "x,y" in mm;
- EXIF ``FocalPlaneXResolution`` / ``FocalPlaneYResolution`` (pixels per
  ``FocalPlaneResolutionUnit``: 2 inch, 3 cm, 4 mm);
- XMP ``Camera:PerspectiveDistortion`` ``[k1, k2, k3, p1, p2]``, reordered to OpenCV's
  ``[k1, k2, p1, p2, k3]``;
- the same tags in a Sentera Double 4K JPEG (exifread for its EXIF, XMP from APP1), one lens
  for the file's bands;
- a maker's own lens tags in a file without them (DJI: ``drone-dji:DewarpData`` and
  ``CalibratedOpticalCenterX/Y``, :func:`pipeline.ingest.cameras.dji.dewarp_intrinsics`): the
  ``intrinsics`` hook of :class:`pipeline.ingest.cameras.registry.Maker`.
"""

from __future__ import annotations

import io
import math
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from mscal_core.errors import FrameError, SessionError
from mscal_core.geometry import Intrinsics
from pydantic import AliasChoices, BaseModel, Field, create_model

from pipeline.ingest.camera_meta import xmp_properties
from pipeline.ingest.cameras.registry import by_order
from pipeline.ingest.exif import EXIF_CODES, rational
from pipeline.ingest.schema import Strict, validate
from pipeline.ingest.xmp import Xmp, jpeg_xmp_packet

#: Parameter order of the store's ``intrinsics (band, intrinsics_param)`` variable.
INTRINSICS_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")

# TIFF/EXIF tag codes (EXIF 2.32)
EXIF_IFD = 34665
XMP_TAG = 700
FOCAL_PLANE_X_RES = 41486
FOCAL_PLANE_Y_RES = 41487
FOCAL_PLANE_UNIT = 41488
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # mm per unit: inch, cm, mm, um


def tiff_tags(path: Path) -> dict[int, Any]:
    """IFD0 tags of a TIFF by code, with the EXIF IFD's tags merged in (EXIF wins); tags a
    writer put into IFD0 instead of the EXIF IFD are found too."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            tags = {t.code: t.value for t in page.tags.values()}
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise FrameError(f"not a readable TIFF ({type(exc).__name__}: {exc})", path=path) from None
    exif = tags.get(EXIF_IFD)
    if isinstance(exif, dict):  # tifffile gives the EXIF IFD as {name: value}
        for name, value in exif.items():
            code = EXIF_CODES.get(name) if isinstance(name, str) else name
            if isinstance(code, int):
                tags[code] = value
    return tags


def intrinsics_from_tags(tags: dict[int, Any], path: Path) -> Intrinsics | None:
    """Intrinsics from a band file's tags (see the module docstring): the Pix4D perspective
    tags, else a maker's own (:func:`maker_intrinsics`); None when the file carries neither."""
    packet = tags.get(XMP_TAG)
    if packet is None:
        return None
    try:
        props = xmp_properties(packet, path)
    except FrameError:
        return None
    if "PerspectiveFocalLength" not in props or "PrincipalPoint" not in props:
        return maker_intrinsics(packet, path)
    unit_mm = _UNIT_MM.get(int(_first(tags.get(FOCAL_PLANE_UNIT, 4)) or 4), 1.0)
    try:
        rx = rational(tags[FOCAL_PLANE_X_RES]) / unit_mm
        ry = rational(tags.get(FOCAL_PLANE_Y_RES, tags[FOCAL_PLANE_X_RES])) / unit_mm
    except KeyError:
        raise FrameError("XMP PrincipalPoint is in mm but EXIF FocalPlaneXResolution is missing", path=path,
                         hint="give the intrinsics in session.yaml, or fit them with 'mscal fit intrinsics'") from None
    try:
        f = float(props["PerspectiveFocalLength"] if not isinstance(props["PerspectiveFocalLength"], list)
                  else props["PerspectiveFocalLength"][0])
        pp = [float(v) for v in str(props["PrincipalPoint"]).replace(" ", "").split(",")]
        dist = props.get("PerspectiveDistortion", [])
        dist = [float(v) for v in (dist if isinstance(dist, list) else str(dist).replace(",", " ").split())]
    except (TypeError, ValueError, IndexError):  # IndexError: an empty rdf:Seq
        raise FrameError("XMP PerspectiveFocalLength / PrincipalPoint / PerspectiveDistortion are not numbers",
                         path=path, hint="give the intrinsics in session.yaml instead") from None
    if (len(pp) != 2 or not all(math.isfinite(v) for v in (f, rx, ry, *pp, *dist, f * rx, f * ry, pp[0] * rx,
                                                             pp[-1] * ry)) or rx <= 0 or ry <= 0):
        raise FrameError(f"XMP PrincipalPoint {props['PrincipalPoint']!r} or the focal plane resolution is unusable",
                         path=path, hint="give the intrinsics in session.yaml instead")
    fx, fy = (f * rx, f * ry) if _focal_in_mm(props, f, tags) else (f, f * ry / rx)
    if not (math.isfinite(fx) and math.isfinite(fy)):
        raise FrameError(f"XMP PerspectiveFocalLength {props['PerspectiveFocalLength']!r} gives no finite focal length "
                         "in pixels", path=path, hint="give the intrinsics in session.yaml instead")
    k = (dist + [0.0] * 5)[:5]
    opencv = (k[0], k[1], k[3], k[4], k[2])  # [k1, k2, k3, p1, p2] -> [k1, k2, p1, p2, k3]
    try:
        return Intrinsics(fx=fx, fy=fy, cx=pp[0] * rx, cy=pp[1] * ry, dist=opencv)
    except Exception as exc:
        raise FrameError(f"intrinsics from metadata are unusable: {exc}", path=path) from None


def _first(value: Any) -> Any:
    """A tag value that a reader gives as a one-item list (exifread) as the item."""
    return value[0] if isinstance(value, (list, tuple)) and len(value) == 1 else value


def _focal_in_mm(props: dict[str, Any], f: float, tags: dict[int, Any]) -> bool:
    """Whether ``Camera:PerspectiveFocalLength`` is in mm: as ``PerspectiveFocalLengthUnits``
    says; without that tag, when it is within a factor of 1.5 of the EXIF FocalLength (mm;
    Sentera Double 4K: 5.4 and 27/5) -- RedEdge 3 writes pixels (1449) beside FocalLength 5.5 --,
    else (no EXIF FocalLength) when it is below 100 (no lens of these cameras is 100 px)."""
    units = props.get("PerspectiveFocalLengthUnits")
    if units is not None:
        return str(units).strip().lower() == "mm"
    focal = tags.get(EXIF_CODES["FocalLength"])
    try:
        mm = rational(_first(focal)) if focal is not None else None
    except (TypeError, ValueError, ZeroDivisionError):
        mm = None
    if mm is not None and mm > 0:
        return 1 / 1.5 <= f / mm <= 1.5
    return f < 100


def maker_intrinsics(packet: Any, path: Path) -> Intrinsics | None:
    """The lens of a file without the Pix4D perspective tags, from the first maker whose own
    lens tags it holds (:attr:`pipeline.ingest.cameras.registry.Maker.intrinsics`), or None."""
    x = Xmp.parse(packet, path)
    for maker in by_order():
        found = maker.intrinsics(x, path) if maker.intrinsics is not None else None
        if found is not None:
            return found
    return None


def jpeg_tags(path: Path) -> dict[int, Any]:
    """The EXIF tags of a JPEG by code (exifread) with its XMP packet as tag 700, the form
    :func:`intrinsics_from_tags` reads."""
    import exifread

    data = path.read_bytes()
    tags: dict[int, Any] = {}
    for key, tag in exifread.process_file(io.BytesIO(data), details=False).items():
        name = key.partition(" ")[2]
        if name in EXIF_CODES:
            tags[EXIF_CODES[name]] = tag.values
    packet = jpeg_xmp_packet(data)
    if packet is not None:
        tags[XMP_TAG] = packet
    return tags


def intrinsics_from_file(path: str | Path) -> Intrinsics | None:
    """Intrinsics written into one band file (TIFF) or multi-channel file (JPEG: Sentera), or
    None (:func:`intrinsics_from_tags`)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return intrinsics_from_tags(jpeg_tags(path), path)
    if suffix not in (".tif", ".tiff"):
        return None
    return intrinsics_from_tags(tiff_tags(path), path)


def band_intrinsics_from_files(files: Sequence[Path], n_bands: int | None = None) -> tuple[Intrinsics, ...] | None:
    """Per band the intrinsics of ``files`` (one band file per band, camera band order; or
    one file holding all ``n_bands`` bands behind one lens: a Sentera JPEG), or None if any
    file carries none."""
    out = []
    for f in files:
        intr = intrinsics_from_file(f)
        if intr is None:
            return None
        out.append(intr)
    if n_bands is not None and len(out) == 1:
        out *= n_bands
    return tuple(out)


# --------------------------------------------------------------------------- session.yaml


def parse_band_intrinsics(data: Any, band_keys: Sequence[Sequence[str]], path: Path, entry: type[BaseModel],
                          build: Callable[[Any], Intrinsics]) -> tuple[Intrinsics, ...]:
    """session.yaml ``intrinsics`` given per band: a mapping from each band's name (or file
    suffix, ``band_keys[b]`` lists the accepted keys of band ``b``) to ``{fx, fy, cx, cy,
    dist}``, validated by :func:`band_intrinsics_model` (every band exactly once, no other key;
    one line naming the key path, :func:`pipeline.ingest.schema.validate`). ``entry``: the
    model of one band's mapping, ``build(model)`` its :class:`Intrinsics`."""
    keys = tuple(tuple(str(k) for k in ks) for ks in band_keys)
    if isinstance(data, dict):  # one band by its name and its suffix: which was meant?
        for ks in keys:
            hits = [k for k in ks if k in data]
            if len(hits) > 1:
                raise SessionError(f"intrinsics: band {ks[0]!r} is given twice (as {' and '.join(hits)})", path=path,
                                   hint="give each band once, by its name or its file suffix")
    m = validate(band_intrinsics_model(keys, entry), data, path, SessionError, prefix="intrinsics")
    return tuple(build(getattr(m, f"band_{b}")) for b in range(len(keys)))


@lru_cache(maxsize=32)
def band_intrinsics_model(band_keys: tuple[tuple[str, ...], ...], entry: type[BaseModel]) -> type[BaseModel]:
    """The pydantic model of per-band intrinsics: one required ``entry`` per band, given by any
    of its keys (``band_keys[b]``: its name, its file suffix)."""
    fields: dict[str, Any] = {f"band_{b}": (entry, Field(validation_alias=AliasChoices(*ks)))
                              for b, ks in enumerate(band_keys)}
    return create_model("BandIntrinsics", __base__=Strict, **fields)


# --------------------------------------------------------------------------- store


def intrinsics_array(intrinsics: Sequence[Intrinsics]) -> np.ndarray:
    """(band, 9) float64 in :data:`INTRINSICS_PARAMS` order."""
    return np.array([[i.fx, i.fy, i.cx, i.cy, *i.dist] for i in intrinsics], dtype=np.float64)


def intrinsics_from_array(values: np.ndarray) -> tuple[Intrinsics, ...]:
    """Inverse of :func:`intrinsics_array`."""
    a = np.asarray(values, dtype=np.float64)
    return tuple(Intrinsics(fx=r[0], fy=r[1], cx=r[2], cy=r[3], dist=tuple(r[4:9])) for r in a)


__all__ = [
    "EXIF_CODES",
    "INTRINSICS_PARAMS",
    "band_intrinsics_from_files",
    "intrinsics_array",
    "intrinsics_from_array",
    "intrinsics_from_file",
    "intrinsics_from_tags",
    "parse_band_intrinsics",
    "tiff_tags",
]
