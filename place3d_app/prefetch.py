"""A scene built in a forked process while this one imports a backend runtime.

A cold ``place3d optimize`` or ``evaluate`` builds the scene (pure Python and small NumPy calls) at the
moment the backend probe imports Warp or PyOpenCL (also Python). Within one process the two share the
interpreter lock, and the scene took several times longer beside Warp's import than alone (bench/README.md,
"What the studies found", cold command: the P-SOG build). A forked
child has its own interpreter, so the scene is built on another core, and this process meanwhile waits
on a pipe (which releases the lock) instead of taking turns with the import.

:func:`start` forks the child, which builds the scene, its cache key, the static mesh's normals and every
frame's actor mesh (all that the simulation needs before it needs a backend), and sends them pickled:
through an unnamed file in /dev/shm whose length goes through a pipe (the pipe itself where no such file
can be made). :func:`take` returns that scene (the same arrays, bit for bit: the child runs the same
code on a copy of this process's memory, and pickling keeps NumPy arrays exactly), and
the actor meshes kept on it (``Scene.take_prebuilt``). A child that fails, or a platform where forking is not safe, gives
``None`` and the caller builds the scene itself, as before.

Forking is safe only while this process runs one thread (a lock held by another thread at the fork stays
held in the child), so :func:`start` does nothing when other threads run (``place3d serve``, tests), on
platforms other than Linux, with a single usable core, or with ``PLACE3D_SCENE_PREFETCH=0``.
"""

from __future__ import annotations

import atexit
import os
import pickle
import signal
import sys
import tempfile
import threading
import time
from typing import Callable, Hashable

from place3d_kernels.profiling import record, section
from place3d_kernels.threads import usable_cores

__all__ = ["start", "take", "enabled", "ENV", "usable_cores", "start_for_spec", "backend_after_actors",
           "PREFETCH_ENV", "prefetch_wanted", "prepare_in_background", "import_in_background", "LATE_IMPORTS"]

#: Environment variable: "0" turns the forked scene build off (the scene is built in this process).
ENV = "PLACE3D_SCENE_PREFETCH"

_pending: dict[Hashable, tuple] = {}   # key -> (child pid, read end of its pipe, fork time, payload file or None)


def enabled() -> bool:
    """Whether :func:`start` would fork now (Linux, 2+ usable cores, one thread, not turned off)."""
    if os.environ.get(ENV, "1").strip() == "0" or not sys.platform.startswith("linux"):
        return False
    return usable_cores() >= 2 and threading.active_count() == 1


def start(key: Hashable, build: Callable[[], object], normals: bool = True) -> bool:
    """Build ``build()`` (a ``Scene``) in a forked child; :func:`take` with the same ``key`` collects it.
    ``normals``: compute the meshes' face normals there too (the returns' intensities read them; a P-SOG
    without a condition needs none).

    Returns:
        True when a child was started (False: not :func:`enabled`, already started, or the fork failed).
    """
    if key in _pending or not enabled():
        return False
    try:
        r, w = os.pipe()
    except OSError:
        return False
    # The payload (megabytes on the default town) goes through an unnamed file in memory (/dev/shm), made
    # here and inherited by the child: the pipe then carries only its length, and this process reads it in
    # one call. Through the pipe itself it came in 64 KiB (or, enlarged, 1 MiB) pieces, each read waiting
    # for the interpreter lock that the backend probe's import holds, which made the hand-over a visible
    # part of a cold command. Without such a file the payload goes through the pipe.
    try:
        shm = tempfile.TemporaryFile(dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    except OSError:
        shm = None
    forked = time.perf_counter()
    try:
        pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        if shm is not None:
            shm.close()
        return False
    if pid == 0:                                      # the child: build, send, and leave without cleanup
        code = 1
        try:
            t0 = time.perf_counter()                  # CLOCK_MONOTONIC: the parent's clock too (Linux)
            os.close(r)
            scene = build()
            t1 = time.perf_counter()
            payload = _prepared(scene, normals)
            times = (t0, t1, time.perf_counter())
            data = pickle.dumps((payload, times), protocol=pickle.HIGHEST_PROTOCOL)
            with os.fdopen(w, "wb") as f:
                if shm is not None:                   # the payload in the file, its length in the pipe
                    view, at = memoryview(data), 0
                    while at < len(data):
                        at += os.pwrite(shm.fileno(), view[at:], at)
                    f.write(b"F" + len(data).to_bytes(8, "little"))
                else:
                    f.write(b"P")
                    f.write(data)
            code = 0
        finally:
            # os._exit: no atexit handlers, no flush of stdio buffers copied from the parent
            os._exit(code)
    os.close(w)
    _pending[key] = (pid, r, forked, shm)
    return True


def _prepared(scene, normals: bool = True):
    """(scene, {frame: actor Mesh}) with the key and (``normals``) the meshes' normals computed and kept on them."""
    scene.key                       # noqa: B018 - cached on the scene (Scene.key)
    if normals:
        scene.static.normals        # noqa: B018 - cached on the mesh (Mesh.normals)
    dynamic = {}
    if scene.actors:
        dynamic = {f: scene.dynamic(f) for f in range(scene.n_frames)}
        for mesh in dynamic.values() if normals else ():
            mesh.normals            # noqa: B018 - the intensities of actor returns read them
    return scene, dynamic


def take(key: Hashable):
    """The scene the child started for ``key`` built (waiting for it), or None (none started, or it
    failed: the caller builds the scene itself)."""
    entry = _pending.pop(key, None)
    if entry is None:
        return None
    pid, r, forked, shm = entry
    with section("scene: forked build (wait)"):
        try:
            with os.fdopen(r, "rb") as f:
                data = f.read()
            if data[:1] == b"F" and len(data) == 9 and shm is not None:
                n = int.from_bytes(data[1:], "little")
                data = os.pread(shm.fileno(), n, 0)
                while len(data) < n:                  # a short read (not seen on tmpfs): the rest
                    more = os.pread(shm.fileno(), n - len(data), len(data))
                    if not more:                      # the file ends early: unpickling fails, built here
                        break
                    data += more
            else:
                data = data[1:] if data[:1] == b"P" else b""
        except OSError:
            data = b""
        finally:
            if shm is not None:
                shm.close()
        arrived = time.perf_counter()
        _reap(pid)
    if not data:
        return None
    try:
        (scene, dynamic), (t0, t1, t2) = pickle.loads(data)
    except Exception:  # noqa: BLE001 - a truncated payload (the child died): build here instead
        return None
    # the child's steps, from the fork (the rows say where a long wait went; they overlap this process's work)
    record("scene: child: fork to start", t0 - forked)
    record("scene: child: scene", t1 - t0)
    record("scene: child: actor meshes, normals", t2 - t1)
    record("scene: child: pickle and hand-over", arrived - t2)
    if dynamic:
        scene.keep_prebuilt(dynamic)
    return scene


def start_for_spec(spec, cache: bool | str = True, drives: int = 1) -> bool:
    """Start building ``spec``'s scene (a ``PSOGSpec``) in a forked child when its P-SOG build will need it:
    not for recorded frames, nor when the scene's key is remembered in the cache folder (a cached P-SOG is
    then found without it), nor when the command has several ``drives`` (worker processes build them, and
    nothing took the scene: no profile of a pooled command waited for it). Call it before the backend is
    probed; ``PSOGSpec.build`` then takes the scene through the supplier this registers
    (``place3d_kernels.spec.supply_scenes``).

    Returns:
        True when the build was started (False: not needed, or forking is off or unsafe here).
    """
    import functools

    from place3d_kernels import spec as specs

    if drives > 1 or spec.scene.kind == "semantickitti" or not enabled():
        return False
    if cache:
        from place3d_kernels.scene.keymemo import identity, recall
        from place3d_kernels.sog import cache_folder

        folder = cache_folder(cache)
        if recall(folder, identity(spec.scene.to_dict(), spec.scene.kind, spec.scene.path)) is not None:
            return False
    specs.supply_scenes(take)
    return start(spec.scene, functools.partial(specs.make_scene, spec.scene), normals=spec.condition is not None)


def backend_after_actors(spec, probe):
    """The backend a probe (a ``concurrent.futures.Future``) gives, building meanwhile what the simulation
    of ``spec``'s P-SOG needs and no backend computes: the actors' meshes of as many frames as the probe
    leaves time for, kept on the scene for ``scene_psog`` (``Scene.keep_prebuilt``). Recorded frames and
    conditions need the backend at once (they are not simulated, or their condition is made with it)."""
    if spec.scene.kind == "semantickitti" or spec.condition is not None:
        return probe.result()
    with section("P-SOG build: actors (probe)"):
        scene = spec.scene.build()
        dynamic = scene.take_prebuilt()
        for f in range(scene.n_frames):
            if probe.done():
                break
            if f not in dynamic:
                dynamic[f] = scene.dynamic(f)
        scene.keep_prebuilt(dynamic)
    with section("P-SOG build: backend wait"):
        return probe.result()


def prepare_in_background(spec, reference, lidar, task: str, occlusion: str, backend,
                          normalisation: str = "paper"):
    """Prepare, on a daemon thread, the left-out grids that the jackknife of
    ``uncertainty.rig_vs_baselines_intervals(spec, ..., reference=reference, method="jackknife")`` will ask ``HANDLES``
    for, so that a command can run it while it searches.

    The grids depend on the drive's subset records, the task, the occlusion and the backend, never on the
    rigs scored; the thread takes the records (``keyed_subset_records``) and calls ``HANDLES.get`` with the
    same key and the same preparation as the jackknife, which, arriving while the thread still works,
    waits for its list instead of preparing its own (``PreparedLeftOut.get``). No thread is started (None)
    when the jackknife would not use such grids (another path: ``fused_path``) or would not find them
    (``HANDLES`` keeps none); the thread's Future gives None when the records have no file identity (then
    nothing is kept between the two). An error on the thread is not raised there: the jackknife then
    prepares the grids itself and meets the error, if it is one, in the command.
    """
    from concurrent.futures import Future

    from place3d_kernels.left_out import HANDLES, fused_path, prepared_grids
    from place3d_kernels.pooled import PooledPSOG
    from place3d_kernels.subset_records import keyed_subset_records

    if not fused_path(lidar, occlusion, normalisation) or not HANDLES.keeps:
        return None
    done: Future = Future()

    def work():
        try:
            with section("jackknife grids (thread)"):
                records, pool_key = keyed_subset_records(spec, backend)
                pooled = PooledPSOG(spec.grid.grid(), records)
                if pool_key is None or not HANDLES.fits(pooled.grid, len(pooled)):
                    done.set_result(None)
                    return
                HANDLES.plain_psog(pooled, reference, pool_key)     # the counts from the reference, checked once
                done.set_result(HANDLES.get(pool_key, pooled.grid, task, occlusion, backend,
                                            lambda: prepared_grids(pooled, task, occlusion, backend, normalisation),
                                            normalisation=normalisation))
        except BaseException as e:  # noqa: BLE001 - handed to whoever asks the Future; the jackknife retries
            done.set_exception(e)

    threading.Thread(target=work, name="place3d-jackknife-grids", daemon=True).start()
    return done


#: ``PLACE3D_JACKKNIFE_PREFETCH``: ``1`` = ``place3d optimize`` prepares the jackknife's left-out grids (one
#: drive) or its held-out P-SOGs (pooled held-out drives, ``optimize.held_out_ahead``; their grids too, except
#: on a GPU) on a thread during the search; ``0`` = never (they are made after the search); unset or ``auto`` = on
#: hosts with 4 or more usable cores (on 2 the thread would take turns with the search's scoring).
PREFETCH_ENV = "PLACE3D_JACKKNIFE_PREFETCH"


def prefetch_wanted() -> bool:
    """What ``PLACE3D_JACKKNIFE_PREFETCH`` asks for (see ``PREFETCH_ENV``)."""
    v = os.environ.get(PREFETCH_ENV, "auto").strip().lower()
    if v in ("0", "1"):
        return v == "1"
    return usable_cores() >= 4


def _reap(pid: int) -> None:
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


@atexit.register
def _discard() -> None:
    # a scene started but never taken (a cached P-SOG was found after all, or the command failed): stop
    # the child rather than leave it building
    while _pending:
        _, (pid, r, _forked, shm) = _pending.popitem()
        if shm is not None:
            shm.close()
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
        os.close(r)
        _reap(pid)


#: What a command imports only at its end: SciPy's t distribution for the intervals, and matplotlib (without
#: pyplot, which the plotting code imports after choosing the Agg backend) for the plot.
LATE_IMPORTS = {"intervals": ("scipy.special",),
                "plot": ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg")}


def import_in_background(*modules: str) -> threading.Thread | None:
    """Import ``modules`` on a daemon thread, so a command's late imports (``LATE_IMPORTS``) load while it
    waits on the GPU, the disk or NumPy calls that release the interpreter lock, instead of after them.
    Python's per-module import locks make the command's own import of the same module wait for this one
    or find it done. Start it after :func:`start` (a fork needs a single thread). A module that fails to
    import is left to the command's own import, which reports it."""
    if not modules:
        return None

    def run():
        import importlib

        for m in modules:
            try:
                importlib.import_module(m)
            except Exception:           # noqa: BLE001 - the command's own import raises it where it matters
                return

    t = threading.Thread(target=run, name="place3d-late-imports", daemon=True)
    t.start()
    return t
