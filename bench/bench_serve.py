"""Wall time of ``place3d optimize`` (or ``evaluate``) in-process against the same command through a warm
``place3d serve``.

    python3 bench/bench_serve.py --backend warp:cuda:0 --machine H100
    python3 bench/bench_serve.py --backend opencl:pocl --machine cpu-2core-dev
    python3 bench/bench_serve.py --backend warp:cuda:0 --command evaluate

Both are the ``place3d`` entry point (``python -m place3d_app``) in a subprocess, timed from start to
exit; the server variant adds ``--server=SOCKET``. One untimed run of each first fills the Warp kernel
cache, the P-SOG cache and the server's memory; then the two alternate, ``--runs`` times each, so drift
on a shared machine hits both alike. Also timed: the client alone (``--server=SOCKET --version``, a
round trip to the server with no work) and ``python -c pass`` for the interpreter's own start.

Writes ``bench/results/serve-<machine>-<date>.json``: median, min, max and every run of each variant,
whether the outputs matched (timing figures masked), and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from results_io import write_result  # noqa: E402

from place3d_app.serve import is_listening  # noqa: E402

TIMING = re.compile(r"\d+(\.\d+)? s\b")


def stats(xs: list[float]) -> dict:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    env.pop("PLACE3D_SERVER", None)
    return env


def _timed(cmd: list[str], cwd: Path, timeout: float) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-3000:]}")
    return wall, r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="auto", help="backend of the command and the server (default auto)")
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--runs", type=int, default=3, help="timed runs of each variant (default 3, at least 3)")
    ap.add_argument("--command", choices=("optimize", "evaluate"), default="optimize",
                    help="the command timed (default optimize; evaluate: its defaults, every placement)")
    ap.add_argument("--max-evals", type=int, default=2000, help="optimize's evaluations (default 2000)")
    ap.add_argument("--task", default="seg")
    ap.add_argument("--timeout", type=float, default=600)
    ap.add_argument("--output", default=None, help="JSON path (default bench/results/serve-<machine>-<date>.json, "
                                                    "or $OUT/...)")
    args = ap.parse_args(argv)
    if args.runs < 3:
        ap.error(f"--runs must be at least 3 (median of three or more), got {args.runs}")

    work = Path(tempfile.mkdtemp(prefix="p3b-", dir="/tmp"))     # short: a socket path holds 107 bytes
    sock = work / "s.sock"
    base = [sys.executable, "-m", "place3d_app"]
    command = (["optimize", "--max-evals", str(args.max_evals), "--task", args.task] if args.command == "optimize"
               else ["evaluate"]) + ["--backend", args.backend, "--quiet"]
    out = "out" if args.command == "optimize" else "out.json"     # optimize writes a folder, evaluate a JSON file
    load_before = os.getloadavg()
    t = time.perf_counter()
    # cwd: ``python -m`` puts the working directory first on the path, so a server started from another
    # checkout would run that checkout's code, not ROOT's (and refuse the clients, whose identity differs)
    server = subprocess.Popen(base + ["serve", "--socket", str(sock), "--backend", args.backend,
                                      "--idle-timeout", "0"], cwd=work, env=_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    try:
        while not is_listening(sock):
            if server.poll() is not None:
                raise RuntimeError(f"server exited: {server.stdout.read()}")
            time.sleep(0.05)
        server_start = time.perf_counter() - t
        variants = {"in_process": base + command, "server": base + [f"--server={sock}"] + command}
        walls: dict[str, list[float]] = {k: [] for k in variants}
        texts: dict[str, str] = {}
        for i in range(args.runs + 1):                  # run 0 of each: warm-up, not timed
            for name, cmd in variants.items():
                run_dir = work / f"{name}-{i}"
                run_dir.mkdir()
                wall, r = _timed(cmd + ["--output", out], run_dir, args.timeout)
                if "running here" in r.stderr:
                    raise RuntimeError(f"the server did not take the command: {r.stderr[-2000:]}")
                texts[name] = TIMING.sub("<t> s", r.stdout).replace(str(run_dir), "<dir>")
                if i:
                    walls[name].append(wall)
                print(f"{name:10s} run {i}{' (warm-up)' if not i else ''}: {wall:.2f} s", file=sys.stderr)
                shutil.rmtree(run_dir / "out", ignore_errors=True)
        client = [_timed(base + [f"--server={sock}", "--version"], work, 60)[0] for _ in range(5)]
        bare = [_timed([sys.executable, "-c", "pass"], work, 60)[0] for _ in range(5)]
    finally:
        server.send_signal(signal.SIGTERM)
        log = server.communicate(timeout=60)[0]
        shutil.rmtree(work, ignore_errors=True)
    res = {
        "backend": args.backend, "max_evals": args.max_evals,
        "command": "place3d " + " ".join(command) + " --output DIR",
        "in_process_s": stats(walls["in_process"]), "server_s": stats(walls["server"]),
        "speedup_median": statistics.median(walls["in_process"]) / statistics.median(walls["server"]),
        "same_stdout_timing_masked": texts["in_process"] == texts["server"],
        "client_round_trip_s": stats(client), "python_c_pass_s": stats(bare),
        # the server's own time per command (its log), warm-up first: the rest of server_s is the client,
        # the socket and the interpreter's start
        "server_side_s": [float(m) for m in re.findall(rf" {args.command} .*-> exit 0 in ([0-9.]+) s", log)],
        "server_start_s": server_start, "server_log": log.splitlines()[:2],
        "loadavg_1_5_15_before": load_before, "loadavg_1_5_15_after": os.getloadavg(),
        "note": "alternating runs after one untimed warm-up run of each; wall time of the whole subprocess",
    }
    bench = ("serve" if args.max_evals == 2000 else f"serve-evals{args.max_evals}") if args.command == "optimize" \
        else "serve-evaluate"
    out = write_result(bench, res, args.machine, path=args.output)
    print(json.dumps({k: res[k] for k in ("in_process_s", "server_s", "speedup_median", "client_round_trip_s",
                                          "same_stdout_timing_masked")}, indent=1))
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
