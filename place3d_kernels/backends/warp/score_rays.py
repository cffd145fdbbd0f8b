"""Warp kernel of ``Backend.score_rays``: explicit rays, each tagged with its candidate.

The walk and the bricked bitsets are those of the placement score kernel (``kernels.py``: ``walk32_*``,
``brick_word``, ``brick_bit``), so the covered voxel sets, and the exact int64 sums, agree with the
reference bit for bit. Rays come from the host (float64 origins and directions, a float64 segment end
per ray) instead of being generated from sensor poses, so candidates may have any number of rays.
"""

from __future__ import annotations

import warp as wp

from place3d_kernels.backends.warp.kernels import brick_bit, brick_word, flat32, walk32_begin, walk32_next

# the same module options as kernels.py (no adjoints; no FMA contraction, which would change voxel ties)
wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.kernel
def score_rays_kernel(
    origins: wp.array(dtype=wp.vec3d),          # (N,) grid-local
    dirs: wp.array(dtype=wp.vec3d),             # (N,) unit
    t_end: wp.array(dtype=wp.float64),          # (N,) segment lengths
    cand: wp.array(dtype=wp.int32),             # (N,) candidate of each ray
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32,               # bricks along y and z (see brick_word)
    masks: wp.array(dtype=wp.uint32),           # per brick: (occlusion bits, nonzero-weight bits)
    weights: wp.array(dtype=wp.int64),          # flat voxel order
    words_per_candidate: wp.int64,
    bits: wp.array(dtype=wp.uint32),            # (P * words_per_candidate,) zeroed, bricked
    sums: wp.array(dtype=wp.int64),             # (P,) zeroed
):
    tid = wp.tid()
    o = origins[tid]
    d = dirs[tid]
    c = cand[tid]
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_end[tid], s, sf, nx, ny, nz)
    base = wp.int64(c) * words_per_candidate
    # as score_ray in kernels.py: the ray that sets a voxel's bit first adds its weight (integer partial
    # sums, one atomic per ray), so the total does not depend on thread order
    my_sum = wp.int64(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        word = brick_word(w, bny, bnz)
        bit = brick_bit(w)
        if (bits[base + word] & bit) == wp.uint32(0):
            if (masks[wp.int64(2) * word + wp.int64(1)] & bit) != wp.uint32(0):
                old = wp.atomic_or(bits, base + word, bit)
                if (old & bit) == wp.uint32(0):
                    my_sum += weights[flat32(w, ny, nz)]
            else:
                wp.atomic_or(bits, base + word, bit)
        if (masks[wp.int64(2) * word] & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
            break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, c, my_sum)
