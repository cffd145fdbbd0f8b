"""Drive workers spawned at the console script's start, each making its CUDA context while it imports.

A cold ``evaluate`` or ``optimize`` on a Warp CUDA backend builds its drives in worker processes. Forked from the
commands' forkserver (``place3d_app.forkserver``), a worker can make its CUDA context only after the server has
imported NumPy, Warp and the package (a forked copy of a process that started CUDA cannot use it, so the server
never does): the imports, then the fork, then the context, one after the other, and the driver makes the eight
workers' contexts together in about half a second (bench/results/ab-2026-12-01-s41/, section 2). A worker spawned
(a fresh interpreter) imports those modules itself, but it can ask the driver for its context first, on a thread
(``cuda_early``, standard library only, loaded here without the package's ``__init__``), so the context is made
while it imports instead of after.

:func:`start` spawns them from ``forkserver.start_early``, before this process imports the package; the
drives' step (``routes.build_missing``) takes them (:func:`take`) as its ``ProcessExecutor``'s pool. A pool
nobody takes is let go when the command ends. Standard library only at import, as ``forkserver``.
``PLACE3D_EARLY_WORKERS=0`` turns it off (the forkserver then serves the workers, as before).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import threading

__all__ = ["ENV", "start", "take", "release", "cuda_early", "wanted"]

#: Environment variable: "0" = never spawn the drive workers at the start (they are forked from the forkserver).
ENV = "PLACE3D_EARLY_WORKERS"

_lock = threading.Lock()
_pool: list = []          # [(ProcessPoolExecutor, workers, backend name)] while started and not taken


def cuda_early():
    """``place3d_kernels.backends.cuda_early`` (standard library only), without running the package's
    ``__init__`` (NumPy and the library) where the package is not imported yet: the module is loaded from its
    file under its own name, so a later import of it, through the package, finds this same module (its record
    of the context's thread, which Warp's start waits for, included). None where the package cannot be found."""
    name = "place3d_kernels.backends.cuda_early"
    if name in sys.modules:
        return sys.modules[name]
    try:
        pkg = importlib.util.find_spec("place3d_kernels")
    except (ImportError, ValueError):
        return None
    if pkg is None or not pkg.submodule_search_locations:
        return None
    path = os.path.join(list(pkg.submodule_search_locations)[0], "backends", "cuda_early.py")
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None or not os.path.exists(path):
        return None
    module = importlib.util.module_from_spec(spec)
    with _lock:
        if name in sys.modules:
            return sys.modules[name]
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            sys.modules.pop(name, None)
            raise
    return module


def wanted(backend: str) -> bool:
    """Whether the drive workers of a command on ``backend`` should be spawned early: a name that takes a CUDA
    device through Warp (``cuda_early.ordinal_of``: ``auto``, ``warp``, ``warp:cuda[:N]``), Warp installed, the
    NVIDIA driver library loadable, on Linux, and neither ``PLACE3D_EARLY_WORKERS=0`` nor
    ``PLACE3D_START_METHOD=forkserver``."""
    if os.environ.get(ENV, "1").strip() == "0" or not sys.platform.startswith("linux"):
        return False
    if os.environ.get("PLACE3D_START_METHOD", "").strip().lower() == "forkserver":
        return False
    ce = cuda_early()
    if ce is None or ce.ordinal_of(backend) is None:
        return False
    try:
        if importlib.util.find_spec("warp") is None:
            return False
    except (ImportError, ValueError):
        return False
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    return True


def start(workers: int, backend: str, preload: list[str]) -> None:
    """Spawn ``workers`` worker processes now, each starting ``backend``'s CUDA context on a thread, then
    importing ``preload`` (``forkserver.preload_for``) and starting the backend (``executors._start_worker``).
    The processes are started on a thread (a spawn is a fork and an exec of this interpreter, most of it outside
    the interpreter lock), so this process goes on with its own imports."""
    import concurrent.futures
    import multiprocessing

    pool = concurrent.futures.ProcessPoolExecutor(int(workers), mp_context=multiprocessing.get_context("spawn"),
                                                  initializer=_init, initargs=(backend, list(preload)))
    with _lock:
        _pool.append((pool, int(workers), backend))

    def spawn():
        # one empty task per worker: a pool of spawned processes starts one per task while none is idle
        try:
            for _ in range(int(workers)):
                pool.submit(_no_task)
        except RuntimeError:           # let go meanwhile (release): nothing to start
            pass

    threading.Thread(target=spawn, daemon=True, name="place3d-early-workers").start()
    import atexit

    atexit.register(release)


def take():
    """(the pool, its worker count, its backend name) that :func:`start` spawned, now the caller's; None when none
    was started (or it was taken already)."""
    with _lock:
        return _pool.pop() if _pool else None


def release() -> None:
    """Let go of a pool nobody took: its workers leave without taking any task."""
    got = take()
    if got is not None:
        got[0].shutdown(wait=False, cancel_futures=True)


def _no_task() -> None:
    return None


def _init(backend: str, preload: list[str]) -> None:
    """A spawned worker's start: the workers' environment (``forkserver.WORKER_ENV``, before NumPy or CUDA read
    it), the device's context asked for on a thread, the preload imported meanwhile, then the backend started as
    a forked worker starts it (``executors._start_worker``)."""
    from place3d_app.forkserver import WORKER_ENV

    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    ce = cuda_early()
    if ce is not None:
        ce.start(backend)
    for m in preload:
        importlib.import_module(m)
    from place3d_app.executors import _start_worker

    _start_worker(backend)
