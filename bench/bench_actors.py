"""Population scoring on Ray actors (issue 17): rigs/s and per-generation latency, in-process against
actor pools, with every pool's scores checked identical to the in-process ones.

    python3 bench/bench_actors.py                  # dev CPU: in-process, then 1 and 2 CPU actors
    python3 bench/bench_actors.py --gpus 2         # a 2-GPU host: also 2 GPU actors (only what runs is reported)

Workload: populations of 22 and 256 rigs drawn uniformly (seed 0) from the 4-LiDAR search box of
``place3d optimize`` (x, y, z, roll per LiDAR), the paper's 16-channel LiDAR (place3d_16ch), M-SOG seg
with "sog" occlusion on the default town P-SOG (40 frames, 0.2 m grid; built once into the cache).
Configurations:
  (a) ``msog_batch`` in-process on one backend (a GPU one when a GPU is visible);
  (b) a pool of G GPU actors (G = 1 .. --gpus, those the host has);
  (c) G GPU actors + k CPU actors;
  (d) k CPU actors only (k in --cpu-actors);
  (e) today's Ray task path (``DistributedObjective`` on ``RayExecutor`` tasks: k CPU tasks, or g one-GPU
      tasks on a GPU host, per generation), for contrast.
Each configuration: pool start and warm-up (actors load the P-SOG, compile kernels) timed apart, one
untimed generation per population, then --repeats timed generations: median, min, max seconds and
rigs/s; each timed generation of a pool is followed by one in-process generation, and the speed-up is
the median of the ratios of these pairs (the dev VM is shared with other jobs; pairs see the same load).
Every generation's scores are compared with (a) bit for bit; the JSON records it and the script exits 1
after writing it if any differs. Requested configurations that cannot run here (more GPUs than
visible) are listed under "not_run" with the reason.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# the Ray workers inherit the environment: they import this checkout, as the driver does
sys.path.insert(0, str(ROOT))
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])


def _machine() -> dict:
    """CPU model, cores, GPUs (nvidia-smi) and package versions."""
    info = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "gpus": [],
            "python": platform.python_version(), "host": platform.node()}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    if shutil.which("nvidia-smi"):
        r = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
                           capture_output=True, text=True)
        info["gpus"] = [ln.strip() for ln in r.stdout.splitlines() if ln.strip()] if r.returncode == 0 else []
    for mod in ("ray", "warp", "pyopencl", "numpy"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:        # not installed, or no version attribute: record that
            info[mod] = None
    return info


def _summary(times: list[float], P: int) -> dict:
    med = statistics.median(times)
    return {"seconds_median": med, "seconds_min": min(times), "seconds_max": max(times),
            "rigs_per_s_median": P / med, "repeats": len(times), "seconds": times}


def _run(score, sizes, want: dict, repeats: int, paired=None) -> dict:
    """Time ``score(P)`` (one generation of P rigs) for each P: one untimed generation, then ``repeats``
    timed ones. With ``paired`` (the in-process scorer), each timed generation is followed by one of
    ``paired``, so that the ratio of each pair is taken under the same load (the dev VM is shared)."""
    out = {}
    for P in sizes:
        t = time.perf_counter()
        first = score(P)
        first_s = time.perf_counter() - t
        times, ref, same = [], [], [np.array_equal(first, want[P])]
        for _ in range(repeats):
            t = time.perf_counter()
            s = score(P)
            times.append(time.perf_counter() - t)
            same.append(np.array_equal(s, want[P]))
            if paired is not None:
                t = time.perf_counter()
                paired(P)
                ref.append(time.perf_counter() - t)
        r = out[str(P)] = {**_summary(times, P), "first_generation_s": first_s,
                           "identical_to_in_process": all(same)}
        line = (f"    P={P:4d}: {r['rigs_per_s_median']:9.1f} rigs/s, {r['seconds_median'] * 1e3:8.1f} ms per "
                f"generation [{r['seconds_min'] * 1e3:.1f}-{r['seconds_max'] * 1e3:.1f}], identical {all(same)}")
        if paired is not None:
            r["in_process_paired"] = _summary(ref, P)
            r["speedup_vs_in_process_median"] = statistics.median(a / b for a, b in zip(ref, times))
            line += (f"; paired in-process {r['in_process_paired']['seconds_median'] * 1e3:.1f} ms, speed-up "
                     f"x{r['speedup_vs_in_process_median']:.2f}")
        print(line, file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pops", type=int, nargs="+", default=[22, 256], help="population sizes (default 22 256)")
    ap.add_argument("--repeats", type=int, default=3, help="timed generations per configuration (default 3)")
    ap.add_argument("--gpus", type=int, default=None,
                    help="GPU actors to try, 1..N (default: the GPUs visible); more than visible are listed "
                         "as not run")
    ap.add_argument("--cpu-actors", type=int, nargs="*", default=[1, 2], help="CPU actor counts (default 1 2)")
    ap.add_argument("--backend", default=None, help="in-process backend (default: warp:cuda:0 if a GPU is "
                                                    "visible, else the fastest available)")
    ap.add_argument("--cpu-backend", default="cpu", help="CPU actors' backend (default: the first of "
                                                         "opencl:pocl, warp:cpu, reference)")
    ap.add_argument("--chunk", type=int, default=None, help="rigs per chunk (default: ScoringPool's rule)")
    ap.add_argument("--no-tasks", action="store_true", help="skip (e), the Ray task path")
    ap.add_argument("--machine", default=None, help="label in the file name (default: GPU or cpu + cores)")
    ap.add_argument("--output", default=None)
    args = ap.parse_args(argv)

    try:
        import ray
    except ImportError:
        ray = None
    from results_io import write_result

    from place3d_app.actors import CPU_BACKENDS, ScoringPool, is_gpu_backend
    from place3d_kernels.backends.registry import available_backends, get_backend
    from place3d_app.executors import DistributedObjective, PSOGSpec, SceneSpec, get_executor
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.optimize import SearchSpace

    info = _machine()
    have = available_backends()
    visible = sum(b.startswith("warp:cuda") for b in have) or len(info["gpus"])
    backend = get_backend(args.backend or ("warp:cuda:0" if "warp:cuda:0" in have else "auto"))
    want_gpus = visible if args.gpus is None else args.gpus
    label = args.machine or (f"{info['gpus'][0].split(',')[0].replace('NVIDIA ', '').split()[0]}x{visible}"
                             if visible else f"cpu-{info['cores']}core")
    date = time.strftime("%Y-%m-%d")
    print(f"machine {label}: {info['cpu']}, {info['cores']} cores, GPUs {info['gpus'] or 'none'}; "
          f"in-process backend {backend.name}", file=sys.stderr)

    lidar = "place3d_16ch"
    rig = LidarModel.load(lidar)
    spec = PSOGSpec(SceneSpec("town"), backend.name, 0.2).resolved()     # 0.2 m, as its published figures
    t = time.perf_counter()
    psog = spec.load()
    psog_s = time.perf_counter() - t
    space = SearchSpace(n_lidars=4)
    rng = np.random.default_rng(0)
    xs = {P: rng.uniform(space.lower, space.upper, size=(P, space.dim)) for P in args.pops}
    pops = {P: np.asarray(space.to_poses(x)) for P, x in xs.items()}
    res = {"date": date, "machine": {"label": label, **info}, "in_process_backend": backend.name,
           "cpu_actor_backend": args.cpu_backend, "lidar": lidar, "lidars_per_rig": 4,
           "scene": "town seed 0, 40 frames, the 0.2 m grid", "population": "uniform in the 4-LiDAR search box, "
           "seed 0", "occlusion": "sog", "task": "seg", "chunk": args.chunk or "ScoringPool default",
           "psog_load_s": psog_s, "configs": {}, "not_run": {}}

    # (a) in-process: the reference scores
    def local(P):
        return msog_batch(psog, rig, pops[P], occlusion="sog", task="seg", backend=backend)

    want = {P: local(P) for P in pops}                     # also the warm-up
    print(f"(a) in-process {backend.name}", file=sys.stderr)
    res["configs"]["in-process"] = {"backend": backend.name, "populations": _run(local, pops, want, args.repeats)}

    cpu_ks = [k for k in args.cpu_actors if k > 0]
    plan = [(g, 0) for g in range(1, want_gpus + 1)]
    plan += [(g, k) for g in range(1, want_gpus + 1) for k in cpu_ks] + [(0, k) for k in cpu_ks]
    need_cpus = max([g + k for g, k in plan] + [max(cpu_ks, default=1)])
    if ray is None:
        res["not_run"]["all pools and tasks"] = "Ray is not installed: pip install 'place3d-kernels[dist]'"
        plan, args.no_tasks = [], True
        print(res["not_run"]["all pools and tasks"], file=sys.stderr)
    else:
        ray.init(num_cpus=max(os.cpu_count() or 1, need_cpus), num_gpus=visible, include_dashboard=False,
                 log_to_driver=False)
    try:
        for g, k in plan:
            name = f"actors-{g}gpu-{k}cpu"
            if g > visible:
                gb = backend.name if is_gpu_backend(backend.name) else "warp:cuda:0"
                res["not_run"][name] = (
                    f"{g} GPU actor(s) asked for, {visible} GPU(s) visible on this host. It would start {g} actors of "
                    f"num_gpus=1 (Ray gives each its own CUDA_VISIBLE_DEVICES, so each runs {gb} on its own GPU)"
                    + (f" beside {k} CPU actor(s)" if k else "")
                    + ", load the P-SOG once per actor and take chunks of each generation as they fall idle")
                print(f"{name}: not run ({res['not_run'][name]})", file=sys.stderr)
                continue
            print(f"{name}", file=sys.stderr)
            t = time.perf_counter()
            pool = ScoringPool(ray, g, k, backend=backend.name, cpu_backends=args.cpu_backend)
            try:
                pool.warm(spec, lidar, pops[args.pops[0]])
                start_s = time.perf_counter() - t
                before = [dict(s) for s in pool.stats]
                runs = _run(lambda P: pool.score(spec, lidar, pops[P], chunk=args.chunk), pops, want, args.repeats,
                            local)
                share = [{"kind": d["kind"], "backend": d["backend"], "cuda_visible_devices": d["cuda_visible_devices"],
                          "rigs": s["rigs"] - b["rigs"], "chunks": s["chunks"] - b["chunks"],
                          "busy_s": s["seconds"] - b["seconds"]} for d, s, b in zip(pool.info(), pool.stats, before)]
            finally:
                pool.shutdown()
            res["configs"][name] = {"gpu_actors": g, "cpu_actors": k, "start_and_warm_s": start_s, "actors": share,
                                    "populations": runs}
        if not args.no_tasks:
            # today's path for contrast: k CPU tasks per generation, and g one-GPU tasks on a GPU host
            cpu_name = (args.cpu_backend if args.cpu_backend != "cpu"
                        else next(b for b in CPU_BACKENDS if b in have))
            gpu_name = backend.name if is_gpu_backend(backend.name) else "warp:cuda:0"
            for name, k, gpus, bname in ([(f"ray-tasks-{k}cpu", k, 0, cpu_name) for k in cpu_ks]
                                         + [(f"ray-tasks-{g}gpu", g, 1, gpu_name)
                                            for g in range(1, min(want_gpus, visible) + 1)]):
                print(f"{name} (today's task path, {bname})", file=sys.stderr)
                ex = get_executor("ray", num_gpus_per_task=gpus)
                obj = DistributedObjective(spec, lidar, space, ex, backend=bname, n_chunks=k, chunk=args.chunk)
                obj(xs[args.pops[0]][:k])                    # warm-up: each worker loads the P-SOG once
                runs = _run(lambda P: obj(xs[P]), pops, want, args.repeats, local)
                res["configs"][name] = {"tasks_per_generation": k, "gpus_per_task": gpus, "backend": bname,
                                        "populations": runs}
    finally:
        if ray is not None:
            ray.shutdown()

    ok = all(r["identical_to_in_process"] for c in res["configs"].values() for r in c["populations"].values())
    res["all_identical_to_in_process"] = ok
    out = write_result("actors", res, label, path=args.output)
    print(f"wrote {out}; every configuration's scores identical to in-process: {ok}", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
