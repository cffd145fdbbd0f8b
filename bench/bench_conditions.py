"""Per-frame time of each adverse condition on every backend with condition kernels.

The frame: one sweep of a 64 x 2048 LiDAR (2.5 m above the ego vehicle) in the embedded town, cut or
tiled to exactly ``--points`` returns (default 120,000). Each condition runs with the paper's parameters
(fog: alpha = 0.03, beta = 0.05). Times are wall-clock medians of ``--repeats`` calls after one warm-up
call (the warm-up includes Warp's kernel compilation / cache load and fog's table integration).

    python bench/bench_conditions.py [--points 120000] [--repeats 5] [--backends reference,warp:cpu]

Prints a table and writes ``bench/results/conditions-<machine>-<date>.json``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from results_io import write_result

import place3d_kernels as p3k
from place3d_kernels import conditions as C
from place3d_kernels.backends.conditions_base import ConditionKernels

PARAMS = {
    "fog": dict(alpha=0.03, beta=0.05),
    "wet_ground": dict(water_height_mm=1.0),
    "snow": dict(snowfall_rate=1.0, terminal_velocity=1.6),
    "motion_blur": dict(sigma=0.30),
    "crosstalk": dict(ratio=0.07),
    "incomplete_echo": dict(ratio=0.85),
}


def frame(n_points: int) -> p3k.PointCloud:
    scene = p3k.scene.town(seed=0)
    base = p3k.LidarModel.load("collection_64ch")
    lidar = p3k.LidarModel(base.elevations, np.arange(2048) * (2 * np.pi / 2048), base.max_range, "bench_64x2048")
    f = p3k.simulate(scene, lidar, frames=[0], backend="reference" if "warp:cpu" not in
                     p3k.available_backends() else "warp:cpu")[0]
    n = len(f.points)
    idx = np.arange(n_points) % n
    o = np.asarray(f.origins, dtype=np.float64)
    origins = np.broadcast_to(o, (n_points, 3)) if o.shape == (3,) else o.reshape(-1, 3)[idx]
    return p3k.PointCloud(np.asarray(f.points)[idx], np.asarray(f.labels)[idx], np.asarray(f.intensity)[idx], origins)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--backends", default=None, help="comma-separated (default: all with condition kernels)")
    ap.add_argument("--out", default=None, help="JSON path (default: bench/results/conditions-<machine>-<date>.json)")
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    args = ap.parse_args(argv)

    names = args.backends.split(",") if args.backends else [
        b for b in p3k.available_backends() if isinstance(p3k.get_backend(b), ConditionKernels)]
    cloud = frame(args.points)
    print(f"frame: {len(cloud)} points, {np.count_nonzero(cloud.labels == 10)} vehicle, "
          f"{np.count_nonzero(np.isin(cloud.labels, [6, 7, 8, 13, 21]))} ground; backends {names}")
    rows = []
    for b in names:
        for cond, params in PARAMS.items():
            t0 = time.perf_counter()
            out = C.apply(cloud, cond, seed=0, backend=b, **params)
            first = time.perf_counter() - t0
            times = []
            for r in range(args.repeats):
                t0 = time.perf_counter()
                out = C.apply(cloud, cond, seed=r + 1, backend=b, **params)
                p3k.get_backend(b).synchronize()
                times.append(time.perf_counter() - t0)
            row = dict(backend=b, condition=cond, params=params, points_in=len(cloud), points_out=len(out),
                       scattered=int(out.scattered.sum()) if out.scattered is not None else 0,
                       median_s=statistics.median(times), min_s=min(times), first_call_s=first, repeats=args.repeats)
            rows.append(row)
            print(f"{b:12s} {cond:16s} {1e3 * row['median_s']:9.1f} ms/frame   (first call {1e3 * first:8.1f} ms, "
                  f"{row['points_out']} points out, {row['scattered']} scattered)")
    result = dict(points=len(cloud), rows=rows)
    print("wrote", write_result("conditions", result, args.machine, path=args.out))
    return result


if __name__ == "__main__":
    main()
