"""Everything that reads the user's inputs.

Catalog YAML (``catalog``), ``session.yaml`` and ``frames.csv`` (``session``), camera
metadata from EXIF and XMP (``camera_meta``), which files of a folder are frames or captures
(``discover``), and the chunked raw datacube ``raw.zarr`` (``raw``). May import ``storage``.
"""
