#!/usr/bin/env python3
"""Where the time of ``reproduce``'s pool goes, per worker: the drives' tasks as ``build_pooled`` makes them
(``scene_groups``: two routes of one town a task), on the commands' worker processes (a forkserver, the backend
started in each worker on a thread), each task timed from inside its worker: when it started and ended (from the
start of the map) and its sections (``profiling.section``: the scene build with the P-SOG cache look-up,
``P-SOG build: simulate`` with its parts, ``aggregate``, the save thread). Time inside ``simulate`` that none of
its parts accounts for is mostly the wait for the worker's backend (sixteen workers starting CUDA on one GPU at
once, bench/README.md).

    python3 bench/pool_trace.py warp:cuda:0 --workers 16 --routes 8 --out trace.json

Prints a line per task and writes every section to ``--out`` (JSON). A fresh temporary P-SOG cache: every drive
is built (``--cache DIR``: that folder, so a second run reads the drives the first one built).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time


def _task(t):
    from place3d_kernels import pooled
    from place3d_kernels.profiling import profile, section

    if not getattr(pooled.Drive, "_traced", False):
        # the scene build as a section of its own: a task asks the P-SOG cache first (``_cached_record``), which
        # builds the scene of a drive whose key is not remembered (every drive of a fresh cache); a scene is
        # built by ``Drive.build`` only where the cache was not asked
        build, cached = pooled.Drive.build, pooled._cached_record

        def traced(self):
            with section("scene"):
                return build(self)

        def traced_cached(drive, settings):
            with section("scene"):
                return cached(drive, settings)

        pooled.Drive.build = traced
        pooled._cached_record = traced_cached
        pooled.Drive._traced = True
        _trace_backend()
    t0 = time.time()
    with profile(print_table=False) as p:
        out = pooled._records_task(t)
    return out, {"pid": os.getpid(), "start": t0, "end": time.time(), "labels": [d.label for d in t[0]],
                 "sections": {"/".join(k): round(v[0], 3) for k, v in p.totals.items()}}


def _trace_backend() -> None:
    # the simulation's wait for the worker's backend (started on a thread, executors._start_worker) and, on
    # OpenCL, each program built on first use, as sections of their own
    import importlib

    from place3d_kernels.profiling import section

    for name in ("place3d_kernels.simulate", "place3d_kernels.sog"):    # (the package's `simulate` is a function)
        module = importlib.import_module(name)
        get = module.get_backend

        def traced_get(*a, _get=get, **k):
            with section("backend wait"):
                return _get(*a, **k)

        module.get_backend = traced_get
    try:
        from place3d_kernels.backends.opencl import _runtime as rt
    except ImportError:
        return
    build = rt.build_program

    def traced_build(*a, **k):
        with section("OpenCL programs"):
            return build(*a, **k)

    rt.build_program = traced_build


def main(argv=None) -> int:
    from place3d_app.commands.reproduce import DEFAULT_TOWNS, resolve_town
    from place3d_app.executors import ProcessExecutor, command_start_method
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.pooled import Drive, PoolSettings, scene_groups

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("backend")
    ap.add_argument("--workers", type=int, default=16)
    ap.add_argument("--routes", type=int, default=8)
    ap.add_argument("--towns", default=",".join(DEFAULT_TOWNS))
    ap.add_argument("--out", default=None)
    ap.add_argument("--cache", default=None,
                    help="P-SOG cache folder (default: a fresh temporary one, so every drive is built); a second "
                         "run with the same folder reads every drive from it")
    a = ap.parse_args(argv)
    t_start = time.time()
    ex = ProcessExecutor(a.workers, backend=a.backend, start_method=command_start_method(), prestart=True)
    name = get_backend(a.backend).name
    drives = [Drive(resolve_town(t), seed=r) for r in range(a.routes) for t in a.towns.split(",")]
    cache = a.cache or tempfile.mkdtemp(prefix="pool-trace-")
    settings = PoolSettings(None, "collection_64ch", None, name, cache, None)
    groups = scene_groups(drives, a.workers)
    t1 = time.time()
    got = ex.map(_task, [([drives[i] for i in g], settings) for g in groups])
    t2 = time.time()
    ex.shutdown(wait=False)
    print(f"executor made {t1 - t_start:.2f} s before the map; the map {t2 - t1:.2f} s")
    tasks = []
    for _, info in got:
        top = {k: v for k, v in info["sections"].items() if "/" not in k}
        parts = sum(v for k, v in info["sections"].items() if k.startswith("P-SOG build: simulate/") and k.count("/") == 1)
        info["simulate_unaccounted_s"] = round(top.get("P-SOG build: simulate", 0.0) - parts, 3)
        for key, label in (("backend_wait_s", "backend wait"), ("opencl_programs_s", "OpenCL programs")):
            info[key] = round(sum(v for k, v in info["sections"].items() if k.split("/")[-1] == label), 3)
        tasks.append(info)
        print(f"{' '.join(info['labels']):30s} start {info['start'] - t1:5.2f} end {info['end'] - t1:5.2f} s | "
              + " ".join(f"{k.replace('P-SOG build: ', '')} {v:.2f}" for k, v in top.items())
              + f" | simulate outside its parts {info['simulate_unaccounted_s']:.2f} | backend wait "
              f"{info['backend_wait_s']:.2f}, OpenCL programs {info['opencl_programs_s']:.2f}")
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"backend": name, "workers": a.workers, "map_s": t2 - t1, "before_map_s": t1 - t_start,
                       "tasks": [{**i, "start": i["start"] - t1, "end": i["end"] - t1} for i in tasks]}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
