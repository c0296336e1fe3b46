"""The shortcuts in the factory path give the values of the longer way, exactly: the sun
sensor from the XMP properties kept with each band file's metadata (not a second read of the
file), the report's frame levels straight from raw.zarr's chunk files with a counting median."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.apply.captures import capture_times, find_captures
from pipeline.ingest import sunsensor as sunlight
from pipeline.ingest.camera_meta import read_file_metas, sun_sensor_xmp, sun_sensor_xmp_names
from pipeline.ingest.identify import identify_camera
from pipeline.ingest.medians import DN_MEDIAN, band_medians, median_uint16
from pipeline.products.report import flight as report_flight
from pipeline.products.report.flight import frame_levels
from pipeline.products.report.inputs import open_flight

SHARED = Path(__file__).parents[3].parent / "shared" / "data"


@pytest.mark.parametrize("camera", ["micasense-rededge", "parrot-sequoia"])
def test_sensor_light_from_kept_properties_equals_reading_the_files(camera, monkeypatch) -> None:
    folder = SHARED / camera
    if not folder.is_dir():
        pytest.skip(f"{camera} sample not found")
    caps = find_captures(folder, identify_camera(folder, None).camera).captures
    assert all(m.sun_sensor_props is not None for c in caps for m in c.metas)
    kept = sunlight.sensor_light(caps, capture_times(caps))
    monkeypatch.setattr(sunlight, "sun_sensor_xmp", lambda meta: None)  # the files' XMP, read again
    again = sunlight.sensor_light(caps, capture_times(caps))
    for f in dataclasses.fields(kept):
        a, b = getattr(kept, f.name), getattr(again, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b, f.name


def test_kept_properties_are_the_files_own() -> None:
    files = sorted((SHARED / "micasense-rededge").glob("*.tif")) + sorted((SHARED / "parrot-sequoia").glob("*.TIF"))
    if not files:
        pytest.skip("no sample files")
    for path in files:
        meta = read_file_metas(path)[0]
        full = sunlight.file_xmp(path).props
        want = {k: v for k, v in full.items() if k[1] in sun_sensor_xmp_names()}
        assert want, path  # every sample carries a reading
        assert sun_sensor_xmp(meta).props == want
        assert meta == dataclasses.replace(meta, sun_sensor_props=None)  # not part of the metadata's identity
        hash(meta)


def test_counting_median_is_numpys() -> None:
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 9, 10, 4097, 10_000):
        for top in (1, 2, 255, 4096, 65536):
            v = rng.integers(0, top, n).astype(np.uint16)
            assert median_uint16(v) == np.median(v.astype(np.float64))
    assert median_uint16(np.array([65534, 65535], np.uint16)) == 65534.5
    assert median_uint16(np.array([[7, 1], [3, 200]], np.uint8)) == 5.0
    cube = rng.integers(0, 4096, (3, 17, 9)).astype(np.uint16)
    np.testing.assert_array_equal(band_medians(cube), np.median(cube.astype(np.float64), axis=(1, 2)))
    # full-resolution bands (OpenCV's histogram), a non-contiguous view, a constant band
    for top in (1, 1024, 65536):
        band = rng.integers(0, top, (217, 409)).astype(np.uint16)
        for v in (band, band[::2, 1::3], band.T):
            assert median_uint16(v) == np.median(v.astype(np.float64)), (top, v.shape)
    skewed = np.minimum(rng.exponential(40, (1088, 2048)), 1023).astype(np.uint16)
    assert median_uint16(skewed) == np.median(skewed.astype(np.float64))


def test_counting_median_of_wide_values_in_two_steps(monkeypatch) -> None:
    """16-bit values (MicaSense bands) are counted by high byte, then by the low bytes of the
    middle values' high byte: np.median's value, wherever the middle ranks fall (across two
    high bytes, at a bin's first or last value, on a constant band, 12-bit DN in the high
    bits with a low bit set somewhere), and the same as one count per value."""
    import pipeline.ingest.medians as medians

    rng = np.random.default_rng(12)
    cases = [rng.integers(0, 65536, n).astype(np.uint16) for n in (1, 2, 3, 4, 255, 256, 257, 4097)]
    cases += [np.array([4095, 4096], np.uint16), np.array([4351, 4352, 4352, 9000], np.uint16),
              np.array([255, 256, 65535, 0], np.uint16), np.full((30, 40), 65535, np.uint16),
              ((rng.integers(0, 4096, (960, 1280)) << 4) | (rng.random((960, 1280)) < 1e-5)).astype(np.uint16),
              np.where(rng.random((200, 301)) < 0.5, rng.integers(0, 256, (200, 301)),
                       rng.integers(60_000, 65_536, (200, 301))).astype(np.uint16)]
    band = rng.integers(4000, 4300, (217, 409)).astype(np.uint16)
    cases += [band, band[::2, 1::3], band.T]
    calls = []
    real = medians._ranked_wide
    monkeypatch.setattr(medians, "_ranked_wide", lambda *a: calls.append(1) or real(*a))
    for v in cases:
        want = np.median(v.astype(np.float64))
        assert median_uint16(v) == want, v.shape
    assert len(calls) == len(cases)  # every case reaches 4096: the two-step count
    monkeypatch.setattr(medians, "_WIDE_HISTOGRAM", 1 << 16)  # one count per value: the same medians
    assert [median_uint16(v) for v in cases] == [np.median(v.astype(np.float64)) for v in cases]
    assert len(calls) == len(cases)


def test_counting_median_of_wide_values_with_low_zero_bits_in_one_count(monkeypatch) -> None:
    """12-bit DN stored in the high bits of 16 (MicaSense band files) have their low 4 bits 0:
    they are counted shifted down, in one count, not two; np.median's value, also where the
    shift does not bring them below 4096 (then counted in two steps) and on views."""
    import pipeline.ingest.medians as medians

    rng = np.random.default_rng(13)
    calls = []
    real = medians._ranked_wide
    monkeypatch.setattr(medians, "_ranked_wide", lambda *a: calls.append(1) or real(*a))
    shifted = [(rng.integers(0, 4096, (960, 1280)) << 4).astype(np.uint16), np.array([4096, 8192], np.uint16),
               np.array([61440], np.uint16), (rng.integers(1, 4096, (217, 409)) << 4).astype(np.uint16)[::3, 1::2],
               (rng.integers(0, 16, 101) << 12).astype(np.uint16)]
    for v in shifted:
        assert median_uint16(v) == np.median(v.astype(np.float64)), v.shape
    assert calls == []
    wide = (rng.integers(0, 1 << 14, 999) << 2).astype(np.uint16)  # 14-bit: still past 4096 after the shift
    assert median_uint16(wide) == np.median(wide.astype(np.float64)) and calls == [1]


def test_counting_median_of_more_values_than_float32_counts_exactly(monkeypatch) -> None:
    """Past 2**24 values OpenCV's float32 counts would round: those arrays are counted by
    numpy (the limit lowered here so the test stays small)."""
    import cv2

    import pipeline.ingest.medians as medians

    v = np.random.default_rng(6).integers(0, 300, 5_001).astype(np.uint16)
    want = np.median(v.astype(np.float64))

    def not_here(*args, **kwargs):
        raise AssertionError("OpenCV's float32 counts used past the exact limit")

    monkeypatch.setattr(cv2, "calcHist", not_here)
    monkeypatch.setattr(medians, "_EXACT_HISTOGRAM", 5_001)
    assert median_uint16(v) == want  # numpy's count
    monkeypatch.setattr(medians, "_EXACT_HISTOGRAM", 5_002)
    with pytest.raises(AssertionError, match="exact limit"):
        median_uint16(v)  # below the limit: OpenCV's


def test_frame_levels_from_stored_medians_equal_decoding_the_frames(tmp_path: Path) -> None:
    """A capture folder's raw.zarr keeps each band's median DN, written with the frame; the
    report's levels from it are those of the frames decoded again (an older raw.zarr)."""
    from pipeline.run.cli import main

    folder = SHARED / "micasense-rededge"
    if not folder.is_dir():
        pytest.skip("no MicaSense sample")
    out = tmp_path / "out"
    assert main(["apply", str(folder), "--calibration", "factory", "-o", str(out)]) == 0
    flight = open_flight(out)
    stored = flight.raw[DN_MEDIAN].values
    dn = flight.raw["dn"].values
    np.testing.assert_array_equal(stored, np.median(dn.astype(np.float64), axis=(2, 3)))
    fast = frame_levels(flight)
    assert len(fast) == dn.shape[0] and all(np.isfinite(v) and v > 0 for v in fast.values())
    older = dataclasses.replace(flight, raw=flight.raw.drop_vars(DN_MEDIAN))
    assert frame_levels(older) == fast


def test_frame_levels_from_chunk_files_equal_the_dask_read(applied, monkeypatch) -> None:
    out = applied[2]
    flight = open_flight(out)
    # a snapshot flight's raw.zarr keeps its band medians too; without them (an older cube) the
    # report decodes the frames again, from the chunk files or through dask: the same levels
    np.testing.assert_array_equal(flight.raw[DN_MEDIAN].values,
                                  np.median(flight.raw["dn"].values.astype(np.float64), axis=(2, 3)))
    stored = frame_levels(flight)
    flight = dataclasses.replace(flight, raw=flight.raw.drop_vars(DN_MEDIAN))
    fast = frame_levels(flight)
    assert len(fast) >= 3 and all(np.isfinite(v) for v in fast.values())
    assert stored == fast
    monkeypatch.setattr(report_flight.FrameChunks, "open", staticmethod(lambda path: None))
    monkeypatch.setattr(report_flight, "median_uint16", lambda v: float(np.median(np.asarray(v, dtype=float))))
    assert frame_levels(flight) == fast


def test_frame_levels_of_a_sample_of_the_frames_read_only_their_medians(applied, monkeypatch) -> None:
    """Past LEVEL_MAX_FRAMES the report checks evenly spaced frames: the stored medians of just
    those frames (one chunk each) give each its own level, as decoding those frames does."""
    flight = open_flight(applied[2])
    n = flight.raw.sizes["frame"]
    assert n >= 3
    monkeypatch.setattr(report_flight, "LEVEL_MAX_FRAMES", 2)
    stored = frame_levels(flight)
    names = [str(f) for f in flight.raw["frame"].values]
    assert list(stored) == [names[0], names[-1]]
    decoded = frame_levels(dataclasses.replace(flight, raw=flight.raw.drop_vars(DN_MEDIAN)))
    assert stored == decoded
    monkeypatch.setattr(report_flight, "LEVEL_MAX_FRAMES", n)
    every = frame_levels(flight)
    assert stored == {k: every[k] for k in stored} and len(set(every.values())) > 1
    # the medians through zarr (a layout FrameChunks does not write) give the same levels
    monkeypatch.setattr(report_flight.FrameChunks, "open", staticmethod(lambda path: None))
    assert frame_levels(flight) == every


def test_kept_properties_hold_every_orientation_the_model_reads(tmp_path: Path) -> None:
    """DJI writes no sensor orientation of its own: the aircraft's FlightYaw/Pitch/RollDegree
    must survive in the kept properties, or the tilt model would take a level sensor."""
    from tests import camera_files as cf

    if not (SHARED / "micasense-rededge").is_dir():
        pytest.skip("no MicaSense sample")
    folder = tmp_path / "dji"
    folder.mkdir()
    angles = 'drone-dji:FlightYawDegree="+37.5" drone-dji:FlightPitchDegree="-9.25" drone-dji:FlightRollDegree="+6.0" '
    packet = cf.dji_xmp(1, "dji-capture-x").replace('drone-dji:SensorGain=', angles + 'drone-dji:SensorGain=')
    cf.rewrite(cf.band_file(cf.CAPTURES[0], 1), folder / "DJI_0011.TIF", lambda _x: packet, make="DJI",
               model="FC6360", black=(3200,))
    path = folder / "DJI_0011.TIF"
    meta = read_file_metas(path)[0]
    full = sunlight.sensor_orientation(sunlight.file_xmp(path))
    kept = sunlight.sensor_orientation(sun_sensor_xmp(meta))
    assert full is not None and full.source.startswith("drone-dji")
    assert kept == full
    assert np.degrees([kept.yaw, kept.pitch, kept.roll]) == pytest.approx([37.5, -9.25, 6.0])


def test_sampled_frames_from_chunk_files_equal_the_xarray_read(applied) -> None:
    """The report's frame samples (the DN of the warning that ``mscal apply`` prints, the
    reflectance histograms) read straight from the chunk files, a thread per core, are the
    values xarray reads: raw DN as uint16, reflectance as float32."""
    flight = open_flight(applied[2])
    n = flight.raw.sizes["frame"]
    frames = report_flight.sample_indices(n, n)
    assert len(frames) >= 3
    for da, chunks in ((flight.raw["dn"], report_flight._chunk_files(flight, "dn")),
                       (flight.reflectance["reflectance"],
                        report_flight._chunk_files(flight, "reflectance", "reflectance.zarr"))):
        assert chunks is not None, da.name
        fast = report_flight._sampled(da, frames, 2_000, chunks)
        slow = report_flight._sampled(da, frames, 2_000)
        assert fast.dtype == slow.dtype == da.dtype and fast.shape == slow.shape
        assert fast.shape[0] == len(frames) and fast.shape[-1] < da.shape[-1]  # strided
        np.testing.assert_array_equal(fast, slow)
    assert fast.dtype == np.float32 and np.isfinite(fast).mean() > 0.75  # flagged pixels (V unobserved) are NaN


def test_sampled_frames_fall_back_to_xarray_where_the_files_differ(applied, tmp_path: Path) -> None:
    """A frame without its chunk file reads as zarr's fill value, and an array xarray would
    decode (scale, offset, a fill value other than NaN) is not read from the files at all."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(applied[2], out)
    flight = open_flight(out)
    chunks = report_flight._chunk_files(flight, "dn")
    (chunks.chunk_path(1)).unlink()
    frames = np.array([0, 1])
    got = report_flight._sampled(flight.raw["dn"], frames, 2_000, chunks)
    assert (got[1] == 0).all() and got[0].any()
    np.testing.assert_array_equal(got, report_flight._sampled(flight.raw["dn"], frames, 2_000))
    for key, value in (("scale_factor", 0.5), ("add_offset", 1.0), ("_FillValue", 7)):
        decoded = flight.raw.copy()
        decoded["dn"].encoding[key] = value
        assert report_flight._chunk_files(dataclasses.replace(flight, raw=decoded), "dn") is None, key
    refl = flight.reflectance.copy()
    refl["reflectance"].encoding["_FillValue"] = -1.0
    assert report_flight._chunk_files(dataclasses.replace(flight, reflectance=refl), "reflectance",
                                      "reflectance.zarr") is None
