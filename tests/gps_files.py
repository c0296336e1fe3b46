"""Band files of the real MicaSense RedEdge sample with their GPS and time rewritten in place:
a receiver without a fix (latitude and longitude 0, or GPSStatus V) and a position the flight
could not have reached."""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

import tifffile

from tests.camera_files import _exif_ifd, gps_entries, rewrite
from tests.micasense_data import DATA


def set_gps(path: Path, lat: float, lon: float, alt_m: float, status: str | None = None) -> Path:
    """Give a TIFF a new GPS IFD (appended at the end of the file, IFD0's GPSInfo pointed at
    it): ``lat``/``lon`` in degrees, ``alt_m``, and with ``status`` an EXIF GPSStatus."""
    with tifffile.TiffFile(path) as tif:
        assert tif.byteorder == "<" and not tif.is_bigtiff
        entry = tif.pages[0].tags[34853].offset  # the IFD0 entry: tag, type, count, value
    entries = gps_entries(lat, lon, alt_m) + ([(0x0009, "ASCII", status)] if status else [])
    size = path.stat().st_size
    at = size + size % 2
    with path.open("r+b") as fh:
        fh.seek(size)
        fh.write(b"\x00" * (at - size) + _exif_ifd(entries, at, 0))
        fh.seek(entry + 8)
        fh.write(struct.pack("<I", at))
    return path


def copy_sample(folder: Path) -> Path:
    """The sample's band files (IMG_0000: panel capture, IMG_0001: flight capture) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for p in sorted(DATA.glob("IMG_*.tif")):
        shutil.copyfile(p, folder / p.name)
        (folder / p.name).chmod(0o644)
    return folder


def copy_capture(src: Path, capture: str, new: str, *, seconds_later: int, lat: float, lon: float, alt_m: float
                 ) -> None:
    """IMG_<new>_1..5.tif in ``src``'s folder: IMG_<capture>'s files with another CaptureId,
    a time ``seconds_later`` (DateTime, DateTimeOriginal, DateTimeDigitized; under a minute,
    in the same minute) and the given position."""
    for b in range(1, 6):
        dst = src / f"IMG_{new}_{b}.tif"
        rewrite(src / f"IMG_{capture}_{b}.tif", dst,
                lambda x: re.sub(r"(<MicaSense:CaptureId>)(.*?)(</MicaSense:CaptureId>)",
                                 lambda m: m[1] + m[2][:-4] + "COPY" + m[3], x))
        data = bytearray(dst.read_bytes())
        with tifffile.TiffFile(dst) as tif:
            stamp = tif.pages[0].tags[34665].value["DateTimeOriginal"]
        sec = int(stamp[-2:]) + seconds_later
        assert sec < 60, "stay in the minute"
        later = (stamp[:-2] + f"{sec:02d}").encode()
        dst.write_bytes(bytes(data).replace(stamp.encode(), later))
        set_gps(dst, lat, lon, alt_m)
