"""pipeline.storage.directio: files written past the page cache hold exactly the bytes given, and
every case that cannot take O_DIRECT falls back to an ordinary write."""

from __future__ import annotations

import errno
import os
import threading

import numpy as np
import pytest

from pipeline.storage import directio
from pipeline.storage.directio import MIN_BYTES, write_file


@pytest.fixture(autouse=True)
def _fresh_state(monkeypatch):
    monkeypatch.delenv("MSCAL_DIRECT_IO", raising=False)
    monkeypatch.setattr(directio, "_refused", set())


def _payload(n: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def _direct_possible(folder) -> bool:
    """Whether this file system takes O_DIRECT at all (tmpfs does not)."""
    if not hasattr(os, "O_DIRECT"):
        return False
    try:
        fd = os.open(folder / ".probe", os.O_WRONLY | os.O_CREAT | os.O_DIRECT, 0o600)
    except OSError:
        return False
    os.close(fd)
    os.unlink(folder / ".probe")
    return True


@pytest.mark.parametrize("n", [0, 100, MIN_BYTES - 1, MIN_BYTES, 4096 * 40, 4096 * 40 + 1, 8_874_100])
def test_bytes_round_trip_at_every_size(tmp_path, n) -> None:
    data = _payload(n, seed=n)
    how = write_file(tmp_path / "f.bin", [data])
    assert (tmp_path / "f.bin").read_bytes() == data
    expected = "direct" if n >= MIN_BYTES and _direct_possible(tmp_path) else "buffered"
    assert how == expected


def test_parts_are_concatenated_and_arrays_taken_as_bytes(tmp_path) -> None:
    head = b"II*\0" + bytes(1000)
    pixels = np.arange(217 * 409, dtype="<u2").reshape(217, 409)
    write_file(tmp_path / "f.tif", [head, pixels])
    raw = (tmp_path / "f.tif").read_bytes()
    assert raw[: len(head)] == head
    assert np.array_equal(np.frombuffer(raw[len(head):], "<u2").reshape(217, 409), pixels)


def test_exclusive_refuses_an_existing_file_and_keeps_it(tmp_path) -> None:
    p = tmp_path / "f.bin"
    p.write_bytes(b"old")
    for n in (10, 2 * MIN_BYTES):
        with pytest.raises(FileExistsError):
            write_file(p, [_payload(n)])
        assert p.read_bytes() == b"old"
    write_file(p, [_payload(2 * MIN_BYTES, 3)], exclusive=False)
    assert p.read_bytes() == _payload(2 * MIN_BYTES, 3)
    write_file(p, [b"short"], exclusive=False)  # replaces, no stale tail
    assert p.read_bytes() == b"short"


def test_missing_folder_raises_file_not_found(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        write_file(tmp_path / "no" / "f.bin", [_payload(2 * MIN_BYTES)])


def test_environment_switch_turns_it_off(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MSCAL_DIRECT_IO", "0")
    data = _payload(3 * MIN_BYTES)
    assert write_file(tmp_path / "f.bin", [data]) == "buffered"
    assert (tmp_path / "f.bin").read_bytes() == data


def test_file_system_refusing_o_direct_falls_back_and_is_remembered(tmp_path, monkeypatch) -> None:
    calls = []
    real_open = os.open

    def refusing_open(path, flags, *args):
        if flags & getattr(os, "O_DIRECT", 0):
            calls.append(path)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *args)

    monkeypatch.setattr(directio.os, "open", refusing_open)
    monkeypatch.setattr(directio.os, "O_DIRECT", 0o40000, raising=False)
    data = _payload(2 * MIN_BYTES)
    assert write_file(tmp_path / "a.bin", [data]) == "buffered"
    assert write_file(tmp_path / "b.bin", [data]) == "buffered"
    assert (tmp_path / "a.bin").read_bytes() == data == (tmp_path / "b.bin").read_bytes()
    assert len(calls) == 1  # the refusal is remembered for that file system


def test_write_refused_after_open_falls_back(tmp_path, monkeypatch) -> None:
    if not _direct_possible(tmp_path):
        pytest.skip("this file system does not take O_DIRECT")

    def refusing_pwrite(fd, data, offset):
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.setattr(directio.os, "pwrite", refusing_pwrite)
    data = _payload(2 * MIN_BYTES + 5)
    assert write_file(tmp_path / "f.bin", [data]) == "buffered"
    assert (tmp_path / "f.bin").read_bytes() == data


def test_threads_each_write_their_own_bytes(tmp_path) -> None:
    sizes = [MIN_BYTES + 7 * k for k in range(8)] + [3_000_000 + k for k in range(8)]
    errors: list[BaseException] = []

    def work(k: int) -> None:
        try:
            for rep in range(3):
                write_file(tmp_path / f"f{k}_{rep}.bin", [_payload(sizes[k], seed=k * 10 + rep)])
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(sizes))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for k, n in enumerate(sizes):
        for rep in range(3):
            assert (tmp_path / f"f{k}_{rep}.bin").read_bytes() == _payload(n, seed=k * 10 + rep)


@pytest.mark.parametrize("n", [MIN_BYTES + 1, 4096 * 40 + 4095, 8_874_100])
def test_partial_last_block_is_written_without_truncating(tmp_path, monkeypatch, n) -> None:
    """The whole blocks go direct and the partial last block through the page cache, after
    O_DIRECT is cleared on the descriptor: no padding and no ftruncate, which made ext4 read
    the last block back from the device for every file."""
    if not _direct_possible(tmp_path):
        pytest.skip("this file system does not take O_DIRECT")

    def no_truncate(*args, **kwargs):
        raise AssertionError("write_file must not truncate")

    writes: list[tuple[int, int, bool]] = []
    real_pwrite = os.pwrite

    def recording_pwrite(fd, data, offset):
        direct = bool(directio.fcntl.fcntl(fd, directio.fcntl.F_GETFL) & os.O_DIRECT)
        writes.append((offset, len(data), direct))
        return real_pwrite(fd, data, offset)

    monkeypatch.setattr(directio.os, "ftruncate", no_truncate)
    monkeypatch.setattr(directio.os, "pwrite", recording_pwrite)
    data = _payload(n, seed=n)
    assert write_file(tmp_path / "f.bin", [data]) == "direct"
    assert (tmp_path / "f.bin").read_bytes() == data
    head = n // 4096 * 4096
    assert sum(k for off, k, direct in writes if direct) == head
    assert all(off + k <= head for off, k, direct in writes if direct)
    assert [(off, k) for off, k, direct in writes if not direct] == [(head, n - head)]


@pytest.mark.parametrize("n", [MIN_BYTES, 4096 * 40, 4096 * 40 + 6, 1_000_003])
def test_aligned_array_written_from_its_own_memory(tmp_path, monkeypatch, n) -> None:
    """An array from aligned_empty starts on a 4096-byte boundary and is written without the
    copy into the thread's buffer (which is never made), with exactly its bytes."""
    arr = directio.aligned_empty((n,), np.uint8)
    assert arr.ctypes.data % 4096 == 0 and arr.flags.c_contiguous and arr.shape == (n,)
    arr[...] = np.frombuffer(_payload(n, seed=7), np.uint8)
    cube = directio.aligned_empty((3, 5, 7), np.float32)
    assert cube.ctypes.data % 4096 == 0 and cube.shape == (3, 5, 7) and cube.dtype == np.float32
    monkeypatch.setattr(directio, "_local", threading.local())
    how = write_file(tmp_path / "a.bin", [arr])
    assert (tmp_path / "a.bin").read_bytes() == arr.tobytes()
    if _direct_possible(tmp_path):
        assert how == "direct"
        assert getattr(directio._local, "buf", None) is None  # no copy through the aligned buffer
    unaligned = np.empty(n + 1, np.uint8)[1:]
    unaligned[...] = arr
    write_file(tmp_path / "b.bin", [unaligned])
    assert (tmp_path / "b.bin").read_bytes() == arr.tobytes()
