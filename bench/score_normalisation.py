#!/usr/bin/env python3
"""What one CMA-ES generation of ``place3d optimize`` waits for: ``msog_batch`` of a population of rigs (the paper's
LiDAR, four sensors, the eight paper placements and five more: 13 rigs, pycma's default population for 16
variables) on the default pooled P-SOG (the embedded town, four routes, 0.1 m), under each normalisation. The
default ``uncertain`` and ``evidence`` divide by a count that a second grid of 0/1 weights gives; a backend that
counts it from the same walk (``Backend.score_placements_many``) pays a fraction of the paper normalisation's
time for it, one that walks again pays it twice.

    python3 bench/score_normalisation.py warp:cuda:0 opencl:nvidia --runs 3 [--tree .old --tree .] --out $OUT

Each ``--tree`` (a checkout) runs in a process of its own, from an empty folder with the tree first on the path,
alternately (A B, B A, ...). Every tree's scores must agree bit for bit (their digest is recorded). The P-SOG
comes from the P-SOG cache (``$PLACE3D_CACHE``), built there by the first run that lacks it, untimed. Writes
``score-normalisation-<machine>-<date>.json``: per tree, backend and normalisation the milliseconds of one call
(median, min, max of ``--runs`` runs, each the median of ``--calls`` calls after a warm-up call).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NORMALISATIONS = ("paper", "evidence", "uncertain")


def measure(backends: list[str], calls: int) -> dict:
    """{backend: {normalisation: (median ms of ``calls`` calls, digest of the scores)}} in this process."""
    import numpy as np

    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.metrics import msog_batch
    from place3d_kernels.placement import PAPER_PLACEMENTS, Placement
    from place3d_kernels.pooled import DEFAULT_ROUTES, pool_specs
    from place3d_kernels.spec import PSOGSpec, SceneSpec

    psog = pool_specs([PSOGSpec(SceneSpec("town", seed=s, frames=40)) for s in range(DEFAULT_ROUTES)]).psog()
    lidar = LidarModel.load("place3d_16ch")
    rigs = [Placement.load(n).poses for n in PAPER_PLACEMENTS]
    poses = np.stack((rigs + rigs)[:13])
    out: dict = {}
    for b in backends:
        out[b] = {}
        for norm in NORMALISATIONS:
            scores = msog_batch(psog, lidar, poses, backend=b, normalisation=norm)     # warm-up: uploads, kernels
            ts = []
            for _ in range(calls):
                t = time.perf_counter()
                msog_batch(psog, lidar, poses, backend=b, normalisation=norm)
                ts.append(1e3 * (time.perf_counter() - t))
            out[b][norm] = (statistics.median(ts), hashlib.sha256(scores.tobytes()).hexdigest()[:12])
    return out


def _in_tree(tree: Path, backends: list[str], calls: int) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)}
    with tempfile.TemporaryDirectory() as work:
        p = subprocess.run([sys.executable, str(Path(__file__).resolve()), *backends, "--calls", str(calls),
                            "--child"], env=env, cwd=work, capture_output=True, text=True, timeout=600)
    if p.returncode:
        raise SystemExit(f"{tree}: failed ({p.returncode}):\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("backends", nargs="+")
    ap.add_argument("--tree", action="append", default=None, help="checkout to run (repeat for an A/B)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--calls", type=int, default=5, help="timed calls per run (their median is the run's figure)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--machine", default=None)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(measure(a.backends, a.calls)))
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import write_result

    trees = [Path(t).resolve() for t in (a.tree or [Path(__file__).resolve().parents[1]])]
    got: dict = {str(t): {b: {n: [] for n in NORMALISATIONS} for b in a.backends} for t in trees}
    digests: set = set()
    for r in range(a.runs):
        for t in (trees if r % 2 == 0 else trees[::-1]):
            res = _in_tree(t, a.backends, a.calls)
            for b, per in res.items():
                for n, (ms, digest) in per.items():
                    got[str(t)][b][n].append(round(ms, 3))
                    digests.add((b, n, digest))
                    print(f"run {r + 1} {t.name}: {b} {n} {ms:.2f} ms  scores {digest}", flush=True)
    figures = {"what": "ms per msog_batch call of 13 rigs (place3d_16ch x 4) on the default pooled P-SOG",
               "trees": {t: {b: {n: {"median": statistics.median(v), "min": min(v), "max": max(v), "runs": v}
                                 for n, v in per.items()} for b, per in bs.items()} for t, bs in got.items()},
               "same_scores": len(digests) == len(a.backends) * len(NORMALISATIONS)}
    print(write_result("score-normalisation", figures, machine=a.machine, out=a.out or os.environ.get("OUT")))


if __name__ == "__main__":
    main()
