"""DJI band files (pipeline.ingest.cameras.dji): band names and wavelengths as the manuals spell them,
exposure time zones, black levels."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import camera_files as cf
from tests.micasense_data import require_data


def _dji_tags(packet: str) -> tuple[Path, dict]:
    """The tags of a real band file with a DJI XMP packet and DJI's EXIF black level (4096)."""
    import tifffile

    require_data()
    path = cf.band_file("0000", 2)
    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    tags.update({700: packet.encode(), 271: "DJI", 272: "M3M", 50714: (4096,)})
    return path, tags


def test_dji_band_from_the_mavic_3m_manuals_spellings() -> None:
    """The Mavic 3M User Manual ("Photo File") writes BandFreq ``560(±16)nm`` and
    ``drone-dji:CentralWavelength``; the P4 Multispectral guide ``840(+/-26)nm``. Each names the
    band; drone-dji:CentralWavelength wins over BandFreq's centre."""
    from pipeline.ingest.camera_meta import meta_from_tags

    base = cf.dji_xmp(2, "abc", band_freq=True)  # BandFreq 560(+/-16)nm, no Camera: band tags
    for freq, extra, want in (("560(+/-16)nm", "", (560.0, 32.0)), ("560(\u00b116)nm", "", (560.0, 32.0)),
                              ("560 (\u00b1 16) nm", "", (560.0, 32.0)),
                              ("garbled", 'drone-dji:CentralWavelength="561" ', (561.0, None)),
                              ("560(\u00b116)nm", 'drone-dji:CentralWavelength="561" ', (561.0, 32.0))):
        packet = base.replace('drone-dji:BandFreq="560(+/-16)nm"', f'{extra}drone-dji:BandFreq="{freq}"')
        assert freq in packet
        m = meta_from_tags(*_dji_tags(packet), (960, 1280), 16)
        assert (m.band_name, m.wavelength_nm, m.fwhm_nm) == ("Green", *want), freq
    with pytest.raises(Exception, match="drone-dji:CentralWavelength"):
        meta_from_tags(*_dji_tags(base.replace("560(+/-16)nm", "garbled")), (960, 1280), 16)


def test_exposure_time_in_utc_when_the_file_says_its_zone() -> None:
    """drone-dji:UTCAtExposure (UTC) wins over a DJI file's local DateTimeOriginal; EXIF 2.31
    OffsetTimeOriginal turns DateTimeOriginal into UTC; without either the time is as written
    (zone unknown: MicaSense's, which its own library reads as UTC). A garbled UTCAtExposure
    or offset leaves the time as written."""
    from pipeline.ingest.camera_meta import meta_from_tags

    packet = cf.dji_xmp(2, "abc")
    path, tags = _dji_tags(packet)
    assert meta_from_tags(path, tags, (960, 1280), 16).time == "2017-10-19T20:40:39.200173789"
    for stamp, want in (("2017:10:20 03:40:39.25", "2017-10-20T03:40:39.25Z"), ("2017:10:20 03:40:39", "2017-10-20T03:40:39Z"),
                        ("garbled", "2017-10-19T20:40:39.200173789")):
        p = packet.replace("drone-dji:SensorIndex=", f'drone-dji:UTCAtExposure="{stamp}" drone-dji:SensorIndex=')
        assert meta_from_tags(*_dji_tags(p), (960, 1280), 16).time == want, stamp
    for offset, want in (("-07:00", "2017-10-20T03:40:39.200173789Z"), ("+09:30", "2017-10-19T11:10:39.200173789Z"),
                         ("+00:00", "2017-10-19T20:40:39.200173789Z"), ("   ", "2017-10-19T20:40:39.200173789"),
                         ("+7", "2017-10-19T20:40:39.200173789")):
        exif = {**tags[34665], "OffsetTimeOriginal": offset}
        assert meta_from_tags(path, {**tags, 34665: exif}, (960, 1280), 16).time == want, offset


def test_dji_black_level_from_exif_xmp_or_the_manuals_black_current() -> None:
    """EXIF BlackLevel first (P4 Multispectral guide), else drone-dji:BlackLevel (Mavic 3M
    guide), else drone-dji:BlackCurrent (the Mavic 3M User Manual's name for it)."""
    from pipeline.ingest.camera_meta import meta_from_tags

    packet = cf.dji_xmp(2, "abc", band_freq=True)
    path, tags = _dji_tags(packet)
    assert meta_from_tags(path, tags, (960, 1280), 16).black_levels == (4096.0,)
    del tags[50714]
    for attr, want in (('drone-dji:BlackLevel="3200" ', (3200.0,)), ('drone-dji:BlackCurrent="3200" ', (3200.0,)),
                       ('drone-dji:BlackLevel="3100" drone-dji:BlackCurrent="3200" ', (3100.0,))):
        tags[700] = packet.replace("drone-dji:SensorGain=", attr + "drone-dji:SensorGain=").encode()
        assert meta_from_tags(path, tags, (960, 1280), 16).black_levels == want, attr
    tags[700] = packet.encode()
    with pytest.raises(Exception, match="BlackLevel"):
        meta_from_tags(path, tags, (960, 1280), 16)
