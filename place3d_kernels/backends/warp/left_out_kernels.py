"""Warp kernel of the jackknife's left-out fields on the device (``WarpCore.left_out_fields``).

For each row a left-out record touched: its count row in the pool minus the record's entries (or, for a
base, every row of the pool with no entries), the empty count T - (occupied), each count clipped into
[0, T] as the host's base is, and from them the voxel's fixed-point entropy weight and stop flag, as
``left_out.FieldTables`` computes them on the host. Bit for bit: every entropy term -p ln p comes from
the host's tables (NumPy's log on NumPy's c / T), and the terms of a row are added in the order NumPy
adds a row of an (R, K) float64 array (``ndarray.sum(axis=-1)``: for K >= 8 eight running sums over
blocks of eight, combined pairwise, then the rest one by one; below 8, one by one), with no fused
multiply-add; tests/test_left_out.py compares with the host on every record. A module of its own, shipped
compiled for CUDA (``aot.modules``).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.func
def count_at(counts: wp.array2d(dtype=wp.int32), row: wp.int64, k: wp.int32, e0: wp.int32, e1: wp.int32,
             ecls: wp.array(dtype=wp.int32), ecnt: wp.array(dtype=wp.int32)):
    # the pool's count of class k in this row, less the record's entry for k (a row has a few entries)
    c = counts[row, k]
    for e in range(e0, e1):
        if ecls[e] == k:
            c = c - ecnt[e]
    return c


@wp.func
def clip_t(c: wp.int32, t: wp.int32):
    # a count clipped into [0, T], as left_out.LeftOutGrids._base_fields clips its rows: a base row some
    # record touched can hold more than T subsets (its grid value is overwritten by every left-out grid); a
    # left-out row always lies in [0, T], where this changes nothing
    return wp.max(wp.min(c, t), 0)


@wp.func
def term_at(counts: wp.array2d(dtype=wp.int32), row: wp.int64, k: wp.int32, c0: wp.int32, e0: wp.int32,
            e1: wp.int32, ecls: wp.array(dtype=wp.int32), ecnt: wp.array(dtype=wp.int32),
            term: wp.array2d(dtype=wp.float64), ti: wp.int32, t: wp.int32):
    c = c0
    if k > 0:
        c = clip_t(count_at(counts, row, k, e0, e1, ecls, ecnt), t)
    return term[ti, c]


@wp.kernel
def left_out_fields_kernel(counts: wp.array2d(dtype=wp.int32), rows: wp.array(dtype=wp.int64),
                           estart: wp.array(dtype=wp.int32), ecls: wp.array(dtype=wp.int32),
                           ecnt: wp.array(dtype=wp.int32), row_t: wp.array(dtype=wp.int32),
                           Ts: wp.array(dtype=wp.int32), term: wp.array2d(dtype=wp.float64),
                           stop_t: wp.array2d(dtype=wp.uint8), other: wp.array3d(dtype=wp.float64),
                           det: wp.int32, veh: wp.int32, scale: wp.float64,
                           w_out: wp.array(dtype=wp.int64), s_out: wp.array(dtype=wp.uint8)):
    r = wp.tid()
    row = rows[r]
    e0 = estart[r]
    e1 = estart[r + 1]
    ti = row_t[r]
    K = counts.shape[1]
    occ = wp.int32(0)
    for k in range(1, K):
        occ = occ + count_at(counts, row, k, e0, e1, ecls, ecnt)
    t = Ts[ti]
    c0 = clip_t(t - occ, t)
    h = wp.float64(0.0)
    if det != 0:
        cv = wp.int32(0)
        if veh < K:
            cv = clip_t(count_at(counts, row, veh, e0, e1, ecls, ecnt), t)
        h = ((wp.float64(-0.0) + term[ti, c0]) + term[ti, cv]) + other[ti, c0, cv]
    elif K < 8:
        h = wp.float64(-0.0)
        for k in range(K):
            h = h + term_at(counts, row, k, c0, e0, e1, ecls, ecnt, term, ti, t)
    else:
        r0 = term_at(counts, row, 0, c0, e0, e1, ecls, ecnt, term, ti, t)
        r1 = term_at(counts, row, 1, c0, e0, e1, ecls, ecnt, term, ti, t)
        r2 = term_at(counts, row, 2, c0, e0, e1, ecls, ecnt, term, ti, t)
        r3 = term_at(counts, row, 3, c0, e0, e1, ecls, ecnt, term, ti, t)
        r4 = term_at(counts, row, 4, c0, e0, e1, ecls, ecnt, term, ti, t)
        r5 = term_at(counts, row, 5, c0, e0, e1, ecls, ecnt, term, ti, t)
        r6 = term_at(counts, row, 6, c0, e0, e1, ecls, ecnt, term, ti, t)
        r7 = term_at(counts, row, 7, c0, e0, e1, ecls, ecnt, term, ti, t)
        i = wp.int32(8)
        while i < K - K % 8:
            r0 = r0 + term_at(counts, row, i, c0, e0, e1, ecls, ecnt, term, ti, t)
            r1 = r1 + term_at(counts, row, i + 1, c0, e0, e1, ecls, ecnt, term, ti, t)
            r2 = r2 + term_at(counts, row, i + 2, c0, e0, e1, ecls, ecnt, term, ti, t)
            r3 = r3 + term_at(counts, row, i + 3, c0, e0, e1, ecls, ecnt, term, ti, t)
            r4 = r4 + term_at(counts, row, i + 4, c0, e0, e1, ecls, ecnt, term, ti, t)
            r5 = r5 + term_at(counts, row, i + 5, c0, e0, e1, ecls, ecnt, term, ti, t)
            r6 = r6 + term_at(counts, row, i + 6, c0, e0, e1, ecls, ecnt, term, ti, t)
            r7 = r7 + term_at(counts, row, i + 7, c0, e0, e1, ecls, ecnt, term, ti, t)
            i = i + 8
        h = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < K:
            h = h + term_at(counts, row, i, c0, e0, e1, ecls, ecnt, term, ti, t)
            i = i + 1
    w_out[r] = wp.int64(wp.rint(h * scale))
    s_out[r] = stop_t[ti, c0]
