"""Factory radiometric metadata of one band file (MicaSense RedEdge/Altum style), pure Python.

Reads a TIFF's EXIF (ExposureTime, ISO, BlackLevel, GPS, DateTimeOriginal + SubsecTime) and
its XMP packet (TIFF tag 700) with tifffile and ``xml.etree.ElementTree`` -- no exiftool
binary. XMP properties are matched by namespace URI and local name, whether written as
attributes of ``rdf:Description`` or as child elements (plain text or ``rdf:Seq``/``rdf:Bag``
lists). MicaSense writes the band tags in Pix4D's ``Camera:`` namespace (two URIs are in use)
and the calibration tags in ``MicaSense:``; a tag is looked up in both.

Missing or invalid calibration tags (old firmware) raise :class:`FrameError` naming the file
and the tag: mscal never silently falls back to raw DN.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mscal_core.errors import FrameError
from mscal_core.factory import field_response_scale, field_response_signal, radiance, vignetting_map

from pipeline.ingest.exif import dms_to_degrees, exif_datetime_iso, rational, signed_gps

if TYPE_CHECKING:
    from pipeline.ingest.catalog import Camera

RDF_NS = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
XMP_NAMESPACES = (
    "http://pix4d.com/camera/1.0/",  # Pix4D's documented Camera namespace (pipeline.products.writers)
    "http://pix4d.com/camera/1.0",
    "http://pix4d.com/1.0",  # what RedEdge firmware 2.x writes
    "http://pix4d.com/1.0/",
    "http://micasense.com/MicaSense/1.0/",
    "http://micasense.com/MicaSense/1.0",
)
FIRMWARE_HINT = "the camera firmware may be too old to write factory calibration; update it, or use a field calibration"
MAX_EXPOSURE_S = 1.0  # RedEdge/Altum exposures are at most a few tens of ms
WAVELENGTH_RANGE_NM = (300.0, 1100.0)  # silicon sensors: anything else is a unit error


@dataclass(frozen=True)
class CaptureMeta:
    """Factory metadata of one band file of a capture (units: s, nm, DN, degrees, metres)."""

    path: Path
    shape: tuple[int, int]  # (height, width)
    bits_per_sample: int  # TIFF container depth (16 for RedEdge's 12-bit data)
    band_name: str
    wavelength_nm: float
    fwhm_nm: float | None
    exposure_s: float
    gain: float  # ISO / 100
    black_levels: tuple[float, ...]  # EXIF BlackLevel (per CFA position)
    dark_row_values: tuple[float, ...] | None
    radiometric_calibration: tuple[float, float, float]  # a1, a2, a3
    vignetting_center: tuple[float, float] | None  # (x, y) pixels
    vignetting_polynomial: tuple[float, ...] | None  # k1..kn, lowest power first
    vignetting_polynomial_2d: tuple[float, ...] | None
    vignetting_polynomial_2d_exponents: tuple[float, ...] | None
    irradiance: float | None  # downwelling light sensor, W m-2 nm-1
    capture_id: str | None
    rig_camera_index: int | None
    reflect_area: tuple[float, ...] | None  # panel region written by the camera, if any
    lat: float | None
    lon: float | None
    alt_m: float | None
    time: str | None  # ISO 8601, with fraction of a second when SubsecTime is present

    @property
    def black_level(self) -> float:
        """Black level in DN: the mean of EXIF BlackLevel, else of DarkRowValue."""
        levels = self.black_levels or self.dark_row_values or ()
        return float(sum(levels) / len(levels))


# --------------------------------------------------------------------------- XMP


def xmp_properties(packet: bytes | str, path: Path | str) -> dict[str, Any]:
    """Properties of an XMP packet in the known namespaces, by local name.

    A value is a string (element text or attribute) or a list of strings (``rdf:Seq``,
    ``rdf:Bag`` or ``rdf:Alt`` items).
    """
    text = packet.decode("utf-8", errors="replace") if isinstance(packet, bytes) else packet
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>")
    if start < 0 or end < 0:
        raise FrameError("the XMP packet has no x:xmpmeta element", path=path, hint=FIRMWARE_HINT)
    try:
        root = ET.fromstring(text[start : end + len("</x:xmpmeta>")])
    except ET.ParseError as exc:
        raise FrameError(f"the XMP packet is not valid XML ({exc})", path=path) from None
    props: dict[str, Any] = {}
    for desc in root.iter(f"{{{RDF_NS}}}Description"):
        for key, value in desc.attrib.items():
            local = _known_local(key)
            if local is not None:
                props[local] = value
        for child in desc:
            local = _known_local(child.tag)
            if local is not None:
                props[local] = _element_value(child)
    return props


def _known_local(qname: str) -> str | None:
    """Local name of ``{ns}local`` if ``ns`` is one of :data:`XMP_NAMESPACES`."""
    if not qname.startswith("{"):
        return None
    ns, _, local = qname[1:].partition("}")
    return local if ns in XMP_NAMESPACES else None


def _element_value(elem: ET.Element) -> str | list[str]:
    for kind in ("Seq", "Bag", "Alt"):
        container = elem.find(f"{{{RDF_NS}}}{kind}")
        if container is not None:
            return [(li.text or "").strip() for li in container.findall(f"{{{RDF_NS}}}li")]
    return (elem.text or "").strip()


def _floats(value: Any, path: Path, tag: str, count: int | None = None) -> tuple[float, ...]:
    """A list value (or a comma/space separated string) as finite floats; FrameError if not."""
    items = value if isinstance(value, list) else str(value).replace(",", " ").split()
    try:
        out = tuple(float(v) for v in items)
    except ValueError:
        out = ()
    if not out or not all(math.isfinite(v) for v in out) or (count is not None and len(out) != count):
        want = f"{count} numbers" if count is not None else "numbers"
        raise FrameError(f"XMP {tag} is {value!r}, expected {want}", path=path, hint=FIRMWARE_HINT)
    return out


def _text(value: Any) -> str | None:
    """A text property; a one-item list (``rdf:Seq`` of one ``rdf:li``) counts as its item."""
    if isinstance(value, list):
        value = value[0] if len(value) == 1 else None
    return None if value is None or str(value).strip() == "" else str(value).strip()


def _required(props: dict[str, Any], tag: str, path: Path) -> Any:
    if tag not in props or props[tag] in ("", []):
        raise FrameError(f"no XMP {tag} tag", path=path, hint=FIRMWARE_HINT)
    return props[tag]


def _optional_floats(props: dict[str, Any], tag: str, path: Path) -> tuple[float, ...] | None:
    return _floats(props[tag], path, tag) if props.get(tag) not in (None, "", []) else None


# --------------------------------------------------------------------------- EXIF


def _gps(gps: dict[str, Any]) -> tuple[float | None, float | None, float | None]:
    has_pos = "GPSLatitude" in gps and "GPSLongitude" in gps
    return signed_gps(
        dms_to_degrees(gps["GPSLatitude"]) if has_pos else None, gps.get("GPSLatitudeRef"),
        dms_to_degrees(gps["GPSLongitude"]) if has_pos else None, gps.get("GPSLongitudeRef"),
        rational(gps["GPSAltitude"]) if "GPSAltitude" in gps else None,
        gps.get("GPSAltitudeRef") in (1, b"\x01"),
    )


def _exposure_and_gain(exif: dict[str, Any], path: Path) -> tuple[float, float]:
    if "ExposureTime" not in exif:
        raise FrameError("no EXIF ExposureTime tag", path=path, hint=FIRMWARE_HINT)
    exposure = rational(exif["ExposureTime"])
    if not (math.isfinite(exposure) and 0 < exposure <= MAX_EXPOSURE_S):
        raise FrameError(
            f"EXIF ExposureTime {exposure!r} s is outside (0, {MAX_EXPOSURE_S:g}] s",
            path=path,
            hint="exposure must be in seconds; a value in ms or us means the file was rewritten with wrong units",
        )
    iso = exif.get("ISOSpeed") or exif.get("ISOSpeedRatings")
    if isinstance(iso, tuple):
        iso = iso[0] if iso else None
    if not iso:
        raise FrameError("no EXIF ISOSpeed/ISOSpeedRatings tag (the gain)", path=path, hint=FIRMWARE_HINT)
    return exposure, float(iso) / 100.0


# --------------------------------------------------------------------------- the reader


def read_capture_meta(path: str | Path) -> CaptureMeta:
    """Factory metadata of one band file; :class:`FrameError` naming the file and tag if unusable."""
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise FrameError("file does not exist", path=path)
    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) == 0:  # header read, but the first IFD lies past the end of the file
                raise FrameError("TIFF has no readable image directory (file truncated?)", path=path,
                                 hint="copy the file again from the camera's card")
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}
            shape = (int(page.imagelength), int(page.imagewidth))
            bits = int(page.bitspersample)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as exc:
        raise FrameError(f"not a readable TIFF ({type(exc).__name__}: {exc})", path=path,
                         hint="copy the file again from the camera's card") from None
    if 700 not in tags:
        raise FrameError("no XMP packet (TIFF tag 700)", path=path, hint=FIRMWARE_HINT)
    return meta_from_tags(path, tags, shape, bits)


def meta_from_tags(path: Path, tags: dict[int, Any], shape: tuple[int, int], bits: int) -> CaptureMeta:
    """Build and check a :class:`CaptureMeta` from a TIFF's tag values keyed by tag code."""
    props = xmp_properties(tags[700], path)
    exif = tags.get(34665) or {}
    exposure, gain = _exposure_and_gain(exif, path)

    wavelength = _floats(_required(props, "CentralWavelength", path), path, "CentralWavelength", 1)[0]
    lo, hi = WAVELENGTH_RANGE_NM
    if not lo <= wavelength <= hi:
        raise FrameError(
            f"XMP CentralWavelength {wavelength:g} is outside {lo:g}-{hi:g} nm",
            path=path,
            hint="the wavelength must be in nanometres",
        )
    fwhm = _optional_floats(props, "WavelengthFWHM", path)

    black = tags.get(50714)
    black_levels = tuple(float(v) for v in black) if isinstance(black, tuple) else (
        (float(black),) if black is not None else ()
    )
    dark_rows = _optional_floats(props, "DarkRowValue", path)
    if not black_levels and not dark_rows:
        raise FrameError("no EXIF BlackLevel and no XMP DarkRowValue tag", path=path, hint=FIRMWARE_HINT)

    cal = _floats(_required(props, "RadiometricCalibration", path), path, "RadiometricCalibration", 3)
    if cal[0] <= 0:
        raise FrameError(f"XMP RadiometricCalibration a1 = {cal[0]!r} must be positive", path=path, hint=FIRMWARE_HINT)
    center = _optional_floats(props, "VignettingCenter", path)
    poly = _optional_floats(props, "VignettingPolynomial", path)
    poly2d = _optional_floats(props, "VignettingPolynomial2D", path)
    exps2d = _optional_floats(props, "VignettingPolynomial2DName", path)
    if not ((center and len(center) == 2 and poly) or (poly2d and exps2d)):
        raise FrameError(
            "no vignetting model: needs XMP VignettingCenter + VignettingPolynomial "
            "or VignettingPolynomial2D + VignettingPolynomial2DName",
            path=path,
            hint=FIRMWARE_HINT,
        )
    irr = _optional_floats(props, "Irradiance", path)
    rig = _text(props.get("RigCameraIndex"))
    band_name = _text(_required(props, "BandName", path))
    if band_name is None:
        raise FrameError(f"XMP BandName is {props['BandName']!r}, expected one name", path=path, hint=FIRMWARE_HINT)
    lat, lon, alt = _gps(tags.get(34853) or {})
    return CaptureMeta(
        path=path,
        shape=shape,
        bits_per_sample=bits,
        band_name=band_name,
        wavelength_nm=wavelength,
        fwhm_nm=fwhm[0] if fwhm else None,
        exposure_s=exposure,
        gain=gain,
        black_levels=black_levels,
        dark_row_values=dark_rows,
        radiometric_calibration=(cal[0], cal[1], cal[2]),
        vignetting_center=(center[0], center[1]) if center and len(center) == 2 else None,
        vignetting_polynomial=poly,
        vignetting_polynomial_2d=poly2d,
        vignetting_polynomial_2d_exponents=exps2d,
        irradiance=irr[0] if irr else None,
        capture_id=_text(props.get("CaptureId")) or _text(props.get("CaptureUUID")),
        rig_camera_index=int(rig) if rig is not None and rig.isdigit() else None,
        reflect_area=_optional_floats(props, "ReflectArea", path),
        lat=lat,
        lon=lon,
        alt_m=alt,
        time=exif_datetime_iso(exif.get("DateTimeOriginal"), exif.get("SubsecTimeOriginal") or exif.get("SubsecTime")),
    )


# --------------------------------------------------------------------------- factory model


def factory_vignetting(meta: CaptureMeta) -> np.ndarray:
    """The factory vignetting correction ``(H, W)`` of one band file (>= 1, multiplies DN)."""
    return vignetting_map(
        meta.shape,
        meta.vignetting_center,
        meta.vignetting_polynomial,
        poly_2d=meta.vignetting_polynomial_2d,
        exponents_2d=meta.vignetting_polynomial_2d_exponents,
    )


@dataclass(frozen=True, eq=False)
class FieldParts:
    """Components of one band fitted in the field that replace the factory's (issue 6;
    see :mod:`mscal_core.factory`): ``inverse_response`` U over the sensor DN (Eq. 5-7) and
    ``vignetting`` V ``(H, W)``, max 1 (Eq. 8-10); None keeps the factory's."""

    inverse_response: np.ndarray | None = None
    vignetting: np.ndarray | None = None
    dn_shift: int = 0  # stored DN = sensor DN << dn_shift (4 for 12-bit data in 16-bit TIFFs)


def factory_radiance(meta: CaptureMeta, dn: np.ndarray, parts: FieldParts | None = None) -> np.ndarray:
    """Radiance (W m-2 sr-1 nm-1) of one band file's DN with its own factory calibration,
    or with the field-fitted ``parts`` in place of the factory's response and/or vignetting."""
    if dn.shape != meta.shape:
        raise FrameError(f"image {dn.shape} does not match its metadata {meta.shape}", path=meta.path)
    vignetting = factory_vignetting(meta)
    signal = None
    if parts is not None and parts.vignetting is not None:
        if parts.vignetting.shape != dn.shape:
            raise FrameError(f"field vignetting {parts.vignetting.shape} does not match the image {dn.shape}",
                             path=meta.path)
        v = np.asarray(parts.vignetting, dtype=np.float64)
        vignetting = np.divide(1.0, v, out=np.full(v.shape, np.nan), where=v > 0)
    if parts is not None and parts.inverse_response is not None:
        c = field_response_scale(parts.inverse_response, dn_shift=parts.dn_shift, black_level=meta.black_level,
                                 bits_per_sample=meta.bits_per_sample)
        signal = field_response_signal(dn, parts.inverse_response, dn_shift=parts.dn_shift, scale=c)
    return radiance(
        dn,
        exposure_s=meta.exposure_s,
        gain=meta.gain,
        black_level=meta.black_level,
        calibration=meta.radiometric_calibration,
        vignetting=vignetting,
        bits_per_sample=meta.bits_per_sample,
        signal=signal,
    )


# --------------------------------------------------------------------------- irradiance (issue 8)


def xmp_irradiance(path: str | Path) -> float | None:
    """The XMP ``Irradiance`` (downwelling light sensor) of a TIFF frame, else None.

    Reads only the first page's tags (no pixels); a file that is not a TIFF or has no XMP
    packet, or whose packet has no Irradiance, gives None (most cameras do not write one).
    A present but unusable value (not a number, not positive) raises :class:`FrameError`
    naming the file.
    """
    import tifffile

    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(700)
            packet = None if tag is None else tag.value
    except (tifffile.TiffFileError, ValueError, OSError, IndexError):  # IndexError: truncated, no IFD
        return None
    if packet is None:
        return None
    try:
        props = xmp_properties(packet, path)
    except FrameError:
        return None
    values = _optional_floats(props, "Irradiance", path)
    if not values:
        return None
    if not (math.isfinite(values[0]) and values[0] > 0):
        raise FrameError(f"XMP Irradiance {values[0]!r} is not a positive number", path=path,
                         hint="the sun sensor reading is unusable; remove the frame or give an irradiance column in frames.csv")
    return float(values[0])


def capture_irradiance(capture: "Capture") -> float | None:
    """One irradiance level of a one-file-per-band capture: the mean of its bands' XMP
    Irradiance (each band's sensor reading), None unless every band has one. Only ratios of
    these levels are used (:func:`mscal_core.illumination.frame_illumination`)."""
    values = [m.irradiance for m in capture.metas]
    if not values or any(v is None or not v > 0 for v in values):
        return None
    return float(sum(values) / len(values))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- captures

DEFAULT_CAPTURE_PATTERN = r"^(?P<capture>.+)_(?P<band>[0-9]+)\.tif$"


@dataclass(frozen=True)
class Capture:
    """One capture of a one-file-per-band camera: its band files in band order."""

    name: str  # file name stem without the band suffix, e.g. IMG_0000
    capture_id: str
    metas: tuple[CaptureMeta, ...]  # ordered by band (catalog order, else by suffix)

    @property
    def files(self) -> tuple[Path, ...]:
        return tuple(m.path for m in self.metas)


def group_captures(
    folder: str | Path, camera: Camera | None = None
) -> tuple[list[Capture], list[dict[str, str]]]:
    """Group ``IMG_XXXX_<band>.tif`` files into captures by their name and check them.

    With ``camera`` its ``capture_pattern`` and band list are used: every band's file must be
    present and its XMP BandName must be the catalog's. Without it, the band suffixes seen in
    the folder are expected in every capture. The band files of one capture must carry one
    XMP CaptureId, and no two captures may share one (the later name is a copy).

    Returns the complete captures (sorted by name) and one problem per incomplete or unusable
    capture as ``[{file, reason}]`` (``file`` the offending band file, else the capture's first
    file), for the run's quarantine list.
    """
    folder = Path(folder)
    pattern = re.compile(camera.layout.capture_pattern or DEFAULT_CAPTURE_PATTERN) if camera else re.compile(
        DEFAULT_CAPTURE_PATTERN
    )
    by_name: dict[str, dict[str, CaptureMeta]] = {}
    unusable: dict[str, list[tuple[Path, str]]] = {}
    for path in sorted(folder.iterdir()):
        m = pattern.match(path.name)
        if m is None or not path.is_file():
            continue
        bands = by_name.setdefault(m["capture"], {})
        try:
            bands[m["band"]] = read_capture_meta(path)
        except FrameError as exc:
            unusable.setdefault(m["capture"], []).append((path, exc.reason))
    expected = _expected_suffixes(camera, by_name)
    problems: list[dict[str, str]] = []
    captures: list[Capture] = []
    owner: dict[str, str] = {}  # CaptureId -> the first capture name that carries it
    for name in sorted(by_name):
        bands = by_name[name]
        first = min([m.path for m in bands.values()] + [p for p, _ in unusable.get(name, [])])
        if name in unusable:
            (path, why), more = unusable[name][0], len(unusable[name]) - 1
            problems.append({"file": str(path), "reason": f"capture {name}: band file {path.name}: {why}"
                             + (f" (and {more} more unusable band file(s))" if more else "")})
            continue
        reason = _capture_problem(bands, expected, name, camera)
        ids = sorted({m.capture_id for m in bands.values() if m.capture_id})
        if reason is None and len(ids) > 1:
            reason = f"capture {name}: its band files carry {len(ids)} different XMP CaptureIds (files of other captures renamed?)"
        cid = ids[0] if ids else name
        if reason is None and cid in owner:
            reason = f"capture {name}: same XMP CaptureId as {owner[cid]} (a copy of that capture?)"
        if reason:
            problems.append({"file": str(first), "reason": reason})
            continue
        owner[cid] = name
        captures.append(Capture(name=name, capture_id=cid, metas=tuple(bands[s] for s in expected)))
    return captures, problems


def _expected_suffixes(camera: Camera | None, by_id: dict[str, dict[str, CaptureMeta]]) -> list[str]:
    if camera is not None:
        return [str(b.file_suffix) for b in camera.bands]
    seen = {s for bands in by_id.values() for s in bands}
    return sorted(seen, key=lambda s: (len(s), s))


def _capture_problem(
    bands: dict[str, CaptureMeta], expected: list[str], name: str, camera: Camera | None
) -> str | None:
    """Why a capture's files do not make one complete capture, or None."""
    missing = [s for s in expected if s not in bands]
    extra = sorted(set(bands) - set(expected))
    if missing or extra:
        parts = ([f"missing band file(s) {', '.join(missing)}"] if missing else []) + (
            [f"unexpected band file(s) {', '.join(extra)}"] if extra else []
        )
        return f"capture {name}: {'; '.join(parts)}"
    if camera is not None:
        wrong = [
            f"_{b.file_suffix} is {bands[str(b.file_suffix)].band_name!r}, catalog says {b.name!r}"
            for b in camera.bands
            if bands[str(b.file_suffix)].band_name != b.name
        ]
        if wrong:
            return f"capture {name}: band names differ from camera {camera.name}: {'; '.join(wrong)}"
    return None
