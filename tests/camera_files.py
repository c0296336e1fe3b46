"""Band files of cameras that have no real files in ../shared/data, built from the real
MicaSense RedEdge files: the pixels (and EXIF) are kept, the tags a camera writes are
rewritten in place with tifffile (the XMP packet, Make, Model, BlackLevel), following each
manufacturer's documented tag set (cameras.md; catalogs/cameras/*.yaml cite the documents).

Each builder returns the folder; the parameters it wrote are in ``PARAMS`` so that tests can
compute the expected values from the published formulas on their own.
"""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import tifffile

from tests.micasense_data import DATA, require_data

CAPTURES = ("0000", "0001")
DUAL_BANDS = (("Blue-444", 444), ("Green-531", 531), ("Red-650", 650), ("Red edge-705", 705), ("Red edge-740", 740))
# 2-D vignetting (RedEdge-P / Altum-PT, MicaSense image.py vignette()): P = sum c u^ex v^ey, V = 1/P
POLY2D = (0.62, 0.75, 0.58, -0.74, -0.57, 0.12)
POLY2D_EXPONENTS = (0, 0, 1, 0, 0, 1, 2, 0, 0, 2, 1, 1)
# DJI P4 Multispectral tags (P4M Image Processing Guide table; values of its examples)
DJI = {
    "black": 4096.0, "gain": 1.0, "exposure_us": 472.5, "adjust": 1.002, "center": (640.0, 480.0),
    "k": (1.0e-4, 3.0e-7, -2.0e-10, 1.0e-13, -2.0e-17, 1.0e-21),
    "irradiance": (1210.5, 1530.25, 1402.0, 1105.75, 980.5),
    "dewarp": "2020-02-04;1949.45,1939.77,28,-17,-0.4082,0.3418,0.00068,0.00068,-0.3540",
    "hmatrix": "1.001,0.0002,2.5,-0.0003,0.999,-1.5,0,0,1",
}
DJI_BANDS = (("Blue", 450, 32), ("Green", 560, 32), ("Red", 650, 32), ("RedEdge", 730, 32), ("NIR", 840, 52))


def band_file(capture: str, band: int) -> Path:
    """A MicaSense sample file; skips the calling test when the sample is absent."""
    return require_data() / f"IMG_{capture}_{band}.tif"


def rewrite(src: Path, dst: Path, edit: Callable[[str], str] | None = None, *, make: str | None = None,
            model: str | None = None, black: tuple[int, ...] | None = None) -> Path:
    """Copy ``src`` to ``dst`` with its XMP packet passed through ``edit`` and the given tags
    overwritten (pixels and the other tags unchanged)."""
    shutil.copyfile(src, dst)
    dst.chmod(0o644)
    with tifffile.TiffFile(dst, mode="r+b") as tif:
        tags = tif.pages[0].tags
        if edit is not None:
            tags[700].overwrite(edit(tags[700].value.decode("utf-8")).encode("utf-8"))
        if make is not None:
            tags[271].overwrite(make)
        if model is not None:
            tags[272].overwrite(model)
        if black is not None:
            tags[50714].overwrite(black)
    return dst


def set_element(xmp: str, qname: str, value: str) -> str:
    """Replace the content of ``<qname>...</qname>`` (text or an rdf list)."""
    new, n = re.subn(rf"<{qname}>.*?</{qname}>", f"<{qname}>{value}</{qname}>", xmp, flags=re.S)
    assert n == 1, qname
    return new


def drop_element(xmp: str, qname: str) -> str:
    new, n = re.subn(rf"<{qname}>.*?</{qname}>", "", xmp, flags=re.S)
    assert n == 1, qname
    return new


def add_camera_element(xmp: str, element: str) -> str:
    """Insert ``element`` into the rdf:Description that declares the Camera namespace."""
    start = xmp.index("xmlns:Camera=")
    end = xmp.index("</rdf:Description>", start)
    return xmp[:end] + element + xmp[end:]


def seq(*items: object) -> str:
    return "<rdf:Seq>" + "".join(f"<rdf:li>{i}</rdf:li>" for i in items) + "</rdf:Seq>"


def poly2d(xmp: str) -> str:
    """The radial vignetting replaced by the 2-D polynomial (RedEdge-P / Altum-PT)."""
    xmp = drop_element(xmp, "Camera:VignettingCenter")
    xmp = drop_element(xmp, "Camera:VignettingPolynomial")
    return add_camera_element(
        xmp, f"<Camera:VignettingPolynomial2DName>{seq(*POLY2D_EXPONENTS)}</Camera:VignettingPolynomial2DName>"
             f"<Camera:VignettingPolynomial2D>{seq(*POLY2D)}</Camera:VignettingPolynomial2D>")


def capture_id(capture: str) -> str:
    with tifffile.TiffFile(band_file(capture, 1)) as tif:
        x = tif.pages[0].tags[700].value.decode()
    return re.search(r"<MicaSense:CaptureId>(.*?)</MicaSense:CaptureId>", x)[1]


def extra_band(path: Path, shape: tuple[int, int], band: str, wavelength: float, capture: str, model: str,
               value: int) -> Path:
    """A band file of another resolution (panchromatic, thermal) written from scratch: Make,
    Model and an XMP packet with BandName, CentralWavelength and the capture's CaptureId."""
    packet = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description xmlns:MicaSense="http://micasense.com/MicaSense/1.0/" xmlns:Camera="http://pix4d.com/camera/1.0">'
        f"<MicaSense:CaptureId>{capture_id(capture)}</MicaSense:CaptureId><Camera:BandName>{band}</Camera:BandName>"
        f"<Camera:CentralWavelength>{wavelength}</Camera:CentralWavelength></rdf:Description></rdf:RDF></x:xmpmeta>"
    ).encode()
    tifffile.imwrite(path, np.full(shape, value, np.uint16), photometric="minisblack",
                     extratags=[(271, "s", 0, "MicaSense", True), (272, "s", 0, model, True),
                                (700, 1, len(packet), packet, True)])
    return path


def pack12(dn: np.ndarray) -> bytes:
    """12-bit samples (< 4096) packed as TIFF 6.0 stores BitsPerSample 12 (section 2: FillOrder
    1, the most significant bit first whatever the byte order; each row starts on a byte):
    two pixels ``a b`` in three bytes ``a>>4, (a&15)<<4 | b>>8, b&255``."""
    h, w = dn.shape
    a = np.zeros((h, w + w % 2), np.uint16)
    a[:, :w] = dn
    x0, x1 = a[:, 0::2], a[:, 1::2]
    packed = np.stack([x0 >> 4, ((x0 & 15) << 4) | (x1 >> 8), x1 & 255], axis=-1).astype(np.uint8).reshape(h, -1)
    return packed[:, :(w * 12 + 7) // 8].tobytes()


def rededge_12bit(src: Path, dst: Path) -> Path:
    """``src``, a real RedEdge band file (12-bit DN in the high bits of 16-bit samples), as a
    RedEdge set to save 12-bit TIFFs writes it (MicaSense, "RedEdge Camera Radiometric
    Calibration Model": "12-bit or 16-bit format ... divide the raw DN by 2^N"): the sensor's
    DN (``sample >> 4``) packed in 12 bits (:func:`pack12`), each strip in place of the
    16-bit one (same RowsPerStrip; StripByteCounts 3/4 of theirs), BitsPerSample 12 and the
    EXIF BlackLevel in the file's own DN (4800 -> 300). Every other tag is the source's."""
    shutil.copyfile(src, dst)
    dst.chmod(0o644)
    dn = tifffile.imread(src)
    assert not np.any(dn & 15), src  # the real files: multiples of 16
    with tifffile.TiffFile(dst, mode="r+b") as tif:
        page = tif.pages[0]
        rows = int(page.rowsperstrip)
        offsets = page.dataoffsets
        counts = []
        for i, at in enumerate(offsets):
            strip = pack12(dn[i * rows:(i + 1) * rows] >> 4)
            tif.filehandle.seek(at)
            tif.filehandle.write(strip)
            counts.append(len(strip))
        tags = page.tags
        tags[279].overwrite(tuple(counts))
        tags[258].overwrite(12)
        tags[50714].overwrite(tuple(v // 16 for v in tags[50714].value))
    return dst


def rededge_mx_dual(folder: Path) -> Path:
    """Two five-lens rigs sharing one CaptureId per capture: IMG_XXXX_1..10.tif."""
    folder.mkdir(parents=True, exist_ok=True)
    for cap in CAPTURES:
        for b in range(1, 6):
            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", model="RedEdge-MX")
            name, wl = DUAL_BANDS[b - 1]

            def edit(x: str, name: str = name, wl: int = wl, b: int = b) -> str:
                x = set_element(x, "Camera:BandName", name)
                x = set_element(x, "Camera:CentralWavelength", str(wl))
                return set_element(x, "Camera:RigCameraIndex", str(b + 4))

            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b + 5}.tif", edit, model="RedEdge-MX")
    return folder


def rededge_p(folder: Path, *, altum_pt: bool = False) -> Path:
    """RedEdge-P (5 bands + Panchro at another resolution, 2-D vignetting); with
    ``altum_pt`` an Altum-PT (+ a LWIR band in centi-kelvin)."""
    folder.mkdir(parents=True, exist_ok=True)
    model = "Altum-PT" if altum_pt else "RedEdge-P"
    for cap in CAPTURES:
        for b in range(1, 6):
            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", poly2d, model=model)
        extra_band(folder / f"IMG_{cap}_6.tif", (1200, 1600), "Panchro", 634.5, cap, model, 20000)
        if altum_pt:
            extra_band(folder / f"IMG_{cap}_7.tif", (120, 160), "LWIR", 11000, cap, model, 29315)
    return folder


def reflect_area_one_li(folder: Path, corners: tuple[tuple[tuple[int, int], ...], ...], *,
                        bad: str | None = None) -> Path:
    """The real captures as a firmware that writes ReflectArea as one rdf:li of comma-separated
    numbers (``bad``: that text instead, in band 1), with the Camera namespace under another
    prefix and URI form in band 2."""
    folder.mkdir(parents=True, exist_ok=True)
    for cap in CAPTURES:
        for b in range(1, 6):
            def edit(x: str, b: int = b, cap: str = cap) -> str:
                if cap == "0000":
                    text = ",".join(f"{px},{py}" for px, py in corners[b - 1])
                    if bad is not None and b == 1:
                        text = bad
                    x = add_camera_element(x, f"<Camera:ReflectArea>{seq(text)}</Camera:ReflectArea>")
                if b == 2:  # prefix "Cam", URI with the trailing slash: the same namespace
                    x = x.replace('xmlns:Camera="http://pix4d.com/1.0"', 'xmlns:Cam="http://pix4d.com/camera/1.0/"')
                    x = x.replace("<Camera:", "<Cam:").replace("</Camera:", "</Cam:")
                return x

            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", edit)
    return folder


def rededge_auto_panel(folder: Path, albedo: Sequence[str], *, capture: str = "0000", picture: int = 2) -> Path:
    """The real captures, ``capture`` (IMG_0000: the panel) as a MicaSense firmware writes an
    automatic panel capture: XMP ``Camera:CalibrationPicture`` ``picture`` (2: a valid panel
    capture) and ``Camera:Albedo`` (the panel's reflectance in the band, read from its QR code;
    ``albedo[b - 1]`` as written, garbled text allowed)."""
    folder.mkdir(parents=True, exist_ok=True)
    for cap in CAPTURES:
        for b in range(1, 6):
            def edit(x: str, b: int = b, cap: str = cap) -> str:
                if cap == capture:
                    x = add_camera_element(x, f"<Camera:CalibrationPicture>{picture}</Camera:CalibrationPicture>"
                                              f"<Camera:Albedo>{albedo[b - 1]}</Camera:Albedo>")
                return x

            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", edit)
    return folder


def dji_xmp(band: int, cap_uuid: str, *, band_freq: bool = False, dewarp: str | None = None,
            hmatrix: str | None = None) -> str:
    name, wl, fwhm = DJI_BANDS[band - 1]
    attrs = {
        "drone-dji:SensorGain": f"{DJI['gain']:.3f}", "drone-dji:ExposureTime": f"{DJI['exposure_us']}",
        "drone-dji:SensorGainAdjustment": f"{DJI['adjust']}", "drone-dji:Irradiance": f"{DJI['irradiance'][band - 1]}",
        "drone-dji:CalibratedOpticalCenterX": f"{DJI['center'][0]}", "drone-dji:CalibratedOpticalCenterY": f"{DJI['center'][1]}",
        "drone-dji:VignettingData": ", ".join(f"{k:.6e}" for k in DJI["k"]),
        "drone-dji:DewarpData": dewarp or DJI["dewarp"], "drone-dji:CalibratedHMatrix": hmatrix or DJI["hmatrix"], "drone-dji:CaptureUUID": cap_uuid, "drone-dji:SensorIndex": str(band),
        "drone-dji:BandName": name,
    }
    elements = ""
    if band_freq:
        attrs["drone-dji:BandFreq"] = f"{wl}(+/-{fwhm // 2})nm"
    else:
        elements = (f"<Camera:BandName>{name}</Camera:BandName><Camera:CentralWavelength>{wl}</Camera:CentralWavelength>"
                    f"<Camera:WavelengthFWHM>{fwhm}</Camera:WavelengthFWHM>")
    attr_text = " ".join(f'{k}="{v}"' for k, v in attrs.items())
    return ('<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
            '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
            'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" xmlns:Camera="http://pix4d.com/camera/1.0/" '
            f'{attr_text}>{elements}</rdf:Description></rdf:RDF></x:xmpmeta><?xpacket end="w"?>')


def dji_p4m(folder: Path) -> Path:
    """P4 Multispectral captures DJI_0011..0015.TIF and DJI_0021..0025.TIF (band = last digit)."""
    folder.mkdir(parents=True, exist_ok=True)
    for c, cap in enumerate(CAPTURES, start=1):
        for b in range(1, 6):
            packet = dji_xmp(b, f"dji-capture-{cap}", band_freq=b == 5)
            rewrite(band_file(cap, b), folder / f"DJI_00{c}{b}.TIF", lambda _x, p=packet: p, make="DJI",
                    model="FC6360", black=(int(DJI["black"]),))
    return folder


def altum(folder: Path) -> Path:
    """Altum: five bands (radial vignetting) and a LWIR band (_6, 160 x 120, centi-kelvin)."""
    folder.mkdir(parents=True, exist_ok=True)
    for cap in CAPTURES:
        for b in range(1, 6):
            rewrite(band_file(cap, b), folder / f"IMG_{cap}_{b}.tif", model="Altum")
        extra_band(folder / f"IMG_{cap}_6.tif", (120, 160), "LWIR", 11000, cap, "Altum", 29815)
    return folder


def jpeg_segments(data: bytes) -> list[bytes]:
    """The APPn segments (marker included) of a JPEG, in order."""
    out, i = [], 2
    while data[i] == 0xFF and 0xE0 <= data[i + 1] <= 0xEF:
        n = int.from_bytes(data[i + 2 : i + 4], "big")
        out.append(data[i : i + 2 + n])
        i += 2 + n
    return out


def sentera_with_panel(src_folder: Path, folder: Path, value: int = 200) -> Path:
    """The real Sentera captures, the first with a uniform gray panel painted in (all channels
    ``value``), re-encoded losslessly enough (quality 100) with the original EXIF and XMP."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    files = sorted(src_folder.glob("*.jpg"))
    for k, path in enumerate(files):
        data = path.read_bytes()
        if k > 0:
            (folder / path.name).write_bytes(data)
            continue
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        img[1200:1700, 1700:2200] = value
        ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 100])
        assert ok
        enc = enc.tobytes()
        app1 = [s for s in jpeg_segments(data) if s[1] == 0xE1]  # EXIF and XMP
        (folder / path.name).write_bytes(enc[:2] + b"".join(app1) + enc[2:])
    return folder


# --------------------------------------------------------------------------- Sentera 6X

SENTERA_D4K = DATA.parent / "sentera-d4k"
SENTERA_6X_SHAPE = (1428, 1904)  # documented ImageLength x ImageWidth
# band -> (folder, D4K sensor, channel of its RGB-ordered JPEG, wavelength, FWHM); folders listed
# out of the catalog's band order on purpose: the band is the file's XMP BandName
SENTERA_6X_BANDS = {
    "NIR": ("nir_840", "NDRE", 2, 840, 20), "Blue": ("blue_475", "nRGB", 2, 475, 30),
    "RedEdge": ("rededge_715", "NDRE", 0, 715, 10), "Green": ("green_550", "nRGB", 1, 550, 20),
    "Red": ("red_670", "nRGB", 0, 670, 30),
}
SENTERA_6X_SESSION = "2020-09-15_04-37-17"
SENTERA_6X_PANEL = (slice(500, 800), slice(700, 1100), 3600)  # rows, columns, 12-bit DN in every band


def _d4k_exif(path: Path) -> dict[str, object]:
    import exifread

    with open(path, "rb") as f:
        t = exifread.process_file(f, details=False)
    e = t["EXIF ExposureTime"].values[0]
    return {"iso": int(t["EXIF ISOSpeedRatings"].values[0]), "exposure": (int(e.num), int(e.den)),
            "time": str(t["EXIF DateTimeOriginal"].values), "subsec": str(t["EXIF SubSecTimeOriginal"].values)}


def _d4k_packet_one_band(packet: str, band: str, wl: int, fwhm: int, sun: float) -> str:
    """The real Double 4K XMP packet (Camera + ILS namespaces) for one band of a 6X file: the
    band lists cut to that band, no ColorTransform (one imager per band), no perspective tags
    (the 6X's are not published) and no rig tags (not in its tag table)."""
    for tag, value in (("BandName", band), ("CentralWavelength", wl), ("WavelengthFWHM", fwhm), ("SunSensor", sun)):
        packet = set_element(packet, f"Camera:{tag}", seq(value))
    packet = drop_element(packet, "Camera:ColorTransform")
    return re.sub(r'\s+Camera:(ModelType|PrincipalPoint|PerspectiveFocalLength|PerspectiveDistortion|IsNormalized|RigName|RigCameraIndex)="[^"]*"',
                  "", packet)


def sentera_6x(folder: Path, *, panel: bool = False) -> Path:
    """A 6X session folder ``folder/2020-09-15_04-37-17/<band folder>/IMG_0000N.tif`` for the two
    real Double 4K captures: each band is one channel of a D4K JPEG (NDRE: RedEdge, NIR; nRGB:
    Blue, Green, Red) resized to the 6X's 1904 x 1428 and put on 12 bits (x 16); IFD0 holds the
    documented tags (Make, Model, Software, ImageUniqueID, LensModel) and the EXIF ones the
    documents list under "EXIF (IFD0)" (ExposureTime, ISOSpeedRatings, DateTimeOriginal; the
    D4K capture's values); XMP from the D4K packet (:func:`_d4k_packet_one_band`). ``panel``: a
    uniform gray square (:data:`SENTERA_6X_PANEL`) in every band of the first capture.
    Returns the session folder; ``PARAMS`` has each file's ISO and exposure."""
    import cv2

    from pipeline.ingest.xmp import jpeg_xmp_packet

    session = folder / SENTERA_6X_SESSION
    for n, cap in enumerate(("IMG_00006", "IMG_00007"), start=1):
        decoded = {}
        for sensor in ("NDRE", "nRGB"):
            data = (SENTERA_D4K / sensor / f"{cap}.jpg").read_bytes()
            rgb = cv2.cvtColor(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            decoded[sensor] = (cv2.resize(rgb, SENTERA_6X_SHAPE[::-1], interpolation=cv2.INTER_AREA),
                               jpeg_xmp_packet(data).decode("utf-8"), _d4k_exif(SENTERA_D4K / sensor / f"{cap}.jpg"))
        for k, (band, (sub, sensor, ch, wl, fwhm)) in enumerate(SENTERA_6X_BANDS.items()):
            img, packet, ex = decoded[sensor]
            dn = img[:, :, ch].astype(np.uint16) * 16
            if panel and n == 1:
                rows, cols, value = SENTERA_6X_PANEL
                dn[rows, cols] = value
            xmp = _d4k_packet_one_band(packet, band, wl, fwhm, 3000.0 + 100 * k).encode("utf-8")
            path = session / sub / f"{cap}.tif"
            path.parent.mkdir(parents=True, exist_ok=True)
            tifffile.imwrite(path, dn, photometric="minisblack", software="2.0.0-21214", metadata=None, extratags=[
                (271, "s", 0, "Sentera", True), (272, "s", 0, "21214-00_3.2MP-GS-0001", True), (42016, "s", 0, f"{SENTERA_6X_SESSION}_{n}", True),
                (42036, "s", 0, "8.0mm-0001-0001", True), (33434, "2I", 1, ex["exposure"], True),
                (34855, "H", 1, ex["iso"], True), (36867, "s", 0, ex["time"], True),
                (37521, "s", 0, ex["subsec"], True), (700, 1, len(xmp), xmp, True)])
            PARAMS[str(path)] = {"iso": ex["iso"], "exposure": ex["exposure"]}
    return session


PARAMS: dict[str, dict[str, object]] = {}


# --------------------------------------------------------------------------- DJI band registration

# Per band: (tx, ty) px, rotation deg, scale of the physical image plane against the designed
# one (about the image centre), and the DewarpData's fx, cx, cy, k1 (the rest: DJI's example)
DJI_WARPS = {1: (3.2, -2.7, 0.25, 1.003, 1949.45, 28.0, -17.0, -0.4082), 2: (-1.5, 4.1, -0.2, 0.998, 1935.0, -12.0, 9.0, -0.39),
             3: (2.0, 2.0, 0.1, 1.0, 1960.0, 5.0, 20.0, -0.41), 4: (5.4, 1.3, -0.15, 1.001, 1942.0, 15.0, -6.0, -0.40),
             5: (0.0, 0.0, 0.0, 1.0, 1951.0, 0.0, 0.0, -0.4082)}


def dji_warp(band: int, shape: tuple[int, int] = (960, 1280)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The built band's CalibratedHMatrix H (physical -> designed plane), camera matrix K and
    distortion (k1, k2, p1, p2, k3) of :data:`DJI_WARPS`."""
    tx, ty, deg, sc, f, cx, cy, k1 = DJI_WARPS[band]
    h, w = shape
    c, s = np.cos(np.radians(deg)) * sc, np.sin(np.radians(deg)) * sc
    ox, oy = (w - 1) / 2, (h - 1) / 2
    hm = np.array([[c, -s, ox - c * ox + s * oy + tx], [s, c, oy - s * ox - c * oy + ty], [0, 0, 1]])
    k = np.array([[f, 0, DJI["center"][0] + cx], [0, f * 0.995, DJI["center"][1] + cy], [0, 0, 1]])
    return hm, k, np.array([k1, 0.3418, 0.00068, 0.00068, -0.3540])


def dji_p4m_warped(folder: Path, h_error: dict[int, tuple[float, float]] | None = None,
                   scenes: Sequence[np.ndarray] | None = None) -> Path:
    """P4 Multispectral captures whose bands show one scene (the real RedEdge NIR frame of the
    capture, DN as stored) through each band's own lens distortion and plane: stored band
    ``I_b(q) = scene(H_b u)``, ``u`` the undistorted point of ``q`` (OpenCV's iterative
    ``undistortPoints`` to 1e-12, camera matrix K_b kept). The tags say so (DewarpData, per-band
    CalibratedHMatrix), so the guide's steps 2-3 put every band back onto the scene's grid.
    ``h_error``: band (1-5) -> ``(dx, dy)`` px written wrong into its CalibratedHMatrix (a
    translation after ``H_b`` on the designed plane): the guide's steps then put that band at
    ``scene(x - (dx, dy))``, as a wrong matrix of the camera's firmware would. ``scenes``: one
    capture per (960, 1280) image (ids ``dji-scene-1``, ...) instead of the RedEdge NIR frames."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    h, w = 960, 1280
    qy, qx = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([qx.ravel(), qy.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    maps = {}
    for b in range(1, 6):  # stored pixel -> scene pixel, the same for every capture
        hm, k, dist = dji_warp(b)
        u = cv2.undistortPoints(pts, k, dist, R=None, P=k, criteria=crit).reshape(-1, 2)
        x = (hm @ np.stack([u[:, 0], u[:, 1], np.ones(len(u))]))
        maps[b] = (x[0] / x[2]).reshape(h, w).astype(np.float32), (x[1] / x[2]).reshape(h, w).astype(np.float32)
    shown = ([(f"dji-capture-{cap}", tifffile.imread(band_file(cap, 4))) for cap in CAPTURES] if scenes is None
             else [(f"dji-scene-{c}", s) for c, s in enumerate(scenes, start=1)])
    for c, (uuid, scene) in enumerate(shown, start=1):
        scene = np.asarray(scene, np.float32)
        for b in range(1, 6):
            hm, k, dist = dji_warp(b)
            dn = cv2.remap(scene, *maps[b], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
            dn = np.clip(np.rint(dn), 0, 65535).astype(np.uint16)
            dewarp = "2020-02-04;" + ",".join(f"{v:.10g}" for v in (k[0, 0], k[1, 1], k[0, 2] - DJI["center"][0],
                                                                     k[1, 2] - DJI["center"][1], dist[0], dist[1],
                                                                     dist[2], dist[3], dist[4]))
            err = (h_error or {}).get(b, (0.0, 0.0))
            written = np.array([[1, 0, err[0]], [0, 1, err[1]], [0, 0, 1]]) @ hm
            packet = dji_xmp(b, uuid, dewarp=dewarp,
                             hmatrix=",".join(f"{v:.12g}" for v in written.ravel())).encode("utf-8")
            tifffile.imwrite(folder / f"DJI_00{c}{b}.TIF", dn, photometric="minisblack", metadata=None, extratags=[
                (271, "s", 0, "DJI", True), (272, "s", 0, "FC6360", True), (50714, "H", 1, int(DJI["black"]), True),
                (700, 1, len(packet), packet, True)])
    return folder


SEQUOIA = DATA.parent / "parrot-sequoia"
SEQUOIA_CAPTURE = "IMG_180413_080658_0000"
SEQUOIA_BANDS = ("GRE", "RED", "REG", "NIR")


def sequoia_without_golden(folder: Path) -> Path:
    """The real Sequoia capture with ``Camera:IrradianceSensitivitiesGolden`` taken out of every
    band file (firmware that did not write it): IrradianceList, IrradianceCalibrationMeasurement
    and SensorModel intact."""
    folder.mkdir(parents=True, exist_ok=True)
    for band in SEQUOIA_BANDS:
        name = f"{SEQUOIA_CAPTURE}_{band}.TIF"

        def edit(xmp: str) -> str:
            new, n = re.subn(r'\s+Camera:IrradianceSensitivitiesGolden="[^"]*"', "", xmp)
            assert n == 1
            return new

        rewrite(SEQUOIA / name, folder / name, edit)
    return folder


# --------------------------------------------------------------------------- DJI P4M card

# EXIF (CIPA DC-008, "Exif 2.32") field types and the struct format of one item of each
EXIF_TYPES = {"BYTE": (1, "B"), "ASCII": (2, "s"), "SHORT": (3, "H"), "LONG": (4, "I"), "RATIONAL": (5, "II"),
              "UNDEFINED": (7, "s"), "SRATIONAL": (10, "ii"), "DOUBLE": (12, "d")}
# What the P4 Multispectral's RGB camera (FC6360) writes into its JPEG, the part mscal looks at
DJI_RGB = {"model": "FC6360", "exposure": (1, 1000), "f_number": (22, 10), "iso": 100,
           "lat": 47.3769, "lon": 8.5417, "alt_m": 512.25}
DJI_RGB_SHAPE = (48, 64)  # the real camera: 1300 x 1600; a small one keeps the card small


def _exif_value(kind: str, value: object) -> tuple[int, int, bytes]:
    """``(type code, count, little-endian bytes)`` of one EXIF entry's value: ASCII ``str``
    (NUL added), BYTE/UNDEFINED ``bytes``, SHORT/LONG ints, (S)RATIONAL ``(num, den)`` pairs
    (a zero denominator written as given), DOUBLE floats."""
    code, item = EXIF_TYPES[kind]
    if kind == "ASCII":
        raw = (value.encode("utf-8") if isinstance(value, str) else bytes(value)) + b"\x00"
        return code, len(raw), raw
    if kind in ("BYTE", "UNDEFINED"):
        return code, len(value), bytes(value)
    items = list(value) if isinstance(value, (list, tuple)) and not (
        kind.endswith("RATIONAL") and len(value) == 2 and isinstance(value[0], int)) else [value]
    raw = b"".join(struct.pack("<" + item, *(v if isinstance(v, tuple) else (v,))) for v in items)
    return code, len(items), raw


def _exif_ifd(entries: Sequence[tuple[int, str, object]], at: int, next_ifd: int) -> bytes:
    """One IFD at offset ``at`` of the TIFF block (entries sorted by tag, values over 4 bytes
    in a data area right after the IFD, each on a word boundary), ``next_ifd`` its link."""
    entries = sorted(entries, key=lambda e: e[0])
    data_at = at + 2 + 12 * len(entries) + 4
    head, data = [struct.pack("<H", len(entries))], b""
    for tag, kind, value in entries:
        code, count, raw = _exif_value(kind, value)
        if len(raw) <= 4:
            head.append(struct.pack("<HHI", tag, code, count) + raw.ljust(4, b"\x00"))
        else:
            head.append(struct.pack("<HHII", tag, code, count, data_at + len(data)))
            data += raw + b"\x00" * (len(raw) % 2)
    return b"".join(head) + struct.pack("<I", next_ifd) + data


def exif_app1(ifd0: Sequence[tuple[int, str, object]], exif: Sequence[tuple[int, str, object]] = (),
              gps: Sequence[tuple[int, str, object]] = (), thumbnail: bytes | None = None) -> bytes:
    """A JPEG APP1 EXIF segment (marker included): ``Exif\\0\\0``, a little-endian TIFF header,
    IFD0 (``ifd0`` + the ExifIFD 0x8769 and GPS IFD 0x8825 pointers when ``exif``/``gps``), the
    ExifIFD, the GPS IFD and, with ``thumbnail`` (a JPEG), IFD1: Compression 6,
    JPEGInterchangeFormat (0x0201, its offset) and JPEGInterchangeFormatLength (0x0202), the
    thumbnail's bytes last -- the layout that makes exifread return it as ``JPEGThumbnail``.
    Entries are ``(tag, type name of EXIF_TYPES, value)``; offsets are from the TIFF header."""
    def size(entries: Sequence[tuple[int, str, object]]) -> int:
        return len(_exif_ifd(entries, 0, 0))

    ifd0 = list(ifd0) + ([(0x8769, "LONG", 0)] if exif else []) + ([(0x8825, "LONG", 0)] if gps else [])
    thumb_ifd = [(0x0103, "SHORT", 6), (0x0201, "LONG", 0), (0x0202, "LONG", len(thumbnail or b""))]
    at0 = 8
    at_exif = at0 + size(ifd0)
    at_gps = at_exif + (size(exif) if exif else 0)
    at1 = at_gps + (size(gps) if gps else 0)
    at_thumb = at1 + (size(thumb_ifd) if thumbnail is not None else 0)
    ifd0 = [(t, k, at_exif if t == 0x8769 else at_gps if t == 0x8825 else v) for t, k, v in ifd0]
    thumb_ifd[1] = (0x0201, "LONG", at_thumb)
    tiff = b"II*\x00" + struct.pack("<I", at0) + _exif_ifd(ifd0, at0, at1 if thumbnail is not None else 0)
    tiff += _exif_ifd(exif, at_exif, 0) if exif else b""
    tiff += _exif_ifd(gps, at_gps, 0) if gps else b""
    if thumbnail is not None:
        tiff += _exif_ifd(thumb_ifd, at1, 0) + thumbnail
    body = b"Exif\x00\x00" + tiff
    assert len(body) + 2 <= 0xFFFF, "an APP1 segment holds at most 65533 bytes"
    return b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body


def gps_entries(lat: float, lon: float, alt_m: float) -> list[tuple[int, str, object]]:
    """The GPS IFD of a position: version 2.3, N/S and E/W, degrees/minutes/seconds, altitude
    above sea level."""
    from pipeline.ingest.exif import degrees_to_dms

    return [(0x0000, "BYTE", bytes((2, 3, 0, 0))), (0x0001, "ASCII", "N" if lat >= 0 else "S"),
            (0x0002, "RATIONAL", degrees_to_dms(lat)), (0x0003, "ASCII", "E" if lon >= 0 else "W"),
            (0x0004, "RATIONAL", degrees_to_dms(lon)), (0x0005, "BYTE", b"\x00"),
            (0x0006, "RATIONAL", (round(alt_m * 1000), 1000))]


def with_app1(jpeg: bytes, *segments: bytes) -> bytes:
    """``jpeg`` (as cv2.imencode writes it: SOI, APP0 JFIF, ...) with ``segments`` after its
    SOI (EXIF's APP1 then XMP's, where cameras put them)."""
    assert jpeg[:2] == b"\xff\xd8"
    return jpeg[:2] + b"".join(segments) + jpeg[2:]


def xmp_app1(packet: str) -> bytes:
    """An APP1 XMP segment (``http://ns.adobe.com/xap/1.0/``) holding ``packet``."""
    body = b"http://ns.adobe.com/xap/1.0/\x00" + packet.encode("utf-8")
    return b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body


def encode_jpeg(img: np.ndarray, quality: int = 90) -> bytes:
    import cv2

    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return enc.tobytes()


def dji_rgb_jpeg(path: Path, *, stamp: str = "2024:05:20 10:12:34", cap_uuid: str | None = None,
                 exif_extra: Sequence[tuple[int, str, object]] = (), thumbnail: bool = True,
                 maker_note: bytes | None = b"[ae_dbg_info:...]\x00DJI\x01\x02\xff" * 3) -> Path:
    """The RGB camera's JPEG of a P4 Multispectral capture: a small colour image with EXIF as
    the FC6360 writes it (Make DJI, Model FC6360, ExposureTime, FNumber, ISO, DateTimeOriginal,
    ExifImageWidth/Length, an undefined-bytes MakerNote, GPS) and an EXIF thumbnail (IFD1,
    JPEGInterchangeFormat: exifread's ``JPEGThumbnail``), and an XMP packet of DJI's flight
    tags (``drone-dji:`` altitude, gimbal and flight angles; ``cap_uuid`` as its CaptureUUID),
    no band or calibration tags. ``exif_extra``: further ExifIFD entries (replacing those of
    the same tag)."""
    h, w = DJI_RGB_SHAPE
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([xx * 255 // w, yy * 255 // h, np.full((h, w), 96)], axis=-1).astype(np.uint8)
    thumb = encode_jpeg(img[::4, ::4], 70) if thumbnail else None
    d = DJI_RGB
    exif = {t: (t, k, v) for t, k, v in [
        (0x829A, "RATIONAL", d["exposure"]), (0x829D, "RATIONAL", d["f_number"]), (0x8827, "SHORT", d["iso"]),
        (0x9000, "UNDEFINED", b"0230"), (0x9003, "ASCII", stamp), (0x9004, "ASCII", stamp),
        (0xA002, "LONG", w), (0xA003, "LONG", h),
        *([(0x927C, "UNDEFINED", maker_note)] if maker_note is not None else [])]}
    exif.update({t: (t, k, v) for t, k, v in exif_extra})
    app1 = exif_app1([(0x010F, "ASCII", "DJI"), (0x0110, "ASCII", d["model"]), (0x0112, "SHORT", 1)],
                     list(exif.values()), gps_entries(d["lat"], d["lon"], d["alt_m"]), thumb)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(with_app1(encode_jpeg(img), app1, xmp_app1(dji_rgb_xmp(cap_uuid))))
    return path


def dji_rgb_xmp(cap_uuid: str | None = None) -> str:
    """The XMP packet of the P4 Multispectral's RGB JPEG: DJI's flight tags (``drone-dji:``
    altitudes, gimbal and aircraft angles, RTK flag; ``cap_uuid`` as its CaptureUUID), no band
    or radiometric tags."""
    d = DJI_RGB
    attrs = {"drone-dji:AbsoluteAltitude": f"+{d['alt_m']:.2f}", "drone-dji:RelativeAltitude": "+60.10",
             "drone-dji:GimbalRollDegree": "+0.00", "drone-dji:GimbalYawDegree": "-12.30",
             "drone-dji:GimbalPitchDegree": "-89.90", "drone-dji:FlightRollDegree": "+1.20",
             "drone-dji:FlightYawDegree": "-12.50", "drone-dji:FlightPitchDegree": "-3.40",
             "drone-dji:RtkFlag": "50", **({"drone-dji:CaptureUUID": cap_uuid} if cap_uuid else {})}
    return ('<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
            '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
            'xmlns:tiff="http://ns.adobe.com/tiff/1.0/" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
            f'tiff:Make="DJI" tiff:Model="{d["model"]}" '
            + " ".join(f'{k}="{v}"' for k, v in attrs.items())
            + '/></rdf:RDF></x:xmpmeta><?xpacket end="w"?>')


def dji_card(folder: Path) -> Path:
    """A P4 Multispectral SD card as the drone writes it: ``folder/DCIM/100MEDIA/`` holding two
    captures, each the RGB camera's ``DJI_00N0.JPG`` (:func:`dji_rgb_jpeg`: EXIF with a
    thumbnail, maker note and GPS) and the five band files ``DJI_00N1.TIF .. DJI_00N5.TIF``
    (:func:`dji_p4m`: DJI's documented tags). Returns ``folder`` (the card's root)."""
    media = dji_p4m(folder / "DCIM" / "100MEDIA")
    for c, cap in enumerate(CAPTURES, start=1):
        dji_rgb_jpeg(media / f"DJI_00{c}0.JPG", stamp=f"2024:05:20 10:12:{30 + c:02d}", cap_uuid=f"dji-capture-{cap}")
    return folder
