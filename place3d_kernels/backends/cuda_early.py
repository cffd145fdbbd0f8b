"""The CUDA driver started on its own thread while Warp is imported (the cold start of a CUDA backend).

A cold ``get_backend("warp:cuda:0")`` imports Warp (Python, most of a second), then Warp initialises the
CUDA driver and retains the device's primary context (``cuInit`` and ``cuDevicePrimaryCtxRetain``, a
fraction of a second more), one after the other. The driver's part needs no
Warp: :func:`start` makes those calls through ``libcuda`` on a daemon thread (a foreign call through
ctypes releases the interpreter lock, so the import goes on meanwhile), and Warp, when it gets there,
finds the driver started and the context made (a retained primary context is the one context of that
device in this process; Warp retains it once more). The two
overlap (figures: bench/README.md, "What the studies found", cold command: kernels and start).

Where Warp is imported but not yet initialised (a worker forked from a server that imported it,
``place3d_app.forkserver``), :func:`start` starts the same thread; the Warp backend's start then imports its
kernels' modules while the driver works (about 0.18 s of Python that used to follow Warp's ``init``) and
waits for the thread (:func:`pending`) before Warp's ``init``, which finds the context made. On the H200 host the
drive step of a cold default optimize ended 0.07-0.14 s sooner so (two leases, 6 runs each; no effect on
``reproduce``; bench/results/ab-2026-12-01-s41/, sections 5 and 8).

Only for names that pick a Warp CUDA device (``warp:cuda:N``, ``warp:cuda``, ``warp``, ``auto``), only
while Warp is not initialised, only where Warp is installed and ``libcuda`` loads; every failure is
silent here (Warp then meets it and reports it as before). ``PLACE3D_CUDA_EARLY=0`` turns it off.
"""

from __future__ import annotations

import importlib.util
import os
import re
import sys
import threading

__all__ = ["start", "pending", "ordinal_of", "ENV"]

#: Environment variable: "0" = never start the driver early.
ENV = "PLACE3D_CUDA_EARLY"

_started: set[int] = set()
_threads: list[threading.Thread] = []
_lock = threading.Lock()


def ordinal_of(name: str) -> int | None:
    """The CUDA device a backend name would take through Warp (``auto``, ``warp`` and ``warp:cuda`` take
    device 0, Warp's default), or None for a name that takes none."""
    n = name.strip().lower()
    if n in ("auto", "warp", "warp:cuda"):
        return 0
    m = re.fullmatch(r"warp:cuda:(\d+)", n)
    return int(m.group(1)) if m else None


def start(name: str) -> threading.Thread | None:
    """Start the CUDA driver and retain the primary context of the device ``name`` takes, on a daemon
    thread (returned), or None when nothing was started (see the module's conditions)."""
    ordinal = ordinal_of(name)
    if (ordinal is None or ordinal in _started or os.environ.get(ENV, "1").strip() == "0"
            or not sys.platform.startswith("linux")):
        return None
    if "warp" in sys.modules and _warp_initialised():
        return None
    with _lock:
        if ordinal in _started:
            return None
        _started.add(ordinal)         # tried once per process, started or not: get_backend("auto") repeats
    try:
        if importlib.util.find_spec("warp") is None:
            return None
    except (ImportError, ValueError):
        return None
    t = threading.Thread(target=_retain, args=(ordinal,), name="place3d-cuda-start", daemon=True)
    _threads.append(t)
    t.start()
    return t


def pending() -> list[threading.Thread]:
    """The threads :func:`start` started that are still making a context (Warp's start waits for them)."""
    return [t for t in _threads if t.is_alive()]


def _warp_initialised() -> bool:
    """Whether the imported Warp has made its runtime (``init``); True where that cannot be told (a Warp
    whose module layout differs), so nothing is started then."""
    for module in ("warp._src.context", "warp.context"):
        ctx = sys.modules.get(module)
        if ctx is not None and hasattr(ctx, "runtime"):
            return ctx.runtime is not None
    return True


def _retain(ordinal: int) -> bool:
    """cuInit, cuDeviceGet, cuDevicePrimaryCtxRetain; True when all three succeeded. The context is kept
    (never released): the process uses it until it exits."""
    import ctypes

    try:
        cu = ctypes.CDLL("libcuda.so.1")
        dev, ctx = ctypes.c_int(), ctypes.c_void_p()
        return (cu.cuInit(0) == 0 and cu.cuDeviceGet(ctypes.byref(dev), ordinal) == 0
                and cu.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev) == 0)
    except (OSError, AttributeError):       # no driver library, or one without these entry points
        return False
