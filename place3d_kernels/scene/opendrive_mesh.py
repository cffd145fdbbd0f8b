"""Meshing of OpenDRIVE roads: lane surfaces by type, raised sidewalks with curbs, painted road marks."""

from __future__ import annotations

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.xodr import Lane, Road

__all__ = ["DRIVING_TYPES", "LANE_CLASS", "RAISED", "Strips", "orient_up", "mesh_road"]

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
RAISED = frozenset({"sidewalk", "curb"})
_PAINTED = ("solid", "broken", "solid solid", "solid broken", "broken solid", "broken broken", "botts dots")


class Strips:
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


def orient_up(v, f):
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


def mesh_road(road: Road, opt, out: Strips, lines: Strips, info):
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
                    dz = ch if ltype in RAISED else 0.0
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
                    if ltype in DRIVING_TYPES or ltype in RAISED:
                        pts = centre if fwd else centre[::-1]
                        info["lanes"].append((ltype, road.junction != "-1", pts, (width if fwd else width[::-1]),
                                              road.id))
                    info["edges"].append(at(t_out, dz))
                _marks(lane, s, ds, t_out, at, lines, opt, inner_types=(ltype,))
                t_in = t_out


def _marks(lane: Lane, s, ds, t, at, lines: Strips, opt, inner_types=()):
    """Painted road marks on the outer border ``t`` of ``lane`` (the reference line for the centre lane);
    outer borders of non-driving lanes (sidewalk edges, shoulders) get none."""
    if not lane.marks:
        return
    if not any(tp.lower() in DRIVING_TYPES for tp in inner_types) and lane.id != 0:
        return
    mid = 0.5 * (s[1:] + s[:-1])
    mid_ds = 0.5 * (ds[1:] + ds[:-1])
    kinds = [lane.mark_at(v) for v in mid_ds]
    # first-appearance order, not set order: string hashes vary per process (PYTHONHASHSEED), and the face
    # order must not, or the scene key (and the P-SOG cache) would differ between runs
    for mtype in dict.fromkeys(k[1] for k in kinds if k is not None):
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
