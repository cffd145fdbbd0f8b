"""Kernel microbenchmarks per backend (used by ``place3d bench`` and ``bench/run_bench.py``).

Workloads are fixed and named: the paper rig (4 LiDARs x 16 channels x 250 azimuth steps, placement
"pyramid") on the default box at 0.2 m (``BENCH_VOXEL``) and the default town's P-SOG; ray-mesh on the
town's static mesh with one sweep of the 64 x 1024 collection LiDAR, and (unless ``quick``) on a 1M-triangle box city
with the dense rig (4 x 64 x 2048). Every timing is the median of repeated runs after a warm-up
(kernel compilation and uploads excluded; they are reported separately where they matter).

Kernel-only figures (``raycast_kernel_mrays_s``, ``raycast_town_kernel_mrays_s``, ``traverse_kernel_gsteps_s``)
are measured where a backend has resident kernels (``Backend.resident_kernels``: ``resident_raycast`` /
``resident_traverse``, Warp and OpenCL): the rays are uploaded once, and the timed call only launches the
kernel (ray-mesh, or the traversal count pass) and waits for it, so the gap to the API figures is host-side
work and data movement.
"""

from __future__ import annotations

import platform
import statistics
import time
from datetime import date

import numpy as np

__all__ = ["run_kernel_bench", "machine_info", "format_table", "METRICS", "BENCH_VOXEL"]

#: Voxel edge (m) of the benchmark grid, the default box: 0.2 m, the default when the published figures
#: (docs/performance.md) were taken, kept fixed so that later runs compare with them although the package
#: default is now 0.1 m.
BENCH_VOXEL = 0.2

#: (result key, row label with its unit) of every figure ``run_kernel_bench`` reports, in table order
METRICS: list[tuple[str, str]] = [
    ("placement_eval_ms", "M-SOG, paper rig [ms]"),
    ("population16_eval_ms", "M-SOG, population of 16 rigs [ms]"),
    ("lidar_rays_ms", "rig rays, 16 000 [ms]"),
    ("traverse_gsteps_s", "voxel traversal, API [G steps/s]"),
    ("traverse_kernel_gsteps_s", "voxel traversal, kernel [G steps/s]"),
    ("psog_build_s", "P-SOG from 8 frames [s]"),
    ("town_bvh_build_s", "BVH build, town [s]"),
    ("raycast_town_mrays_s", "ray-mesh, town, API [M rays/s]"),
    ("raycast_town_kernel_mrays_s", "ray-mesh, town, kernel [M rays/s]"),
    ("city_bvh_build_s", "BVH build, 1M-tri city [s]"),
    ("raycast_mrays_s", "ray-mesh, city, API [M rays/s]"),
    ("raycast_kernel_mrays_s", "ray-mesh, city, kernel [M rays/s]"),
]


def machine_info() -> dict:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"machine": platform.node(), "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "date": date.today().isoformat()}


def _time(fn, sync, repeat=5, min_time=0.0):
    fn()
    sync()
    times = []
    t_all = time.perf_counter()
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
        if min_time and time.perf_counter() - t_all > min_time:
            break
    return statistics.median(times)


def _ray_mesh(r: dict, label: str, b, mesh, o, d, t_max: float, repeat: int) -> None:
    """BVH build time, API ray-mesh rate and (where the backend offers it) the kernel-only rate."""
    import place3d_kernels as p3k

    t0 = time.perf_counter()
    mesh.handle(b)
    b.synchronize()
    r[f"{label}_bvh_build_s"] = time.perf_counter() - t0
    api = "raycast_town_mrays_s" if label == "town" else "raycast_mrays_s"   # names kept from earlier results
    r[api] = len(o) / _time(lambda: p3k.raycast(mesh, o, d, t_max, backend=b), b.synchronize, repeat=repeat) / 1e6
    if b.resident_kernels:
        run = b.resident_raycast(mesh.handle(b), o - mesh.shift, d / np.linalg.norm(d, axis=1)[:, None], t_max)
        r[api.replace("_mrays_s", "_kernel_mrays_s")] = len(o) / _time(run, b.synchronize, repeat=repeat + 2) / 1e6


def run_kernel_bench(backends=None, quick: bool = False, progress: bool = True, seed: int = 0) -> dict:
    import place3d_kernels as p3k
    from place3d_kernels.pipeline import scene_psog
    from place3d_kernels.scene.city import box_city
    from place3d_kernels.simulate import DEFAULT_MOUNT, simulate
    from place3d_kernels.sog import PSOG

    names = backends or p3k.available_backends()
    scene = p3k.scene.town(seed=seed)
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, BENCH_VOXEL)
    psog = scene_psog(scene, grid, progress=progress)
    lidar = p3k.LidarModel.load("place3d_16ch")
    collection = p3k.LidarModel.load("collection_64ch")
    rig = p3k.Placement.load("pyramid")
    rng = np.random.default_rng(seed)
    pop = np.repeat(rig.poses[None], 16, axis=0)
    pop[..., :3] += rng.uniform(-0.3, 0.3, pop[..., :3].shape)
    ego0 = scene.ego_poses[0].copy()
    ego0[2] += DEFAULT_MOUNT[2]
    fast = next((n for n in p3k.available_backends() if n != "reference"), "reference")
    frames = simulate(scene, collection, frames=range(8), backend=fast)   # inputs for the P-SOG timing
    out = {"info": machine_info(), "workloads": {
        "paper_rig": f"4 x 16 x 250 rays (pyramid), grid {'x'.join(map(str, grid.shape))} @ {BENCH_VOXEL} m",
        "town_sweep": f"collection LiDAR 64 x 1024 rays from the first ego pose, town static mesh "
                      f"{scene.static.n_faces} triangles",
        "city_dense": "1M-triangle box city, dense rig 4 x 64 x 2048 rays",
        "psog_build": f"8 simulated frames, k = 4, the same {BENCH_VOXEL} m grid"}, "backends": {}}
    from tqdm import tqdm

    # five workloads everywhere; the kernel-only traversal and ray-mesh (town, city) off the reference
    steps_per_backend = {n: 5 + (n != "reference") * (2 if quick else 3) for n in names}
    bar = tqdm(total=sum(steps_per_backend.values()), desc="bench", unit="workload", disable=not progress,
               leave=False)

    def tick(backend: str, workload: str) -> None:
        bar.set_postfix_str(f"{backend}: {workload}")
        bar.update(1)

    city = None
    for name in names:
        b = p3k.get_backend(name)
        sync = b.synchronize
        r: dict = {}
        o, d = p3k.lidar_rays(lidar, rig, backend=b)
        r["lidar_rays_ms"] = 1e3 * _time(lambda: b.lidar_rays(lidar.elevations, lidar.azimuths, rig.poses), sync)
        tick(b.name, "rig rays")
        tr = p3k.traverse(psog.grid, o, d, lidar.max_range, backend=b)
        steps = len(tr.voxels)
        t = _time(lambda: p3k.traverse(psog.grid, o, d, lidar.max_range, backend=b), sync, repeat=3)
        r["traverse_gsteps_s"] = steps / t / 1e9
        r["traverse_steps"] = steps
        tick(b.name, "traversal")
        r["placement_eval_ms"] = 1e3 * _time(lambda: p3k.msog(psog, lidar, rig, backend=b), sync, repeat=5)
        tick(b.name, "M-SOG")
        r["population16_eval_ms"] = 1e3 * _time(lambda: p3k.msog_batch(psog, lidar, pop, backend=b), sync,
                                                repeat=3)
        tick(b.name, "population of 16")
        r["psog_build_s"] = _time(lambda: PSOG.from_frames(frames, psog.grid, 4, backend=b), sync, repeat=2)
        tick(b.name, "P-SOG build")
        if b.resident_kernels:    # kernel only, rays already on the device
            run = b.resident_traverse(psog.grid.spec, psog.grid.to_local(o), d, lidar.max_range)
            r["traverse_kernel_gsteps_s"] = steps / _time(run, sync, repeat=5) / 1e9
        if name != "reference":
            tick(b.name, "traversal kernel")
        if name != "reference":   # brute-force reference ray-mesh is far too slow for these meshes
            co, cd = b.lidar_rays(collection.elevations, collection.azimuths, ego0[None])
            mesh = p3k.Mesh(scene.static.vertices, scene.static.faces, scene.static.labels)  # fresh: no cached BVH
            _ray_mesh(r, "town", b, mesh, co, cd, 100.0, repeat=3)
            tick(b.name, "ray-mesh, town")
            if not quick:
                if city is None:
                    city = box_city(1_000_000, seed=seed)
                    dense = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=200.0)
                    do, dd = p3k.get_backend("reference").lidar_rays(dense.elevations, dense.azimuths, rig.poses)
                _ray_mesh(r, "city", b, city, do, dd, 200.0, repeat=2)
                tick(b.name, "ray-mesh, city")
        out["backends"][b.name] = r
    bar.close()
    return out


def format_table(res: dict) -> str:
    """``run_kernel_bench``'s result as a text table: one row per workload (unit in the label), one column
    per backend; "-" where a backend does not run a workload (the reference has no ray-mesh or kernel-only
    figures)."""
    cols = list(res["backends"])
    rows = [(label, [res["backends"][c].get(key) for c in cols]) for key, label in METRICS
            if any(key in res["backends"][c] for c in cols)]

    def fmt(v) -> str:
        if v is None:
            return "-"
        return f"{v:,.3g}" if abs(v) < 100 else f"{v:,.0f}"

    width = max([len("workload")] + [len(label) for label, _ in rows])
    cw = [max(len(c), 8) for c in cols]
    info = res.get("info", {})
    lines = [f"{info.get('cpu', '?')}, {info.get('cores', '?')} cores, {info.get('date', '?')}; "
             f"median of repeated runs after a warm-up",
             f"{'workload':{width}s}  " + "  ".join(f"{c:>{w}s}" for c, w in zip(cols, cw))]
    lines.append("-" * len(lines[-1]))
    lines += [f"{label:{width}s}  " + "  ".join(f"{fmt(v):>{w}s}" for v, w in zip(vals, cw)) for label, vals in rows]
    return "\n".join(lines)
