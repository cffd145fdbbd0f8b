#!/usr/bin/env python3
"""The library's operations, one workload each, on every available backend: M-SOG of one rig and of a
population of 16 (``msog`` / ``msog_batch``), voxel traversal, ray-mesh on the town and on a 1M-triangle city,
BVH builds and the P-SOG build (``place3d_app.kernel_bench``, which ``place3d bench`` runs too). Writes
``bench/results/kernels-<label>-<date>.json`` and merges the run into ``bench/results/summary.json`` (one entry
per machine label).

    python3 bench/run_bench.py [--label cpu-2core-dev] [--backends warp:cpu reference] [--quick]

A summary.json run is ``{"machine": label, "device", "date", "backends": {...}, "peers": {...}}``. This
script writes ``machine``, ``device``, ``date`` and ``backends`` and keeps the run's ``peers``, which
``bench/peers.py`` measures and merges (open3d / embree / mitsuba ``raycast_mrays_s``, ``numpy_baseline``
``traverse_gsteps_s`` and rays/s). Run both with the same ``--label`` (default: the GPU model or
``cpu-<cores>core``; the dev VM's runs are ``cpu-2core-dev``), in either order. ``perf_table.py`` turns three
or more runs per machine into the README's table.

``--quick`` (no 1M-triangle city, so no ``raycast_mrays_s`` / ``city_*``) is a smoke run: it writes
``kernels-quick-<label>-<date>.json`` and leaves summary.json alone, whose runs carry the full set of keys.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from results_io import default_machine, results_path, write_result

from place3d_app.kernel_bench import run_kernel_bench

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--device", default="", help="free text naming the accelerator, e.g. 'NVIDIA H100'")
    ap.add_argument("--backends", nargs="*", default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    res = run_kernel_bench(args.backends, quick=args.quick)
    info = res["info"]
    label = args.label or default_machine()
    out = Path(args.out)
    res["info"]["label"] = label
    res["info"]["device"] = args.device or info["cpu"]
    res["info"]["quick"] = bool(args.quick)
    bench = "kernels-quick" if args.quick else "kernels"
    path = write_result(bench, res, label, path=results_path(bench, label, info["date"], out))
    if args.quick:
        print(f"wrote {path} (quick: summary.json not updated)")
        return
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {"runs": []}
    old = next((r for r in summary["runs"] if r.get("machine") == label), {})
    summary["runs"] = [r for r in summary["runs"] if r.get("machine") != label]
    summary["runs"].append({"machine": label, "device": res["info"]["device"], "date": info["date"],
                            "backends": res["backends"], "peers": old.get("peers", {})})  # peers: bench/peers.py
    summary_path.write_text(json.dumps(summary, indent=2))
    print(f"wrote {path} and {summary_path}")


if __name__ == "__main__":
    main()
