#!/usr/bin/env python3
"""The actors' BVH per frame: which Warp builder a small mesh should get (cold P-SOG build, issue 17).

``simulate`` casts each frame's rays into that frame's actor mesh (3,468 triangles on the default town), so
a cold P-SOG build uploads and builds 40 small BVHs. For each builder this times those 40 uploads
(``WarpCore.upload_mesh``: padded boxes, the tree, the corner and face tables) and the 40 casts, in
interleaved rounds, and checks that every builder gives the hits (distance, face, label) of the first
builder named on every ray of every frame.

    python3 bench/actor_bvh.py --backend warp:cuda:0 --builders cubql,sah,lbvh --out $OUT
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="warp:cuda:0")
    ap.add_argument("--builders", default="cubql,sah,lbvh")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--label", default="")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench/results"))
    a = ap.parse_args()

    import warp as wp

    import place3d_kernels as p3k
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.mesh import Mesh
    from place3d_kernels.ops import raycast
    from place3d_kernels.pose import pose_from_matrix, pose_matrix
    from place3d_kernels.simulate import DEFAULT_MOUNT

    b = get_backend(a.backend)
    scene = p3k.scene.town(seed=0)
    lidar = LidarModel.load("collection_64ch")
    mount_T = pose_matrix(DEFAULT_MOUNT)
    frames = range(scene.n_frames)
    dyn = [scene.dynamic(f) for f in frames]
    rays = [b.lidar_rays(lidar.elevations, lidar.azimuths,
                         pose_from_matrix(pose_matrix(scene.ego_poses[f]) @ mount_T)[None]) for f in frames]
    builders = a.builders.split(",")
    times = {k: {"upload": [], "cast": []} for k in builders}
    hits = {}
    for r in range(a.rounds + 1):           # round 0 warms up (kernel loads) and is not timed
        for k in builders:
            b.bvh_constructor = k
            meshes = [Mesh(m.vertices, m.faces, m.labels) for m in dyn]      # no handles yet
            wp.synchronize()
            t0 = time.perf_counter()
            for m in meshes:
                m.handle(b)
            wp.synchronize()
            t1 = time.perf_counter()
            got = [raycast(m, o, d, lidar.max_range, backend=b) for m, (o, d) in zip(meshes, rays)]
            t2 = time.perf_counter()
            if r:
                times[k]["upload"].append(t1 - t0)
                times[k]["cast"].append(t2 - t1)
            hits[k] = got
    b.bvh_constructor = None
    first = builders[0]
    # rays whose distance, face or label differ from the first builder's, and of those how many change label
    differ = {k: int(sum(((x.t != y.t) | (x.face != y.face) | (x.label != y.label)).sum()
                         for x, y in zip(hits[k], hits[first]))) for k in builders}
    label_differ = {k: int(sum((x.label != y.label).sum() for x, y in zip(hits[k], hits[first]))) for k in builders}
    same = {k: differ[k] == 0 for k in builders}
    n_hit = int(sum(np.isfinite(h.t).sum() for h in hits[first]))
    res = {"backend": b.name, "device": str(getattr(b, "device", "")), "frames": len(dyn),
           "triangles": int(dyn[0].n_faces), "rays_per_frame": int(len(rays[0][0])), "actor_hits": n_hit,
           "rounds": a.rounds, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "same_hits_as_" + first: same, "rays_differing_from_" + first: differ,
           "rays_with_another_label_than_" + first: label_differ,
           "seconds_for_all_frames": {k: {s: {"median": statistics.median(v), "min": min(v), "max": max(v)}
                                          for s, v in t.items()} for k, t in times.items()}}
    for k in builders:
        u, c = res["seconds_for_all_frames"][k]["upload"], res["seconds_for_all_frames"][k]["cast"]
        print(f"{k:6s} upload+build {1e3 * u['median']:7.1f} ms [{1e3 * u['min']:.1f}-{1e3 * u['max']:.1f}]  "
              f"cast {1e3 * c['median']:7.1f} ms [{1e3 * c['min']:.1f}-{1e3 * c['max']:.1f}]  rays differing: {differ[k]} (label: {label_differ[k]})")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"actor-bvh{a.label}.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
