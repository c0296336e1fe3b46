"""The session's fits, from frames to a calibration store.

``fit``: inverse response (Eq. 5-7), vignetting (Eq. 8-10) and illumination (Eq. 11-14) of a
session folder; ``registration``: band-to-band homographies of multi-lens cameras. The maths
is in ``mscal_core``; this package reads the frames and writes the store. May import
``storage`` and ``ingest``.
"""
