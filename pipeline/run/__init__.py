"""Running things: the ``mscal`` command line (``cli``), the steps of the post-flight flow
that ``flows/`` wires together (``runner``), the inbox of ``mscal serve`` (``inbox``) and the
demo (``demo``). May import every other subpackage; nothing imports it but ``flows``.
"""
