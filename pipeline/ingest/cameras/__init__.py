"""One module per camera maker: its tag reading, radiance model, sun-sensor reading and quirks
(:mod:`pipeline.ingest.cameras.micasense`, ``parrot``, ``dji``, ``sentera``), each registered
in :mod:`pipeline.ingest.cameras.registry`; :mod:`pipeline.ingest.cameras.dispatch` imports
them all and picks one by a file's tags, a band's radiometry or a catalog camera's
``factory_model``."""
