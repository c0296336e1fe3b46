"""mscal's catalogs as package data: ``cameras/``, ``targets/`` and ``indices/`` YAML files.

This folder holds no code; it is a package so that an installed mscal finds its catalogs with
``importlib.resources.files("catalogs")`` (see :mod:`pipeline.ingest.catalog`).
"""
