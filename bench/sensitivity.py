"""Sensitivity of the paper-placement order to each choice the paper leaves open (docs/assumptions.md).

One modest pooled P-SOG per setting (default 4 CARLA towns x 2 routes x 40 frames), the eight placements
of the paper's Table 1 scored for seg and det, Kendall tau against the paper's M-SOG order and against
its downstream results (``place3d_kernels.paper_results``), each with a bootstrap interval over routes
(resampled within towns). One alternative at a time against the package's defaults:

    voxel 0.1 / 0.4 m, occlusion none, k = 2 / 8 frames per subset, roll read as degrees,
    collection LiDAR = the paper's 16-channel sensor, detection classes vehicle + pedestrian, the rigs'
    LiDAR = the authors' public CARLA 16-channel settings (two units), the five heuristic baselines at the
    authors' public CARLA positions.

Run: ``PYTHONPATH=. python3 bench/sensitivity.py [--routes 2] [--resamples 30] [--only base voxel-0.1]``
Writes ``bench/results/sensitivity-<date>.json``. P-SOGs are cached in ``$PLACE3D_CACHE``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from place3d_kernels import paper_results as paper
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.lidar import LidarModel
from place3d_kernels.pooled import Drive, PoolSettings, build_pooled
from place3d_app.commands.reproduce import DEFAULT_TOWNS, machine_info, resolve_town
from place3d_kernels.uncertainty import bootstrap_pooled, kendall_tau

BASE = {"voxel_size": 0.2, "occlusion": "sog", "k": 4, "roll_units": "rad", "collection": "collection_64ch",
        "det_variant": "vehicle", "rig_lidar": "place3d_16ch", "baselines": "paper"}
#: (name, the one setting that differs from BASE, what it tests)
ALTERNATIVES = [
    ("base", {}, "the package's defaults"),
    ("voxel-0.1", {"voxel_size": 0.1}, "finer voxels"),
    ("voxel-0.4", {"voxel_size": 0.4}, "coarser voxels"),
    ("occlusion-none", {"occlusion": "none"}, "rays cast to full range through occupied voxels (S-MIG's rule)"),
    ("k-2", {"k": 2}, "2 frames per SOG (T = 20 per drive)"),
    ("k-8", {"k": 8}, "8 frames per SOG (T = 5 per drive)"),
    ("roll-deg", {"roll_units": "deg"}, "the placements' roll values read as degrees (CARLA's unit)"),
    ("collection-16ch", {"collection": "place3d_16ch"}, "P-SOG recorded with the paper's 16-channel LiDAR"),
    ("det-vehicle+pedestrian", {"det_variant": "vehicle+pedestrian"}, "detection P-SOG keeps pedestrians too"),
    ("rig-16ch-carla", {"rig_lidar": "place3d_16ch_carla"},
     "rigs scored with the authors' public CARLA 16-channel settings (-25..+5 deg, 720 steps, 200 m)"),
    ("rig-16ch-carla-narrow", {"rig_lidar": "place3d_16ch_carla_narrow"},
     "rigs scored with the authors' narrower public unit (-14..+2 deg, 720 steps, 200 m)"),
    ("baselines-carla-public", {"baselines": "carla_public"},
     "the five heuristic baselines at the authors' public CARLA positions (carla_public/*)"),
]


def scorer(s: dict, backend):
    """score(psog) -> (16,) seg then det scores of the eight placements, as reproduce.placement_scorer, with
    the rig LiDAR of ``s`` and, for ``baselines = carla_public``, the five heuristic baselines replaced by
    the authors' public rigs (the roll rigs and "ours" have no public counterpart)."""
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import Placement
    from place3d_app.commands.reproduce import det_view, paper_poses

    lidar = LidarModel.load(s["rig_lidar"])
    poses = {t: paper_poses(t, s["roll_units"]) for t in ("seg", "det")}
    if s["baselines"] == "carla_public":
        for t in poses:
            for j, name in enumerate(paper.PLACEMENTS[:5]):
                poses[t][j] = Placement.load(f"carla_public/{name}").poses
    elif s["baselines"] != "paper":
        raise ValueError(f"baselines must be 'paper' or 'carla_public', got {s['baselines']!r}")

    def score(psog):
        seg = msog_batch(psog, lidar, poses["seg"], occlusion=s["occlusion"], task="seg", backend=backend)
        det = msog_batch(det_view(psog, s["det_variant"]), lidar, poses["det"], occlusion=s["occlusion"],
                         task="seg", backend=backend)
        return np.concatenate([seg, det])

    return score


def run_one(name, change, towns, routes, frames, resamples, backend, progress) -> dict:
    s = {**BASE, **change}
    scenes = [resolve_town(t) for t in towns]
    drives, town_of = [], []
    for r in range(routes):
        for i, sc in enumerate(scenes):
            drives.append(Drive(sc, seed=r, frames=frames))
            town_of.append(i)
    t0 = time.perf_counter()
    pooled = build_pooled(drives, PoolSettings(s["voxel_size"], s["collection"], s["k"], backend), progress=progress)
    t_pool = time.perf_counter() - t0
    score = scorer(s, backend)
    t0 = time.perf_counter()
    point, samples, _ = bootstrap_pooled(pooled, score, resamples, seed=0, strata=town_of)
    t_boot = time.perf_counter() - t0
    row = {"name": name, "settings": s, "pool_seconds": round(t_pool, 2), "bootstrap_seconds": round(t_boot, 2),
           "n_drives": len(drives), "n_subsets": pooled.n_subsets}
    for i, task in enumerate(("seg", "det")):
        pt, sm = point[i * 8:(i + 1) * 8], samples[:, i * 8:(i + 1) * 8]
        for ref_name, ref in (("paper", paper.paper_msog(task)), ("downstream", paper.downstream(task))):
            taus = np.array([kendall_tau(x, ref) for x in sm])
            row[f"tau_{task}_{ref_name}"] = kendall_tau(pt, ref)
            row[f"tau_{task}_{ref_name}_ci"] = [float(v) for v in np.nanquantile(taus, [0.025, 0.975])]
        row[f"{task}_msog"] = pt.tolist()
        row[f"{task}_order"] = [paper.PLACEMENTS[j] for j in np.argsort(-pt, kind="stable")]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--towns", nargs="+", default=list(DEFAULT_TOWNS))
    ap.add_argument("--routes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--resamples", type=int, default=30)
    ap.add_argument("--only", nargs="*", default=None, help="alternatives to run (default all)")
    ap.add_argument("--backend", default=None)
    ap.add_argument("--output", default=None)
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    b = get_backend(a.backend)
    rows = []
    t0 = time.perf_counter()
    for name, change, why in ALTERNATIVES:
        if a.only and name not in a.only:
            continue
        r = run_one(name, change, a.towns, a.routes, a.frames, a.resamples, b.name, not a.quiet)
        r["what"] = why
        rows.append(r)
        print(f"{name:24s} seg tau paper {r['tau_seg_paper']:+.3f} downstream {r['tau_seg_downstream']:+.3f} | det "
              f"tau paper {r['tau_det_paper']:+.3f} downstream {r['tau_det_downstream']:+.3f}  "
              f"(pool {r['pool_seconds']:.0f} s, bootstrap {r['bootstrap_seconds']:.0f} s)", flush=True)
    date = datetime.now(timezone.utc).date().isoformat()
    out = Path(a.output or f"bench/results/sensitivity-{date}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    res = {"settings": {"towns": a.towns, "routes": a.routes, "frames": a.frames, "resamples": a.resamples,
                        "rig_lidar": "place3d_16ch", "base": BASE,
                        "bootstrap": "routes resampled with replacement within each town; 95 % percentile interval"},
           "machine": machine_info(b.name), "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "seconds": round(time.perf_counter() - t0, 1),
           "paper_tau_msog_vs_downstream": {t: kendall_tau(paper.paper_msog(t), paper.downstream(t))
                                            for t in ("seg", "det")},
           "rows": rows}
    if a.only and out.exists():                 # a partial rerun updates its rows, keeps the others
        old = json.loads(out.read_text())
        keep = [r for r in old.get("rows", []) if r["name"] not in {x["name"] for x in rows}]
        res["rows"] = keep + rows
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
