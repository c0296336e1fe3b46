"""Everything that reads the user's inputs.

Catalog YAML (``catalog``), ``session.yaml`` and ``frames.csv`` (``session``), frame files'
pixels (``tiff``), XMP packets as cameras write them (``xmp``), camera metadata from EXIF and
XMP (``camera_meta``, ``meta``), one module per camera maker (``cameras``), band files grouped
into captures (``grouping``), which catalog camera wrote a folder (``identify``), which files of
a folder are frames or captures (``discover``), and the chunked raw datacube ``raw.zarr``
(``raw``, ``medians``). May import ``storage``.
"""

# Every camera maker's module registers itself (its XMP namespaces among the rest) before any
# file is read: a packet parsed by pipeline.ingest.xmp knows every maker's namespaces.
from pipeline.ingest.cameras import dispatch as _makers  # noqa: F401
