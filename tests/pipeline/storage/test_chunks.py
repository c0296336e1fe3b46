"""pipeline.storage.chunks: whole-frame chunk files, byte-identical to zarr's own and read back by it."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
import zarr
import zarr.codecs
from zarr.core.sync import sync

from pipeline.storage.chunks import FLAT_CHUNK_KEYS, FrameChunks

CODECS = {
    "raw": None,
    "lz4": [zarr.codecs.BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")],
    "zstd-bit": [zarr.codecs.BloscCodec(cname="zstd", clevel=1, shuffle="bitshuffle", typesize=2)],
}


@pytest.mark.parametrize("separator", ["/", "."])
@pytest.mark.parametrize("codec", list(CODECS))
@pytest.mark.parametrize("dtype", ["uint16", "float32", "uint8"])
def test_chunks_match_zarr_and_read_back(tmp_path, separator, codec, dtype) -> None:
    keys = {"name": "default", "separator": separator}
    a = zarr.create_array(str(tmp_path / "a"), shape=(5, 3, 20, 30), chunks=(1, 3, 20, 30), dtype=dtype,
                          compressors=CODECS[codec], chunk_key_encoding=keys)
    fc = FrameChunks.open(tmp_path / "a")
    assert fc is not None and fc.separator == separator
    rng = np.random.default_rng(1)
    x = (rng.random((3, 20, 30)) * 200).astype(dtype)
    fc.write(3, x)
    np.testing.assert_array_equal(zarr.open_array(str(tmp_path / "a"))[3], x)
    np.testing.assert_array_equal(fc.read(3), x)
    a[1] = x  # zarr's own chunk for the same data: the same bytes
    assert fc.chunk_path(1).read_bytes() == bytes(fc.encode(x))
    assert not list((tmp_path / "a").rglob("*.partial"))


@pytest.mark.parametrize("separator", ["/", "."])
def test_remove_from_deletes_the_frames_chunks_beyond_the_shape_too(tmp_path, separator) -> None:
    """Chunks of frames from ``n`` on go, those the shape no longer covers included (a run
    killed while a commit had shrunk the array below chunks still being written); the frames
    before stay, and nothing else in the array's folder is touched."""
    keys = {"name": "default", "separator": separator}
    zarr.create_array(str(tmp_path / "a"), shape=(12, 2, 4), chunks=(1, 2, 4), dtype="uint16",
                      compressors=None, chunk_key_encoding=keys)
    fc = FrameChunks.open(tmp_path / "a")
    assert fc is not None
    for f in range(12):
        fc.write(f, np.full((2, 4), f, np.uint16))
    arr = zarr.open_array(str(tmp_path / "a"), mode="r+")
    sync(arr.async_array.resize((6, 2, 4), delete_outside_chunks=False))  # 6..11 left outside
    fc.remove_from(3)
    assert [f for f in range(12) if fc.chunk_path(f).exists()] == [0, 1, 2]
    assert (tmp_path / "a" / "zarr.json").is_file()
    np.testing.assert_array_equal(zarr.open_array(str(tmp_path / "a"))[2], np.full((2, 4), 2))
    fc.remove_from(0)
    FrameChunks.open(tmp_path / "a").remove_from(0)  # nothing left: no error
    assert not any(fc.chunk_path(f).exists() for f in range(12))


def test_flat_keys_through_xarray(tmp_path) -> None:
    ds = xr.Dataset({"v": (("frame", "y", "x"), np.zeros((4, 6, 7), np.float32))})
    ds.to_zarr(tmp_path / "s.zarr", zarr_format=3, consolidated=True, compute=True,
               encoding={"v": {"chunks": (1, 6, 7), "chunk_key_encoding": FLAT_CHUNK_KEYS, "compressors": None}})
    fc = FrameChunks.open(tmp_path / "s.zarr" / "v")
    assert fc is not None and fc.chunk_path(2).name == "c.2.0.0"
    fc.write(2, np.full((6, 7), 2.5, np.float32))
    got = xr.open_zarr(tmp_path / "s.zarr")["v"].values
    assert got[2].tolist() == np.full((6, 7), 2.5).tolist() and not got[[0, 1, 3]].any()


def test_other_layouts_are_left_to_zarr(tmp_path) -> None:
    zarr.create_array(str(tmp_path / "multi"), shape=(4, 10), chunks=(2, 10), dtype="f4")
    zarr.create_array(str(tmp_path / "split"), shape=(4, 10), chunks=(1, 5), dtype="f4")
    zarr.create_array(str(tmp_path / "shard"), shape=(4, 10), chunks=(1, 10), shards=(2, 10), dtype="f4")
    zarr.create_array(str(tmp_path / "gzip"), shape=(4, 10), chunks=(1, 10), dtype="f4",
                      compressors=[zarr.codecs.GzipCodec()])
    for name in ("multi", "split", "shard", "gzip", "missing"):
        assert FrameChunks.open(tmp_path / name) is None, name
    zarr.create_array(str(tmp_path / "zstd"), shape=(4, 10), chunks=(1, 10), dtype="f4")  # zarr's default codec
    assert FrameChunks.open(tmp_path / "zstd") is None
    ok = zarr.create_array(str(tmp_path / "ok"), shape=(4, 10), chunks=(1, 10), dtype="f4", compressors=None)
    with pytest.raises(ValueError, match="is \\(10,\\)"):
        FrameChunks.open(tmp_path / "ok").write(0, np.zeros(11, np.float32))
    assert ok.shape == (4, 10)


def test_template_of_unwritten_frames_then_frames_written_whole(tmp_path) -> None:
    """A store template as apply makes it (one lazy dask chunk, never computed; one Zarr chunk
    per frame from frame_encoding): the same metadata as a template with one dask chunk per
    frame, no chunk file until a frame is written, then each frame's chunk as FrameChunks
    wrote it, read through xarray."""
    import dask.array as da

    from pipeline.storage.chunks import frame_encoding, unwritten_frames

    n, shape = 5, (3, 4, 6)
    lazy = unwritten_frames((n, *shape), np.float32)
    assert lazy.numblocks == (1, 1, 1, 1) and lazy.shape == (n, *shape)
    stores = {}
    per_frame = da.zeros((n, *shape), chunks=(1, *shape), dtype=np.float32)
    for name, data in (("one", lazy), ("per_frame", per_frame)):
        ds = xr.Dataset({"reflectance": (("frame", "band", "y", "x"), data)},
                        coords={"frame": np.array([f"f{i}" for i in range(n)], dtype=object)})
        path = tmp_path / f"{name}.zarr"
        ds.to_zarr(path, mode="w", compute=False, consolidated=False, zarr_format=3,
                   encoding={"reflectance": frame_encoding(ds["reflectance"].shape, None)})
        stores[name] = path
    one, per = ((stores[k] / "reflectance" / "zarr.json").read_text() for k in ("one", "per_frame"))
    assert one == per
    assert not [p for p in (stores["one"] / "reflectance").iterdir() if p.name != "zarr.json"]
    fc = FrameChunks.open(stores["one"] / "reflectance")
    assert fc is not None
    frames = np.random.default_rng(0).random((n, *shape)).astype(np.float32)
    for f in (3, 0):
        fc.write(f, frames[f])
    got = xr.open_zarr(stores["one"], consolidated=False)["reflectance"].values
    np.testing.assert_array_equal(got[[0, 3]], frames[[0, 3]])
    assert np.isnan(got[[1, 2, 4]]).all()  # never written: the fill value (NaN for xarray floats)
