"""The CPU walk of ``score_placements``: one ray per work-item (score_walk) against 16 rays in vector
lanes (score_walk_lanes, walk_lanes.cl), on an OpenCL CPU device.

    python3 bench/bench_pocl_walk.py --machine dev-2core [--rounds 7] [--backend opencl:pocl]

Two workloads, each scored with ``score_placements`` on the default town's prepared grid (occlusion
"sog", seg weights), the paper LiDAR (4 x 16 x 250 rays), 22 rigs a call (CMA-ES's population here):
- "perturbed": the paper's pyramid rig with positions and angles moved by up to 0.3 m / 0.3 rad (fixed
  seed), the same rigs in every call;
- "cma": the first 40 generations of a real ``place3d optimize --task seg`` run on this backend,
  recorded while it runs (positions on the search's 0.05 m lattice near the roof, rolls in 0.1 rad steps,
  no pitch or yaw: rays that run along grid planes).
The two kernels alternate, ``--rounds`` times each after one untimed pass, so drift on a shared machine
hits both alike. Timed per call: wall seconds and the process's CPU seconds (PoCL's threads included),
which a busy neighbour disturbs less than the wall. Before timing, both kernels' sums and counts are
compared on every call of both workloads, with and without the stop mask: they must be identical.

Writes ``bench/results/pocl-walk-lanes-<machine>-<date>.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import place3d_kernels as p3k  # noqa: E402
from place3d_app.kernel_bench import machine_info  # noqa: E402
from place3d_kernels.spec import PSOGSpec, SceneSpec  # noqa: E402


def stats(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def record_generations(b, n: int) -> list:
    """The grid-local poses of the first ``n`` CMA-ES generations of ``place3d optimize --task seg`` on
    backend ``b`` (the registry's instance, which the command uses), captured from its score calls."""
    from place3d_app.cli import main as cli_main

    seen, score = [], b.score_placements

    def recording(handle, el, az, t_max, poses):
        if len(poses) > 1 and len(seen) < n:
            seen.append(np.array(poses))
        return score(handle, el, az, t_max, poses)

    b.score_placements = recording
    try:
        with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)    # a short run may not leave its start
            cli_main(["optimize", "--task", "seg", "--backend", b.name, "--max-evals", str(30 * n),
                      "--interval", "none", "--quiet", "--output", tmp])
    finally:
        del b.score_placements
    return seen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="opencl:pocl")
    ap.add_argument("--machine", required=True, help="a short name for the results file (e.g. dev-2core)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--rigs", type=int, default=22, help="rigs per call of the perturbed workload")
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
    local = pop.copy()
    local[..., :3] = psog.grid.to_local(pop[..., :3])
    workloads = {"perturbed": [local] * 10, "cma": record_generations(b, 40)}
    el, az, r = lidar.elevations, lidar.azimuths, lidar.max_range
    handles = {"sog": psog.handle(b, "sog"), "none": psog.handle(b, "none")}

    def run(calls, lanes: bool, occlusion="sog"):
        b.walk_lanes = lanes
        return [b.score_placements(handles[occlusion], el, az, r, p) for p in calls]

    for name, calls in workloads.items():
        for occ in handles:
            for x, y in zip(run(calls, False, occ), run(calls, True, occ)):
                if not (np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1])):
                    raise SystemExit(f"score_walk and score_walk_lanes disagree ({name}, {occ}): not timing a wrong kernel")
    results = {}
    for name, calls in workloads.items():
        wall, cpu = {False: [], True: []}, {False: [], True: []}
        for _ in range(args.rounds):
            for lanes in (False, True):
                t, c = time.perf_counter(), time.process_time()
                run(calls, lanes)
                wall[lanes].append((time.perf_counter() - t) / len(calls))
                cpu[lanes].append((time.process_time() - c) / len(calls))
        results[name] = {"calls_per_round": len(calls),
                         "score_walk": {"wall_s": stats(wall[False]), "cpu_s": stats(cpu[False])},
                         "score_walk_lanes": {"wall_s": stats(wall[True]), "cpu_s": stats(cpu[True])},
                         "speedup_wall_median": statistics.median(wall[False]) / statistics.median(wall[True]),
                         "speedup_cpu_median": statistics.median(cpu[False]) / statistics.median(cpu[True])}
    b.walk_lanes = True
    out = {**machine_info(), "machine_name": args.machine, "backend": b.name, "device": b.device.name,
           "grid": f"{psog.grid.shape} @ {psog.grid.voxel_size} m", "rigs_per_call": args.rigs,
           "identical_scores": True, "loadavg_after": list(os.getloadavg()), "workloads": results}
    path = ROOT / "bench" / "results" / f"pocl-walk-lanes-{args.machine}-{datetime.date.today()}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    for name, res in results.items():
        for k in ("score_walk", "score_walk_lanes"):
            w, c = res[k]["wall_s"], res[k]["cpu_s"]
            print(f"{name:9s} {k:18s} wall {1e3 * w['median']:.1f} ms [{1e3 * w['min']:.1f}-{1e3 * w['max']:.1f}]  "
                  f"cpu {1e3 * c['median']:.1f} ms [{1e3 * c['min']:.1f}-{1e3 * c['max']:.1f}] a call")
        print(f"{name:9s} speed-up (median): wall {res['speedup_wall_median']:.2f}x, cpu {res['speedup_cpu_median']:.2f}x")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
