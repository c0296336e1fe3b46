"""What users take away from a run.

Per-frame TIFFs with EXIF/XMP for photogrammetry (``writers``), index maps of orthomosaics
(``indexmap``), the STAC catalog (``stac``), per-field statistics (``zonal``) and the QA
report (``report``). May import ``storage`` and ``ingest``; reads the stores and outputs that
``calibrate`` and ``apply`` wrote.
"""
