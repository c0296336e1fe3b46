"""Synthetic sessions with known truth: the seeded physical forward model (``world``: camera,
sensor, scene, light, pure numpy arrays), the session folders written from it as a user's
would be (``synth``, ``varied``, ``multilens``, ``dji``, ``sunlight``), and the errors of a
calibration against that truth (``evaluate``). Used by the
demo, the tests and the benchmarks. May import ``storage``, ``ingest`` and ``calibrate``.
"""
