"""The peak memory of a benchmark's forked child: what its own work added, not its parent's heap.

A forked child shares its parent's resident pages, the heap the parent freed but kept among them,
and starts from the parent's high-water mark. Its arrays then fill that freed heap unseen and its
peak is the parent's: :func:`fresh_peak` hands the freed heap back and resets the mark (Linux's
``/proc/self/clear_refs``), so :func:`peak_mb` after it counts the child's own growth.
"""

from __future__ import annotations

import resource

from gpomap.resources import release_freed_memory, rss_mb


def fresh_peak() -> float:
    """This process's resident MiB, its peak reset to it where Linux lets it be (else the peak so far)."""
    release_freed_memory()
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return rss_mb() or 0.0


def peak_mb() -> float:
    """This process's peak resident MiB since :func:`fresh_peak` (Linux's VmHWM; else ``ru_maxrss``)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
