"""Bytes on disk, and nothing about cameras.

Atomic file and folder writes, writes past the page cache (``directio``), whole-frame Zarr
chunk files that zarr-python reads back (``chunks``), the calibration store (``store``:
write atomically, open with checks) and where the cache folder is (``cache``). Imports no
other ``pipeline`` subpackage.
"""
