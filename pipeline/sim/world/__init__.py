"""Seeded physical forward model of the calibration data (pure numpy arrays, no I/O).

``sensor`` turns exposure energy into DN (response curve, black level, shot and read noise,
clipping); ``scene`` renders the geometry (static sweep scene, gray reflector with its ArUco
marker, vignetting, non-uniform light). ``pipeline/sim/synth.py`` writes the arrays to folders.
Every random draw comes from a ``numpy.random.Generator`` passed in by the caller.
"""
