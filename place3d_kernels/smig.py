"""S-MIG: the surrogate metric of Hu et al. (2022), the baseline Place3D compares M-SOG with.

Model. Over T frames, the 3-D boxes of the objects of interest (``(n, 7)`` rows x, y, z, l, w, h, yaw in
the ego frame of each frame; z is the box centre) give each voxel of the ROI grid a Bernoulli occupancy
probability p(v) = (number of frames in which the voxel centre lies inside a box) / T. Its entropy is
H(v) = -p log p - (1 - p) log(1 - p) (natural log, 0 log 0 = 0). A placement L covers the set of voxels
its rays cross (the same traversal kernels as M-SOG); once observed, a covered voxel's uncertainty is
removed, so

- ``reduce="sum"`` (default, the information gain): S-MIG(L) = H_total - H(S | L) = sum of H(v) over the
  covered voxels, where H(S | L) = sum over the uncovered voxels is what remains; higher is better;
- ``reduce="remaining"``: H(S | L) = H_total - sum over covered H(v), the literal "total entropy minus the
  entropy of the covered voxels"; lower is better (this reading and the gain differ only by sign and the
  constant H_total, so they rank placements identically);
- ``reduce="mean"``: the mean of H(v) over the covered voxels (normalised like M-SOG, without its sign);
  higher is better.

Occlusion modes are those of M-SOG: ``"none"`` (default here, as in Hu's code: rays run to
``lidar.max_range``, clipped to the ROI; give the LiDAR a range that reaches the ROI boundary to cast to
it), ``"sog"`` (a ray stops after the first voxel with p >= 0.5; that voxel counts) and ``"mesh"`` (stops
at the first surface of ``mesh=``, the scene in the ego frame). Sums are the kernels' fixed-point int64
entropy sums, deterministic on every backend; :func:`smig_batch` scores a whole CMA-ES population in one
launch, so it is usable as an optimizer objective.

Ego body: ``body=`` (a ``VehicleBody`` in the ego frame) ends every ray where it first hits the body, as in
M-SOG: the rays are built on the host and scored with ``Backend.score_rays``
(``place3d_kernels.rig_metrics.rigs_rays``, which also honours the LiDAR's ``min_range``); a LiDAR inside
the body raises ``ValueError``. ``body=None`` (default) keeps the original no-body setting.

Defects of the original public code that this version does not repeat:

1. ray directions were rotated with angles in degrees passed to functions expecting radians, so the beam
   pattern was scrambled (here angles are radians throughout, converted once from ``*_deg`` config keys);
2. ray directions were transformed like points (the LiDAR translation was added to direction vectors),
   bending every ray toward the mount position (here directions are rotated only);
3. negative voxel indices from rays leaving through the lower ROI faces were used as Python indices and
   wrapped around to voxels on the opposite side of the grid (here segments are clipped to the grid and
   indices are checked; see ``place3d_kernels.ops.traverse``);
4. (speed) ray casting and the full-grid entropy loop ran in pure Python (minutes per placement; the
   pure-Python loop of bench/peers.py); here both are kernels and the entropy is summed only over covered
   voxels.
"""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.grid import Grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.mesh import Mesh
from place3d_kernels.backends.base import unique_ints
from place3d_kernels.pose import invert, pose_matrix
from place3d_kernels.sog import PSOG

__all__ = ["BernoulliGrid", "smig", "smig_batch", "scene_boxes", "binary_entropy", "REDUCTIONS"]

REDUCTIONS = ("sum", "mean", "remaining")


def binary_entropy(p) -> np.ndarray:
    """H(p) = -p log p - (1 - p) log(1 - p), natural log, 0 log 0 = 0."""
    p = np.asarray(p, dtype=np.float64)
    q = 1.0 - p
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(p > 0, -p * np.log(np.where(p > 0, p, 1.0)), 0.0)
        b = np.where(q > 0, -q * np.log(np.where(q > 0, q, 1.0)), 0.0)
    return a + b


def _check_boxes(b, where="") -> np.ndarray:
    b = np.asarray(b, dtype=np.float64)
    if b.size == 0:
        return np.zeros((0, 7))
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"{where}boxes must have shape (n, 7) (x, y, z, l, w, h, yaw), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{where}boxes must be finite")
    if np.any(b[:, 3:6] < 0):
        raise ValueError(f"{where}box sizes (l, w, h) must be >= 0")
    return b


def _box_voxels(grid: Grid, boxes: np.ndarray) -> np.ndarray:
    """Sorted unique flat indices of the voxels whose centre lies inside any box (closed boxes)."""
    nx, ny, nz = grid.shape
    lo = np.asarray(grid.lower)
    vs = grid.voxel_size
    out = []
    for x, y, z, l, w, h, yaw in boxes:
        c, s = math.cos(yaw), math.sin(yaw)
        ex = 0.5 * (abs(c) * l + abs(s) * w)
        ey = 0.5 * (abs(s) * l + abs(c) * w)
        ez = 0.5 * h
        # centre of voxel i is lo + (i + 0.5) vs: candidate index range of the box's AABB
        rng = []
        for cmin, cmax, o, n in ((x - ex, x + ex, lo[0], nx), (y - ey, y + ey, lo[1], ny), (z - ez, z + ez, lo[2], nz)):
            i0 = max(int(math.ceil((cmin - o) / vs - 0.5 - 1e-9)), 0)
            i1 = min(int(math.floor((cmax - o) / vs - 0.5 + 1e-9)), n - 1)
            rng.append((i0, i1))
        if any(i1 < i0 for i0, i1 in rng):
            continue
        I, J, K = np.meshgrid(*(np.arange(i0, i1 + 1) for i0, i1 in rng), indexing="ij")
        cx = lo[0] + (I + 0.5) * vs - x
        cy = lo[1] + (J + 0.5) * vs - y
        cz = lo[2] + (K + 0.5) * vs - z
        u = c * cx + s * cy
        v = -s * cx + c * cy
        tol = 1e-9
        inside = (np.abs(u) <= l / 2 + tol) & (np.abs(v) <= w / 2 + tol) & (np.abs(cz) <= h / 2 + tol)
        out.append(((I[inside] * ny + J[inside]) * nz + K[inside]).astype(np.int64))
    return unique_ints(np.concatenate(out)) if out else np.zeros(0, np.int64)


class BernoulliGrid:
    """Per-voxel Bernoulli occupancy over an ego-frame grid.

    Attributes:
        grid: the ROI grid.
        voxels: (M,) ascending flat indices of voxels with p > 0.
        p: (M,) their occupancy probabilities.
        n_frames: T (None when built from probabilities).
    """

    def __init__(self, grid: Grid, voxels, p, n_frames=None):
        self.grid = grid
        self.voxels = np.asarray(voxels, dtype=np.int64)
        self.p = np.asarray(p, dtype=np.float64)
        if self.p.shape != self.voxels.shape:
            raise ValueError(f"p must have one value per voxel ({self.voxels.shape}), got {self.p.shape}")
        if self.p.size and (self.p.min() < 0 or self.p.max() > 1 or not np.all(np.isfinite(self.p))):
            raise ValueError("occupancy probabilities must lie in [0, 1]")
        if self.voxels.size and (self.voxels.min() < 0 or self.voxels.max() >= grid.n_voxels):
            raise ValueError(f"voxel indices must lie in [0, {grid.n_voxels - 1}]")
        self.n_frames = n_frames
        self._psog = None

    @classmethod
    def from_boxes(cls, boxes_per_frame, grid: Grid) -> "BernoulliGrid":
        """From a sequence of (n_t, 7) box arrays, one per frame (ego frame of that frame)."""
        frames = list(boxes_per_frame)
        if not frames:
            raise ValueError("BernoulliGrid.from_boxes needs at least one frame")
        allv = [_box_voxels(grid, _check_boxes(b, f"frame {t}: ")) for t, b in enumerate(frames)]
        cat = np.concatenate(allv) if allv else np.zeros(0, np.int64)
        vox, n = np.unique(cat, return_counts=True)
        return cls(grid, vox, n / float(len(frames)), n_frames=len(frames))

    @classmethod
    def from_probabilities(cls, grid: Grid, p) -> "BernoulliGrid":
        """From a dense (nx, ny, nz) array of probabilities."""
        p = np.asarray(p, dtype=np.float64)
        if p.shape != grid.shape:
            raise ValueError(f"p must have the grid shape {grid.shape}, got {p.shape}")
        flat = p.reshape(-1)
        keep = np.flatnonzero(flat > 0)
        return cls(grid, keep, flat[keep])

    @classmethod
    def from_scene(cls, scene, grid: Grid, frames=None, kinds=None) -> "BernoulliGrid":
        """From the boxes of a Scene's actors (and static boxes in ``scene.meta``), see :func:`scene_boxes`."""
        idx = range(scene.n_frames) if frames is None else frames
        return cls.from_boxes([scene_boxes(scene, f, kinds) for f in idx], grid)

    def dense(self) -> np.ndarray:
        out = np.zeros(self.grid.n_voxels)
        out[self.voxels] = self.p
        return out.reshape(self.grid.shape)

    @property
    def entropy(self) -> np.ndarray:
        """(nx, ny, nz) float64 voxel entropy."""
        h = np.zeros(self.grid.n_voxels)
        h[self.voxels] = binary_entropy(self.p)
        return h.reshape(self.grid.shape)

    @property
    def psog(self) -> PSOG:
        """The same distribution as a two-channel P-SOG (empty, occupied): its entropy is H(v), its stop mask
        is p >= 0.5, so the M-SOG kernels and caches serve S-MIG unchanged."""
        if self._psog is None:
            self._psog = PSOG(self.grid, self.voxels, np.stack([1.0 - self.p, self.p], 1), ("empty", "occupied"),
                              self.n_frames)
        return self._psog

    @property
    def total_entropy(self) -> float:
        """H_total, from the same fixed-point weights the kernels sum."""
        return float(self.psog.weights.sum(dtype=np.int64) / ENTROPY_SCALE)

    def __repr__(self) -> str:
        return f"BernoulliGrid(grid {self.grid.shape}, {len(self.voxels)} voxels with p > 0, T={self.n_frames})"


def _sums(bg: BernoulliGrid, lidar: LidarModel, poses: np.ndarray, occlusion: str, backend, mesh, body=None):
    from place3d_kernels.metrics import check_inputs, mesh_sums

    p = bg.psog
    check_inputs(p, poses, occlusion, mesh)
    b = get_backend(backend)
    if body is not None:
        from place3d_kernels.rig_metrics import rig_sums, rigs_rays

        # mesh occlusion becomes a clipped t_end (rigs_rays), so the rays then traverse without SOG stops
        o, d, te, off, reasons = rigs_rays([([lidar] * len(rig), rig) for rig in poses], body, b,
                                           mesh if occlusion == "mesh" else None)
        bad = [i for i, r in enumerate(reasons) if r]
        if bad:
            raise ValueError(f"rig {bad[0]}: {reasons[bad[0]]}")
        sums, counts = rig_sums(p, o, d, te, off, "seg", "none" if occlusion == "mesh" else occlusion, b)
        return np.asarray(sums, np.int64), np.asarray(counts, np.int64)
    if occlusion == "mesh":
        sums, counts = zip(*(mesh_sums(p, lidar, rig, mesh, b) for rig in poses))
        return np.array(sums, np.int64), np.array(counts, np.int64)
    local = poses.copy()
    local[..., :3] = p.grid.to_local(poses[..., :3])
    sums, counts = b.score_placements(p.handle(b, occlusion), lidar.elevations, lidar.azimuths, lidar.max_range,
                                      local)
    return np.asarray(sums, np.int64), np.asarray(counts, np.int64)


def smig_batch(bgrid: BernoulliGrid, lidar: LidarModel, poses, occlusion: str = "none", reduce: str = "sum",
               backend=None, mesh: Mesh | None = None, body=None) -> np.ndarray:
    """S-MIG of P candidate rigs ((P, L, 6) ego-frame poses) in one backend launch.

    ``body``: optional ``VehicleBody`` (ego frame) whose surface ends the rays (see the module docstring).

    Returns (P,) float64: see the module docstring for ``reduce``; NaN for ``mean`` of a rig that covers
    no voxel.
    """
    if reduce not in REDUCTIONS:
        raise ValueError(f"reduce must be one of {REDUCTIONS}, got {reduce!r}")
    poses = np.asarray(poses.poses if hasattr(poses, "poses") else poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    sums, counts = _sums(bgrid, lidar, poses, occlusion, backend, mesh, body)
    h = sums.astype(np.float64) / ENTROPY_SCALE
    if reduce == "sum":
        return h
    if reduce == "remaining":
        return bgrid.total_entropy - h
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, h / np.maximum(counts, 1), np.nan)


def smig(bgrid: BernoulliGrid, lidar: LidarModel, placement, occlusion: str = "none", reduce: str = "sum",
         backend=None, mesh: Mesh | None = None, body=None) -> float:
    """S-MIG of one placement (see :func:`smig_batch`; ``body`` is an optional ``VehicleBody``)."""
    p = np.asarray(placement.poses if hasattr(placement, "poses") else placement, dtype=np.float64)
    return float(smig_batch(bgrid, lidar, p[None], occlusion, reduce, backend, mesh, body)[0])


def scene_boxes(scene, frame: int, kinds=None) -> np.ndarray:
    """(n, 7) boxes (x, y, z, l, w, h, yaw; z = box centre) in the ego frame of ``frame``.

    One box per actor from its mesh's bounds in its own frame (x forward), posed by the actor's pose at
    that frame, plus any world-frame ``(n, 7)`` boxes in ``scene.meta["static_boxes"]`` (the parked cars of
    OpenDRIVE scenes). ``kinds``: keep only actors with these ``kind`` tags (static boxes count as
    "parked"); default all. Roll and pitch of actors and ego are folded into the box centre only (boxes
    stay upright; yaw is the relative heading).
    """
    ego_inv = invert(pose_matrix(scene.ego_poses[frame]))
    ego_yaw = float(scene.ego_poses[frame][5])
    rows = []
    for a in scene.actors:
        if kinds is not None and a.kind not in kinds:
            continue
        lo, hi = a.mesh.bounds
        c_local = np.r_[(lo + hi) / 2, 1.0]
        T = ego_inv @ pose_matrix(a.poses[frame])
        c = T @ c_local
        size = hi - lo
        rows.append([c[0], c[1], c[2], size[0], size[1], size[2], _wrap(float(a.poses[frame][5]) - ego_yaw)])
    static = scene.meta.get("static_boxes") if isinstance(scene.meta, dict) else None
    if static is not None and len(static) and (kinds is None or "parked" in kinds):
        sb = np.asarray(static, dtype=np.float64).reshape(-1, 7)
        c = np.c_[sb[:, :3], np.ones(len(sb))] @ ego_inv.T
        yaw = np.array([_wrap(v - ego_yaw) for v in sb[:, 6]])
        rows.extend(np.c_[c[:, :3], sb[:, 3:6], yaw].tolist())
    return np.asarray(rows, dtype=np.float64).reshape(-1, 7)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
