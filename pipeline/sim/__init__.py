"""Synthetic sessions with known truth, written as a user's session folder would be
(``synth``), and the errors of a calibration against that truth (``evaluate``). Used by the
demo, the tests and the benchmarks. May import ``storage``, ``ingest`` and ``calibrate``.
"""
