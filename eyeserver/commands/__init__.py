"""Subcommand groups of the command line (``eyeserver sim``, ``eyeserver bench``)."""
