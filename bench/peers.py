"""Ray-mesh throughput and hit agreement of our backends vs peer ray casters, and voxel traversal vs a
pure-Python S-MIG-style baseline (per-ray loop stepping voxels, as in Hu et al. 2022's public code).

Scene: ``box_city(1_000_000)``; rays: 4 LiDARs x 64 channels x 2048 azimuths of
``LidarModel.uniform(64, (-25, 15), 2048, max_range=200)`` at the ``pyramid`` placement (524,288 rays).
Peers, each used only when importable: Open3D ``RaycastingScene``, Embree 4 via ``embreex``, Mitsuba 3
(``llvm_ad_rgb``, ``scene.ray_intersect_preliminary``). Timings: best of ``--repeats`` after one warm-up;
BVH / scene builds timed separately. Agreement: for rays both sides hit (within max_range), the fraction
with |t_peer - t_ours| <= 1e-4 m, the max difference, and the hit/miss disagreements.

Usage: python bench/peers.py [--label vm] [--rays N] [--traverse-rays N] [--python-rays N]
Writes bench/results/peers-<label>-<date>.json and prints a table.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import place3d_kernels as p3k
from place3d_kernels.grid import DEFAULT_GRID
from place3d_kernels.scene.city import box_city

AGREE_M = 1e-4


def _best(fn, repeats):
    fn()  # warm-up (JIT, caches)
    best = np.inf
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


# ----------------------------------------------------------------------------- peers
def peer_open3d(v, f, o, d, t_max, repeats):
    import open3d as o3d

    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    rays = o3d.core.Tensor(np.hstack([o, d]).astype(np.float32))
    scene.cast_rays(rays[:1])  # the BVH is committed lazily on the first query
    build = time.perf_counter() - t0

    def run():
        r = scene.cast_rays(rays)
        return r["t_hit"].numpy().astype(np.float64), r["primitive_ids"].numpy().astype(np.int64)

    sec, (t, face) = _best(run, repeats)
    miss = ~(t <= t_max)
    return build, sec, np.where(miss, np.inf, t), np.where(miss, -1, face), f"open3d {o3d.__version__}"


def peer_embree(v, f, o, d, t_max, repeats):
    import embreex
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    t0 = time.perf_counter()
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, v[f].astype(np.float32))
    oo, dd = o.astype(np.float32), d.astype(np.float32)
    scene.run(oo[:1], dd[:1])
    build = time.perf_counter() - t0

    def run():
        r = scene.run(oo, dd, output=1)
        return r["tfar"].astype(np.float64), r["primID"].astype(np.int64)

    sec, (t, face) = _best(run, repeats)
    miss = (face < 0) | ~(t <= t_max)
    return build, sec, np.where(miss, np.inf, t), np.where(miss, -1, face), \
        f"embreex {getattr(embreex, '__version__', '?')}"


def peer_mitsuba(v, f, o, d, t_max, repeats):
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    t0 = time.perf_counter()
    m = mi.Mesh("city", len(v), len(f))
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(f.astype(np.uint32).ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "city": m})
    build = time.perf_counter() - t0
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    ray.maxt = mi.Float(np.full(len(o), t_max, np.float32))

    def run():
        pi = scene.ray_intersect_preliminary(ray)
        t = np.array(pi.t, dtype=np.float64)
        face = np.array(pi.prim_index, dtype=np.int64)
        dr.sync_thread()
        return t, face

    sec, (t, face) = _best(run, repeats)
    miss = ~(t <= t_max)
    return build, sec, np.where(miss, np.inf, t), np.where(miss, -1, face), f"mitsuba {mi.__version__} llvm_ad_rgb"


PEERS = {"open3d": peer_open3d, "embree": peer_embree, "mitsuba": peer_mitsuba}


def ours(name, mesh, o, d, t_max, repeats):
    b = p3k.get_backend(name)
    t0 = time.perf_counter()
    mesh.handle(b)
    build = time.perf_counter() - t0

    def run():
        h = p3k.raycast(mesh, o, d, t_max, backend=b)
        return h.t, h.face

    sec, (t, face) = _best(run, repeats)
    return build, sec, t, face, name


def agreement(t_a, t_b):
    both = np.isfinite(t_a) & np.isfinite(t_b)
    diff = np.abs(t_a[both] - t_b[both])
    return {
        "both_hit": int(both.sum()),
        "agree_1e-4": float(np.mean(diff <= AGREE_M)) if both.any() else None,
        "max_abs_diff_m": float(diff.max()) if both.any() else None,
        "p999_abs_diff_m": float(np.quantile(diff, 0.999)) if both.any() else None,
        "hit_miss_disagree": int(np.sum(np.isfinite(t_a) != np.isfinite(t_b))),
    }


# ----------------------------------------------------------------------------- pure-Python traversal
def smig_python_traverse(grid, o, d, t_end):
    """Per-ray Python loop stepping voxels (Amanatides-Woo with accumulated tMax, like S-MIG reference
    code): the 'pure Python' baseline. Returns the union of visited voxels (flat indices)."""
    s = grid.voxel_size
    n = grid.shape
    lo = np.asarray(grid.lower)
    seen = set()
    for r in range(len(o)):
        p = (o[r] - lo) / s
        dr_ = d[r]
        ijk = [int(np.floor(p[a])) for a in range(3)]
        if not all(0 <= ijk[a] < n[a] for a in range(3)):
            continue  # LiDARs sit inside the ROI
        step = [1 if dr_[a] > 0 else -1 for a in range(3)]
        tmax, tdelta = [], []
        for a in range(3):
            if dr_[a] == 0:
                tmax.append(np.inf)
                tdelta.append(np.inf)
            else:
                nxt = ijk[a] + (step[a] > 0)
                tmax.append((nxt - p[a]) * s / dr_[a])
                tdelta.append(s / abs(dr_[a]))
        t = 0.0
        while t < t_end:
            seen.add((ijk[0] * n[1] + ijk[1]) * n[2] + ijk[2])
            a = int(np.argmin(tmax))
            t = tmax[a]
            ijk[a] += step[a]
            if not 0 <= ijk[a] < n[a]:
                break
            tmax[a] += tdelta[a]
    return np.array(sorted(seen), dtype=np.int64)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", default=platform.node() or "host")
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--rays", type=int, default=0, help="use every k-th ray so that about N remain (0: all)")
    ap.add_argument("--traverse-rays", type=int, default=0, help="rays for our traverse (0: all)")
    ap.add_argument("--python-rays", type=int, default=2000, help="rays for the pure-Python baseline")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default=",".join(sorted((b for b in p3k.available_backends() if b != "reference"),
                                                          key=lambda b: not b.startswith("opencl"))))
    ap.add_argument("--peers", default="open3d,embree,mitsuba")
    args = ap.parse_args(argv)

    lidar = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=200)
    placement = p3k.Placement.load("pyramid")
    o, d = p3k.lidar_rays(lidar, placement, backend="reference")
    n_all = len(o)
    stride = max(1, n_all // args.rays) if args.rays else 1
    o_r, d_r = o[::stride], d[::stride]
    t_max = float(lidar.max_range)
    print(f"building box_city({args.triangles:,}) ...", flush=True)
    mesh = box_city(args.triangles)
    v, f = mesh.vertices, mesh.faces

    rows, hits = [], {}
    for name in [b for b in args.backends.split(",") if b]:
        try:
            build, sec, t, face, ver = ours(name, mesh, o_r, d_r, t_max, args.repeats)
        except Exception as e:  # noqa: BLE001 - a missing backend is a row, not a crash
            rows.append({"name": name, "kind": "ours", "error": repr(e)})
            continue
        hits[name] = t
        rows.append({"name": name, "kind": "ours", "version": ver, "build_s": build, "raycast_s": sec,
                     "mrays_per_s": len(o_r) / sec / 1e6, "hit_fraction": float(np.isfinite(t).mean())})
        print(f"  {name}: {len(o_r) / sec / 1e6:.3f} Mrays/s", flush=True)
    for name in [p for p in args.peers.split(",") if p]:
        try:
            build, sec, t, face, ver = PEERS[name](v, f, o_r, d_r, t_max, args.repeats)
        except Exception as e:  # noqa: BLE001 - peers are optional
            rows.append({"name": name, "kind": "peer", "error": f"{type(e).__name__}: {e}"[:300]})
            print(f"  {name}: unavailable ({type(e).__name__}: {e})", flush=True)
            continue
        hits[name] = t
        rows.append({"name": name, "kind": "peer", "version": ver, "build_s": build, "raycast_s": sec,
                     "mrays_per_s": len(o_r) / sec / 1e6, "hit_fraction": float(np.isfinite(t).mean())})
        print(f"  {name}: {len(o_r) / sec / 1e6:.3f} Mrays/s", flush=True)
    base = next((r["name"] for r in rows if r["kind"] == "ours" and "error" not in r), None)
    for r in rows:
        if "error" not in r and base is not None:
            r["vs_" + base] = agreement(hits[r["name"]], hits[base])
            r["speed_vs_" + base] = next(x["raycast_s"] for x in rows if x["name"] == base) / r["raycast_s"]
    # a check of our own hits against the float64 brute force on a few rays
    ref_idx = np.linspace(0, len(o_r) - 1, 64).astype(int)
    ref_t = p3k.raycast(mesh, o_r[ref_idx], d_r[ref_idx], t_max, backend="reference").t
    for r in rows:
        if "error" not in r:
            r["vs_reference_64_rays"] = agreement(hits[r["name"]][ref_idx], ref_t)

    # ---- traversal: ours vs pure Python, on DEFAULT_GRID (80 m x 80 m x 5 m, 0.2 m voxels)
    grid = DEFAULT_GRID
    trav = []
    ts = max(1, n_all // args.traverse_rays) if args.traverse_rays else 1
    o_t, d_t = o[::ts], d[::ts]
    ps = max(1, n_all // args.python_rays)
    o_p, d_p = o[::ps], d[::ps]
    t0 = time.perf_counter()
    py_union = smig_python_traverse(grid, o_p, d_p, t_max)
    py_sec = time.perf_counter() - t0
    py_rate = len(o_p) / py_sec
    trav.append({"name": "numpy-python-loop (S-MIG style)", "rays": len(o_p), "seconds": py_sec,
                 "rays_per_s": py_rate})
    for name in ["reference"] + [b for b in args.backends.split(",") if b]:
        oo, dd = (o_p, d_p) if name == "reference" else (o_t, d_t)
        try:
            sec, cov = _best(lambda: p3k.coverage(grid, oo, dd, t_max, backend=name), 1 if name == "reference"
                             else args.repeats)
        except Exception as e:  # noqa: BLE001
            trav.append({"name": name, "error": repr(e)})
            continue
        row = {"name": name, "rays": len(oo), "seconds": sec, "rays_per_s": len(oo) / sec,
               "speedup_vs_python": len(oo) / sec / py_rate}
        if name != "reference":
            mine = np.flatnonzero(p3k.coverage(grid, o_p, d_p, t_max, backend=name).reshape(-1))
            row["python_union_equal"] = bool(np.array_equal(mine, py_union))
            row["python_union_sym_diff"] = int(len(np.setxor1d(mine, py_union)))
        trav.append(row)

    out = {
        "label": args.label, "date": dt.date.today().isoformat(),
        "machine": {"node": platform.node(), "platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "scene": {"name": "box_city", "triangles": int(mesh.n_faces)},
        "rays": {"lidar": "uniform(64, (-25, 15), 2048, max_range=200)", "placement": "pyramid",
                 "total": n_all, "used": len(o_r), "stride": stride},
        "raycast": rows, "traverse": {"grid": grid.to_dict(), "t_end": t_max, "rows": trav},
    }
    path = Path(__file__).parent / "results" / f"peers-{args.label}-{out['date']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))

    print(f"\nray-mesh: box_city {mesh.n_faces:,} triangles, {len(o_r):,} of {n_all:,} rays (stride {stride})")
    print(f"{'caster':<14}{'build s':>9}{'cast s':>9}{'Mrays/s':>9}{'speed':>7}{'hit %':>7}"
          f"{'agree<=1e-4':>12}{'max |dt| m':>12}{'hit/miss':>9}")
    for r in rows:
        if "error" in r:
            print(f"{r['name']:<14}  unavailable: {r['error'][:80]}")
            continue
        a = r.get("vs_" + base, {})
        print(f"{r['name']:<14}{r['build_s']:>9.2f}{r['raycast_s']:>9.3f}{r['mrays_per_s']:>9.3f}"
              f"{r['speed_vs_' + base]:>7.2f}{100 * r['hit_fraction']:>7.1f}"
              f"{100 * (a.get('agree_1e-4') or 0):>11.3f}%{a.get('max_abs_diff_m') or 0:>12.2e}"
              f"{a.get('hit_miss_disagree', 0):>9}")
    print(f"(speed and agreement relative to {base})")
    print(f"\ncoverage on DEFAULT_GRID {grid.shape}, t_end {t_max} m")
    print(f"{'traversal':<34}{'rays':>9}{'s':>9}{'rays/s':>12}{'x python':>10}{'union==python':>14}")
    for r in trav:
        if "error" in r:
            print(f"{r['name']:<34} error {r['error'][:60]}")
            continue
        print(f"{r['name']:<34}{r['rays']:>9}{r['seconds']:>9.3f}{r['rays_per_s']:>12.0f}"
              f"{r.get('speedup_vs_python', 1.0):>10.1f}{str(r.get('python_union_equal', '-')):>14}")
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
