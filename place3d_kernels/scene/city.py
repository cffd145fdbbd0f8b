"""A synthetic city of boxes with an exact triangle budget, for ray-mesh intersection benchmarks."""

from __future__ import annotations

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.primitives import BOX_TRIANGLES, boxes, plane_grid

__all__ = ["box_city"]

BUILDING, ROAD, GROUND = CLASS_ID["building"], CLASS_ID["road"], CLASS_ID["ground"]


def _module_counts(W, D, H, a):
    nx = np.maximum(1, np.rint(W / a)).astype(np.int64)
    ny = np.maximum(1, np.rint(D / a)).astype(np.int64)
    nz = np.maximum(1, np.rint(H / a)).astype(np.int64)
    return nx, ny, nz


def box_city(n_triangles: int = 1_000_000, seed: int = 0, extent: float = 400.0,
             max_yaw: float = 0.0) -> Mesh:
    """A grid of city blocks on a flat ground, every building a cluster of closed boxes.

    The ground (z = 0) is a rectilinear grid of road (7) and ground (13) quads; roads cross at the origin,
    so a rig at (0, 0, ~2 m) stands in a junction with streets of buildings in every direction. Each
    building (label 1) is a stack of "modules" (storey x bay boxes of about the same size, jittered so
    facades are rough), plus small rooftop boxes that take up the remainder of the budget. The box count is
    chosen so that the triangle count is within 12 of ``n_triangles`` (ground triangles included).

    Args:
        n_triangles: triangle budget (at least 100).
        seed: seed of ``numpy.random.default_rng``; equal seeds give identical meshes.
        extent: side of the square town in metres (road centrelines span [-extent/2, extent/2]).
        max_yaw: buildings are rotated about z by a uniform angle in [-max_yaw, max_yaw] (radians).

    Faces are ordered: ground first, then boxes of 12 triangles each (8 vertices of their own).
    """
    n_triangles = int(n_triangles)
    if n_triangles < 100:
        raise ValueError(f"box_city needs n_triangles >= 100, got {n_triangles}")
    if not extent > 0:
        raise ValueError(f"box_city extent must be positive, got {extent}")
    rng = np.random.default_rng(seed)

    nb = 8 if n_triangles >= 200_000 else 6 if n_triangles >= 50_000 else 4 if n_triangles >= 10_000 else 2
    pitch = extent / nb
    road_w = min(12.0, 0.25 * pitch)
    centres = (np.arange(nb + 1) - nb / 2) * pitch
    lines = np.sort(np.concatenate([centres - road_w / 2, centres + road_w / 2]))
    vg, fg, cell = plane_grid(lines, lines, 0.0)
    is_road = (cell[:, 0] % 2 == 0) | (cell[:, 1] % 2 == 0)
    lg = np.where(is_road, ROAD, GROUND)
    n_boxes = int(round((n_triangles - len(fg)) / BOX_TRIANGLES))
    if n_boxes < 1:
        raise ValueError(f"box_city: n_triangles={n_triangles} leaves no room for boxes")

    # lots: m x m per block, one building each
    setback = min(2.0, 0.05 * pitch)
    inner = pitch - road_w - 2 * setback
    m = max(1, int(round(inner / 13.0)))
    lot = inner / m
    bi, bj, li, lj = np.meshgrid(np.arange(nb), np.arange(nb), np.arange(m), np.arange(m), indexing="ij")
    bx = centres[bi.ravel()] + road_w / 2 + setback + (li.ravel() + 0.5) * lot
    by = centres[bj.ravel()] + road_w / 2 + setback + (lj.ravel() + 0.5) * lot
    nbld = len(bx)
    W = lot * rng.uniform(0.6, 0.92, nbld)
    D = lot * rng.uniform(0.6, 0.92, nbld)
    H = np.clip(rng.lognormal(np.log(18.0), 0.6, nbld), 4.0, 120.0)
    yaw = rng.uniform(-max_yaw, max_yaw, nbld) if max_yaw > 0 else np.zeros(nbld)
    # wiggle lot centres a little
    slack_x, slack_y = (lot - W) / 2, (lot - D) / 2
    bx = bx + rng.uniform(-1, 1, nbld) * slack_x * 0.8
    by = by + rng.uniform(-1, 1, nbld) * slack_y * 0.8
    order = rng.permutation(nbld)

    if nbld >= n_boxes:  # tiny budget: one box per building, some lots stay empty
        keep = order[:n_boxes]
        nx = ny = nz = np.ones(n_boxes, np.int64)
        bx, by, W, D, H, yaw = bx[keep], by[keep], W[keep], D[keep], H[keep], yaw[keep]
        n_roof = 0
    else:
        # module size a: the largest with count(a) <= n_boxes (count is non-increasing in a)
        lo, hi = 1e-3, 1e4
        for _ in range(80):
            mid = np.sqrt(lo * hi)
            nx, ny, nz = _module_counts(W, D, H, mid)
            if (nx * ny * nz).sum() > n_boxes:
                lo = mid
            else:
                hi = mid
        nx, ny, nz = _module_counts(W, D, H, hi)
        n_roof = n_boxes - int((nx * ny * nz).sum())

    counts = nx * ny * nz
    bid = np.repeat(np.arange(len(counts)), counts)
    # module index within its building -> (ix, iy, iz)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = np.arange(counts.sum()) - start[bid]
    iz = k // (nx[bid] * ny[bid])
    rem = k % (nx[bid] * ny[bid])
    ix, iy = rem // ny[bid], rem % ny[bid]
    cw, cd, ch = W[bid] / nx[bid], D[bid] / ny[bid], H[bid] / nz[bid]
    lx = (ix + 0.5) * cw - W[bid] / 2
    ly = (iy + 0.5) * cd - D[bid] / 2
    sx = cw * rng.uniform(0.88, 1.0, len(bid))
    sy = cd * rng.uniform(0.88, 1.0, len(bid))
    c_yaw, s_yaw = np.cos(yaw[bid]), np.sin(yaw[bid])
    cx = bx[bid] + c_yaw * lx - s_yaw * ly
    cy = by[bid] + s_yaw * lx + c_yaw * ly
    cz = (iz + 0.5) * ch
    centers = np.stack([cx, cy, cz], 1)
    sizes = np.stack([sx, sy, ch], 1)
    yaws = yaw[bid]

    if n_roof > 0:  # rooftop units (vents, stair houses) fill the budget exactly
        rb = rng.integers(0, len(counts), n_roof)
        rs = rng.uniform(0.15, 0.35, (n_roof, 2)) * np.stack([W[rb], D[rb]], 1)
        rh = rng.uniform(0.8, 3.0, n_roof)
        rl = (rng.uniform(-0.5, 0.5, (n_roof, 2)) * (np.stack([W[rb], D[rb]], 1) - rs))
        c_r, s_r = np.cos(yaw[rb]), np.sin(yaw[rb])
        rc = np.stack([bx[rb] + c_r * rl[:, 0] - s_r * rl[:, 1], by[rb] + s_r * rl[:, 0] + c_r * rl[:, 1],
                       H[rb] + rh / 2], 1)
        centers = np.concatenate([centers, rc])
        sizes = np.concatenate([sizes, np.c_[rs, rh]])
        yaws = np.concatenate([yaws, yaw[rb]])

    vb, fb = boxes(centers, sizes, yaws)
    v = np.concatenate([vg, vb])
    f = np.concatenate([fg, fb + len(vg)])
    labels = np.concatenate([lg, np.full(len(fb), BUILDING)])
    return Mesh(v, f, labels)
