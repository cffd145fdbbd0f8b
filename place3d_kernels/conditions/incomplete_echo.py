"""Incomplete echo (Robo3D): dark vehicle paint returns too little light, REFERENCE.md section 6.

With ratio r: every vehicle object with more than 10 points loses ``int(n r)`` of its n points, chosen at
random. Objects are the given ``instances`` or, by default, the connected groups of vehicle points
(class 10): two vehicle points belong to one object when a chain of vehicle points joins them whose
neighbours lie in the same or adjacent cells of a ``cluster_radius`` grid (so points closer than the
radius always join; farther ones up to 2 sqrt(3) radii may). Robo3D, lacking instances, dropped per class
in the whole frame; objects make the drop local, as the physics (dark paint) is.
"""

from __future__ import annotations

import itertools

import numpy as np

from place3d_kernels.classes import VEHICLE
from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rng
from place3d_kernels.pointcloud import PointCloud

__all__ = ["incomplete_echo", "cluster_points", "SEVERITIES"]

#: Robo3D levels (its script: light 0.75, moderate 0.85, heavy 0.95); the paper uses 0.85.
SEVERITIES = {"light": {"ratio": 0.75}, "moderate": {"ratio": 0.85}, "heavy": {"ratio": 0.95}}

# the 13 neighbour offsets with a lexicographically positive (dx, dy, dz): each adjacent pair once
_HALF = [o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)]


def cluster_points(points, radius: float = 1.0) -> np.ndarray:
    """Connected components of points on a grid of cell size ``radius`` (26-neighbourhood).

    Returns:
        (N,) int64 component ids 0..K-1, numbered by first appearance.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor((p - p.min(axis=0)) / radius).astype(np.int64) + 1
    uniq, inv = np.unique(cells, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    span = uniq.max(axis=0) + 2
    keys = (uniq[:, 0] * span[1] + uniq[:, 1]) * span[2] + uniq[:, 2]      # ascending, as uniq is sorted
    a_list, b_list = [], []
    for dx, dy, dz in _HALF:
        nk = keys + (dx * span[1] + dy) * span[2] + dz
        pos = np.clip(np.searchsorted(keys, nk), 0, len(keys) - 1)
        hit = keys[pos] == nk
        a_list.append(np.nonzero(hit)[0])
        b_list.append(pos[hit])
    a = np.concatenate(a_list)
    b = np.concatenate(b_list)
    lab = np.arange(len(uniq))
    while True:                                   # min-label propagation with pointer jumping
        m = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    comp = lab[inv]
    _, first, ids = np.unique(comp, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))         # renumber by first appearance
    return order[ids.reshape(-1)].astype(np.int64)


def _instances(cloud, instances, classes, cluster_radius):
    if instances is not None:
        inst = np.asarray(instances).astype(np.int64).reshape(-1)
        if inst.shape != (len(cloud),):
            raise ValueError(f"instances must have one id per point ({len(cloud)}), got {inst.shape}")
        inst = np.where(inst >= 0, inst, -1)
        _, dense = np.unique(inst[inst >= 0], return_inverse=True)
        out = np.full(len(cloud), -1, dtype=np.int64)
        out[inst >= 0] = dense.reshape(-1)
        return out
    sel = np.isin(cloud.labels, np.asarray(classes))
    out = np.full(len(cloud), -1, dtype=np.int64)
    out[sel] = cluster_points(cloud.points[sel], cluster_radius)
    return out


def incomplete_echo(cloud: PointCloud, ratio: float = 0.85, seed=0, backend=None, *, instances=None,
                    classes=(VEHICLE,), min_points: int = 10, cluster_radius: float = 1.0) -> PointCloud:
    """Drop ``int(n ratio)`` points of each vehicle object with more than ``min_points`` points.

    Args:
        cloud: the frame.
        ratio: fraction of an object's points lost, in [0, 1]; the paper uses 0.85.
        seed: int or numpy Generator; orders each object's points at random.
        backend: backend name or instance (None: current default).
        instances: optional (N,) object id per point (< 0: no object) instead of clustering.
        classes: labels clustered into objects when ``instances`` is None (default: vehicle, 10).
        min_points: objects with at most this many points are left alone.
        cluster_radius: cell size (m) of the clustering grid.

    Returns:
        A new PointCloud without the dropped points (order of the rest kept).
    """
    cloud = check_cloud(cloud, "incomplete_echo")
    ratio = check_range("ratio", ratio, lo=0.0, hi=1.0)
    if ratio == 0.0 or len(cloud) == 0:
        return cloud.copy()
    inst = _instances(cloud, instances, classes, cluster_radius)
    n_inst = int(inst.max()) + 1 if (inst >= 0).any() else 0
    if n_inst == 0:
        return cloud.copy()
    counts = np.bincount(inst[inst >= 0], minlength=n_inst)
    n_drop = np.where(counts > min_points, np.floor(counts * ratio), 0).astype(np.int64)
    # a random order inside each object: sort by (object, random key); rank = position in the object's run
    key = rng(seed, 0).random(len(cloud))
    order = np.lexsort((key, inst))
    starts = np.searchsorted(inst[order], inst[order], side="left")
    rank = np.empty(len(cloud), dtype=np.int64)
    rank[order] = np.arange(len(cloud)) - starts
    keep = np.asarray(kernels(backend).incomplete_echo_points(inst, rank, n_drop), dtype=bool)
    return cloud.subset(keep)
