"""The session's fits, from frames to a calibration store.

``fit``: runs the stages of a session folder in order and writes the store with its
provenance (``mscal calibrate``, ``mscal fit response|vignetting|illumination``). The stages:
``response_stage`` (inverse response, Eq. 5-7, from the exposure sweep read by ``sweep``),
``vignetting_stage`` (Eq. 8-10, with the screening of views) and ``illumination_stage``
(Eq. 11-14, per reflector capture of ``captures``); each returns a ``stage.StageReport``.
``views``: the marker found and its pose in the frames of both marker folders;
``intrinsics``: the intrinsics a session uses and ``mscal fit intrinsics``; ``bands`` and
``pool``: the per-band fits and their worker processes; ``registration``: band-to-band
homographies of multi-lens cameras; ``library``: every calibration fitted, by camera and
serial number. The maths is in ``mscal_core``; this package reads the frames and writes the
store. May import ``storage`` and ``ingest``.
"""
