"""ROI size study: `place3d reproduce` for a few ROI boxes x voxel sizes, summarised in one JSON.

Each cell runs the command a user would (`python -m place3d_app reproduce --route-seeds ... --roi ...
--voxel-size ... --no-convergence`: the pooled P-SOG of every town x route, the jackknife over routes,
Kendall tau; `--convergence` keeps reproduce's N vs 2N table) in a process of its own, and keeps its
reproduce.json, reproduce.png and log under OUT/runs/<roi>-<voxel>/. The summary, OUT/roi-study.json,
takes from each reproduce.json the fields the grid study reported (docs/assumptions.md, section 1): the
best and worst M-SOG of the paper's eight placements, the worst/best ratio beside the paper's (Table 1),
tau against the paper's M-SOG and downstream results with their leave-one-route-out ranges (computed by
`place3d reproduce`, never here), the grid's shape and voxel count, and the cell's wall seconds.

A cell whose reproduce.json is already in OUT/runs/ with the same settings is read, not run again, so a
run cut short by a time limit goes on where it stopped (give an --out that outlives the call and copy it
at the end). The P-SOG cache (--cache, default /tmp/place3d-roi-cache) stays outside OUT: its files are
large.

GPU host (the lead's run; ../shared/gpu/README.md), in two calls of under 10 minutes each:
    source /tmp/gpu-env.sh && python3 bench/roi_study.py --backend warp:cuda:0 --voxels 0.2 --out /tmp/roi
    source /tmp/gpu-env.sh && python3 bench/roi_study.py --backend warp:cuda:0 --out /tmp/roi && cp -r /tmp/roi $OUT/
Dev VM, a tiny check:
    PYTHONPATH=. python3 bench/roi_study.py --backend opencl:pocl --towns Town01 Town03 --route-seeds 100-101 \
        --frames 8 --voxels 0.2 --rois default 40x40x5 --out /tmp/roi-tiny
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

#: The boxes studied by default (ego frame, metres): the package's default; half its width; the standard
#: nuScenes detection range ([-54, 54] x [-54, 54] x [-5, 3] m in the LIDAR_TOP frame, mmdetection3d's
#: CenterPoint 0.075 m configs) moved to the ego frame by the authors' LIDAR_TOP height of 1.8 m
#: (ywyeli/Place3D, nus_tool/position_3d.py); and the default footprint twice as tall.
ROIS = {"default": None, "40x40x5": (40.0, 40.0, 5.0), "nuscenes-det": (-54.0, -54.0, -3.2, 54.0, 54.0, 4.8),
        "80x80x10": (80.0, 80.0, 10.0)}
VOXELS = (0.2, 0.1)
TASKS = ("seg", "det")


def parse_roi(text: str):
    """A named ROI of ``ROIS``, ``LXxLYxLZ`` (sizes) or ``X0,Y0,Z0,X1,Y1,Z1`` (corners) -> (label, numbers)."""
    if text in ROIS:
        return text, ROIS[text]
    sep = "x" if "x" in text else ","
    try:
        nums = tuple(float(v) for v in text.split(sep))
    except ValueError:
        raise SystemExit(f"--rois: {text!r} is not one of {sorted(ROIS)}, LXxLYxLZ or X0,Y0,Z0,X1,Y1,Z1") from None
    return text, nums


def cell_label(roi_label: str, voxel: float) -> str:
    return f"{roi_label}-{voxel:g}m".replace(",", "_")


def reproduce_argv(args, roi, voxel: float, out: Path) -> list:
    """The `place3d reproduce` command line of one cell."""
    argv = [sys.executable, "-m", "place3d_app", "reproduce", "--towns", *args.towns, "--route-seeds",
            args.route_seeds, "--frames", str(args.frames), "--voxel-size", f"{voxel:g}", "--backend", args.backend,
            "--output", str(out)]
    if roi is not None:
        argv += ["--roi", *(f"{v:g}" for v in roi)]
    if not args.convergence:
        argv.append("--no-convergence")
    return argv


def _same_settings(res: dict, args, roi, voxel: float) -> bool:
    s = res.get("settings", {})
    return (s.get("towns") == list(args.towns) and s.get("frames") == args.frames and s.get("backend") == args.backend
            and math.isclose(s.get("voxel_size", -1), voxel) and s.get("roi") == (None if roi is None else list(roi))
            and _seeds_text(s.get("route_seeds", [])) == args.route_seeds_norm)


def _seeds_text(seeds) -> str:
    return ",".join(str(int(s)) for s in seeds)


def summarise_cell(res: dict, label: str, roi, wall_s: float | None) -> dict:
    """One summary row from a reproduce.json (``res``): the grid, the paper's eight placements' range and
    spread per task, reproduce's own taus and their leave-one-route-out ranges, the seconds."""
    from place3d_kernels import paper_results as paper

    grid = res["settings"]["grid"]
    row = {"cell": label, "roi": None if roi is None else list(roi), "voxel_size": res["settings"]["voxel_size"],
           "grid": grid, "n_voxels": int(math.prod(grid["shape"])),
           "box_m": [round(u - lo, 6) for lo, u in zip(grid["lower"], grid["upper"])],
           "wall_s": None if wall_s is None else round(wall_s, 2), "reproduce_seconds": res.get("seconds"),
           "n_subsets_total": res["settings"].get("n_subsets_total"), "drives": len(res.get("drives", []))}
    for task in TASKS:
        t = res["tasks"][task]
        names, msog = t["placements"][:8], t["msog"][:8]          # the paper's eight come first
        best, worst = max(range(8), key=lambda i: msog[i]), min(range(8), key=lambda i: msog[i])
        ref = paper.paper_msog(task)
        row[task] = {"msog_best": msog[best], "msog_worst": msog[worst], "best": names[best], "worst": names[worst],
                     # M-SOG is negative: worst/best > 1 measures the spread, as Table 1's -3.13 / -1.29 = 2.4
                     "worst_best_ratio": msog[worst] / msog[best] if msog[best] else None,
                     "paper_worst_best_ratio": min(ref) / max(ref),
                     "tau_paper": t["tau_paper"], "tau_paper_loo_range": t["tau_paper_loo_range"],
                     "tau_downstream": t["tau_downstream"], "tau_downstream_loo_range": t["tau_downstream_loo_range"],
                     "rank": t["rank"][:8], "within_noise": t.get("within_noise")}
    return row


def summarise(cells: list, args_dict: dict) -> dict:
    """The study's one JSON: settings, the machine of the first cell, and one row per cell."""
    rows = [summarise_cell(res, label, roi, wall) for label, roi, res, wall in cells]
    first = cells[0][2] if cells else {}
    return {"study": "roi", "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "settings": args_dict, "machine": first.get("machine"),
            "note": "tau and its ranges are place3d reproduce's own (reproduce.json); worst/best is over the "
                    "paper's eight placements; wall_s is the whole command (P-SOGs built fresh per cell: a new "
                    "ROI or voxel size is a new cache key)",
            "rows": rows, "total_wall_s": round(sum(r["wall_s"] or 0.0 for r in rows), 2)}


def _warm_up(args, env) -> None:
    """One small untimed run, so the first cell does not pay for building the backend's kernels."""
    argv = [sys.executable, "-m", "place3d_app", "reproduce", "--towns", args.towns[0], "--route-seeds", "0-1",
            "--frames", "8", "--backend", args.backend, "--no-convergence", "--quiet", "--output",
            str(Path(env["PLACE3D_CACHE"]) / "warmup")]
    subprocess.run(argv, env=env, capture_output=True, text=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", required=True, help="e.g. warp:cuda:0 (the lead's H100), opencl:pocl, warp:cpu")
    ap.add_argument("--out", default=os.environ.get("OUT") or "bench/results/roi-study",
                    help="folder of roi-study.json and runs/ (default $OUT)")
    ap.add_argument("--rois", nargs="+", default=list(ROIS),
                    help=f"boxes: names {sorted(ROIS)}, LXxLYxLZ or X0,Y0,Z0,X1,Y1,Z1 (default: all named)")
    ap.add_argument("--voxels", nargs="+", type=float, default=list(VOXELS), help="voxel sizes, m (default 0.2 0.1)")
    ap.add_argument("--towns", nargs="+", default=["Town01", "Town03", "Town04", "Town06"])
    ap.add_argument("--route-seeds", default="100-103", help="route seeds (default 100-103)")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--convergence", action="store_true",
                    help="also the N vs 2N routes table (reproduce's default; off here: the summary does not use it)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up run")
    ap.add_argument("--cache", default="/tmp/place3d-roi-cache", help="P-SOG cache folder (outside --out)")
    args = ap.parse_args(argv)
    from place3d_kernels.pooled import parse_route_seeds

    args.route_seeds_norm = _seeds_text(parse_route_seeds(args.route_seeds))
    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PLACE3D_CACHE=args.cache)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1])]
                                        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    rois = [parse_roi(r) for r in args.rois]
    warmed = args.no_warmup
    cells = []
    for voxel in args.voxels:
        for label, roi in rois:
            cell = cell_label(label, voxel)
            folder = out / "runs" / cell
            js, wall_file = folder / "reproduce.json", folder / "wall.json"
            if js.exists() and wall_file.exists():
                res = json.loads(js.read_text())
                if _same_settings(res, args, roi, voxel):
                    print(f"{cell}: kept from an earlier run", file=sys.stderr)
                    cells.append((cell, roi, res, json.loads(wall_file.read_text())["wall_s"]))
                    continue
            if not warmed:
                _warm_up(args, env)
                warmed = True
            folder.mkdir(parents=True, exist_ok=True)
            t = time.perf_counter()
            r = subprocess.run(reproduce_argv(args, roi, voxel, folder), env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t
            (folder / f"{cell}.log").write_text(r.stdout + r.stderr)
            if r.returncode != 0:
                print(f"{cell}: reproduce failed (exit {r.returncode}); see {folder / (cell + '.log')}:\n"
                      f"{r.stderr[-2000:]}", file=sys.stderr)
                return 1
            wall_file.write_text(json.dumps({"wall_s": wall}))
            res = json.loads(js.read_text())
            cells.append((cell, roi, res, wall))
            print(f"{cell}: {wall:.1f} s, grid {res['settings']['grid']['shape']}", file=sys.stderr)
            # the summary after every cell: a run cut short keeps what it finished
            _write(out, summarise(cells, _settings(args, rois)))
    _write(out, summarise(cells, _settings(args, rois)))
    print(f"wrote {out / 'roi-study.json'}", file=sys.stderr)
    return 0


def _settings(args, rois) -> dict:
    return {"backend": args.backend, "towns": list(args.towns), "route_seeds": args.route_seeds,
            "frames": args.frames, "voxels": list(args.voxels), "convergence": args.convergence,
            "rois": {label: None if roi is None else list(roi) for label, roi in rois}}


def _write(out: Path, summary: dict) -> None:
    from place3d_kernels.atomic import atomic_write_text

    atomic_write_text(out / "roi-study.json", json.dumps(summary, indent=1))


if __name__ == "__main__":
    sys.exit(main())
