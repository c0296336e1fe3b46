"""From raw frames to reflectance.

``executor``: Eq. 15 (or the factory chain) over a flight's frames, one task per few frames;
``flight``: snapshot flights (frames ingested into raw.zarr); ``captures``: folders of
one-file-per-band captures; ``factory``: the factory chain's set-up for such folders. What
both paths share, imported by each and never by each other: ``options`` (ApplyOptions, bands,
normalisation), ``record`` (run.json, one schema, up to date by content), ``template`` (the
output stores' layout), ``stores`` (chunks and calibration stores held per process).
``light``: the light at each frame's time (reflector captures, irradiance readings);
``panel``: reflectance factors from a panel capture. May import ``storage``, ``ingest``,
``calibrate`` and ``products.writers`` (the per-frame files it writes as it goes).
"""
