"""``python -m gpomap.cli``: the ``gpomap`` command."""

from gpomap.cli import console

console()
