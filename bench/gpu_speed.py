#!/usr/bin/env python3
"""What a user waits for, in one command (issue 17's goals): optimise end to end, ray-mesh, the dense rig.

(a) ``place3d optimize --max-evals 2000 --task seg --backend B`` as a whole command, wall time in a
    subprocess: warm (kernel and P-SOG caches filled by one untimed run, then 3 timed runs) and cold
    (3 runs, each with a fresh Warp kernel cache, ``WARP_CACHE_PATH``, and a fresh P-SOG cache,
    ``PLACE3D_CACHE``).
(b) Ray-mesh through the API (``p3k.raycast``, NumPy in and out; float32 rays as the plain kernel gets,
    and float64 rays) against a plain Warp ``mesh_query_ray``
    kernel on the same ``box_city`` and rays (the dense rig of bench/peers.py: 4 x 64 x 2048 rays of
    ``LidarModel.uniform(64, (-25, 15), 2048, max_range=200)`` at ``pyramid``): the plain kernel both with
    NumPy in and out (upload, launch, download) and kernel only.
(c) The dense rig (bench/gpu_dense.py, 0.05 m grid, population 16), run 3 times in subprocesses.

Every figure is 3 repeats: median, min and max. Writes ``gpu-speed-<machine>-<date>.json`` (the backend and
``quick`` inside) to ``--out`` (default $OUT, else bench/results/).

    python3 bench/gpu_speed.py --out $OUT                    # the GPU host (warp:cuda:0)
    python3 bench/gpu_speed.py --backend opencl:pocl --skip b,c --machine cpu-2core-dev   # the CPU's (a)
    python3 bench/gpu_speed.py --backend warp:cpu --quick    # smoke test on a CPU
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

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
REPEATS = 3
API_REPEATS = 9   # calls per block of the API and of the plain kernel with NumPy in and out (part (b))
PAIRED = 15      # back-to-back rounds of the ray-mesh API and the plain kernel (part (b))


def stats(xs) -> dict:
    """Median, min, max and the values of a list of timings (seconds)."""
    xs = [float(x) for x in xs]
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}


def _env(**extra) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _run(cmd, env, timeout) -> tuple[float, str]:
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd)} exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    return wall, p.stdout[-2000:]


# ----------------------------------------------------------------------------- (a) whole command
def whole_command(backend: str, max_evals: int, timeout: int) -> dict:
    cmd = [sys.executable, "-m", "place3d_app.cli", "optimize", "--max-evals", str(max_evals), "--task", "seg",
           "--backend", backend, "--quiet"]
    out = {"command": " ".join(["place3d"] + cmd[3:])}
    with tempfile.TemporaryDirectory() as warm_dir:
        env = _env(WARP_CACHE_PATH=Path(warm_dir, "warp"), PLACE3D_CACHE=Path(warm_dir, "psog"))
        with tempfile.TemporaryDirectory() as o:
            _run(cmd + ["--output", o], env, timeout)          # fills both caches; not timed
        walls = []
        for _ in range(REPEATS):
            with tempfile.TemporaryDirectory() as o:
                w, tail = _run(cmd + ["--output", o], env, timeout)
            walls.append(w)
        out["warm_s"] = stats(walls)
        out["stdout_tail"] = tail
    walls = []
    for _ in range(REPEATS):
        with tempfile.TemporaryDirectory() as cold_dir, tempfile.TemporaryDirectory() as o:
            env = _env(WARP_CACHE_PATH=Path(cold_dir, "warp"), PLACE3D_CACHE=Path(cold_dir, "psog"))
            walls.append(_run(cmd + ["--output", o], env, timeout)[0])
    out["cold_s"] = stats(walls)
    print(f"(a) {out['command']}: warm {out['warm_s']['median']:.2f} s, cold {out['cold_s']['median']:.2f} s",
          flush=True)
    return out


# ----------------------------------------------------------------------------- (b) ray-mesh
def _plain_device(backend: str) -> str | None:
    """Warp device of the plain kernel for ``backend``: its own for warp:*, the first CUDA GPU for an OpenCL
    GPU backend when Warp has one (the same GPU on a one-GPU host), else None (no plain comparison)."""
    if backend.startswith("warp:"):
        return backend[5:]
    if backend.startswith("opencl:") and backend != "opencl:pocl":
        try:
            import warp as wp

            wp.init()
            return "cuda:0" if wp.get_cuda_device_count() else None
        except Exception:  # noqa: BLE001 - no Warp here: the OpenCL figures stand alone
            return None
    return None


def _plain_warp(device: str):
    """A plain Warp ray caster: float32 rays, SAH BVH, ``mesh_query_ray``, hit distance or -1."""
    import warp as wp

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def plain_raycast(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), t_max: float,
                      out_t: wp.array(dtype=float)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], d[i], t_max)
        out_t[i] = wp.where(q.result, q.t, -1.0)

    return wp, plain_raycast


def ray_mesh(backend: str, triangles: int, azimuths: int) -> dict:
    import place3d_kernels as p3k
    from place3d_kernels.scene.city import box_city

    lidar = p3k.LidarModel.uniform(64, (-25, 15), azimuths, max_range=200)
    o, d = p3k.lidar_rays(lidar, p3k.Placement.load("pyramid"), backend="reference")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t_max = float(lidar.max_range)
    mesh = box_city(triangles)
    b = p3k.get_backend(backend)
    n = len(o)
    out = {"rays": n, "triangles": int(len(mesh.faces))}

    t = time.perf_counter()
    mesh.handle(b)
    out["api_bvh_build_s"] = time.perf_counter() - t
    # the API on float32 rays (the same dtype and bytes as the plain kernel's inputs below; origins in the
    # world frame, as the API takes them) and on the float64 rays, each with its per-step split
    o32w, d32 = np.ascontiguousarray(o, dtype=np.float32), np.ascontiguousarray(d, dtype=np.float32)
    from place3d_kernels.profiling import profile

    for key, (oo, dd) in (("api", (o32w, d32)), ("api_f64", (o, d))):
        p3k.raycast(mesh, oo, dd, t_max, backend=b)    # warm-up (compiles on a cold cache)
        walls = []
        with profile(print_table=False) as prof:       # per-step split of the API call (prepare, backend, ...)
            for _ in range(API_REPEATS):
                t = time.perf_counter()
                got = p3k.raycast(mesh, oo, dd, t_max, backend=b)
                walls.append(time.perf_counter() - t)
        out[f"{key}_s"] = stats(walls)
        out[f"{key}_steps_mean_s"] = {k[-1]: v[0] / v[1] for k, v in prof.totals.items()}
        out[f"{key}_mrays_s"] = n / out[f"{key}_s"]["median"] / 1e6
        if key == "api":
            hits = got
    out["api_rays"] = "float32 world-frame origins and directions (api_f64: the float64 rays)"

    dev = _plain_device(backend)
    if dev is not None:
        wp, kernel = _plain_warp(dev)
        out["plain_device"] = f"warp:{dev}"
        v32 = np.ascontiguousarray(mesh.vertices - mesh.shift, dtype=np.float32)
        t = time.perf_counter()
        wmesh = wp.Mesh(points=wp.array(v32, dtype=wp.vec3, device=dev),
                        indices=wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32,
                                         device=dev), bvh_constructor="sah")
        wp.synchronize_device(dev)
        out["plain_bvh_build_s"] = time.perf_counter() - t
        o32 = np.ascontiguousarray(o - mesh.shift, dtype=np.float32)

        def numpy_io():
            oa = wp.array(o32, dtype=wp.vec3, device=dev)
            da = wp.array(d32, dtype=wp.vec3, device=dev)
            ta = wp.empty(n, dtype=float, device=dev)
            wp.launch(kernel, dim=n, inputs=[wmesh.id, oa, da, t_max, ta], device=dev)
            return ta.numpy()

        plain_t = numpy_io()
        walls = []
        for _ in range(API_REPEATS):
            t = time.perf_counter()
            numpy_io()
            walls.append(time.perf_counter() - t)
        out["plain_numpy_io_s"] = stats(walls)
        oa, da = wp.array(o32, dtype=wp.vec3, device=dev), wp.array(d32, dtype=wp.vec3, device=dev)
        ta = wp.empty(n, dtype=float, device=dev)
        walls = []
        for _ in range(REPEATS):
            wp.synchronize_device(dev)
            t = time.perf_counter()
            wp.launch(kernel, dim=n, inputs=[wmesh.id, oa, da, t_max, ta], device=dev)
            wp.synchronize_device(dev)
            walls.append(time.perf_counter() - t)
        out["plain_kernel_s"] = stats(walls)
        out["plain_numpy_io_mrays_s"] = n / out["plain_numpy_io_s"]["median"] / 1e6
        out["plain_kernel_mrays_s"] = n / out["plain_kernel_s"]["median"] / 1e6
        out["api_over_plain_numpy_io"] = out["api_s"]["median"] / out["plain_numpy_io_s"]["median"]
        out["api_f64_over_plain_numpy_io"] = out["api_f64_s"]["median"] / out["plain_numpy_io_s"]["median"]
        # The host's copies vary from call to call (2.5-5.5 ms for the same call on one H100 host), so the
        # ratio is also taken in PAIRED rounds that time the API (float32 rays) and the plain kernel back to
        # back: median and range of the per-round ratios. For an OpenCL backend these alternate OpenCL and
        # CUDA calls, which may pay context switches; api_over_plain_numpy_io (blocks of one kind) has none.
        api_w, plain_w = [], []
        for _ in range(PAIRED):
            t = time.perf_counter()
            p3k.raycast(mesh, o32w, d32, t_max, backend=b)
            api_w.append(time.perf_counter() - t)
            t = time.perf_counter()
            numpy_io()
            plain_w.append(time.perf_counter() - t)
        out["paired_rounds"] = PAIRED
        out["paired_api_s"], out["paired_plain_s"] = stats(api_w), stats(plain_w)
        out["paired_api_over_plain"] = stats([a / p for a, p in zip(api_w, plain_w)])
        both = np.isfinite(hits.t) & (plain_t >= 0)
        out["hits_agree_1e-4m"] = float(np.mean(np.abs(hits.t[both] - plain_t[both]) <= 1e-4)) if both.any() else None
        out["hit_mismatch"] = int(np.sum(np.isfinite(hits.t) != (plain_t >= 0)))
    if getattr(b, "resident_kernels", False):
        _kernel_only(out, b, mesh, o, d, t_max, backend)
    if "paired_api_over_plain" in out:
        r = out["paired_api_over_plain"]
        print(f"(b) paired rounds: API / plain {r['median']:.2f} [{r['min']:.2f}-{r['max']:.2f}]; in blocks "
              f"{out['api_over_plain_numpy_io']:.2f}", flush=True)
    print(f"(b) ray-mesh {n} rays: API {out['api_mrays_s']:.1f} M rays/s "
          f"(float32; float64 {out['api_f64_mrays_s']:.1f})"
          + (f", plain Warp numpy-io {out['plain_numpy_io_mrays_s']:.1f}, kernel {out['plain_kernel_mrays_s']:.1f}"
             if "plain_kernel_mrays_s" in out else ""), flush=True)
    return out


# ----------------------------------------------------------------------------- (c) dense rig
def _kernel_only(out: dict, b, mesh, o, d, t_max: float, backend: str) -> None:
    """This backend's ray-mesh kernel alone (``resident_raycast``: rays already on the device, float64 hit
    distances, watertight BVH) against the plain Warp ``mesh_query_ray`` kernel on the same GPU, same
    rays (float32) and same city with a SAH BVH, launched back to back in ``PAIRED`` rounds, each launch
    synchronised, each timed launch after an untimed one (since 2026-11-25): per-round ratio, median and
    range (issue 17 goal 2: the kernel at or above the plain one)."""
    import warp as wp

    dev = _plain_device(backend)
    if dev is None:
        print(f"(b) kernel only: no plain Warp kernel to pair {backend} with (no CUDA GPU for Warp)", flush=True)
        return
    wp_, plain = _plain_warp(dev)
    run = b.resident_raycast(mesh.handle(b), o - mesh.shift, d, t_max)
    v32 = np.ascontiguousarray(mesh.vertices - mesh.shift, dtype=np.float32)
    wmesh = wp.Mesh(points=wp.array(v32, dtype=wp.vec3, device=dev),
                    indices=wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32,
                                     device=dev), bvh_constructor="sah")
    oa = wp.array(np.ascontiguousarray(o - mesh.shift, dtype=np.float32), dtype=wp.vec3, device=dev)
    da = wp.array(np.ascontiguousarray(d, dtype=np.float32), dtype=wp.vec3, device=dev)
    ta = wp.empty(len(o), dtype=float, device=dev)

    def ours():
        run()
        b.synchronize()

    def theirs():
        wp.launch(plain, dim=len(o), inputs=[wmesh.id, oa, da, t_max, ta], device=dev)
        wp.synchronize_device(dev)

    ours(), theirs()                              # compile and warm both
    mine, plain_w = [], []
    for _ in range(PAIRED):
        for fn, acc in ((ours, mine), (theirs, plain_w)):
            # once untimed: an OpenCL backend's first launch after a CUDA one (and back) paid for the switch
            # between the two APIs' contexts on the GPU (raymesh_bvh.py, tag lab-2026-11-27), not the kernel's time
            fn()
            t = time.perf_counter()
            fn()
            acc.append(time.perf_counter() - t)
    n = len(o)
    out["kernel_only_paired_rounds"] = PAIRED
    out["kernel_only_s"], out["kernel_only_plain_s"] = stats(mine), stats(plain_w)
    out["kernel_only_mrays_s"] = n / out["kernel_only_s"]["median"] / 1e6
    out["kernel_only_plain_mrays_s"] = n / out["kernel_only_plain_s"]["median"] / 1e6
    out["kernel_only_over_plain"] = stats([a / p for a, p in zip(mine, plain_w)])
    r = out["kernel_only_over_plain"]
    print(f"(b) kernel only, {PAIRED} paired rounds: {out['kernel_only_mrays_s']:.0f} M rays/s against plain Warp "
          f"{out['kernel_only_plain_mrays_s']:.0f}; time ratio {r['median']:.2f} [{r['min']:.2f}-{r['max']:.2f}]",
          flush=True)


def dense_rig(backend: str, voxel: float, pop: int, timeout: int) -> dict:
    runs = []
    for _ in range(REPEATS):
        with tempfile.TemporaryDirectory() as o:
            _run([sys.executable, str(ROOT / "bench" / "gpu_dense.py"), "--backends", backend, "--voxel", str(voxel),
                  "--pop", str(pop), "--output", str(Path(o, "dense.json"))], _env(), timeout)
            runs.append(json.loads(Path(o, "dense.json").read_text())["backends"][backend])
    out = {"voxel": voxel, "population": pop, "rig": "4 x 64 x 2048 rays"}
    for key in ("single_eval_ms", "population_eval_ms", "amortised_eval_ms"):
        out[key] = stats([r[key] for r in runs])
    out["scores_head"] = runs[0]["scores_head"]
    out["scores_identical_across_runs"] = all(r["scores_head"] == runs[0]["scores_head"] for r in runs)
    print(f"(c) dense rig: {out['amortised_eval_ms']['median']:.2f} ms per rig amortised over {pop}", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", default="warp:cuda:0")
    ap.add_argument("--out", default=os.environ.get("OUT") or str(ROOT / "bench" / "results"))
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test on a CPU)")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: a,b,c")
    ap.add_argument("--machine", default=None, help="machine label (default: the GPU model, or cpu-<cores>core)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from results_io import write_result

    skip = set(filter(None, args.skip.split(",")))
    q = args.quick
    res = {"backend": args.backend, "quick": q, "repeats": REPEATS}
    parts = {"a": ("whole_command", lambda: whole_command(args.backend, 60 if q else 2000, 900)),
             "b": ("ray_mesh", lambda: ray_mesh(args.backend, 20_000 if q else 1_000_000, 128 if q else 2048)),
             "c": ("dense_rig", lambda: dense_rig(args.backend, 0.4 if q else 0.05, 2 if q else 16, 900))}
    for key, (name, fn) in parts.items():
        if key in skip:
            continue
        try:
            res[name] = fn()
        except Exception as e:  # noqa: BLE001 - one failing part must not lose the others' figures
            res[name] = {"error": f"{type(e).__name__}: {e}"[-3000:]}
            print(f"({key}) {name} failed: {res[name]['error']}", flush=True)
    print("wrote", write_result("gpu-speed", res, args.machine, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
