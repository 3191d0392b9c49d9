"""Subcommands of the ``gpomap`` command that live in their own module (``gpomap stream``)."""
