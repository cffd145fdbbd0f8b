#!/usr/bin/env python3
"""M-SOG (seg, det) and S-MIG side by side for the eleven paper placements on one scene.

    python3 bench/msog_vs_smig.py [--scene town | PATH.xodr] [--out bench/results/msog_vs_smig-<scene>.json]

S-MIG follows Hu et al. 2022 (Bernoulli occupancy from 3D boxes over the frames, rays cast to the ROI
boundary without occlusion, information gain = sum of covered voxels' entropy); M-SOG uses the default
"sog" occlusion. Prints a Markdown table with ranks.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import place3d_kernels as p3k


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="town")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scene = p3k.scene.town(seed=0) if args.scene == "town" else p3k.scene.from_opendrive(args.scene, seed=0)
    psog = p3k.scene_psog(scene)
    bern = p3k.BernoulliGrid.from_scene(scene, psog.grid)
    lidar = p3k.LidarModel.load("place3d_16ch")
    rows = []
    for name in p3k.PAPER_PLACEMENTS:
        pl = p3k.Placement.load(name)
        rows.append({"placement": name, "msog_seg": p3k.msog(psog, lidar, pl, task="seg"),
                     "msog_det": p3k.msog(psog, lidar, pl, task="det"),
                     "smig": p3k.smig(bern, lidar, pl, occlusion="none", reduce="sum")})
    rank = {k: {r["placement"]: i + 1 for i, r in enumerate(sorted(rows, key=lambda r: -r[k]))}
            for k in ("msog_seg", "msog_det", "smig")}
    label = Path(args.scene).stem
    print(f"| placement | M-SOG seg (rank) | M-SOG det (rank) | S-MIG (rank) |\n|---|---|---|---|")
    for r in rows:
        n = r["placement"]
        print(f"| {n} | {r['msog_seg']:.6f} ({rank['msog_seg'][n]}) | {r['msog_det']:.6f} ({rank['msog_det'][n]}) "
              f"| {r['smig']:.1f} ({rank['smig'][n]}) |")
    out = Path(args.out or Path(__file__).resolve().parent / "results" / f"msog_vs_smig-{label}.json")
    out.write_text(json.dumps({"scene": args.scene, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
