"""M-SOG of real rigs: any number of LiDARs with their own beam patterns, on an ego vehicle body.

A rig's rays are built on the host in float64 (sensor-frame direction table rotated by each pose, as the
reference ``lidar_rays`` does), clipped where they hit the body (``VehicleBody``: the backend's ray-mesh
kernel, float64 t) and scored with ``Backend.score_rays``, whose covered voxel sets and fixed-point sums
are identical on every backend. Candidates of one batch may have different ray counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from place3d_kernels.backends.base import ENTROPY_SCALE, rotation_matrices, sensor_directions
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.indicators import check_normalisation, indicator_handle
from place3d_kernels.ops import raycast
from place3d_kernels.sog import PSOG
from place3d_kernels.vehicle import VehicleBody

__all__ = ["msog_from_sums", "direction_table", "rig_rays", "body_t_end", "rig_sums", "msog_rays", "msog_with_body",
           "msog_with_body_batch", "BatchScores", "check_outside_body", "rigs_rays", "msog_rigs"]

_MODES = ("sog", "none")


def msog_from_sums(sums, counts) -> np.ndarray:
    """M-SOG from the kernels' fixed-point sums and counts: -(sum / ENTROPY_SCALE) / count, NaN for 0."""
    s = np.asarray(sums, dtype=np.int64)
    c = np.asarray(counts, dtype=np.int64)
    return np.where(c > 0, -(s.astype(np.float64) / ENTROPY_SCALE) / np.maximum(c, 1), np.nan)


def direction_table(lidar) -> tuple[np.ndarray, float | None]:
    """(R, 3) float64 sensor-frame unit directions of a LiDAR, and its max range (None for a bare table).

    Accepts a ``LidarModel`` (its ``directions()`` where it has one, else its channel x azimuth grid) or a
    plain (R, 3) array.
    """
    if hasattr(lidar, "directions"):
        return np.asarray(lidar.directions(), dtype=np.float64).reshape(-1, 3), float(lidar.max_range)
    if hasattr(lidar, "elevations"):
        return sensor_directions(lidar.elevations, lidar.azimuths), float(lidar.max_range)
    d = np.asarray(lidar, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0 or not np.all(np.isfinite(d)):
        raise ValueError(f"a direction table must be a non-empty finite (R, 3) array, got shape {d.shape}")
    with np.errstate(over="ignore", under="ignore"):     # a row off unit either way is refused below
        n = np.linalg.norm(d, axis=1)
    if np.any(np.abs(n - 1.0) > 1e-9):
        i = int(np.argmax(np.abs(n - 1)))
        m = float(np.max(np.abs(d[i])))
        length = m * float(np.linalg.norm(d[i] / m)) if m > 0 else 0.0     # scaled first: 1e200 is no inf
        raise ValueError(f"direction table rows must be unit vectors; row {i} has length {length:.6g} (normalise "
                         f"it first)")
    return d, None


def rig_rays(directions: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
    """Rays of L LiDARs sharing one (R, 3) sensor-frame table at (L, 6) ego-frame poses: origins and
    directions (L*R, 3), ordered (lidar, ray); direction = R(pose) @ table row, as the reference does."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    d = np.einsum("lij,nj->lni", rotation_matrices(poses), np.asarray(directions, np.float64)).reshape(-1, 3)
    return np.repeat(poses[:, :3], len(directions), axis=0), d


def check_outside_body(body: VehicleBody | None, origins) -> str | None:
    """None when every LiDAR origin ((L, 3)) lies outside the body; else a message naming the first one
    inside it (index and position)."""
    if body is None:
        return None
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    inside = body.contains(o)
    if not np.any(inside):
        return None
    i = int(np.argmax(inside))
    return (f"LiDAR {i} at {np.round(o[i], 4).tolist()} lies inside (or on) the vehicle body {body.name!r} "
            f"(bounds {np.round(body.bounds, 3).tolist()}); mount it outside the body, e.g. above the roof")


def body_t_end(body: VehicleBody | None, origins, directions, max_range: float, backend=None) -> np.ndarray:
    """Per-ray segment length: ``min(max_range, first body hit)`` (the body's ray-mesh hit in float64)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    t = np.full(len(o), float(max_range))
    if body is None or len(o) == 0:
        return t
    hits = raycast(body.mesh, o, directions, float(max_range), backend=backend)
    return np.minimum(t, hits.t)


def rig_sums(psog: PSOG, origins, directions, t_end, ray_offsets, task: str = "seg", occlusion: str = "sog",
             backend=None) -> tuple[np.ndarray, np.ndarray]:
    """Exact int64 entropy sums and covered voxel counts of P candidates given as explicit ego-frame rays
    (CSR ``ray_offsets``); see ``Backend.score_rays``."""
    if occlusion not in _MODES:
        raise ValueError(f"occlusion must be one of {_MODES} for explicit rays, got {occlusion!r} (mesh "
                         f"occlusion: clip t_end with raycast first)")
    p = psog.for_task(task)
    b = get_backend(backend)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    te = np.asarray(t_end, dtype=np.float64)
    if np.any(~np.isfinite(te)) or np.any(te < 0):
        raise ValueError("t_end must be finite and >= 0 for every ray")
    return b.score_rays(p.handle(b, occlusion), p.grid.to_local(o), directions, te, ray_offsets)


def msog_rays(psog: PSOG, origins, directions, t_end, ray_offsets, task: str = "seg", occlusion: str = "sog",
              backend=None) -> np.ndarray:
    """(P,) M-SOG of candidates given as explicit rays (NaN for a candidate that covers nothing)."""
    return msog_from_sums(*rig_sums(psog, origins, directions, t_end, ray_offsets, task, occlusion, backend))


@dataclass
class BatchScores:
    """Scores of a batch of rigs on a body.

    Attributes:
        msog: (P,) M-SOG, NaN for infeasible rigs (a LiDAR inside the body) and rigs that cover nothing.
        feasible: (P,) bool, False where a LiDAR lies inside the body.
        reasons: (P,) message per rig ("" when feasible).
        sums, counts: (P,) int64 exact entropy sums and covered voxel counts (0 for infeasible rigs).
    """

    msog: np.ndarray
    feasible: np.ndarray
    reasons: list
    sums: np.ndarray
    counts: np.ndarray


def msog_with_body_batch(psog: PSOG, lidar, poses, body: VehicleBody | None = None, task: str = "seg",
                         occlusion: str = "sog", backend=None, max_range: float | None = None) -> BatchScores:
    """M-SOG of P rigs of L LiDARs each on a body, for optimisers: infeasible rigs get NaN and a reason,
    never an exception.

    Args:
        psog: the scene's P-SOG (ego frame).
        lidar: ``LidarModel`` or (R, 3) sensor-frame direction table (then ``max_range`` is required).
        poses: (P, L, 6) or (L, 6) ego-frame poses.
        body: the ego vehicle (None: no body, the paper's setting).
        task, occlusion, backend: as in ``msog_batch``.
        max_range: overrides the LiDAR's range.
    """
    table, rng = direction_table(lidar)
    rng = max_range if max_range is not None else rng
    if rng is None or not (np.isfinite(rng) and rng > 0):
        raise ValueError(f"max_range must be a positive number of metres (a bare direction table has none), "
                         f"got {rng!r}")
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[2] != 6 or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be finite (P, L, 6) rows (x, y, z, roll, pitch, yaw), got {poses.shape}")
    P = len(poses)
    reasons = [check_outside_body(body, rig[:, :3]) or "" for rig in poses]
    feasible = np.array([r == "" for r in reasons], dtype=bool)
    b = get_backend(backend)
    os_, ds, off = [], [], [0]
    for p in range(P):
        if feasible[p]:
            o, d = rig_rays(table, poses[p])
            os_.append(o)
            ds.append(d)
        off.append(off[-1] + (len(os_[-1]) if feasible[p] else 0))
    o = np.concatenate(os_) if os_ else np.empty((0, 3))
    d = np.concatenate(ds) if ds else np.empty((0, 3))
    te = body_t_end(body, o, d, rng, backend=b)
    sums, counts = rig_sums(psog, o, d, te, np.asarray(off, np.int64), task, occlusion, b)
    return BatchScores(np.where(feasible, msog_from_sums(sums, counts), np.nan), feasible, reasons, sums, counts)


def msog_with_body(psog: PSOG, lidar, poses, body: VehicleBody | None = None, task: str = "seg",
                   occlusion: str = "sog", backend=None, max_range: float | None = None) -> np.ndarray:
    """(P,) M-SOG of rigs on a body (see ``msog_with_body_batch``).

    Raises:
        ValueError: a LiDAR origin lies inside the body (the message names the LiDAR and its position).
    """
    r = msog_with_body_batch(psog, lidar, poses, body, task, occlusion, backend, max_range)
    bad = np.flatnonzero(~r.feasible)
    if len(bad):
        raise ValueError(f"rig {int(bad[0])}: {r.reasons[bad[0]]}")
    return r.msog


def _min_range(lidar) -> float:
    return float(getattr(lidar, "min_range", 0.0) or 0.0)


def rigs_rays(rigs, body: VehicleBody | None = None, backend=None, mesh=None):
    """Explicit rays of P heterogeneous rigs, ready for ``Backend.score_rays``.

    Each rig is ``(lidars, poses)``: a sequence of L ``LidarModel`` (one per slot, any mix of spinning,
    offset and rosette units) and (L, 6) ego-frame poses. Rigs may differ in size and sensors.

    Minimum range: a sensor drops returns nearer than ``min_range``, so a ray covers voxels only from
    ``min_range`` on. The ray's origin is moved to ``o + min_range * d`` (float64, on the host, the same
    for every backend) and its length shortened to ``t - min_range``. Blocking is measured from the true
    origin: a ray whose first body (or ``mesh``) hit is nearer than ``min_range`` covers nothing and is
    dropped. Occupied P-SOG voxels inside the first ``min_range`` metres do not stop the ray (the kernels
    start traversing at the moved origin); for min ranges of 0.3-0.8 m (the presets) that is the voxel
    holding the sensor.

    Args:
        rigs: sequence of ``(lidars, poses)``.
        body: ego vehicle whose surface ends rays (None: no body).
        backend: backend for the ray-mesh hits.
        mesh: optional scene mesh (ego frame) that also ends rays (occlusion "mesh").

    Returns:
        origins (N, 3), directions (N, 3), t_end (N,), ray_offsets (P+1,), reasons (P,) ("" when
        feasible; an infeasible rig, a LiDAR inside the body, contributes no rays).
    """
    b = get_backend(backend)
    tables: dict[int, tuple[np.ndarray, float]] = {}
    os_, ds, rngs, mins, off, reasons = [], [], [], [], [0], []
    for lidars, poses in rigs:
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
        lidars = list(lidars)
        if len(lidars) != len(poses):
            raise ValueError(f"a rig needs one LiDAR model per pose, got {len(lidars)} models and {len(poses)} poses")
        msg = check_outside_body(body, poses[:, :3]) or ""
        reasons.append(msg)
        n = 0
        if not msg:
            for lid, pose in zip(lidars, poses):
                if id(lid) not in tables:
                    tables[id(lid)] = direction_table(lid)
                table, rng = tables[id(lid)]
                o, d = rig_rays(table, pose[None])
                os_.append(o)
                ds.append(d)
                rngs.append(np.full(len(o), float(rng)))
                mins.append(np.full(len(o), _min_range(lid)))
                n += len(o)
        off.append(off[-1] + n)
    if not os_:
        return (np.empty((0, 3)), np.empty((0, 3)), np.empty(0), np.asarray(off, np.int64), reasons)
    o, d, rng, mn = np.concatenate(os_), np.concatenate(ds), np.concatenate(rngs), np.concatenate(mins)
    t = rng.copy()
    if body is not None:
        t = np.minimum(t, raycast(body.mesh, o, d, float(rng.max()), backend=b).t)
    if mesh is not None:
        t = np.minimum(t, raycast(mesh, o, d, float(rng.max()), backend=b).t)
    t = t - mn
    keep = t > 0
    o = o + mn[:, None] * d
    # drop rays that end before the minimum range, rebuilding the CSR offsets
    cum = np.concatenate([[0], np.cumsum(keep)])
    off = cum[np.asarray(off, np.int64)].astype(np.int64)
    return o[keep], d[keep], t[keep], off, reasons


def msog_rigs(psog: PSOG, rigs, body: VehicleBody | None = None, task: str = "seg", occlusion: str = "sog",
              backend=None, mesh=None, normalisation: str = "paper") -> BatchScores:
    """M-SOG of P heterogeneous rigs (see ``rigs_rays``) in one ``score_rays`` launch.

    Infeasible rigs (a LiDAR inside the body) get NaN and a reason, never an exception.

    ``normalisation`` picks the denominator as in ``metrics.msog_batch``. For ``"evidence"`` and
    ``"uncertain"`` the same rays are scored a second time on the grid of 0/1 indicator weights
    (``metrics.indicator_weights``), whose exact integer sums count the covered voxels that belong in the
    denominator; ``counts`` stays N_L.
    """
    check_normalisation(normalisation)
    b = get_backend(backend)
    o, d, te, off, reasons = rigs_rays(rigs, body, b, mesh)
    feasible = np.array([r == "" for r in reasons], dtype=bool)
    sums, counts = rig_sums(psog, o, d, te, off, task, occlusion, b)
    den = counts
    if normalisation != "paper":
        p = psog.for_task(task)
        den, _ = b.score_rays(indicator_handle(p, normalisation, b, occlusion), p.grid.to_local(o), d, te, off)
    return BatchScores(np.where(feasible, msog_from_sums(sums, den), np.nan), feasible, reasons, sums, counts)
