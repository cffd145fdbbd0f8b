"""The ego drive and moving actors of OpenDRIVE towns: routes chained along lane centre lines."""

from __future__ import annotations

import numpy as np

from place3d_kernels.scene.base import Actor
from place3d_kernels.scene.bodies import EGO_LENGTH, pedestrian_mesh, vehicle_mesh
from place3d_kernels.scene.opendrive_mesh import DRIVING_TYPES, RAISED
from place3d_kernels.scene.opendrive_routes import LaneGraph, Route, polylen

__all__ = ["ego_drive", "traffic"]


def ego_drive(rng, lanes, opt, t, where) -> tuple[Route, np.ndarray, float, LaneGraph, float]:
    """The ego route: the longest of up to 40 random lane chains, stopping at the first long enough.

    Args:
        rng: the scene's generator.
        lanes: ``(type, in_junction, centre points, widths, road id)`` per meshed lane.
        opt: the builder options (``ego_speed``).
        t: (n_frames,) frame times, s.
        where: names the file in errors.

    Returns:
        the route, the ego poses (n_frames, 6), the ego speed (m/s), the graph of driving lanes
        and the ego's start on the route (m).

    Raises:
        ValueError: the map has no driving lanes.
    """
    driving = [l for l in lanes if l[0] in DRIVING_TYPES and l[0] != "parking"]
    graph = LaneGraph(driving)
    if not graph.lanes:
        raise ValueError(f"{where}: no driving lanes for the ego route")
    ego_speed = opt["ego_speed"]
    ego_speed = float(rng.uniform(6.5, 8.5)) if ego_speed is None else float(ego_speed)
    need = ego_speed * t[-1] + 30.0
    best = None
    cand = [i for i, l in enumerate(graph.lanes) if not l[1]] or list(range(len(graph.lanes)))
    for _ in range(40):
        i = cand[int(rng.integers(0, len(cand)))]
        r = graph.route(i, need, rng)
        if best is None or r.length > best.length:
            best = r
        if r.length >= need:
            break
    ego_route = best
    s0 = min(rng.uniform(0.0, 10.0), max(ego_route.length - ego_speed * t[-1], 0.0))
    s_ego = s0 + ego_speed * t
    return ego_route, ego_route.poses(s_ego), ego_speed, graph, s0


def traffic(rng, graph: LaneGraph, lanes, opt, t, ego_xy, ego_route=None, ego_s0=0.0, ego_speed=0.0) -> list[Actor]:
    """A lead vehicle on the ego route (``ego_route`` from ``ego_s0`` at ``ego_speed``), moving vehicles (half
    of them starting near the ego route) and pedestrians on the sidewalks; none comes closer to the ego or to
    another actor than their radii at any frame."""
    n_frames = len(t)
    actors: list[Actor] = []
    tracks: list[np.ndarray] = [ego_xy]
    radii: list[float] = [EGO_LENGTH / 2 + 0.5]

    def clear(xy, rad):
        return all(np.min(np.linalg.norm(xy - o, axis=1)) > rad + r0 for o, r0 in zip(tracks, radii))

    # a lead vehicle ahead of the ego in its lane, as in the embedded town: random traffic spread over a
    # large map (Town06: 7 km of road) may never come near the ego
    if ego_route is not None and opt["n_lead"]:
        m, _ = vehicle_mesh(rng, str(rng.choice(["car", "car", "van"])))
        half = float(max(m.bounds[1, 0] - m.bounds[0, 0], 2.0)) / 2
        v = ego_speed * rng.uniform(0.9, 1.05)
        poses = ego_route.poses(ego_s0 + rng.uniform(14.0, 22.0) + v * t)
        if clear(poses[:, :2], half):
            tracks.append(poses[:, :2])
            radii.append(half)
            actors.append(Actor(m, poses, "lead"))

    for k in range(int(opt["n_traffic"])):
        for _attempt in range(10):
            # half of the traffic starts near the ego route
            if k % 2 == 0:
                near = ego_xy[int(rng.integers(0, n_frames))]
                dist = np.linalg.norm(graph.starts - near, axis=1)
                pool = np.flatnonzero(dist < 80.0)
                i = int(pool[int(rng.integers(0, len(pool)))]) if len(pool) else int(rng.integers(0, len(graph.lanes)))
            else:
                i = int(rng.integers(0, len(graph.lanes)))
            v = rng.uniform(5.0, 11.0)
            r = graph.route(i, v * t[-1] + 20.0, rng)
            if r.length < v * t[-1] + 5.0:
                continue
            s = rng.uniform(0.0, max(r.length - v * t[-1] - 1.0, 0.0)) + v * t
            m, _ = vehicle_mesh(rng)
            half = float(max(m.bounds[1, 0] - m.bounds[0, 0], 2.0)) / 2
            poses = r.poses(s)
            if clear(poses[:, :2], half):
                tracks.append(poses[:, :2])
                radii.append(half)
                actors.append(Actor(m, poses, "vehicle"))
                break
    walks = [l for l in lanes if l[0] in RAISED and polylen(l[2]) > 1.5 * 1.6 * t[-1] + 5.0]
    for k in range(int(opt["n_pedestrians"]) if walks else 0):
        for _attempt in range(10):
            l = walks[int(rng.integers(0, len(walks)))]
            pts = l[2] if rng.random() < 0.5 else l[2][::-1]
            r = Route(pts)
            v = rng.uniform(0.9, 1.6)
            s = rng.uniform(0.0, max(r.length - v * t[-1], 0.0)) + v * t
            poses = r.poses(s)
            poses[:, 4] = 0.0
            if clear(poses[:, :2], 0.4):
                tracks.append(poses[:, :2])
                radii.append(0.4)
                actors.append(Actor(pedestrian_mesh(rng), poses, "pedestrian"))
                break
    return actors
