"""Static props shared by the scene builders: buildings, houses, trees, street furniture, barriers."""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.bodies import template, vehicle_body
from place3d_kernels.scene.primitives import MeshBuilder, gable_roof

__all__ = ["Props"]

C = CLASS_ID
BUILDING, FENCE, PEDESTRIAN, POLE, ROAD_LINE, ROAD, SIDEWALK = (
    C["building"], C["fence"], C["pedestrian"], C["pole"], C["road line"], C["road"], C["sidewalk"])
VEGETATION, VEHICLE, WALL, SIGN, GROUND, GUARD_RAIL, LIGHT, STATIC, WATER, TERRAIN = (
    C["vegetation"], C["vehicle"], C["wall"], C["traffic sign"], C["ground"], C["guard rail"],
    C["traffic light"], C["static"], C["water"], C["terrain"])


class Props:
    """Static geometry builder with helpers for every kind of object.

    Attributes:
        rng: the generator every size and style is drawn from (call order is part of the output).
        b: the MeshBuilder collecting the labelled solids.
        opt: the builder options (unused by the helpers themselves).
    """

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
        pv, pf = template("prism6")
        self.b.add_moved(pv, pf, VEGETATION, x, y, z0, scale=(tr, tr, th + 0.3))
        cr = rng.uniform(1.4, 2.6) * scale
        if crown_max is not None:
            cr = min(cr, crown_max)
        cz = rng.uniform(0.9, 1.4)
        iv, if_ = template("ico1")
        self.b.add_moved(iv, if_, VEGETATION, x, y, z0 + th + cr * cz, yaw=rng.uniform(0, 6.3),
                         scale=(cr, cr * rng.uniform(0.85, 1.0), cr * cz))
        if rng.random() < 0.35:  # a second, smaller blob on top
            c2 = cr * 0.7
            self.b.add_moved(iv, if_, VEGETATION, x + rng.uniform(-0.4, 0.4) * (cr - c2),
                             y + rng.uniform(-0.4, 0.4) * (cr - c2), z0 + th + cr * cz * 1.7, scale=(c2, c2, c2 * cz))

    def cylinder(self, x, y, z0, r, h, label, n=8):
        pv, pf = template(f"prism{n}")
        self.b.add_moved(pv, pf, label, x, y, z0, scale=(r, r, h))

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
            pv, pf = template("prism8")
            v = pv.copy()
            v[:, :2] *= 0.33
            v[:, 2] = (v[:, 2] - 0.5) * 0.04
            # turn the plate's axis from z to x (rotation about y by +90 deg), so it faces along yaw
            v = np.stack([v[:, 2], v[:, 1], -v[:, 0]], 1)
            self.b.add_moved(v, pf, SIGN, x + ox, y + oy, z0 + 2.5, yaw=yaw)
        elif shape == "tri":
            rv, rf = gable_roof(0.04, 0.8, 0.7)  # a thin triangular prism, base at z = 0
            self.b.add_moved(rv, rf, SIGN, x + ox, y + oy, z0 + 2.2, yaw=yaw)
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
        m, _ = vehicle_body(self.rng, kind)
        self.b.add_moved(m.vertices, m.faces, m.labels, x, y, z0, yaw=yaw)

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
        self.b.add_moved(rv, rf, BUILDING, x, y, z0 + h, yaw=yaw)
        if rng.random() < 0.5:  # chimney
            c, s = math.cos(yaw), math.sin(yaw)
            lx, ly = rng.uniform(-0.3, 0.3) * w, rng.uniform(-0.25, 0.25) * d
            self.b.add_box(x + c * lx - s * ly, y + s * lx + c * ly, z0 + h, 0.6, 0.6, 2.6, yaw, BUILDING)
