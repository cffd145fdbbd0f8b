"""Warp kernels that turn a batch of LiDAR sweeps' hits into their returns on the device
(``WarpCore.sweep_returns``): each ray's nearer hit of the static mesh and the actors' mesh, the rays that hit
kept in ray order, and each return's world point and label. ``simulate._returns`` does the same on the host
from downloaded rays and hits; these give its arrays bit for bit: the nearer hit is the actors' only where its
distance is smaller (``dh.t < t``), a ray returns where that distance is finite, and the point is
``o + t * d`` with the product rounded before the sum (no fused multiply-add: ``fuse_fp`` is off, as in
kernels.py), NumPy's order.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.kernel
def returns_hit_kernel(
    t_static: wp.array(dtype=wp.float64),
    t_actors: wp.array(dtype=wp.float64),   # (N,), or (1,) unused without actors
    has_actors: wp.int32,
    hit: wp.array(dtype=wp.int32),          # (N,) out: 1 where the ray returns
):
    i = wp.tid()
    t = t_static[i]
    if has_actors != 0:
        if t_actors[i] < t:
            t = t_actors[i]
    hit[i] = wp.where(wp.isfinite(t), 1, 0)


@wp.kernel
def returns_write_kernel(
    origins: wp.array(dtype=wp.vec3d),
    dirs: wp.array(dtype=wp.vec3d),
    t_static: wp.array(dtype=wp.float64),
    label_static: wp.array(dtype=wp.int32),
    t_actors: wp.array(dtype=wp.float64),
    label_actors: wp.array(dtype=wp.int32),
    has_actors: wp.int32,
    hit: wp.array(dtype=wp.int32),
    at: wp.array(dtype=wp.int32),           # exclusive prefix sum of hit: each return's row
    points: wp.array(dtype=wp.vec3d),       # (H,) out
    labels: wp.array(dtype=wp.int32),       # (H,) out
):
    i = wp.tid()
    if hit[i] == 0:
        return
    t = t_static[i]
    lab = label_static[i]
    if has_actors != 0:
        if t_actors[i] < t:
            t = t_actors[i]
            lab = label_actors[i]
    o = origins[i]
    d = dirs[i]
    j = at[i]
    points[j] = wp.vec3d(o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2])
    labels[j] = lab


@wp.kernel
def sweep_starts_kernel(
    hit: wp.array(dtype=wp.int32),
    at: wp.array(dtype=wp.int32),
    rays_per_sweep: wp.int32,
    sweeps: wp.int32,
    out: wp.array(dtype=wp.int32),          # (sweeps + 1,): sweep k's returns are rows out[k]:out[k + 1]
):
    k = wp.tid()
    if k < sweeps:
        out[k] = at[k * rays_per_sweep]
    else:
        last = sweeps * rays_per_sweep - 1
        out[k] = at[last] + hit[last]
