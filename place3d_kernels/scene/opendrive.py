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
traffic lights, parked cars on parking lanes or beside the road) on a 1 m occupancy raster of the road
area, so nothing stands on a lane. Traffic drives along lane centre lines (right lanes along +s, left
lanes against s); routes chain lanes whose centre lines meet end to start (within 1 m and 45 degrees),
which follows the junction connecting roads without parsing lane links. The ego vehicle does the same.

``Scene.meta``: ``road_length`` (sum of road lengths, junction connecting roads included),
``road_length_no_junction``, ``road_area`` (area of the driving-like lanes, m^2; lanes of different
connecting roads overlap inside junctions and each counts), ``area_by_type``, ``n_roads``,
``n_junctions``, ``bounds``, ``file``, ``static_boxes`` ((n, 7) world boxes x, y, z, l, w, h, yaw of the
parked cars, z = centre; used by ``place3d_kernels.smig.scene_boxes``).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path as _FsPath

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Actor, Scene
from place3d_kernels.scene.primitives import transform
from place3d_kernels.scene.bodies import EGO_LENGTH, pedestrian_mesh, vehicle_mesh
from place3d_kernels.scene.props import Props

__all__ = ["from_opendrive", "parse_opendrive", "OpenDrive", "Road", "OPENDRIVE_OPTIONS", "LANE_CLASS"]

C = CLASS_ID
ROAD, ROAD_LINE, SIDEWALK, TERRAIN, RAIL = C["road"], C["road line"], C["sidewalk"], C["terrain"], C["rail track"]

DRIVING_TYPES = frozenset({
    "driving", "parking", "bidirectional", "entry", "exit", "onramp", "offramp", "connectingramp", "stop",
    "bus", "taxi", "hov", "biking", "special1", "special2", "special3", "roadworks"})
#: lane type (lower case) -> Place3D class; ``None``: not meshed
LANE_CLASS = {**{t: ROAD for t in DRIVING_TYPES},
              "sidewalk": SIDEWALK, "curb": SIDEWALK,
              "shoulder": TERRAIN, "border": TERRAIN, "median": TERRAIN, "restricted": TERRAIN,
              "rail": RAIL, "tram": RAIL, "none": None}
_RAISED = frozenset({"sidewalk", "curb"})
_PAINTED = ("solid", "broken", "solid solid", "solid broken", "broken solid", "broken broken", "botts dots")

#: options of :func:`from_opendrive` and their defaults
OPENDRIVE_OPTIONS = {
    "step": 1.5,             # sampling step along s, m (halved and so on near tight curves)
    "curb_height": 0.14,     # sidewalk height above the road, m (0.15 is a face of the default grid)
    "line_width": 0.15,      # default painted line width, m
    "ground": True,          # terrain height field between the roads
    "ground_cell": 8.0,      # m
    "ground_margin": 30.0,   # m around the road network
    "roadside": True,        # buildings, vegetation, street furniture, parked cars
    "fill": 1.0,             # density of buildings and trees filling the space between roads (0: none)
    "n_traffic": 12,         # moving vehicles
    "n_pedestrians": 10,     # pedestrians on sidewalks
    "ego_speed": None,       # m/s; None: uniform in [6.5, 8.5]
    "frame_interval": 0.5,   # s
}


# ------------------------------------------------------------------------------------------- parsing
def _f(el, name, path, default=None):
    v = el.get(name)
    if v is None:
        if default is not None:
            return float(default)
        raise ValueError(f"{path}: <{el.tag}> is missing attribute {name!r}")
    try:
        x = float(v)
    except ValueError:
        raise ValueError(f"{path}: <{el.tag}> attribute {name}={v!r} is not a number") from None
    if not math.isfinite(x):
        raise ValueError(f"{path}: <{el.tag}> attribute {name}={v!r} is not finite")
    return x


class _Cubic:
    """Piecewise cubic a + b ds + c ds^2 + d ds^3 over records starting at s (``elevation``, ``laneOffset``)."""

    def __init__(self, records):
        recs = sorted(records, key=lambda r: r[0])
        self.s = np.array([r[0] for r in recs], float) if recs else np.zeros(1)
        self.k = np.array([r[1:] for r in recs], float) if recs else np.zeros((1, 4))

    @classmethod
    def parse(cls, els, path, s_key="s"):
        return cls([(_f(e, s_key, path), _f(e, "a", path, 0), _f(e, "b", path, 0), _f(e, "c", path, 0),
                     _f(e, "d", path, 0)) for e in els])

    def __call__(self, s):
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        ds = s - self.s[i]
        a, b, c, d = self.k[i].T
        return a + ds * (b + ds * (c + ds * d))

    def slope(self, s):
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        ds = s - self.s[i]
        _, b, c, d = self.k[i].T
        return b + ds * (2 * c + 3 * ds * d)


class _Geometry:
    """One planView record: evaluates (x, y, heading) at offsets ds in [0, length]."""

    def __init__(self, s, x, y, hdg, length, kind, p):
        self.s, self.x, self.y, self.hdg, self.length, self.kind, self.p = s, x, y, hdg, length, kind, p
        self._table = None
        if kind in ("spiral", "poly3", "paramPoly3"):
            self._build_table()

    def max_curvature(self) -> float:
        if self.kind == "arc":
            return abs(self.p["curvature"])
        if self.kind == "spiral":
            return max(abs(self.p["curvStart"]), abs(self.p["curvEnd"]))
        if self._table is not None:
            h = np.unwrap(self._table[3])
            s = self._table[0]
            if len(s) > 2:
                return float(np.max(np.abs(np.diff(h) / np.maximum(np.diff(s), 1e-9))))
        return 0.0

    def _build_table(self):
        """Dense (s, x, y, hdg) table for curves without a closed form."""
        L = self.length
        n = int(max(64, math.ceil(L / 0.05)))
        n += n % 2  # even for Simpson
        if self.kind == "spiral":
            k0, k1 = self.p["curvStart"], self.p["curvEnd"]
            cd = (k1 - k0) / L if L > 0 else 0.0
            s = np.linspace(0.0, L, n + 1)
            th = self.hdg + k0 * s + 0.5 * cd * s * s
            # cumulative Simpson over pairs of intervals, trapezoid midpoint for the odd nodes
            hm = 0.5 * (s[1:] + s[:-1])
            thm = self.hdg + k0 * hm + 0.5 * cd * hm * hm
            ds = np.diff(s)
            dx = ds / 6 * (np.cos(th[:-1]) + 4 * np.cos(thm) + np.cos(th[1:]))
            dy = ds / 6 * (np.sin(th[:-1]) + 4 * np.sin(thm) + np.sin(th[1:]))
            x = self.x + np.r_[0.0, np.cumsum(dx)]
            y = self.y + np.r_[0.0, np.cumsum(dy)]
            self._table = np.stack([s, x, y, th])
            return
        if self.kind == "poly3":
            a, b, c, d = (self.p[k] for k in "abcd")
            # arc length along u >= u, so u(L) <= L; sample u on [0, L] (extended if the curve is short)
            umax = L
            coef_u = (0.0, 1.0, 0.0, 0.0)
            coef_v = (a, b, c, d)
            param = "u"
        else:
            coef_u = tuple(self.p[k] for k in ("aU", "bU", "cU", "dU"))
            coef_v = tuple(self.p[k] for k in ("aV", "bV", "cV", "dV"))
            normalized = self.p.get("pRange", "arcLength").lower() == "normalized"
            umax = 1.0 if normalized else L
            param = "p"
        for _ in range(8):
            u = np.linspace(0.0, umax, n + 1)
            pu = coef_u[0] + u * (coef_u[1] + u * (coef_u[2] + u * coef_u[3]))
            pv = coef_v[0] + u * (coef_v[1] + u * (coef_v[2] + u * coef_v[3]))
            du = coef_u[1] + u * (2 * coef_u[2] + 3 * u * coef_u[3])
            dv = coef_v[1] + u * (2 * coef_v[2] + 3 * u * coef_v[3])
            sp = np.hypot(du, dv)
            arc = np.r_[0.0, np.cumsum(0.5 * (sp[1:] + sp[:-1]) * np.diff(u))]
            if param == "p" or arc[-1] >= L - 1e-9 or umax > 1e6:
                break
            umax *= 1.5
        if param == "p" and self.p.get("pRange", "arcLength").lower() != "normalized":
            s = u  # arcLength: p is the arc length by definition
        elif param == "p":
            s = arc * (L / arc[-1]) if arc[-1] > 0 else u * L
        else:
            s = arc
        ch, sh = math.cos(self.hdg), math.sin(self.hdg)
        # local (u, v) rotated by hdg and shifted to (x, y); a non-zero a / aU / aV offsets the start as in the spec
        x = self.x + ch * pu - sh * pv
        y = self.y + sh * pu + ch * pv
        th = self.hdg + np.arctan2(dv, du)
        self._table = np.stack([s, x, y, np.unwrap(th)])

    def eval(self, ds):
        ds = np.asarray(ds, float)
        if self.kind == "line" or (self.kind == "arc" and abs(self.p["curvature"]) < 1e-12):
            c, s = math.cos(self.hdg), math.sin(self.hdg)
            return self.x + ds * c, self.y + ds * s, np.full_like(ds, self.hdg)
        if self.kind == "arc":
            k = self.p["curvature"]
            th = self.hdg + k * ds
            return (self.x + (np.sin(th) - math.sin(self.hdg)) / k,
                    self.y - (np.cos(th) - math.cos(self.hdg)) / k, th)
        t = self._table
        return np.interp(ds, t[0], t[1]), np.interp(ds, t[0], t[2]), np.interp(ds, t[0], t[3])


class _Lane:
    def __init__(self, lid, ltype, widths, borders, marks):
        self.id, self.type = lid, ltype
        self.width = _Cubic(widths) if widths else None
        self.border = _Cubic(borders) if borders else None
        self.marks = sorted(marks)  # (sOffset, type, width)

    def mark_at(self, ds):
        m = None
        for rec in self.marks:
            if rec[0] <= ds + 1e-9:
                m = rec
        return m


class _Section:
    def __init__(self, s, left, right, center):
        self.s = s
        self.left = sorted(left, key=lambda l: l.id)            # 1, 2, 3, ...
        self.right = sorted(right, key=lambda l: -l.id)         # -1, -2, -3, ...
        self.center = center
        self.s_end = None


class Road:
    """A parsed road: reference line, elevation, lane offset and lane sections."""

    def __init__(self, rid, name, length, junction, geoms, elevation, offset, sections):
        self.id, self.name, self.length, self.junction = rid, name, length, junction
        self.geoms, self.elevation, self.offset, self.sections = geoms, elevation, offset, sections
        self._gs = np.array([g.s for g in geoms])

    def reference(self, s):
        """x, y, heading of the reference line at s (array)."""
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self._gs, s, side="right") - 1, 0, len(self.geoms) - 1)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for k in np.unique(i):
            m = i == k
            g = self.geoms[k]
            x[m], y[m], h[m] = g.eval(np.clip(s[m] - g.s, 0.0, max(g.length, 0.0)))
        return x, y, h

    def samples(self, step: float) -> np.ndarray:
        """Sample positions along s: a uniform grid of ``step`` (finer on tight curves) plus every
        geometry and lane-section start and the road end."""
        pts = [np.arange(0.0, self.length, step), [self.length]]
        for g in self.geoms:
            pts.append([g.s])
            kmax = g.max_curvature()
            if kmax > 1e-9 and 0.15 / kmax < step:  # about 0.15 rad per step
                fine = max(0.15 / kmax, 0.1)
                pts.append(g.s + np.arange(0.0, g.length, fine))
        for sec in self.sections:
            pts.append([sec.s])
        s = np.unique(np.clip(np.concatenate([np.asarray(p, float) for p in pts]), 0.0, self.length))
        keep = np.r_[True, np.diff(s) > 1e-6]
        return s[keep]


class OpenDrive:
    """A parsed OpenDRIVE file: roads and the number of junctions."""

    def __init__(self, path, roads, n_junctions, header):
        self.path, self.roads, self.n_junctions, self.header = path, roads, n_junctions, header

    @property
    def road_length(self) -> float:
        return float(sum(r.length for r in self.roads))


def _lane(el, path, rid) -> _Lane:
    try:
        lid = int(el.get("id"))
    except (TypeError, ValueError):
        raise ValueError(f"{path}: road {rid}: <lane> has no integer id (got {el.get('id')!r})") from None
    ltype = (el.get("type") or "none").strip()
    widths = [(_f(w, "sOffset", path), _f(w, "a", path, 0), _f(w, "b", path, 0), _f(w, "c", path, 0),
               _f(w, "d", path, 0)) for w in el.findall("width")]
    borders = [(_f(w, "sOffset", path), _f(w, "a", path, 0), _f(w, "b", path, 0), _f(w, "c", path, 0),
                _f(w, "d", path, 0)) for w in el.findall("border")]
    if lid != 0 and not widths and not borders:
        raise ValueError(f"{path}: road {rid}: lane {lid} has neither <width> nor <border>")
    marks = [(_f(m, "sOffset", path, 0), (m.get("type") or "none").strip().lower(),
              _f(m, "width", path, 0.0)) for m in el.findall("roadMark")]
    return _Lane(lid, ltype, widths, borders, marks)


def parse_opendrive(path) -> OpenDrive:
    """Parse an OpenDRIVE (1.4-style) file. Raises ValueError naming the file and the problem."""
    path = _FsPath(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such OpenDRIVE file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ValueError(f"{path}: not well-formed XML ({e})") from None
    if root.tag != "OpenDRIVE":
        raise ValueError(f"{path}: root element is <{root.tag}>, expected <OpenDRIVE>")
    road_els = root.findall("road")
    if not road_els:
        raise ValueError(f"{path}: no <road> elements")
    roads = []
    for r in road_els:
        rid = r.get("id", "?")
        length = _f(r, "length", path)
        if length <= 0:
            raise ValueError(f"{path}: road {rid} has non-positive length {length}")
        pv = r.find("planView")
        if pv is None:
            raise ValueError(f"{path}: road {rid} has no <planView>")
        geoms = []
        for g in pv.findall("geometry"):
            kids = [k for k in g if k.tag in ("line", "arc", "spiral", "poly3", "paramPoly3")]
            if not kids:
                raise ValueError(f"{path}: road {rid}: <geometry s={g.get('s')}> has no line/arc/spiral/poly3/"
                                 f"paramPoly3 child")
            k = kids[0]
            if k.tag == "line":
                p = {}
            elif k.tag == "arc":
                p = {"curvature": _f(k, "curvature", path)}
            elif k.tag == "spiral":
                p = {"curvStart": _f(k, "curvStart", path), "curvEnd": _f(k, "curvEnd", path)}
            elif k.tag == "poly3":
                p = {c: _f(k, c, path) for c in "abcd"}
            else:
                p = {c: _f(k, c, path) for c in ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")}
                p["pRange"] = k.get("pRange", "arcLength")
            glen = _f(g, "length", path)
            if glen < 0:
                raise ValueError(f"{path}: road {rid}: geometry with negative length {glen}")
            geoms.append(_Geometry(_f(g, "s", path), _f(g, "x", path), _f(g, "y", path), _f(g, "hdg", path),
                                   glen, k.tag, p))
        if not geoms:
            raise ValueError(f"{path}: road {rid}: <planView> has no <geometry>")
        geoms.sort(key=lambda g: g.s)
        ep = r.find("elevationProfile")
        elevation = _Cubic.parse(ep.findall("elevation") if ep is not None else [], path)
        lanes_el = r.find("lanes")
        if lanes_el is None:
            raise ValueError(f"{path}: road {rid} has no <lanes>")
        offset = _Cubic.parse(lanes_el.findall("laneOffset"), path)
        sections = []
        for sec in lanes_el.findall("laneSection"):
            s0 = _f(sec, "s", path)
            left = [_lane(l, path, rid) for side in sec.findall("left") for l in side.findall("lane")]
            right = [_lane(l, path, rid) for side in sec.findall("right") for l in side.findall("lane")]
            cen = [_lane(l, path, rid) for side in sec.findall("center") for l in side.findall("lane")]
            sections.append(_Section(s0, left, right, cen[0] if cen else None))
        if not sections:
            raise ValueError(f"{path}: road {rid}: <lanes> has no <laneSection>")
        sections.sort(key=lambda x: x.s)
        for a, b in zip(sections[:-1], sections[1:]):
            a.s_end = b.s
        sections[-1].s_end = length
        roads.append(Road(rid, r.get("name", ""), length, r.get("junction", "-1"), geoms, elevation, offset,
                          sections))
    return OpenDrive(path, roads, len(root.findall("junction")), root.find("header"))


# ------------------------------------------------------------------------------------------ meshing
class _Strips:
    """Accumulates quad strips between two boundary polylines."""

    def __init__(self):
        self.v: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.l: list[np.ndarray] = []
        self.n = 0

    def strip(self, inner, outer, label, keep=None):
        """inner/outer (n, 3) polylines; quads between consecutive samples (``keep``: (n-1,) bool)."""
        n = len(inner)
        if n < 2:
            return
        v = np.concatenate([inner, outer])
        i = np.arange(n - 1)
        if keep is not None:
            i = i[keep]
        if len(i) == 0:
            return
        a, b, c, d = i, i + 1, n + i + 1, n + i
        f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) + self.n
        self.v.append(v)
        self.f.append(f)
        self.l.append(np.full(len(f), label, np.int32))
        self.n += len(v)

    def add(self, v, f, lab):
        self.v.append(np.asarray(v, float))
        self.f.append(np.asarray(f) + self.n)
        self.l.append(np.broadcast_to(np.asarray(lab, np.int32), (len(f),)))
        self.n += len(v)

    def parts(self):
        if not self.v:
            return None
        return np.concatenate(self.v), np.concatenate(self.f), np.concatenate(self.l)


def _orient_up(v, f):
    """Flip faces whose normal points down (strips may be wound either way by side)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    down = n[:, 2] < 0
    f = f.copy()
    f[down] = f[down][:, ::-1]
    return f


def _quad_area(inner, outer):
    """Area of the quad strip between two polylines (xy), per segment."""
    a, b, c, d = inner[:-1, :2], inner[1:, :2], outer[1:, :2], outer[:-1, :2]

    def tri(p, q, r):
        return 0.5 * np.abs((q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0]))

    return tri(a, b, c) + tri(a, c, d)


def _mesh_road(road: Road, opt, out: _Strips, lines: _Strips, info):
    step = float(opt["step"])
    ch = float(opt["curb_height"])
    s_all = road.samples(step)
    x, y, h = road.reference(s_all)
    z = road.elevation(s_all)
    off = road.offset(s_all)
    nx, ny = -np.sin(h), np.cos(h)
    info["ref"].append(np.stack([x, y, z], 1))
    for sec in road.sections:
        m = (s_all >= sec.s - 1e-9) & (s_all <= sec.s_end + 1e-9)
        if m.sum() < 2:
            continue
        s = s_all[m]
        ds = s - sec.s
        px, py, pz, pnx, pny, po = x[m], y[m], z[m], nx[m], ny[m], off[m]

        def at(t, dz=0.0):
            return np.stack([px + t * pnx, py + t * pny, pz + dz], 1)

        for side, lanes, sgn in (("left", sec.left, 1.0), ("right", sec.right, -1.0)):
            t_in = po.copy()
            # the centre lane's mark lies on the reference line (+ offset)
            if side == "left" and sec.center is not None:
                _marks(sec.center, s, ds, t_in, at, lines, opt)
            for lane in lanes:
                if lane.width is not None:
                    w = np.maximum(lane.width(ds), 0.0)
                    t_out = t_in + sgn * w
                else:  # <border>: outer border position relative to the reference line (+ offset)
                    t_out = po + sgn * np.abs(lane.border(ds))
                ltype = lane.type.lower()
                label = LANE_CLASS.get(ltype, TERRAIN)
                if label is not None and np.any(np.abs(t_out - t_in) > 1e-6):
                    dz = ch if ltype in _RAISED else 0.0
                    inner, outer = at(t_in, dz), at(t_out, dz)
                    out.strip(inner, outer, label)
                    area = float(_quad_area(inner, outer).sum())
                    info["area"][ltype] = info["area"].get(ltype, 0.0) + area
                    if dz > 0:  # curb faces on both edges
                        out.strip(at(t_in, 0.0), inner, SIDEWALK)
                        out.strip(at(t_out, 0.0), outer, SIDEWALK)
                    centre = at(0.5 * (t_in + t_out), dz)
                    width = np.abs(t_out - t_in)
                    fwd = sgn < 0  # right-hand traffic: right lanes run along +s
                    if ltype in DRIVING_TYPES or ltype in _RAISED:
                        pts = centre if fwd else centre[::-1]
                        info["lanes"].append((ltype, road.junction != "-1", pts, (width if fwd else width[::-1]),
                                              road.id))
                    info["edges"].append(at(t_out, dz))
                _marks(lane, s, ds, t_out, at, lines, opt, inner_types=(ltype,))
                t_in = t_out


def _marks(lane: _Lane, s, ds, t, at, lines: _Strips, opt, inner_types=()):
    """Painted road marks on the outer border ``t`` of ``lane`` (the reference line for the centre lane);
    outer borders of non-driving lanes (sidewalk edges, shoulders) get none."""
    if not lane.marks:
        return
    if not any(tp.lower() in DRIVING_TYPES for tp in inner_types) and lane.id != 0:
        return
    mid = 0.5 * (s[1:] + s[:-1])
    mid_ds = 0.5 * (ds[1:] + ds[:-1])
    kinds = [lane.mark_at(v) for v in mid_ds]
    for mtype in set(k[1] for k in kinds if k is not None):
        if mtype not in _PAINTED:
            continue
        sel = np.array([k is not None and k[1] == mtype for k in kinds])
        width = next(k[2] for k in kinds if k is not None and k[1] == mtype) or float(opt["line_width"])
        parts = mtype.split()
        offsets = [0.0] if len(parts) == 1 else [-(width / 2 + 0.06), width / 2 + 0.06]
        for part, o in zip(parts if len(parts) > 1 else [mtype], offsets):
            keep = sel.copy()
            if part in ("broken", "botts"):
                keep &= np.mod(mid, 9.0) < 3.0
            if not keep.any():
                continue
            lines.strip(at(t + o - width / 2, 0.02), at(t + o + width / 2, 0.02), ROAD_LINE, keep)


# --------------------------------------------------------------------------------------------- routes
class _Route:
    """A 3-D polyline with poses by arc length (clamped at both ends)."""

    def __init__(self, pts):
        p = np.asarray(pts, float)
        keep = np.r_[True, np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1) > 1e-6]
        p = p[keep]
        self.p = p
        d = np.diff(p, axis=0)
        seg = np.linalg.norm(d[:, :2], axis=1)
        self.s = np.r_[0.0, np.cumsum(seg)]
        head = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        self.yaw = np.r_[head[0], (head[:-1] + head[1:]) / 2, head[-1]] if len(head) else np.zeros(1)
        slope = d[:, 2] / np.maximum(seg, 1e-9)
        self.pitch = -np.arctan(np.r_[slope[0], (slope[:-1] + slope[1:]) / 2, slope[-1]]) if len(slope) else np.zeros(1)

    @property
    def length(self):
        return float(self.s[-1])

    def poses(self, s):
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        out = np.zeros((len(s), 6))
        for k in range(3):
            out[:, k] = np.interp(s, self.s, self.p[:, k])
        out[:, 4] = np.interp(s, self.s, self.pitch)
        out[:, 5] = np.interp(s, self.s, self.yaw)
        return out


class _LaneGraph:
    """Directed lane centre lines chained where one ends at another's start."""

    def __init__(self, lanes):
        from scipy.spatial import cKDTree

        self.lanes = [l for l in lanes if len(l[2]) >= 2]
        self.starts = np.array([l[2][0, :2] for l in self.lanes]) if self.lanes else np.zeros((0, 2))
        self.h0 = np.array([_heading(l[2], 0) for l in self.lanes])
        self.tree = cKDTree(self.starts) if self.lanes else None

    def next(self, i, rng):
        end = self.lanes[i][2][-1, :2]
        h1 = _heading(self.lanes[i][2], -1)
        cand = self.tree.query_ball_point(end, 1.0)
        cand = [j for j in cand if j != i and abs(_wrap(self.h0[j] - h1)) < math.pi / 4]
        if not cand:
            return None
        return cand[int(rng.integers(0, len(cand)))]

    def route(self, i, length, rng):
        pts = [self.lanes[i][2]]
        total = _polylen(pts[0])
        cur = i
        while total < length:
            nxt = self.next(cur, rng)
            if nxt is None:
                break
            pts.append(self.lanes[nxt][2][1:])
            total += _polylen(self.lanes[nxt][2])
            cur = nxt
        return _Route(np.concatenate(pts))


def _heading(p, i):
    d = p[1] - p[0] if i == 0 else p[-1] - p[-2]
    return math.atan2(d[1], d[0])


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def _polylen(p):
    return float(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum())


# ------------------------------------------------------------------------------------------ roadside
class _Raster:
    """A 1 m occupancy raster over the map (road area plus placed objects)."""

    def __init__(self, lo, hi, cell=1.0):
        self.lo = np.asarray(lo, float)
        self.cell = cell
        self.shape = tuple(int(math.ceil((h - l) / cell)) + 1 for l, h in zip(lo, hi))
        self.occ = np.zeros(self.shape, bool)

    def idx(self, xy):
        ij = np.floor((np.asarray(xy, float) - self.lo) / self.cell).astype(np.int64)
        return ij

    def mark_points(self, xy):
        ij = self.idx(xy)
        ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] < self.shape[1])
        self.occ[ij[ok, 0], ij[ok, 1]] = True

    def _rect_points(self, x, y, w, d, yaw, pad):
        u = np.arange(-w / 2 - pad, w / 2 + pad + 1e-9, self.cell * 0.5)
        v = np.arange(-d / 2 - pad, d / 2 + pad + 1e-9, self.cell * 0.5)
        U, V = np.meshgrid(np.r_[u, w / 2 + pad], np.r_[v, d / 2 + pad], indexing="ij")
        c, s = math.cos(yaw), math.sin(yaw)
        return np.stack([x + c * U.ravel() - s * V.ravel(), y + s * U.ravel() + c * V.ravel()], 1)

    def free(self, x, y, w, d, yaw, pad=0.5):
        # cheap rejection on the centre and the corners first
        c, s = math.cos(yaw), math.sin(yaw)
        a, b = w / 2 + pad, d / 2 + pad
        quick = np.array([[x, y], [x + c * a - s * b, y + s * a + c * b], [x - c * a - s * b, y - s * a + c * b],
                          [x + c * a + s * b, y + s * a - c * b], [x - c * a + s * b, y - s * a - c * b]])
        ij = self.idx(quick)
        if np.any(ij < 0) or np.any(ij[:, 0] >= self.shape[0]) or np.any(ij[:, 1] >= self.shape[1]):
            return False
        if self.occ[ij[:, 0], ij[:, 1]].any():
            return False
        ij = self.idx(self._rect_points(x, y, w, d, yaw, pad))
        if np.any(ij < 0) or np.any(ij[:, 0] >= self.shape[0]) or np.any(ij[:, 1] >= self.shape[1]):
            return False
        return not self.occ[ij[:, 0], ij[:, 1]].any()

    def take(self, x, y, w, d, yaw, pad=0.5):
        if not self.free(x, y, w, d, yaw, pad):
            return False
        self.mark_points(self._rect_points(x, y, w, d, yaw, pad))
        return True


def _road_area_points(static_parts, spacing=0.5):
    """Points covering every meshed lane triangle (vertices + barycentric samples), for the raster."""
    v, f, lab = static_parts
    tri = v[f]
    pts = [v[:, :2]]
    for a, b in ((1 / 3, 1 / 3), (0.5, 0.25), (0.25, 0.5), (0.25, 0.25), (0.5, 0.5), (0.0, 0.5), (0.5, 0.0)):
        pts.append((tri[:, 0] * (1 - a - b) + tri[:, 1] * a + tri[:, 2] * b)[:, :2])
    return np.concatenate(pts)


def _box_of(m: Mesh, x, y, z, yaw):
    """World (x, y, z, l, w, h, yaw) box of mesh ``m`` posed at (x, y, z, yaw); z = box centre."""
    lo, hi = m.bounds
    c = (lo + hi) / 2
    cs, sn = math.cos(yaw), math.sin(yaw)
    return [x + cs * c[0] - sn * c[1], y + sn * c[0] + cs * c[1], z + c[2], *(hi - lo).tolist(), yaw]


def _roadside(T: Props, rng, raster: _Raster, edges, lanes, height_at, opt, boxes):
    """Street furniture, buildings, trees and parked cars next to the outer lane edges."""
    parked = 0
    # parked cars on parking lanes
    for ltype, junc, pts, width, rid in lanes:
        if ltype != "parking" or junc:
            continue
        r = _Route(pts)
        u = rng.uniform(1.0, 5.0)
        while u < r.length - 5.0:
            if rng.random() < 0.6:
                m, _ = vehicle_mesh(rng, "car" if rng.random() < 0.85 else "van")
                L = float(m.bounds[1, 0] - m.bounds[0, 0])
                p = r.poses([u + L / 2])[0]
                T.b.add(transform(m.vertices, p[0], p[1], p[2], yaw=p[5]), m.faces, m.labels)
                boxes.append(_box_of(m, p[0], p[1], p[2], p[5]))
                parked += 1
                u += L + rng.uniform(0.8, 2.5)
            else:
                u += rng.uniform(4.0, 9.0)
    for e in edges:
        if len(e) < 2:
            continue
        d = np.diff(e[:, :2], axis=0)
        seg = np.linalg.norm(d, axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        if s[-1] < 6.0:
            continue
        # the outward side: edges are polylines of the outer lane border; the outward normal points
        # away from the road, found from the raster (the side that is free)
        def pose(u):
            x = np.interp(u, s, e[:, 0])
            y = np.interp(u, s, e[:, 1])
            k = min(int(np.searchsorted(s, u, side="right")) - 1, len(d) - 1)
            k = max(k, 0)
            t = d[k] / max(seg[k], 1e-9)
            return x, y, t

        x, y, t = pose(s[-1] / 2)
        nrm = np.array([-t[1], t[0]])
        probe = np.array([[x + nrm[0] * 2.0, y + nrm[1] * 2.0], [x - nrm[0] * 2.0, y - nrm[1] * 2.0]])
        ij = raster.idx(probe)
        ij = np.clip(ij, 0, np.array(raster.shape) - 1)
        occ = raster.occ[ij[:, 0], ij[:, 1]]
        if occ[0] and occ[1]:
            continue  # an inner edge (lanes on both sides)
        if occ[0]:
            nrm = -nrm
        u = rng.uniform(2.0, 10.0)
        while u < s[-1] - 2.0:
            x, y, t = pose(u)
            yaw = math.atan2(t[1], t[0])
            n = np.array([-t[1], t[0]]) if np.dot([-t[1], t[0]], nrm) > 0 else np.array([t[1], -t[0]])
            out_yaw = math.atan2(-n[1], -n[0])  # facing the road
            r = rng.random()
            z0 = height_at(x, y)
            if r < 0.18:  # lamp just off the edge
                px, py = x + n[0] * 0.6, y + n[1] * 0.6
                if raster.take(px, py, 0.4, 0.4, 0.0, 0.1):
                    T.lamp(px, py, z0, out_yaw)
            elif r < 0.26:
                px, py = x + n[0] * 0.5, y + n[1] * 0.5
                if raster.take(px, py, 0.4, 0.4, 0.0, 0.1):
                    T.sign(px, py, z0, math.atan2(-t[1], -t[0]))
            elif r < 0.30:
                px, py = x + n[0] * 0.7, y + n[1] * 0.7
                if raster.take(px, py, 0.5, 0.5, 0.0, 0.1):
                    T.traffic_light(px, py, z0, (-n[0], -n[1]), rng.uniform(3.5, 5.0))
            elif r < 0.55:  # a tree or hedge a little further out
                off = rng.uniform(2.5, 5.0)
                px, py = x + n[0] * off, y + n[1] * off
                if raster.take(px, py, 2.0, 2.0, 0.0, 0.5):
                    if rng.random() < 0.8:
                        T.tree(px, py, z0, rng.uniform(0.8, 1.2))
                    else:
                        T.hedge(px, py, z0, rng.uniform(2.0, 4.0), 1.0, rng.uniform(0.8, 1.6), yaw)
            elif r < 0.85:  # a building set back from the road
                w, dd = rng.uniform(8.0, 20.0), rng.uniform(8.0, 16.0)
                off = rng.uniform(4.0, 9.0) + dd / 2
                px, py = x + n[0] * off, y + n[1] * off
                if raster.take(px, py, w, dd, yaw, 1.0):
                    T.building(px, py, z0, w, dd, rng.uniform(5.0, 22.0), yaw)
                    u += w / 2
            elif r < 0.9 and parked < 400:  # a car parked beside the road
                m, _ = vehicle_mesh(rng, "car")
                px, py = x + n[0] * 2.2, y + n[1] * 2.2
                if raster.take(px, py, 4.8, 2.0, yaw, 0.3):
                    T.b.add(transform(m.vertices, px, py, z0, yaw=yaw), m.faces, m.labels)
                    boxes.append(_box_of(m, px, py, z0, yaw))
                    parked += 1
            u += rng.uniform(5.0, 12.0)
    return parked


def _fill(T: Props, rng, raster: _Raster, road_mask: np.ndarray, height_at, density: float):
    """Buildings and trees in the free space between the roads, facing the nearest road."""
    from scipy import ndimage

    dist, (ni, nj) = ndimage.distance_transform_edt(~road_mask, return_indices=True)
    free_area = float((dist > 3.0).sum()) * raster.cell ** 2
    lo, cell = raster.lo, raster.cell

    def sample(dmin, dmax, n):
        ii, jj = np.nonzero((dist >= dmin / cell) & (dist <= dmax / cell))
        if len(ii) == 0:
            return []
        k = rng.integers(0, len(ii), size=n)
        return list(zip(ii[k], jj[k]))

    for i, j in sample(5.0, 45.0, int(density * free_area / 250.0)):
        x, y = lo[0] + (i + 0.5) * cell, lo[1] + (j + 0.5) * cell
        dx, dy = (ni[i, j] - i) * cell, (nj[i, j] - j) * cell
        yaw = math.atan2(dy, dx) + math.pi / 2  # the long side along the road
        w, dd = rng.uniform(10.0, 26.0), rng.uniform(8.0, 18.0)
        if dist[i, j] * cell < dd / 2 + 1.5:
            continue
        if raster.take(x, y, w, dd, yaw, 1.5):
            h = rng.uniform(4.0, 7.0) if rng.random() < 0.3 else rng.uniform(7.0, 30.0)
            T.building(x, y, height_at(x, y), w, dd, h, yaw)
    for i, j in sample(3.0, 80.0, int(density * free_area / 200.0)):
        x, y = lo[0] + (i + 0.5) * cell, lo[1] + (j + 0.5) * cell
        if raster.take(x, y, 2.0, 2.0, 0.0, 0.8):
            z0 = height_at(x, y)
            if rng.random() < 0.85:
                T.tree(x, y, z0, rng.uniform(0.8, 1.3))
            else:
                T.hedge(x, y, z0, rng.uniform(2.0, 5.0), rng.uniform(0.8, 1.5), rng.uniform(0.8, 1.8),
                        rng.uniform(0, math.pi))


# --------------------------------------------------------------------------------------------- scene
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
    od = parse_opendrive(path)
    rng = np.random.default_rng(seed)
    surf, lines = _Strips(), _Strips()
    info = {"area": {}, "lanes": [], "edges": [], "ref": []}
    for road in od.roads:
        _mesh_road(road, opt, surf, lines, info)
    sp = surf.parts()
    if sp is None:
        raise ValueError(f"{od.path}: no lane surfaces to mesh (all lanes have zero width or type 'none')")
    v, f, lab = sp
    f = _orient_up(v, f)
    parts = [(v, f, lab)]
    lp = lines.parts()
    if lp is not None:
        parts.append((lp[0], _orient_up(lp[0], lp[1]), lp[2]))

    ref = np.concatenate(info["ref"])
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    from scipy.spatial import cKDTree

    ref_tree = cKDTree(ref[:, :2])

    def height_at(x, y):
        d, i = ref_tree.query([x, y], k=min(8, len(ref)))
        return float(np.min(ref[np.atleast_1d(i), 2]))

    if opt["ground"]:
        m = float(opt["ground_margin"])
        cell = float(opt["ground_cell"])
        xs = np.arange(lo[0] - m, hi[0] + m + cell, cell)
        ys = np.arange(lo[1] - m, hi[1] + m + cell, cell)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        q = np.stack([X.ravel(), Y.ravel()], 1)
        k = min(8, len(ref))
        _, idx = ref_tree.query(q, k=k)
        zg = ref[idx.reshape(len(q), -1), 2].min(axis=1) - 0.03
        gv = np.stack([q[:, 0], q[:, 1], zg], 1)
        I, J = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
        I, J = I.ravel(), J.ravel()
        a = I * len(ys) + J
        b = (I + 1) * len(ys) + J
        c = (I + 1) * len(ys) + J + 1
        d = I * len(ys) + J + 1
        gf = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        parts.append((gv, gf, np.full(len(gf), TERRAIN, np.int32)))

    T = Props(rng, {})
    n_parked = 0
    static_boxes: list = []
    if opt["roadside"]:
        raster = _Raster(lo - 40.0, hi + 40.0, 1.0)
        raster.mark_points(_road_area_points((v, f, lab)))
        road_mask = raster.occ.copy()
        edges = [e for e in info["edges"]]
        order = rng.permutation(len(edges))
        n_parked = _roadside(T, rng, raster, [edges[i] for i in order], info["lanes"], height_at, opt,
                             static_boxes)
        if float(opt["fill"]) > 0:
            _fill(T, rng, raster, road_mask, height_at, float(opt["fill"]))
    if T.b._parts or T.b._box_c:
        rs = T.b.build()
        parts.append((rs.vertices, rs.faces, rs.labels))
    offs = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    static = Mesh(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] + o for p, o in zip(parts, offs)]),
                  np.concatenate([p[2] for p in parts]))

    # ---- ego route and traffic
    dt = float(opt["frame_interval"])
    t = np.arange(n_frames) * dt
    driving = [l for l in info["lanes"] if l[0] in DRIVING_TYPES and l[0] != "parking"]
    graph = _LaneGraph(driving)
    if not graph.lanes:
        raise ValueError(f"{od.path}: no driving lanes for the ego route")
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
    ego_poses = ego_route.poses(s_ego)
    ego_xy = ego_poses[:, :2]

    actors: list[Actor] = []
    tracks: list[np.ndarray] = [ego_xy]
    radii: list[float] = [EGO_LENGTH / 2 + 0.5]

    def clear(xy, rad):
        return all(np.min(np.linalg.norm(xy - o, axis=1)) > rad + r0 for o, r0 in zip(tracks, radii))

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
    walks = [l for l in info["lanes"] if l[0] in _RAISED and _polylen(l[2]) > 1.5 * 1.6 * t[-1] + 5.0]
    for k in range(int(opt["n_pedestrians"]) if walks else 0):
        for _attempt in range(10):
            l = walks[int(rng.integers(0, len(walks)))]
            pts = l[2] if rng.random() < 0.5 else l[2][::-1]
            r = _Route(pts)
            v = rng.uniform(0.9, 1.6)
            s = rng.uniform(0.0, max(r.length - v * t[-1], 0.0)) + v * t
            poses = r.poses(s)
            poses[:, 4] = 0.0
            if clear(poses[:, :2], 0.4):
                tracks.append(poses[:, :2])
                radii.append(0.4)
                actors.append(Actor(pedestrian_mesh(rng), poses, "pedestrian"))
                break

    drive_area = float(sum(a for tp, a in info["area"].items() if tp.lower() in DRIVING_TYPES))
    meta = {
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
