"""The CPU walk of ``score_placements``: one ray per work-item (score_walk) against 16 rays in vector
lanes (score_walk_lanes, walk_lanes.cl), on an OpenCL CPU device.

    python3 bench/bench_pocl_walk.py --machine dev-2core [--rounds 7] [--backend opencl:pocl]

Workload: one CMA-ES generation of ``place3d optimize`` on the default town, 22 rigs (the paper's pyramid
rig with its positions and angles moved by up to 0.3 m / 0.3 rad, fixed seed) of the paper LiDAR
(4 x 16 x 250 rays), occlusion "sog", task seg, scored in one ``msog_batch`` call. The two kernels
alternate, ``--rounds`` times each after one untimed call, so drift on a shared machine hits both alike.
Timed per call: wall seconds and the process's CPU seconds (PoCL's threads included), which a busy
neighbour on the machine disturbs less than the wall. Before timing, both kernels' scores are compared
for both tasks and both occlusion modes: they must be identical.

Writes ``bench/results/pocl-walk-lanes-<machine>-<date>.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import place3d_kernels as p3k  # noqa: E402
from place3d_kernels.kernel_bench import machine_info  # noqa: E402
from place3d_kernels.spec import PSOGSpec, SceneSpec  # noqa: E402


def stats(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="opencl:pocl")
    ap.add_argument("--machine", required=True, help="a short name for the results file (e.g. dev-2core)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--rigs", type=int, default=22, help="rigs per call (CMA-ES's population here is 22)")
    args = ap.parse_args(argv)
    b = p3k.get_backend(args.backend)
    if not getattr(b, "walk_lanes", False):
        raise SystemExit(f"{b.name} does not walk in lanes (not an OpenCL CPU device)")
    psog = PSOGSpec(SceneSpec()).build(backend=b)
    lidar = p3k.LidarModel.load("place3d_16ch")
    rig = p3k.Placement.load("pyramid")
    rng = np.random.default_rng(0)
    pop = np.repeat(rig.poses[None], args.rigs, axis=0)
    pop[..., :3] += rng.uniform(-0.3, 0.3, pop[..., :3].shape)
    pop[..., 3:] += rng.uniform(-0.3, 0.3, pop[..., 3:].shape)

    def score(lanes: bool, occlusion="sog", task="seg"):
        b.walk_lanes = lanes
        return p3k.msog_batch(psog, lidar, pop, occlusion=occlusion, task=task, backend=b)

    same = all(np.array_equal(score(False, o, t), score(True, o, t)) for o in ("sog", "none") for t in ("seg", "det"))
    if not same:
        raise SystemExit("score_walk and score_walk_lanes disagree: not timing a wrong kernel")
    wall = {False: [], True: []}
    cpu = {False: [], True: []}
    for _ in range(args.rounds):
        for lanes in (False, True):
            t, c = time.perf_counter(), time.process_time()
            score(lanes)
            wall[lanes].append(time.perf_counter() - t)
            cpu[lanes].append(time.process_time() - c)
    steps = len(p3k.traverse(psog.grid, *p3k.lidar_rays(lidar, pop[0], backend=b), lidar.max_range, backend=b,
                             stop=psog.stop_mask).voxels)
    out = {**machine_info(), "machine_name": args.machine, "backend": b.name, "device": b.device.name,
           "workload": f"{args.rigs} rigs of place3d_16ch (4 x 16 x 250 rays) on the default town grid "
                       f"{psog.grid.shape} @ {psog.grid.voxel_size} m, occlusion sog, one msog_batch call",
           "voxel_steps_first_rig": steps, "identical_scores": same,
           "loadavg_after": list(os.getloadavg()),
           "score_walk": {"wall_s": stats(wall[False]), "cpu_s": stats(cpu[False])},
           "score_walk_lanes": {"wall_s": stats(wall[True]), "cpu_s": stats(cpu[True])},
           "speedup_wall_median": statistics.median(wall[False]) / statistics.median(wall[True]),
           "speedup_cpu_median": statistics.median(cpu[False]) / statistics.median(cpu[True])}
    path = ROOT / "bench" / "results" / f"pocl-walk-lanes-{args.machine}-{datetime.date.today()}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    for k in ("score_walk", "score_walk_lanes"):
        w, c = out[k]["wall_s"], out[k]["cpu_s"]
        print(f"{k:18s} wall {1e3 * w['median']:.1f} ms [{1e3 * w['min']:.1f}-{1e3 * w['max']:.1f}]  "
              f"cpu {1e3 * c['median']:.1f} ms [{1e3 * c['min']:.1f}-{1e3 * c['max']:.1f}]")
    print(f"speed-up (median): wall {out['speedup_wall_median']:.2f}x, cpu {out['speedup_cpu_median']:.2f}x; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
