"""How many threads NumPy work may use here, a map over them, and how a worker process leaves.

NumPy's indexing, comparisons and reductions over large arrays release the interpreter lock, so independent
pieces of such work (a pool's records, blocks of its rows) run side by side on threads. The library's
per-record pool work takes its thread count from :func:`threads_for`; the application's worker pools and
forks ask :func:`usable_cores`.
"""

from __future__ import annotations

import os

__all__ = ["usable_cores", "threads_for", "thread_map", "block_map", "leave_at_exit", "THREADED_ENTRIES",
           "MAX_THREADS"]

#: Record entries (all records together) from which a pool's per-record NumPy work runs on several threads
#: (``pooled.PooledPSOG`` sums, ``left_out.device_fields`` indexes), and count-table entries from which the
#: fields of count rows do (``block_map``: ``PSOG`` weights and stop flags, the jackknife's left-out rows).
THREADED_ENTRIES = 1 << 20
#: At most this many threads (and no more than the usable cores).
MAX_THREADS = 8


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it, else all), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads_for(entries: int) -> int:
    """Threads for NumPy work over ``entries`` record entries: 1 below ``THREADED_ENTRIES``, else up to
    ``MAX_THREADS`` and the usable cores."""
    return min(MAX_THREADS, usable_cores()) if entries >= THREADED_ENTRIES else 1


def thread_map(fn, items, threads: int) -> list:
    """``[fn(x) for x in items]``, on ``threads`` threads when more than one (results in item order)."""
    if threads <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads, thread_name_prefix="place3d-pool") as ex:
        return list(ex.map(fn, items))


def block_map(fn, n: int, block: int, entries_per_item: int = 1) -> None:
    """``fn(a, b)`` for each block ``[a, b)`` of ``block`` items of ``range(n)``, in order within each of a few
    contiguous spans, the spans side by side on threads (``threads_for(n * entries_per_item)``). For row work
    whose blocks write disjoint slices of outputs made beforehand: each block's values are what the same call
    gives alone, so the outputs do not depend on the threads."""
    t = threads_for(n * entries_per_item)
    starts = range(0, n, block)
    if t <= 1 or len(starts) <= 1:
        for a in starts:
            fn(a, min(a + block, n))
        return
    per = -(-len(starts) // (4 * t))            # a few spans per thread: one slow span does not hold the rest

    def span(j: int) -> None:
        for a in starts[j * per:(j + 1) * per]:
            fn(a, min(a + block, n))

    thread_map(span, range(-(-len(starts) // per)), t)


def leave_at_exit() -> None:
    """In a worker process: leave at the interpreter's first exit handler (``atexit`` runs the last registered
    first), with the standard streams flushed and ``os._exit(0)``, skipping the rest of the teardown (module
    namespaces, the loaded C libraries' destructors, a device context's). By then the process's non-daemon
    threads are joined. The status is 0 even for a worker that failed: a pool tells a dead worker by its
    process sentinel, not by its status."""
    import atexit

    atexit.register(_leave_now)


def _leave_now() -> None:
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(0)
