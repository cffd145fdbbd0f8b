"""The embedded default scene: a seeded procedural semantic town with an ego drive and moving actors.

Layout (world frame: x/y horizontal, z up, ground at z = 0): a grid of ``blocks x blocks`` city blocks
separated by two-lane roads (right-hand traffic) with parking strips, painted lines and zebra crossings.
Each block is a raised slab (top z = curb height) whose rim is sidewalk; its interior is one of four
kinds -- perimeter (a ring of buildings around a courtyard), towers (podium towers on a plaza), park
(lawns, paths, pond, trees, fences) or houses (gabled houses on fenced lots). Street furniture (trees,
lamps, signs, traffic lights, benches, bins, hydrants) stands in the curb zone of the sidewalks; parked
cars line the parking strips. Outside the network: terrain with trees, a pond, sheds, and guard rails,
a noise wall and a fence along the border roads.

Every face carries a Place3D class (``place3d_kernels.classes``). Solids are closed boxes, prisms and
icospheres; the ground is an open surface made of non-overlapping quads (road, terrain, water), and block
slabs are closed with curbs as their side walls.

The builder is split by concern: ``town_layout`` (ground, roads, parked cars, block slabs),
``town_blocks`` (block interiors), ``town_furniture`` (sidewalk furniture, outskirts), ``props`` and
``bodies`` (meshes shared with the OpenDRIVE towns), ``paths`` (lane centrelines, walks) and
``town_actors`` (ego drive and moving actors); this module checks the options and assembles the Scene.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.scene.base import Scene
from place3d_kernels.scene.bodies import EGO_LENGTH, EGO_WIDTH, pedestrian_mesh, vehicle_mesh
from place3d_kernels.scene.paths import Path
from place3d_kernels.scene.props import Props
from place3d_kernels.scene.town_actors import ego_drive, place_actors
from place3d_kernels.scene.town_furniture import outskirts
from place3d_kernels.scene.town_layout import blocks, ground, road_markings

__all__ = ["town", "TOWN_OPTIONS", "EGO_LENGTH", "EGO_WIDTH", "Path", "vehicle_mesh", "pedestrian_mesh"]

#: options of :func:`town` and their defaults
TOWN_OPTIONS = {
    "blocks": 3,             # blocks per side (roads: blocks + 1 per direction)
    "block_size": 90.0,      # distance between road centrelines, m
    "lane_width": 3.5,       # one lane per direction, m
    "parking_width": 2.5,    # parking strip between lane and curb, m
    "sidewalk_width": 3.5,   # m
    "curb_height": 0.14,     # sidewalk / block top, m; not 0.15, a voxel face of the default grid (below)
    "margin": 45.0,          # terrain band around the road network, m
    "ego_speed": None,       # m/s; None: uniform in [6.5, 8.5] from the seed
    "n_traffic": 10,         # moving vehicles on random routes (besides lead/follow/oncoming ones)
    "n_oncoming": 3,         # vehicles in the opposite lane of the ego route, meeting the ego
    "n_pedestrians": 24,     # pedestrians walking the sidewalks
    "frame_interval": 0.5,   # s between frames
}



def town(seed: int = 0, n_frames: int = 40, **options) -> Scene:
    """The embedded default scene: a procedural semantic town, an ego drive and moving actors.

    Deterministic for a seed (one ``numpy.random.default_rng(seed)``); different seeds give different
    towns. Generation takes a fraction of a second; the static mesh holds roughly 40k-80k triangles.

    Args:
        seed: random seed.
        n_frames: frames of the drive (ego poses and actor poses per frame).
        **options: any of
            ``blocks`` (3) city blocks per side; ``block_size`` (90.0) m between road centrelines;
            ``lane_width`` (3.5) m, one lane per direction; ``parking_width`` (2.5) m parking strip by each
            curb; ``sidewalk_width`` (3.5) m; ``curb_height`` (0.14) m, the sidewalk/block top (0.15 m, a usual curb, is a
            voxel face of the default 0.1 m grid (and of 0.2 m), whose z faces lie at -0.05 + 0.1 k: every sidewalk point
            would sit exactly on it and fall in one voxel or the other by float rounding);
            ``margin`` (45.0) m of terrain around the network; ``ego_speed`` (None: uniform in
            [6.5, 8.5] m/s) constant ego speed along the lane centre; ``n_traffic`` (10) vehicles on random
            routes; ``n_oncoming`` (3) vehicles in the opposite lane of the ego route that meet the ego;
            ``n_pedestrians`` (24) walkers on the sidewalks; ``frame_interval`` (0.5) s between frames.

    Returns:
        Scene(name="town"): ``static`` (labelled Mesh; z = 0 is the road surface), ``ego_poses``
        (n_frames, 6) on the right-hand lane centre at z = 0, turning at least once at a junction for the
        default length, ``actors`` (vehicles: "vehicle", plus "lead", "follow", "oncoming" tags; and
        "pedestrian"), none of which overlaps the ego footprint (EGO_LENGTH x EGO_WIDTH) at any frame.
        ``meta`` holds ``roads`` (centrelines, widths), ``bounds``, ``blocks`` (kind and rectangle),
        ``route`` (junction nodes of the ego walk), ``ego_speed``, ``ego_path_s`` (arc length per frame).
    """
    unknown = set(options) - set(TOWN_OPTIONS)
    if unknown:
        raise TypeError(f"town() got unknown options {sorted(unknown)}; valid: {sorted(TOWN_OPTIONS)}")
    opt = {**TOWN_OPTIONS, **options}
    n_frames = int(n_frames)
    if n_frames < 1:
        raise ValueError(f"town needs n_frames >= 1, got {n_frames}")
    nb = int(opt["blocks"])
    if nb < 1:
        raise ValueError(f"town needs blocks >= 1, got {nb}")
    P = float(opt["block_size"])
    lw, pkw, sw, ch = (float(opt[k]) for k in ("lane_width", "parking_width", "sidewalk_width", "curb_height"))
    hw = lw + pkw
    if float(opt["margin"]) < 25.0:
        raise ValueError(f"town needs margin >= 25 m, got {opt['margin']}")
    if P - 2 * hw - 2 * sw < 30.0:
        raise ValueError(f"block_size {P} too small for roads of half-width {hw} and sidewalks of {sw} m")
    margin = float(opt["margin"])
    dt = float(opt["frame_interval"])

    rng = np.random.default_rng(seed)
    T = Props(rng, opt)
    c = (np.arange(nb + 1) - nb / 2) * P  # road centrelines (both axes)
    E_net = c[-1] + hw
    E = E_net + margin

    pond = ground(T, c, hw, E_net, E)
    road_markings(T, c, nb, hw, lw, pkw)
    blocks_meta = blocks(T, c, nb, hw, sw, ch)
    outskirts(T, c, hw, E_net, E, pond)  # border barriers, trees, sheds, utility poles
    static = T.b.build()

    ego = ego_drive(rng, opt, c, nb, P, hw, lw, n_frames, dt)
    actors = place_actors(rng, opt, c, nb, P, hw, sw, ch, ego)
    meta = {
        "roads": {"centres": c.copy(), "half_width": hw, "lane_width": lw, "parking_width": pkw,
                  "sidewalk_width": sw, "curb_height": ch},
        "bounds": static.bounds,
        "blocks": blocks_meta,
        "route": ego["nodes"],
        "ego_speed": ego["speed"],
        "ego_path_s": ego["s"],
        "pond": pond,
    }
    return Scene(static=static, ego_poses=ego["poses"], actors=actors, name="town", seed=seed,
                 frame_interval=dt, meta=meta)
