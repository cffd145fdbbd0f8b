"""M-SOG as a batched optimisation objective, with coverage cached per LiDAR pose.

On the delta grid the same LiDAR pose recurs in many candidate rigs. The voxels one LiDAR covers do
not depend on the other LiDARs (occlusion comes from the P-SOG or the scene, not from the rig), so
each distinct pose is traversed once; a rig's M-SOG is then the fixed-point sum over the union of its
LiDARs' cached voxel sets, bit-identical to ``msog_batch``.

Trade-off: a new pose costs a traversal to a visit list, which is not
much cheaper than scoring the whole rig in the fused ``score_placements`` kernel, and every rig then
pays a union of its LiDARs' voxel sets; so the cache wins when most poses of a batch were seen before
(late CMA-ES generations, local search) and loses when few were, as over most of a 2,000-evaluation
run. ``place3d optimize`` therefore uses the fused kernel unless ``--pose-cache`` is given. Each cached
pose holds its distinct voxel ids (a few hundred thousand int32 on the default grid), hence the LRU bound.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.ops import traverse

__all__ = ["MSOGObjective"]


class MSOGObjective:
    """Callable ``X (P, D) -> (P,)`` M-SOG scores of the rigs ``space.to_poses(X)``.

    Args:
        psog: the scene's P-SOG.
        lidar: the rig's LiDAR model.
        space: a ``SearchSpace`` (maps vectors to (P, L, 6) poses).
        task: "seg" or "det".
        occlusion: "sog" or "none" (mesh occlusion: use ``msog_batch`` with ``mesh=``).
        backend: backend name or instance.
        max_cached_poses: LRU bound on cached poses (each holds the pose's covered voxel ids).
        normalisation: M-SOG denominator, as in ``msog_batch`` ("paper", "evidence", "uncertain").

    Attributes:
        pose_hits, pose_misses: cache statistics (LiDAR poses answered from / added to the cache).
    """

    def __init__(self, psog, lidar, space, task: str = "seg", occlusion: str = "sog", backend=None,
                 max_cached_poses: int = 512, normalisation: str = "paper"):
        from place3d_kernels.metrics import check_normalisation, indicator_weights

        if occlusion not in ("sog", "none"):
            raise ValueError(f"MSOGObjective supports occlusion 'sog' or 'none', got {occlusion!r}")
        if not lidar.is_grid or lidar.min_range > 0:
            # its cache holds grid traversals from the LiDAR origin, with no body: scores would differ from
            # msog_batch, which starts rays at min_range (issue 16)
            raise ValueError(f"MSOGObjective (--pose-cache) takes grid LiDARs without a minimum range; "
                             f"{lidar.name!r} is not one: drop --pose-cache (msog_batch scores it exactly)")
        self.psog = psog
        self.task_psog = psog.for_task(task)
        self.lidar = lidar
        self.space = space
        self.occlusion = occlusion
        self.backend = get_backend(backend)
        self.max_cached_poses = int(max_cached_poses)
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.pose_hits = 0
        self.pose_misses = 0
        self._stamp: np.ndarray | None = None
        self.normalisation = check_normalisation(normalisation)
        # 0/1 weights of the voxels that count in the denominator (None: every covered voxel, N_L)
        self._den = None if normalisation == "paper" else indicator_weights(self.task_psog, normalisation)

    def _distinct(self, v: np.ndarray) -> np.ndarray:
        """Distinct voxel ids in O(n) with a scratch array (np.unique sorts, and dominated run time)."""
        if self._stamp is None:
            self._stamp = np.zeros(self.psog.grid.n_voxels, dtype=np.int64)
        pos = np.arange(len(v), dtype=np.int64)
        self._stamp[v] = pos                    # one write survives per voxel
        return v[self._stamp[v] == pos]

    def _fill(self, poses: np.ndarray) -> None:
        """Traverse every not-yet-cached pose in one backend call."""
        keys = [p.tobytes() for p in poses]
        new = {}
        for k, p in zip(keys, poses):
            if k in self._cache:
                self._cache.move_to_end(k)
                self.pose_hits += 1
            elif k in new:
                self.pose_hits += 1          # repeated within this batch: traversed once
            else:
                new[k] = p
        if not new:
            return
        self.pose_misses += len(new)
        todo = np.array(list(new.values()))
        b = self.backend
        o, d = b.lidar_rays(self.lidar.elevations, self.lidar.azimuths, todo)
        stop = self.psog.stop_mask if self.occlusion == "sog" else None
        tr = traverse(self.psog.grid, o, d, self.lidar.max_range, backend=b, stop=stop)
        per = self.lidar.n_rays
        for i, k in enumerate(new):
            v = tr.voxels[tr.offsets[i * per]:tr.offsets[(i + 1) * per]]
            self._cache[k] = self._distinct(v)

    def __call__(self, X) -> np.ndarray:
        poses = self.space.to_poses(np.atleast_2d(np.asarray(X, dtype=np.float64)))
        P, L = poses.shape[:2]
        # +0.0 folds -0.0 so equal poses share one key
        flat = np.ascontiguousarray(poses.reshape(-1, 6) + 0.0)
        from place3d_kernels.metrics import check_inputs

        check_inputs(self.psog, poses, self.occlusion, None)
        self._fill(flat)
        w = self.task_psog.weights
        out = np.empty(P)
        for p in range(P):
            sets = [self._cache[flat[p * L + j].tobytes()] for j in range(L)]
            u = self._distinct(np.concatenate(sets)) if L > 1 else sets[0]
            n = len(u) if self._den is None else int(self._den[u].sum(dtype=np.int64))
            out[p] = -(float(w[u].sum(dtype=np.int64)) / ENTROPY_SCALE) / n if n else np.nan
        # evict least recently used poses, never the ones this call needed
        while len(self._cache) > max(self.max_cached_poses, P * L):
            self._cache.popitem(last=False)
        return out
