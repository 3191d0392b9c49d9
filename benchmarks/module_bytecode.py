"""gpomap's bytecode written before a benchmark times fresh processes, as an installed package has it.

``pip install`` compiles a package's modules to bytecode, so a user's process loads them. Where
``PYTHONDONTWRITEBYTECODE`` is set, or the source tree is a fresh checkout, every timed process
would compile each module it imports from source instead, a cost no user pays
(docs/benchmarks.md). :func:`write_bytecode` compiles them once, untimed; the interpreter reads
bytecode whatever that variable says.
"""

from __future__ import annotations

import compileall
import sys
from pathlib import Path


def write_bytecode() -> None:
    """Compile every module of the gpomap package imported here (its ``__pycache__``), quietly;
    where that cannot be written, say so and go on (the timings then include the compiling)."""
    import gpomap

    package = Path(gpomap.__file__).parent
    if not compileall.compile_dir(package, quiet=1):
        print(f"warning: could not write gpomap's bytecode in {package}; timed processes compile its modules", file=sys.stderr)
