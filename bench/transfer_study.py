"""Do the optimiser's winners transfer? Search on training routes, rank the winner on held-out P-SOGs.

For every training town x seed x objective (M-SOG normalisation) this runs ``place3d optimize`` on the
P-SOG pooled over the town's routes seed .. seed+3 and re-scores the winner and the paper's placements on
P-SOGs pooled over routes the search never saw (--holdout-seeds, default 100-103) of every town in
--holdout-towns. It reports, per objective, the winner's rank among the 9 rigs (itself and the paper's
eight baselines) on each held-out P-SOG, judged by the objective it optimised and by the other two
(issue 34, item 4; docs/metric-normalisation.md has the reading).

    python3 bench/transfer_study.py --backend warp:cuda:0 --out bench/results/transfer-<date>

Cells made by the same optimize command (``argv.json``) are read, not rerun (a second call resumes). Writes results.json,
table.csv, transfer.png and the winners' placement TOMLs (winners/<objective>-<town>-s<seed>.toml).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import platform
import shutil
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

NORMS = ("paper", "evidence", "uncertain")


def run_cell(town, seed, objective, args, cell: Path) -> dict:
    from place3d_app.cli import main

    res, made_by = cell / "result.json", cell / "argv.json"
    argv = ["optimize", "--scene", f"opendrive:{town}", "--seed", str(seed), "--routes", str(args.routes),
            "--frames", str(args.frames), "--normalisation", objective, "--holdout-scenes", args.holdout_towns,
            "--holdout-seeds", args.holdout_seeds, "--interval", "none", "--max-evals", str(args.max_evals),
            "--quiet", "--overwrite", "--output", str(cell)] + (["--backend", args.backend] if args.backend else [])
    # a cell is reused only when the command that made it is this one (every option, the backend included)
    if not (res.exists() and made_by.exists() and json.loads(made_by.read_text()) == argv):
        t0 = time.perf_counter()
        rc = main(argv)
        if rc != 0:
            raise SystemExit(f"optimize failed (exit {rc}) for {town} seed {seed} {objective}")
        (cell / "wall.txt").write_text(f"{time.perf_counter() - t0:.2f}\n")
        made_by.write_text(json.dumps(argv))
    r = json.loads(res.read_text())
    wall = float((cell / "wall.txt").read_text()) if (cell / "wall.txt").exists() else None
    return {"town": town, "seed": seed, "objective": objective, "wall_s": wall,
            "train_score": r["best_score"], "train_baselines": r["baseline_scores"],
            "on_bounds": r["diagnostics"]["n_on_bounds"] if r.get("diagnostics") else None,
            "transfers": r["transfer"]["transfers"],
            "heldout": [{"scene": Path(h["scene"].split(":", 1)[-1]).stem, "seeds": h["seeds"], "rank": h["rank"],
                         "ranks": h["ranks"], "n_rigs": h["n_rigs"]} for h in r["holdout"]],
            "winner": r["best_placement"], "toml": str(cell / "optimized-seg.toml")}


def summarise(cells: list[dict]) -> dict:
    """Per objective: the winners' held-out ranks judged by each normalisation (median, share first)."""
    out = {}
    for obj in dict.fromkeys(c["objective"] for c in cells):
        mine = [c for c in cells if c["objective"] == obj]
        row = {"runs": len(mine), "runs_that_transfer": sum(bool(c["transfers"]) for c in mine)}
        for judge in NORMS:
            ranks = [h["ranks"][judge] for c in mine for h in c["heldout"] if h["ranks"][judge] is not None]
            row[f"median_rank_by_{judge}"] = float(np.median(ranks)) if ranks else None
            row[f"first_share_by_{judge}"] = float(np.mean([r == 1 for r in ranks])) if ranks else None
            row[f"ranks_by_{judge}"] = ranks
        out[obj] = row
    return out


def plot(cells, summary, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objs = list(summary)
    fig, axes = plt.subplots(1, len(NORMS), figsize=(4 * len(NORMS), 3.6), sharey=True)
    n_rigs = max(h["n_rigs"] for c in cells for h in c["heldout"])
    for ax, judge in zip(axes, NORMS):
        for i, obj in enumerate(objs):
            r = summary[obj][f"ranks_by_{judge}"]
            jitter = np.random.default_rng(i).uniform(-0.15, 0.15, len(r))
            ax.plot(np.full(len(r), i) + jitter, r, "o", alpha=0.5, ms=4)
            ax.plot([i - 0.3, i + 0.3], [np.median(r)] * 2, "k-", lw=2)
        ax.set_xticks(range(len(objs)))
        ax.set_xticklabels([f"optimised\n{o}" for o in objs])
        ax.set_title(f"judged by M-SOG ({judge})")
        ax.set_ylim(n_rigs + 0.5, 0.5)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel(f"held-out rank of the winner\n(1 = best of {n_rigs} rigs)")
    fig.suptitle("Do the optimiser's winners transfer? (dots: held-out P-SOGs x runs; bar: median)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--towns", default="Town01,Town06", help="training towns")
    p.add_argument("--seeds", default="0,10,20", help="first training route seed of each run (routes seed..seed+3)")
    p.add_argument("--objectives", default=",".join(NORMS))
    p.add_argument("--routes", type=int, default=4)
    p.add_argument("--holdout-towns", default="Town01,Town03,Town04,Town06")
    p.add_argument("--holdout-seeds", default="100-103")
    p.add_argument("--frames", type=int, default=40, help="frames per route (default 40, as the paper)")
    p.add_argument("--max-evals", type=int, default=2000)
    p.add_argument("--backend", default=None)
    p.add_argument("--out", default=f"bench/results/transfer-{datetime.now(timezone.utc).date().isoformat()}")
    p.add_argument("--replot", action="store_true", help="only redraw transfer.png from --out's results.json")
    args = p.parse_args(argv)
    out = Path(args.out)
    if args.replot:
        res = json.loads((out / "results.json").read_text())
        plot(res["cells"], res["summary"], out / "transfer.png")
        return 0
    (out / "cells").mkdir(parents=True, exist_ok=True)
    (out / "winners").mkdir(exist_ok=True)
    t0 = time.perf_counter()
    cells = []
    grid = [(t, int(s), o) for t in args.towns.split(",") for s in args.seeds.split(",") for o in args.objectives.split(",")]
    for i, (town, seed, obj) in enumerate(grid):
        cell = run_cell(town, seed, obj, args, out / "cells" / f"{obj}-{town}-s{seed}")
        shutil.copyfile(cell["toml"], out / "winners" / f"{obj}-{town}-s{seed}.toml")
        cells.append(cell)
        ranks = ", ".join(f"{h['scene']} {h['rank']}" for h in cell["heldout"])
        print(f"[{i + 1}/{len(grid)}] {obj:9s} {town} seed {seed}: held-out ranks {ranks} of "
              f"{cell['heldout'][0]['n_rigs']}; transfers {cell['transfers']}", flush=True)
    summary = summarise(cells)
    import place3d_kernels

    machine = {"host": platform.node(), "cpu": platform.processor() or platform.machine(),
               "python": sys.version.split()[0], "place3d_kernels": place3d_kernels.__version__}
    try:
        import warp as wp

        wp.init()
        machine["gpu"] = [wp.get_device(d).name for d in wp.get_cuda_devices()] if wp.get_cuda_device_count() else []
    except Exception:               # no Warp CUDA here: the CPU backends ran it
        pass
    res = {"settings": vars(args), "machine": machine, "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "seconds": round(time.perf_counter() - t0, 1), "summary": summary, "cells": cells}
    (out / "results.json").write_text(json.dumps(res, indent=1, default=float))
    fh = io.StringIO(newline="")
    w = csv.writer(fh)
    w.writerow(["objective", "runs", "runs_that_transfer", *[f"median_rank_by_{j}" for j in NORMS],
                *[f"first_share_by_{j}" for j in NORMS]])
    for obj, row in summary.items():
        w.writerow([obj, row["runs"], row["runs_that_transfer"], *[row[f"median_rank_by_{j}"] for j in NORMS],
                    *[None if row[f"first_share_by_{j}"] is None else round(row[f"first_share_by_{j}"], 3) for j in NORMS]])
    (out / "table.csv").write_text(fh.getvalue())
    plot(cells, summary, out / "transfer.png")
    print(fh.getvalue())
    print(f"{len(cells)} runs in {res['seconds']} s; wrote {out}/results.json, table.csv, transfer.png, winners/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
