#!/usr/bin/env python3
"""The dense rig's bit count inside the score kernel, or as a pass of its own (issue 17, goal 3).

After every score launch the backend counts each candidate's set bits (``count_clear_kernel``, which also
zeroes the words for the next call): 0.87-0.94 ms per 16 dense rigs on the H100, against 25.45 ms of
score kernel. Two alternatives, timed here against it, each launch's sums and counts checked equal:

* ``fused``: the score kernel's flush always waits for the old bitset word (today only bricks holding
  entropy do) and adds the bits it set first to a per-ray count, so no count pass is needed, only the
  buffer's zeroing (``zero_``);
* ``clear4``: the count pass with four independent loads per thread in flight per iteration;
* ``clear64``: the count pass on 64-bit words, two loads a thread per iteration (even word counts only).

Workload as ``dense_api_parts.py`` (16 perturbed ``pyramid`` rigs of 4 x 64 x 2048 rays, 0.05 m grid).
5 interleaved rounds after a warm-up; median [min-max] ms per launch of each complete sequence.

    python3 bench/dense_fused_count.py [--device cuda:0] [--out FILE]

The fused kernel reuses the shipped kernel's helpers from ``score_gpu`` (it is a study, not a frozen copy).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from place3d_kernels.backends.warp import score_gpu as g  # noqa: E402
from place3d_kernels.backends.warp.kernels import walk32_begin  # noqa: E402

wp.set_module_options({"enable_backward": False, "fuse_fp": False, "block_dim": g.SCORE_BLOCK_DIM})


@wp.func
def flush_count(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, bny: wp.int32,
                bnz: wp.int32, ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)):
    # every flush waits for the old word: the bits this ray set first are counted, and weighted where
    # they hold entropy
    add = wp.int64(0)
    cnt = wp.int32(0)
    if pending != wp.uint32(0):
        old = g.atomic_or_word(p, word, pending)
        fresh = pending & ~old
        cnt = wp.bit_count(fresh)
        m = fresh & nz_w
        if m != wp.uint32(0):
            uw = wp.uint32(word)
            bk = wp.int32(uw % wp.uint32(bnz))
            r = uw / wp.uint32(bnz)
            bj = wp.int32(r % wp.uint32(bny))
            bi = wp.int32(r / wp.uint32(bny))
            while m != wp.uint32(0):
                b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))
                i = bi * 4 + (b & 3)
                j = bj * 4 + ((b >> 2) & 3)
                k = bk * 2 + (b >> 4)
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint32(1))
    return add, cnt


@wp.kernel(cuda_max_registers=g.SCORE_MAX_REGISTERS)
def score_fused(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32), sums: wp.array(dtype=wp.int64),
                counts: wp.array(dtype=wp.int64)):
    # score_gpu.score_kernel_gpu with flush_count in place of flush_brick32
    tid = wp.tid()
    n = sensor_dirs.shape[0]
    rig = tid / n
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[tid - rig * n]
    sf = wp.float32(s)
    w0 = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
    t1d = w0.t1d
    w = g.walk_from(w0)
    cbits = g.word_address(bits, wp.int64(cand) * words_per_candidate)
    my_sum = wp.int64(0)
    my_cnt = wp.int32(0)
    cur = wp.int32(-1)
    seen = wp.uint32(0)
    pending = wp.uint32(0)
    nz_w = wp.uint32(0)
    for _ in range(nx + ny + nz + 3):
        if not g.inside(w, nx, ny, nz):
            break
        word = g.word32(w, bny, bnz)
        change = word != cur
        if change and pending != wp.uint32(0):
            a, c = flush_count(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            my_sum += a
            my_cnt += c
        m = g.load_mask(masks64, word)
        fresh = g.load_word(cbits, word)
        stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
        nz_w = wp.uint32(m >> wp.uint64(32))
        seen = wp.where(change, fresh, seen)
        pending = wp.where(change, wp.uint32(0), pending)
        cur = word
        bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
        pending = pending | (bit & ~seen)
        seen = seen | bit
        if (stop_w & bit) != wp.uint32(0):
            break
        w = g.next_step(w, o, d, t1d, s, sf)
    if pending != wp.uint32(0):
        a, c = flush_count(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        my_sum += a
        my_cnt += c
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)
    if my_cnt > 0:
        wp.atomic_add(counts, cand, wp.int64(my_cnt))


@wp.kernel
def count_clear4(bits: wp.array(dtype=wp.uint32), words_per_candidate: wp.int32, threads_per_candidate: wp.int32,
                 counts: wp.array(dtype=wp.int64)):
    # count_clear_kernel with four words a thread per iteration (c, c + T, c + 2T, c + 3T), loaded before
    # any is used
    tid = wp.tid()
    T = threads_per_candidate
    cand = tid / T
    p = g.word_address(bits, wp.int64(cand) * wp.int64(words_per_candidate))
    n = wp.int32(0)
    c = tid - cand * T
    if c < words_per_candidate:
        it = (words_per_candidate - 1 - c) / T + 1
        q = wp.int32(0)
        while q + 4 <= it:
            a0 = c + q * T
            v0 = g.load_word(p, a0)
            v1 = g.load_word(p, a0 + T)
            v2 = g.load_word(p, a0 + 2 * T)
            v3 = g.load_word(p, a0 + 3 * T)
            n += wp.bit_count(v0) + wp.bit_count(v1) + wp.bit_count(v2) + wp.bit_count(v3)
            if (v0 | v1 | v2 | v3) != wp.uint32(0):
                g.store_word(p, a0, wp.uint32(0))
                g.store_word(p, a0 + T, wp.uint32(0))
                g.store_word(p, a0 + 2 * T, wp.uint32(0))
                g.store_word(p, a0 + 3 * T, wp.uint32(0))
            q += 4
        while q < it:
            a0 = c + q * T
            v0 = g.load_word(p, a0)
            if v0 != wp.uint32(0):
                n += wp.bit_count(v0)
                g.store_word(p, a0, wp.uint32(0))
            q += 1
    if n > 0:
        wp.atomic_add(counts, cand, wp.int64(n))


@wp.kernel
def count_clear64(bits64: wp.array(dtype=wp.uint64), halves_per_candidate: wp.int64, threads_per_candidate: wp.int64,
                  counts: wp.array(dtype=wp.int64)):
    # count_clear_kernel on the bitset read as 64-bit words (two 32-bit words a load; needs an even number
    # of words per candidate), two loads a thread per iteration
    tid = wp.int64(wp.tid())
    T = threads_per_candidate
    cand = tid / T
    base = cand * halves_per_candidate
    c = tid - cand * T
    n = wp.int64(0)
    at = c
    while at + T < halves_per_candidate:
        v0 = bits64[base + at]
        v1 = bits64[base + at + T]
        n += wp.int64(wp.bit_count(v0)) + wp.int64(wp.bit_count(v1))
        if v0 != wp.uint64(0):
            bits64[base + at] = wp.uint64(0)
        if v1 != wp.uint64(0):
            bits64[base + at + T] = wp.uint64(0)
        at += wp.int64(2) * T
    if at < halves_per_candidate:
        v0 = bits64[base + at]
        n += wp.int64(wp.bit_count(v0))
        if v0 != wp.uint64(0):
            bits64[base + at] = wp.uint64(0)
    if n > wp.int64(0):
        wp.atomic_add(counts, wp.int32(cand), n)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from dense_api_parts import dense_workload

    from place3d_app.kernel_bench import machine_info

    w = dense_workload(args.device, args.voxel, args.pop)
    b, dense, handle, local, spec = w.b, w.dense, w.handle, w.local, w.spec
    nx, ny, nz, by, bz, words, P, L, dev = w.nx, w.ny, w.nz, w.by, w.bz, w.words, w.P, w.L, w.dev
    sd, sd_a, masks64, rot, pos = w.sd, w.sd_a, w.masks64, w.rot, w.pos
    bits = wp.zeros(P * words, dtype=wp.uint32, device=dev)
    both = wp.zeros(2 * P, dtype=wp.int64, device=dev)
    sums, counts = both[:P], both[P:]
    T = g.count_threads_per_candidate(words, P)
    common = [sd_a, rot, pos, int(L), float(dense.max_range), float(spec.voxel_size), int(nx), int(ny), int(nz),
              int(by), int(bz), masks64, handle.weights, int(words), bits, sums]

    def shipped():          # the backend's CUDA sequence on a clean kept buffer
        both.zero_()
        wp.launch(g.score_kernel_gpu, dim=P * L * len(sd), device=dev, inputs=common, block_dim=g.SCORE_BLOCK_DIM)
        wp.launch(g.count_clear_kernel, dim=P * T, device=dev, inputs=[bits, int(words), int(T), counts],
                  block_dim=g.SCORE_BLOCK_DIM)
        return both.numpy().copy()

    def clear4():
        both.zero_()
        wp.launch(g.score_kernel_gpu, dim=P * L * len(sd), device=dev, inputs=common, block_dim=g.SCORE_BLOCK_DIM)
        wp.launch(count_clear4, dim=P * T, device=dev, inputs=[bits, int(words), int(T), counts],
                  block_dim=g.SCORE_BLOCK_DIM)
        return both.numpy().copy()

    def clear64():
        both.zero_()
        wp.launch(g.score_kernel_gpu, dim=P * L * len(sd), device=dev, inputs=common, block_dim=g.SCORE_BLOCK_DIM)
        half = words // 2
        t = max(1, min(half // 32, (1 << 18) // P))
        wp.launch(count_clear64, dim=P * t, device=dev, inputs=[bits64, int(half), int(t), counts],
                  block_dim=g.SCORE_BLOCK_DIM)
        return both.numpy().copy()

    def fused():            # no count pass; the buffer zeroed before the kernel
        both.zero_()
        bits.zero_()
        wp.launch(score_fused, dim=P * L * len(sd), device=dev, inputs=common + [counts], block_dim=g.SCORE_BLOCK_DIM)
        return both.numpy().copy()

    def parts(kernel_only):
        def run():
            both.zero_()
            wp.launch(kernel_only[0], dim=P * L * len(sd), device=dev, inputs=common + kernel_only[1],
                      block_dim=g.SCORE_BLOCK_DIM)
            wp.synchronize_device(dev)
        return run

    variants = {"shipped": shipped, "clear4": clear4, "fused": fused}
    if words % 2 == 0:
        bits64 = wp.array(ptr=bits.ptr, shape=(P * words // 2,), dtype=wp.uint64, device=dev)
        variants["clear64"] = clear64
    want = b.score_placements(handle, dense.elevations, dense.azimuths, dense.max_range, local)
    want = np.concatenate([np.asarray(want[0]), np.asarray(want[1])])
    equal = {}
    for k, fn in variants.items():
        bits.zero_()
        equal[k] = bool(np.array_equal(fn(), want))
        if k != "fused":
            equal[k] = equal[k] and not bits.numpy().any()   # the count left the buffer zero
    times = {k: [] for k in variants}
    kern = {"kernel shipped": [], "kernel fused": []}
    for _ in range(args.rounds):
        for k, fn in variants.items():
            wp.synchronize_device(dev)
            t = time.perf_counter()
            fn()
            times[k].append(1e3 * (time.perf_counter() - t))
            if k == "fused":    # it leaves its bits set: the others start, as in the backend, on a clean buffer
                bits.zero_()
        alone = {"kernel shipped": (g.score_kernel_gpu, []), "kernel fused": (score_fused, [counts])}
        for k, (kk, extra) in alone.items():
            bits.zero_()
            wp.synchronize_device(dev)
            t = time.perf_counter()
            parts((kk, extra))()
            kern[k].append(1e3 * (time.perf_counter() - t))
        bits.zero_()
    times.update(kern)
    res = {"info": machine_info(), "device": args.device, "population": P, "equal_to_api": equal, "ms": {}}
    for k, xs in times.items():
        res["ms"][k] = {"median": statistics.median(xs), "min": min(xs), "max": max(xs), "runs": xs}
        print(f"{k:16s} {statistics.median(xs):8.3f} ms [{min(xs):.3f}-{max(xs):.3f}]  per rig "
              f"{statistics.median(xs) / P:.3f}", flush=True)
    print("sums and counts equal the API's (and the buffer left zero):", equal, flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=2))
    return 0 if all(equal.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
