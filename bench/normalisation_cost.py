"""What optimize's default normalisation costs: ``place3d optimize`` with --normalisation paper and uncertain,
alternating, each run in its own process with ``--profile``; wall time and the profile's scoring, jackknife and
held-out sections per run, medians per normalisation (issue 34, item 4; docs/metric-normalisation.md).

    python3 bench/normalisation_cost.py --backend warp:cuda:0 --runs 3 --out "$OUT"

The first run of each normalisation is untimed (it fills the P-SOG cache). Writes ONE JSON,
``OUT/normalisation-cost.json``, with the machine, the time, the command and every run.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = {"scoring": "scoring (objective)", "jackknife": "intervals (jackknife)", "held_out": "held-out P-SOGs"}


def one_run(norm: str, args, out: Path) -> dict:
    cmd = [sys.executable, "-m", "place3d_app", "--profile", "optimize", "--max-evals", str(args.max_evals), "--quiet",
           "--backend", args.backend, "--normalisation", norm, "--output", str(out), *args.extra]
    t = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    row = {"normalisation": norm, "wall_s": wall}
    for key, name in SECTIONS.items():
        m = re.search(rf"^\s*{re.escape(name)}\s+([0-9.]+)", r.stderr, re.M)
        row[f"{key}_s"] = float(m.group(1)) if m else None
    row["best_score"] = json.loads((out / "result.json").read_text())["best_score"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--runs", type=int, default=3, help="timed runs per normalisation, alternating (default 3)")
    ap.add_argument("--max-evals", type=int, default=2000)
    ap.add_argument("--out", required=True, help="folder for normalisation-cost.json")
    ap.add_argument("extra", nargs="*", help="further optimize options (after --)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs + 1):
            for norm in ("paper", "uncertain"):
                row = one_run(norm, args, Path(tmp) / f"{norm}-{i}")
                if i:                                   # run 0 fills the cache
                    rows.append(dict(row, run=i))
    med = {n: {k: statistics.median(r[k] for r in rows if r["normalisation"] == n and r[k] is not None)
               for k in ("wall_s", "scoring_s", "jackknife_s", "held_out_s")
               if any(r["normalisation"] == n and r[k] is not None for r in rows)}
           for n in ("paper", "uncertain")}
    summary = {"what": "place3d optimize, --normalisation paper vs uncertain, alternating", "runs": rows,
               "median": med, "max_evals": args.max_evals, "backend": args.backend, "extra": args.extra,
               "machine": {"node": platform.node(), "processor": platform.processor(),
                           "python": sys.version.split()[0]},
               "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "normalisation-cost.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(med, indent=2))


if __name__ == "__main__":
    main()
