"""Does an M-SOG denominator other than the paper's N_L order the paper's placements more like its results?

For each of the four CARLA towns (shipped OpenDRIVE maps; one route, seed 0, 40 frames, default 0.2 m ROI:
the dev VM has 2 CPU cores, so this is a single-route study, not the pooled one), score the paper's eight
placements under each normalisation ("paper", "evidence", "uncertain"; docs/metric-normalisation.md) for
seg and det, and report Kendall tau of each order against the paper's M-SOG (Table 1) and against its
downstream results (mean clean mIoU / car mAP over four models, ``paper_results``). Also: the same over
the four towns' counts summed (one score per placement from all towns' integer sums and denominators).

Usage: PYTHONPATH=. python3 bench/normalisation_study.py [--backend opencl:pocl] [--towns Town01,Town03]
Writes bench/results/normalisation-2026-11-24.json (after each town, so a cut-short run keeps its towns).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.stats import kendalltau

from place3d_kernels import paper_results as paper
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import NORMALISATIONS, coverage_counts, score_from_counts
from place3d_app.commands.reproduce import paper_poses, resolve_town
from place3d_kernels.spec import PSOGSpec, SceneSpec

TOWNS = ("Town01", "Town03", "Town04", "Town06")


def _tau(a, b) -> float | None:
    t = kendalltau(a, b).statistic
    return None if not np.isfinite(t) else round(float(t), 4)


def _table(counts: dict, task: str) -> dict:
    out = {}
    for n in NORMALISATIONS:
        s = score_from_counts(counts, n)
        out[n] = {"scores": dict(zip(paper.PLACEMENTS, s.tolist())),
                  "tau_vs_paper_msog": _tau(s, paper.paper_msog(task)),
                  "tau_vs_downstream": _tau(s, paper.downstream(task))}
    out["entropy_share"] = dict(zip(paper.PLACEMENTS, (counts["n_uncertain"] / counts["n_covered"]).tolist()))
    out["n_covered"] = dict(zip(paper.PLACEMENTS, counts["n_covered"].tolist()))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl:pocl")
    ap.add_argument("--towns", default=",".join(TOWNS))
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--output", default="bench/results/normalisation-2026-11-24.json")
    args = ap.parse_args(argv)
    b = get_backend(args.backend)
    lidar = LidarModel.load("place3d_16ch")
    res = {"what": __doc__.split("\n\n")[0], "machine": f"dev VM 2-core ({platform.processor() or platform.machine()})",
           "backend": b.name, "route_seed": args.seed, "frames": args.frames, "voxel_size": "default (0.2 m)",
           "occlusion": "sog", "rig_lidar": lidar.name, "normalisations": list(NORMALISATIONS),
           "note": "single route per town (seed 0, 40 frames): per-route taus vary strongly with the route "
                   "(issue 13: sd 0.30-0.38 over seeds); read these as one sample, not a verdict",
           "towns": {}, "time_utc": None}
    pooled = {t: None for t in ("seg", "det")}
    for town in args.towns.split(","):
        t0 = time.perf_counter()
        spec = PSOGSpec(SceneSpec(resolve_town(town), seed=args.seed, frames=args.frames), backend=b.name)
        psog = spec.build(backend=b, cache=True)
        row = {"n_subsets": psog.n_subsets}
        for task in ("seg", "det"):
            c = coverage_counts(psog, lidar, paper_poses(task), task=task, backend=b)
            row[task] = _table(c, task)
            pooled[task] = c if pooled[task] is None else {k: pooled[task][k] + c[k] for k in c}
        row["seconds"] = round(time.perf_counter() - t0, 1)
        res["towns"][town] = row
        res["pooled_counts"] = {t: _table(c, t) for t, c in pooled.items()}
        res["time_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(json.dumps(res, indent=2))
        print(town, {t: {n: (row[t][n]["tau_vs_paper_msog"], row[t][n]["tau_vs_downstream"]) for n in NORMALISATIONS}
                     for t in ("seg", "det")}, f"{row['seconds']} s", flush=True)
    print("pooled", {t: {n: (v[n]["tau_vs_paper_msog"], v[n]["tau_vs_downstream"]) for n in NORMALISATIONS}
                     for t, v in res["pooled_counts"].items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
