"""Everything that reads the user's inputs.

Catalog YAML (``catalog``), ``session.yaml`` and ``frames.csv`` (``session``), XMP packets
as cameras write them (``xmp``), camera metadata from EXIF and XMP for every vendor
(``camera_meta``), which catalog camera wrote a folder (``identify``), which files of a folder are frames or captures
(``discover``), and the chunked raw datacube ``raw.zarr`` (``raw``). May import ``storage``.
"""
