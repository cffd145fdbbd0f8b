#!/usr/bin/env python3
"""A lock-step lane model of the dense-rig score kernel's variants, from per-ray step counts (no GPU).

For one dense rig (``pyramid``, 4 x 64 x 2048 rays) over the default town's P-SOG, with the stop mask,
it counts each ray's voxel steps (the shipped float32 walk, ``traverse_count_kernel``, on the CPU), then
models a warp as 32 lanes in lock-step:

* one thread per ray (the shipped kernel, ``tiled-CxA``): a warp of 32 rays costs ``S`` (the set-up,
  walk32_begin, in step-equivalents) plus its longest ray's steps;
* persistent threads (``persist-*``): each pass costs one step, plus ``S`` when any lane sets up a new ray
  in it (a lane's set-up stalls the warp); a lane whose ray has ended takes the next one from a shared
  counter (in tile order) at once, or, with batch B, once B lanes of its warp (or all that still have
  work) are done. ``threads_per_rig`` persistent threads serve the rig: the GPU's resident threads at
  80 registers, 101,376 on an H100, shared by 16 rigs.

It also measures divergence inside a step, for the rays of one LiDAR in the shipped order (``branches``):
how many different axes the lanes of a warp step along at the same step (walk32_next takes one branch
per axis, and a warp runs each branch present, the other lanes idle), and how often a lane enters a new
4 x 4 x 2 brick (the masks load, bitset read and flush run only for those lanes).

Lane efficiency = useful steps / (32 x modelled warp passes). It leaves out memory (coherence of nearby
rays, atomics), the end-of-launch tail and everything but step counts; it ranks variants for the GPU run
(``gpu_dense_variants.py``), it does not time them. Writes ``<--out>/gpu-dense-lanes-<voxel>m.json``.

    python3 bench/gpu_dense_lanes.py [--voxel 0.1] [--setup 0 5 10] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import warp as wp

import place3d_kernels as p3k
from place3d_kernels.backends.base import rotation_matrices, sensor_directions
from place3d_app.kernel_bench import machine_info

H100_THREADS_80_REGS = 132 * 768     # 132 SMs x 6 blocks of 128 threads (80 registers each)


def step_counts(psog, lidar, poses) -> np.ndarray:
    """Voxel steps of each ray of one rig ((L, 6) poses), in the shipped (LiDAR, channel, azimuth) order,
    the stop mask on: the walk of the score kernel, counted with ``traverse_count_kernel`` on the CPU."""
    b = p3k.get_backend("warp:cpu")
    sd = sensor_directions(lidar.elevations, lidar.azimuths)
    rot = rotation_matrices(poses)
    local = psog.grid.to_local(poses[:, :3])
    d = np.einsum("lij,nj->lni", rot, sd).reshape(-1, 3)
    o = np.repeat(local, len(sd), axis=0)
    nx, ny, nz = psog.grid.shape
    counts = wp.zeros(len(o), dtype=wp.int64, device="cpu")
    stop = wp.array(np.asarray(psog.stop_mask).reshape(-1).astype(np.uint8), dtype=wp.uint8, device="cpu")
    wp.launch(b.k.traverse_count_kernel, dim=len(o), device="cpu",
              inputs=[wp.array(o, dtype=wp.vec3d, device="cpu"), wp.array(d, dtype=wp.vec3d, device="cpu"),
                      wp.array(np.full(len(o), lidar.max_range), dtype=wp.float64, device="cpu"),
                      float(psog.grid.voxel_size), int(nx), int(ny), int(nz), stop, 1, counts])
    return counts.numpy()


def tile_order(n_lidars: int, n_el: int, n_az: int, tile_c: int) -> np.ndarray:
    """Shipped ray indices in ``tiled_ray``'s order (gpu_dense_variants_kernels.py)."""
    tile_a = 32 // tile_c
    idx = np.arange(n_lidars * n_el * n_az).reshape(n_lidars, n_el // tile_c, tile_c, n_az // tile_a, tile_a)
    return idx.transpose(0, 1, 3, 2, 4).reshape(-1)


def one_thread_per_ray(c: np.ndarray, setup: float) -> float:
    per_warp = c.reshape(-1, 32).max(axis=1) + setup
    return float(c.sum() / (32 * per_warp.sum()))


def persistent(c: np.ndarray, threads: int, setup: float, batch: int) -> float:
    """Lane efficiency of persistent warps taking rays ``c`` (in fetch order) from a shared counter. As in
    ``make_persistent``: a lane sets a new ray up in a pass of its own (no step in it), and takes it in the
    pass after its previous ray's last step; while rays are left, a lane without one waits until ``batch``
    lanes of its warp are without one."""
    W = threads // 32
    left = np.zeros((W, 32), dtype=np.int64)          # steps left of each lane's ray (0: none in hand)
    nxt, n = 0, len(c)
    cost = 0.0
    while True:
        done = left == 0
        if nxt >= n and done.all():
            break
        busy = ~done.all(axis=1) | (nxt < n)          # warps still looping
        take = np.zeros_like(done)
        if nxt < n:
            take = done & (done.sum(axis=1) >= batch)[:, None]
            idx = np.flatnonzero(take)[: n - nxt]     # the counter hands out rays in warp, lane order
            take = np.zeros(take.size, bool)
            take[idx] = True
            take = take.reshape(done.shape)
            left[take] = c[nxt:nxt + len(idx)]
            nxt += len(idx)
        step = ~done & ~take
        left[step] -= 1
        cost += float((busy + setup * take.any(axis=1)).sum())
    return float(c.sum() / (32 * cost))


def branch_stats(psog, lidar, pose) -> dict:
    """Per-step branch divergence of one LiDAR's rays (``pose``: (6,)) run 32 to a warp in the shipped
    (channel, azimuth) order, lane t of every warp at its ray's t-th step."""
    grid = psog.grid
    o, d = p3k.lidar_rays(lidar, pose[None])
    tr = p3k.traverse(grid, o, d, lidar.max_range, backend="warp:cpu", stop=np.asarray(psog.stop_mask))
    nx, ny, nz = grid.shape
    v = tr.voxels
    i, j, k = v // (ny * nz), (v // nz) % ny, v % nz
    dv = np.stack([np.diff(i), np.diff(j), np.diff(k)], axis=1)
    axis = np.where((dv != 0).sum(axis=1) == 1, np.argmax(dv != 0, axis=1), 3).astype(np.int8)   # 3: a corner
    brick = (i >> 2) * 1_000_000_007 + (j >> 2) * 65_537 + (k >> 1)
    enter = np.diff(brick) != 0
    first = tr.offsets[:-1]
    n = np.diff(tr.offsets) - 1                      # steps from one voxel to the next, per ray
    T = int(n.max())
    A = np.full((len(n), T), -1, dtype=np.int8)
    E = np.zeros((len(n), T), dtype=bool)
    r = np.repeat(np.arange(len(n)), np.maximum(n, 0))
    t = np.arange(len(r)) - np.repeat(np.cumsum(np.maximum(n, 0)) - np.maximum(n, 0), np.maximum(n, 0))
    src = np.repeat(first, np.maximum(n, 0)) + t     # transition voxels[src] -> voxels[src + 1]
    A[r, t] = axis[src]
    E[r, t] = enter[src]
    W = len(n) // 32
    A, E = A[:W * 32].reshape(W, 32, T), E[:W * 32].reshape(W, 32, T)
    active = A >= 0
    lanes = active.sum(axis=1)                       # (W, T) active lanes per warp-step
    live = lanes > 0
    kinds = sum((A == a).any(axis=1) for a in range(4))
    entries = E.sum(axis=1)
    return {"rays": int(len(n)), "warp_steps": int(live.sum()),
            "mean_active_lanes": float(lanes[live].mean()),
            "mean_axes_per_warp_step": float(kinds[live].mean()),
            "share_of_warp_steps_with_2plus_axes": float((kinds[live] >= 2).mean()),
            "lane_use_in_axis_branches": float(lanes.sum() / (32 * kinds.sum())),
            "share_of_warp_steps_with_a_brick_entry": float((entries[live] > 0).mean()),
            "lane_use_in_brick_entry_branch": float(entries.sum() / (32 * (entries > 0).sum())),
            "brick_entries_per_step": float(E.sum() / active.sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.1)
    ap.add_argument("--azimuths", type=int, default=2048)
    ap.add_argument("--setup", type=float, nargs="*", default=[0.0, 5.0, 10.0],
                    help="ray set-up cost in step-equivalents")
    ap.add_argument("--threads-per-rig", type=int, default=H100_THREADS_80_REGS // 16)
    ap.add_argument("--out", default=os.environ.get("OUT", str(Path(__file__).resolve().parent / "results")))
    args = ap.parse_args()
    d0 = p3k.DEFAULT_GRID
    grid = p3k.Grid(d0.lower, d0.upper, args.voxel)
    t = time.perf_counter()
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend="warp:cpu")
    lidar = p3k.LidarModel.uniform(64, (-25, 15), args.azimuths, max_range=100.0)
    poses = p3k.Placement.load("pyramid").poses
    c = step_counts(psog, lidar, poses)
    count_s = time.perf_counter() - t
    L, C, A = len(poses), len(lidar.elevations), len(lidar.azimuths)
    out = {"info": machine_info(), "grid": grid.to_dict(), "rays": len(c), "steps": int(c.sum()),
           "steps_per_ray_p10_p50_p90_max": [float(np.percentile(c, q)) for q in (10, 50, 90)] + [int(c.max())],
           "zero_step_rays": int((c == 0).sum()), "threads_per_rig": args.threads_per_rig,
           "count_s": count_s, "lane_efficiency": {}}
    for S in args.setup:
        row = {}
        for tc in (1, 2, 4, 8, 32):
            row[f"tiled-{tc}x{32 // tc}"] = one_thread_per_ray(c[tile_order(L, C, A, tc)], S)
        for tc in (1, 4):
            order = c[tile_order(L, C, A, tc)]
            for batch in (1, 8, 16):
                row[f"persist-t{tc}x{32 // tc}-b{batch}"] = persistent(order, args.threads_per_rig, S, batch)
        out["lane_efficiency"][f"setup={S:g}"] = row
        print(f"setup {S:g} step-equivalents:", {k: round(v, 3) for k, v in row.items()}, flush=True)
    out["branches_lidar0"] = branch_stats(psog, lidar, poses[0])
    print("branches (LiDAR 0):", out["branches_lidar0"], flush=True)
    res = Path(args.out)
    res.mkdir(parents=True, exist_ok=True)
    path = res / f"gpu-dense-lanes-{args.voxel}m.json"
    path.write_text(json.dumps(out, indent=2))
    print("wrote", path)


if __name__ == "__main__":
    main()
