"""Warp kernel of ``Backend.score_rays``: explicit rays, each tagged with its candidate.

The walk and the bricked bitsets are those of the placement score kernel (``kernels.py``: ``mark_walk``),
so the covered voxel sets, and the exact int64 sums, agree with the
reference bit for bit. Rays come from the host (float64 origins and directions, a float64 segment end
per ray) instead of being generated from sensor poses, so candidates may have any number of rays.
"""

from __future__ import annotations

import warp as wp

from place3d_kernels.backends.warp.kernels import mark_walk

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
    my_sum = mark_walk(o, d, t_end[tid], s, nx, ny, nz, bny, bnz, masks, weights,
                       wp.int64(c) * words_per_candidate, bits)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, c, my_sum)
