"""The town's ego drive and moving actors: lead, follow and oncoming vehicles, traffic, pedestrians."""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Actor
from place3d_kernels.scene.bodies import EGO_LENGTH, EGO_WIDTH, pedestrian_mesh, vehicle_mesh
from place3d_kernels.scene.paths import DIRS, fillet, lane_path, walk

__all__ = ["ego_drive", "place_actors"]


def _axes(yaw) -> np.ndarray:
    """(N, 2, 2): each rectangle's unit x and y axes for yaws (N,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)


def _obb_overlap(c1, a1, h1, c2, a2, h2) -> np.ndarray:
    """Whether oriented rectangles overlap (SAT), row by row.

    c: (N, 2) centres, a: (N, 2, 2) axes (``_axes``), h: (N, 2) half extents.
    """
    d = c2 - c1
    sep = np.zeros(len(c1), bool)
    for axes in (a1, a2):
        for k in range(2):
            ax = axes[:, k]
            r1 = h1[:, 0] * np.abs(np.einsum("nj,nj->n", ax, a1[:, 0])) + \
                h1[:, 1] * np.abs(np.einsum("nj,nj->n", ax, a1[:, 1]))
            r2 = h2[:, 0] * np.abs(np.einsum("nj,nj->n", ax, a2[:, 0])) + \
                h2[:, 1] * np.abs(np.einsum("nj,nj->n", ax, a2[:, 1]))
            sep |= np.abs(np.einsum("nj,nj->n", ax, d)) > r1 + r2
    return ~sep


def _footprint(mesh: Mesh):
    """Local centre offset (2,) and half extents (2,) of a mesh's xy bounding box."""
    lo, hi = mesh.vertices[:, :2].min(0), mesh.vertices[:, :2].max(0)
    return (lo + hi) / 2, (hi - lo) / 2


def _world_centre(poses, offset):
    c, s = np.cos(poses[:, 5]), np.sin(poses[:, 5])
    return np.stack([poses[:, 0] + c * offset[0] - s * offset[1], poses[:, 1] + s * offset[0] + c * offset[1]], 1)


def ego_drive(rng, opt, c, nb, P, hw, lw, n_frames, dt) -> dict:
    """The ego drive along the right-hand lane of a random junction walk, turning once at a junction.

    Returns:
        dict with ``nodes`` (junction walk), ``path`` (lane centreline), ``s`` (arc length per frame),
        ``poses`` (n_frames, 6), ``speed`` (m/s), ``offset`` (lateral lane offset) and ``t`` (s per frame).
    """
    ego_speed = opt["ego_speed"]
    ego_speed = float(rng.uniform(6.5, 8.5)) if ego_speed is None else float(ego_speed)
    L_ego = ego_speed * dt * (n_frames - 1)
    t = np.arange(n_frames) * dt
    off = -lw / 2  # right-hand lane (left normal points left)
    start = (int(rng.integers(0, nb + 1)), int(rng.integers(0, nb + 1)))
    opts = [d for d in DIRS if 0 <= start[0] + d[0] <= nb and 0 <= start[1] + d[1] <= nb]
    d0 = opts[int(rng.integers(0, len(opts)))]
    n_seg = int(math.ceil((L_ego + 120.0) / P)) + 3
    fwd = walk(rng, start, d0, n_seg, nb, force_turn_at=1)
    # extend backwards (for the follow vehicle and the oncoming traffic leaving the scene)
    bopts = [d for d in opts if d != d0] or opts
    back = walk(rng, start, bopts[int(rng.integers(0, len(bopts)))], 2, nb)
    nodes = back[::-1] + fwd[1:]
    ego_path = lane_path(nodes, c, off)
    node_s = [0.0]  # arc length where the path passes each junction (walks may revisit a junction)
    for i, j in nodes[1:]:
        node_s.append(ego_path.nearest_s((c[i], c[j]), node_s[-1] + P / 2, node_s[-1] + 1.5 * P))
    k_start = len(back) - 1
    s_turn = node_s[k_start + 1]
    s0 = s_turn - rng.uniform(0.35, 0.6) * L_ego
    s0 = max(s0, node_s[k_start] + hw + 4.0)
    s0 = min(s0, s_turn - 2.0) if L_ego > 0 else s0
    s_ego = s0 + ego_speed * t
    ex, ey, eyaw = ego_path.at(s_ego)
    ego_poses = np.zeros((n_frames, 6))
    ego_poses[:, 0], ego_poses[:, 1], ego_poses[:, 5] = ex, ey, eyaw
    return {"nodes": nodes, "path": ego_path, "s": s_ego, "poses": ego_poses, "speed": ego_speed, "offset": off,
            "t": t}


class _Placer:
    """Actors accepted so far; rejects any that overlaps the ego, or (vehicles) another vehicle, at any frame."""

    def __init__(self, ego_poses):
        self.ego_c = ego_poses[:, :2].copy()
        self.ego_a = _axes(ego_poses[:, 5])
        n = len(ego_poses)
        self.ego_h = np.broadcast_to(np.array([EGO_LENGTH / 2 + 0.4, EGO_WIDTH / 2 + 0.3]), (n, 2))  # with a margin
        self.actors: list[Actor] = []
        # the accepted vehicles' boxes at every frame, one block of rows per vehicle: centres, axes, half extents
        # (with a 0.3 m margin); a candidate is checked against all of them at once
        self.veh_c = np.empty((0, 2))
        self.veh_a = np.empty((0, 2, 2))
        self.veh_h = np.empty((0, 2))

    def try_add(self, mesh, poses, tag, check_vehicles=True):
        off_c, half = _footprint(mesh)
        cen = _world_centre(poses, off_c)
        axes = _axes(poses[:, 5])
        h = np.broadcast_to(half, cen.shape)
        if np.any(_obb_overlap(self.ego_c, self.ego_a, self.ego_h, cen, axes, h)):
            return False
        if check_vehicles:
            k = len(self.veh_c) // len(cen)
            if k and np.any(_obb_overlap(self.veh_c, self.veh_a, self.veh_h, np.tile(cen, (k, 1)),
                                         np.tile(axes, (k, 1, 1)), np.tile(h, (k, 1)))):
                return False
            self.veh_c = np.concatenate([self.veh_c, cen])
            self.veh_a = np.concatenate([self.veh_a, axes])
            self.veh_h = np.concatenate([self.veh_h, np.broadcast_to(half + 0.3, cen.shape)])
        self.actors.append(Actor(mesh, poses, tag))
        return True


def _poses_on(path, s, z=0.0):
    x, y, yaw = path.at(s)
    p = np.zeros((len(s), 6))
    p[:, 0], p[:, 1], p[:, 2], p[:, 5] = x, y, z, yaw
    return p


def place_actors(rng, opt, c, nb, P, hw, sw, ch, ego: dict) -> list[Actor]:
    """Lead, follow and oncoming vehicles around the ego, random traffic, and pedestrians on the sidewalks."""
    placer = _Placer(ego["poses"])
    _ego_lane_traffic(rng, opt, c, ego, placer)
    _random_traffic(rng, opt, c, nb, P, hw, ego, placer)
    _pedestrians(rng, opt, c, nb, hw, sw, ch, ego, placer)
    return placer.actors


def _ego_lane_traffic(rng, opt, c, ego, placer: _Placer):
    """A lead and a follow vehicle in the ego lane, and oncoming vehicles meeting the ego."""
    s_ego, t, ego_speed, n_frames = ego["s"], ego["t"], ego["speed"], len(ego["t"])
    lead, _ = vehicle_mesh(rng, str(rng.choice(["car", "car", "van"])))
    placer.try_add(lead, _poses_on(ego["path"], s_ego + rng.uniform(14.0, 24.0) +
                                   ego_speed * rng.uniform(-0.1, 0.1) * t), "lead")
    follow, _ = vehicle_mesh(rng, "car")
    placer.try_add(follow, _poses_on(ego["path"], s_ego - rng.uniform(13.0, 22.0)), "follow")
    # oncoming traffic: the reversed walk in the opposite lane, meeting the ego
    onc_path = lane_path(ego["nodes"][::-1], c, ego["offset"])
    n_onc = int(opt["n_oncoming"])
    meet = np.linspace(0.15, 0.85, max(n_onc, 1)) * max(n_frames - 1, 0)
    for k in range(n_onc):
        for attempt in range(12):
            fm = int(np.clip(round(meet[k] + rng.uniform(-3, 3)), 0, n_frames - 1))
            v = rng.uniform(6.0, 10.0)
            est = onc_path.length - s_ego[fm]  # the reversed walk: arc lengths run backwards
            s_m = onc_path.nearest_s(placer.ego_c[fm], est - 40.0, est + 40.0)
            s = s_m + v * (t - t[fm])
            m, kind = vehicle_mesh(rng)
            if placer.try_add(m, _poses_on(onc_path, s), "oncoming"):
                break


def _random_traffic(rng, opt, c, nb, P, hw, ego, placer: _Placer):
    """Vehicles on random junction walks in the right-hand lane."""
    t = ego["t"]
    T_total = t[-1] if len(t) > 1 else 0.0
    for k in range(int(opt["n_traffic"])):
        for attempt in range(12):
            st = (int(rng.integers(0, nb + 1)), int(rng.integers(0, nb + 1)))
            dd = [d for d in DIRS if 0 <= st[0] + d[0] <= nb and 0 <= st[1] + d[1] <= nb]
            d0 = dd[int(rng.integers(0, len(dd)))]
            v = rng.uniform(5.0, 11.0)
            nseg = int(math.ceil((v * T_total + 2 * P) / P)) + 1
            path = lane_path(walk(rng, st, d0, nseg, nb), c, ego["offset"])
            s = rng.uniform(hw + 3.0, P - hw) + v * t
            m, kind = vehicle_mesh(rng)
            if placer.try_add(m, _poses_on(path, s), "vehicle"):
                break


def _pedestrians(rng, opt, c, nb, hw, sw, ch, ego, placer: _Placer):
    """Pedestrians walking laps on the sidewalk rims; half of them around blocks next to the ego route."""
    nodes, t = ego["nodes"], ego["t"]
    T_total = t[-1] if len(t) > 1 else 0.0
    route_blocks = set()
    for (i0, j0), (i1, j1) in zip(nodes[:-1], nodes[1:]):
        for bi in range(nb):
            for bj in range(nb):
                if i0 == i1 and i0 in (bi, bi + 1) and min(j0, j1) == bj:
                    route_blocks.add((bi, bj))
                if j0 == j1 and j0 in (bj, bj + 1) and min(i0, i1) == bi:
                    route_blocks.add((bi, bj))
    route_blocks = sorted(route_blocks) or [(0, 0)]
    peds: list[np.ndarray] = []
    for k in range(int(opt["n_pedestrians"])):
        for attempt in range(10):
            if k % 2 == 0:
                bi, bj = route_blocks[int(rng.integers(0, len(route_blocks)))]
            else:
                bi, bj = int(rng.integers(0, nb)), int(rng.integers(0, nb))
            X0, X1, Y0, Y1 = c[bi] + hw, c[bi + 1] - hw, c[bj] + hw, c[bj + 1] - hw
            dlt = rng.uniform(1.8, min(2.8, sw - 0.6))
            ring = np.array([(X0 + dlt, Y0 + dlt), (X1 - dlt, Y0 + dlt), (X1 - dlt, Y1 - dlt), (X0 + dlt, Y1 - dlt)])
            if rng.random() < 0.5:
                ring = ring[::-1]
            ring = np.roll(ring, int(rng.integers(0, 4)), axis=0)
            v = rng.uniform(0.9, 1.6)
            laps = int(math.ceil(v * T_total / (4 * (X1 - X0)))) + 2
            path = fillet(np.concatenate([ring] * laps + [ring[:1]]), 1.0, 0.2)
            s = rng.uniform(0.0, path.length / laps) + v * t
            poses = _poses_on(path, s, ch)
            xy = poses[:, :2]
            if any(np.any(np.linalg.norm(xy - q, axis=1) < 0.9) for q in peds):
                continue
            if placer.try_add(pedestrian_mesh(rng), poses, "pedestrian", check_vehicles=False):
                peds.append(xy)
                break
