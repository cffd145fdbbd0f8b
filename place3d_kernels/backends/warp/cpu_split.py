"""How the Warp backend splits launches on Warp's CPU device over Python threads: the thread count and
the chunk sizes (``WarpCore._prepare`` and the score methods of scoring.py use them)."""

from __future__ import annotations

import os

__all__ = ["cpu_threads", "MIN_CHUNK", "CHUNKS_PER_THREAD"]


def cpu_threads() -> int:
    """Threads for split CPU launches: ``PLACE3D_WARP_CPU_THREADS`` if set, else the usable cores."""
    env = os.environ.get("PLACE3D_WARP_CPU_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"PLACE3D_WARP_CPU_THREADS must be a positive integer, got {env!r}") from None
        if n < 1:
            raise ValueError(f"PLACE3D_WARP_CPU_THREADS must be a positive integer, got {env!r}")
        return n
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


# a chunk smaller than this many items is not worth a thread hand-off (its launch costs more than the work
# it moves)
MIN_CHUNK = 2048
CHUNKS_PER_THREAD = 8    # many small chunks per thread balance rays of very different lengths
