"""pipeline.storage.lock and .outputs: one writer per folder, named when refused; output
paths refused before any work, never replacing what the user made."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mscal_core.errors import InputError, LockedError
from pipeline.storage.lock import FolderLock, describe_holder
from pipeline.storage.outputs import check_output

HOLD = """
import sys, time
from pipeline.storage.lock import FolderLock
lock = FolderLock(sys.argv[1]).acquire()
print("held", flush=True)
sys.stdin.readline()   # hold until told (or killed)
lock.release()
"""


def _holder(folder: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True, cwd=Path(__file__).resolve().parents[3])
    assert p.stdout.readline().strip() == "held"
    return p


def test_second_writer_refused_with_the_holder_named(tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = _holder(out)
    try:
        with pytest.raises(LockedError) as e:
            FolderLock(out, what="another mscal run").acquire()
        msg = str(e.value)
        assert f"pid {p.pid}" in msg and "another mscal run is writing here" in msg and str(out) in msg
        assert "--wait" in msg and "\n" not in msg
        assert e.value.exit_code == 75
        with pytest.raises(LockedError):  # waiting a little is not enough while it holds on
            FolderLock(out, wait=0.3).acquire()
    finally:
        p.communicate("\n", timeout=30)
    assert p.returncode == 0
    with FolderLock(out) as lock:  # released: free again
        assert lock.held
    assert not lock.held


def test_lock_of_a_killed_process_is_taken_over(tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = _holder(out)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    assert "pid" in (out / ".mscal.lock").read_text()  # what it wrote is still there
    with FolderLock(out) as lock:
        assert lock.held and f'"pid": {os.getpid()}' in (out / ".mscal.lock").read_text()
    assert not (out / ".mscal.lock").exists()  # the holder removes its file as it finishes


def test_wait_gets_the_lock_when_the_holder_finishes(tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = _holder(out)
    import threading

    def finish() -> None:
        p.stdin.write("\n")
        p.stdin.flush()

    threading.Timer(0.5, finish).start()
    with FolderLock(out, wait=True) as lock:
        assert lock.held
    p.wait(timeout=30)
    assert p.returncode == 0


def test_two_locks_of_one_process_exclude_each_other(tmp_path: Path) -> None:
    with FolderLock(tmp_path):
        with pytest.raises(LockedError):
            FolderLock(tmp_path).acquire()


def test_describe_holder_of_any_content() -> None:
    assert describe_holder('{"pid": 7, "host": "h", "started": "t", "command": "mscal run s"}') == \
        "pid 7 on h, since t, `mscal run s`"
    assert "not said who" in describe_holder("")
    assert "not said who" in describe_holder("{broken")


def test_existing_file_is_refused_and_kept(tmp_path: Path) -> None:
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    for kind in ("folder", "store"):
        with pytest.raises(InputError, match="existing file") as e:
            check_output(f, kind=kind)
        assert str(f) in str(e.value)
    assert f.read_text() == "mine"


def test_path_under_a_file_and_unwritable_places(tmp_path: Path) -> None:
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    with pytest.raises(InputError, match="which is a file, not a folder"):
        check_output(f / "out")
    with pytest.raises(InputError, match="cannot write here"):
        check_output("/proc/mscal-out")  # os.access says yes to root here
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:  # root writes through mode bits
        ro.chmod(0o555)
        with pytest.raises(InputError, match="no permission"):
            check_output(ro / "out")
    assert not any(p.name.startswith(".mscal-probe") for p in tmp_path.rglob("*"))


def test_store_replaced_only_when_mscal_wrote_it(tmp_path: Path) -> None:
    mine = tmp_path / "photos"
    mine.mkdir()
    (mine / "a.jpg").write_bytes(b"x")
    with pytest.raises(InputError, match="did not write"):
        check_output(mine, kind="store", owned=lambda p: (p / "zarr.json").is_file())
    assert (mine / "a.jpg").read_bytes() == b"x"
    ours = tmp_path / "calib.zarr"
    ours.mkdir()
    (ours / "zarr.json").write_text("{}")
    assert check_output(ours, kind="store", owned=lambda p: (p / "zarr.json").is_file()) == ours
    assert check_output(tmp_path / "empty", kind="store") == tmp_path / "empty"
    assert check_output(mine) == mine  # an output folder may be added to


def test_free_space_estimate(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not enough free space") as e:
        check_output(tmp_path / "out", need_bytes=2**62)
    assert "MiB needed" in str(e.value)
    assert check_output(tmp_path / "out", need_bytes=1) == tmp_path / "out"
    assert not (tmp_path / "out").exists()  # checking creates nothing


def test_guarded_output_locks_beside_a_store_and_inside_a_folder(tmp_path: Path) -> None:
    from pipeline.storage.outputs import guarded_output, is_mscal_store

    store = tmp_path / "calib.zarr"
    with guarded_output(store, kind="store") as p:
        assert p == store and (tmp_path / ".calib.zarr.lock").is_file()
        with pytest.raises(LockedError):
            with guarded_output(store, kind="store"):
                pass
    assert not (tmp_path / ".calib.zarr.lock").exists()
    store.mkdir()
    (store / "zarr.json").write_text('{"attributes": {"format": "mscal-calibration/1"}}')
    assert is_mscal_store(store)
    with guarded_output(store, kind="store"):
        pass
    (store / "zarr.json").write_text('{"attributes": {"format": "someone-else"}}')
    assert not is_mscal_store(store)
    with pytest.raises(InputError, match="did not write"):
        with guarded_output(store, kind="store"):
            pass
    with guarded_output(tmp_path / "out") as p:
        assert (p / ".mscal.lock").is_file()
        (p / "run.json").write_text("{}")
    assert sorted(q.name for q in (tmp_path / "out").iterdir()) == ["run.json"]
    with pytest.raises(InputError, match="existing folder; mscal writes a file"):
        with guarded_output(tmp_path / "out", kind="file"):
            pass
    report = tmp_path / "report.html"
    report.write_text("old")
    with guarded_output(report, kind="file"):  # a file output is replaced
        pass


def test_a_command_that_fails_at_once_leaves_no_folder(tmp_path: Path) -> None:
    from pipeline.storage.outputs import guarded_output

    out = tmp_path / "a" / "b" / "out"
    with pytest.raises(ValueError):
        with guarded_output(out):
            raise ValueError("bad input found after the lock was taken")
    assert not (tmp_path / "a").exists()
    with guarded_output(out) as p:  # a command that wrote something keeps it
        (p / "run.json").write_text("{}")
    assert (out / "run.json").is_file()


def test_waiters_in_turn_each_lock_the_live_file(tmp_path: Path) -> None:
    """Three processes, the lock file removed by each holder as it finishes: the waiters never
    hold the lock at the same time (each appends start/end marks; no interleaving)."""
    code = """
import sys, time
from pipeline.storage.lock import FolderLock
folder, mark = sys.argv[1], sys.argv[2]
with FolderLock(folder, wait=True):
    with open(folder + "/log", "a") as fh:
        fh.write(mark + "<")
        fh.flush()
        time.sleep(0.3)
        fh.write(">" + mark + ";")
"""
    folder = tmp_path / "out"
    folder.mkdir()
    procs = [subprocess.Popen([sys.executable, "-c", code, str(folder), str(k)], cwd=Path(__file__).resolve().parents[3])
             for k in range(3)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0, 0]
    log = (folder / "log").read_text().rstrip(";").split(";")
    assert sorted(log) == [f"{k}<>{k}" for k in range(3)]  # each holder's marks together
    assert not (folder / ".mscal.lock").exists()


def test_a_refusal_names_a_holder_that_has_just_taken_the_lock(tmp_path) -> None:
    """The holder writes who it is just after taking the lock; a second process that comes in
    between still names it (found by the 20 trials of SIGKILL then two restarts)."""
    import fcntl
    import threading

    from pipeline.storage.lock import LOCK_NAME, holder_info

    fd = os.open(tmp_path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # taken, nothing written yet
    info = {**holder_info(), "pid": 4127, "host": "farm-pc"}
    writer = threading.Timer(0.3, lambda: os.pwrite(fd, json.dumps(info).encode(), 0))
    writer.start()
    try:
        with pytest.raises(LockedError) as refused:
            FolderLock(tmp_path).acquire()
        assert "pid 4127 on farm-pc" in str(refused.value)
    finally:
        writer.join()
        os.close(fd)
