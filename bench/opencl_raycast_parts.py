#!/usr/bin/env python3
"""Where an OpenCL GPU backend's ray-mesh API call spends its time (issue 17, goal 2's API clause).

    python3 bench/opencl_raycast_parts.py [--backend opencl:nvidia] [--cprofile]

On the 1M-triangle city with the dense rig's 524,288 rays: ``p3k.raycast`` on float32 and float64 rays,
then the pieces a call is made of, each timed alone (7 repeats, median [min-max] ms, queue finished
before and after): an input buffer made with ``COPY_HOST_PTR``, a 4 MB output allocation, pageable
copies each way, and the same through a pinned (``ALLOC_HOST_PTR``) staging buffer; then the API with
the backend's device buffers pooled between calls and made per call (alternating blocks), and the steps
of one ``raycast_checked`` call. ``--cprofile``
adds a cProfile of 10 API calls (where the Python side waits). A probe: one run of it is what
``bench/results/opencl-api-probe-H100-2026-11-25.txt`` and ``opencl-api-cprofile-H100-2026-11-25.txt`` hold.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", default="opencl:nvidia")
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--cprofile", action="store_true")
    args = ap.parse_args(argv)
    import pyopencl as cl

    import place3d_kernels as p3k
    from place3d_kernels.scene.city import box_city

    b = p3k.get_backend(args.backend)
    lidar = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=200)
    o, d = p3k.lidar_rays(lidar, p3k.Placement.load("pyramid"), backend="reference")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    city = box_city(args.triangles)
    city.handle(b)
    o32, d32 = np.ascontiguousarray(o, dtype=np.float32), np.ascontiguousarray(d, dtype=np.float32)
    n = len(o)

    def timed(name, fn, k=7):
        fn()
        xs = []
        for _ in range(k):
            b.queue.finish()
            t = time.perf_counter()
            fn()
            b.queue.finish()
            xs.append(1e3 * (time.perf_counter() - t))
        print(f"{name:40s} {statistics.median(xs):7.3f} ms [{min(xs):.3f}-{max(xs):.3f}]", flush=True)

    mf = cl.mem_flags
    timed("p3k.raycast float32", lambda: p3k.raycast(city, o32, d32, 200.0, backend=b))
    timed("p3k.raycast float64", lambda: p3k.raycast(city, o, d, 200.0, backend=b))
    timed("COPY_HOST_PTR buffer, 6.3 MB", lambda: cl.Buffer(b.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=o32))
    timed("output buffer allocated, 4 MB", lambda: cl.Buffer(b.ctx, mf.READ_WRITE, size=8 * n))
    buf, host = cl.Buffer(b.ctx, mf.READ_WRITE, size=8 * n), np.empty(n, np.float64)
    timed("enqueue_copy D2H 4 MB pageable", lambda: cl.enqueue_copy(b.queue, host, buf))
    dev = cl.Buffer(b.ctx, mf.READ_ONLY, size=o32.nbytes)
    timed("enqueue_copy H2D 6.3 MB pageable", lambda: cl.enqueue_copy(b.queue, dev, o32))
    pin = cl.Buffer(b.ctx, mf.READ_WRITE | mf.ALLOC_HOST_PTR, size=o32.nbytes)
    m, _ = cl.enqueue_map_buffer(b.queue, pin, cl.map_flags.WRITE, 0, (o32.nbytes,), np.uint8)
    timed("host memcpy into mapped pinned 6.3 MB", lambda: np.copyto(m, o32.view(np.uint8).reshape(-1)))
    m.base.release(b.queue)
    b.queue.finish()
    timed("enqueue_copy pinned->device 6.3 MB", lambda: cl.enqueue_copy(b.queue, dev, pin))
    # the API with device buffers pooled between calls (the default) and made per call, alternating blocks
    api = {True: [], False: []}
    for _ in range(5):
        for reuse in (True, False):
            b.reuse_device_buffers = reuse
            p3k.raycast(city, o32, d32, 200.0, backend=b)
            for _ in range(7):
                t = time.perf_counter()
                p3k.raycast(city, o32, d32, 200.0, backend=b)
                api[reuse].append(1e3 * (time.perf_counter() - t))
    b.reuse_device_buffers = True
    for reuse, xs in api.items():
        print(f"{'p3k.raycast f32, buffers ' + ('pooled' if reuse else 'per call'):40s} "
              f"{statistics.median(xs):7.3f} ms [{min(xs):.3f}-{max(xs):.3f}] ({len(xs)} calls)", flush=True)
    # the steps of one raycast_checked call, each waited for
    h = city.handle(b)
    timed("raycast_checked alone (f32)", lambda: b.raycast_checked(h, o32, d32, 200.0, shift=city.shift))
    scratch: list = []
    timed("two ray uploads into pooled buffers", lambda: (b._upload(o32, scratch), b._upload(d32, scratch),
                                                          b._scratch_give(scratch), scratch.clear()))
    out = cl.Buffer(b.ctx, mf.READ_WRITE, size=20 * n)
    if b._pinned is not None:           # GPUs only (CPU devices write the host block in place)
        blk, pinned_host = b._pinned.take(20 * n)
        timed("one 10.5 MB download into a pinned block", lambda: cl.enqueue_copy(b.queue, pinned_host, out))
    timed("one 10.5 MB download, pageable, fresh", lambda: cl.enqueue_copy(b.queue, np.empty(20 * n, np.uint8), out))
    if args.cprofile:
        pr = cProfile.Profile()
        pr.enable()
        for _ in range(10):
            p3k.raycast(city, o32, d32, 200.0, backend=b)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(18)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
