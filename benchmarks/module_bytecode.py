"""gpomap's bytecode written before a benchmark times fresh processes, as an installed package has it.

``pip install`` compiles a package's modules to bytecode, so a user's process loads them. Where
``PYTHONDONTWRITEBYTECODE`` is set, or the source tree is a fresh checkout, every timed process
would compile each module it imports from source instead (about 0.35 CPU s for ``gpomap map``),
a cost no user pays. :func:`write_bytecode` compiles them once, untimed; the interpreter reads
bytecode whatever that variable says.
"""

from __future__ import annotations

import compileall
from pathlib import Path


def write_bytecode() -> None:
    """Compile every module of the gpomap package imported here (its ``__pycache__``), quietly."""
    import gpomap

    if not compileall.compile_dir(Path(gpomap.__file__).parent, quiet=1):
        raise SystemExit(f"could not compile gpomap's modules in {Path(gpomap.__file__).parent}")
