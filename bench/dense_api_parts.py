#!/usr/bin/env python3
"""Where the dense rig's API time goes beyond its kernel (issue 17, goal 3), on a CUDA Warp backend.

Workload as ``gpu_dense.py``: 16 perturbed ``pyramid`` rigs of the dense LiDAR (4 x 64 x 2048 rays) on the
default town's P-SOG at 0.05 m. Times, each synchronised, 5 rounds after a warm-up, median [min-max] ms:
``msog_batch`` as a user calls it; ``score_placements`` on local poses; and the parts that
``WarpBackend.score_placements`` runs on CUDA, one at a time: zeroed bitsets as a fresh array (``zeros``,
``wp.zeros``: the backend's way until 2026-11-25) and as the backend now does it, a kept buffer zeroed
in place (``zero_kept``), the score kernel, the bit count (``count``: since 2026-11-25 the backend's
``score_gpu.count_clear_kernel``, coalesced reads that also zero what they count, so a kept buffer needs no
``zero_kept``; ``count_old``: ``kernels.count_bits_kernel`` with the words per thread the backend used
before), the download (``download``: sums and counts in one array, as the backend now fetches them;
``download_two``: two arrays, as before). Checks that the parts' sums and counts equal the API's.

    python3 bench/dense_api_parts.py [--device cuda:0] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def dense_workload(device: str, voxel: float, pop: int) -> SimpleNamespace:
    """The dense-rig workload on backend ``warp:<device>``: the default town's P-SOG at ``voxel``, the dense
    LiDAR, ``pop`` perturbed ``pyramid`` rigs (also in grid-local poses), the seg handle and the score
    kernel's device inputs (sensor directions, rotations, positions, each brick's masks as one uint64)."""
    import warp as wp

    import place3d_kernels as p3k
    from place3d_kernels.backends.base import rotation_matrices, sensor_directions
    from place3d_kernels.backends.bricks import brick_shape

    b = p3k.get_backend(f"warp:{device}")
    d = p3k.DEFAULT_GRID
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=p3k.Grid(d.lower, d.upper, voxel), backend=b)
    dense = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=100.0, name="dense64x2048")
    rng = np.random.default_rng(0)
    poses = np.repeat(p3k.Placement.load("pyramid").poses[None], pop, axis=0)
    poses[..., :3] += rng.uniform(-0.3, 0.3, poses[..., :3].shape).round(1)
    p = psog.for_task("seg")
    handle = p.handle(b, "sog")
    local = poses.copy()
    local[..., :3] = p.grid.to_local(poses[..., :3])
    spec = handle.spec
    bx, by, bz = brick_shape(spec.shape)
    dev = b.device
    sd = sensor_directions(dense.elevations, dense.azimuths)
    # the CUDA handle holds each brick's masks as one uint64; a CPU handle (smoke runs) as two uint32
    masks64 = handle.masks if handle.masks.dtype == wp.uint64 else wp.array(
        handle.masks.numpy().view(np.uint64), dtype=wp.uint64, device=dev)
    return SimpleNamespace(
        b=b, psog=psog, dense=dense, pop=poses, handle=handle, local=local, spec=spec,
        nx=spec.shape[0], ny=spec.shape[1], nz=spec.shape[2], by=by, bz=bz, words=bx * by * bz,
        P=local.shape[0], L=local.shape[1], dev=dev, sd=sd, sd_a=wp.array(sd, dtype=wp.vec3d, device=dev),
        masks64=masks64, rot=wp.array(rotation_matrices(local.reshape(-1, 6)), dtype=wp.mat33d, device=dev),
        pos=wp.array(np.ascontiguousarray(local.reshape(-1, 6)[:, :3]), dtype=wp.vec3d, device=dev))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    import place3d_kernels as p3k
    from place3d_app.kernel_bench import machine_info

    w = dense_workload(args.device, args.voxel, args.pop)
    b, psog, dense, pop, handle, local, spec = w.b, w.psog, w.dense, w.pop, w.handle, w.local, w.spec
    nx, ny, nz, by, bz, words, P, L, dev = w.nx, w.ny, w.nz, w.by, w.bz, w.words, w.P, w.L, w.dev
    sd, sd_a, masks64, rot, pos = w.sd, w.sd_a, w.masks64, w.rot, w.pos
    g = b.score_gpu
    state = {}

    def zeros():
        state["bits"] = wp.zeros(P * words, dtype=wp.uint32, device=dev)
        state["both"] = wp.zeros(2 * P, dtype=wp.int64, device=dev)
        state["sums"], state["counts"] = state["both"][:P], state["both"][P:]

    def kernel():
        wp.launch(g.score_kernel_gpu, dim=P * L * len(sd), device=dev,
                  inputs=[sd_a, rot, pos, int(L), float(dense.max_range), float(spec.voxel_size), int(nx), int(ny),
                          int(nz), int(by), int(bz), masks64, handle.weights, int(words), state["bits"],
                          state["sums"]], block_dim=g.SCORE_BLOCK_DIM)

    def count():
        t = g.count_threads_per_candidate(words, P)       # as the backend counts
        wp.launch(g.count_clear_kernel, dim=P * t, device=dev, inputs=[state["bits"], int(words), int(t),
                                                                        state["counts"]], block_dim=g.SCORE_BLOCK_DIM)

    def count_old():
        per = b.k.count_words_per_thread(P * words)       # as the backend counted until 2026-11-25
        chunks = -(-words // per)
        wp.launch(b.k.count_bits_kernel, dim=P * chunks, device=dev,
                  inputs=[state["bits"], int(words), int(chunks), int(per), state["counts"]])

    def download():
        out = state["both"].numpy()
        state["out"] = (out[:P], out[P:])

    def download_two():
        state["out"] = (state["sums"].numpy(), state["counts"].numpy())

    def timed(fn, before=None):
        xs = []
        for _ in range(args.rounds + 1):
            if before is not None:
                before()
            wp.synchronize_device(dev)
            t = time.perf_counter()
            fn()
            wp.synchronize_device(dev)
            xs.append(1e3 * (time.perf_counter() - t))
        xs = xs[1:]
        return {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}

    res = {"info": machine_info(), "device": args.device, "population": P, "rays_per_rig": L * len(sd),
           "bitset_bytes": 4 * P * words, "ms": {}}
    res["ms"]["msog_batch"] = timed(lambda: p3k.msog_batch(psog, dense, pop, backend=b))
    res["ms"]["score_placements"] = timed(lambda: b.score_placements(handle, dense.elevations, dense.azimuths,
                                                                     dense.max_range, local))
    res["ms"]["zeros"] = timed(zeros)
    kept = wp.empty(P * words, dtype=wp.uint32, device=dev)
    res["ms"]["zero_kept"] = timed(lambda: kept.zero_())
    res["ms"]["kernel"] = timed(kernel, before=zeros)
    res["ms"]["count"] = timed(count, before=lambda: (zeros(), kernel()))
    res["ms"]["count_old"] = timed(count_old, before=lambda: (zeros(), kernel()))
    res["ms"]["download_two"] = timed(download_two, before=lambda: (zeros(), kernel(), count()))
    res["ms"]["download"] = timed(download, before=lambda: (zeros(), kernel(), count()))
    want = b.score_placements(handle, dense.elevations, dense.azimuths, dense.max_range, local)
    res["parts_equal_api"] = bool(np.array_equal(state["out"][0], want[0]) and np.array_equal(state["out"][1], want[1]))
    for k, v in res["ms"].items():
        print(f"{k:18s} {v['median']:8.3f} ms [{v['min']:.3f}-{v['max']:.3f}]", flush=True)
    print("parts' sums and counts equal the API's:", res["parts_equal_api"], flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=2))
    return 0 if res["parts_equal_api"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
