"""The interiors of the procedural town's blocks: perimeter, towers, park and houses."""

from __future__ import annotations

import math

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.props import Props

__all__ = ["Occupancy", "scatter", "BLOCK_KINDS"]

C = CLASS_ID
BUILDING, FENCE, PEDESTRIAN, POLE, ROAD_LINE, ROAD, SIDEWALK = (
    C["building"], C["fence"], C["pedestrian"], C["pole"], C["road line"], C["road"], C["sidewalk"])
VEGETATION, VEHICLE, WALL, SIGN, GROUND, GUARD_RAIL, LIGHT, STATIC, WATER, TERRAIN = (
    C["vegetation"], C["vehicle"], C["wall"], C["traffic sign"], C["ground"], C["guard rail"],
    C["traffic light"], C["static"], C["water"], C["terrain"])


class Occupancy:
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


def scatter(rng, occ: Occupancy, rect, n, rad, tries=30):
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
def _block_perimeter(T: Props, occ, inner, z0):
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
    for x, y in scatter(rng, occ, (cx0, cy0, cx1, cy1), int(rng.integers(4, 9)), 2.5):
        T.tree(x, y, z0)
    for x, y in scatter(rng, occ, (cx0, cy0, cx1, cy1), int(rng.integers(2, 5)), 2.0):
        T.hedge(x, y, z0, rng.uniform(2.0, 4.0), rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.5),
                rng.choice([0.0, math.pi / 2]))
    return rects, TERRAIN


def _block_towers(T: Props, occ, inner, z0):
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
            for x, y in scatter(rng, occ, (qx0 + 3, qy0 + 3, qx1 - 3, qy1 - 3), int(rng.integers(4, 8)), 2.5):
                T.tree(x, y, z0)
    # planters, low walls, benches, bollards, lamps on the plaza
    for x, y in scatter(rng, occ, inner, int(rng.integers(4, 9)), 2.2):
        if rng.random() < 0.5:
            T.hedge(x, y, z0, rng.uniform(2.0, 3.5), rng.uniform(1.0, 2.0), rng.uniform(0.6, 1.1))
        else:
            T.wall((x - 1.5, y), (x + 1.5, y), z0, rng.uniform(0.5, 1.0), 0.4)
    for x, y in scatter(rng, occ, inner, int(rng.integers(2, 5)), 1.2):
        T.bench(x, y, z0, rng.choice([0.0, math.pi / 2]))
    for x, y in scatter(rng, occ, inner, int(rng.integers(3, 7)), 0.5):
        T.bollard(x, y, z0)
    for x, y in scatter(rng, occ, inner, 3, 0.8):
        T.lamp(x, y, z0, rng.uniform(0, 2 * math.pi))
    return rects, GROUND


def _block_park(T: Props, occ, inner, z0):
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
    for x, y in scatter(rng, occ, inner, int(rng.integers(25, 40)), 2.2):
        T.tree(x, y, z0, rng.uniform(0.8, 1.25))
    for x, y in scatter(rng, occ, inner, int(rng.integers(6, 12)), 1.8):
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


def _block_houses(T: Props, occ, inner, z0):
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
                spots = scatter(rng, occ, lot, 1, 3.0)
                if spots:
                    px, py = spots[0]
                    rects.append((px - 2.8, py - 2.8, px + 2.8, py + 2.8, GROUND))
                    T.vehicle(px, py, rng.choice([0.0, math.pi / 2]), "car", z0)
            for x, y in scatter(rng, occ, lot, int(rng.integers(0, 3)), 2.0):
                T.tree(x, y, z0, rng.uniform(0.7, 1.0))
    return rects, TERRAIN


BLOCK_KINDS = {"perimeter": _block_perimeter, "towers": _block_towers, "park": _block_park,
                "houses": _block_houses}
