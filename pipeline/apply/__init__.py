"""From raw frames to reflectance.

``flight``: the executor of Eq. 15 over a flight (one pass, one task per frame);
``factory``: captures of cameras with factory radiometric metadata; ``light``: the light at
each frame's time (reflector captures, irradiance readings); ``panel``: reflectance factors
from a panel capture. May import ``storage``, ``ingest``, ``calibrate`` and
``products.writers`` (the per-frame files it writes as it goes).
"""
