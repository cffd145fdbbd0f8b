#!/usr/bin/env python3
"""Goal 1's cold command, profiled: ``place3d --profile optimize --max-evals 2000 --task seg`` on a cold host.

Each run gets fresh Warp kernel, CUDA driver and P-SOG caches (``WARP_CACHE_PATH``, ``CUDA_CACHE_PATH``,
``PLACE3D_CACHE`` in new temporary folders), so the P-SOG is built and every kernel module loaded or compiled
as on a machine that never ran the package. Trees named with ``--tree`` (folders holding a checkout of
this project) are run alternately, so two versions share one machine's mood; the default is this tree. A
tree may carry environment settings, ``--tree .:PLACE3D_FAST_EXIT=0,NAME=VALUE``, to set a switch of one
tree against the same tree without it. The command runs as the ``place3d`` console script runs it
(``python -m place3d_app``, with ``PLACE3D_SERVER`` unset), so its exit is the script's; a tree from before the
application wing (such as tag lab-2026-11-27) runs it under its old name, ``place3d_client``.
``--cprofile`` adds one run under cProfile per tree (the top functions by own and cumulative time).
``--warm`` runs the command a second time after each cold run, with the caches the cold run filled (the P-SOGs
read from the cache instead of built, Warp's kernels and the driver's cache kept): what a user's next run waits
for. Its walls and profile tables are reported beside the cold ones.

Python bytecode. ``pip install`` compiles the installed packages' bytecode and a package's first import
writes its own, so a user's cold command reads ``.pyc`` files. A host that sets ``PYTHONDONTWRITEBYTECODE=1``
and got its packages with ``pip install --no-compile`` (the lent GPU host, through ``../shared/gpu/prepare.sh``)
compiles Warp's and this package's sources in every process instead (``import warp`` alone 0.88-0.96 s there).
``--bytecode`` compiles them once before the runs (``compileall``: the trees and the packages the command
imports, where writable) and says so in the output; without it the runs measure whatever the host has.

    python3 bench/cold_profile.py --runs 4 --out $OUT                         # this tree
    python3 bench/cold_profile.py --runs 4 --tree /tmp/old --tree . --out $OUT # an A/B, alternating
    python3 bench/cold_profile.py --runs 4 --tree .:PLACE3D_FAST_EXIT=0 --tree . --out $OUT

Writes one file per run of this script, ``cold-profile-<machine>-<date>.json`` in ``--out`` (default $OUT, else
bench/results/): the walls per tree (median, min, max, every run), ``marks`` per tree (the same for each cold run's
process exit and the profile's ``MARK_ROWS``: the drives' step's end, the pooled P-SOG's, the search, the span) and
``log``, every run's wall, last stdout line
(with a digest of the results, which must match between trees) and profile table, and the cProfile listings.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import pstats
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from results_io import write_result

ROOT = Path(__file__).resolve().parent.parent


def parse_tree(arg: str) -> tuple[str, Path, dict]:
    """``TREE`` or ``TREE:NAME=VALUE,...`` -> (label, resolved tree, environment settings)."""
    path, _, sets = arg.partition(":")
    tree = Path(path).resolve()
    env = dict(kv.split("=", 1) for kv in sets.split(",") if kv)
    return tree.name + ("" if not env else "[" + ",".join(f"{k}={v}" for k, v in env.items()) + "]"), tree, env


def entry_module(tree: Path, cprofile: bool) -> str:
    """The console script's module in ``tree``, or under cProfile the CLI's module (old names in old trees)."""
    if (tree / "place3d_app").is_dir():
        return "place3d_app.cli" if cprofile else "place3d_app"
    return "place3d_kernels.cli" if cprofile else "place3d_client"


def cold_run(tree: Path, backend: str, max_evals: int, cprofile: Path | None = None, args: tuple = (),
             extra_env: dict | None = None, caches: str | None = None) -> tuple[float, str, str]:
    """One cold run of the command from ``tree``: (wall seconds, last stdout line, stderr's profile table).
    The wall ends when every process holding the command's output has closed it (its workers too); the line
    also names when the command's own process ended (``process exit``), which is what a shell waits for.
    ``caches``: a folder for the Warp, CUDA and P-SOG caches, kept after the run (a later run with the same
    folder is a warm one); default a new temporary folder."""
    with (contextlib.nullcontext(caches) if caches else tempfile.TemporaryDirectory()) as cold, \
            tempfile.TemporaryDirectory() as o:
        env = dict(os.environ, WARP_CACHE_PATH=f"{cold}/warp", CUDA_CACHE_PATH=f"{cold}/cuda",
                   PLACE3D_CACHE=f"{cold}/psog", PYTHONPATH=str(tree) + os.pathsep + os.environ.get("PYTHONPATH", ""),
                   PLACE3D_SERVER="", **(extra_env or {}))
        if cprofile:        # the console script's fast exit (os._exit) would leave before cProfile writes its file
            env["PLACE3D_FAST_EXIT"] = "0"
        pre = [sys.executable] + (["-m", "cProfile", "-o", str(cprofile)] if cprofile else [])
        # the console script's module (its exit included); cProfile runs the package's CLI module, as before
        entry = entry_module(tree, cprofile)
        cmd = pre + ["-m", entry, "--profile", "optimize", "--max-evals", str(max_evals),
                     "--task", "seg", "--backend", backend, "--quiet", *args, "--output", o]
        t = time.perf_counter()
        p = subprocess.Popen(cmd, env=env, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        texts = {}
        readers = [threading.Thread(target=lambda n, f: texts.__setitem__(n, f.read()), args=(n, f), daemon=True)
                   for n, f in (("stdout", p.stdout), ("stderr", p.stderr))]
        for r in readers:
            r.start()
        try:
            code = p.wait(timeout=600)
        except subprocess.TimeoutExpired:       # as subprocess.run(timeout=) did: the command killed, then raised
            p.kill()
            p.wait()
            raise
        exited = time.perf_counter() - t         # the command's own process has ended (a shell's prompt returns)
        for r in readers:
            r.join(timeout=600)
        wall = time.perf_counter() - t           # and every process that holds its output (its workers) too
        out, err = texts.get("stdout", ""), texts.get("stderr", "")
        if code:
            raise RuntimeError(f"{tree}: exited {code}\n{out[-2000:]}\n{err[-3000:]}")
        res = json.loads((Path(o) / "result.json").read_text())
    # what must not change between trees: the best rig and score, the baselines' scores, the intervals
    digest = hashlib.sha256(json.dumps([res["best_score"], res["best_placement"], res["baseline_scores"],
                                        res["intervals"]], sort_keys=True).encode()).hexdigest()[:12]
    last = f"process exit {exited:.3f} s | results {digest} | " + (out.strip().splitlines() or [""])[-1]
    table = err[err.find("place3d profile"):] if "place3d profile" in err else err[-3000:]
    return wall, last, table


#: profile rows whose end (``to``) or span a run's summary keeps (``marks``): when the drives' step ended, when the
#: pooled P-SOG was ready, the search (first to last scoring) and the profile's whole span
MARK_ROWS = {"drives_end_s": ("  drives: worker processes", "to"), "pooled_end_s": ("  P-SOG (pooled drives)", "to"),
             "search_s": ("scoring (objective)", "span"), "profile_s": ("total (profile span)", "seconds")}


def marks(last: str, table: str) -> dict:
    """A run's figures for the summary: ``exit_s`` (when the command's own process ended, from ``cold_run``'s
    line) and the ``MARK_ROWS`` read from its profile table (a row the table lacks is left out)."""
    out = {}
    m = re.search(r"process exit ([\d.]+) s", last)
    if m:
        out["exit_s"] = float(m.group(1))
    rows = table.splitlines()
    for key, (prefix, what) in MARK_ROWS.items():
        row = next((r for r in rows if r.startswith(prefix)), None)
        if row is None:
            continue
        f = row.split()                 # ..., seconds, calls, share, from, to (the total's row ends at seconds)
        try:
            out[key] = round(float(f[-1]) if what in ("seconds", "to") else float(f[-1]) - float(f[-2]), 3)
        except (IndexError, ValueError):
            continue
    return out


def _stats(v: list[float]) -> dict:
    return {"median": statistics.median(v), "min": min(v), "max": max(v), "runs": v}


#: packages ``place3d optimize`` imports (besides the standard library), whose bytecode ``--bytecode`` compiles
BYTECODE_PACKAGES = ("warp", "numpy", "cma", "scipy", "matplotlib", "pyopencl", "trimesh", "PIL", "tqdm", "platformdirs")


def compile_bytecode(trees: list[Path]) -> list[str]:
    """Compile the trees' and the command's packages' sources to bytecode (as ``pip install`` does for installed
    packages); returns one line per folder: compiled, or why not."""
    import compileall
    import importlib.util

    folders = [(str(t), [t / "place3d_kernels", t / "place3d_app", t / "place3d_client"]) for t in trees]
    for name in BYTECODE_PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            folders.append((name, [Path(p) for p in spec.submodule_search_locations]))
    lines = []
    for name, dirs in folders:
        for d in dirs:
            if not d.is_dir():
                continue
            if not os.access(d, os.W_OK):
                lines.append(f"{name}: {d} not writable, left as it is")
                continue
            t = time.perf_counter()
            ok = compileall.compile_dir(str(d), quiet=2, workers=0)
            lines.append(f"{name}: {d} compiled in {time.perf_counter() - t:.1f} s{'' if ok else ' (some files failed)'}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", default=None, help="project checkout to run (repeat for an A/B)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--backend", default="warp:cuda:0")
    ap.add_argument("--max-evals", type=int, default=2000)
    ap.add_argument("--cprofile", action="store_true", help="one more run per tree under cProfile")
    ap.add_argument("--bytecode", action="store_true", help="compile the trees' and packages' bytecode first")
    ap.add_argument("--warm", action="store_true",
                    help="after each cold run, the same command again with the caches it filled (a warm run)")
    ap.add_argument("--args", default="", help="more options of the command, e.g. '--routes 1 --no-holdout'")
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    ap.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "bench" / "results")))
    a = ap.parse_args()
    trees = [parse_tree(t) for t in (a.tree or [str(ROOT)])]
    walls: dict[str, list[float]] = {label: [] for label, _, _ in trees}
    warm: dict[str, list[float]] = {label: [] for label, _, _ in trees}
    run_marks: dict[str, list[dict]] = {label: [] for label, _, _ in trees}       # cold runs' marks()
    log = [f"# cold place3d optimize --max-evals {a.max_evals} --task seg --backend {a.backend} {a.args}; fresh Warp, "
           f"CUDA and P-SOG caches each run; trees alternating: {[f'{t} {e or {}}' for _, t, e in trees]}"]
    if a.bytecode:
        lines = compile_bytecode([t for _, t, _ in trees])
        log += ["# bytecode compiled ahead of the runs (as pip install does):"] + [f"#   {x}" for x in lines]
        print("\n".join(lines), flush=True)
    else:
        log.append(f"# bytecode as the host has it (PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', 'unset')})")
    for r in range(a.runs):
        for label, t, env in (trees if r % 2 == 0 else trees[::-1]):     # A B, B A, ...: no order bias
            with tempfile.TemporaryDirectory() as caches:
                for kind, into in (("cold", walls), ("warm", warm))[:2 if a.warm else 1]:
                    w, last, table = cold_run(t, a.backend, a.max_evals, args=tuple(a.args.split()), extra_env=env,
                                              caches=caches)
                    into[label].append(w)
                    if kind == "cold":
                        run_marks[label].append(marks(last, table))
                    name = label if kind == "cold" else f"{label} (warm)"
                    log += [f"## {name} run {r + 1}: wall {w:.3f} s | {last}", table.rstrip(), ""]
                    print(f"{name} run {r + 1}: wall {w:.3f} s | {last}", flush=True)
    summary, warm_summary = {}, {}
    for kind, source, into in (("", walls, summary), (" (warm)", warm, warm_summary)):
        for t, ws in source.items():
            if ws:
                into[t] = _stats(ws)
                log.append(f"{t}{kind}: wall median {into[t]['median']:.3f} [{min(ws):.3f}-{max(ws):.3f}] s "
                           f"over {len(ws)} runs")
    # per tree, the median and range of each mark over its cold runs (process exit: what a shell waits for)
    marks_summary = {t: {k: _stats([m[k] for m in ms if k in m]) for k in ("exit_s", *MARK_ROWS)
                         if any(k in m for m in ms)} for t, ms in run_marks.items()}
    for t, ms in marks_summary.items():
        log.append(f"{t}: " + "; ".join(f"{k} median {v['median']:.3f} [{v['min']:.3f}-{v['max']:.3f}]"
                                        for k, v in ms.items()))
    if a.cprofile:
        for label, t, env in trees:
            pf = Path(tempfile.mkdtemp()) / "cold.pstats"
            w, last, _ = cold_run(t, a.backend, a.max_evals, cprofile=pf, args=tuple(a.args.split()), extra_env=env)
            log.append(f"## cProfile {label}: wall {w:.3f} s (under cProfile) | {last}")
            with tempfile.TemporaryFile("w+") as s:
                st = pstats.Stats(str(pf), stream=s)
                st.sort_stats("tottime").print_stats(40)
                st.sort_stats("cumulative").print_stats(80)
                s.seek(0)
                log.append(s.read())
    path = write_result("cold-profile", {
        "command": f"place3d optimize --max-evals {a.max_evals} --task seg --backend {a.backend} {a.args}".strip(),
        "trees": {label: str(t) for label, t, _ in trees}, "walls_s": summary, "marks": marks_summary,
        **({"warm_walls_s": warm_summary} if a.warm else {}), "bytecode_compiled_ahead": a.bytecode,
        "log": "\n".join(log) + "\n"}, a.machine, a.out)
    print(f"wrote {path}")
    for kind, source in (("cold", summary), ("warm", warm_summary)):
        for t, s in source.items():
            print(f"{t}: {kind} wall median {s['median']:.3f} [{s['min']:.3f}-{s['max']:.3f}] s")
    for t, ms in marks_summary.items():
        print(f"{t}: cold " + "; ".join(f"{k} {v['median']:.3f} [{v['min']:.3f}-{v['max']:.3f}]" for k, v in ms.items()))


if __name__ == "__main__":
    main()
