"""A frame's chunk writes run on a writer thread while the frame goes on (issue 25), and the
frame is done only when they are: FrameWrites."""

from __future__ import annotations

import threading

import pytest

from pipeline.apply.executor import WRITER_THREADS, FrameWrites


def test_the_frame_goes_on_while_a_write_waits_and_wait_returns_when_all_are_done() -> None:
    release = threading.Event()
    done: list[str] = []
    threads: set[str] = set()

    def write(name: str) -> None:
        threads.add(threading.current_thread().name)
        assert release.wait(60), "the writer was never released"
        done.append(name)

    # more writes than writer threads, every one held until released
    names = [f"chunk{i}" for i in range(WRITER_THREADS + 2)]
    writes = FrameWrites()
    for name in names:
        writes.submit(write, name)
    # every writer is blocked in a write: this thread is free to compute meanwhile
    assert done == []
    release.set()
    writes.wait()
    assert sorted(done) == sorted(names)  # all finished when wait returns
    assert threads and threading.current_thread().name not in threads
    assert all(t.startswith("mscal-writer") for t in threads)
    assert len(threads) <= WRITER_THREADS
    # the same writer threads serve this thread's next frame (their direct-I/O buffers are reused)
    again = FrameWrites()
    for name in names:
        again.submit(write, name)
    again.wait()
    assert len(done) == 2 * len(names)
    assert len(threads) <= WRITER_THREADS


def test_wait_raises_the_first_error_after_every_write_has_finished() -> None:
    done: list[str] = []

    def fail(msg: str) -> None:
        raise OSError(28, msg)

    writes = FrameWrites()
    writes.submit(fail, "reflectance: the disk is full")
    writes.submit(done.append, "ndvi")
    writes.submit(fail, "ndvi TIFF")
    with pytest.raises(OSError, match="reflectance: the disk is full"):
        writes.wait()
    assert done == ["ndvi"]
    writes.wait()  # nothing pending any more
    quiet = FrameWrites()
    quiet.submit(fail, "swallowed")
    quiet.wait(raise_errors=False)  # an error is already on its way: wait, do not replace it
