"""The town's ground and roads: terrain with a pond, road surfaces and markings, parked cars, block slabs."""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.bodies import vehicle_body
from place3d_kernels.scene.primitives import plane_grid, slab_grid
from place3d_kernels.scene.props import Props
from place3d_kernels.scene.town_blocks import BLOCK_KINDS, Occupancy
from place3d_kernels.scene.town_furniture import sidewalk_furniture

__all__ = ["ground", "road_markings", "blocks"]

C = CLASS_ID
ROAD_LINE, ROAD, SIDEWALK, TERRAIN, WATER = C["road line"], C["road"], C["sidewalk"], C["terrain"], C["water"]


def ground(T: Props, c, hw, E_net, E):
    """Ground at z = 0: road cells and the outer terrain with a pond; block cells are left to the slabs.

    Returns:
        the pond rectangle (x0, y0, x1, y1).
    """
    rng, b = T.rng, T.b
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
    return pond


def road_markings(T: Props, c, nb, hw, lw, pkw):
    """Zebra crossings, centre and edge lines, and parked cars, per road segment between junctions."""
    rng, b = T.rng, T.b
    line_z = 0.012
    for axis in (0, 1):  # axis 0: roads along x (y = const); axis 1: roads along y (x = const)
        for rc in c:
            for si in range(nb):
                a0, a1 = c[si] + hw, c[si + 1] - hw  # segment extent along the road

                def pt(u, v):  # along-road u, across-road v -> world xy
                    return (u, rc + v) if axis == 0 else (rc + v, u)

                yaw_road = 0.0 if axis == 0 else math.pi / 2
                # zebra crossings at segment ends
                for end, sgn_ in ((a0, 1), (a1, -1)):
                    if rng.random() < 0.6:
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
                    _parking_strip(T, pt, a0, a1, side * (lw + pkw / 2), yaw_road,
                                   side < 0 if axis == 0 else side > 0)


def _parking_strip(T: Props, pt, a0, a1, v, yaw_road, along):
    """Parked cars and vans along one parking strip at lateral offset ``v``; ``along``: they face +u."""
    rng, b = T.rng, T.b
    u = a0 + 10.0 + rng.uniform(0.0, 4.0)
    while u < a1 - 14.0:
        if rng.random() < 0.55:
            kind = "car" if rng.random() < 0.85 else "van"
            m, _ = vehicle_body(rng, kind)
            (lo, hi) = m.bounds[:, 0]
            length = hi - lo
            if u + length > a1 - 10.0:
                break
            x, y = pt(u + length / 2, v)
            # right-hand traffic: the south (axis 0) / east (axis 1) lane runs along +u
            yaw = yaw_road + (0.0 if along else math.pi)
            b.add_moved(m.vertices, m.faces, m.labels, x, y, 0.0, yaw=yaw)
            u += length + rng.uniform(0.8, 2.5)
        else:
            u += rng.uniform(4.0, 8.0)


def blocks(T: Props, c, nb, hw, sw, ch):
    """Every block: a slab whose rim is sidewalk, an interior by kind, and sidewalk furniture.

    Returns:
        one dict per block: ``kind``, ``rect`` (x0, y0, x1, y1) and ``inner`` (inside the sidewalk).
    """
    rng, b = T.rng, T.b
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
            rects, default = BLOCK_KINDS[kind](T, Occupancy(), inner, ch)
            blocks_meta.append({"kind": kind, "rect": (X0, Y0, X1, Y1), "inner": inner})
            b.add(*_slab(X0, Y0, X1, Y1, inner, rects, default, ch))
            sidewalk_furniture(T, (X0, Y0, X1, Y1), ch, bi, bj, nb)
    return blocks_meta


def _slab(X0, Y0, X1, Y1, inner, rects, default, ch):
    """A block slab (top at ``ch``) gridded on the interior rectangles, top cells labelled by them."""
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
    return sv, sf, slab_lab
