"""How many routes does a pooled P-SOG need before the order of the placements stops moving?

Builds one P-SOG per route (``pooled.build_pooled``; each drive cached on disk by its inputs) for two
disjoint groups of route seeds on one scene, scores the paper's eleven placements (seg and det, the
paper's normalisation) on pooled P-SOGs of N routes and of 2N routes, and reports Kendall tau between the
two orders: nested (the 2N pool contains the N pool: what `place3d evaluate --routes N` against
`--routes 2N` would show) and disjoint (routes [a, a+N) against [a+N, a+2N): two independent samples of N
routes). Every window of 2N consecutive seeds of a group gives one run, so N = 1 has the most runs.

Usage (dev VM): PYTHONPATH=. python3 bench/route_convergence.py --scene town --groups 0,100 --routes 16
Writes bench/results/route-convergence-<scene>-<date>.json (machine, time, per-drive build seconds,
every run's taus and a summary per N).
"""

from __future__ import annotations

import argparse
import json
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import msog_batch
from place3d_kernels.placement import PAPER_PLACEMENTS, Placement
from place3d_kernels.pooled import Drive, PooledPSOG, PoolSettings, drive_record
from place3d_kernels.uncertainty import kendall_tau


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="town")
    ap.add_argument("--groups", default="0,100", help="first seed of each group of routes")
    ap.add_argument("--routes", type=int, default=16, help="routes per group (a power of two)")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--voxel-size", type=float, default=None)
    ap.add_argument("--backend", default=None)
    ap.add_argument("--output", default=None)
    args = ap.parse_args(argv)
    from place3d_app.commands.reproduce import machine_info

    b = get_backend(args.backend)
    settings = PoolSettings(args.voxel_size, "collection_64ch", None, b.name, None)
    lidar = LidarModel.load("place3d_16ch")
    names = list(PAPER_PLACEMENTS)
    poses = np.stack([Placement.load(n).poses for n in names])
    groups = [int(g) for g in args.groups.split(",")]
    date = datetime.now(timezone.utc).date().isoformat()
    out = Path(args.output or f"bench/results/route-convergence-{args.scene.replace(':', '-')}-{date}.json")
    res = {"scene": args.scene, "groups": groups, "routes_per_group": args.routes, "frames": args.frames,
           "voxel_size": settings.grid.voxel_size, "placements": names, "normalisation": "paper",
           "machine": machine_info(b.name), "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "drive_seconds": {}, "runs": [], "summary": []}
    records = {}
    for g in groups:
        for s in range(g, g + args.routes):
            t = time.perf_counter()
            records[s] = drive_record(Drive(args.scene, s, args.frames), settings)
            res["drive_seconds"][s] = round(time.perf_counter() - t, 2)
            print(f"drive seed {s}: {res['drive_seconds'][s]} s", flush=True)
    memo = {}

    def scores(seeds):
        key = tuple(seeds)
        if key not in memo:
            ps = PooledPSOG(settings.grid, [records[s] for s in seeds]).psog()
            memo[key] = {t: msog_batch(ps, lidar, poses, "sog", t, b) for t in ("seg", "det")}
        return memo[key]

    n = 1
    while 2 * n <= args.routes:
        for g in groups:
            for a in range(g, g + args.routes, 2 * n):
                first, second, both = list(range(a, a + n)), list(range(a + n, a + 2 * n)), list(range(a, a + 2 * n))
                sa, sb, sab = scores(first), scores(second), scores(both)
                res["runs"].append({"n": n, "seeds": [a, a + 2 * n - 1],
                                    **{f"tau_{t}_nested": kendall_tau(sa[t], sab[t]) for t in ("seg", "det")},
                                    **{f"tau_{t}_disjoint": kendall_tau(sa[t], sb[t]) for t in ("seg", "det")}})
        rows = [r for r in res["runs"] if r["n"] == n]
        summ = {"n": n, "two_n": 2 * n, "runs": len(rows)}
        for k in ("tau_seg_nested", "tau_det_nested", "tau_seg_disjoint", "tau_det_disjoint"):
            v = np.array([r[k] for r in rows])
            summ[k] = {"mean": round(float(v.mean()), 4), "min": round(float(v.min()), 4)}
        res["summary"].append(summ)
        print(json.dumps(summ), flush=True)
        n *= 2
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
