"""mscal's I/O layer, laid out along the data flow of a survey.

Each subpackage may import the ones listed before it, never one after it (a test checks):

1. ``storage``   bytes on disk: atomic writes, direct I/O, whole-frame Zarr chunk files, the
                 calibration store. Imports nothing else of ``pipeline``.
2. ``ingest``    inputs: catalogs, session folders and ``frames.csv``, camera metadata
                 (EXIF/XMP), discovery of frames and captures, the raw datacube.
3. ``calibrate`` the session's fits (Eq. 5-14) and band registration, written to the store.
4. ``apply``     Eq. 15 and the factory model frame by frame, light over time, panels. It
                 may also import ``products.writers``: it writes the per-frame TIFFs as it
                 applies.
5. ``products``  what users take away: per-frame TIFFs, index maps, STAC, statistics, report.
6. ``run``       the command line, the post-flight runner's steps, the inbox, the demo (which
                 uses ``sim``).

``sim`` writes synthetic sessions with known truth (tests, demo, benchmarks) and scores fits
against it; it may import ``storage``, ``ingest`` and ``calibrate``.

An import inside ``if TYPE_CHECKING:`` (annotations only) does not count. No module imports
another module's private (``_x``) names. tests/test_layering.py checks both.

The maths lives in ``mscal_core`` (no I/O); Prefect wiring in ``flows``.
"""
