#!/usr/bin/env python3
"""The README's performance table from repeated ``bench/run_bench.py`` runs: median [min-max] per cell.

Each argument is one run's JSON (``run_bench.py`` writes ``kernels-<label>-<date>.json``); give at least
three runs of each machine. Runs are grouped by the label given with ``--runs LABEL=FILE,FILE,...``; a
backend column is ``backend (LABEL)``. Writes the aggregate (every value, median, min, max, the files) as
JSON, ``bench/results/perf-table-<labels>-<date>.json`` unless ``--out`` names the file, and prints the
Markdown table.

    python3 bench/perf_table.py --runs dev=a.json,b.json,c.json --runs H100=d.json,e.json,f.json
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from results_io import write_result

#: (row title, metric keys) in table order; ray-mesh rows show API / kernel
ROWS = [
    ("M-SOG, paper rig (4 x 16 x 250 rays), default grid, ms", ("placement_eval_ms",)),
    ("batched population of 16 rigs, ms", ("population16_eval_ms",)),
    ("ray-mesh, town, 64 x 1024 rays, M rays/s (API / kernel)",
     ("raycast_town_mrays_s", "raycast_town_kernel_mrays_s")),
    ("ray-mesh, 1M-triangle city, 4 x 64 x 2048 rays, M rays/s (API / kernel)",
     ("raycast_mrays_s", "raycast_kernel_mrays_s")),
    ("BVH build, 1M-triangle city, s", ("city_bvh_build_s",)),
    ("P-SOG build from 8 frames (vote), s", ("psog_build_s",)),
    ("voxel traversal, kernel only, G steps/s", ("traverse_kernel_gsteps_s",)),
]


def num(x: float) -> str:
    """A figure with about three significant digits, thousands separated (no exponent)."""
    x = float(x)
    if abs(x) >= 100:
        return f"{x:,.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    return f"{x:.3g}"


def stats(xs):
    xs = [float(x) for x in xs]
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def aggregate(groups: dict[str, list[Path]]) -> dict:
    """{column: {metric: stats}} with column = "backend (label)"."""
    out = {}
    for label, files in groups.items():
        runs = [json.loads(Path(f).read_text()) for f in files]
        backends = sorted({b for r in runs for b in r["backends"]}, key=lambda b: list(runs[0]["backends"]).index(b)
                          if b in runs[0]["backends"] else 99)
        for b in backends:
            col = {}
            keys = {k for r in runs for k in r["backends"].get(b, {})}
            for k in sorted(keys):
                vals = [r["backends"][b][k] for r in runs if b in r["backends"] and k in r["backends"][b]]
                if vals and all(isinstance(v, (int, float)) for v in vals):
                    col[k] = stats(vals)
            out[f"{b} ({label})"] = {"files": [str(f) for f in files], "n_runs": len(runs), "metrics": col}
    return out


def cell(col: dict, keys) -> str:
    parts = []
    for k in keys:
        s = col["metrics"].get(k)
        if s is None:
            return "-"
        med = num(s["median"])
        txt = med if s["min"] == s["max"] else f"{med} [{num(s['min'])}-{num(s['max'])}]"
        parts.append(txt if len(s["runs"]) >= 3 else f"{txt} (n={len(s['runs'])})")   # too few runs: say so
    return " / ".join(parts)


def table(agg: dict) -> str:
    cols = list(agg)
    lines = ["| workload | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for title, keys in ROWS:
        lines.append(f"| {title} | " + " | ".join(cell(agg[c], keys) for c in cols) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", action="append", required=True, metavar="LABEL=FILE,FILE,...")
    ap.add_argument("--out", default=None, help="aggregate JSON to write (default bench/results/perf-table-...)")
    args = ap.parse_args(argv)
    groups = {}
    for spec in args.runs:
        label, _, files = spec.partition("=")
        groups[label] = [Path(f) for f in files.split(",") if f]
        if len(groups[label]) < 3:
            print(f"warning: {label} has {len(groups[label])} run(s); a README figure needs at least three")
    agg = aggregate(groups)
    md = table(agg)
    print(md)
    print("wrote", write_result("perf-table", {"columns": agg, "markdown": md}, "+".join(groups), path=args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
