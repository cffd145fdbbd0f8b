"""The Warp ray-mesh query on BVHs of other builders and leaf sizes (issue 17, goal 2's kernel clause).

    python3 bench/raymesh_bvh.py [--device cuda:0] [--rounds 15] [--out FILE]
    python3 bench/raymesh_bvh.py --opencl opencl:nvidia [--opencl-variants 4:16,2:16] [--skip-warp]

Warp builds a mesh's BVH with SAH, LBVH or (experimental) cuBQL, with 4 triangles a leaf unless told
otherwise (Warp 1.19, ``wp.Mesh(bvh_constructor=, bvh_leaf_size=)``); its docs advise small leaves for ray
queries. Same city and rays as ``raymesh_gap.py`` (``box_city(1_000_000)``, 4 x 64 x 2048 rays, on the
device). Each round launches, synchronised in turn, each step once untimed and then timed (on one GPU
the first launch after another API's context paid for the switch: a default OpenCL tree read 1.08-1.15x
the yardstick, and the yardstick 1.2-1.4 G rays/s, in a run without it): the plain kernel
(``mesh_query_ray``, float32 in and out) on the plain mesh as built by default (SAH, leaf 4: the goal's
yardstick) and on the same tree options as each variant, and the backend's two passes
(``resident_raycast``) on the backend's padded mesh built with each variant's options. Reports M rays/s
and time over the yardstick's in the same round (median [min-max]), and, per variant, how many rays got
another distance or face than on an SAH tree with leaf 4 (the backend's tree until 2026-11-25; since then
CUDA meshes get cuBQL's, ``WarpCore._build_tree``).
With ``--opencl BACKEND`` the OpenCL backend's host-built binned-SAH tree (``opencl/bvh.py``) is timed the
same way for each ``leaf_size:bins[:dfs][:w4]`` (``dfs``: nodes in depth-first order, ``bvh.dfs_layout``;
``w4``: the 4-wide collapse and ``raycast4`` instead of the binary tree; the backend's default has been
4:16:w4 since 2026-11-25, 4:16 before; ``l<N>``: work-groups of N rays, ``l0`` the driver's choice, none
the backend's ``ray_group_size``, 128 since 2026-11-25), its results compared with the first variant's.
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

VARIANTS = [("sah", None), ("sah", 1), ("sah", 2), ("sah", 8), ("lbvh", None), ("lbvh", 1), ("lbvh", 2),
            ("cubql", None)]


def stats(xs):
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def _with_group(cl, group: int, run):
    """``run`` (a ``resident_raycast`` callable) launched with the backend's ray work-group size set to
    ``group`` for its duration."""
    def wrapped():
        old, cl.ray_group_size = cl.ray_group_size, group
        try:
            run()
        finally:
            cl.ray_group_size = old

    wrapped.read = run.read
    return wrapped


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--variants", default=None, help="e.g. sah:1,lbvh:2 (default: all)")
    ap.add_argument("--opencl", default=None, help="also an OpenCL backend's trees, e.g. opencl:nvidia")
    ap.add_argument("--opencl-variants", default="4:16,2:16,1:16,4:32,8:16",
                    help="leaf_size:bins[:dfs] list (dfs: bvh.dfs_layout)")
    ap.add_argument("--skip-warp", action="store_true", help="only the yardstick and the OpenCL trees")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    import place3d_kernels as p3k
    from place3d_app.kernel_bench import machine_info
    from place3d_kernels.scene.city import box_city

    dev = args.device
    b = p3k.get_backend(f"warp:{dev}")
    variants = VARIANTS if args.variants is None else [
        (c, None if x in ("", "none") else int(x)) for c, x in (v.split(":") for v in args.variants.split(","))]

    @wp.kernel(module="unique", module_options={"enable_backward": False, "fuse_fp": False})
    def k_f32(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), t_max: float,
              out_t: wp.array(dtype=float)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], d[i], t_max)
        out_t[i] = wp.where(q.result, q.t, -1.0)

    lidar = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=200)
    o, d = p3k.lidar_rays(lidar, p3k.Placement.load("pyramid"), backend="reference")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t_max, n = float(lidar.max_range), len(o)
    city = box_city(args.triangles)
    ol = o - city.shift
    v32 = wp.array(np.ascontiguousarray(city.vertices - city.shift, dtype=np.float32), dtype=wp.vec3, device=dev)
    i32 = wp.array(np.ascontiguousarray(city.faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device=dev)
    o32 = wp.array(np.ascontiguousarray(ol, dtype=np.float32), dtype=wp.vec3, device=dev)
    d32 = wp.array(np.ascontiguousarray(d, dtype=np.float32), dtype=wp.vec3, device=dev)
    t32 = wp.empty(n, dtype=float, device=dev)

    def plain(cons, leaf):
        m = wp.Mesh(points=v32, indices=i32, bvh_constructor=cons, bvh_leaf_size=leaf)
        return m, (lambda: wp.launch(k_f32, dim=n, inputs=[m.id, o32, d32, t_max, t32], device=dev))

    def backend_mesh(cons, leaf):
        was = b.bvh_constructor, b.bvh_leaf_size
        b.bvh_constructor, b.bvh_leaf_size = cons, leaf
        try:
            return b.upload_mesh(city.vertices - city.shift, city.faces)
        finally:
            b.bvh_constructor, b.bvh_leaf_size = was

    keep = []                                     # meshes must outlive their launches
    m0, yard = plain("sah", None)
    keep.append(m0)
    h0 = backend_mesh("sah", None)
    want_t, want_f = b.raycast(h0, ol, d, t_max)
    steps, diff = {"plain sah:4 (yardstick)": yard}, {}
    for cons, leaf in ([] if args.skip_warp else variants):
        name = f"{cons}:{leaf or 'default'}"
        try:
            m, fn = plain(cons, leaf)
            h = backend_mesh(cons, leaf)
        except Exception as e:  # noqa: BLE001 - a builder this Warp or device lacks
            print(f"{name}: not built ({e})", flush=True)
            continue
        keep += [m, h]
        if (cons, leaf) != ("sah", None):
            steps[f"plain {name}"] = fn
        steps[f"backend {name}"] = b.resident_raycast(h, ol, d, t_max)
        t, f = b.raycast(h, ol, d, t_max)
        diff[name] = int(np.count_nonzero((t != want_t) | (f != want_f)))
    if args.opencl:
        cl = p3k.get_backend(args.opencl)
        base = None
        for v in args.opencl_variants.split(","):
            parts = v.split(":")
            leaf, bins = int(parts[0]), int(parts[1])
            layout = "dfs" if "dfs" in parts[2:] else "levels"
            width, cl_width = (4 if "w4" in parts[2:] else 2), cl.bvh_width
            group = next((int(x[1:]) for x in parts[2:] if x.startswith("l")), None)
            cl.bvh_options = {"leaf_size": leaf, "bins": bins, "layout": layout}
            cl.bvh_width = width
            try:
                t0 = time.perf_counter()
                h = cl.upload_mesh(city.vertices - city.shift, city.faces)
                build = time.perf_counter() - t0
            finally:
                cl.bvh_options, cl.bvh_width = {}, cl_width
            keep.append(h)
            run = cl.resident_raycast(h, ol, d, t_max)
            if group is not None:   # this variant's launches with its own work-group size (0: the driver's)
                run = _with_group(cl, group or None, run)
            run()
            got = run.read()
            if base is None:
                base = got
            name = (f"{args.opencl} {leaf}:{bins}" + (":dfs" if layout == "dfs" else "") + (":w4" if width == 4 else "")
                    + (f":l{group}" if group is not None else ""))
            diff[name] = int(np.count_nonzero((got[0] != base[0]) | (got[1] != base[1])))
            steps[f"backend {name}"] = run
            print(f"{name}: built in {build:.1f} s, depth {h.bvh.depth if hasattr(h, 'bvh') else '?'}", flush=True)
    for fn in steps.values():
        fn()
        wp.synchronize_device(dev)
    walls = {k: [] for k in steps}
    for _ in range(args.rounds):
        for k, fn in steps.items():
            fn()                # untimed: a switch between CUDA and OpenCL contexts costs the first launch
            wp.synchronize_device(dev)
            t = time.perf_counter()
            fn()
            wp.synchronize_device(dev)
            walls[k].append(time.perf_counter() - t)
    yk = "plain sah:4 (yardstick)"
    res = {"info": machine_info(), "device": dev, "rays": n, "triangles": int(len(city.faces)),
           "rounds": args.rounds, "rays_differing_from_sah4": diff, "steps": {}}
    for k, w in walls.items():
        r = stats([x / a for x, a in zip(w, walls[yk])])
        res["steps"][k] = {"s": stats(w), "mrays_s": n / statistics.median(w) / 1e6, "over_yardstick": r}
        tail = ""
        if k.startswith("backend opencl"):
            tail = f"  rays differing from its default tree: {diff[k.split(' ', 1)[1]]}"
        elif k.startswith("backend "):
            tail = f"  rays differing from sah:4: {diff[k.split(' ', 1)[1]]}"
        print(f"{k:26s} {res['steps'][k]['mrays_s']:7.0f} M rays/s  time / yardstick {r['median']:.3f} "
              f"[{r['min']:.3f}-{r['max']:.3f}]{tail}", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
