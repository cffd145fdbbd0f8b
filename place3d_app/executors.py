"""Scale-out on Ray: an executor choice, distributed dataset simulation and distributed population scoring.

Everything a task needs travels in the task itself (scene spec, LiDAR, backend name, condition spec,
frame indices or candidate rows), so tasks are pure functions of explicit inputs and give the same bytes
on any worker as the local executor does in-process:

    >>> from place3d_app.executors import SceneSpec, get_executor, simulate_to_folder
    >>> ex = get_executor("ray")                           # or "local"; address="ray://head:10001"
    >>> simulate_to_folder(SceneSpec("town", seed=0, frames=40), "collection_64ch", "seq/", ex, chunk=8)

- ``get_executor(kind, address, num_cpus, num_gpus_per_task)`` -> ``Executor`` with ``map(fn, tasks)``
  (results in task order): ``"local"`` (in-process, one task after the other), ``"process"`` (worker
  processes of this machine, ``ProcessExecutor``) or ``"ray"``. The Ray executor retries a task whose worker process dies (Ray's
  ``max_retries``); an exception raised by the task itself is not retried and reaches the caller.
- ``simulate_to_folder``: frames split into chunks of frame indices; each task simulates its frames,
  applies the condition with the frame's *global* index and writes ``velodyne/NNNNNN.bin`` and
  ``labels/NNNNNN.label`` atomically; the driver writes ``poses.txt`` at the end. A rerun skips
  frames whose two files exist, so a killed run resumes without losing or duplicating anything.
- ``DistributedObjective``: splits each CMA-ES batch into chunks scored as tasks; workers load the
  P-SOG from the on-disk cache of ``scene_psog`` (keyed by its inputs), building it only if absent.
  When the Ray executor has scoring actors (``get_executor("ray", gpu_actors=N, cpu_actors=M)``,
  ``--gpu-actors N --cpu-actors M``), the chunks go to long-lived actors instead, one per GPU plus M on
  CPU cores, which keep the backend, its compiled kernels and the P-SOG between generations and take
  chunks dynamically (``place3d_app.actors``). Same scores, bit for bit, as the tasks and as
  ``msog_batch`` in-process.
- The specs (``SceneSpec``, ``ConditionSpec``, ``PSOGSpec``) live in ``place3d_kernels.spec`` and are
  re-exported here.
- ``task_seed(run_seed, task_id)``: seeds derived from the run seed and the task id only. The frame
  conditions already seed each frame from (run seed, global frame index) (``FrameCondition``).

GPU tasks: ``num_gpus_per_task=1`` makes Ray pin one GPU per task and set ``CUDA_VISIBLE_DEVICES``,
so the task's backend is ``warp:cuda:0`` / ``opencl:nvidia`` on every worker.
Multi-machine clusters: the output folder and the P-SOG cache folder should be on shared storage
(a worker that cannot see the cache rebuilds the P-SOG, deterministically, and pays its time).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from place3d_kernels.io import (atomic_write, frame_paths, pose_row, prepare_sequence_folder, sensor_matrix,
                                sequence_spec, write_sequence_metadata)
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.spec import ConditionSpec, PSOGSpec, SceneSpec, backend_name, resolve_lidar
from place3d_kernels.threads import usable_cores

from place3d_app.forkserver import START_METHOD_ENV, WORKER_ENV, WORKERS_ENV, command_start_method, worker_environment

__all__ = ["Executor", "LocalExecutor", "ProcessExecutor", "RayExecutor", "get_executor", "usable_cores",
           "default_workers", "WORKERS_ENV", "WORKER_ENV", "START_METHOD_ENV", "command_start_method",
           "add_executor_arguments",
           "executor_from_args", "check_actor_arguments", "task_seed", "SceneSpec", "ConditionSpec", "PSOGSpec",
           "simulate_to_folder",
           "DistributedObjective", "INSTALL_HINT", "chunks"]

INSTALL_HINT = "pip install 'place3d-kernels[dist]'"


# ============================================================================== executors
def task_seed(run_seed: int, task_id: int) -> int:
    """A 32-bit seed from (run seed, task id) only: never from worker identity, time or order."""
    return int(np.random.SeedSequence([int(run_seed), int(task_id)]).generate_state(1, np.uint32)[0])


class Executor:
    """Runs ``fn(task)`` for each task; ``map`` returns the results in task order.

    ``submitted`` counts the tasks handed to ``map`` over the executor's life (used to show that a
    rerun of a finished job does no work).
    """

    kind = "base"

    def __init__(self) -> None:
        self.submitted = 0

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any], *, num_gpus: float | None = None) -> list:
        tasks = list(tasks)
        self.submitted += len(tasks)
        return self._map(fn, tasks, num_gpus) if tasks else []

    def _map(self, fn: Callable[[Any], Any], tasks: list, num_gpus: float | None) -> list:
        """``map``'s work for a non-empty task list (counted already), in task order."""
        raise NotImplementedError

    def shutdown(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


class LocalExecutor(Executor):
    """In-process, one task after the other (the reference the Ray executor must match)."""

    kind = "local"

    def _map(self, fn, tasks, num_gpus) -> list:
        return [fn(t) for t in tasks]


def default_workers() -> int:
    """Worker processes of the process executor: the usable cores, at most ``$PLACE3D_WORKERS``."""
    n = usable_cores()
    cap = os.environ.get(WORKERS_ENV, "").strip()
    if cap:
        try:
            c = int(cap)
        except ValueError:
            c = 0
        if c < 1:
            raise ValueError(f"{WORKERS_ENV}={cap!r}: give a whole number of worker processes >= 1")
        n = min(n, c)
    return n


def _start_worker(backend: str | None) -> None:
    # a drive task returns before its P-SOG file is written (pipeline.saves_outlive_tasks): the worker waits for
    # its saves when it ends, which it does when it reads the pool's exit sentinel (``shutdown``): its non-daemon
    # threads, the saver's among them, are joined before it leaves (``BaseProcess._bootstrap``)
    from place3d_kernels.pipeline import saves_outlive_tasks
    from place3d_kernels.threads import leave_at_exit

    saves_outlive_tasks(True)
    # a forkserver's worker then leaves with os._exit (the server's child never tears its interpreter down); a
    # spawned one would run the interpreter's whole teardown (its device context's among it): it leaves at its
    # first exit handler instead, once its threads are joined (``threads.leave_at_exit``)
    leave_at_exit()
    # each worker resolves the run's backend once (get_backend keeps one instance per name), on a thread of
    # its own, and takes its first task at once: a drive's scene (Python, the CPU) is built while the backend
    # starts (on CUDA mostly the driver's context and module loads, foreign calls that let this thread run);
    # the task's first get_backend waits for that thread's (the registry makes each backend once)
    if backend:
        start_backend(backend)


_backends_started: set = set()
_backends_lock = threading.Lock()


def start_backend(backend: str) -> None:
    """Resolve ``backend`` on a thread of its own, once per process (a worker's first task, or its start, asks):
    a later ``get_backend`` of that name waits for it instead of starting it again."""
    if not backend:
        return
    with _backends_lock:
        if backend in _backends_started:
            return
        _backends_started.add(backend)
    threading.Thread(target=_resolve_backend, args=(backend,), daemon=True, name="place3d-backend").start()


def _resolve_backend(backend: str) -> None:
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.profiling import section

    try:
        with section("worker backend start (thread)"):
            get_backend(backend)
    except Exception:  # noqa: BLE001 - the task's own get_backend meets the same failure and reports it
        pass


def _no_task() -> None:
    return None


class ProcessExecutor(Executor):
    """Worker processes on this machine (``concurrent.futures.ProcessPoolExecutor``), results in task order.

    Processes start with ``spawn`` (a fresh interpreter; ``forkserver`` by ``start_method``), never by a plain
    fork: a forked copy of a process that has started CUDA or OpenCL cannot use them. A ``forkserver`` imports
    ``forkserver.preload_for(backend)`` once and forks every worker from that clean state, so the workers do not each
    import NumPy, SciPy, Warp and the package (about a second of CPU each). Tasks and results
    cross a pickle boundary, so ``fn`` must be a module-level function and its tasks picklable, as for Ray.
    Several workers share one GPU (each has its own context; Warp and OpenCL allow it).

    Args:
        workers: worker processes (default ``default_workers()``: the usable cores, at most
            ``$PLACE3D_WORKERS``); a ``map`` of fewer tasks starts no more processes than it has tasks.
        backend: backend name each worker resolves when it starts (None: none ahead of the first task).
        start_method: ``"spawn"`` (default) or ``"forkserver"``.
        prestart: start the workers now instead of at the first ``map``, so that they import the package
            and resolve the backend while this process goes on.
        preload: the backend name whose modules a ``forkserver`` imports (``forkserver.preload_for``; default
            ``backend``), for a caller that starts the server (``start_server``) before it knows the backend;
            ``backend`` may then be set until the first ``map``.
        opendrive: whether the workers may build scenes of OpenDRIVE maps (the server then imports the SciPy
            parts of their builders too; ``forkserver.OPENDRIVE_PRELOAD``).
    """

    kind = "process"

    def __init__(self, workers: int | None = None, backend: str | None = None, start_method: str = "spawn",
                 prestart: bool = False, preload: str | None = None, opendrive: bool = True) -> None:
        super().__init__()
        if start_method not in ("spawn", "forkserver"):
            raise ValueError(f"start_method must be 'spawn' or 'forkserver', got {start_method!r}")
        self.workers = default_workers() if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.backend = backend
        self.preload = backend if preload is None else preload
        self.opendrive = opendrive
        self.start_method = start_method
        self._pool = None
        self._started = 0
        self._lock = threading.Lock()           # _ensure and shutdown, which a prestart thread may be in
        self._server_started = False
        if prestart and start_method == "forkserver":
            # the server imports its preload (a second or so) before it forks the first worker, and starting a
            # worker waits for that fork: the workers are started on a thread, so this process goes on meanwhile
            self._start_server()
            threading.Thread(target=self._ensure, args=(self.workers,), daemon=True, name="place3d-workers").start()
        elif prestart:
            self._ensure(self.workers)

    def start_server(self) -> None:
        """Start the forkserver now (a no-op for spawned workers): it imports its preload while this process
        goes on, and the first ``map`` forks the workers from it without waiting for those imports."""
        if self.start_method == "forkserver":
            with self._lock:
                if not self._server_started:
                    self._start_server()

    def _start_server(self) -> None:
        """Start the forkserver (if this process has none yet: ``forkserver.start``) with the workers'
        environment: every worker forked from it has that environment. Called on the thread that made the
        executor."""
        from place3d_app import forkserver

        forkserver.start(self.preload, self.opendrive)
        self._server_started = True

    def _context(self):
        import multiprocessing

        return multiprocessing.get_context(self.start_method)

    def _environment(self):
        """``worker_environment`` where workers are spawned from this process; a forkserver's workers have the
        server's environment, set when it started (and this process's environment is not changed from a
        thread, which another thread's C code reading it could meet half-written)."""
        return worker_environment() if self.start_method == "spawn" else contextlib.nullcontext()

    def _ensure(self, n_tasks: int):
        """The pool, with at least min(n_tasks, workers) processes started."""
        import concurrent.futures

        with self._lock:
            if self._pool is None:
                if self.start_method == "forkserver" and not self._server_started:
                    self._start_server()
                self._pool = concurrent.futures.ProcessPoolExecutor(self.workers, mp_context=self._context(),
                                                                    initializer=_start_worker,
                                                                    initargs=(self.backend,))
            want = min(max(n_tasks, 1), self.workers)
            if self._started < want:
                with self._environment():
                    # one empty task per missing worker: a pool of spawned processes starts one per task while
                    # none is idle; each runs the initializer before anything else
                    for _ in range(want - self._started):
                        self._pool.submit(_no_task)
                self._started = want
            return self._pool

    def _map(self, fn, tasks, num_gpus) -> list:
        pool = self._ensure(len(tasks))
        with self._environment():
            futures = [pool.submit(fn, t) for t in tasks]
        try:
            return [f.result() for f in futures]
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    def submit(self, fn, task):
        """``fn(task)`` on a worker, without waiting: a ``concurrent.futures.Future`` of its result."""
        self.submitted += 1
        pool = self._ensure(1)
        with self._environment():
            return pool.submit(fn, task)

    def shutdown(self, wait: bool = True, cancel: bool = True) -> None:
        """Stop the workers: each leaves once its task, if any, has returned and it reads the pool's exit
        sentinel, after its cache files are written (``_start_worker``); ``wait=False`` returns at once, and the
        interpreter joins them at its exit, so the cache is whole when the command ends. ``cancel``: tasks not
        started yet are dropped (their futures cancelled); with False they still run, and their futures
        complete, before the workers leave. A later ``map`` starts new ones.

        Idle workers are not sent SIGTERM (as they were until 2026-11-30): an idle worker waits in the task
        queue's read, one of them holding the queue's lock, a semaphore shared by the workers. A signal that
        reaches a worker just before it blocks on that lock is not acted on until the lock is had, and the
        lock's holder, ended by its own signal, never gives it back: that worker then waited forever, and the
        interpreter's exit with it (2 of about 600 idle pools on the dev VM; tests/test_executors.py)."""
        with self._lock:
            pool, self._pool, self._started = self._pool, None, 0
        if pool is None:
            return
        pool.shutdown(wait=wait, cancel_futures=cancel)


def _import_ray():
    try:
        import ray
    except ImportError as e:
        raise ImportError(f"the Ray executor needs Ray: {INSTALL_HINT}  (import failed: {e})") from None
    return ray


class RayExecutor(Executor):
    """Tasks on a Ray cluster: a new local one (``address=None``) or an existing one (``"auto"``,
    ``"HOST:PORT"``, ``"ray://HOST:10001"``).

    Args:
        address: cluster address; None starts a local cluster unless Ray is already initialised.
        num_cpus: CPUs of a local cluster started here (default: all).
        num_gpus_per_task: GPUs each task requests (0 = CPU tasks).
        cpus_per_task: CPUs each task requests (default 1).
        max_retries: retries of a task whose worker dies (Ray's ``max_retries``).
        gpu_actors: scoring actors reserving one GPU each (``DistributedObjective`` then scores on
            actors instead of tasks; ``place3d_app.actors``). Started on the first scored batch.
        cpu_actors: scoring actors on CPU cores (alone, or beside the GPU actors).
        cpu_backends: the CPU actors' backend: one name or one per actor (default: the run's backend when
            it is a CPU one, else the first of opencl:pocl, warp:cpu, reference on the actor's host).
    """

    kind = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None, num_gpus_per_task: float = 0,
                 cpus_per_task: float = 1, max_retries: int = 3, gpu_actors: int = 0, cpu_actors: int = 0,
                 cpu_backends: str | Sequence[str] | None = None) -> None:
        super().__init__()
        ray = _import_ray()
        self._ray = ray
        self._owns = False
        if not ray.is_initialized():
            kw: dict = {"include_dashboard": False, "log_to_driver": True}
            if address is None:
                kw["num_cpus"] = num_cpus
            ray.init(address=address, **kw)
            self._owns = True
        self.num_gpus_per_task = float(num_gpus_per_task or 0)
        self.cpus_per_task = float(cpus_per_task)
        self.max_retries = int(max_retries)
        self.gpu_actors, self.cpu_actors = int(gpu_actors or 0), int(cpu_actors or 0)
        if self.gpu_actors < 0 or self.cpu_actors < 0:
            raise ValueError(f"actor counts must be >= 0, got --gpu-actors {gpu_actors} --cpu-actors {cpu_actors}")
        self.cpu_backends = cpu_backends
        self.pool = None

    @property
    def has_actors(self) -> bool:
        """Whether population scoring goes to actors (``gpu_actors + cpu_actors > 0``)."""
        return self.gpu_actors + self.cpu_actors > 0

    def scoring_pool(self, backend: str | None = None):
        """The ``actors.ScoringPool`` (started on first use; ``backend`` is the run's backend name, which
        decides the actors' backends then and is ignored afterwards)."""
        if self.pool is None:
            from place3d_app.actors import ScoringPool

            self.pool = ScoringPool(self._ray, self.gpu_actors, self.cpu_actors, backend=backend,
                                    cpu_backends=self.cpu_backends)
        return self.pool

    def _map(self, fn, tasks, num_gpus) -> list:
        gpus = self.num_gpus_per_task if num_gpus is None else float(num_gpus)
        remote = self._ray.remote(num_cpus=self.cpus_per_task, num_gpus=gpus, max_retries=self.max_retries)(fn)
        return self._ray.get([remote.remote(t) for t in tasks])

    def shutdown(self) -> None:
        if self.pool is not None and self._ray.is_initialized():
            self.pool.shutdown()
        self.pool = None
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()
        self._owns = False


def get_executor(kind: str = "local", address: str | None = None, num_cpus: int | None = None,
                 num_gpus_per_task: float = 0, **kw) -> Executor:
    """``"local"``, ``"process"`` or ``"ray"``; a Ray address implies ``"ray"``. Keywords go to
    ``ProcessExecutor`` (``workers``, ``backend``, ``prestart``) or ``RayExecutor`` (e.g.
    ``gpu_actors=2, cpu_actors=1`` for population scoring on actors)."""
    kind = (kind or "local").lower()
    if kind == "local" and address:
        kind = "ray"
    if kind == "local":
        return LocalExecutor()
    if kind == "process":
        return ProcessExecutor(**kw)
    if kind == "ray":
        return RayExecutor(address=address, num_cpus=num_cpus, num_gpus_per_task=num_gpus_per_task, **kw)
    raise ValueError(f"unknown executor {kind!r}; use 'local', 'process' or 'ray'")


def add_executor_arguments(p, default: str = "local") -> None:
    """``--executor auto|local|process|ray``, ``--ray-address``, ``--num-cpus``, ``--gpus-per-task``, ``--chunk``,
    ``--gpu-actors``, ``--cpu-actors``. ``default="auto"`` for a command that pools several drives."""
    p.add_argument("--executor", default=default, choices=["auto", "local", "process", "ray"],
                   help=f"where tasks run: local (this process), process (one worker process per usable core, "
                        f"at most ${WORKERS_ENV}), ray (needs {INSTALL_HINT}), auto (process where the command "
                        f"has several drives to build and more than one core is usable, else local; default "
                        f"{default})")
    p.add_argument("--ray-address", default=None,
                   help="Ray cluster to join: auto | HOST:PORT | ray://HOST:10001 (default: start a local one)")
    p.add_argument("--num-cpus", type=int, default=None, help="CPUs of a local Ray cluster (default: all)")
    p.add_argument("--gpus-per-task", type=float, default=0, help="GPUs each Ray task requests (default 0)")
    p.add_argument("--chunk", type=int, default=None,
                   help="frames (simulate) or candidates (optimize) per task (default: 8 / batch split over workers)")
    p.add_argument("--gpu-actors", type=int, default=0,
                   help="optimize with --executor ray: score the population on N long-lived actors, one per GPU "
                        "(warm backend and P-SOG between generations; default 0: Ray tasks)")
    p.add_argument("--cpu-actors", type=int, default=0,
                   help="optimize with --executor ray: N scoring actors on CPU cores, alone or beside the GPU "
                        "actors (default 0)")


def check_actor_arguments(args) -> dict:
    """``{"gpu_actors": N, "cpu_actors": M}`` from the command line; ``ValueError`` for a negative count
    or for actors asked for without ``--executor ray`` / ``--ray-address`` (before any work starts)."""
    actors = {"gpu_actors": getattr(args, "gpu_actors", 0) or 0, "cpu_actors": getattr(args, "cpu_actors", 0) or 0}
    if min(actors.values()) < 0:
        raise ValueError(f"--gpu-actors {actors['gpu_actors']} --cpu-actors {actors['cpu_actors']}: counts must "
                         f"be >= 0")
    ray_asked = (getattr(args, "executor", "local") or "local") == "ray" or getattr(args, "ray_address", None)
    if any(actors.values()) and not ray_asked:
        raise ValueError(f"--gpu-actors {actors['gpu_actors']} --cpu-actors {actors['cpu_actors']} need "
                         f"--executor ray")
    return actors


def executor_from_args(args, tasks: int | None = None, backend=None) -> Executor:
    """The executor the command line asks for. ``tasks``: how many independent tasks (drives) the command has,
    for ``--executor auto`` (process when more than one and more than one core is usable, else local);
    ``backend``: the backend name worker processes resolve as they start."""
    kind = getattr(args, "executor", "local") or "local"
    if kind == "auto":
        if getattr(args, "ray_address", None):
            kind = "ray"
        else:
            kind = "process" if (tasks or 0) > 1 and min(default_workers(), tasks) > 1 else "local"
    if kind in ("local", "process") and getattr(args, "ray_address", None):
        raise ValueError("--ray-address needs --executor ray")
    actors = check_actor_arguments(args)
    if kind == "process":
        n = default_workers() if tasks is None else max(1, min(default_workers(), tasks))
        # started now: the workers import the package and resolve the backend while this process does too
        return ProcessExecutor(n, backend=str(backend or "auto"), prestart=True,
                               start_method=command_start_method())
    if kind == "ray":
        try:
            return get_executor("ray", getattr(args, "ray_address", None), getattr(args, "num_cpus", None),
                                getattr(args, "gpus_per_task", 0) or 0, **actors)
        except ImportError as e:
            raise ValueError(str(e)) from None
    return get_executor(kind)


def chunks(items: Sequence, size: int) -> list[list]:
    size = max(1, int(size))
    items = list(items)
    return [items[i:i + size] for i in range(0, len(items), size)]


# ============================================================================== simulate
def _frame_done(out: Path, i: int) -> bool:
    b, lab = frame_paths(out, i)
    return b.exists() and lab.exists()


@dataclass(frozen=True)
class _SimTask:
    task_id: int
    frames: tuple
    scene: SceneSpec
    lidar: Any
    mount: tuple
    backend: str
    condition: ConditionSpec | None
    out: str
    hook: Any = None            # test hook: hook(task_id, frame_index) after each frame is written


def _simulate_task(t: _SimTask) -> list[int]:
    """Simulate and write the task's frames that are not on disk yet; returns the frames written."""
    from place3d_kernels.io import write_frame
    from place3d_kernels.simulate import simulate

    out = Path(t.out)
    sc = t.scene.build()
    cond = None if t.condition is None else t.condition.condition(t.backend)
    written = []
    for i in t.frames:
        if _frame_done(out, i):
            continue
        (f,) = simulate(sc, resolve_lidar(t.lidar), mount=np.asarray(t.mount), frames=[i], backend=t.backend)
        if cond is not None:
            f = cond(f, i)                                     # the frame's global index seeds it
        frame_paths(out, i)[0].unlink(missing_ok=True)         # label written last marks the frame done
        write_frame(out, i, f)
        written.append(int(i))
        if t.hook is not None:
            t.hook(t.task_id, int(i))
    return written


def simulate_to_folder(scene: SceneSpec | tuple, lidar="collection_64ch", out="seq", executor: Executor | None = None,
                       *, chunk: int = 8, mount=None, backend=None, condition=None, frames=None,
                       task_hook: Callable | None = None, overwrite: bool = False) -> dict:
    """Simulate a scene's frames as tasks into a SemanticKITTI folder (resumable; identical to local).

    Args:
        scene: ``SceneSpec`` or (name, seed, n_frames).
        lidar: LiDAR name or ``LidarModel`` (travels with the tasks).
        out: output folder (``velodyne/``, ``labels/``, ``poses.txt``).
        executor: ``get_executor(...)`` (default local).
        chunk: frames per task.
        mount: (6,) sensor pose in the ego frame (default ``simulate.DEFAULT_MOUNT``).
        backend: backend name for the tasks.
        condition: ``FrameCondition``, ``ConditionSpec``, dict or None.
        frames: global frame indices to produce (default all); ``poses.txt`` always lists every frame.
        task_hook: ``hook(task_id, frame_index)`` called in the worker after each frame is written (tests).
        overwrite: replace a sequence in ``out`` made with other settings (otherwise ``ValueError`` naming
            the field that differs, before any task runs; ``sequence.json`` records the settings).

    Returns:
        dict: frames, written, skipped, tasks, seconds, out.
    """
    from place3d_kernels.pose import pose_from_matrix, pose_matrix
    from place3d_kernels.simulate import DEFAULT_MOUNT

    t0 = time.perf_counter()
    spec = scene if isinstance(scene, SceneSpec) else SceneSpec(*scene)
    executor = executor or LocalExecutor()
    mount = tuple(float(v) for v in (DEFAULT_MOUNT if mount is None else np.asarray(mount, np.float64)))
    out = Path(out)
    cspec = ConditionSpec.of(condition)
    meta = sequence_spec(spec.to_dict(), resolve_lidar(lidar), None if cspec is None else cspec.to_dict(), mount)
    prepare_sequence_folder(out, meta, overwrite=overwrite)   # a folder of other settings is refused here
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    idx = list(range(spec.frames)) if frames is None else [int(i) for i in frames]
    todo = [i for i in idx if not _frame_done(out, i)]
    bname = backend_name(backend)
    tasks = [_SimTask(k, tuple(c), spec, lidar, mount, bname, cspec, str(out), task_hook)
             for k, c in enumerate(chunks(todo, chunk))]
    written = [i for w in executor.map(_simulate_task, tasks) for i in w]
    # poses.txt by the driver: the sensor origin is the translation of ego @ mount, exactly as the
    # backends return it (lidar_rays copies the pose's position), so no frame needs re-simulating.
    sc = spec.build()
    mount_T = pose_matrix(np.asarray(mount))
    rows = []
    for i in range(spec.frames):
        origin = pose_from_matrix(pose_matrix(sc.ego_poses[i]) @ mount_T)[:3]
        rows.append(pose_row(sensor_matrix(PointCloud(np.zeros((0, 3)), np.zeros(0), ego_pose=sc.ego_poses[i],
                                                      sweep_origin=origin))))
    atomic_write(out / "poses.txt", ("\n".join(rows) + "\n").encode())
    missing = [i for i in idx if not _frame_done(out, i)]
    if missing:
        raise RuntimeError(f"frames {missing[:10]} were not written to {out}")
    write_sequence_metadata(out, meta)
    return {"frames": len(idx), "written": len(written), "skipped": len(idx) - len(todo), "tasks": len(tasks),
            "seconds": time.perf_counter() - t0, "out": str(out)}


# ============================================================================== P-SOG and scoring
def _score_task(t: tuple) -> np.ndarray:
    psog_spec, lidar, poses, occlusion, task, backend, normalisation = t
    from place3d_kernels.metrics import msog_batch

    return np.asarray(msog_batch(psog_spec.load(), resolve_lidar(lidar), poses, occlusion=occlusion, task=task,
                                 backend=backend, normalisation=normalisation), dtype=np.float64)


@dataclass
class DistributedObjective:
    """``objective(X) -> (P,) M-SOG`` with each batch split into chunks scored as executor tasks, or on
    the executor's scoring actors when it has them (``RayExecutor(gpu_actors=..., cpu_actors=...)``).

    Same scores as ``msog_batch(psog, lidar, space.to_poses(X), ...)`` (each rig is scored on its own), with
    the same ``normalisation`` (the M-SOG denominator travels with every task and actor call).

    Args:
        psog: ``PSOGSpec`` (workers load the cached P-SOG; call ``psog.load()`` in the driver first so
            the cache exists before the first generation).
        lidar: LiDAR name or model of the rig; space: the ``SearchSpace``.
        executor: the executor; chunk: candidates per task (default: batch split into 2 x workers' tasks,
            here simply ``ceil(P / n_chunks)`` with ``n_chunks`` given; on actors: see ``ScoringPool.score``).
        normalisation: M-SOG denominator, as in ``msog_batch`` ("paper", "evidence", "uncertain").
    """

    psog: PSOGSpec
    lidar: Any
    space: Any
    executor: Executor
    task: str = "seg"
    occlusion: str = "sog"
    backend: str | None = None
    chunk: int | None = None
    n_chunks: int = 2
    normalisation: str = "paper"
    calls: int = field(default=0, init=False)

    def __post_init__(self):
        from place3d_kernels.metrics import check_normalisation

        check_normalisation(self.normalisation)       # refused in the driver, before any task
        self.psog = self.psog.resolved()
        self.backend = backend_name(self.backend if self.backend is not None else self.psog.backend)

    def __call__(self, X) -> np.ndarray:
        poses = np.asarray(self.space.to_poses(np.asarray(X, dtype=np.float64)))
        if poses.ndim == 2:
            poses = poses[None]
        self.calls += 1
        if getattr(self.executor, "has_actors", False):
            pool = self.executor.scoring_pool(self.backend)
            return pool.score(self.psog, self.lidar, poses, self.occlusion, self.task, chunk=self.chunk,
                              normalisation=self.normalisation)
        size = self.chunk or -(-len(poses) // max(1, self.n_chunks))
        parts = [poses[i:i + size] for i in range(0, len(poses), size)]
        res = self.executor.map(_score_task, [(self.psog, self.lidar, p, self.occlusion, self.task, self.backend,
                                               self.normalisation) for p in parts])
        return np.concatenate(res) if res else np.zeros(0)
