#!/usr/bin/env python3
"""``place3d reproduce`` with its pooled P-SOGs built from scratch: wall, pool and total, trees alternating.

    python3 bench/bench_pool.py --routes 2 --runs 3 --tree /tmp/before --tree .        # A/B on one machine
    python3 bench/bench_pool.py --routes 8 --backend warp:cuda:0 --runs 3              # the GPU host (gpu_reproduce.sh)
    python3 bench/bench_pool.py --executors local process                             # executors alternating
    python3 bench/bench_pool.py --tree .:PLACE3D_WORKERS=8 --tree .                   # a setting against none

Each run is the command as the ``place3d`` console script runs it (``python -m place3d_app reproduce``), in a
subprocess with the tree first on ``PYTHONPATH``, timed from start to exit, with an empty P-SOG cache
(``PLACE3D_CACHE``), so every drive is simulated and pooled, and a Warp kernel cache shared by the runs of a
tree, filled by one untimed small run first (issue 36's goal is stated with a warm kernel cache). Runs of
the variants (each tree, with each of ``--executors``) alternate. The command's own split (``seconds``: pool, jackknife, total) comes from its
``reproduce.json`` (and ``convergence``, what the command still spent on that table after the jackknife, where the
checkout records it); every run's study numbers (``tasks``, ``convergence``: scores, intervals, taus) must be
the same to the last digit across runs and variants (``same_results``; an A/B that changes them on purpose reads
``same_results_within_variant``).

Writes ``bench/results/reproduce-pool-<machine>-<date>.json`` (or ``$OUT`` / ``--out``), rewritten after every
run so a run cut short by a time limit keeps the runs before it.
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

from results_io import results_path, run_info, write_result

ROOT = Path(__file__).resolve().parents[1]


def stats(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs} if xs else {}


def run_once(tree: Path, args: list[str], psog_cache: Path, warp_cache: Path, timeout: float,
             extra_env: dict | None = None) -> tuple[float, dict]:
    env = dict(os.environ, PLACE3D_CACHE=str(psog_cache), WARP_CACHE_PATH=str(warp_cache),
               PYTHONPATH=os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p),
               **(extra_env or {}))
    env.pop("PLACE3D_SERVER", None)
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "place3d_app", "reproduce", *args, "--quiet", "--output", out]
        t = time.perf_counter()
        p = subprocess.run(cmd, cwd=out, env=env, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t
        if p.returncode:
            raise RuntimeError(f"{' '.join(cmd)} in {tree} exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
        return wall, json.loads(Path(out, "reproduce.json").read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", default=None,
                    help="a checkout to time (repeat for an A/B; default: this one); TREE:NAME=VALUE,... runs it with "
                         "those environment settings (cold_profile.parse_tree)")
    ap.add_argument("--towns", nargs="+", default=["Town01", "Town03", "Town04", "Town06"])
    ap.add_argument("--routes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--resamples", type=int, default=None, help="only for checkouts whose reproduce still bootstraps")
    ap.add_argument("--voxel-size", type=float, default=None, help="the command's --voxel-size (default: its own)")
    ap.add_argument("--no-convergence", action="store_true")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--executors", nargs="+", default=[None],
                    help="--executor values to alternate (default: the command's own default)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--label", default="", help="appended to the file name (e.g. 'before-after')")
    ap.add_argument("--out", default=None, help="folder (default $OUT, else bench/results/)")
    a = ap.parse_args(argv)
    from cold_profile import parse_tree

    parsed = [parse_tree(t) for t in (a.tree or [str(ROOT)])]     # (label, tree, environment settings)
    trees = [str(t) + ("" if not env else label[len(t.name):]) for label, t, env in parsed]
    tree_of = {k: (t, env) for k, (_, t, env) in zip(trees, parsed)}
    cmd = ["--towns", *a.towns, "--routes", str(a.routes), "--frames", str(a.frames), "--backend", a.backend]
    if a.resamples is not None:
        cmd += ["--resamples", str(a.resamples)]
    if a.voxel_size is not None:
        cmd += ["--voxel-size", str(a.voxel_size)]
    if a.no_convergence:
        cmd.append("--no-convergence")
    info = run_info(a.machine)
    name = "reproduce-pool" + (f"-{a.label}" if a.label else "")
    path = results_path(name, info["machine"], info["date"], a.out)
    variants = [(t, e) for t in trees for e in a.executors]

    def vname(t, e):
        return t + ("" if e is None else f" --executor {e}")

    per: dict[str, dict] = {vname(t, e): {"wall_s": [], "pool_s": [], "jackknife_s": [], "convergence_s": [],
                                          "total_s": [], "executor": None} for t, e in variants}
    studies: list[dict] = []
    by_variant: dict[str, list[dict]] = {k: [] for k in per}     # each variant's studies, for A/Bs that change them
    with tempfile.TemporaryDirectory() as scratch:
        warp = {t: Path(scratch, f"warp{i}") for i, t in enumerate(trees)}
        for t in trees:         # kernels compiled into each tree's cache, untimed
            with tempfile.TemporaryDirectory() as c:
                run_once(tree_of[t][0], ["--towns", "town", "--routes", "2", "--frames", "2",
                                         "--no-convergence", "--backend", a.backend], Path(c), warp[t], a.timeout,
                         tree_of[t][1])
        for i in range(a.runs):
            for t, e in (variants if i % 2 == 0 else variants[::-1]):     # A B, B A, ...: no order bias
                with tempfile.TemporaryDirectory() as c:
                    wall, res = run_once(tree_of[t][0], cmd + ([] if e is None else ["--executor", e]), Path(c),
                                         warp[t], a.timeout, tree_of[t][1])
                r = per[vname(t, e)]
                r["wall_s"].append(round(wall, 3))
                for k in ("pool", "jackknife", "convergence", "total"):
                    if k in res["seconds"]:         # convergence: checkouts from issue 36 on
                        r[f"{k}_s"].append(res["seconds"][k])
                r["executor"] = res["settings"].get("executor")
                studies.append({"tasks": {k: {f: v for f, v in d.items()} for k, d in res["tasks"].items()},
                                "convergence": res["convergence"]})
                by_variant[vname(t, e)].append(studies[-1])
                print(f"run {i + 1} {vname(t, e)}: wall {wall:.1f} s, {res['seconds']} on {r['executor']}", file=sys.stderr,
                      flush=True)
                record = {"command": "place3d reproduce " + " ".join(cmd) + " --quiet --output DIR",
                          "settings": res["settings"], "variants": {k: {**v, **{f"{m}_stats": stats(v[f"{m}_s"])
                                                                          for m in ("wall", "pool", "jackknife",
                                                                                    "convergence", "total")}}
                                                               for k, v in per.items()},
                          "same_results": all(s == studies[0] for s in studies),
                          "same_results_within_variant": {k: all(s == v[0] for s in v) for k, v in by_variant.items()},
                          "runs_done": i + 1,
                          "note": "empty P-SOG cache per run, warm kernel cache; variants alternate"}
                write_result(name, record, a.machine, path=path)
    for k, v in per.items():
        print(f"{k}: wall {stats(v['wall_s'])['median']:.1f} s [{min(v['wall_s']):.1f}-{max(v['wall_s']):.1f}], pool "
              f"{stats(v['pool_s'])['median']:.1f} s [{min(v['pool_s']):.1f}-{max(v['pool_s']):.1f}] on {v['executor']}")
    same = all(s == studies[0] for s in studies)
    print(f"same results in every run: {same}; wrote {path}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
