"""A process pool that fails as on a system without working POSIX semaphores (AWS Lambda:
``sem_open`` gives ENOSYS), for the tests of ``pipeline.storage.process.start_pool``'s
callers: patch it in as ``pipeline.storage.process.ProcessPoolExecutor``."""

from __future__ import annotations


class NoSemaphores:
    """Raises what ``ProcessPoolExecutor(...)`` raises there."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        raise OSError(38, "Function not implemented")
