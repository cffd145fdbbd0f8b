#!/usr/bin/env python3
"""Where a cold process's CUDA backend start goes, and whether starting the CUDA driver early helps.

Each run is a fresh process with empty Warp and CUDA caches (as ``cold_profile.py``) that times, from its
first line: ``import warp``, ``wp.init()``, the device's primary context (``wp.get_device(...).context``)
and the package's ``get_backend("warp:cuda:0")`` (its kernel modules imported, the shipped CUDA binaries
loaded). Mode ``early`` first starts a thread that initialises the CUDA driver and retains the device's
primary context through ``libcuda`` (``cuInit``, ``cuDeviceGet``, ``cuDevicePrimaryCtxRetain``), the
calls Warp makes later, so that they run while the main thread imports Warp (ctypes releases the
interpreter lock during a foreign call); Warp then finds the context made. Modes alternate, ``--runs``
each; ``--cprofile`` adds one run of mode ``plain`` under cProfile (top 40 by cumulative time).

    python3 bench/probe_start.py --runs 5 --out $OUT      # writes probe-start<label>.json (and .txt)
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

ROOT = Path(__file__).resolve().parent.parent

CHILD = r"""
import json, os, sys, threading, time
t0 = time.perf_counter()
mode, device = sys.argv[1], sys.argv[2]
early = {}
if mode == "early":
    def start_driver():
        import ctypes
        s = time.perf_counter()
        cu = ctypes.CDLL("libcuda.so.1")
        early["dlopen"] = time.perf_counter() - s
        ok = cu.cuInit(0) == 0
        early["cuInit"] = time.perf_counter() - s
        dev, ctx = ctypes.c_int(), ctypes.c_void_p()
        ok = ok and cu.cuDeviceGet(ctypes.byref(dev), int(device.split(":")[1])) == 0
        ok = ok and cu.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev) == 0
        early["retain"] = time.perf_counter() - s
        early["ok"] = bool(ok)
        early["done_at"] = time.perf_counter() - t0
    th = threading.Thread(target=start_driver)
    th.start()
marks = {}
import warp as wp
marks["import_warp"] = time.perf_counter() - t0
wp.config.quiet = True
wp.init()
marks["wp_init"] = time.perf_counter() - t0
wp.get_device(device).context
marks["context"] = time.perf_counter() - t0
sys.path.insert(0, sys.argv[3])
from place3d_kernels.backends.registry import get_backend
b = get_backend("warp:" + device)
marks["get_backend"] = time.perf_counter() - t0
if mode == "early":
    th.join()
print(json.dumps({"marks": marks, "early": early, "aot": getattr(b, "aot", None)}))
"""


def run(mode: str, device: str, cprofile: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory() as cold:
        env = dict(os.environ, WARP_CACHE_PATH=f"{cold}/warp", CUDA_CACHE_PATH=f"{cold}/cuda")
        pre = [sys.executable] + (["-m", "cProfile", "-o", str(cprofile)] if cprofile else [])
        with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
            f.write(CHILD)
        try:
            t = time.perf_counter()
            p = subprocess.run(pre + [f.name, mode, device, str(ROOT)], env=env, capture_output=True, text=True,
                               timeout=300)
            wall = time.perf_counter() - t
        finally:
            os.unlink(f.name)
    if p.returncode:
        raise RuntimeError(p.stderr[-3000:])
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["wall"] = wall
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--cprofile", action="store_true")
    ap.add_argument("--label", default="")
    ap.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "bench" / "results")))
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = {"plain": [], "early": []}
    for r in range(a.runs):
        for mode in runs:
            res = run(mode, a.device)
            runs[mode].append(res)
            print(mode, r + 1, json.dumps(res), flush=True)
    summary = {}
    for mode, rs in runs.items():
        summary[mode] = {k: {"median": statistics.median(x["marks"][k] for x in rs),
                             "min": min(x["marks"][k] for x in rs), "max": max(x["marks"][k] for x in rs)}
                         for k in rs[0]["marks"]}
        summary[mode]["wall"] = {"median": statistics.median(x["wall"] for x in rs),
                                 "min": min(x["wall"] for x in rs), "max": max(x["wall"] for x in rs)}
    text = []
    if a.cprofile:
        import pstats

        pf = out / f"probe-start{a.label}.pstats"
        run("plain", a.device, cprofile=pf)
        with tempfile.TemporaryFile("w+") as s:
            pstats.Stats(str(pf), stream=s).sort_stats("cumulative").print_stats(40)
            s.seek(0)
            text.append(s.read())
    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                         text=True).stdout.strip() if a.device.startswith("cuda") else ""
    (out / f"probe-start{a.label}.json").write_text(json.dumps(
        {"device": a.device, "gpu": gpu, "cpus": os.cpu_count(), "summary_s": summary, "runs": runs,
         "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}, indent=1))
    if text:
        (out / f"probe-start{a.label}.txt").write_text("\n".join(text))
    for mode, s in summary.items():
        print(mode, " ".join(f"{k} {v['median']:.3f} [{v['min']:.3f}-{v['max']:.3f}]" for k, v in s.items()))


if __name__ == "__main__":
    main()
