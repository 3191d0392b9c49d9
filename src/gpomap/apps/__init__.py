"""The jobs only the ``gpomap`` commands do, with typed arguments: the replay loop, 3-D inputs, saved maps read again.

Their command lines (options, checks, summaries) are in :mod:`gpomap.cli`, which imports these; no
module here imports the CLI.
"""
