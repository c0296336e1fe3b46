"""A frame's chunk writes run on a writer thread while the frame goes on, and the
frame is done only when they are: FrameWrites."""

from __future__ import annotations

import threading

import numpy as np
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


# --------------------------------------------------------------------------- process_frames


class _Frames:
    """start_frame / finish_frame stand-ins: every frame hands one write to its writer
    threads; ``log`` records the order of starts, writes and finishes."""

    def __init__(self, quarantined=(), fail_start=None, fail_write=None, nbytes: int = 0) -> None:
        self.log: list[str] = []
        self.quarantined, self.fail_start, self.fail_write = set(quarantined), fail_start, fail_write
        self.nbytes = nbytes  # the size of the array each frame hands to its writes

    def start(self, plan, job):
        from pipeline.apply import executor

        self.log.append(f"start {job}")
        if job == self.fail_start:
            raise RuntimeError(f"{job} failed")
        if job in self.quarantined:
            return executor.Outcome(job, None, 0, quarantine={"file": job, "reason": "bad"})
        writes = FrameWrites()
        writes.submit(self._write, job, np.zeros(self.nbytes, np.uint8))
        return executor._Writing(job, None, 0, None, writes)  # type: ignore[arg-type]

    def _write(self, job: str, data: np.ndarray) -> None:
        self.log.append(f"written {job}")
        if job == self.fail_write:
            raise OSError(28, f"{job}: the disk is full")

    def finish(self, plan, w):
        from pipeline.apply import executor

        w.writes.wait()
        self.log.append(f"finish {w.job}")
        return executor.Outcome(w.job, None, 0)


def _patched(monkeypatch, frames: _Frames) -> None:
    from pipeline.apply import executor

    monkeypatch.setattr(executor, "start_frame", frames.start)
    monkeypatch.setattr(executor, "finish_frame", frames.finish)


def test_two_frames_write_on_while_the_next_is_computed_and_outcomes_keep_job_order(monkeypatch) -> None:
    from pipeline.apply.executor import WRITING_FRAMES, process_frames

    assert WRITING_FRAMES == 2
    frames = _Frames(quarantined={"c"})
    _patched(monkeypatch, frames)
    out = process_frames(None, ["a", "b", "c", "d", "e"])
    assert [o.name for o in out] == ["a", "b", "c", "d", "e"]
    assert [o.quarantine is not None for o in out] == [False, False, True, False, False]
    log = frames.log
    # a's outcome is made only once two more frames are computed (b's and, c being
    # quarantined without writes, d's): a and b wrote on meanwhile
    assert log.index("start d") < log.index("finish a") < log.index("start e")
    assert log.index("start e") < log.index("finish b")
    assert log.index("finish b") < log.index("finish d") < log.index("finish e") == len(log) - 1
    # every frame's files are written before its outcome and before process_frames returns
    for job in "abde":
        assert log.index(f"written {job}") < log.index(f"finish {job}")


def test_large_frames_write_one_at_a_time(monkeypatch) -> None:
    """Frames whose outputs exceed WRITING_BYTES together (5-band MicaSense captures: ~60 MB
    each) keep one frame writing, as before: memory does not grow with them."""
    from pipeline.apply import executor

    monkeypatch.setattr(executor, "WRITING_BYTES", 1000)
    frames = _Frames(nbytes=600)
    _patched(monkeypatch, frames)
    assert [o.name for o in executor.process_frames(None, ["a", "b", "c"])] == ["a", "b", "c"]
    log = frames.log
    assert log.index("start b") < log.index("finish a") < log.index("start c") < log.index("finish b")
    frames = _Frames(nbytes=400)  # two of them fit
    _patched(monkeypatch, frames)
    executor.process_frames(None, ["a", "b", "c"])
    log = frames.log
    assert log.index("start c") < log.index("finish a")


def test_on_an_error_no_frame_is_left_writing(monkeypatch) -> None:
    from pipeline.apply.executor import process_frames

    frames = _Frames(fail_start="c")
    _patched(monkeypatch, frames)
    with pytest.raises(RuntimeError, match="c failed"):
        process_frames(None, ["a", "b", "c", "d"])
    assert "written b" in frames.log and "start d" not in frames.log  # b's write waited for
    frames = _Frames(fail_write="a")
    _patched(monkeypatch, frames)
    with pytest.raises(OSError, match="a: the disk is full"):
        process_frames(None, ["a", "b", "c", "d"])
    # a's error surfaces when its outcome is due (after c is computed); b and c were waited for
    assert {"written b", "written c"} <= set(frames.log) and "start d" not in frames.log


def test_frames_per_task_keeps_every_worker_busy_to_the_end() -> None:
    from pipeline.apply.executor import FRAMES_PER_TASK, frames_per_task

    assert frames_per_task(512, 2) == FRAMES_PER_TASK == 8
    assert frames_per_task(40, 2) == 5  # four tasks per worker at least
    assert frames_per_task(3, 2) == 1 and frames_per_task(0, 2) == 1
    assert frames_per_task(512, 64) == 2


def test_runner_runs_the_frames_a_few_to_a_task_in_job_order(monkeypatch) -> None:
    from pipeline.apply import executor
    from pipeline.apply.execution import Execution

    tasks: list[list[int]] = []

    def frames(plan, jobs):
        tasks.append(list(jobs))
        return [plan + j for j in jobs]

    monkeypatch.setattr(executor, "process_frames", frames)
    with executor.Runner(100, Execution("threads", 2)) as runner:
        assert runner.run(1000, range(100)) == [1000 + k for k in range(100)]
    assert sorted(j for t in tasks for j in t) == list(range(100))
    assert {len(t) for t in tasks} == {8, 4}  # 12 tasks of 8, one of 4
