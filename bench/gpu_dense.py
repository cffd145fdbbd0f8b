#!/usr/bin/env python3
"""The dense rig through the API: one M-SOG evaluation of a 4 x 64 x 2048-ray rig on the default town's P-SOG
at 0.05 m (256 M voxels), alone and amortised over a population of 16 (``msog_batch``), per GPU backend.

    python3 bench/gpu_dense.py [--backends warp:cuda:0 opencl:nvidia] [--pop 16] [--machine H100]

Times: median of 5 calls after a warm-up (``_time``), synchronised. Writes
``bench/results/gpu-dense-<machine>-<date>.json`` (or ``$OUT``/``--out``; ``--output`` names the file).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from results_io import write_result

import place3d_kernels as p3k
from place3d_app.kernel_bench import _time


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--backends", nargs="*", default=None)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--out", default=None, help="folder (default $OUT, else bench/results/)")
    ap.add_argument("--output", default=None, help="file path (overrides --out and the file name)")
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
    out = {"grid": grid.to_dict(), "n_voxels": grid.n_voxels, "psog_build_s": build,
           "rig": "4 x 64 x 2048 rays", "population": args.pop, "backends": {}}
    for name in names:
        b = p3k.get_backend(name)
        t1 = _time(lambda: p3k.msog_batch(psog, dense, rig.poses[None], backend=b), b.synchronize, repeat=5)
        tp = _time(lambda: p3k.msog_batch(psog, dense, pop, backend=b), b.synchronize, repeat=5)
        scores = p3k.msog_batch(psog, dense, pop, backend=b)
        out["backends"][name] = {"single_eval_ms": 1e3 * t1, "population_eval_ms": 1e3 * tp,
                                 "amortised_eval_ms": 1e3 * tp / args.pop, "scores_head": scores[:3].tolist()}
        print(name, out["backends"][name], flush=True)
    print("wrote", write_result("gpu-dense", out, args.machine, args.out, args.output))


if __name__ == "__main__":
    main()
