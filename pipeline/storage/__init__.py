"""Bytes on disk, and nothing about cameras.

Atomic file and folder writes, writes past the page cache (``directio``), whole-frame Zarr
chunk files that zarr-python reads back (``chunks``), the calibration store (``store``:
write atomically, open with checks), where the cache folder is (``cache``) and the layout of
apply's ``run.json`` (``run_layout``: which keys nest under which kind of input, read from either
layout). Imports no other ``pipeline`` subpackage.
"""
