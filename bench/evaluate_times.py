#!/usr/bin/env python3
"""Issue 36, goal 2: wall seconds of the console command ``place3d evaluate`` (defaults: the embedded town, four
routes pooled, the eleven placements, jackknife intervals), cold (an empty P-SOG cache) and warm (the same
command again), per tree, the trees alternating so that an A/B shares one machine's mood (their order turned
every run: A B, B A, ...). The Warp kernel
cache is warmed by one untimed small run first; bytecode is compiled first for the trees and the packages the
command imports (``cold_profile.compile_bytecode``: Warp, NumPy, ...), as ``pip install`` does for a user.

    python3 bench/evaluate_times.py --runs 3 --tree .old --tree . [--args "--voxel-size 0.2"] --out $OUT
    python3 bench/evaluate_times.py --runs 3 --tree .:NAME=VALUE --tree .     # a setting against none

Writes ``evaluate-times-<machine>-<date>.json``: per tree the cold and warm walls (median, min, max, runs) and
a digest of each run's table (the scores must agree between trees and runs).

``--first-run`` times a new user's first command instead: each cold run also gets empty Warp and PoCL kernel
caches (``WARP_CACHE_PATH``, ``POCL_CACHE_DIR``), kept for its warm run, and nothing is warmed first. With
``--tree .:PLACE3D_BACKEND=warp:cpu --tree .`` it compares the CPU backend a plain install had before PyOpenCL
and PoCL became dependencies with the one ``auto`` picks now.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cold_profile import compile_bytecode, parse_tree
from results_io import write_result


def _run(tree: Path, cache: str, extra: list[str], settings: dict | None = None) -> tuple[float, str]:
    # the tree first, then what the host needs on the path (the lent GPU host keeps Warp in /tmp/site there)
    path = os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, **(settings or {}), "PYTHONPATH": path, "PLACE3D_CACHE": cache}
    env.pop("PLACE3D_SERVER", None)
    # from an empty folder: ``python -m`` puts the working directory first on the path, so run from a checkout
    # it would import that checkout whatever PYTHONPATH says (A/Bs before 2026-11-29 13:45 UTC, run from the
    # repository root, timed the working tree for every --tree)
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se, \
            tempfile.TemporaryDirectory() as work:
        t = time.perf_counter()
        rc = subprocess.run([sys.executable, "-m", "place3d_app", "evaluate", "--quiet", *extra], env=env,
                            stdout=so, stderr=se, timeout=120, cwd=work).returncode
        wall = time.perf_counter() - t
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    if rc:
        raise SystemExit(f"{tree}: evaluate failed ({rc}):\n{stderr[-2000:]}")
    # the table without its timing line
    table = "\n".join(line for line in stdout.splitlines() if not line.rstrip().endswith(" s"))
    return wall, hashlib.sha256(table.encode()).hexdigest()[:12]


def _stats(v: list[float]) -> dict:
    return {"median": statistics.median(v), "min": min(v), "max": max(v), "runs": v}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", action="append", default=None,
                    help="checkout to run (repeat for an A/B); TREE:NAME=VALUE,... runs it with those environment "
                         "settings (cold_profile.parse_tree)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--args", default="", help="more options of the command, e.g. '--voxel-size 0.2'")
    ap.add_argument("--no-warmup", action="store_true", help="the kernel cache is warm already")
    ap.add_argument("--first-run", action="store_true",
                    help="every cold run with empty Warp and PoCL kernel caches too (a new user's first command)")
    ap.add_argument("--machine", default=None)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    variants = [parse_tree(t) for t in (a.tree or ["."])]         # (label, tree, environment settings)
    if len({label for label, _, _ in variants}) != len(variants):
        raise SystemExit("two --tree arguments give the same label; name the checkouts apart")
    trees = list(dict.fromkeys(tree for _, tree, _ in variants))
    extra = shlex.split(a.args)
    # bytecode of the trees and of the packages the command imports (Warp among them), as pip install compiles
    # it for a user: the lent GPU host sets PYTHONDONTWRITEBYTECODE=1, where Warp's import from source alone
    # took most of a second of every run
    for line in compile_bytecode(trees):
        print(line, flush=True)
    if not (a.no_warmup or a.first_run):
        with tempfile.TemporaryDirectory() as c:      # Warp's kernels compiled once, untimed
            _run(variants[-1][1], c, [*extra, "--routes", "2", "--frames", "8"], variants[-1][2])
    walls = {label: {"cold": [], "warm": []} for label, _, _ in variants}
    digests = {label: [] for label, _, _ in variants}
    for r in range(a.runs):
        # the order turns every run (A B, B A, ...): two A/Bs on the H100 host each had the second tree's cold
        # runs slower, a bias a fixed order cannot tell from an effect
        for label, t, settings in (variants if r % 2 == 0 else variants[::-1]):
            with tempfile.TemporaryDirectory() as c:
                kernels = {"WARP_CACHE_PATH": f"{c}/warp", "POCL_CACHE_DIR": f"{c}/pocl"} if a.first_run else {}
                for kind in ("cold", "warm"):
                    w, d = _run(t, f"{c}/psog", extra, {**settings, **kernels})
                    walls[label][kind].append(round(w, 3))
                    digests[label].append(d)
                    print(f"run {r + 1} {label}: {kind} {w:.2f} s  table {d}", flush=True)
    figures = {"command": "place3d evaluate " + " ".join(extra), "first_run": a.first_run, "trees": {
        k: {kind: _stats(v) for kind, v in w.items()} for k, w in walls.items()}, "table_digests": digests,
        "same_tables": len({d for v in digests.values() for d in v}) == 1}
    print(write_result("evaluate-times", figures, machine=a.machine, out=a.out or os.environ.get("OUT")))


if __name__ == "__main__":
    main()
