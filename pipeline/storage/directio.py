"""Write a new output file past the page cache (``O_DIRECT``), with a buffered fallback.

An apply pass writes every frame's products once (reflectance, raw DN, indices, TIFFs:
13.7 MB per full-resolution frame) and reads none of them back. Written the usual way, each
byte is first copied into newly allocated page-cache pages, which a 600-frame flight fills
with 8 GB of dirty data that the kernel then writes out anyway. On the virtual machines
this project is benchmarked on, those newly used pages are the dominant cost: the host
backs guest memory on first touch (measured: 2.8 ms per MB for a first write into the page
cache, 0.24 ms per MB once the page is backed, and the guest hands freed pages back to the
host within ~20 s), so buffered writes cost more CPU than all of Eq. 15. ``O_DIRECT`` moves
the bytes from one reused, page-aligned buffer per thread to the device instead.

Rules of the game (Linux ``open(2)``): with ``O_DIRECT`` the buffer address, the file offset
and the length must be multiples of the logical block size. :func:`write_file` copies the
parts into the thread's page-aligned buffer, writes its whole 4096-byte blocks direct, then
clears ``O_DIRECT`` on the descriptor (``fcntl``) and writes the last partial block through
the page cache. (Padding that block and truncating the file afterwards made ext4 read the
block back from the device to zero its end: one synchronous read per file, which waited
behind the writes and was most of apply's idle time.) Files too small to gain (under
:data:`MIN_BYTES`), file systems that refuse ``O_DIRECT`` (tmpfs, some network file
systems: ``EINVAL``), platforms without it, and ``--no-direct-io`` (:func:`set_direct_io`) all take the
ordinary buffered write. Either way the file holds exactly the bytes given.

Durability is unchanged: neither path fsyncs (see :func:`pipeline.storage.atomic.atomic_path`).
"""

from __future__ import annotations

import errno
import mmap
import os
import threading
from pathlib import Path
from typing import Sequence

import numpy as np

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no O_DIRECT either
    fcntl = None  # type: ignore[assignment]

__all__ = ["DIRECT_IO_ENV", "MIN_BYTES", "aligned_empty", "direct_io_enabled", "set_direct_io", "write_file"]

#: Files smaller than this are written buffered (the copy into the aligned buffer and the
#: extra system calls are not worth it).
MIN_BYTES = 64 * 1024
_ALIGN = 4096

_local = threading.local()
_refused: set[int] = set()  # st_dev of file systems that refused O_DIRECT in this process


#: The process's switch, in the environment so that worker processes inherit it; set by
#: :func:`set_direct_io` (``mscal apply --direct-io/--no-direct-io``, whose default it is).
DIRECT_IO_ENV = "MSCAL_DIRECT_IO"


def direct_io_enabled() -> bool:
    """``O_DIRECT`` writes are on unless switched off (:func:`set_direct_io`, or
    ``MSCAL_DIRECT_IO`` = ``0``/``false``/``no``/``off``) or the platform has no ``O_DIRECT``."""
    flag = os.environ.get(DIRECT_IO_ENV, "1").strip().lower()
    return hasattr(os, "O_DIRECT") and fcntl is not None and flag not in ("0", "false", "no", "off")


def set_direct_io(enabled: bool) -> None:
    """Switch ``O_DIRECT`` writes on or off for this process and the processes it starts."""
    os.environ[DIRECT_IO_ENV] = "1" if enabled else "0"


def aligned_empty(shape: tuple[int, ...], dtype: np.dtype | type | str) -> np.ndarray:
    """An uninitialised C-contiguous array whose data starts on a 4096-byte boundary: written
    whole by :func:`write_file`, its bytes go to the device straight from it, without the copy
    into the thread's aligned buffer."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(n + _ALIGN, np.uint8)
    start = -raw.ctypes.data % _ALIGN
    return raw[start:start + n].view(dtype).reshape(shape)


def _aligned_view(views: Sequence[memoryview]) -> memoryview | None:
    """The only part, if it starts on a 4096-byte boundary (then it needs no copy)."""
    if len(views) != 1:
        return None
    v = views[0]
    return v[:] if np.frombuffer(v, dtype=np.uint8).ctypes.data % _ALIGN == 0 else None  # released on its own


def _buffer(size: int) -> mmap.mmap:
    """This thread's page-aligned buffer of at least ``size`` bytes (reused, grown when needed)."""
    buf = getattr(_local, "buf", None)
    if buf is None or len(buf) < size:
        if buf is not None:
            buf.close()
        buf = _local.buf = mmap.mmap(-1, size)
    return buf


def _device(folder: Path) -> int:
    try:
        return os.stat(folder).st_dev
    except OSError:
        return -1


def _buffered(path: Path, parts: Sequence, exclusive: bool) -> None:
    with open(path, "xb" if exclusive else "wb") as fh:
        for part in parts:
            fh.write(part)


def _pwrite_all(fd: int, mv: memoryview, start: int, end: int, path: Path) -> None:
    """Write ``mv[start:end]`` at file offset ``start`` (system calls may take part of it)."""
    done = start
    while done < end:
        k = os.pwrite(fd, mv[done:end], done)
        if k <= 0:
            raise OSError(errno.ENOSPC, f"{path}: the device took no more bytes")
        done += k


def write_file(path: str | Path, parts: Sequence, *, exclusive: bool = True) -> str:
    """Create ``path`` holding the concatenation of ``parts`` (bytes-like objects).

    ``exclusive``: fail with ``FileExistsError`` if ``path`` exists (as ``open(path, "xb")``),
    else replace its content. Returns ``"direct"`` or ``"buffered"``: how it was written.
    """
    path = Path(path)
    views = [memoryview(p).cast("B") for p in parts]
    n = sum(v.nbytes for v in views)
    if n < MIN_BYTES or not direct_io_enabled():
        _buffered(path, views, exclusive)
        return "buffered"
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | (os.O_EXCL if exclusive else os.O_TRUNC)
    if _refused and _device(path.parent) in _refused:  # stat only once some file system refused
        _buffered(path, views, exclusive)
        return "buffered"
    try:
        fd = os.open(path, flags | os.O_DIRECT, 0o666)
    except OSError as exc:
        if exc.errno != errno.EINVAL:
            raise
        _refused.add(_device(path.parent))
        _buffered(path, views, exclusive)
        return "buffered"
    head = n // _ALIGN * _ALIGN  # written direct; the tail (< 4096 bytes) buffered, after it
    try:
        mv = _aligned_view(views)
        if mv is None:
            buf = _buffer(n)
            dst = np.frombuffer(buf, dtype=np.uint8, count=n)
            pos = 0
            for v in views:  # numpy copies without holding the GIL
                dst[pos:pos + v.nbytes] = np.frombuffer(v, dtype=np.uint8)
                pos += v.nbytes
            del dst
            mv = memoryview(buf)
        try:
            _pwrite_all(fd, mv, 0, head, path)
            if n > head:
                # a buffered write of the last partial block: padding it and truncating the file
                # afterwards made ext4 read that block back from the device, synchronously, to
                # zero its end (one read per file, queued behind the writes)
                fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_DIRECT)
                _pwrite_all(fd, mv, head, n, path)
        finally:
            mv.release()
    except OSError as exc:
        if exc.errno != errno.EINVAL:
            raise
        refused_write = True  # the file system accepted the flag at open but not the write
    else:
        refused_write = False
    finally:
        os.close(fd)
    if refused_write:
        _refused.add(_device(path.parent))
        _buffered(path, views, exclusive=False)  # the file exists now (created by the open above)
        return "buffered"
    return "direct"
