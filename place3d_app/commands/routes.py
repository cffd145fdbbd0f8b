"""Several routes and scenes for one answer: ``--routes N``, ``--route-seeds 100-107``, repeated ``--scene``.

``evaluate`` and ``optimize`` score on a P-SOG pooled over drives (every scene x every route seed,
``pooled.pool_specs``); the default is ``pooled.DEFAULT_ROUTES`` routes per scene. One drive remains an
explicit choice (``--routes 1``), which keeps the single-drive path (intervals over its subsets) and
warns that the order is not converged.
"""

from __future__ import annotations

import dataclasses
import sys
import time

__all__ = ["add_route_arguments", "route_seeds", "drive_specs", "pooled_psog", "psog_for_routes",
           "build_missing", "SINGLE_ROUTE_WARNING"]

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

    from concurrent.futures import Future

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


def _build_spec(spec):
    """A worker's task: the drive's P-SOG built into the cache, and its record sent back, so the command pools
    it without reading the file again. The file is written on the worker's saver thread; the task waits for it
    unless the worker waits for it when it ends (``pipeline.saves_outlive_tasks``, the process executor's
    workers): the command then has the record 0.2-0.3 s sooner, and the cache is whole when the workers end."""
    from place3d_kernels.pipeline import end_task_saves
    from place3d_kernels.pooled import DriveRecord

    record = DriveRecord.from_psog(spec.build(cache=spec.cache or True, save_in_background=True), spec.scene.label)
    end_task_saves()
    return record


def build_missing(args, specs, backend) -> int:
    """Build the drives of ``specs`` that the cache lacks in worker processes, one per usable core (at most
    one per drive); returns how many were built. Each lands in the cache, and its ``DriveRecord`` is kept in
    ``args.built`` ({spec: record}), which ``pooled_psog`` and ``pool_specs(known=...)`` take instead of
    reading the file.

    A drive counts as cached when its cache file exists (``PSOGSpec.cache_file``: found without building
    its scene; one whose scene key was never remembered counts as missing). Nothing is started for fewer
    than two missing drives, one usable core, ``--no-cache``, or an executor other than the local one
    (Ray runs place their own work). ``backend`` may be a Future (optimize's probe), waited for only here."""
    from concurrent.futures import Future

    from place3d_app.executors import ProcessExecutor, command_start_method, default_workers
    from place3d_kernels.sog import cache_dir
    from place3d_kernels.spec import backend_name

    if getattr(args, "no_cache", False) or getattr(args, "ray_address", None) \
            or getattr(args, "executor", "local") not in ("local", "auto", None):
        return 0
    missing = []
    for s in specs:
        f = s.cache_file()
        if s.scene.kind in ("town", "opendrive") and (f is None or not f.exists()):
            missing.append(s)
    n = min(default_workers(), len(missing))
    if len(missing) < 2 or n < 2:
        return 0
    t = time.perf_counter()
    # the workers' server (a forkserver on Linux, command_start_method) imports NumPy, Warp and the drive modules
    # (SciPy's parts too for OpenDRIVE maps) while this process waits for its backend probe; the workers are
    # forked from it once the backend's name is known, and ended as soon as every drive has returned (a worker's
    # last file is written before it ends)
    asked = backend if isinstance(backend, str) else getattr(backend, "name", None) or getattr(args, "backend", None)
    ex = ProcessExecutor(n, start_method=command_start_method(), preload=str(asked or "auto"),
                         opendrive=any(s.scene.kind == "opendrive" for s in missing))
    from place3d_kernels.profiling import section

    try:
        ex.start_server()
        if isinstance(backend, Future):
            backend = backend.result()
        name = backend_name(backend)
        ex.backend = name
        with section("drives: worker processes (start, build, send)"):
            # the cache folder resolved here: a forkserver's workers have the server's environment, which may
            # be older than this command's ($PLACE3D_CACHE set since, or a served client's)
            folder = str(cache_dir())
            records = ex.map(_build_spec, [dataclasses.replace(s, backend=name, cache=s.cache or folder)
                                           for s in missing])
    finally:
        ex.shutdown(wait=False)
    args.built = {**(getattr(args, "built", None) or {}), **dict(zip(missing, records))}
    if not getattr(args, "quiet", False):
        print(f"built {len(missing)} drives in {n} worker processes in {time.perf_counter() - t:.1f} s",
              file=sys.stderr)
    return len(missing)


def psog_for_routes(spec, args, backend):
    """``optimize``'s ``psog_for``: (None, P-SOG) of the run's drives, pooled when there are several
    (``args.pool`` then holds ``(PooledPSOG, strata, P-SOG)`` for the intervals over routes), else the
    single drive's P-SOG as before."""
    from place3d_app.commands.common import psog_for_spec

    drives = getattr(args, "drives", None) or drive_specs(args, spec)
    # the held-out drives (optimize's check) are built beside the searched ones, in parallel
    held_out = [d for _, _, ds in (getattr(args, "holdout", None) or ()) for d in ds]
    build_missing(args, list(drives) + held_out, backend)
    pool = pooled_psog(args, spec, backend, drives)
    args.pool = pool
    if pool is None:
        return psog_for_spec(spec, args, backend, with_scene=False)
    return None, pool[2]
