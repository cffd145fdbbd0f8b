#!/usr/bin/env python3
"""Where the dense rig's near field spends its time (issue 17, goal 3): each launch of the near field timed
alone on the goal workload (``gpu_dense_variants.py``'s: 16 dense rigs, 0.05 m grid), per near box size.

For each ``--h`` (half-width in voxels; 0 is the thirteenth session's shipped kernel, 4 x 4 x 2 bricks, rebuilt
as ``gpu_dense_round9_kernels.make_b32``'s control, walking from the origins): the carve
kernels, the cover kernel and the walks after the boxes (``gpu_dense_near_kernels.py``), each launch
timed alone (synchronised, median of ``--repeat`` after one warm-up), and the boxes' floors and cuts.
Prints a table; writes
``<--out>/dense-near-parts-<voxel>m.json``.

    python3 bench/dense_near_parts.py --out $OUT
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
import place3d_kernels as p3k  # noqa: E402
import gpu_dense_near_kernels as nf  # noqa: E402
import gpu_dense_round9_kernels as r9  # noqa: E402
from gpu_dense_variants import Workload, dense_population  # noqa: E402
from place3d_app.kernel_bench import machine_info  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--azimuths", type=int, default=2048)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--h", default="16,32,64")
    ap.add_argument("--hz", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=os.environ.get("OUT", str(Path(__file__).resolve().parent / "results")))
    args = ap.parse_args()
    dev = args.device
    wp.init()
    d0 = p3k.DEFAULT_GRID
    grid = p3k.Grid(d0.lower, d0.upper, args.voxel)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend=f"warp:{dev}")
    lidar = p3k.LidarModel.uniform(64, (-25, 15), args.azimuths, max_range=100.0, name="dense")
    wl = Workload(psog, lidar, dense_population(args.pop), dev)
    g = wl.backend.score_gpu
    io = wl.inputs
    rigs = wl.P * wl.L
    round8 = r9.make_b32((2, 2, 1), "xyz", 64)

    def timed(fn):
        wp.synchronize_device(dev)
        t = time.perf_counter()
        out = fn()
        wp.synchronize_device(dev)
        return time.perf_counter() - t, out

    def walk(near, h, hz):
        if h == 0:      # the kernel the near field was built on (4 x 4 x 2 bricks, as its inputs)
            wp.launch(round8, dim=wl.n_rays, device=dev, inputs=io + [wl.bits, wl.sums, wl.stats],
                      block_dim=g.SCORE_BLOCK_DIM)
        else:
            wp.launch(nf.score_kernel_near, dim=wl.n_rays, device=dev, inputs=io + [wl.bits, wl.sums, near, h, hz],
                      block_dim=g.SCORE_BLOCK_DIM)

    rows = {}
    for h in [0] + [int(x) for x in args.h.split(",") if x]:
        parts = {"carve": [], "cover": [], "walk": []}
        for _ in range(args.repeat + 1):
            wl.reset()
            if h == 0:
                t, _ = timed(lambda: walk(None, 0, 0))
                parts["walk"].append(t)
                continue
            got = {}

            def carve():
                got["near"] = nf.carve(dev, io[2], io[5], wl.shape, wl.bricks, io[11], h, args.hz)

            def cover():
                nf.cover(dev, got["near"], wl.near_table, io[0], io[1], io[2], wl.L, io[4], io[5], wl.shape, wl.bricks,
                         io[11], io[12], wl.words, wl.bits, wl.sums, h, args.hz)

            parts["carve"].append(timed(carve)[0])
            parts["cover"].append(timed(cover)[0])
            parts["walk"].append(timed(lambda: walk(got["near"], h, args.hz))[0])
        for k in parts:
            parts[k] = parts[k][1:]
        med = {k: 1e3 * statistics.median(v) / wl.P if v else 0.0 for k, v in parts.items()}
        extra = {}
        if h:
            n = got["near"].numpy()
            extra = {"floors": n[:rigs].tolist(), "cuts": n[rigs:].tolist()}
        rows[h] = {"ms_per_rig": med, "runs_s": parts, **extra}
        print(f"h={h:3d}  " + "  ".join(f"{k} {v:.3f}" for k, v in med.items())
              + f"  total {sum(med.values()):.3f} ms/rig", flush=True)
    res = Path(args.out)
    res.mkdir(parents=True, exist_ok=True)
    (res / f"dense-near-parts-{args.voxel}m.json").write_text(json.dumps(
        {"info": machine_info(), "voxel": args.voxel, "pop": args.pop, "hz": args.hz, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
