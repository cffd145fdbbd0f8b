#!/usr/bin/env python3
"""Skip what a scene does not need (issue 6): counters and timings showing that each skip works.

1. ``roi_clip``      rays are clipped to the ROI: voxel steps of the paper rig (pyramid, 4 x 16 x 250 rays)
                     with t_end = 100 m (no occlusion) against a naive fixed-step march that samples every
                     voxel length along 100 m; how many rays leave the grid early and where.
2. ``occlusion``     occlusion ends traversal: total steps with the P-SOG stop mask ("sog") and without.
3. ``imports``       unused conditions and optional packages cost nothing: ``import place3d_kernels`` in
                     fresh interpreters (median wall time, ``-X importtime``), and which optional packages
                     (mitsuba, drjit, pyopencl, warp, open3d, embreex, scipy, matplotlib, cma, ...) are in
                     ``sys.modules`` afterwards, with the import chain of any that is.
4. ``bvh_once``      a mesh builds its BVH on first use only: first vs second ``raycast`` per backend.
5. ``psog_once``     ``scene_psog`` caches on disk: cold vs warm call with a temporary ``PLACE3D_CACHE``.
6. ``pose_cache``    ``MSOGObjective`` reuses per-pose coverage: pose_hits / pose_misses and time of a repeated
                     batch, and of a population that shares three of its four poses; scores equal
                     ``msog_batch`` bit for bit.

Writes bench/results/skips-<date>.json.

    python3 bench/skips.py [--backends warp:cpu opencl:pocl] [--only roi_clip occlusion ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
CHECKS = ("roi_clip", "occlusion", "imports", "bvh_once", "psog_once", "pose_cache")
OPTIONAL = ("mitsuba", "drjit", "pyopencl", "warp", "open3d", "embreex", "trimesh", "scipy", "matplotlib", "cma",
            "hypothesis", "pandas", "torch", "numba")


def _median_time(fn, runs=3):
    fn()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def grid_exit_t(grid, o, d):
    """Distance at which each ray (origin inside the grid) leaves it (slab test, float64)."""
    lo, hi = np.asarray(grid.lower), np.asarray(grid.upper)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
    return t.min(axis=1)


def check_roi_clip(ctx, backends):
    import place3d_kernels as p3k

    psog, lidar, rig = ctx["psog"], ctx["lidar"], ctx["rig"]
    g = psog.grid
    o, d = p3k.lidar_rays(lidar, rig)
    t_exit = grid_exit_t(g, o, d)
    face = np.argmin(np.where(d > 0, (np.asarray(g.upper) - o) / np.where(d == 0, 1, d),
                              np.where(d < 0, (np.asarray(g.lower) - o) / np.where(d == 0, 1, d), np.inf)), axis=1)
    sign = np.sign(d[np.arange(len(d)), face])
    names = {(2, -1): "ground (z low)", (2, 1): "top (z high)"}
    where = {}
    for f, s in zip(face, sign):
        k = names.get((int(f), int(s)), "side (x/y)")
        where[k] = where.get(k, 0) + 1
    naive_per_ray = int(np.ceil(lidar.max_range / g.voxel_size))
    out = {"rays": len(o), "t_end_m": lidar.max_range, "voxel_size_m": g.voxel_size,
           "grid_shape": list(g.shape),
           "rays_leaving_grid_before_t_end": int((t_exit < lidar.max_range).sum()),
           "mean_in_grid_length_m": float(np.minimum(t_exit, lidar.max_range).mean()),
           "median_in_grid_length_m": float(np.median(np.minimum(t_exit, lidar.max_range))),
           "exit_face_counts": where,
           "naive_fixed_step_samples": naive_per_ray * len(o),
           "naive_fixed_step_samples_per_ray": naive_per_ray, "backends": {}}
    for name in backends:
        tr = p3k.traverse(g, o, d, lidar.max_range, backend=name)
        steps = int(len(tr.voxels))
        t100 = _median_time(lambda: p3k.traverse(g, o, d, lidar.max_range, backend=name))
        tinf = _median_time(lambda: p3k.traverse(g, o, d, np.inf, backend=name))
        per = np.diff(tr.offsets)
        pad = (-len(per)) % 32
        grp = np.concatenate([per, np.zeros(pad, per.dtype)]).reshape(-1, 32)
        # share of lanes doing useful steps if 32 consecutive rays (LiDAR, channel, azimuth order) ran in
        # lock-step, as in a GPU warp: a hint of SIMT divergence from step counts alone
        simt = float(per.sum() / (32 * grp.max(axis=1).sum()))
        out["backends"][name] = {"steps": steps, "steps_per_ray": steps / len(o),
                                 "steps_per_ray_p10_p50_p90_max": [float(np.percentile(per, q)) for q in (10, 50, 90)]
                                 + [int(per.max())], "simt_efficiency_32_lanes": simt,
                                 "naive_over_steps": naive_per_ray * len(o) / steps,
                                 "traverse_t100_s": t100, "traverse_tinf_s": tinf}
        print(f"  roi_clip {name}: {steps:,} steps vs naive {naive_per_ray * len(o):,} "
              f"({naive_per_ray * len(o) / steps:.1f}x fewer); t=100 {t100 * 1e3:.1f} ms, t=inf {tinf * 1e3:.1f} ms",
              flush=True)
    return out


def check_occlusion(ctx, backends):
    import place3d_kernels as p3k

    psog, lidar, rig = ctx["psog"], ctx["lidar"], ctx["rig"]
    o, d = p3k.lidar_rays(lidar, rig)
    stop = psog.stop_mask
    out = {"rays": len(o), "stop_voxels": int(stop.sum()), "backends": {}}
    poses = ctx["poses"]
    for name in backends:
        a = p3k.traverse(psog.grid, o, d, lidar.max_range, backend=name, stop=stop)
        b = p3k.traverse(psog.grid, o, d, lidar.max_range, backend=name)
        ends = np.diff(a.offsets) < np.diff(b.offsets)
        r = {"steps_sog": int(len(a.voxels)), "steps_none": int(len(b.voxels)),
             "step_ratio_none_over_sog": len(b.voxels) / len(a.voxels),
             "rays_ended_early_by_occlusion": int(ends.sum()),
             "traverse_sog_s": _median_time(lambda: p3k.traverse(psog.grid, o, d, lidar.max_range, backend=name,
                                                                 stop=stop)),
             "traverse_none_s": _median_time(lambda: p3k.traverse(psog.grid, o, d, lidar.max_range, backend=name)),
             "msog_batch11_sog_s": _median_time(lambda: p3k.msog_batch(psog, lidar, poses, "sog", backend=name)),
             "msog_batch11_none_s": _median_time(lambda: p3k.msog_batch(psog, lidar, poses, "none", backend=name))}
        out["backends"][name] = r
        print(f"  occlusion {name}: steps sog {r['steps_sog']:,} / none {r['steps_none']:,} "
              f"({r['step_ratio_none_over_sog']:.2f}x), {r['rays_ended_early_by_occlusion']:,} rays ended early; "
              f"11 rigs sog {r['msog_batch11_sog_s']:.3f} s / none {r['msog_batch11_none_s']:.3f} s", flush=True)
    return out


def _import_chain(lines: list[str], target: str) -> list[str]:
    """Import chain (outermost first) of ``target`` from ``-X importtime`` output (children print first)."""
    rows = []
    for ln in lines:
        if not ln.startswith("import time:") or "|" not in ln or "self [us]" in ln:
            continue
        name_part = ln.split("|", 2)[2]
        name = name_part.strip()
        depth = (len(name_part) - len(name_part.lstrip(" "))) // 2
        rows.append((depth, name, int(ln.split("|")[1].strip())))
    for i, (depth, name, _) in enumerate(rows):
        if name == target:
            chain, cur = [name], depth
            for dj, nj, _ in rows[i + 1:]:
                if dj < cur:
                    chain.append(nj)
                    cur = dj
                    if dj == 0:
                        break
            return chain[::-1]
    return []


def check_imports(ctx, backends):
    code = ("import sys, time, json; t = time.perf_counter(); import place3d_kernels; "
            "dt = time.perf_counter() - t; "
            "print(json.dumps({'t': dt, 'mods': sorted(m for m in sys.modules)}))")
    env = {k: v for k, v in os.environ.items() if k != "PLACE3D_BACKEND"}
    times, mods = [], []
    for _ in range(5):
        t = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
        wall = time.perf_counter() - t
        r = json.loads(p.stdout.strip().splitlines()[-1])
        times.append((wall, r["t"]))
        mods = r["mods"]
    base = []
    for _ in range(5):
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], check=True, env=env)
        base.append(time.perf_counter() - t)
    p = subprocess.run([sys.executable, "-X", "importtime", "-c", "import place3d_kernels"], capture_output=True,
                       text=True, env=env, check=True)
    lines = p.stderr.splitlines()
    top = {m.split(".")[0] for m in mods}
    present = [m for m in OPTIONAL if m in top]
    chains = {m: _import_chain(lines, m) for m in present}
    # cumulative import time of the package's own sub-packages (microseconds in importtime)
    own = {}
    for ln in lines:
        if ln.startswith("import time:") and "|" in ln and "self [us]" not in ln:
            name = ln.split("|", 2)[2].strip()
            if name.startswith("place3d_kernels") and name.count(".") <= 1:
                own[name] = int(ln.split("|")[1].strip()) / 1e6
    cond_mods = sorted(m for m in mods if m.startswith("place3d_kernels.conditions"))
    backend_mods = sorted(m for m in mods if m.startswith("place3d_kernels.backends"))
    out = {"import_wall_s_median": statistics.median(w for w, _ in times),
           "import_in_process_s_median": statistics.median(t for _, t in times),
           "python_startup_s_median": statistics.median(base),
           "optional_packages_checked": list(OPTIONAL),
           "optional_packages_loaded": present, "import_chains": chains,
           "mitsuba_drjit_pyopencl_loaded": [m for m in ("mitsuba", "drjit", "pyopencl") if m in top],
           "own_subpackages_cumulative_s": dict(sorted(own.items(), key=lambda kv: -kv[1])),
           "condition_modules_loaded": cond_mods, "backend_modules_loaded": backend_mods,
           "n_modules": len(mods)}
    print(f"  imports: {out['import_in_process_s_median'] * 1e3:.0f} ms in-process "
          f"({out['import_wall_s_median'] * 1e3:.0f} ms wall vs {out['python_startup_s_median'] * 1e3:.0f} ms bare "
          f"python); optional loaded: {present}", flush=True)
    for m, c in chains.items():
        print(f"     {m}: {' -> '.join(c)}", flush=True)
    return out


def check_bvh_once(ctx, backends):
    import place3d_kernels as p3k
    from place3d_kernels.simulate import DEFAULT_MOUNT

    scene = ctx["scene"]
    coll = p3k.LidarModel.load("collection_64ch")
    ego0 = scene.ego_poses[0].copy()
    ego0[2] += DEFAULT_MOUNT[2]
    out = {"mesh_faces": int(scene.static.n_faces), "backends": {}}
    for name in backends:
        b = p3k.get_backend(name)
        o, d = b.lidar_rays(coll.elevations, coll.azimuths, ego0[None])
        mesh = p3k.Mesh(scene.static.vertices, scene.static.faces, scene.static.labels)   # fresh: no BVH yet
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            p3k.raycast(mesh, o, d, 100.0, backend=b)
            b.synchronize()
            ts.append(time.perf_counter() - t)
        h1 = mesh.handle(b)
        out["backends"][name] = {"rays": len(o), "first_raycast_s": ts[0], "second_raycast_s": ts[1],
                                 "third_raycast_s": ts[2], "first_over_second": ts[0] / ts[1],
                                 "handle_cached": h1 is mesh.handle(b)}
        print(f"  bvh_once {name}: first {ts[0]:.3f} s, then {ts[1]:.3f} / {ts[2]:.3f} s "
              f"(handle cached: {h1 is mesh.handle(b)})", flush=True)
    return out


def check_psog_once(ctx, backends):
    import place3d_kernels as p3k

    old = os.environ.get("PLACE3D_CACHE")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["PLACE3D_CACHE"] = tmp
        try:
            scene = p3k.scene.town(seed=0)
            t = time.perf_counter()
            a = p3k.scene_psog(scene)
            cold = time.perf_counter() - t
            files = sorted(p.name for p in Path(tmp).iterdir())
            size = sum(p.stat().st_size for p in Path(tmp).iterdir())
            t = time.perf_counter()
            b = p3k.scene_psog(p3k.scene.town(seed=0))   # a new scene object: the key is the scene's identity
            warm = time.perf_counter() - t
        finally:
            if old is None:
                os.environ.pop("PLACE3D_CACHE", None)
            else:
                os.environ["PLACE3D_CACHE"] = old
    same = bool(np.array_equal(a.weights, b.weights) and np.array_equal(a.stop_mask, b.stop_mask))
    out = {"cold_s": cold, "warm_s": warm, "cold_over_warm": cold / warm, "cache_files": files,
           "cache_bytes": size, "identical": same, "backend": p3k.get_backend().name}
    print(f"  psog_once: cold {cold:.2f} s, warm {warm:.3f} s ({cold / warm:.0f}x), identical {same}", flush=True)
    return out


def check_pose_cache(ctx, backends):
    import place3d_kernels as p3k
    from place3d_kernels.optimize import MSOGObjective, SearchSpace

    psog, lidar = ctx["psog"], ctx["lidar"]
    space = SearchSpace(4)
    rows = []
    for n in p3k.PAPER_PLACEMENTS:
        try:
            rows.append((n, space.from_placement(p3k.Placement.load(n))))
        except ValueError:
            pass       # a placement with pitch/yaw is outside this (x, y, z, roll) space
    X = np.stack([x for _, x in rows])
    base = space.from_placement(p3k.Placement.load("pyramid"))
    rng = np.random.default_rng(0)
    Y = np.repeat(base[None], 16, axis=0)
    Y[:, :4] = np.round(Y[:, :4] + rng.uniform(-0.2, 0.2, (16, 4)), 1)    # move only LiDAR 0 (x, y, z, roll)
    out = {"placements": [n for n, _ in rows], "backends": {}}
    for name in backends:
        obj = MSOGObjective(psog, lidar, space, backend=name)
        t = time.perf_counter()
        s1 = obj(X)
        t1 = time.perf_counter() - t
        h1, m1 = obj.pose_hits, obj.pose_misses
        t = time.perf_counter()
        s2 = obj(X)
        t2 = time.perf_counter() - t
        h2, m2 = obj.pose_hits - h1, obj.pose_misses - m1
        t = time.perf_counter()
        s3 = obj(Y)
        t3 = time.perf_counter() - t
        h3, m3 = obj.pose_hits - h1 - h2, obj.pose_misses - m1 - m2
        ref = p3k.msog_batch(psog, lidar, space.to_poses(X), backend=name)
        refY = p3k.msog_batch(psog, lidar, space.to_poses(Y), backend=name)
        tf = _median_time(lambda: p3k.msog_batch(psog, lidar, space.to_poses(Y), backend=name), runs=2)
        r = {"first_batch": {"rigs": len(X), "pose_hits": h1, "pose_misses": m1, "s": t1},
             "repeat_batch": {"rigs": len(X), "pose_hits": h2, "pose_misses": m2, "s": t2},
             "shared3of4_batch": {"rigs": len(Y), "pose_hits": h3, "pose_misses": m3, "s": t3,
                                  "fused_msog_batch_s": tf},
             "bit_identical_to_msog_batch": bool(np.array_equal(s1, ref) and np.array_equal(s2, ref)
                                                 and np.array_equal(s3, refY))}
        out["backends"][name] = r
        print(f"  pose_cache {name}: first {len(X)} rigs {m1} misses/{h1} hits {t1:.3f} s; repeat {m2}/{h2} "
              f"{t2:.3f} s; shared-3-of-4 {m3}/{h3} {t3:.3f} s vs fused msog_batch {tf:.3f} s; identical "
              f"{r['bit_identical_to_msog_batch']}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backends", nargs="*", default=["warp:cpu", "opencl:pocl"])
    ap.add_argument("--only", nargs="*", default=list(CHECKS), choices=CHECKS)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    import place3d_kernels as p3k
    from place3d_app.kernel_bench import machine_info

    info = machine_info()
    backends = [b for b in args.backends if b in p3k.available_backends()]
    scene = p3k.scene.town(seed=0)
    ctx = {"scene": scene, "psog": p3k.scene_psog(scene), "lidar": p3k.LidarModel.load("place3d_16ch"),
           "rig": p3k.Placement.load("pyramid"),
           "poses": np.stack([p3k.Placement.load(n).poses for n in p3k.PAPER_PLACEMENTS])}
    res = {"info": info, "backends": backends, "scene": "town(seed=0)", "rig": "pyramid, place3d_16ch",
           "checks": {}}
    for name in args.only:
        print(f"check {name}", flush=True)
        res["checks"][name] = globals()[f"check_{name}"](ctx, backends)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"skips-{info['date']}.json"
    path.write_text(json.dumps(res, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
