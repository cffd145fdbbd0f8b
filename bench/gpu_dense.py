#!/usr/bin/env python3
"""GPU study for issue 6: one placement evaluation of the dense rig (4 x 64 x 2048 rays) on a 0.05 m grid,
batched and amortised, per GPU backend. Writes JSON to $OUT (or bench/results/).

    python3 bench/gpu_dense.py [--backends warp:cuda:0 opencl:nvidia] [--pop 16]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import place3d_kernels as p3k
from place3d_app.kernel_bench import _time, machine_info


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--backends", nargs="*", default=None)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--voxel", type=float, default=0.05)
    args = ap.parse_args()
    names = args.backends or [b for b in p3k.available_backends() if b.startswith("warp:cuda")
                              or (b.startswith("opencl:") and b != "opencl:pocl")]
    d = p3k.DEFAULT_GRID
    grid = p3k.Grid(d.lower, d.upper, args.voxel)
    t = time.perf_counter()
    scene = p3k.scene.town(seed=0)
    psog = p3k.scene_psog(scene, grid=grid, backend=names[0])
    build = time.perf_counter() - t
    dense = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=100.0, name="dense64x2048")
    rig = p3k.Placement.load("pyramid")
    rng = np.random.default_rng(0)
    pop = np.repeat(rig.poses[None], args.pop, axis=0)
    pop[..., :3] += rng.uniform(-0.3, 0.3, pop[..., :3].shape).round(1)
    out = {"info": machine_info(), "grid": grid.to_dict(), "n_voxels": grid.n_voxels, "psog_build_s": build,
           "rig": "4 x 64 x 2048 rays", "population": args.pop, "backends": {}}
    for name in names:
        b = p3k.get_backend(name)
        t1 = _time(lambda: p3k.msog_batch(psog, dense, rig.poses[None], backend=b), b.synchronize, repeat=5)
        tp = _time(lambda: p3k.msog_batch(psog, dense, pop, backend=b), b.synchronize, repeat=5)
        scores = p3k.msog_batch(psog, dense, pop, backend=b)
        out["backends"][name] = {"single_eval_ms": 1e3 * t1, "population_eval_ms": 1e3 * tp,
                                 "amortised_eval_ms": 1e3 * tp / args.pop, "scores_head": scores[:3].tolist()}
        print(name, out["backends"][name], flush=True)
    res = Path(os.environ.get("OUT", Path(__file__).resolve().parent / "results"))
    res.mkdir(parents=True, exist_ok=True)
    (res / f"gpu-dense-{args.voxel}m.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
