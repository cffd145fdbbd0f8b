"""Peer benchmark: ray casting and voxel traversal on the OpenCL backend vs warp:cpu vs Open3D (Embree).

Workloads (the issue's targets):

* **ray-mesh**: a 1M-triangle box city (``place3d_kernels.scene.city.box_city``), rays of 4 LiDARs x 64
  channels x 2048 azimuth steps (524,288 rays) from the paper's ``pyramid`` rig standing in the central
  junction. Open3D's ``RaycastingScene.cast_rays`` is the peer (Embree on all cores); it is optional.
* **traversal**: the default 80 m x 80 m x 5 m ROI at 0.2 m (4.0 M voxels), the same rays clipped to the
  LiDAR range: ``coverage`` (union mask), ``traverse`` (CSR visit lists) and ``score_placements`` (a
  batched population of P candidate rigs, the optimiser's inner loop).

Timings are wall-clock of one backend call on NumPy inputs already in memory (so host<->device copies
and the host-side parts are included); each measurement is repeated, backends interleaved, and the
minimum and median are kept. Compile and BVH build happen before timing and are reported separately.

Usage::

    python bench/bench_raycast_peers.py                 # full size, writes bench/results/*.json
    python bench/bench_raycast_peers.py --quick         # small smoke run
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import place3d_kernels as p3k

HERE = Path(__file__).resolve().parent


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _load() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def _timeit(fn, repeats: int) -> dict:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return {"min_s": min(ts), "median_s": statistics.median(ts), "runs": len(ts)}


def _interleaved(fns: dict, repeats: int) -> dict:
    """Run each callable ``repeats`` times, round-robin, so background load hits all of them alike."""
    ts = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t)
    return {k: {"min_s": min(v), "median_s": statistics.median(v), "runs": len(v)} for k, v in ts.items()}


def _backends(names):
    out = {}
    for n in names:
        try:
            out[n] = p3k.get_backend(n)
        except ValueError as e:
            print(f"  skipping {n}: {e}", file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--azimuth", type=int, default=2048)
    ap.add_argument("--placement", default="pyramid")
    ap.add_argument("--candidates", type=int, default=8, help="population size P for score_placements")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--backends", default="", help="comma list (default: every opencl:* and warp:cpu)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--quick", action="store_true", help="small sizes, 2 repeats (smoke test)")
    ap.add_argument("--out", default=str(HERE / "results" / "bench_raycast_peers.json"))
    args = ap.parse_args(argv)
    if args.quick:
        args.triangles, args.channels, args.azimuth, args.repeats, args.candidates = 20_000, 16, 256, 2, 2

    avail = p3k.available_backends()
    names = [b for b in args.backends.split(",") if b] or \
        [b for b in avail if b.startswith("opencl:")] + [b for b in avail if b == "warp:cpu"]
    bks = _backends(names)
    for b in bks.values():
        b.warmup()   # Backend.warmup: compiles ahead where the backend compiles at all
    print(f"backends: {list(bks)}; load average {_load()}")

    res: dict = {
        "benchmark": "bench_raycast_peers",
        "date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "machine": {"cpu": _cpu_model(), "logical_cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": sys.version.split()[0], "load_average_start": _load()},
        "versions": {"numpy": np.__version__},
        "config": vars(args).copy(),
        "raycast": {}, "traversal": {}, "notes": [],
    }
    try:
        import pyopencl as cl

        res["versions"]["pyopencl"] = cl.VERSION_TEXT
        for name, b in bks.items():
            if name.startswith("opencl:"):
                res["versions"][name] = f"{b.device.platform.name} {b.device.platform.version} / {b.device.name}"
    except ImportError:
        pass
    try:
        import warp as wp

        res["versions"]["warp"] = wp.config.version
    except ImportError:
        pass

    # ------------------------------------------------------------------ rays
    from place3d_kernels.scene.city import box_city

    lidar = p3k.LidarModel.uniform(args.channels, fov_deg=(-30.0, 10.0), azimuth_steps=args.azimuth)
    placement = p3k.Placement.load(args.placement)
    ref = p3k.get_backend("reference")
    origins, dirs = ref.lidar_rays(lidar.elevations, lidar.azimuths, placement.poses)
    n_rays = len(origins)
    res["config"]["rays"] = n_rays

    # ------------------------------------------------------------------ ray-mesh
    t = time.perf_counter()
    mesh = box_city(args.triangles, seed=0)
    res["raycast"]["scene"] = {"triangles": int(mesh.n_faces), "vertices": int(len(mesh.vertices)),
                               "generate_s": time.perf_counter() - t}
    v = mesh.vertices - mesh.shift
    o = origins - mesh.shift
    t_max = np.full(n_rays, 1e30)   # no range limit: Open3D has none
    handles, builds = {}, {}
    for name, b in bks.items():
        t = time.perf_counter()
        handles[name] = b.upload_mesh(v, mesh.faces)
        b.synchronize()
        builds[name] = time.perf_counter() - t
        b.raycast(handles[name], o[:1000], dirs[:1000], t_max[:1000])   # compile / warm caches
    fns = {name: (lambda b=b, h=handles[name]: (b.raycast(h, o, dirs, t_max), b.synchronize()))
           for name, b in bks.items()}
    o3d_scene = None
    if not args.no_open3d:
        try:
            import open3d as o3d

            res["versions"]["open3d"] = o3d.__version__
            t = time.perf_counter()
            o3d_scene = o3d.t.geometry.RaycastingScene()
            o3d_scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                    o3d.core.Tensor(mesh.faces.astype(np.uint32)))
            rays32 = np.concatenate([o, dirs], axis=1).astype(np.float32)
            o3d_scene.cast_rays(o3d.core.Tensor(rays32[:1000]))  # Embree builds its BVH lazily: here
            builds["open3d"] = time.perf_counter() - t

            def _o3d():
                r = o3d_scene.cast_rays(o3d.core.Tensor(rays32))
                return r["t_hit"].numpy(), r["primitive_ids"].numpy()

            fns["open3d"] = _o3d
        except ImportError as e:
            res["notes"].append(f"open3d not available ({e}); pip install open3d (Python <= 3.12)")
    times = _interleaved(fns, args.repeats)
    for name, tm in times.items():
        tm["rays_per_s"] = n_rays / tm["min_s"]
        tm["build_s"] = builds.get(name)
    res["raycast"]["results"] = times
    # agreement with the first OpenCL backend (or whatever ran first)
    first = next(iter(bks), None)
    if first is not None:
        t0, f0 = bks[first].raycast(handles[first], o, dirs, t_max)
        agree = {}
        for name, b in bks.items():
            if name == first:
                continue
            t1, f1 = b.raycast(handles[name], o, dirs, t_max)
            both = (f0 >= 0) & (f1 >= 0)
            agree[name] = {"hit_mask_equal": float(np.mean((f0 >= 0) == (f1 >= 0))),
                           "same_face": float(np.mean(f0[both] == f1[both])),
                           "max_rel_dt": float(np.max(np.abs(t0[both] - t1[both]) / np.maximum(t0[both], 1e-9)))}
        if o3d_scene is not None:
            th, pid = fns["open3d"]()
            hit = np.isfinite(th)
            both = (f0 >= 0) & hit
            agree["open3d"] = {"hit_mask_equal": float(np.mean((f0 >= 0) == hit)),
                               "same_face": float(np.mean(pid[both].astype(np.int64) == f0[both])),
                               "max_rel_dt": float(np.max(np.abs(t0[both] - th[both]) / np.maximum(t0[both], 1e-9)))}
        res["raycast"]["agreement_vs_" + first] = agree
        res["raycast"]["hit_fraction"] = float(np.mean(f0 >= 0))

    # ------------------------------------------------------------------ traversal
    grid = p3k.DEFAULT_GRID
    spec = grid.spec
    lo = grid.to_local(origins)
    t_end = np.full(n_rays, lidar.max_range)
    cl_names = [n for n in bks if n.startswith("opencl:")]
    counter = bks[cl_names[0]] if cl_names else None
    steps = int(counter.count_visits(spec, lo, dirs, t_end).sum()) if counter else None
    tr: dict = {"grid_shape": list(spec.shape), "voxel_size": spec.voxel_size, "rays": n_rays,
                "t_end": lidar.max_range, "voxel_steps": steps}
    for b in bks.values():
        b.coverage(spec, lo[:1000], dirs[:1000], t_end[:1000])
    tr["coverage"] = _interleaved({n: (lambda b=b: (b.coverage(spec, lo, dirs, t_end), b.synchronize()))
                                  for n, b in bks.items()}, args.repeats)
    tr["traverse"] = _interleaved({n: (lambda b=b: (b.traverse(spec, lo, dirs, t_end), b.synchronize()))
                                  for n, b in bks.items()}, max(2, args.repeats // 2))
    # a population of P rigs jittered around the placement, scored in one batched call each
    rng = np.random.default_rng(0)
    P = args.candidates
    local_poses = placement.poses.copy()
    local_poses[:, :3] = grid.to_local(local_poses[:, :3])
    cand = local_poses[None] + rng.normal(size=(P,) + local_poses.shape) * [0.3, 0.3, 0.1, 0.02, 0.02, 0.1]
    weights = rng.integers(0, int(np.log(22) * 2**32), spec.n_voxels)
    preps = {n: b.prepare_grid(spec, weights, None) for n, b in bks.items()}
    for n, b in bks.items():
        b.score_placements(preps[n], lidar.elevations[:2], lidar.azimuths[:8], lidar.max_range, cand[:1])
    tr["score_placements"] = _interleaved(
        {n: (lambda b=b, h=preps[n]: b.score_placements(h, lidar.elevations, lidar.azimuths, lidar.max_range, cand))
         for n, b in bks.items()}, max(2, args.repeats // 2))
    tr["score_candidates"] = P
    score_steps = None
    if counter is not None:
        score_steps = 0
        for p in range(P):
            oo, dd = ref.lidar_rays(lidar.elevations, lidar.azimuths, cand[p])
            score_steps += int(counter.count_visits(spec, oo, dd, np.full(len(oo), lidar.max_range)).sum())
    tr["score_voxel_steps"] = score_steps
    for kind, n_r, st in (("coverage", n_rays, steps), ("traverse", n_rays, steps),
                          ("score_placements", n_rays * P, score_steps)):
        for name, tm in tr[kind].items():
            tm["rays_per_s"] = n_r / tm["min_s"]
            if st:
                tm["voxel_steps_per_s"] = st / tm["min_s"]
    # identical answers across backends
    outs = {n: b.score_placements(preps[n], lidar.elevations, lidar.azimuths, lidar.max_range, cand)
            for n, b in bks.items()}
    vals = list(outs.values())
    tr["score_identical_across_backends"] = bool(all(np.array_equal(x[0], vals[0][0]) and
                                                     np.array_equal(x[1], vals[0][1]) for x in vals))
    res["traversal"] = tr
    res["machine"]["load_average_end"] = _load()

    # ------------------------------------------------------------------ ratios and report
    ratios = {}
    rc = res["raycast"]["results"]
    for name in cl_names:
        if "open3d" in rc:
            ratios[f"{name} / open3d raycast"] = rc[name]["rays_per_s"] / rc["open3d"]["rays_per_s"]
        if "warp:cpu" in bks:
            for kind in ("coverage", "traverse", "score_placements"):
                ratios[f"{name} / warp:cpu {kind}"] = tr[kind]["warp:cpu"]["min_s"] / tr[kind][name]["min_s"]
            ratios[f"{name} / warp:cpu raycast"] = rc[name]["rays_per_s"] / rc["warp:cpu"]["rays_per_s"]
    res["speedups"] = ratios

    print(f"\nray-mesh: {res['raycast']['scene']['triangles']:,} triangles, {n_rays:,} rays")
    for name, tm in rc.items():
        bs = tm.get("build_s")
        print(f"  {name:14s} {tm['rays_per_s'] / 1e6:7.2f} Mrays/s  (min {tm['min_s'] * 1e3:7.1f} ms, "
              f"median {tm['median_s'] * 1e3:7.1f} ms)" + (f"  build {bs:.2f} s" if bs is not None else ""))
    print(f"traversal: grid {tuple(spec.shape)} @ {spec.voxel_size} m, {n_rays:,} rays, "
          f"{steps or 0:,} voxel steps")
    for kind in ("coverage", "traverse", "score_placements"):
        for name, tm in tr[kind].items():
            extra = f"  {tm['voxel_steps_per_s'] / 1e6:8.1f} Msteps/s" if "voxel_steps_per_s" in tm else ""
            print(f"  {kind:17s} {name:14s} {tm['rays_per_s'] / 1e6:7.2f} Mrays/s{extra}  "
                  f"(min {tm['min_s'] * 1e3:7.1f} ms, median {tm['median_s'] * 1e3:7.1f} ms)")
    for k, r in ratios.items():
        print(f"  {k}: {r:.2f}x")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2, default=float))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
