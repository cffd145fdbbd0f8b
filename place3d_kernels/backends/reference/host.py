"""Reference kernels: NumPy float64, written for clarity, not speed.

This module is the executable specification of the kernel contract (``place3d_kernels/backends/base.py``). Every other
backend is tested against it. It is slow: ray-mesh intersection is brute force over all triangles, and
voxel traversal loops over rays in Python.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.base import (Backend, GridSpec, check_ray_batch, check_voxel_rows, rotation_matrices,
                                          sensor_directions)
from place3d_kernels.backends.geometry import closest_hits
from place3d_kernels.backends.reference.conditions import ReferenceConditions
from place3d_kernels.backends.base import host_vote, unique_ints

__all__ = ["ReferenceBackend", "ReferenceCore", "traverse_ray"]


def _start_index(p: float, d: float, s: float, n: int) -> int:
    """Voxel index of the clipped start point along one axis; a start exactly on a plane belongs to the
    voxel the ray moves into."""
    i = int(np.floor(p / s))
    if d < 0.0 and p <= i * s:
        i -= 1
    if d > 0.0 and p >= (i + 1) * s:
        i += 1
    return min(max(i, 0), n - 1)


def traverse_ray(origin: np.ndarray, direction: np.ndarray, t_end: float, spec: GridSpec,
                 stop: np.ndarray | None = None) -> np.ndarray:
    """Flat indices of the voxels whose interior the segment [0, t_end] passes through, in order.

    Method (Amanatides-Woo, evaluated all at once): clip the segment to the grid box and find the voxel of
    the clipped start point. Along each axis the ray then crosses the planes after that voxel at
    parameters t_b = (b * s - o) / d, computed from the integer plane index b (never accumulated). Each
    distinct crossing parameter below the segment's end moves the ray into the voxel whose index along
    each axis is the start index plus the number of that axis's crossings at or before it. Crossings at
    exactly the same t (a ray through an edge or corner) move all their axes at once, so no side voxel is
    visited; crossings one rounding step apart do visit it, since the ray passes through it. The walk
    ends where an index leaves the grid. With ``stop``, the list ends at the first voxel whose mask is set.
    """
    # tiny direction components make crossing parameters overflow to +-inf, which the walk handles (a
    # crossing at inf is never reached); the division warnings would only be noise
    with np.errstate(over="ignore", divide="ignore"):
        return _traverse_ray(origin, direction, t_end, spec, stop)


def _traverse_ray(origin: np.ndarray, direction: np.ndarray, t_end: float, spec: GridSpec,
                  stop: np.ndarray | None = None) -> np.ndarray:
    """The walk of ``traverse_ray``."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    s = float(spec.voxel_size)
    n = np.asarray(spec.shape, dtype=np.int64)
    size = n * s
    t0, t1 = 0.0, float(t_end)
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < 0.0 or o[a] > size[a]:
                return np.empty(0, dtype=np.int64)
            continue
        ta = (0.0 - o[a]) / d[a]
        tb = (size[a] - o[a]) / d[a]
        t0 = max(t0, min(ta, tb))
        t1 = min(t1, max(ta, tb))
    if not t1 > t0:
        return np.empty(0, dtype=np.int64)
    p = o + t0 * d
    start = np.array([_start_index(p[a], d[a], s, int(n[a])) for a in range(3)], dtype=np.int64)
    steps = np.sign(d).astype(np.int64)
    crossings = []
    for a in range(3):
        if steps[a] == 0:
            crossings.append(np.empty(0))
            continue
        # planes after the start voxel in the direction of travel, up to the grid's far face
        b = np.arange(start[a] + 1, n[a] + 1) if steps[a] > 0 else np.arange(start[a], -1, -1)
        tb = (b.astype(np.float64) * s - o[a]) / d[a]
        crossings.append(tb[tb < t1])
    events = np.unique(np.concatenate(crossings))
    ijk = np.repeat(start[None, :], len(events) + 1, axis=0)
    for a in range(3):
        if crossings[a].size:
            ijk[1:, a] += steps[a] * np.searchsorted(crossings[a], events, side="right")
    inside = np.all((ijk >= 0) & (ijk < n), axis=1)
    if not inside.all():
        ijk = ijk[: np.argmin(inside)]
    flat = (ijk[:, 0] * n[1] + ijk[:, 1]) * n[2] + ijk[:, 2]
    if stop is not None and flat.size:
        hit = np.flatnonzero(stop[flat])
        if hit.size:
            flat = flat[: hit[0] + 1]
    return flat


class _RefMesh:
    def __init__(self, vertices, faces):
        self.v0 = vertices[faces[:, 0]]
        self.v1 = vertices[faces[:, 1]]
        self.v2 = vertices[faces[:, 2]]
        self.lo = np.minimum(np.minimum(self.v0, self.v1), self.v2)
        self.hi = np.maximum(np.maximum(self.v0, self.v1), self.v2)


class _RefGrid:
    def __init__(self, spec, weights, stop):
        self.spec = spec
        # copies, as the device backends' uploads are: a caller may reuse its arrays for the next grid while
        # this handle is still kept (left_out.PreparedLeftOut keeps the jackknife's)
        self.weights = np.array(weights, dtype=np.int64)
        self.stop = None if stop is None else np.array(stop, dtype=np.uint8)


class ReferenceCore(Backend):
    """NumPy float64 implementation of every kernel of the contract."""

    name = "reference"
    dtype = np.float64

    def lidar_rays(self, elevations, azimuths, poses):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
        local = sensor_directions(elevations, azimuths)                  # (C*A, 3)
        R = rotation_matrices(poses)                                       # (L, 3, 3)
        d = np.einsum("lij,nj->lni", R, local).reshape(-1, 3)
        o = np.repeat(poses[:, :3], len(local), axis=0)
        return o, d

    def upload_mesh(self, vertices, faces, face_ids=None, labels=None):
        # face_ids and labels serve raycast_checked, which this backend does not have (the domain maps faces)
        return _RefMesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))

    def raycast(self, mesh, origins, directions, t_max):
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        tm = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (len(o),))
        return closest_hits(mesh.v0, mesh.v1, mesh.v2, o, d, tm)

    def traverse(self, grid, origins, directions, t_end, stop=None):
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        te = np.broadcast_to(np.asarray(t_end, dtype=np.float64), (len(o),))
        lists = [traverse_ray(o[i], d[i], te[i], grid, stop) for i in range(len(o))]
        offsets = np.zeros(len(o) + 1, dtype=np.int64)
        offsets[1:] = np.cumsum([len(x) for x in lists])
        voxels = np.concatenate(lists) if lists else np.empty(0, dtype=np.int64)
        return offsets, voxels.astype(np.int64)

    def coverage(self, grid, origins, directions, t_end, stop=None):
        _, voxels = self.traverse(grid, origins, directions, t_end, stop)
        mask = np.zeros(grid.n_voxels, dtype=bool)
        mask[voxels] = True
        return mask

    def prepare_grid(self, grid, weights, stop):
        return _RefGrid(grid, weights, stop)

    writes_grids = True

    def working_grid(self, grid, voxels, weights, stop):
        h = _RefGrid(grid, np.zeros(grid.n_voxels, dtype=np.int64),
                     None if stop is None else np.zeros(grid.n_voxels, dtype=np.uint8))
        self.write_voxels(h, voxels, weights, stop)
        return h

    def write_voxels(self, handle, voxels, weights, stop):
        ids, w, s = check_voxel_rows(voxels, weights, stop, handle.spec.n_voxels, handle.stop is not None)
        handle.weights[ids] = w
        if handle.stop is not None:
            handle.stop[ids] = s

    def score_placements(self, handle, elevations, azimuths, t_max, poses):
        poses = np.asarray(poses, dtype=np.float64)
        sums = np.zeros(len(poses), dtype=np.int64)
        counts = np.zeros(len(poses), dtype=np.int64)
        for p, rig in enumerate(poses):
            o, d = self.lidar_rays(elevations, azimuths, rig)
            _, voxels = self.traverse(handle.spec, o, d, np.full(len(o), float(t_max)), handle.stop)
            u = unique_ints(voxels)
            sums[p] = int(handle.weights[u].sum(dtype=np.int64))
            counts[p] = len(u)
        return sums, counts

    def score_rays(self, handle, origins, directions, t_end, ray_offsets):
        o, d, te, off = check_ray_batch(origins, directions, t_end, ray_offsets)
        P = len(off) - 1
        sums = np.zeros(P, dtype=np.int64)
        counts = np.zeros(P, dtype=np.int64)
        for p in range(P):
            a, b = int(off[p]), int(off[p + 1])
            _, voxels = self.traverse(handle.spec, o[a:b], d[a:b], te[a:b], handle.stop)
            u = unique_ints(voxels)
            sums[p] = int(handle.weights[u].sum(dtype=np.int64))
            counts[p] = len(u)
        return sums, counts

    def voxel_keys(self, grid, points):
        p = np.asarray(points, dtype=np.float64)
        ijk = np.floor(p / grid.voxel_size).astype(np.int64)
        n = np.asarray(grid.shape)
        inside = np.all((ijk >= 0) & (ijk < n), axis=1)
        flat = (ijk[:, 0] * n[1] + ijk[:, 1]) * n[2] + ijk[:, 2]
        return np.where(inside, flat, -1).astype(np.int64)

    def vote(self, keys, labels, n_classes):
        return host_vote(keys, labels, n_classes)


class ReferenceBackend(ReferenceCore, ReferenceConditions):
    """The reference backend: the geometry kernels above and the adverse-condition kernels."""

    name = "reference"
