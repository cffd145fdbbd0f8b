"""Several routes and scenes for one answer: ``--routes N``, ``--route-seeds 100-107``, repeated ``--scene``.

``evaluate`` and ``optimize`` score on a P-SOG pooled over drives (every scene x every route seed,
``pooled.pool_specs``); the default is ``pooled.DEFAULT_ROUTES`` routes per scene. One drive remains an
explicit choice (``--routes 1``), which keeps the single-drive path (intervals over its subsets) and
warns that the order is not converged.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from concurrent.futures import Future

__all__ = ["add_route_arguments", "route_seeds", "drive_specs", "pooled_psog", "psog_for_routes",
           "build_missing", "built_records", "drive_parts", "drive_plan", "DRIVE_PARTS", "SINGLE_ROUTE_WARNING"]

SINGLE_ROUTE_WARNING = ("place3d: warning: one route: the order of the placements is not converged on a single "
                        "drive (docs/guide.md, 'How many routes'); pool several with --routes N")


def add_route_arguments(p) -> None:
    from place3d_kernels.pooled import DEFAULT_ROUTES

    p.set_defaults(scenes=None)
    p.add_argument("--routes", type=int, default=None,
                   help=f"routes per scene pooled into one P-SOG, seeds --seed .. --seed+N-1 (default "
                        f"{DEFAULT_ROUTES}; 1 = a single drive, with a warning that its order is not converged)")
    p.add_argument("--route-seeds", default=None, metavar="SEEDS",
                   help="the route seeds to pool instead, e.g. 100-107 or 1,2,5 (ranges inclusive)")


def route_seeds(args) -> list[int]:
    """The route seeds of the run (``--route-seeds``, else ``--routes`` from ``--seed``)."""
    from place3d_kernels.pooled import DEFAULT_ROUTES, parse_route_seeds

    routes = getattr(args, "routes", None)
    text = getattr(args, "route_seeds", None)
    if text is not None:
        seeds = parse_route_seeds(text)
        if routes is not None and routes != len(seeds):
            raise ValueError(f"--routes {routes} and --route-seeds {text} ({len(seeds)} seeds) disagree; give one")
        return seeds
    n = DEFAULT_ROUTES if routes is None else routes
    if n < 1:
        raise ValueError(f"--routes must be >= 1, got {n}")
    return [int(args.seed) + i for i in range(n)]


def drive_specs(args, spec) -> list:
    """One ``PSOGSpec`` per drive: every ``--scene`` x every route seed, each with the run's condition,
    grid and vehicle. Scenes that take no seed (mesh, semantickitti: one fixed route) give one drive;
    asking them for several routes is refused."""
    scenes = getattr(args, "scenes", None) or [spec.scene.name]
    seeds = route_seeds(args)
    explicit = getattr(args, "routes", None) is not None or getattr(args, "route_seeds", None) is not None
    out = []
    for name in scenes:
        scene = dataclasses.replace(spec.scene, name=name)
        if name != spec.scene.name:
            scene = dataclasses.replace(scene, labels=None, route=None)
        scene.validate()
        if scene.kind in ("mesh", "semantickitti"):
            if explicit and len(seeds) > 1:
                raise ValueError(f"scene {name!r} has one fixed route (its file), so --routes / --route-seeds "
                                 f"cannot pool several; use --routes 1 (or several --scene)")
            out.append(dataclasses.replace(spec, scene=scene))
            continue
        out.extend(dataclasses.replace(spec, scene=dataclasses.replace(scene, seed=s)) for s in seeds)
    return out


def pooled_psog(args, spec, backend, specs=None):
    """(PooledPSOG, strata, its P-SOG) for the run's drives, or None for a single drive (then the caller
    keeps the single-drive path and this prints the warning)."""
    from place3d_kernels.pipeline import check_entropy
    from place3d_kernels.pooled import pool_specs
    from place3d_kernels.profiling import section

    specs = drive_specs(args, spec) if specs is None else specs
    if len(specs) == 1:
        if specs[0].scene.kind in ("town", "opendrive"):
            print(SINGLE_ROUTE_WARNING, file=sys.stderr)
        return None
    if spec.scene.kind == "semantickitti" and len({s.scene.name for s in specs}) != len(specs):
        raise ValueError("a semantickitti: sequence is one recorded drive; pool several sequences with --scene")

    t = time.perf_counter()
    # the cached drives read side by side (pooled.cached_records) before the backend is waited for: reading needs
    # none, so a warm optimize reads them while its probe runs (on the H200 it waited for the probe, 0.55 s, then
    # read four drives one after the other, 0.71 s); with every record at hand nothing is built, and the pool
    # is summed while the probe may still run
    from place3d_kernels.pool_memo import kept_pool, pool_files_key
    from place3d_kernels.pooled import cached_records

    built = getattr(args, "built", None) or {}
    todo = [s for s in specs if s not in built]
    read = {}
    # a pool an earlier command kept (place3d serve: pool_memo) needs neither reads nor a backend; the files'
    # identities are taken before they are read
    key = None if built else pool_files_key(specs, not args.no_cache)
    kept = kept_pool(key) is not None
    if todo and not args.no_cache and not kept:
        with section("P-SOG cache reads (side by side)"):
            read = cached_records(todo)
    if isinstance(backend, Future) and not kept and not all(s in built or s in read for s in specs):
        backend = backend.result()      # optimize's probe thread: the library takes a resolved backend
    with section("P-SOG (pooled drives)"):
        pooled = pool_specs(specs, backend=None if isinstance(backend, Future) else backend, cache=not args.no_cache,
                            progress=not args.quiet, known=built, read=read, files_key=key)
        # the plain pool (the jackknife's point takes it without comparing arrays), kept with a kept pool
        psog = pooled.kept_psog()
    check_entropy(psog, spec.frames_per_subset)
    strata = [s.scene.name for s in specs]
    if not args.quiet:
        print(f"pooled P-SOG of {len(specs)} drives ready in {time.perf_counter() - t:.1f} s: {psog}", file=sys.stderr)
    return pooled, strata, psog


#: Parts a missing drive is built in where the host has the cores (``drive_parts``): each part builds the scene
#: and simulates and votes its share of the drive's subsets, and the parts' records are merged (exact integer
#: sums) into the drive's. On the lent H200 (16 cores) the cold default optimize's median went down by 0.16-0.42 s
#: on three leases, e.g. 4.32 [4.08-4.59] -> 3.90 [3.84-4.34] s (5 runs each; bench/results/ab-2026-11-30-s37/).
DRIVE_PARTS = 2


def _build_spec_then(task):
    """A worker's task ``(spec, then)``: the drive's record (``_drive_record``), the worker's backend started at
    once, on a thread, while the scene of ``spec``, and that of ``then`` (the drive the command sends this worker
    next, ``_after``; or None), are built in forked children (``prefetch.start_for_spec``; a worker's first task
    runs on its one thread, before its backend starts, so forking is safe there; elsewhere nothing is forked and
    the build makes the scene here). In this process the scene's Python took turns with the backend's start on
    the other thread (0.37 [0.18-0.41] s a scene there, session 47's worker probe on the H200 host), and a held-out
    drive built its scene only once it came to the worker."""
    from place3d_app.executors import start_backend
    from place3d_app.prefetch import start_for_spec

    spec, then = task
    for s in (spec, then):
        if s is not None:
            start_for_spec(s, cache=False)     # cache=False: the scene is needed, its key remembered or not
    start_backend(spec.backend)
    return _drive_record(spec)


def _drive_record(spec):
    """The drive's P-SOG built into the cache, and its record sent back, so the command pools it without
    reading the file again. The file is written on the worker's saver thread; the task waits for it unless the
    worker waits for it when it ends (``pipeline.saves_outlive_tasks``, the process executor's workers): the
    command then has the record 0.2-0.3 s sooner, and the cache is whole when the workers end."""
    from place3d_kernels.pipeline import end_task_saves
    from place3d_kernels.pooled import DriveRecord

    record = DriveRecord.from_psog(spec.build(cache=spec.cache or True, save_in_background=True), spec.scene.label)
    end_task_saves()
    return record


def _build_part(task):
    """A worker's task: ``(spec, subsets)``'s record (``PSOGSpec.build_part``), not cached (the command merges
    the parts and has ``_save_drive`` write the drive); the worker's backend starts at once, as
    ``_build_spec_then``'s."""
    from place3d_app.executors import start_backend
    from place3d_kernels.pooled import DriveRecord

    spec, subsets = task
    start_backend(spec.backend)
    return DriveRecord.from_psog(spec.build_part(subsets, cache=spec.cache or True), spec.scene.label)


def _save_drive(task):
    """A worker's task: ``(spec, record)``, the drive's merged record, written to the cache as ``build`` would."""
    from place3d_kernels.pooled import PooledPSOG

    spec, record = task
    # a pool of one record is that drive's P-SOG exactly (PooledPSOG.psog)
    spec.save(PooledPSOG(spec.grid.grid(), [record]).psog(), cache=spec.cache or True)


def drive_parts(first: int, later: int, workers: int) -> int:
    """Parts each of ``first`` missing drives, and of ``later`` ones (queued behind them), is built in by
    ``workers`` usable cores: ``DRIVE_PARTS`` where the worker processes that takes (``DRIVE_PARTS`` per drive of
    the larger group) are at most three quarters of the cores, else 1 (a quarter stays for this process and the
    workers' own threads). On the H200 host (16 cores) eight part workers built the searched drives 0.3-0.4 s
    sooner than eight whole drives, and sixteen 20-frame drives at once took as long as eight 40-frame ones."""
    return DRIVE_PARTS if first and max(first, later) * DRIVE_PARTS <= workers * 3 // 4 else 1


def drive_plan(first: int, later: int, workers: int) -> tuple[int, bool]:
    """(parts per drive, whether the ``later`` drives queue behind the ``first`` ones in the same workers) for
    ``first`` missing drives needed now and ``later`` ones needed after optimize's search, on ``workers`` usable
    cores. With later drives, where one worker a drive of the larger group takes at most three quarters of the
    cores: every drive whole, the later ones queued. They are built during the search, and whole there are half
    as many processes beside it and no parts for the command's threads to merge: the search took 0.81 s against
    0.89 s with part workers, the cold default optimize 3.22 against 3.24 s (medians of 32 runs each in five
    alternated rounds on one H200 lease, four of the rounds faster; the searched drives back as soon;
    bench/results/ab-2026-12-02-s46/, section 3). Otherwise ``drive_parts``, the later drives queued behind the
    first where that gives parts."""
    if first and later and max(first, later) <= workers * 3 // 4:
        return 1, True
    parts = drive_parts(first, later, workers)
    return parts, parts > 1


def built_records(args, specs) -> dict:
    """{spec: record} of the drives of ``specs`` that the workers built (``build_missing``): ``args.built``, with
    the drives still building (``args.building``) waited for."""
    built = dict(getattr(args, "built", None) or {})
    for s in specs:
        f = (getattr(args, "building", None) or {}).get(s)
        if s not in built and f is not None:
            built[s] = f.result()
    return built


def build_missing(args, specs, backend, later=()) -> int:
    """Build the drives of ``specs`` and ``later`` that the cache lacks in worker processes, one per usable core
    (at most one per drive, or per part of a drive); returns how many drives it builds. Each lands in the cache, and its
    ``DriveRecord`` is kept in ``args.built`` ({spec: record}), which ``pooled_psog`` and ``pool_specs(known=...)``
    take instead of reading the file.

    How (``drive_plan``): where the cores allow, ``specs``' drives first, one worker each (with ``later`` drives:
    optimize's held-out drives, needed after the search) or one worker a part (``DRIVE_PARTS`` parts,
    ``_build_part``), and ``later``'s queued behind them: the same workers take them as they finish, their
    backends made already. Whole, each later drive is paired with a first one: that drive's worker builds the
    later drive's scene in a forked child while it builds its own (``_build_spec_then``), and the later drive
    is sent once its paired drive's task is done (``_after``), when that worker is the idle one. This returns
    when ``specs``' drives are back (merged where built in parts), ``later``'s in ``args.building`` ({spec:
    Future of its record}, ``built_records``), taken by a thread of this process as they come back; workers
    write the drives to the cache (a part-built one merged, ``_save_drive``), and leave once every task is done. Otherwise every drive is built whole at once and this returns when all
    are back.

    A drive counts as cached when its cache file exists (``PSOGSpec.cache_file``: found without building
    its scene; one whose scene key was never remembered counts as missing). Nothing is started for fewer
    than two missing drives, one usable core, ``--no-cache``, or an executor other than the local one
    (Ray runs place their own work). ``backend`` may be a Future (optimize's probe), which the workers do not
    wait for (``_workers_backend``)."""
    from place3d_app.executors import ProcessExecutor, command_start_method, default_workers
    from place3d_kernels.sog import cache_dir

    if getattr(args, "no_cache", False) or getattr(args, "ray_address", None) \
            or getattr(args, "executor", "local") not in ("local", "auto", None):
        return 0

    def lacking(group):
        out = []
        for s in group:
            f = s.cache_file()
            if s.scene.kind in ("town", "opendrive") and (f is None or not f.exists()):
                out.append(s)
        return out

    first, rest = lacking(specs), lacking(later)
    cores = default_workers()
    parts, queued = drive_plan(len(first), len(rest), cores)
    if not queued:
        first, rest = first + rest, []         # every drive whole, one worker each, as many as the cores
    n = min(cores, max(len(first), len(rest)) * parts)      # the later drives' parts queue behind
    if len(first) + len(rest) < 2 or n < 2:
        return 0
    t = time.perf_counter()
    # the workers' server (a forkserver on Linux, command_start_method) imports NumPy, Warp and the drive modules
    # (SciPy's parts too for OpenDRIVE maps) while this process makes its backend on the probe's thread; the
    # workers are forked from it as soon as it has them, and ended as soon as every drive has returned (a
    # worker's last file is written before it ends)
    asked = backend if isinstance(backend, str) else getattr(backend, "name", None) or getattr(args, "backend", None)
    ex = ProcessExecutor(n, start_method=command_start_method(), preload=str(asked or "auto"),
                         opendrive=any(s.scene.kind == "opendrive" for s in first + rest))
    from place3d_kernels.profiling import section

    done, later_tasks = False, []
    building = {s: Future() for s in rest}
    try:
        ex.start_server()
        name = _workers_backend(args, backend)
        # each task starts its worker's backend (none at the worker's start)
        with section("drives: worker processes (start, build, send)"):
            # the cache folder resolved here: a forkserver's workers have the server's environment, which may
            # be older than this command's ($PLACE3D_CACHE set since, or a served client's)
            folder = str(cache_dir())
            mine = [dataclasses.replace(s, backend=name, cache=s.cache or folder) for s in first]
            theirs = [dataclasses.replace(s, backend=name, cache=s.cache or folder) for s in rest]
            # whole drives: the i-th held-out drive goes to the worker of the i-th searched one, which builds its
            # scene meanwhile
            paired = len(mine) if parts == 1 else 0
            first_tasks = [_submit_drive(ex, s, parts, then=theirs[i] if i < len(theirs) and i < paired else None)
                           for i, s in enumerate(mine)]
            # the drives needed later (optimize's held-out drives) in parts too, queued behind the searched ones:
            # the same workers take them as they finish, their backends made already. Built beside the parts in
            # four more workers, each making a CUDA context while the parts' were being made, they had kept the
            # parts' contexts and GPU work waiting: a cold default optimize ended at 3.67 [3.44-3.80] s, 3.40
            # [3.34-3.60] s so (H200, 6 runs each; the held-out drives back no later; bench/results/ab-2026-12-01-s41/)
            later_tasks = [(s, _submit_drive(ex, d, parts, after=first_tasks[i][1][0] if i < paired else None))
                           for i, (s, d) in enumerate(zip(rest, theirs))]
            records = [_finish_drive(ex, spec, tasks) for spec, tasks in first_tasks]
        done = True
    finally:
        if done and later_tasks:
            # the later drives are merged, and their files' writes sent to the workers, as they come back; then
            # the pool is let go (its workers leave once every file is written)
            threading.Thread(target=_finish_later, args=(ex, later_tasks, building), name="place3d-later-drives").start()
        else:
            # after a failure the tasks not started are dropped
            ex.shutdown(wait=False, cancel=not done)
    args.built = {**(getattr(args, "built", None) or {}), **dict(zip(first, records))}
    args.building = {**(getattr(args, "building", None) or {}), **building}
    if not getattr(args, "quiet", False):
        how = f" ({parts} parts each)" if parts > 1 else ""
        also = f"; {len(rest)} held-out drives still building" if rest else ""
        print(f"built {len(first)} drives{how} in {n} worker processes in {time.perf_counter() - t:.1f} s{also}",
              file=sys.stderr)
    return len(first) + len(rest)


def _finish_later(ex, later_tasks, building) -> None:
    """Merge each later drive's parts as they come back into its Future (``building``), sending the merged
    drive's write to a worker; then let the pool go."""
    try:
        for (s, (spec, tasks)) in later_tasks:
            try:
                building[s].set_result(_finish_drive(ex, spec, tasks))
            except BaseException as e:  # noqa: BLE001 - the held-out check reports it (built_records)
                building[s].set_exception(e)
    finally:
        ex.shutdown(wait=False, cancel=False)


def _workers_backend(args, backend) -> str:
    """The backend name the drive workers start: ``backend``'s name, or, while ``backend`` is a probe still
    running (optimize's ``Future``), the name the command was given (``--backend``, else
    ``registry.default_name``: ``$PLACE3D_BACKEND``, else ``auto``), which each worker resolves itself: on this
    machine it resolves as the probe does, and a P-SOG is the same bit for bit on every backend
    (tests/test_sog.py, tests/test_pipeline.py). So the workers are forked as soon as their server has its
    imports, not once this process has started its own backend as well (Warp's import and a CUDA context:
    0.44-0.61 s of a cold default optimize on the H200 host). The drives' step of a cold default optimize then
    ended at 1.76 [1.59-1.91] s of its profile instead of 1.93 [1.77-2.09] s (5 runs each, H200;
    bench/results/ab-2026-12-01-s40/). A name no worker can resolve fails in the workers with the message the
    probe would give."""
    from place3d_kernels.backends.registry import default_name
    from place3d_kernels.spec import backend_name

    if isinstance(backend, Future):
        if not backend.done():
            return str(getattr(args, "backend", None) or default_name()).strip()
        backend = backend.result()
    return backend_name(backend)


def _submit_drive(ex, spec, parts: int, then=None, after=None):
    """``(spec, futures)``: the worker tasks that build ``spec`` (its backend and cache folder set), the whole
    drive (``_build_spec_then``, its worker building ``then``'s scene too) or ``parts`` parts of about equal
    subsets (``_build_part``). A whole drive with ``after`` (a task's Future) is sent once that task is done
    (``_after``)."""
    T = spec.subsets()
    if parts == 1 or T < parts:
        if after is not None:
            return spec, [_after(ex, after, _build_spec_then, (spec, None))]
        return spec, [_submit(ex, _build_spec_then, (spec, then))]
    cut = [round(T * j / parts) for j in range(parts + 1)]
    return spec, [_submit(ex, _build_part, (spec, range(a, b))) for a, b in zip(cut, cut[1:])]


def _after(ex, first, fn, arg) -> Future:
    """A Future of ``fn(arg)`` on a worker of ``ex``, sent once the Future ``first`` is done: that task's worker,
    idle then, takes it unless another worker is idle too (each takes the next task it reads). The worker that
    built a drive's scene ahead (``_build_spec_then``) so builds the drive; another would build the scene again,
    with the same result."""
    out = Future()

    def copy(done):
        if done.cancelled():
            out.cancel()
        elif done.exception() is not None:
            out.set_exception(done.exception())
        else:
            out.set_result(done.result())

    def send(_):
        try:
            task = _submit(ex, fn, arg)
        except BaseException as e:  # noqa: BLE001 - the pool was shut down (a failure): the drive reports it
            out.set_exception(e)
            return
        task.add_done_callback(copy)

    first.add_done_callback(send)
    return out


def _submit(ex, fn, arg):
    """``ex.submit(fn, arg)``; under ``place3d --profile`` the task records its sections in its process
    (``profiling.task``: "drive worker task" and its steps), which ``_finish_drive`` adds to the command's
    table."""
    from place3d_kernels.profiling import task

    return ex.submit(task("drive worker task", fn), arg)


def _finish_drive(ex, spec, tasks):
    """The drive's record from its tasks (waited for); a drive built in parts is merged, and a worker task
    writes it to the cache (a drive built whole was written by its task)."""
    from place3d_kernels.pooled import DriveRecord

    from place3d_kernels.profiling import untraced

    record = DriveRecord.merge([untraced(f.result()) for f in tasks])
    if len(tasks) > 1:
        ex.submit(_save_drive, (spec, record)).add_done_callback(_report_failed_save)
    return record


def _report_failed_save(f) -> None:
    # a failed write leaves the drive out of the cache: the next command builds it again
    if not f.cancelled() and f.exception() is not None:
        print(f"place3d: warning: a drive's P-SOG cache file was not written: {f.exception()}", file=sys.stderr)


def psog_for_routes(spec, args, backend):
    """``optimize``'s ``psog_for``: (None, P-SOG) of the run's drives, pooled when there are several
    (``args.pool`` then holds ``(PooledPSOG, strata, P-SOG)`` for the intervals over routes), else the
    single drive's P-SOG as before."""
    from place3d_app.commands.common import psog_for_spec

    drives = getattr(args, "drives", None) or drive_specs(args, spec)
    # the held-out drives (optimize's check) are built beside the searched ones, in parallel
    held_out = [d for _, _, ds in (getattr(args, "holdout", None) or ()) for d in ds]
    build_missing(args, list(drives), backend, later=held_out)
    pool = pooled_psog(args, spec, backend, drives)
    args.pool = pool
    if pool is None:
        return psog_for_spec(spec, args, backend, with_scene=False)
    return None, pool[2]
