#!/usr/bin/env python3
"""``place3d reproduce`` end to end: wall time of the whole command, cold and warm.

    python3 bench/bench_reproduce.py [--backend opencl:pocl] [--runs 3] [--machine cpu-2core-dev]
    python3 bench/bench_reproduce.py --towns Town01 Town03 Town04 Town06 --routes 4 --frames 40

The command runs as the ``place3d`` console script runs it (``python -m place3d_app reproduce``), in a
subprocess, timed from start to exit. The default size (one town, two routes of 8 frames, no
convergence table) finishes in about 20 s on the 2-core dev VM; the second line above is the paper's size
(``docs/commands.md``). Cold: every run gets empty P-SOG and Warp kernel caches (``PLACE3D_CACHE``,
``WARP_CACHE_PATH``), so each drive is simulated and pooled; warm: one untimed run fills a pair of caches,
then each timed run reads them. Cold and warm runs alternate, ``--runs`` each.

Writes ``bench/results/reproduce-wall-<machine>-<date>.json`` (or ``$OUT``/``--out``): the walls of both (median,
min, max, every run), the command's own split (``seconds``: pool, bootstrap, total) of the last run of each,
and Kendall's tau against the paper per task, which must be the same in every run (``same_results``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from results_io import write_result

ROOT = Path(__file__).resolve().parents[1]


def stats(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def run_once(cmd: list[str], cache: Path, timeout: float) -> tuple[float, dict]:
    """(wall seconds, reproduce.json) of one run of ``cmd`` with its caches under ``cache``."""
    env = dict(os.environ, PLACE3D_CACHE=str(cache / "psog"), WARP_CACHE_PATH=str(cache / "warp"),
               PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    env.pop("PLACE3D_SERVER", None)
    with tempfile.TemporaryDirectory() as out:
        t = time.perf_counter()
        p = subprocess.run(cmd + ["--output", out], cwd=out, env=env, capture_output=True, text=True,
                           timeout=timeout)
        wall = time.perf_counter() - t
        if p.returncode:
            raise RuntimeError(f"{' '.join(cmd)} exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
        return wall, json.loads(Path(out, "reproduce.json").read_text())


def headline(res: dict) -> dict:
    """What must not change between runs: tau against the paper and the scores' order, per task."""
    return {t: {"tau_paper": r["tau_paper"], "rank": r["rank"]} for t, r in res["tasks"].items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--towns", nargs="+", default=["Town01"])
    ap.add_argument("--routes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--convergence", action="store_true", help="also the N vs 2N routes table (off by default)")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--runs", type=int, default=3, help="timed runs of each, cold and warm (default 3)")
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--out", default=None, help="folder (default $OUT, else bench/results/)")
    args = ap.parse_args(argv)
    cmd = [sys.executable, "-m", "place3d_app", "reproduce", "--towns", *args.towns, "--routes", str(args.routes),
           "--frames", str(args.frames), "--backend", args.backend, "--quiet"]
    if not args.convergence:
        cmd.append("--no-convergence")
    walls: dict[str, list[float]] = {"cold": [], "warm": []}
    last: dict[str, dict] = {}
    heads = []
    with tempfile.TemporaryDirectory() as warm_cache:
        run_once(cmd, Path(warm_cache), args.timeout)                 # fills the warm caches; not timed
        for i in range(args.runs):
            for kind in ("cold", "warm"):
                with tempfile.TemporaryDirectory() as cold_cache:
                    wall, res = run_once(cmd, Path(cold_cache if kind == "cold" else warm_cache), args.timeout)
                walls[kind].append(wall)
                last[kind] = res
                heads.append(headline(res))
                print(f"{kind} run {i + 1}: {wall:.2f} s (the command's own total {res['seconds']['total']:.2f} s)",
                      file=sys.stderr, flush=True)
    same = all(h == heads[0] for h in heads)
    record = {"command": "place3d " + " ".join(cmd[3:]) + " --output DIR", "settings": last["warm"]["settings"],
              "cold_s": stats(walls["cold"]), "warm_s": stats(walls["warm"]),
              "seconds_last_cold": last["cold"]["seconds"], "seconds_last_warm": last["warm"]["seconds"],
              "tau_paper": {t: r["tau_paper"] for t, r in last["warm"]["tasks"].items()}, "same_results": same,
              "note": "wall of the whole subprocess; cold and warm runs alternate after one untimed warm-up run"}
    path = write_result("reproduce-wall", record, args.machine, args.out)
    print(f"cold {record['cold_s']['median']:.2f} s, warm {record['warm_s']['median']:.2f} s (medians of "
          f"{args.runs}); same results: {same}; wrote {path}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
