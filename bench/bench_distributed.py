"""Distributed `place3d simulate`: frames per second with the local executor and 1, 2 local Ray workers,
and a PROJECTION of the paper-scale dataset time (280,000 frames) on N GPUs from a per-frame GPU time.

    python3 bench/bench_distributed.py                       # dev CPU, warp:cpu, 16 frames of the 64-ch LiDAR
    python3 bench/bench_distributed.py --gpu-backend warp:cuda:0   # on a GPU host: measure the per-frame basis

Per-frame GPU basis, in order of preference:
  1. measured here with --gpu-backend (simulate() per frame on that backend, warm, in-process);
  2. the latest run_bench.py run with warp:cuda:0 in bench/results/summary.json: lidar_rays_ms + 2 x (65,536 rays / raycast_town_mrays_s), i.e. one static and
     one dynamic-actor ray cast per frame at the API rate (copies included), no host work.
The projection assumes one task stream per GPU, perfect scaling and host work (actor meshes, conditions,
file writes) overlapped on the CPU cores; it is a projection, not a measurement. Writes
``bench/results/distributed-<machine>-<date>.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RAYS_PER_FRAME = 64 * 1024


def _fps(executor, scene, lidar, backend, chunk, frames):
    from place3d_app.executors import simulate_to_folder

    tmp = tempfile.mkdtemp(prefix="p3k-bench-")
    try:
        r = simulate_to_folder(scene, lidar, tmp, executor, chunk=chunk, backend=backend, frames=range(frames))
        return frames / r["seconds"], r["seconds"]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _per_frame(backend, scene, lidar, n=8):
    from place3d_kernels.simulate import simulate

    sc = scene.build()
    simulate(sc, lidar, frames=[0], backend=backend)          # warm-up: kernels, BVH of the static mesh
    t = time.perf_counter()
    simulate(sc, lidar, frames=list(range(1, n + 1)), backend=backend)
    return (time.perf_counter() - t) / n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--chunk", type=int, default=2)
    ap.add_argument("--backend", default="warp:cpu")
    ap.add_argument("--lidar", default="collection_64ch")
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--gpu-backend", default=None, help="measure the per-frame GPU time here on this backend")
    ap.add_argument("--gpus", type=int, nargs="*", default=[1, 8, 64])
    ap.add_argument("--output", default=None, help="JSON path (default bench/results/distributed-<machine>-<date>.json)")
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    args = ap.parse_args(argv)

    from results_io import write_result

    from place3d_app.executors import LocalExecutor, SceneSpec, get_executor

    scene = SceneSpec("town", seed=0, frames=max(args.frames, 10))
    res = {"backend": args.backend, "lidar": args.lidar, "frames": args.frames, "chunk": args.chunk,
           "scene": "town seed 0", "runs": {}}
    # local executor (in-process), after a warm-up frame
    _fps(LocalExecutor(), scene, args.lidar, args.backend, args.chunk, 1)
    fps, s = _fps(LocalExecutor(), scene, args.lidar, args.backend, args.chunk, args.frames)
    res["runs"]["local"] = {"fps": fps, "seconds": s}
    print(f"local executor: {fps:.2f} frames/s ({s:.1f} s for {args.frames})", file=sys.stderr)
    try:
        import ray
    except ImportError:
        ray = None
        print("Ray missing: pip install 'place3d-kernels[dist]'", file=sys.stderr)
    for w in args.workers if ray else []:
        ray.init(num_cpus=w, include_dashboard=False, log_to_driver=False)
        ex = get_executor("ray")
        t = time.perf_counter()
        _fps(ex, scene, args.lidar, args.backend, 1, w)            # warm-up: one frame per worker
        warm = time.perf_counter() - t
        fps, s = _fps(ex, scene, args.lidar, args.backend, args.chunk, args.frames)
        ray.shutdown()
        res["runs"][f"ray-{w}"] = {"workers": w, "fps": fps, "seconds": s, "warmup_s": warm}
        print(f"ray, {w} worker(s): {fps:.2f} frames/s ({s:.1f} s; warm-up {warm:.1f} s)", file=sys.stderr)

    # ---------------------------------------------------------------- projection
    if args.gpu_backend:
        t_frame = _per_frame(args.gpu_backend, scene, args.lidar)
        basis = {"source": f"measured here: simulate() per frame on {args.gpu_backend}", "seconds_per_frame": t_frame}
    else:
        # the latest run_bench.py run with warp:cuda:0 (summary.json keeps one per machine label)
        runs = json.loads((ROOT / "bench" / "results" / "summary.json").read_text())["runs"]
        g = max((r for r in runs if "warp:cuda:0" in r["backends"]), key=lambda r: r["date"])
        b = g["backends"]["warp:cuda:0"]
        t_frame = b["lidar_rays_ms"] / 1e3 + 2 * RAYS_PER_FRAME / (b["raycast_town_mrays_s"] * 1e6)
        basis = {"source": f"summary.json, {g['machine']} {g['date']}: lidar_rays_ms + 2 x 65,536 rays at "
                           "raycast_town_mrays_s (API)", "device": g["device"], "lidar_rays_ms": b["lidar_rays_ms"],
                 "raycast_town_mrays_s": b["raycast_town_mrays_s"], "seconds_per_frame": t_frame}
    proj = {str(n): 280_000 * t_frame / n / 3600 for n in args.gpus}
    res["projection"] = {"label": "PROJECTION (not measured): 280,000 frames x per-frame GPU time / N GPUs, "
                                  "perfect scaling, host work overlapped", "frames": 280_000, "basis": basis,
                         "hours_by_gpus": proj}
    print(f"PROJECTION, 280,000 frames at {t_frame * 1e3:.1f} ms/frame ({basis['source']}): "
          + ", ".join(f"{n} GPU(s) {h:.2f} h" for n, h in proj.items()), file=sys.stderr)
    print(json.dumps(res, indent=2))
    print("wrote", write_result("distributed", res, args.machine, path=args.output), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
