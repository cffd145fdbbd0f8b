"""The server the commands fork their worker processes from, and its early start.

On Linux the commands' workers (``executors.ProcessExecutor(start_method=command_start_method())``) are forked
from a ``multiprocessing`` forkserver that imported ``preload_for(backend)`` once: NumPy, the drive tasks' modules
and Warp, and SciPy's spatial and image parts where the drives include OpenDRIVE maps (0.4-1.5 s of imports,
which sixteen spawned workers would otherwise each repeat side by side). A worker can start only once that server
has its imports.

``place3d reproduce`` always builds its drives on workers where more than one core is usable, and ``evaluate``
and ``optimize`` build on workers the drives their cache lacks: the console script starts the server
(``start_early``) before it imports the package and parses the command line, for ``reproduce`` always and for the
other two while the P-SOG cache holds no drive yet (a machine's first run): the server's imports then run beside
this process's own (about 0.6-0.8 s of start-up on the H200 host) and its backend probe, instead of after them.
A cold default ``evaluate`` on an H200 took 2.97 [2.93-3.03] s without it, 2.53 [2.33-2.58] s with it (3 runs each,
bench/results/ab-2026-11-30-s35/README.md). Standard library only, for that reason.
"""

from __future__ import annotations

import contextlib
import os
import sys

__all__ = ["WORKER_ENV", "FORKSERVER_PRELOAD", "START_METHOD_ENV", "WORKERS_ENV", "worker_environment",
           "OPENDRIVE_PRELOAD", "preload_for", "command_start_method", "start", "start_early"]

#: What each worker process starts with, unless the user set it: one BLAS thread. The workers fill the cores
#: themselves; a BLAS library that also starts a thread per core in every worker (NumPy's OpenBLAS does for a
#: matrix product of one frame's points) oversubscribes them many times over. BLAS threads split a product's
#: output, not its sums, so a product's values are the same with any number of them (the test of the process
#: executor compares its pooled counts with the local executor's bit for bit).
#:
#: And one hardware work queue per CUDA context (``CUDA_DEVICE_MAX_CONNECTIONS``, default 8: without MPS each
#: context gets its own pool of host-to-device connections, NVIDIA's MPS documentation, "Environment Variables").
#: The driver makes the workers' contexts one after another, and their queues are most of that work: on an
#: H200, sixteen processes starting a context at once waited 2.2-2.4 s each, 0.8-0.9 s with one queue (Warp's
#: whole start 2.4-2.5 -> 1.1 s); NVIDIA's OpenCL driver makes CUDA contexts too. A worker runs its kernels on
#: one stream (Warp's) or one OpenCL queue, in order, so a single queue takes nothing from it; the console script
#: sets it for the kernel commands' own process too (``place3d_app.ONE_QUEUE_COMMANDS``;
#: bench/results/ab-2026-11-30-s34/README.md).
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "CUDA_DEVICE_MAX_CONNECTIONS": "1"}

#: What a forkserver imports once before it forks the workers: the drive tasks' modules (the scene builders
#: with them). Imports only: no backend, device, thread or file is made by importing them, so a forked copy is a
#: clean worker.
FORKSERVER_PRELOAD = ("place3d_kernels.pooled", "place3d_kernels.pipeline", "place3d_kernels.simulate",
                      "place3d_kernels.scene.opendrive", "place3d_kernels.spec")
#: What it imports besides for workers that may build scenes of OpenDRIVE maps: the SciPy parts their builders
#: take (k-d trees, image morphology). A drive of the embedded town imports neither, and they were half of the
#: server's imports, which every worker waits for (1.00-1.52 -> 0.44-0.69 s without them on the H200 host, 3 rounds;
#: bench/results/ab-2026-11-30-s35/README.md).
OPENDRIVE_PRELOAD = ("scipy.spatial", "scipy.ndimage")

#: Environment variable: how the commands' worker processes start, ``spawn`` or ``forkserver`` (default: a
#: forkserver on Linux, see ``command_start_method``).
START_METHOD_ENV = "PLACE3D_START_METHOD"

#: ``PLACE3D_WORKERS=N``: at most N worker processes for the process executor (default: the usable cores;
#: ``executors.default_workers``).
WORKERS_ENV = "PLACE3D_WORKERS"


@contextlib.contextmanager
def worker_environment():
    """``WORKER_ENV`` in ``os.environ`` while worker processes (or their server) start: a spawned process, and a
    forkserver with every worker it forks, copies it then."""
    added = {k: v for k, v in WORKER_ENV.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def preload_for(backend: str | None, opendrive: bool = True) -> list[str]:
    """``FORKSERVER_PRELOAD`` (and ``OPENDRIVE_PRELOAD`` unless ``opendrive`` is False: workers that build no
    scene of an OpenDRIVE map) plus Warp (imported, not initialised) for a backend that runs on it, or PyOpenCL
    and the OpenCL backend's modules (imported; no platform is asked for, so no driver is loaded) for an OpenCL
    one: sixteen workers importing PyOpenCL side by side took 0.53-0.81 s each on a 16-core H200 host, 0.3-0.4 s
    alone (bench/results/ab-2026-11-30-s32/README.md, section 2)."""
    import importlib.util

    mods = list(FORKSERVER_PRELOAD) + (list(OPENDRIVE_PRELOAD) if opendrive else [])
    name = (backend or "").strip().lower()
    if name in ("auto", "warp") or name.startswith("warp:"):
        if importlib.util.find_spec("warp") is not None:
            mods.append("place3d_kernels.backends.warp")
    elif name == "opencl" or name.startswith("opencl:"):
        if importlib.util.find_spec("pyopencl") is not None:
            mods.append("place3d_kernels.backends.opencl")
    return mods


def command_start_method() -> str:
    """How the commands' worker processes start: ``$PLACE3D_START_METHOD``, else ``"forkserver"`` on Linux, else
    ``"spawn"`` (macOS has a forkserver, but a process forked after Apple's system frameworks were loaded, as
    NumPy's Accelerate build loads them, may crash: Python spawns there by default for that reason).

    Raises:
        ValueError: ``$PLACE3D_START_METHOD`` names another method, or one this platform lacks.
    """
    import multiprocessing

    have = multiprocessing.get_all_start_methods()
    asked = os.environ.get(START_METHOD_ENV, "").strip().lower()
    if asked:
        if asked not in ("spawn", "forkserver") or asked not in have:
            raise ValueError(f"{START_METHOD_ENV}={asked!r}: use spawn or forkserver (this platform has "
                             f"{', '.join(m for m in have if m != 'fork')})")
        return asked
    return "forkserver" if sys.platform.startswith("linux") and "forkserver" in have else "spawn"


def start(backend: str | None, opendrive: bool = True) -> None:
    """Start this process's forkserver (a no-op if it runs already) with ``preload_for(backend, opendrive)`` and
    the workers' environment. Returns at once: the server imports its preload on its own."""
    import multiprocessing
    import multiprocessing.forkserver

    # only read by a forkserver not yet running (one per process; every later executor shares it: a worker that
    # needs a module the server did not import imports it itself)
    multiprocessing.get_context("forkserver").set_forkserver_preload(preload_for(backend, opendrive))
    with worker_environment():
        multiprocessing.forkserver.ensure_running()


def _options(argv: list[str], name: str) -> list[str]:
    """Every value of ``--name VALUE`` / ``--name=VALUE`` in ``argv``, in order."""
    out = []
    for i, a in enumerate(argv):
        if a == name and i + 1 < len(argv):
            out.append(argv[i + 1])
        elif a.startswith(name + "="):
            out.append(a.partition("=")[2])
    return out


def _option(argv: list[str], name: str) -> str | None:
    """The value of ``--name VALUE`` or ``--name=VALUE`` in ``argv`` (the last one given), else None."""
    return (_options(argv, name) or [None])[-1]


def _usable_cores() -> int:
    # place3d_kernels.threads.usable_cores, which this module cannot import: importing any part of the package
    # runs place3d_kernels/__init__.py (NumPy and the library, the start-up this module exists to run beside)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _cache_folder() -> str:
    """``backends.base.cache_dir()`` without importing the package: ``$PLACE3D_CACHE`` or ``~/.cache/place3d``
    (tests/test_executors.py holds the two together)."""
    return os.environ.get("PLACE3D_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "place3d"))


def _no_drive_cached() -> bool:
    """Whether the P-SOG cache folder (``_cache_folder``) holds no P-SOG file (``psog-*.npz``, as
    ``pipeline.cache_file`` names them) yet: the first run on a machine, whose drives are all built by worker
    processes."""
    try:
        with os.scandir(_cache_folder()) as it:
            return not any(e.name.startswith("psog-") and e.name.endswith(".npz") for e in it)
    except OSError:                   # no folder yet
        return True


#: The commands that build a cold cache's drives in worker processes (``routes.build_missing``): ``start_early``
#: starts their server while the cache holds no drive (``_no_drive_cached``).
DRIVE_COMMANDS = ("evaluate", "optimize")


def start_early(argv: list[str]) -> bool:
    """Start the forkserver now when ``argv`` (the command line without the program name) is a command that will
    fork its workers from it: a ``reproduce`` with the default or ``--executor process``/``auto``, or an
    ``evaluate`` / ``optimize`` of several drives (not ``--routes 1``, not only mesh or recorded scenes, which
    have one route each) with the local executor, the cache on and no drive in it yet; never with
    ``--ray-address``; a forkserver as the start method, more than one usable core (and ``$PLACE3D_WORKERS`` not
    1). The backend of ``--backend`` (default ``auto``) picks the preload, as ``executors.executor_from_args``
    does; SciPy's parts are left out for drives of the embedded town only.

    A guess from the raw arguments (argparse, which reads them later, also takes abbreviated options): a wrong
    one costs an idle server, never a result, and an invalid setting is left for the command to report.
    Returns whether the server was started."""
    try:
        cmd = next((a for a in argv if not a.startswith("-")), None)
        if cmd not in ("reproduce", *DRIVE_COMMANDS) or "-h" in argv or "--help" in argv:
            return False
        executors = ("auto", "process") if cmd == "reproduce" else ("local", "auto")
        if (_option(argv, "--executor") or executors[0]) not in executors or _option(argv, "--ray-address"):
            return False
        scenes = _options(argv, "--scene") or ["town"]
        if cmd != "reproduce" and ("--no-cache" in argv or _option(argv, "--routes") == "1" or not _no_drive_cached()
                                   or all(v.startswith(("mesh:", "semantickitti:")) for v in scenes)):
            return False        # nothing for workers: drives cached, or scenes of one fixed route each
        if command_start_method() != "forkserver":
            return False
        cap = os.environ.get(WORKERS_ENV, "").strip()
        if min(_usable_cores(), int(cap) if cap.isdigit() else 2) < 2:
            return False
        town_only = cmd != "reproduce" and all(v == "town" for v in scenes)
        start(_option(argv, "--backend") or "auto", opendrive=not town_only)
        return True
    except Exception:  # noqa: BLE001 - a speed-up only: the command starts its server itself, or reports why not
        return False
