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
"""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Actor, Scene
from place3d_kernels.scene.primitives import (MeshBuilder, gable_roof, icosphere, plane_grid, prism,
                                              slab_grid, transform)

__all__ = ["town", "TOWN_OPTIONS", "EGO_LENGTH", "EGO_WIDTH", "Path", "vehicle_mesh", "pedestrian_mesh"]

C = CLASS_ID
BUILDING, FENCE, PEDESTRIAN, POLE, ROAD_LINE, ROAD, SIDEWALK = (
    C["building"], C["fence"], C["pedestrian"], C["pole"], C["road line"], C["road"], C["sidewalk"])
VEGETATION, VEHICLE, WALL, SIGN, GROUND, GUARD_RAIL, LIGHT, STATIC, WATER, TERRAIN = (
    C["vegetation"], C["vehicle"], C["wall"], C["traffic sign"], C["ground"], C["guard rail"],
    C["traffic light"], C["static"], C["water"], C["terrain"])

#: footprint of the ego vehicle (not part of the scene), metres
EGO_LENGTH, EGO_WIDTH = 4.6, 2.0

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

_RIGHT_TURN_RADIUS = 8.0
_LEFT_TURN_RADIUS = 12.0


# ----------------------------------------------------------------------------------------------- paths
class Path:
    """A planar curve sampled densely; poses by arc length (linear extrapolation past both ends)."""

    def __init__(self, points: np.ndarray):
        p = np.asarray(points, float)
        keep = np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9]
        p = p[keep]
        self.points = p
        d = np.diff(p, axis=0)
        seg = np.linalg.norm(d, axis=1)
        self.s = np.r_[0.0, np.cumsum(seg)]
        head = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        # yaw at vertices: mean of adjacent segment headings
        self.yaw = np.r_[head[0], (head[:-1] + head[1:]) / 2, head[-1]]
        self.dir0 = d[0] / seg[0]
        self.dir1 = d[-1] / seg[-1]

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y, yaw at arc lengths ``s``."""
        s = np.asarray(s, float)
        x = np.interp(s, self.s, self.points[:, 0])
        y = np.interp(s, self.s, self.points[:, 1])
        yaw = np.interp(s, self.s, self.yaw)
        lo, hi = s < 0, s > self.length
        x = np.where(lo, self.points[0, 0] + s * self.dir0[0], x)
        y = np.where(lo, self.points[0, 1] + s * self.dir0[1], y)
        e = s - self.length
        x = np.where(hi, self.points[-1, 0] + e * self.dir1[0], x)
        y = np.where(hi, self.points[-1, 1] + e * self.dir1[1], y)
        return x, y, yaw

    def nearest_s(self, xy, lo: float = -np.inf, hi: float = np.inf) -> float:
        """Arc length of the sample nearest to ``xy`` among those with lo <= s <= hi."""
        i0, i1 = np.searchsorted(self.s, lo), np.searchsorted(self.s, hi, side="right")
        i1 = max(i1, i0 + 1)
        k = i0 + int(np.argmin(np.linalg.norm(self.points[i0:i1] - np.asarray(xy)[None], axis=1)))
        return float(self.s[min(k, len(self.s) - 1)])


def _fillet(corners: np.ndarray, radii, step: float = 0.25) -> Path:
    """Polyline through ``corners`` with circular fillets of ``radii`` at interior corners."""
    P = np.asarray(corners, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(P),))
    pts = [P[0]]
    for i in range(1, len(P) - 1):
        u, w = P[i] - P[i - 1], P[i + 1] - P[i]
        lu, lw = np.linalg.norm(u), np.linalg.norm(w)
        u, w = u / lu, w / lw
        cross = u[0] * w[1] - u[1] * w[0]
        theta = math.acos(float(np.clip(u @ w, -1.0, 1.0)))
        if theta < 1e-6:
            pts.append(P[i])
            continue
        t = min(radii[i] * math.tan(theta / 2), 0.49 * lu, 0.49 * lw)
        r = t / math.tan(theta / 2)
        A = P[i] - u * t
        sgn = 1.0 if cross > 0 else -1.0
        centre = A + sgn * r * np.array([-u[1], u[0]])
        a0 = math.atan2(A[1] - centre[1], A[0] - centre[0])
        k = max(2, int(math.ceil(r * theta / step)))
        a = a0 + sgn * theta * np.linspace(0, 1, k + 1)
        pts.extend(np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)], 1))
    pts.append(P[-1])
    pts = np.array(pts)
    # densify straight stretches
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out.extend(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return Path(np.array(out))


# ------------------------------------------------------------------------------------------ meshes
_TEMPLATES: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def _tmpl(name: str):
    if name not in _TEMPLATES:
        if name == "ico1":
            _TEMPLATES[name] = icosphere(1)
        elif name == "ico0":
            _TEMPLATES[name] = icosphere(0)
        elif name.startswith("prism"):
            n = int(name[5:])
            _TEMPLATES[name] = prism(n, 1.0, 0.0, 1.0, phase=math.pi / n)
        else:
            raise KeyError(name)
    return _TEMPLATES[name]


def _wheel(v_unit, x, y, r, w):
    """A wheel: unit prism (axis z) turned to axis y, radius r, width w, centred (x, y, r)."""
    v = v_unit.copy()
    v[:, :2] *= r
    v[:, 2] = (v[:, 2] - 0.5) * w
    # rotation about x by +90 deg: (x, y, z) -> (x, -z, y)
    return np.stack([v[:, 0] + x, -v[:, 2] + y, v[:, 1] + r], 1)


def vehicle_mesh(rng: np.random.Generator, kind: str | None = None) -> tuple[Mesh, str]:
    """A low-poly vehicle in its own frame (x forward, z up, origin on the ground under its centre)."""
    if kind is None:
        kind = rng.choice(["car", "car", "car", "car", "car", "car", "van", "van", "truck", "bus"])
    b = MeshBuilder()
    wv, wf = _tmpl("prism6")
    if kind == "car":
        L, W, H = rng.uniform(4.0, 4.9), rng.uniform(1.75, 1.95), rng.uniform(1.4, 1.6)
        b.add_box(0, 0, 0.3, L, W, 0.65, 0, VEHICLE)
        cab = L * rng.uniform(0.45, 0.55)
        b.add_box(-0.05 * L, 0, 0.95, cab, W - 0.14, H - 0.95, 0, VEHICLE)
        r, ax = 0.32, L / 2 - 0.8
    elif kind == "van":
        L, W, H = rng.uniform(4.8, 5.6), 2.0, rng.uniform(1.9, 2.4)
        b.add_box(0, 0, 0.35, L, W, 0.9, 0, VEHICLE)
        b.add_box(-0.1, 0, 1.25, L - 0.8, W - 0.06, H - 1.25, 0, VEHICLE)
        r, ax = 0.35, L / 2 - 0.85
    elif kind == "truck":
        L, W, H = rng.uniform(6.5, 8.0), 2.3, rng.uniform(2.8, 3.4)
        b.add_box(L / 2 - 1.0, 0, 0.45, 2.0, W, 2.1, 0, VEHICLE)            # cab
        b.add_box(-0.9, 0, 0.6, L - 2.2, W, H - 0.6, 0, VEHICLE)            # cargo box
        r, ax = 0.45, L / 2 - 1.1
    elif kind == "bus":
        L, W, H = rng.uniform(10.0, 12.0), 2.5, rng.uniform(2.9, 3.2)
        b.add_box(0, 0, 0.35, L, W, H - 0.35, 0, VEHICLE)
        r, ax = 0.5, L / 2 - 2.2
    else:
        raise ValueError(f"unknown vehicle kind {kind!r}; use car, van, truck or bus")
    for sx in (-ax, ax):
        for sy in (-1, 1):
            b.add(_wheel(wv, sx, sy * (W / 2 - 0.12), r, 0.24), wf, VEHICLE)
    return b.build(), str(kind)


def pedestrian_mesh(rng: np.random.Generator) -> Mesh:
    """A low-poly pedestrian (label 4), origin on the ground between the feet, facing +x."""
    h = rng.uniform(1.55, 1.92)
    b = MeshBuilder()
    for sy in (-0.09, 0.09):
        b.add_box(0, sy, 0, 0.14, 0.14, 0.47 * h, 0, PEDESTRIAN)                 # legs
    b.add_box(0, 0, 0.47 * h, 0.22, 0.38, 0.35 * h, 0, PEDESTRIAN)              # torso
    for sy in (-0.245, 0.245):
        b.add_box(0, sy, 0.48 * h, 0.1, 0.09, 0.33 * h, 0, PEDESTRIAN)          # arms
    hv, hf = _tmpl("ico0")
    b.add(transform(hv, 0, 0, 0.9 * h, scale=0.075 * h), hf, PEDESTRIAN)        # head
    return b.build()


# ----------------------------------------------------------------------------------- static objects
class _Town:
    """Static geometry builder with helpers for every kind of object."""

    def __init__(self, rng: np.random.Generator, opt: dict):
        self.rng = rng
        self.b = MeshBuilder()
        self.opt = opt

    # -- simple solids
    def tree(self, x, y, z0, scale=1.0, trunk_min=0.0, crown_max=None):
        """Trunk plus one or two crown blobs; the crown starts at the trunk top (>= ``trunk_min``)."""
        rng = self.rng
        th = max(rng.uniform(2.2, 3.4) * scale, trunk_min)
        tr = rng.uniform(0.14, 0.24) * scale
        pv, pf = _tmpl("prism6")
        self.b.add(transform(pv, x, y, z0, scale=(tr, tr, th + 0.3)), pf, VEGETATION)
        cr = rng.uniform(1.4, 2.6) * scale
        if crown_max is not None:
            cr = min(cr, crown_max)
        cz = rng.uniform(0.9, 1.4)
        iv, if_ = _tmpl("ico1")
        self.b.add(transform(iv, x, y, z0 + th + cr * cz, yaw=rng.uniform(0, 6.3),
                             scale=(cr, cr * rng.uniform(0.85, 1.0), cr * cz)), if_, VEGETATION)
        if rng.random() < 0.35:  # a second, smaller blob on top
            c2 = cr * 0.7
            self.b.add(transform(iv, x + rng.uniform(-0.4, 0.4) * (cr - c2), y + rng.uniform(-0.4, 0.4) * (cr - c2),
                                 z0 + th + cr * cz * 1.7, scale=(c2, c2, c2 * cz)), if_, VEGETATION)

    def cylinder(self, x, y, z0, r, h, label, n=8):
        pv, pf = _tmpl(f"prism{n}")
        self.b.add(transform(pv, x, y, z0, scale=(r, r, h)), pf, label)

    def lamp(self, x, y, z0, yaw):
        """A street lamp at (x, y) with its arm pointing along ``yaw``."""
        self.cylinder(x, y, z0, 0.09, 6.5, POLE, 6)
        cx, cy = x + 0.8 * math.cos(yaw), y + 0.8 * math.sin(yaw)
        self.b.add_box(cx, cy, z0 + 6.3, 1.6, 0.1, 0.1, yaw, POLE)
        self.b.add_box(x + 1.5 * math.cos(yaw), y + 1.5 * math.sin(yaw), z0 + 6.1, 0.6, 0.3, 0.18, yaw, POLE)

    def sign(self, x, y, z0, yaw, shape=None):
        """A traffic sign whose face looks along ``yaw``."""
        rng = self.rng
        self.cylinder(x, y, z0, 0.05, 2.9, POLE, 6)
        shape = shape or rng.choice(["round", "square", "rect", "tri"])
        ox, oy = 0.08 * math.cos(yaw), 0.08 * math.sin(yaw)
        if shape == "round":
            pv, pf = _tmpl("prism8")
            v = pv.copy()
            v[:, :2] *= 0.33
            v[:, 2] = (v[:, 2] - 0.5) * 0.04
            # turn the plate's axis from z to x (rotation about y by +90 deg), so it faces along yaw
            v = np.stack([v[:, 2], v[:, 1], -v[:, 0]], 1)
            self.b.add(transform(v, x + ox, y + oy, z0 + 2.5, yaw=yaw), pf, SIGN)
        elif shape == "tri":
            rv, rf = gable_roof(0.04, 0.8, 0.7)  # a thin triangular prism, base at z = 0
            self.b.add(transform(rv, x + ox, y + oy, z0 + 2.2, yaw=yaw), rf, SIGN)
        elif shape == "rect":
            self.b.add_box(x + ox, y + oy, z0 + 2.0, 0.04, 0.6, 0.9, yaw, SIGN)
        else:
            self.b.add_box(x + ox, y + oy, z0 + 2.2, 0.04, 0.62, 0.62, yaw, SIGN)

    def traffic_light(self, x, y, z0, arm_dir, arm_len):
        """A signal mast at (x, y) with an arm over the road along unit vector ``arm_dir``."""
        yaw = math.atan2(arm_dir[1], arm_dir[0])
        self.cylinder(x, y, z0, 0.13, 6.2, POLE, 8)
        self.b.add_box(x + arm_dir[0] * arm_len / 2, y + arm_dir[1] * arm_len / 2, z0 + 5.8, arm_len, 0.14,
                       0.16, yaw, POLE)
        for f in (0.55, 0.95):  # hanging heads over the lanes
            self.b.add_box(x + arm_dir[0] * arm_len * f, y + arm_dir[1] * arm_len * f, z0 + 4.75, 0.35, 0.4,
                           1.05, yaw, LIGHT)
        # pole-mounted head facing traffic, and a pedestrian signal
        self.b.add_box(x + 0.25 * arm_dir[0], y + 0.25 * arm_dir[1], z0 + 2.3, 0.3, 0.35, 0.95, yaw, LIGHT)
        self.b.add_box(x - 0.22 * arm_dir[1], y + 0.22 * arm_dir[0], z0 + 2.0, 0.28, 0.28, 0.6, yaw, LIGHT)

    def bench(self, x, y, z0, yaw):
        self.b.add_box(x, y, z0 + 0.42, 1.8, 0.45, 0.06, yaw, STATIC)
        bx, by = -0.2 * math.sin(yaw), 0.2 * math.cos(yaw)  # backrest behind the seat (local +y)
        self.b.add_box(x + bx, y + by, z0 + 0.48, 1.8, 0.06, 0.45, yaw, STATIC)
        for s in (-0.75, 0.75):
            self.b.add_box(x + s * math.cos(yaw), y + s * math.sin(yaw), z0, 0.08, 0.4, 0.42, yaw, STATIC)

    def bin(self, x, y, z0):
        self.cylinder(x, y, z0, 0.28, 0.95, STATIC, 8)

    def hydrant(self, x, y, z0):
        self.cylinder(x, y, z0, 0.13, 0.7, STATIC, 6)
        self.b.add_box(x, y, z0 + 0.45, 0.45, 0.12, 0.12, 0.0, STATIC)

    def bollard(self, x, y, z0):
        self.cylinder(x, y, z0, 0.1, 0.9, STATIC, 6)

    def hedge(self, x, y, z0, lx, ly, h, yaw=0.0):
        self.b.add_box(x, y, z0, lx, ly, h, yaw, VEGETATION)

    def wall(self, p0, p1, z0, h=2.2, t=0.3):
        self.b.add_segment_box(p0, p1, t, z0, z0 + h, WALL)

    def fence(self, p0, p1, z0, h=1.4, label=FENCE, spacing=2.5):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        L = float(np.linalg.norm(p1 - p0))
        if L < 0.5:
            return
        d = (p1 - p0) / L
        yaw = math.atan2(d[1], d[0])
        n = max(1, int(math.ceil(L / spacing)))
        for k in range(n + 1):
            p = p0 + d * (L * k / n)
            self.b.add_box(p[0], p[1], z0, 0.09, 0.09, h, yaw, label)
        for zr in (0.25 * h, 0.85 * h):
            self.b.add_segment_box(p0, p1, 0.04, z0 + zr, z0 + zr + 0.07, label)

    def guard_rail(self, p0, p1, z0=0.0, piece=20.0):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        L = float(np.linalg.norm(p1 - p0))
        d = (p1 - p0) / L
        yaw = math.atan2(d[1], d[0])
        n = int(math.ceil(L / 4.0))
        for k in range(n + 1):
            p = p0 + d * (L * k / n)
            self.b.add_box(p[0], p[1], z0, 0.12, 0.12, 0.72, yaw, GUARD_RAIL)
        m = int(math.ceil(L / piece))
        for k in range(m):
            a, c = p0 + d * (L * k / m), p0 + d * (L * (k + 1) / m)
            self.b.add_segment_box(a, c, 0.06, z0 + 0.42, z0 + 0.75, GUARD_RAIL)

    def vehicle(self, x, y, yaw, kind=None, z0=0.0):
        m, _ = vehicle_mesh(self.rng, kind)
        self.b.add(transform(m.vertices, x, y, z0, yaw=yaw), m.faces, m.labels)

    def building(self, x, y, z0, w, d, h, yaw=0.0, style=None):
        """A building centred at (x, y) with footprint w x d (local x, y), height h above z0."""
        rng, b = self.rng, self.b
        style = style or rng.choice(["box", "box", "setback", "L", "parapet"])
        c, s = math.cos(yaw), math.sin(yaw)

        def at(lx, ly):
            return x + c * lx - s * ly, y + s * lx + c * ly

        if style == "L" and w > 12 and d > 10:
            w1 = w * rng.uniform(0.45, 0.6)
            px, py = at(-w / 2 + w1 / 2, 0)
            b.add_box(px, py, z0, w1, d, h, yaw, BUILDING)
            d2 = d * rng.uniform(0.45, 0.6)
            px, py = at(w1 / 2, -d / 2 + d2 / 2)
            b.add_box(px, py, z0, w - w1, d2, h * rng.uniform(0.6, 1.0), yaw, BUILDING)
        else:
            b.add_box(x, y, z0, w, d, h, yaw, BUILDING)
            if style == "setback" and h > 9:
                h2 = rng.uniform(3.0, min(12.0, 0.6 * h))
                b.add_box(x, y, z0 + h, w * rng.uniform(0.5, 0.8), d * rng.uniform(0.5, 0.8), h2, yaw,
                          BUILDING)
            elif style == "parapet":
                t = 0.25
                for lx, ly, sx, sy in ((0, -d / 2 + t / 2, w, t), (0, d / 2 - t / 2, w, t),
                                       (-w / 2 + t / 2, 0, t, d - 2 * t), (w / 2 - t / 2, 0, t, d - 2 * t)):
                    px, py = at(lx, ly)
                    b.add_box(px, py, z0 + h, sx, sy, 0.9, yaw, BUILDING)
        for _ in range(int(rng.integers(0, 3))):  # rooftop units
            ux, uy = rng.uniform(-0.3, 0.3) * w, rng.uniform(-0.3, 0.3) * d
            px, py = at(ux, uy)
            b.add_box(px, py, z0 + h, rng.uniform(1.0, 3.0), rng.uniform(1.0, 3.0), rng.uniform(0.8, 2.5), yaw,
                      BUILDING)
        # storey ledges on some facades (thin slabs sticking out 0.3 m): rough, lidar-visible facades
        if rng.random() < 0.35 and h > 7 and style != "L":
            for zl in np.arange(3.2, h - 1.0, 3.2):
                b.add_box(x, y, z0 + zl, w + 0.6, d + 0.6, 0.18, yaw, BUILDING)

    def house(self, x, y, z0, w, d, yaw):
        rng = self.rng
        h = rng.uniform(3.0, 6.5)
        self.b.add_box(x, y, z0, w, d, h, yaw, BUILDING)
        rv, rf = gable_roof(w + 0.6, d + 0.6, rng.uniform(1.5, 3.0))
        self.b.add(transform(rv, x, y, z0 + h, yaw=yaw), rf, BUILDING)
        if rng.random() < 0.5:  # chimney
            c, s = math.cos(yaw), math.sin(yaw)
            lx, ly = rng.uniform(-0.3, 0.3) * w, rng.uniform(-0.25, 0.25) * d
            self.b.add_box(x + c * lx - s * ly, y + s * lx + c * ly, z0 + h, 0.6, 0.6, 2.6, yaw, BUILDING)


class _Occupancy:
    """Axis-aligned rectangles already used in a region (to scatter objects without overlaps)."""

    def __init__(self):
        self.r: list[tuple[float, float, float, float]] = []

    def add(self, x0, y0, x1, y1):
        self.r.append((min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)))

    def free(self, x, y, rad) -> bool:
        for a, b, c, d in self.r:
            if x + rad > a and x - rad < c and y + rad > b and y - rad < d:
                return False
        return True


def _scatter(rng, occ: _Occupancy, rect, n, rad, tries=30):
    """Up to n points in rect = (x0, y0, x1, y1) at least rad from every occupied rectangle."""
    x0, y0, x1, y1 = rect
    out = []
    if x1 - x0 < 2 * rad or y1 - y0 < 2 * rad:
        return out
    for _ in range(n):
        for _ in range(tries):
            x, y = rng.uniform(x0 + rad, x1 - rad), rng.uniform(y0 + rad, y1 - rad)
            if occ.free(x, y, rad):
                occ.add(x - rad, y - rad, x + rad, y + rad)
                out.append((x, y))
                break
    return out


# --------------------------------------------------------------------------------------- the blocks
def _block_perimeter(T: _Town, occ, inner, z0):
    rng = T.rng
    x0, y0, x1, y1 = inner
    d = rng.uniform(10.0, 15.0)
    rects = []
    sides = [  # (start, direction, inward normal, length along)
        ((x0, y0), (1, 0), (0, 1), x1 - x0),
        ((x1, y1), (-1, 0), (0, -1), x1 - x0),
        ((x0, y1 - d), (0, -1), (1, 0), y1 - y0 - 2 * d),
        ((x1, y0 + d), (0, 1), (-1, 0), y1 - y0 - 2 * d),
    ]
    for (sx, sy), (tx, ty), (nx, ny), L in sides:
        u = 0.0
        while u < L - 1e-6:
            w = rng.uniform(10.0, 24.0)
            if L - (u + w) < 8.0:
                w = L - u
            if rng.random() < 0.25 and L - u > 14.0:  # a gap closed by a wall, fence or gate
                g = min(rng.uniform(4.0, 9.0), L - u - 8.0)
                p0 = (sx + tx * u + nx * 0.3, sy + ty * u + ny * 0.3)
                p1 = (sx + tx * (u + g) + nx * 0.3, sy + ty * (u + g) + ny * 0.3)
                if rng.random() < 0.6:
                    T.wall(p0, p1, z0, rng.uniform(1.6, 2.6))
                else:
                    T.fence(p0, p1, z0, rng.uniform(1.2, 2.0))
                u += g
                continue
            dd = d - rng.uniform(0.0, 2.5)
            cx = sx + tx * (u + w / 2) + nx * dd / 2
            cy = sy + ty * (u + w / 2) + ny * dd / 2
            yaw = math.atan2(ty, tx)
            h = rng.uniform(4.0, 6.0) if rng.random() < 0.15 else rng.uniform(7.0, 28.0)
            T.building(cx, cy, z0, w - 0.2, dd, h, yaw)
            u += w
    occ.add(x0, y0, x1, y0 + d)
    occ.add(x0, y1 - d, x1, y1)
    occ.add(x0, y0, x0 + d, y1)
    occ.add(x1 - d, y0, x1, y1)
    # courtyard: lawn (default terrain), a paved playground, trees, hedges, a bench
    cx0, cy0, cx1, cy1 = x0 + d + 1, y0 + d + 1, x1 - d - 1, y1 - d - 1
    pw, ph = rng.uniform(8, 14), rng.uniform(8, 14)
    px, py = rng.uniform(cx0, cx1 - pw), rng.uniform(cy0, cy1 - ph)
    rects.append((px, py, px + pw, py + ph, GROUND))
    occ.add(px, py, px + pw, py + ph)
    T.bench(px + pw / 2, py + 0.6, z0, 0.0)
    T.bin(px + 1.0, py + 1.0, z0)
    for x, y in _scatter(rng, occ, (cx0, cy0, cx1, cy1), int(rng.integers(4, 9)), 2.5):
        T.tree(x, y, z0)
    for x, y in _scatter(rng, occ, (cx0, cy0, cx1, cy1), int(rng.integers(2, 5)), 2.0):
        T.hedge(x, y, z0, rng.uniform(2.0, 4.0), rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.5),
                rng.choice([0.0, math.pi / 2]))
    return rects, TERRAIN


def _block_towers(T: _Town, occ, inner, z0):
    rng = T.rng
    x0, y0, x1, y1 = inner
    mx, my = (x0 + x1) / 2, (y0 + y1) / 2
    rects = []
    quads = [(x0, y0, mx, my), (mx, y0, x1, my), (x0, my, mx, y1), (mx, my, x1, y1)]
    for qx0, qy0, qx1, qy1 in quads:
        qcx, qcy = (qx0 + qx1) / 2, (qy0 + qy1) / 2
        qs = min(qx1 - qx0, qy1 - qy0)
        r = rng.random()
        if r < 0.75:
            pw, pd = rng.uniform(0.55, 0.8) * qs, rng.uniform(0.55, 0.8) * qs
            ph = rng.uniform(4.0, 9.0)
            T.building(qcx, qcy, z0, pw, pd, ph, 0.0, "box")
            occ.add(qcx - pw / 2 - 1, qcy - pd / 2 - 1, qcx + pw / 2 + 1, qcy + pd / 2 + 1)
            if rng.random() < 0.3:
                rr = rng.uniform(5.0, min(pw, pd) / 2 - 0.5)
                T.cylinder(qcx, qcy, z0 + ph, rr, rng.uniform(25.0, 60.0), BUILDING, 12)
            else:
                tw, td = rng.uniform(0.45, 0.75) * pw, rng.uniform(0.45, 0.75) * pd
                T.building(qcx, qcy, z0 + ph, tw, td, rng.uniform(20.0, 60.0), 0.0,
                           rng.choice(["box", "setback", "parapet"]))
        else:  # a pocket park
            rects.append((qx0 + 3, qy0 + 3, qx1 - 3, qy1 - 3, TERRAIN))
            for x, y in _scatter(rng, occ, (qx0 + 3, qy0 + 3, qx1 - 3, qy1 - 3), int(rng.integers(4, 8)), 2.5):
                T.tree(x, y, z0)
    # planters, low walls, benches, bollards, lamps on the plaza
    for x, y in _scatter(rng, occ, inner, int(rng.integers(4, 9)), 2.2):
        if rng.random() < 0.5:
            T.hedge(x, y, z0, rng.uniform(2.0, 3.5), rng.uniform(1.0, 2.0), rng.uniform(0.6, 1.1))
        else:
            T.wall((x - 1.5, y), (x + 1.5, y), z0, rng.uniform(0.5, 1.0), 0.4)
    for x, y in _scatter(rng, occ, inner, int(rng.integers(2, 5)), 1.2):
        T.bench(x, y, z0, rng.choice([0.0, math.pi / 2]))
    for x, y in _scatter(rng, occ, inner, int(rng.integers(3, 7)), 0.5):
        T.bollard(x, y, z0)
    for x, y in _scatter(rng, occ, inner, 3, 0.8):
        T.lamp(x, y, z0, rng.uniform(0, 2 * math.pi))
    return rects, GROUND


def _block_park(T: _Town, occ, inner, z0):
    rng = T.rng
    x0, y0, x1, y1 = inner
    mx, my = (x0 + x1) / 2 + rng.uniform(-8, 8), (y0 + y1) / 2 + rng.uniform(-8, 8)
    pw = 3.0
    rects = [(x0, my - pw / 2, x1, my + pw / 2, GROUND), (mx - pw / 2, y0, mx + pw / 2, y1, GROUND)]
    occ.add(x0, my - pw / 2 - 0.5, x1, my + pw / 2 + 0.5)
    occ.add(mx - pw / 2 - 0.5, y0, mx + pw / 2 + 0.5, y1)
    # pond in one quadrant
    q = int(rng.integers(0, 4))
    qx0, qx1 = (x0, mx - pw) if q % 2 == 0 else (mx + pw, x1)
    qy0, qy1 = (y0, my - pw) if q < 2 else (my + pw, y1)
    w, h = rng.uniform(0.4, 0.7) * (qx1 - qx0), rng.uniform(0.4, 0.7) * (qy1 - qy0)
    px, py = (qx0 + qx1 - w) / 2, (qy0 + qy1 - h) / 2
    rects.append((px, py, px + w, py + h, WATER))
    occ.add(px - 1, py - 1, px + w + 1, py + h + 1)
    T.fence((px - 0.6, py - 0.6), (px + w + 0.6, py - 0.6), z0, 1.0)
    T.fence((px - 0.6, py + h + 0.6), (px + w + 0.6, py + h + 0.6), z0, 1.0)
    # perimeter fence with gaps where the paths leave the park
    e = 0.5
    for (a, b, c, d) in (((x0 + e, y0 + e), (x1 - e, y0 + e), mx, 0), ((x0 + e, y1 - e), (x1 - e, y1 - e), mx, 0),
                         ((x0 + e, y0 + e), (x0 + e, y1 - e), my, 1), ((x1 - e, y0 + e), (x1 - e, y1 - e), my, 1)):
        gap0, gap1 = c - pw, c + pw
        if d == 0:
            T.fence(a, (gap0, a[1]), z0)
            T.fence((gap1, a[1]), b, z0)
        else:
            T.fence(a, (a[0], gap0), z0)
            T.fence((a[0], gap1), b, z0)
    occ.add(x0, y0, x1, y0 + 1.2)
    occ.add(x0, y1 - 1.2, x1, y1)
    occ.add(x0, y0, x0 + 1.2, y1)
    occ.add(x1 - 1.2, y0, x1, y1)
    if rng.random() < 0.6:  # kiosk / pavilion
        kx, ky = mx + pw / 2 + 4, my + pw / 2 + 4
        if occ.free(kx, ky, 3.0):
            T.building(kx, ky, z0, 4.0, 4.0, 3.2, 0.0, "box")
            occ.add(kx - 3, ky - 3, kx + 3, ky + 3)
    for x, y in _scatter(rng, occ, inner, int(rng.integers(25, 40)), 2.2):
        T.tree(x, y, z0, rng.uniform(0.8, 1.25))
    for x, y in _scatter(rng, occ, inner, int(rng.integers(6, 12)), 1.8):
        T.hedge(x, y, z0, rng.uniform(1.5, 3.5), rng.uniform(0.8, 1.5), rng.uniform(0.7, 1.6),
                rng.uniform(0, math.pi))
    for k in range(int(rng.integers(3, 7))):  # benches and bins along the paths
        if k % 2 == 0:
            bx, by = rng.uniform(x0 + 5, x1 - 5), my + pw / 2 + 0.5
            T.bench(bx, by, z0, 0.0)
            T.bin(bx + 1.5, by, z0)
        else:
            bx, by = mx + pw / 2 + 0.5, rng.uniform(y0 + 5, y1 - 5)
            T.bench(bx, by, z0, -math.pi / 2)
    for k in range(4):
        T.lamp(mx - pw / 2 - 0.4, y0 + (k + 0.5) * (y1 - y0) / 4, z0, 0.0)
    return rects, TERRAIN


def _block_houses(T: _Town, occ, inner, z0):
    rng = T.rng
    x0, y0, x1, y1 = inner
    n = 4
    lw, lh = (x1 - x0) / n, (y1 - y0) / n
    rects = []
    for i in range(n):
        for j in range(n):
            lx0, ly0 = x0 + i * lw, y0 + j * lh
            cx, cy = lx0 + lw / 2, ly0 + lh / 2
            w, d = rng.uniform(7.5, 11.5), rng.uniform(6.5, 9.5)
            yaw = rng.choice([0.0, math.pi / 2])
            hx, hy = (w / 2, d / 2) if yaw == 0 else (d / 2, w / 2)
            ox, oy = rng.uniform(-1, 1) * max(0.0, lw / 2 - hx - 2.0), rng.uniform(-1, 1) * max(0.0, lh / 2 - hy - 2.0)
            T.house(cx + ox, cy + oy, z0, w, d, yaw)
            occ.add(cx + ox - hx - 0.5, cy + oy - hy - 0.5, cx + ox + hx + 0.5, cy + oy + hy + 0.5)
            # lot boundaries: fences, hedges or walls on the east / north edges, street fronts on the rim
            for edge in ("e", "n", "w", "s"):
                on_rim = (edge == "w" and i == 0) or (edge == "s" and j == 0) or \
                         (edge == "e" and i == n - 1) or (edge == "n" and j == n - 1)
                if edge in ("w", "s") and not on_rim:
                    continue  # the neighbour draws it
                if rng.random() < (0.3 if on_rim else 0.45):
                    continue
                inset = 0.4 if on_rim else 0.0
                if edge == "e":
                    a, b = (lx0 + lw - inset, ly0 + 0.5), (lx0 + lw - inset, ly0 + lh - 0.5)
                elif edge == "w":
                    a, b = (lx0 + inset, ly0 + 0.5), (lx0 + inset, ly0 + lh - 0.5)
                elif edge == "n":
                    a, b = (lx0 + 0.5, ly0 + lh - inset), (lx0 + lw - 0.5, ly0 + lh - inset)
                else:
                    a, b = (lx0 + 0.5, ly0 + inset), (lx0 + lw - 0.5, ly0 + inset)
                r = rng.random()
                if r < 0.45:
                    T.fence(a, b, z0, rng.uniform(1.0, 1.8))
                elif r < 0.75:
                    T.b.add_segment_box(a, b, 0.8, z0, z0 + rng.uniform(1.0, 1.8), VEGETATION)
                else:
                    T.wall(a, b, z0, rng.uniform(1.2, 2.0), 0.25)
                occ.add(min(a[0], b[0]) - 0.5, min(a[1], b[1]) - 0.5, max(a[0], b[0]) + 0.5, max(a[1], b[1]) + 0.5)
            lot = (lx0 + 1, ly0 + 1, lx0 + lw - 1, ly0 + lh - 1)
            if rng.random() < 0.35:  # a car on a paved driveway
                spots = _scatter(rng, occ, lot, 1, 3.0)
                if spots:
                    px, py = spots[0]
                    rects.append((px - 2.8, py - 2.8, px + 2.8, py + 2.8, GROUND))
                    T.vehicle(px, py, rng.choice([0.0, math.pi / 2]), "car", z0)
            for x, y in _scatter(rng, occ, lot, int(rng.integers(0, 3)), 2.0):
                T.tree(x, y, z0, rng.uniform(0.7, 1.0))
    return rects, TERRAIN


_BLOCK_KINDS = {"perimeter": _block_perimeter, "towers": _block_towers, "park": _block_park,
                "houses": _block_houses}


# ------------------------------------------------------------------------------------ road network
def _lane_path(nodes, centres, offset, step=0.25) -> Path:
    """Lane centreline of a junction walk: ``offset`` metres along the left normal of travel (negative: the
    right-hand lane), with fillets of the turn radii at junctions."""
    P = np.array([[centres[i], centres[j]] for i, j in nodes], float)
    dirs = np.diff(P, axis=0)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    nrm = np.stack([-dirs[:, 1], dirs[:, 0]], 1)
    corners = [P[0] + offset * nrm[0]]
    radii = [0.0]
    for k in range(1, len(P) - 1):
        if np.allclose(dirs[k - 1], dirs[k]):
            corners.append(P[k] + offset * nrm[k])
            radii.append(0.0)
        else:
            corners.append(P[k] + offset * (nrm[k - 1] + nrm[k]))
            left = dirs[k - 1][0] * dirs[k][1] - dirs[k - 1][1] * dirs[k][0] > 0
            # with offset < 0 (right-hand traffic) left turns sweep wide, right turns hug the corner
            radii.append(_LEFT_TURN_RADIUS if left == (offset < 0) else _RIGHT_TURN_RADIUS)
    corners.append(P[-1] + offset * nrm[-1])
    radii.append(0.0)
    return _fillet(np.array(corners), radii, step)


_DIRS = ((1, 0), (0, 1), (-1, 0), (0, -1))


def _walk(rng, start, d0, n_seg, nmax, force_turn_at=None, p_straight=0.55, avoid_border=False):
    """A random node walk on the (nmax+1)^2 junction grid without U-turns."""
    nodes = [start, (start[0] + d0[0], start[1] + d0[1])]
    d = d0
    while len(nodes) < n_seg + 1:
        cur = nodes[-1]
        opts = [e for e in _DIRS if e != (-d[0], -d[1])
                and 0 <= cur[0] + e[0] <= nmax and 0 <= cur[1] + e[1] <= nmax]
        if force_turn_at is not None and len(nodes) - 1 == force_turn_at:
            turns = [e for e in opts if e != d]
            opts = turns or opts
        if avoid_border:
            inner = [e for e in opts if 0 < cur[0] + e[0] < nmax or 0 < cur[1] + e[1] < nmax]
            opts = inner or opts
        if d in opts and rng.random() < p_straight and not (force_turn_at is not None and len(nodes) - 1 == force_turn_at):
            e = d
        else:
            e = opts[int(rng.integers(0, len(opts)))]
        nodes.append((cur[0] + e[0], cur[1] + e[1]))
        d = e
    return nodes


def _obb_overlap(c1, yaw1, h1, c2, yaw2, h2) -> np.ndarray:
    """Whether oriented rectangles overlap (SAT), vectorised over the leading axis.

    c: (N, 2) centres, yaw: (N,), h: (2,) or (N, 2) half extents.
    """
    c1, c2 = np.asarray(c1, float), np.asarray(c2, float)
    yaw1, yaw2 = np.asarray(yaw1, float), np.asarray(yaw2, float)
    h1 = np.broadcast_to(np.asarray(h1, float), c1.shape)
    h2 = np.broadcast_to(np.asarray(h2, float), c2.shape)
    a1 = np.stack([np.stack([np.cos(yaw1), np.sin(yaw1)], -1), np.stack([-np.sin(yaw1), np.cos(yaw1)], -1)], 1)
    a2 = np.stack([np.stack([np.cos(yaw2), np.sin(yaw2)], -1), np.stack([-np.sin(yaw2), np.cos(yaw2)], -1)], 1)
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


# ------------------------------------------------------------------------------------------- town
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
            voxel face of the default 0.2 m grid, whose z faces lie at -0.05 + 0.2 k: every sidewalk point
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
    T = _Town(rng, opt)
    b = T.b
    c = (np.arange(nb + 1) - nb / 2) * P  # road centrelines (both axes)
    E_net = c[-1] + hw
    E = E_net + margin

    # ---- ground at z = 0: road cells, outer terrain (with a pond and ground aprons); blocks are slabs
    pond_side = int(rng.integers(0, 4))
    pond_a = rng.uniform(c[0], c[-1] - 40.0)
    pond_len = rng.uniform(25.0, 40.0)
    band0, band1 = E_net + 10.0, min(E_net + 10.0 + rng.uniform(15.0, 25.0), E - 5.0)
    lines = list(c - hw) + list(c + hw) + [-E, E]
    extra_x, extra_y = [], []
    if pond_side in (0, 2):  # north / south band: pond spans x in [a, a+len]
        extra_x += [pond_a, pond_a + pond_len]
        sgn = 1 if pond_side == 0 else -1
        extra_y += [sgn * band0, sgn * band1]
        pond = (pond_a, min(sgn * band0, sgn * band1), pond_a + pond_len, max(sgn * band0, sgn * band1))
    else:
        extra_y += [pond_a, pond_a + pond_len]
        sgn = 1 if pond_side == 1 else -1
        extra_x += [sgn * band0, sgn * band1]
        pond = (min(sgn * band0, sgn * band1), pond_a, max(sgn * band0, sgn * band1), pond_a + pond_len)
    xs = np.unique(np.round(np.array(lines + extra_x), 6))
    ys = np.unique(np.round(np.array(lines + extra_y), 6))

    def kind_of(v):
        if v < -E_net or v > E_net:
            return "outer"
        return "road" if np.any(np.abs(v - c) < hw) else "block"

    mx_, my_ = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
    kx, ky = [kind_of(v) for v in mx_], [kind_of(v) for v in my_]
    lab = np.zeros((len(mx_), len(my_)), np.int32)
    keep = np.ones_like(lab, bool)
    for i, a in enumerate(kx):
        for j, bb in enumerate(ky):
            if a == "outer" or bb == "outer":
                inside_pond = pond[0] < mx_[i] < pond[2] and pond[1] < my_[j] < pond[3]
                lab[i, j] = WATER if inside_pond else TERRAIN
            elif a == "road" or bb == "road":
                lab[i, j] = ROAD
            else:
                keep[i, j] = False
    gv, gf, gcell = plane_grid(xs, ys, 0.0, keep)
    b.add(gv, gf, lab[gcell[:, 0], gcell[:, 1]])

    # ---- road markings, crossings, parked cars (per segment between junctions)
    line_z = 0.012
    crossings = {}
    for axis in (0, 1):  # axis 0: roads along x (y = const); axis 1: roads along y (x = const)
        for ri, rc in enumerate(c):
            for si in range(nb):
                a0, a1 = c[si] + hw, c[si + 1] - hw  # segment extent along the road

                def pt(u, v):  # along-road u, across-road v -> world xy
                    return (u, rc + v) if axis == 0 else (rc + v, u)

                yaw_road = 0.0 if axis == 0 else math.pi / 2
                # zebra crossings at segment ends
                for end, sgn_ in ((a0, 1), (a1, -1)):
                    has = rng.random() < 0.6
                    crossings[(axis, ri, si, sgn_)] = has
                    if has:
                        u_mid = end + sgn_ * 2.25
                        for v in np.arange(-hw + 0.7, hw - 0.4, 1.1):
                            x, y = pt(u_mid, v)
                            b.add_box(x, y, 0.0, *((3.0, 0.5) if axis == 0 else (0.5, 3.0)), line_z, 0.0, ROAD_LINE)
                # dashed centre line and solid lane edge lines
                u0, u1 = a0 + 5.0, a1 - 5.0
                n_d = int((u1 - u0 + 5.0) // 8.0)
                for k in range(n_d):
                    x, y = pt(u0 + k * 8.0 + 1.5, 0.0)
                    b.add_box(x, y, 0.0, *((3.0, 0.15) if axis == 0 else (0.15, 3.0)), line_z, 0.0, ROAD_LINE)
                for v in (-lw, lw):
                    x, y = pt((u0 + u1) / 2, v)
                    b.add_box(x, y, 0.0, *((u1 - u0, 0.12) if axis == 0 else (0.12, u1 - u0)), line_z, 0.0,
                              ROAD_LINE)
                # parked vehicles on both parking strips (facing the traffic of their side)
                for side in (-1, 1):
                    u = a0 + 10.0 + rng.uniform(0.0, 4.0)
                    while u < a1 - 14.0:
                        if rng.random() < 0.55:
                            kind = "car" if rng.random() < 0.85 else "van"
                            m, _ = vehicle_mesh(rng, kind)
                            (lo, hi) = m.bounds[:, 0]
                            length = hi - lo
                            if u + length > a1 - 10.0:
                                break
                            x, y = pt(u + length / 2, side * (lw + pkw / 2))
                            # right-hand traffic: the south (axis 0) / east (axis 1) lane runs along +u
                            along = side < 0 if axis == 0 else side > 0
                            yaw = yaw_road + (0.0 if along else math.pi)
                            b.add(transform(m.vertices, x, y, 0.0, yaw=yaw), m.faces, m.labels)
                            u += length + rng.uniform(0.8, 2.5)
                        else:
                            u += rng.uniform(4.0, 8.0)

    # ---- blocks: slab with sidewalk rim + interior by kind + sidewalk furniture
    kinds = ["park", "towers", "perimeter", "houses"]
    n_blocks = nb * nb
    block_kinds = list(rng.permutation(kinds)) if n_blocks >= 4 else []
    while len(block_kinds) < n_blocks:
        block_kinds.append(str(rng.choice(kinds, p=[0.15, 0.25, 0.35, 0.25])))
    block_kinds = [str(k) for k in rng.permutation(block_kinds)][:n_blocks]
    blocks_meta = []
    for bi in range(nb):
        for bj in range(nb):
            X0, X1 = c[bi] + hw, c[bi + 1] - hw
            Y0, Y1 = c[bj] + hw, c[bj + 1] - hw
            inner = (X0 + sw, Y0 + sw, X1 - sw, Y1 - sw)
            kind = block_kinds[bi * nb + bj]
            occ = _Occupancy()
            rects, default = _BLOCK_KINDS[kind](T, occ, inner, ch)
            blocks_meta.append({"kind": kind, "rect": (X0, Y0, X1, Y1), "inner": inner})
            bxs = [X0, inner[0], inner[2], X1] + [r[k] for r in rects for k in (0, 2)]
            bys = [Y0, inner[1], inner[3], Y1] + [r[k] for r in rects for k in (1, 3)]
            bxs = np.unique(np.round(np.clip(bxs, inner[0], inner[2]).tolist() + [X0, X1], 6))
            bys = np.unique(np.round(np.clip(bys, inner[1], inner[3]).tolist() + [Y0, Y1], 6))
            sv, sf, part = slab_grid(bxs, bys, 0.0, ch)
            _, _, tcell = plane_grid(bxs, bys, ch)
            cxm, cym = (bxs[:-1] + bxs[1:]) / 2, (bys[:-1] + bys[1:]) / 2
            grid_lab = np.full((len(cxm), len(cym)), default, np.int32)
            CX, CY = np.meshgrid(cxm, cym, indexing="ij")
            for r in rects:
                grid_lab[(CX > r[0]) & (CX < r[2]) & (CY > r[1]) & (CY < r[3])] = r[4]
            rim = (CX < inner[0]) | (CX > inner[2]) | (CY < inner[1]) | (CY > inner[3])
            grid_lab[rim] = SIDEWALK
            slab_lab = np.full(len(sf), SIDEWALK, np.int32)
            slab_lab[:len(tcell)] = grid_lab[tcell[:, 0], tcell[:, 1]]
            b.add(sv, sf, slab_lab)
            _sidewalk_furniture(T, (X0, Y0, X1, Y1), ch, bi, bj, nb)

    # ---- outside the network: border barriers, trees, sheds, utility poles
    _outskirts(T, c, hw, E_net, E, pond)

    static = b.build()

    # ---- ego route and actors
    ego_speed = opt["ego_speed"]
    ego_speed = float(rng.uniform(6.5, 8.5)) if ego_speed is None else float(ego_speed)
    L_ego = ego_speed * dt * (n_frames - 1)
    t = np.arange(n_frames) * dt
    off = -lw / 2  # right-hand lane (left normal points left)
    start = (int(rng.integers(0, nb + 1)), int(rng.integers(0, nb + 1)))
    opts = [d for d in _DIRS if 0 <= start[0] + d[0] <= nb and 0 <= start[1] + d[1] <= nb]
    d0 = opts[int(rng.integers(0, len(opts)))]
    n_seg = int(math.ceil((L_ego + 120.0) / P)) + 3
    walk = _walk(rng, start, d0, n_seg, nb, force_turn_at=1)
    # extend backwards (for the follow vehicle and the oncoming traffic leaving the scene)
    bopts = [d for d in opts if d != d0] or opts
    back = _walk(rng, start, bopts[int(rng.integers(0, len(bopts)))], 2, nb)
    nodes = back[::-1] + walk[1:]
    ego_path = _lane_path(nodes, c, off)
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
    ego_c = np.stack([ex, ey], 1)
    ego_h = np.array([EGO_LENGTH / 2 + 0.4, EGO_WIDTH / 2 + 0.3])  # with a safety margin

    actors: list[Actor] = []
    veh_boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (centres (n,2), yaw (n,), half (2,))

    def try_add(mesh, poses, tag, check_vehicles=True):
        off_c, half = _footprint(mesh)
        cen = _world_centre(poses, off_c)
        if np.any(_obb_overlap(ego_c, eyaw, ego_h, cen, poses[:, 5], half)):
            return False
        if check_vehicles:
            for oc, oy, oh in veh_boxes:
                if np.any(_obb_overlap(oc, oy, oh + 0.3, cen, poses[:, 5], half)):
                    return False
            veh_boxes.append((cen, poses[:, 5], half))
        actors.append(Actor(mesh, poses, tag))
        return True

    def poses_on(path, s, z=0.0):
        x, y, yaw = path.at(s)
        p = np.zeros((len(s), 6))
        p[:, 0], p[:, 1], p[:, 2], p[:, 5] = x, y, z, yaw
        return p

    # lead and follow vehicles in the ego lane
    lead, _ = vehicle_mesh(rng, str(rng.choice(["car", "car", "van"])))
    try_add(lead, poses_on(ego_path, s_ego + rng.uniform(14.0, 24.0) + ego_speed * rng.uniform(-0.1, 0.1) * t),
            "lead")
    follow, _ = vehicle_mesh(rng, "car")
    try_add(follow, poses_on(ego_path, s_ego - rng.uniform(13.0, 22.0)), "follow")
    # oncoming traffic: the reversed walk in the opposite lane, meeting the ego
    onc_path = _lane_path(nodes[::-1], c, off)
    n_onc = int(opt["n_oncoming"])
    meet = np.linspace(0.15, 0.85, max(n_onc, 1)) * max(n_frames - 1, 0)
    for k in range(n_onc):
        for attempt in range(12):
            fm = int(np.clip(round(meet[k] + rng.uniform(-3, 3)), 0, n_frames - 1))
            v = rng.uniform(6.0, 10.0)
            est = onc_path.length - s_ego[fm]  # the reversed walk: arc lengths run backwards
            s_m = onc_path.nearest_s(ego_c[fm], est - 40.0, est + 40.0)
            s = s_m + v * (t - t[fm])
            m, kind = vehicle_mesh(rng)
            if try_add(m, poses_on(onc_path, s), "oncoming"):
                break
    # random traffic
    T_total = t[-1] if n_frames > 1 else 0.0
    for k in range(int(opt["n_traffic"])):
        for attempt in range(12):
            st = (int(rng.integers(0, nb + 1)), int(rng.integers(0, nb + 1)))
            dd = [d for d in _DIRS if 0 <= st[0] + d[0] <= nb and 0 <= st[1] + d[1] <= nb]
            d0 = dd[int(rng.integers(0, len(dd)))]
            v = rng.uniform(5.0, 11.0)
            nseg = int(math.ceil((v * T_total + 2 * P) / P)) + 1
            path = _lane_path(_walk(rng, st, d0, nseg, nb), c, off)
            s = rng.uniform(hw + 3.0, P - hw) + v * t
            m, kind = vehicle_mesh(rng)
            if try_add(m, poses_on(path, s), "vehicle"):
                break
    # pedestrians on the sidewalk rims; half of them around blocks next to the ego route
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
            path = _fillet(np.concatenate([ring] * laps + [ring[:1]]), 1.0, 0.2)
            s = rng.uniform(0.0, path.length / laps) + v * t
            poses = poses_on(path, s, ch)
            xy = poses[:, :2]
            if any(np.any(np.linalg.norm(xy - q, axis=1) < 0.9) for q in peds):
                continue
            if try_add(pedestrian_mesh(rng), poses, "pedestrian", check_vehicles=False):
                peds.append(xy)
                break

    meta = {
        "roads": {"centres": c.copy(), "half_width": hw, "lane_width": lw, "parking_width": pkw,
                  "sidewalk_width": sw, "curb_height": ch},
        "bounds": static.bounds,
        "blocks": blocks_meta,
        "route": nodes,
        "ego_speed": ego_speed,
        "ego_path_s": s_ego,
        "pond": pond,
    }
    return Scene(static=static, ego_poses=ego_poses, actors=actors, name="town", seed=seed,
                 frame_interval=dt, meta=meta)


def _sidewalk_furniture(T: _Town, rect, z0, bi, bj, nb):
    """Street trees, lamps, benches, bins, hydrants, signs and traffic lights in the curb zone of a block."""
    rng = T.rng
    X0, Y0, X1, Y1 = rect
    # sides: start corner, direction along, inward normal (into the block)
    sides = [((X0, Y0), (1.0, 0.0), (0.0, 1.0), X1 - X0), ((X1, Y0), (0.0, 1.0), (-1.0, 0.0), Y1 - Y0),
             ((X1, Y1), (-1.0, 0.0), (0.0, -1.0), X1 - X0), ((X0, Y1), (0.0, -1.0), (1.0, 0.0), Y1 - Y0)]
    for (sx, sy), (tx, ty), (nx, ny), S in sides:
        used: list[tuple[float, float]] = []

        def take(u, half):
            if any(abs(u - a) < half + h for a, h in used):
                return False
            used.append((u, half))
            return True

        def at(u, dlt):
            return sx + tx * u + nx * dlt, sy + ty * u + ny * dlt

        out_yaw = math.atan2(-ny, -nx)  # facing the road
        if rng.random() < 0.75:  # street trees
            u = rng.uniform(8.0, 12.0)
            while u < S - 8.0:
                if take(u, 1.0):
                    T.tree(*at(u, 0.8), z0, rng.uniform(0.8, 1.1), trunk_min=3.0, crown_max=2.2)
                u += rng.uniform(9.0, 14.0)
        u = rng.uniform(12.0, 20.0)
        while u < S - 10.0:  # lamps
            if take(u, 0.5):
                T.lamp(*at(u, 0.45), z0, out_yaw)
            u += rng.uniform(22.0, 30.0)
        for _ in range(int(rng.integers(0, 3))):
            u = rng.uniform(8.0, S - 8.0)
            if take(u, 1.1):
                x, y = at(u, 0.9)
                T.bench(x, y, z0, math.atan2(ty, tx))  # backrest on the building side
                if take(u + 1.6, 0.4):
                    T.bin(*at(u + 1.6, 0.7), z0)
        for _ in range(int(rng.integers(0, 2))):
            u = rng.uniform(8.0, S - 8.0)
            if take(u, 0.4):
                T.hydrant(*at(u, 0.5), z0)
        if rng.random() < 0.4:  # a mid-block sign (parking, speed limit)
            u = rng.uniform(15.0, S - 15.0)
            if take(u, 0.6):
                T.sign(*at(u, 0.4), z0, math.atan2(-ty, -tx), str(rng.choice(["round", "rect"])))
        # near the start corner: a sign facing the traffic (moving along -t) that approaches the junction
        if rng.random() < 0.45:
            u = rng.uniform(3.0, 4.5)
            if take(u, 0.5):
                T.sign(*at(u, 0.45), z0, math.atan2(ty, tx))
    # traffic lights at the four corners (arms over the adjacent roads)
    corners = [((X0, Y0), (1, 1)), ((X1, Y0), (-1, 1)), ((X1, Y1), (-1, -1)), ((X0, Y1), (1, -1))]
    for (cx, cy), (ix, iy) in corners:
        if rng.random() < 0.55:
            px, py = cx + ix * 0.6, cy + iy * 0.6
            arm = (-ix, 0.0) if rng.random() < 0.5 else (0.0, -iy)
            T.traffic_light(px, py, z0, arm, rng.uniform(4.0, 5.5))


def _outskirts(T: _Town, c, hw, E_net, E, pond):
    rng = T.rng
    occ = _Occupancy()
    occ.add(-E_net - 3.0, -E_net - 3.0, E_net + 3.0, E_net + 3.0)
    occ.add(pond[0] - 1.5, pond[1] - 1.5, pond[2] + 1.5, pond[3] + 1.5)
    e = E_net + 0.5
    kinds = list(rng.permutation(["guard", "guard", "wall", "fence"]))
    sides = [((-e, -e), (e, -e)), ((e, -e), (e, e)), ((e, e), (-e, e)), ((-e, e), (-e, -e))]
    for (p0, p1), k in zip(sides, kinds):
        if k == "guard":
            T.guard_rail(p0, p1)
        elif k == "wall":  # noise barrier, in 12 m panels
            p0, p1 = np.array(p0), np.array(p1)
            n = int(math.ceil(np.linalg.norm(p1 - p0) / 12.0))
            for q in range(n):
                T.wall(p0 + (p1 - p0) * q / n, p0 + (p1 - p0) * (q + 1) / n, 0.0, 2.8, 0.3)
        else:
            T.fence(p0, p1, 0.0, 1.8, spacing=3.0)
    # utility poles with signs along one side
    side = int(rng.integers(0, 4))
    p0, p1 = np.array(sides[side][0], float), np.array(sides[side][1], float)
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    out = np.array([d[1], -d[0]])  # the loop is counter-clockwise, so the outside is on the right
    for u in np.arange(15.0, np.linalg.norm(p1 - p0) - 10.0, 35.0):
        q = p0 + d * u + out * 1.5
        T.cylinder(q[0], q[1], 0.0, 0.14, 8.0, POLE, 8)
        T.b.add_box(q[0], q[1], 7.2, 0.12, 1.8, 0.12, math.atan2(d[1], d[0]), POLE)
    # a few sheds on the terrain
    band = (-E + 4, -E + 4, E - 4, E - 4)
    for _ in range(3):
        for _ in range(20):
            w, dd = rng.uniform(10, 24), rng.uniform(8, 16)
            x, y = rng.uniform(band[0] + w, band[2] - w), rng.uniform(band[1] + w, band[3] - w)
            r = max(w, dd) / 2 + 2.0
            if occ.free(x, y, r):
                occ.add(x - r, y - r, x + r, y + r)
                T.building(x, y, 0.0, w, dd, rng.uniform(4.0, 8.0), 0.0, "box")
                break
    for x, y in _scatter(rng, occ, band, 70, 2.5, tries=15):
        T.tree(x, y, 0.0, rng.uniform(0.8, 1.4))
    for x, y in _scatter(rng, occ, band, 15, 2.0, tries=15):
        T.hedge(x, y, 0.0, rng.uniform(2.0, 6.0), rng.uniform(1.0, 2.0), rng.uniform(0.8, 2.0),
                rng.uniform(0, math.pi))
