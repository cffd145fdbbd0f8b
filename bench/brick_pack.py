#!/usr/bin/env python3
"""``brick_bits``' two packings on the default town's P-SOG masks: the scatter of set voxels against the
dense packing of the whole grid (``place3d_kernels/backends/bricks.py``), and the path ``brick_bits`` takes.

The masks are what ``prepare_grid`` packs: voxels with a nonzero weight and voxels that stop a ray. Rounds
are interleaved; every call's words are checked equal between the two packings.

    python3 bench/brick_pack.py [--backend warp:cpu] [--rounds 7] --out bench/results
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default=None, help="backend that builds the P-SOG on a cache miss")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--label", default="")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench/results"))
    a = ap.parse_args()

    import place3d_kernels as p3k
    from place3d_kernels.backends import bricks

    psog = p3k.scene_psog(p3k.scene.town(seed=0), backend=a.backend)
    shape = psog.grid.shape
    masks = {"nonzero weight": psog.weights != 0, "stop": psog.stop_mask != 0}
    res = {"machine": platform.node(), "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "grid": list(shape), "rounds": a.rounds,
           "masks": {}}
    for name, m in masks.items():
        t = {"sparse": [], "dense": []}
        for _ in range(a.rounds):
            for kind, pack in (("sparse", bricks._brick_bits_sparse), ("dense", bricks._brick_bits_dense)):
                t0 = time.perf_counter()
                w = pack(m, shape)
                t[kind].append(time.perf_counter() - t0)
                if kind == "sparse":
                    want = w
                elif not np.array_equal(w, want):
                    raise SystemExit(f"{name}: the packings differ")
        dense_path = m.size >= bricks.DENSE_MIN_VOXELS and np.count_nonzero(m) * bricks.DENSE_SHARE >= m.size
        res["masks"][name] = {"share_set": float(np.count_nonzero(m) / m.size),
                              "brick_bits_takes": "dense" if dense_path else "sparse",
                              **{k: {"median_ms": 1e3 * statistics.median(v), "min_ms": 1e3 * min(v),
                                     "max_ms": 1e3 * max(v)} for k, v in t.items()}}
        r = res["masks"][name]
        print(f"{name}: {100 * r['share_set']:.2f} % set; sparse {r['sparse']['median_ms']:.2f} "
              f"[{r['sparse']['min_ms']:.2f}-{r['sparse']['max_ms']:.2f}] ms, dense {r['dense']['median_ms']:.2f} "
              f"[{r['dense']['min_ms']:.2f}-{r['dense']['max_ms']:.2f}] ms; brick_bits takes {r['brick_bits_takes']}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"brick-pack{a.label}.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
