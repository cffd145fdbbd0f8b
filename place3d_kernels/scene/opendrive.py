"""Scenes from OpenDRIVE 1.4 road networks (``.xodr``, e.g. the CARLA towns).

:func:`from_opendrive` parses the file with ``xml.etree`` (no third-party reader: the maintained PyPI
packages are converters to other map formats, not small readers), samples every road's reference line,
elevation profile, lane offset and lane sections, and meshes the lanes into labelled surfaces:

- driving-like lanes (driving, parking, bidirectional, entry, exit, on/off ramps, stop, bus, taxi, HOV,
  biking, special*, roadWorks) -> road (7), on the road surface;
- sidewalks (and ``curb`` lanes) -> sidewalk (8), raised 0.14 m (not 0.15 m: a voxel face of the default
  grid, see ``town``), closed by curb faces on both edges;
- shoulder, border, median, restricted -> terrain (21), on the road surface; ``rail``/``tram`` -> rail
  track (15); ``none`` lanes are skipped;
- lane boundaries with a painted ``roadMark`` (solid, broken, double marks) -> road line (6) strips
  0.02 m above the road (broken marks: 3 m on, 6 m off along s);
- the ground between the roads: a terrain (21) height field 0.03 m under the nearest lowest road.

Geometry: ``line``, ``arc``, ``spiral`` (clothoid, integrated numerically with Simpson's rule on a fine
step), ``poly3`` (local u/v cubic, arc length mapped to u numerically) and ``paramPoly3`` (``pRange``
``arcLength``: p = s; ``normalized``: arc length mapped to p numerically). The lateral profile
(superelevation, crossfall) and lane ``height`` records are ignored. Roads are sampled every
``step`` metres (default 1.5 m; finer on tight curves), so Town03 (9 km of road) meshes in seconds.

Roadside content is placed procedurally from ``seed`` (buildings, trees and hedges, lamps, signs,
traffic lights, parked cars on parking lanes or beside the road, and beside every outer road edge within
60 m of the ego route) on a 1 m occupancy raster of the road area, so nothing stands on a lane. A lead
vehicle drives ahead of the ego on its route. Traffic drives along lane centre lines (right lanes along +s, left
lanes against s); routes chain lanes whose centre lines meet end to start (within 1 m and 45 degrees),
which follows the junction connecting roads without parsing lane links. The ego vehicle does the same.

``Scene.meta``: ``road_length`` (sum of road lengths, junction connecting roads included),
``road_length_no_junction``, ``road_area`` (area of the driving-like lanes, m^2; lanes of different
connecting roads overlap inside junctions and each counts), ``area_by_type``, ``n_roads``,
``n_junctions``, ``bounds``, ``file``, ``static_boxes`` ((n, 7) world boxes x, y, z, l, w, h, yaw of the
parked cars, z = centre; used by ``place3d_kernels.smig.scene_boxes``).

Modules: ``xodr_geometry`` and ``xodr`` (parsing), ``opendrive_mesh`` (lanes and marks),
``opendrive_roadside`` (raster, furniture, buildings, parked cars), ``opendrive_routes`` and
``opendrive_traffic`` (ego drive, traffic, pedestrians); this module assembles the Scene.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path as _FsPath

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Scene
from place3d_kernels.scene.opendrive_mesh import DRIVING_TYPES, LANE_CLASS, Strips, mesh_road, orient_up
from place3d_kernels.scene.opendrive_roadside import (Raster, RoadDistance, edge_geometry, fill, road_area_points,
                                                      roadside, route_parking)
from place3d_kernels.scene.opendrive_traffic import ego_drive, traffic
from place3d_kernels.scene.props import Props
from place3d_kernels.scene.xodr import OpenDrive, Road, parse_opendrive

__all__ = ["from_opendrive", "parse_opendrive", "OpenDrive", "Road", "OPENDRIVE_OPTIONS", "LANE_CLASS"]

TERRAIN = CLASS_ID["terrain"]

#: bumped whenever the builder changes what it places, so scene keys (and the P-SOG cache) change with it;
#: 2: cars parked along the ego route, a lead vehicle, deterministic road-mark order
BUILDER_VERSION = 2

#: options of :func:`from_opendrive` and their defaults
OPENDRIVE_OPTIONS = {
    "step": 1.5,             # sampling step along s, m (halved and so on near tight curves)
    "curb_height": 0.14,     # sidewalk height above the road, m (0.15 is a face of the default grid)
    "line_width": 0.15,      # default painted line width, m
    "ground": True,          # terrain height field between the roads
    "ground_cell": 8.0,      # m
    "ground_margin": 30.0,   # m around the road network
    "roadside": True,        # buildings, vegetation, street furniture, parked cars
    "route_parking": True,   # cars parked beside the road edges along the ego route (needs roadside)
    "fill": 1.0,             # density of buildings and trees filling the space between roads (0: none)
    "n_traffic": 12,         # moving vehicles
    "n_lead": 1,             # a vehicle ahead of the ego on its route (0: none)
    "n_pedestrians": 10,     # pedestrians on sidewalks
    "ego_speed": None,       # m/s; None: uniform in [6.5, 8.5]
    "frame_interval": 0.5,   # s
}


def from_opendrive(path, seed: int = 0, n_frames: int = 40, **options) -> Scene:
    """Build a Scene from an OpenDRIVE file (see the module docstring).

    Args:
        path: the ``.xodr`` file.
        seed: seeds the roadside content, traffic and the ego route.
        n_frames: frames of the ego drive (``frame_interval`` apart, default 0.5 s).
        **options: see ``OPENDRIVE_OPTIONS``.

    Raises:
        ValueError: unknown options, or a malformed file (the message names the file and the problem).
    """
    unknown = set(options) - set(OPENDRIVE_OPTIONS)
    if unknown:
        raise ValueError(f"unknown from_opendrive options {sorted(unknown)}; known: {sorted(OPENDRIVE_OPTIONS)}")
    opt = {**OPENDRIVE_OPTIONS, **options}
    if float(opt["step"]) <= 0:
        raise ValueError(f"step must be > 0, got {opt['step']}")
    n_frames = int(n_frames)
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    base = _town_base(path, opt)
    od, info, ref, ref_tree, lo, hi = base.od, base.info, base.ref, base.ref_tree, base.lo, base.hi
    rng = np.random.default_rng(seed)

    def heights_at(x, y):
        return _lowest_ref_z(ref, ref_tree, np.stack([np.asarray(x, float), np.asarray(y, float)], 1))

    def height_at(x, y):
        return float(heights_at([x], [y])[0])

    T = Props(rng, {})
    n_parked = 0
    static_boxes: list = []
    if opt["roadside"]:
        raster = Raster(lo - 40.0, hi + 40.0, 1.0)
        raster.occ = base.road_occ.copy()
        edges = [e for e in info["edges"]]
        order = rng.permutation(len(edges))
        geometry = [info["edge_geometry"][i] for i in order]          # made once per town (_town_base)
        n_parked = roadside(T, rng, raster, [edges[i] for i in order], info["lanes"], height_at, opt,
                            static_boxes, geometry)
        if float(opt["fill"]) > 0:
            fill(T, rng, raster, base.road_distance(), heights_at, float(opt["fill"]))
    dt = float(opt["frame_interval"])
    t = np.arange(n_frames) * dt
    ego_route, ego_poses, ego_speed, graph, ego_s0 = ego_drive(rng, info["lanes"], opt, t, od.path)
    if opt["roadside"] and opt["route_parking"]:
        # cars parked beside the roads the ego drives along, so every map shows some (the route is the drive
        # plus at most one more lane)
        n_parked += route_parking(T, rng, raster, [edges[i] for i in order], ego_route.p[:, :2], height_at,
                                  static_boxes, geometry=geometry)
    if T.b._parts or T.b._box_c:
        # the town's roads and ground, then this route's roadside: one mesh (checked once), which remembers
        # the town's part so that a backend extending meshes builds its tree once per town (Mesh.extended)
        static = Mesh.extended(base.mesh(), *T.b.arrays())
    else:
        static = base.mesh()

    actors = traffic(rng, graph, info["lanes"], opt, t, ego_poses[:, :2], ego_route, ego_s0, ego_speed)
    drive_area = float(sum(a for tp, a in info["area"].items() if tp.lower() in DRIVING_TYPES))
    meta = {
        "builder": f"opendrive-{BUILDER_VERSION}",
        "file": str(od.path),
        "road_length": od.road_length,
        "road_length_no_junction": float(sum(r.length for r in od.roads if r.junction == "-1")),
        "road_area": drive_area,
        "area_by_type": dict(info["area"]),
        "n_roads": len(od.roads),
        "n_junctions": od.n_junctions,
        "bounds": static.bounds,
        "ego_speed": ego_speed,
        "n_parked": n_parked,
        "static_boxes": np.asarray(static_boxes, np.float64).reshape(-1, 7),  # parked cars, world frame
        "ego_route_length": ego_route.length,
    }
    return Scene(static=static, ego_poses=ego_poses, actors=actors, name=f"opendrive-{_FsPath(path).stem}",
                 seed=seed, frame_interval=dt, meta=meta)


#: options that decide a town's roads, lane marks, ground and road raster (``_town_base``); the others
#: (roadside content, traffic, the drive) are drawn per seed
_BASE_OPTIONS = ("step", "curb_height", "line_width", "ground", "ground_cell", "ground_margin")


@dataclass(frozen=True)
class _TownBase:
    """What a town's scene is made of before its seed is drawn, the same for every route: the parsed file,
    the meshed lanes, marks and ground (``parts``), the lanes and edges the roadside and traffic use
    (``info``), the reference line samples and their tree (heights), the road area on the 1 m raster, and
    what is made from it on first use (``road_distance``). Its arrays are read-only: every route's scene reads
    them and none may change them."""

    od: OpenDrive
    parts: tuple
    info: dict
    ref: np.ndarray
    ref_tree: object
    lo: np.ndarray
    hi: np.ndarray
    road_occ: np.ndarray
    _made: dict = field(default_factory=dict, compare=False, repr=False)

    def mesh(self) -> Mesh:
        """The town's parts as one Mesh (made on first use): every route's static mesh begins with it."""
        if "mesh" not in self._made:
            parts = self.parts
            offs = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
            self._made["mesh"] = Mesh(np.concatenate([p[0] for p in parts]),
                                      np.concatenate([p[1] + o for p, o in zip(parts, offs)]),
                                      np.concatenate([p[2] for p in parts]))
        return self._made["mesh"]

    def road_distance(self) -> RoadDistance:
        """The road raster's ``RoadDistance`` (the fill's), made on the first route that fills."""
        if "road_distance" not in self._made:
            self._made["road_distance"] = RoadDistance(self.road_occ)
        return self._made["road_distance"]


#: a few towns' bases, most recent last (the study's four towns fit)
_BASES: "OrderedDict[tuple, _TownBase]" = OrderedDict()
_BASES_KEPT = 4


def _town_base(path, opt) -> _TownBase:
    """The town's ``_TownBase`` for these options, built once per process and file content: the routes of a
    pooled study share one town's roads instead of parsing and meshing the file again for each (the seed is
    drawn after all of this, so every route's scene is what a fresh build makes)."""
    import hashlib

    try:
        # by content: a file rewritten in place is a new town, the same map under two paths one
        key = (hashlib.sha256(_FsPath(path).read_bytes()).hexdigest(),) + tuple(repr(opt[k]) for k in _BASE_OPTIONS)
    except OSError:         # a map found by name (parse_opendrive resolves it) or unreadable: not kept
        key = None
    if key is not None and key in _BASES:
        _BASES.move_to_end(key)
        return _BASES[key]
    od = parse_opendrive(path)
    surf, lines = Strips(), Strips()
    info = {"area": {}, "lanes": [], "edges": [], "ref": []}
    for road in od.roads:
        mesh_road(road, opt, surf, lines, info)
    sp = surf.parts()
    if sp is None:
        raise ValueError(f"{od.path}: no lane surfaces to mesh (all lanes have zero width or type 'none')")
    v, f, lab = sp
    f = orient_up(v, f)
    parts = [(v, f, lab)]
    lp = lines.parts()
    if lp is not None:
        parts.append((lp[0], orient_up(lp[0], lp[1]), lp[2]))

    ref = np.concatenate(info["ref"])
    info["edge_geometry"] = [edge_geometry(e) for e in info["edges"]]    # what the routes' roadside passes share
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    from scipy.spatial import cKDTree

    ref_tree = cKDTree(ref[:, :2])
    if opt["ground"]:
        parts.append(_ground(ref, ref_tree, lo, hi, float(opt["ground_margin"]), float(opt["ground_cell"])))
    raster = Raster(lo - 40.0, hi + 40.0, 1.0)
    raster.mark_points(road_area_points((v, f, lab)))
    base = _TownBase(od, tuple(parts), info, ref, ref_tree, lo, hi, raster.occ)
    for a in _arrays(base.parts, info, ref, lo, hi, raster.occ):
        a.setflags(write=False)
    if key is not None:
        _BASES[key] = base
        while len(_BASES) > _BASES_KEPT:
            _BASES.popitem(last=False)
    return base


def _arrays(*objs):
    for o in objs:
        if isinstance(o, np.ndarray):
            yield o
        elif isinstance(o, (list, tuple)):
            yield from _arrays(*o)
        elif isinstance(o, dict):
            yield from _arrays(*o.values())


def _lowest_ref_z(ref, ref_tree, xy: np.ndarray) -> np.ndarray:
    """The lowest height of the 8 reference-line samples nearest each of the (N, 2) points ``xy``: the ground
    height of the town's terrain, roadside and fill. One KD-tree query for all (it answers each point alone,
    so a point's height does not depend on the others asked with it)."""
    if len(xy) == 0:
        return np.zeros(0)
    _, idx = ref_tree.query(xy, k=min(8, len(ref)))
    return ref[idx.reshape(len(xy), -1), 2].min(axis=1)


def _ground(ref, ref_tree, lo, hi, margin, cell):
    """A terrain height field over the map plus ``margin``, 0.03 m under the lowest of the 8 nearest
    reference-line samples (so it never covers a road)."""
    xs = np.arange(lo[0] - margin, hi[0] + margin + cell, cell)
    ys = np.arange(lo[1] - margin, hi[1] + margin + cell, cell)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    q = np.stack([X.ravel(), Y.ravel()], 1)
    zg = _lowest_ref_z(ref, ref_tree, q) - 0.03
    gv = np.stack([q[:, 0], q[:, 1], zg], 1)
    I, J = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    I, J = I.ravel(), J.ravel()
    a = I * len(ys) + J
    b = (I + 1) * len(ys) + J
    c = (I + 1) * len(ys) + J + 1
    d = I * len(ys) + J + 1
    gf = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return gv, gf, np.full(len(gf), TERRAIN, np.int32)
