"""Where the Warp ray-mesh kernel's time goes against a plain ``mesh_query_ray`` kernel (issue 17, goal 2).

    python3 bench/raymesh_gap.py [--device cuda:0] [--rounds 15] [--out FILE]

Same city (``box_city(1_000_000)``), same 4 x 64 x 2048 rays, every kernel alone on rays already on the
device, launched and synchronised in turn in each round (median and range of each, and of its ratio to
A in the same round). The steps from the plain kernel to the shipped one:
  A. plain: shared float32 vertices, SAH BVH, float32 rays, ``mesh_query_ray``, float32 t out;
  B. A's query on the backend's mesh (per-triangle vertices, BVH built over ulp-padded triangles);
  C. B reading float64 rays and t_max and writing float64 t and int32 faces, as the shipped kernel does;
  D. C plus the float64 distance of the winning face (three float64 corners gathered, Woop-Benthin-Wald
     in float64) in the same kernel: the shipped form until 2026-11-25, kept here as a frozen copy;
  E. the shipped two passes (``raycast_query_kernel``, then ``raycast_exact_kernel``): D's results bit
     for bit, with the walk's kernel kept free of the float64 work (checked on every run).
B-A is the mesh, C-B the float64 inputs and outputs, D-C and E-C the exact distance in one kernel and in
a second. Only D and E are exact; the others exist to measure.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def stats(xs):
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    import place3d_kernels as p3k
    from place3d_app.kernel_bench import machine_info
    from place3d_kernels.scene.city import box_city

    dev = args.device
    b = p3k.get_backend(f"warp:{dev}")

    @wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
    def k_f32(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), t_max: float,
              out_t: wp.array(dtype=float)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], d[i], t_max)
        out_t[i] = wp.where(q.result, q.t, -1.0)

    @wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
    def k_f64io(mesh: wp.uint64, o64: wp.array(dtype=wp.vec3d), d64: wp.array(dtype=wp.vec3d),
                tm: wp.array(dtype=wp.float64), out_t: wp.array(dtype=wp.float64), out_f: wp.array(dtype=wp.int32)):
        i = wp.tid()
        a, c = o64[i], d64[i]
        o = wp.vec3(wp.float32(a[0]), wp.float32(a[1]), wp.float32(a[2]))
        d = wp.vec3(wp.float32(c[0]), wp.float32(c[1]), wp.float32(c[2]))
        q = wp.mesh_query_ray(mesh, o, d, wp.float32(tm[i] * wp.float64(1.000001) + wp.float64(1.0e-6)))
        t = wp.float64(-1.0)
        f = wp.int32(-1)
        if q.result:
            t = wp.float64(q.t)
            f = q.face
        out_t[i] = t
        out_f[i] = f

    from place3d_kernels.backends.warp import kernels as K

    @wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
    def k_one_kernel(mesh: wp.uint64, corners64: wp.array(dtype=wp.vec3d), o64: wp.array(dtype=wp.vec3d),
                     d64: wp.array(dtype=wp.vec3d), tm: wp.array(dtype=wp.float64), out_t: wp.array(dtype=wp.float64),
                     out_f: wp.array(dtype=wp.int32)):
        # the shipped kernel's form until 2026-11-25: the walk and the exact distance in one kernel
        i = wp.tid()
        t, f = K.query_hit(mesh, o64[i], d64[i], tm[i])
        t, f = K.exact_hit(corners64, o64[i], d64[i], tm[i], t, f)
        out_t[i] = t
        out_f[i] = f

    lidar = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=200)
    o, d = p3k.lidar_rays(lidar, p3k.Placement.load("pyramid"), backend="reference")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t_max, n = float(lidar.max_range), len(o)
    city = box_city(args.triangles)
    h = city.handle(b)
    ol = o - city.shift
    v32 = np.ascontiguousarray(city.vertices - city.shift, dtype=np.float32)
    plain_mesh = wp.Mesh(points=wp.array(v32, dtype=wp.vec3, device=dev),
                         indices=wp.array(np.ascontiguousarray(city.faces, dtype=np.int32).reshape(-1),
                                          dtype=wp.int32, device=dev), bvh_constructor="sah")
    o32 = wp.array(np.ascontiguousarray(ol, dtype=np.float32), dtype=wp.vec3, device=dev)
    d32 = wp.array(np.ascontiguousarray(d, dtype=np.float32), dtype=wp.vec3, device=dev)
    o64, d64 = wp.array(ol, dtype=wp.vec3d, device=dev), wp.array(d, dtype=wp.vec3d, device=dev)
    tm = wp.array(np.full(n, t_max), dtype=wp.float64, device=dev)
    t32 = wp.empty(n, dtype=float, device=dev)
    t64, f32 = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.int32, device=dev)
    shipped = b.resident_raycast(h, ol, d, t_max)
    steps = {
        "A_plain": lambda: wp.launch(k_f32, dim=n, inputs=[plain_mesh.id, o32, d32, t_max, t32], device=dev),
        "B_backend_mesh": lambda: wp.launch(k_f32, dim=n, inputs=[h.mesh.id, o32, d32, t_max, t32], device=dev),
        "C_float64_io": lambda: wp.launch(k_f64io, dim=n, inputs=[h.mesh.id, o64, d64, tm, t64, f32], device=dev),
        "D_one_kernel": lambda: wp.launch(k_one_kernel, dim=n, inputs=[h.mesh.id, h.corners64, o64, d64, tm, t64, f32],
                                          device=dev),
        "E_shipped": shipped,
    }
    for fn in steps.values():                         # compile and warm each
        fn()
        wp.synchronize_device(dev)
    walls = {k: [] for k in steps}
    for _ in range(args.rounds):
        for k, fn in steps.items():
            wp.synchronize_device(dev)
            t = time.perf_counter()
            fn()
            wp.synchronize_device(dev)
            walls[k].append(time.perf_counter() - t)
    steps["D_one_kernel"]()
    wp.synchronize_device(dev)
    d_t, d_f = t64.numpy().copy(), f32.numpy().copy()
    e_t, e_f = b.raycast(h, ol, d, t_max)           # the shipped two passes, through the backend
    same = bool(np.array_equal(e_t, d_t) and np.array_equal(e_f, d_f))
    print(f"E gives D's distances and faces bit for bit: {same}", flush=True)
    res = {"info": machine_info(), "device": dev, "rays": n, "triangles": int(len(city.faces)),
           "rounds": args.rounds, "E_equals_D": same, "steps": {}}
    for k, w in walls.items():
        res["steps"][k] = {"s": stats(w), "mrays_s": n / statistics.median(w) / 1e6,
                           "over_A": stats([x / a for x, a in zip(w, walls["A_plain"])])}
        r = res["steps"][k]["over_A"]
        print(f"{k:16s} {res['steps'][k]['mrays_s']:7.0f} M rays/s  time / A {r['median']:.2f} "
              f"[{r['min']:.2f}-{r['max']:.2f}]", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
