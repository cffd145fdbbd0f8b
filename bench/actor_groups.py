#!/usr/bin/env python3
"""The actors of a P-SOG build cast per frame (one tree per frame's actors, cuBQL on CUDA) against one grouped
tree for all frames (``ops.MeshGroups``: a subtree per frame, LBVH on CUDA, SAH on the CPU).

On the default town (40 frames of the collection LiDAR): ``simulate``'s time each way (alternating rounds,
after one untimed round each), how many returns differ and by how much, and whether the P-SOGs built from
the two sets of frames are the same (voxels and counts, bit for bit).

    python3 bench/actor_groups.py --backend warp:cuda:0 --rounds 3 --out $OUT
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from place3d_kernels import scene as scenes
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.grid import DEFAULT_GRID
from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET
from place3d_kernels.simulate import ACTOR_GROUPS_ENV, simulate
from place3d_kernels.sog import PSOG

MODES = {"per-frame": "0", "grouped": "1"}


def frames_of(scene, b, mode: str):
    os.environ[ACTOR_GROUPS_ENV] = MODES[mode]
    t = time.perf_counter()
    fr = simulate(scene, backend=b)
    return fr, time.perf_counter() - t


def compare(a, g) -> dict:
    pts = differ = label_changes = count_changes = 0
    worst = 0.0
    for x, y in zip(a, g):
        pts += len(x.points)
        if x.points.shape != y.points.shape:
            count_changes += 1
            continue
        d = np.any(x.points != y.points, axis=1) | (x.labels != y.labels) | (x.intensity != y.intensity)
        differ += int(d.sum())
        label_changes += int((x.labels != y.labels).sum())
        if d.any():
            worst = max(worst, float(np.abs(x.points - y.points).max()))
    return dict(returns=pts, returns_differing=differ, labels_differing=label_changes,
                frames_with_other_return_counts=count_changes, max_point_shift_m=worst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="warp:cuda:0")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--label", default="")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench/results"))
    args = ap.parse_args()
    b = get_backend(args.backend)
    scene = scenes.town(seed=0)
    frames = {m: frames_of(scene, b, m)[0] for m in MODES}        # untimed: kernels loaded, caches warm
    times = {m: [] for m in MODES}
    for _ in range(args.rounds):
        for m in MODES:
            frames[m], dt = frames_of(scene, b, m)
            times[m].append(dt)
    psogs = {m: PSOG.from_frames(frames[m], DEFAULT_GRID, DEFAULT_FRAMES_PER_SUBSET, backend=b) for m in MODES}
    a, g = psogs["per-frame"], psogs["grouped"]
    same_psog = (np.array_equal(a.voxels, g.voxels) and a.counts.shape == g.counts.shape
                 and a.counts.tobytes() == g.counts.tobytes())
    out = dict(backend=args.backend, device=str(getattr(b, "device", "")), date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               frames=len(frames["grouped"]), rounds=args.rounds,
               grouped_builder=b.group_builder() if hasattr(b, "group_builder") else None,
               simulate_s={m: dict(median=statistics.median(v), min=min(v), max=max(v), runs=v) for m, v in times.items()},
               **compare(frames["per-frame"], frames["grouped"]), psog_identical=bool(same_psog),
               psog_voxels=[len(a.voxels), len(g.voxels)])
    text = json.dumps(out, indent=1)
    print(text)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    Path(args.out, f"actor-groups{args.label}.json").write_text(text)


if __name__ == "__main__":
    main()
