"""Imported last by the apply worker processes' server (the forkserver,
:func:`pipeline.apply.execution.worker_context`), after :data:`pipeline.apply.execution.WORKER_MODULE`:
it moves every object the server holds then (the imports of numpy, xarray, zarr, OpenCV and
mscal) out of the garbage collector's reach (``gc.freeze``).

Why: the server's own shutdown walked those objects in several full collections, 0.27-0.33 s of
CPU at the end of every apply that the main process waits for (measured: 0.05 s frozen); and a
worker forked from the server no longer walks them in its full collections, nor writes to
their pages (the collector's links), which would copy them into the worker. Those objects live
as long as the server anyway; nothing else changes.

Only when :data:`SERVER_ENV` is ``1`` (set for the server's start only): imported anywhere else
this module does nothing.
"""
from __future__ import annotations

import gc
import os

#: Set to ``1`` in the environment the worker server starts with
#: (:func:`pipeline.apply.execution.ensure_worker_server`).
SERVER_ENV = "MSCAL_WORKER_SERVER"

if os.environ.get(SERVER_ENV) == "1":
    gc.freeze()
