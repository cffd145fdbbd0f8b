"""M-SOG: the Place3D placement metric (Li et al., NeurIPS 2024, Sec. 3.2).

M-SOG(L) = -(1 / N_L) * sum of H(v) over the N_L distinct voxels crossed by the rays of placement L.
Higher is better (always <= 0). Sums run in fixed-point int64 on every backend, so scores are identical
across backends whenever the covered voxel sets are.

``normalisation`` picks the denominator (docs/metric-normalisation.md): ``"paper"`` (default, the paper's
N_L, computed exactly as before), ``"evidence"`` (covered voxels with occupancy evidence, i.e. stored in the
P-SOG: ever occupied in a subset) or ``"uncertain"`` (covered voxels with H > 0). The alternatives count
their voxels with a second exact integer score call (indicator weights), so they too agree bit for bit.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.lidar import LidarModel
from place3d_kernels.mesh import Mesh
from place3d_kernels.ops import coverage, raycast
from place3d_kernels.indicators import (INDICATORS, NORMALISATIONS, check_normalisation, indicator_handle,
                                        indicator_weights)
from place3d_kernels.sog import PSOG

__all__ = ["msog", "msog_batch", "msog_tasks", "msog_on_grid", "msog_on_handles", "covered_voxels",
           "coverage_mask", "msog_from_voxels", "coverage_counts", "OCCLUSION_MODES", "NORMALISATIONS"]

OCCLUSION_MODES = ("none", "sog", "mesh")
def _poses(placement) -> np.ndarray:
    p = placement.poses if hasattr(placement, "poses") else np.asarray(placement, dtype=np.float64)
    return np.asarray(p, dtype=np.float64)


def check_inputs(psog: PSOG, poses: np.ndarray, occlusion: str, mesh) -> None:
    """Raise ValueError naming the bad value: an unknown occlusion mode, 'mesh' without a mesh, poses that
    are not finite (..., 6) rows or that lie outside the P-SOG's grid."""
    if occlusion not in OCCLUSION_MODES:
        raise ValueError(f"occlusion must be one of {OCCLUSION_MODES}, got {occlusion!r}")
    if occlusion == "mesh" and mesh is None:
        raise ValueError("occlusion='mesh' needs mesh= (the scene in the ego frame)")
    _check_poses(psog.grid, poses)


def _check_poses(grid, poses: np.ndarray) -> None:
    if poses.shape[-1] != 6 or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be finite (..., 6) rows (x, y, z, roll, pitch, yaw); got shape {poses.shape}")
    inside = grid.contains(poses[..., :3].reshape(-1, 3))
    if not np.all(inside):
        bad = poses[..., :3].reshape(-1, 3)[~inside][0]
        raise ValueError(f"LiDAR at {bad.tolist()} lies outside the grid {grid.lower}..{grid.upper}; "
                         f"place LiDARs inside the ROI (ego frame, z up from the ground)")


def _score(sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    sums = np.asarray(sums, dtype=np.int64)
    counts = np.asarray(counts, dtype=np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, -(sums.astype(np.float64) / ENTROPY_SCALE) / np.maximum(counts, 1), np.nan)


def coverage_counts(psog: PSOG, lidar: LidarModel, poses, occlusion: str = "sog", task: str = "seg",
                    backend=None, mesh: Mesh | None = None, kinds=INDICATORS, body=None) -> dict:
    """Exact integer pieces of M-SOG for P rigs: entropy sums, N_L and the indicator counts.

    Args:
        psog, lidar, poses, occlusion, task, backend, mesh, body: as in ``msog_batch``; a sensor that
            ``msog_batch`` scores by explicit rays (not a grid, a minimum range, a body) is counted on the
            same rays, so ``score_from_counts`` gives its scores bit for bit.
        kinds: indicator counts to add (subset of ``("evidence", "uncertain")``).

    Returns:
        dict of (P,) int64 arrays: ``sum`` (fixed-point entropy, scale ``ENTROPY_SCALE``), ``n_covered``
        (N_L), and per kind ``n_evidence`` (covered voxels stored in the P-SOG) / ``n_uncertain``
        (covered voxels with H > 0).
    """
    poses = _poses(poses)
    if poses.ndim == 2:
        poses = poses[None]
    check_inputs(psog, poses, occlusion, mesh)
    for k in kinds:
        if k not in INDICATORS:
            raise ValueError(f"kinds must be among {INDICATORS}, got {k!r}")
    p = psog.for_task(task)
    b = get_backend(backend)
    out = {}
    if body is not None or not lidar.is_grid or lidar.min_range > 0:
        return _ray_counts(p, lidar, poses, occlusion, b, mesh, kinds, body)
    if occlusion == "mesh":
        masks = [mesh_mask(p, lidar, rig, mesh, b) for rig in poses]
        out["sum"] = np.array([p.weights[m].sum(dtype=np.int64) for m in masks], dtype=np.int64)
        out["n_covered"] = np.array([m.sum() for m in masks], dtype=np.int64)
        for k in kinds:
            w = indicator_weights(p, k)
            out[f"n_{k}"] = np.array([w[m].sum(dtype=np.int64) for m in masks], dtype=np.int64)
        return out
    local = poses.copy()
    local[..., :3] = p.grid.to_local(poses[..., :3])
    # the indicator grids share the P-SOG's stop mask, so one score_placements_many call covers them all: a
    # backend that walks the rays once for several grids (OpenCL on CPUs) walks them once here, not 1 + kinds times
    handles = count_handles(p, occlusion, b, kinds)
    res = b.score_placements_many(handles, lidar.elevations, lidar.azimuths, lidar.max_range, local)
    sums, counts = res[0]
    out["sum"], out["n_covered"] = np.asarray(sums, np.int64), np.asarray(counts, np.int64)
    for k, (n, _) in zip(kinds, res[1:]):
        out[f"n_{k}"] = np.asarray(n, np.int64)
    return out


def count_handles(p: PSOG, occlusion: str, b, kinds=INDICATORS) -> list:
    """The prepared grids ``coverage_counts`` scores a task's P-SOG ``p`` on (kept by ``p``): its weights' grid,
    then one indicator grid per kind. A caller may make them ahead (``place3d optimize``'s held-out P-SOGs)."""
    return [p.handle(b, occlusion)] + [indicator_handle(p, k, b, occlusion) for k in kinds]


def _ray_counts(p: PSOG, lidar: LidarModel, poses: np.ndarray, occlusion: str, b, mesh, kinds, body) -> dict:
    """``coverage_counts`` on the explicit rays ``msog_batch`` scores such a sensor with (``rig_metrics``)."""
    from place3d_kernels.rig_metrics import rigs_rays

    o, d, te, off, reasons = rigs_rays([([lidar] * len(rig), rig) for rig in poses], body, b,
                                       mesh if occlusion == "mesh" else None)
    bad = [i for i, r in enumerate(reasons) if r]
    if bad:
        raise ValueError(f"rig {bad[0]}: {reasons[bad[0]]}")
    occ = "none" if occlusion == "mesh" else occlusion       # the mesh already ended the rays
    local = p.grid.to_local(o)
    sums, counts = b.score_rays(p.handle(b, occ), local, d, te, off)
    out = {"sum": np.asarray(sums, np.int64), "n_covered": np.asarray(counts, np.int64)}
    for k in kinds:
        n, _ = b.score_rays(indicator_handle(p, k, b, occ), local, d, te, off)
        out[f"n_{k}"] = np.asarray(n, np.int64)
    return out


def score_from_counts(counts: dict, normalisation: str = "paper") -> np.ndarray:
    """M-SOG from ``coverage_counts`` output: -(sum H) / denominator of ``normalisation`` (NaN when 0)."""
    check_normalisation(normalisation)
    den = counts["n_covered"] if normalisation == "paper" else counts[f"n_{normalisation}"]
    return _score(counts["sum"], den)


def msog_batch(psog: PSOG, lidar: LidarModel, poses, occlusion: str = "sog", task: str = "seg",
               backend=None, mesh: Mesh | None = None, normalisation: str = "paper", body=None) -> np.ndarray:
    """M-SOG of P candidate rigs in one backend launch.

    Grid LiDARs (``lidar.is_grid``) with no minimum range and no body take the fused
    ``score_placements`` kernel. Every other case (per-channel azimuth offsets, rosette scans,
    ``min_range > 0``, a vehicle body) builds the rays on the host and scores them with
    ``Backend.score_rays`` (``place3d_kernels.rig_metrics.msog_rigs``): rays start at ``min_range``
    (origin moved along the ray in float64) and end where the body blocks them. Both paths are exact
    and identical on every backend.

    Args:
        psog: the scene's P-SOG (ego frame).
        lidar: beam pattern shared by all LiDARs.
        poses: (P, L, 6) ego-frame poses.
        occlusion: "sog" (stop after the first voxel occupied with p >= 0.5), "none" (cast to max range),
            or "mesh" (stop at the first surface of ``mesh``, given in the ego frame).
        task: "seg" (22-channel P-SOG) or "det" (empty / vehicle / other).
        backend: backend name or instance.
        mesh: the scene mesh for occlusion "mesh".
        normalisation: denominator of the mean: ``"paper"`` (N_L, every covered voxel; the default and
            the paper's definition), ``"evidence"`` (covered voxels stored in the P-SOG, i.e. occupied in at
            least one subset) or ``"uncertain"`` (covered voxels with H > 0). See
            docs/metric-normalisation.md for why N_L rewards rays through empty air. Every normalisation
            takes every sensor, body and minimum range (the alternatives count their voxels on a grid of 0/1
            weights: for grid LiDARs in the same ``score_placements_many`` call, which Warp and OpenCL answer
            from one walk of the rays; for explicit rays with a second call of the same kernel).
        body: optional ``VehicleBody`` (ego frame) whose surface blocks rays.

    Returns:
        (P,) float64 scores (NaN for a rig whose denominator is 0); an empty array for P = 0 rigs.

    Raises:
        ValueError: bad inputs, or a LiDAR origin inside ``body`` (the message names it).
    """
    rays = body is not None or not lidar.is_grid or lidar.min_range > 0
    if check_normalisation(normalisation) != "paper" and not rays:
        return score_from_counts(coverage_counts(psog, lidar, poses, occlusion, task, backend, mesh,
                                                 kinds=(normalisation,)), normalisation)
    poses = _poses(poses)
    if poses.ndim == 2:
        poses = poses[None]
    check_inputs(psog, poses, occlusion, mesh)
    if len(poses) == 0:      # no rigs: no scores, on every path and backend
        return np.zeros(0, dtype=np.float64)
    p = psog.for_task(task)
    b = get_backend(backend)
    if rays:
        from place3d_kernels.rig_metrics import msog_rigs

        r = msog_rigs(psog, [([lidar] * len(rig), rig) for rig in poses], body, task,
                      "none" if occlusion == "mesh" else occlusion, b, mesh if occlusion == "mesh" else None,
                      normalisation=normalisation)
        bad = np.flatnonzero(~r.feasible)
        if len(bad):
            raise ValueError(f"rig {int(bad[0])}: {r.reasons[bad[0]]}")
        return r.msog
    if occlusion == "mesh":
        sums, counts = zip(*(mesh_sums(p, lidar, rig, mesh, b) for rig in poses))
        return _score(np.array(sums), np.array(counts))
    return _fused_scores(p.grid, p.handle(b, occlusion), lidar, poses, b)


def msog_tasks(psog: PSOG, lidar: LidarModel, poses, occlusion: str = "sog", tasks=("seg", "det"), backend=None,
               normalisation: str = "paper", body=None) -> dict:
    """{task: ``msog_batch(psog, lidar, poses, occlusion, task, backend, normalisation=..., body=...)``}, the
    same scores. Where ``msog_batch`` takes its fused kernel (a grid LiDAR from range 0, no body, occlusion
    by the SOG or none) the tasks' grids, which share the stop mask, are scored in one
    ``Backend.score_placements_many`` call, which may walk the rays once for all of them."""
    check_normalisation(normalisation)
    if body is not None or not lidar.is_grid or lidar.min_range > 0 or occlusion not in ("sog", "none"):
        return {t: msog_batch(psog, lidar, poses, occlusion, t, backend, normalisation=normalisation, body=body)
                for t in tasks}
    poses = _poses(poses)
    if poses.ndim == 2:
        poses = poses[None]
    check_inputs(psog, poses, occlusion, None)
    b = get_backend(backend)
    pairs = []
    for t in tasks:
        p = psog.for_task(t)
        pairs.append((p.handle(b, occlusion),
                      None if normalisation == "paper" else indicator_handle(p, normalisation, b, occlusion)))
    return dict(zip(tasks, msog_on_handles(psog.grid, pairs, lidar, poses, b)))


def _fused_scores(grid, handle, lidar: LidarModel, poses: np.ndarray, b) -> np.ndarray:
    """Scores of rigs (P, L, 6) in the ego frame by the fused kernel on a prepared grid handle."""
    local = poses.copy()
    local[..., :3] = grid.to_local(poses[..., :3])
    sums, counts = b.score_placements(handle, lidar.elevations, lidar.azimuths, lidar.max_range, local)
    return _score(sums, counts)


def msog_on_grid(grid, weights: np.ndarray, stop: np.ndarray | None, lidar: LidarModel, poses,
                 backend=None) -> np.ndarray:
    """``msog_batch`` (paper normalisation, a grid LiDAR without minimum range or body) on a grid given by
    its fixed-point weights and stop mask instead of a ``PSOG``: the values a P-SOG's ``weights`` and
    ``stop_mask`` hold (``stop`` None: occlusion "none"). The jackknife scores its leave-one-out grids so
    (``place3d_kernels.left_out``); the kernel and the arithmetic are ``msog_batch``'s."""
    poses = _grid_lidar_poses(grid, lidar, poses, "msog_on_grid")
    b = get_backend(backend)
    return _fused_scores(grid, b.prepare_grid(grid.spec, weights, stop), lidar, poses, b)


def msog_on_handles(grid, pairs, lidar: LidarModel, poses, backend) -> list[np.ndarray]:
    """``msog_on_grid`` for each (handle, indicator or None) of ``pairs``: grids already prepared by
    ``backend.prepare_grid(grid.spec, weights, stop)`` (``backend`` the same instance) that share one stop
    mask (the seg and det views of one P-SOG do: both stop where p(empty) <= 0.5); the same checks and
    scores, without the upload, in one ``Backend.score_placements_many`` call, which may walk the rays once
    for all of them. The jackknife keeps its left-out grids prepared so (``left_out_memo.PreparedLeftOut``).

    ``indicator``: for the ``evidence`` and ``uncertain`` normalisations, the handle of the grid's 0/1
    ``indicator_weights`` with the same stop mask; its sums are the denominators (``coverage_counts``)."""
    poses = _grid_lidar_poses(grid, lidar, poses, "msog_on_handles")
    b = get_backend(backend)
    local = poses.copy()
    local[..., :3] = grid.to_local(poses[..., :3])
    handles = [h for pair in pairs for h in pair if h is not None]
    res = iter(b.score_placements_many(handles, lidar.elevations, lidar.azimuths, lidar.max_range, local))
    out = []
    for _, indicator in pairs:
        sums, counts = next(res)
        out.append(_score(sums, counts if indicator is None else next(res)[0]))
    return out


def _grid_lidar_poses(grid, lidar: LidarModel, poses, caller: str) -> np.ndarray:
    """(P, L, 6) float64 poses, checked: a grid LiDAR without minimum range, finite poses inside ``grid``."""
    if not lidar.is_grid or lidar.min_range > 0:
        raise ValueError(f"{caller} takes grid LiDARs without a minimum range; use msog_batch for "
                         f"{lidar.name or 'this sensor'}")
    poses = _poses(poses)
    if poses.ndim == 2:
        poses = poses[None]
    _check_poses(grid, poses)
    return poses


def mesh_mask(p: PSOG, lidar: LidarModel, rig: np.ndarray, mesh: Mesh, b) -> np.ndarray:
    """(n_voxels,) bool: voxels covered by one rig whose rays stop at the mesh (occlusion 'mesh')."""
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, rig)
    hits = raycast(mesh, o, d, lidar.max_range, backend=b)
    t_end = np.minimum(hits.t, lidar.max_range)
    return coverage(p.grid, o, d, t_end, backend=b).reshape(-1)


def mesh_sums(p: PSOG, lidar: LidarModel, rig: np.ndarray, mesh: Mesh, b) -> tuple[int, int]:
    """(fixed-point entropy sum, voxel count) covered by one rig whose rays stop at the mesh (occlusion 'mesh')."""
    mask = mesh_mask(p, lidar, rig, mesh, b)
    return int(p.weights[mask].sum(dtype=np.int64)), int(mask.sum())


def msog(psog: PSOG, lidar: LidarModel, placement, occlusion: str = "sog", task: str = "seg", backend=None,
         mesh: Mesh | None = None, normalisation: str = "paper", body=None) -> float:
    """M-SOG of one placement (see ``msog_batch``; ``body`` is an optional ``VehicleBody``)."""
    return float(msog_batch(psog, lidar, _poses(placement)[None], occlusion, task, backend, mesh,
                            normalisation, body)[0])


def covered_voxels(psog: PSOG, lidar: LidarModel, poses, occlusion: str = "sog", backend=None,
                   mesh: Mesh | None = None) -> np.ndarray:
    """Sorted unique flat indices of the voxels covered by the LiDARs at ``poses`` ((L, 6) or (6,)).

    Used to cache coverage per LiDAR pose: the M-SOG of a rig is then a union of cached sets.
    """
    return np.flatnonzero(coverage_mask(psog, lidar, poses, occlusion, backend, mesh))


def coverage_mask(psog: PSOG, lidar: LidarModel, poses, occlusion: str = "sog", backend=None,
                  mesh: Mesh | None = None) -> np.ndarray:
    """(n_voxels,) bool, flat in C order: True at ``covered_voxels``' voxels (the backend's coverage mask as it
    comes, for a caller that wants the mask rather than the indices: a figure's covered columns)."""
    poses = _poses(poses).reshape(-1, 6)
    check_inputs(psog, poses, occlusion, mesh)
    b = get_backend(backend)
    # the union mask of the coverage kernel, not traverse + np.unique: the same sorted set (C order is the
    # flat index order), without writing out every visit (a large part of a CPU optimise run's plot)
    from place3d_kernels.ops import coverage

    if not lidar.is_grid or lidar.min_range > 0:
        # the rays msog_batch scores for such models (start at min_range; see rig_metrics.rigs_rays)
        from place3d_kernels.rig_metrics import rigs_rays

        o, d, t_end, _, _ = rigs_rays([([lidar] * len(poses), poses)], None, b,
                                      mesh if occlusion == "mesh" else None)
    else:
        o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, poses)
        if occlusion == "mesh":
            t_end = np.minimum(raycast(mesh, o, d, lidar.max_range, backend=b).t, lidar.max_range)
        else:
            t_end = lidar.max_range
    stop = psog.stop_mask if occlusion == "sog" else None
    return np.asarray(coverage(psog.grid, o, d, t_end, backend=b, stop=stop), dtype=bool).reshape(-1)


def msog_from_voxels(psog: PSOG, voxels: np.ndarray, task: str = "seg") -> float:
    """M-SOG of a covered voxel set (exact fixed-point sum, like the kernels)."""
    w = psog.for_task(task).weights
    v = np.asarray(voxels, dtype=np.int64)
    return float(_score(np.array([w[v].sum(dtype=np.int64)]), np.array([len(v)]))[0])
