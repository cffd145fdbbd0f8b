"""Sidewalk furniture of the town's blocks and the outskirts around its road network."""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.props import Props
from place3d_kernels.scene.town_blocks import Occupancy, scatter

__all__ = ["sidewalk_furniture", "outskirts"]

POLE = CLASS_ID["pole"]


def sidewalk_furniture(T: Props, rect, z0, bi, bj, nb):
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


def outskirts(T: Props, c, hw, E_net, E, pond):
    """Border barriers, utility poles, sheds, trees and hedges on the terrain outside the road network."""
    rng = T.rng
    occ = Occupancy()
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
    for x, y in scatter(rng, occ, band, 70, 2.5, tries=15):
        T.tree(x, y, 0.0, rng.uniform(0.8, 1.4))
    for x, y in scatter(rng, occ, band, 15, 2.0, tries=15):
        T.hedge(x, y, 0.0, rng.uniform(2.0, 6.0), rng.uniform(1.0, 2.0), rng.uniform(0.8, 2.0),
                rng.uniform(0, math.pi))
