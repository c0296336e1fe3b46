"""pipeline: catalogs, session folders, stores and the command line; I/O lives here."""
