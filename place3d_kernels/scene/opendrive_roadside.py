"""Roadside content of OpenDRIVE towns: an occupancy raster, street furniture, parked cars, buildings, trees."""

from __future__ import annotations

import math

import numpy as np

from place3d_kernels.scene.bodies import Body, vehicle_body
from place3d_kernels.scene.opendrive_routes import Route
from place3d_kernels.scene.props import Props

__all__ = ["Raster", "RoadDistance", "road_area_points", "roadside", "fill", "edge_frame", "edge_geometry", "route_parking"]


class Raster:
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

    def _rect_cells(self, x, y, w, d, yaw, pad):
        """The cells (i, j) of the rectangle's sample points: a grid of half-cell steps over the padded
        rectangle and its far edges, rotated by ``yaw`` about (x, y). Computed as one broadcast pair of
        (u, v) arrays instead of stacked point arrays (a town tries thousands of rectangles): each point's
        sums and products are the ones the stacked form made, so its cells are too. Index arrays (flat, or a
        column and a row for an unrotated rectangle) for ``occ[i, j]``."""
        u = np.append(np.arange(-w / 2 - pad, w / 2 + pad + 1e-9, self.cell * 0.5), w / 2 + pad)[:, None]
        v = np.append(np.arange(-d / 2 - pad, d / 2 + pad + 1e-9, self.cell * 0.5), d / 2 + pad)[None, :]
        if yaw == 0.0:
            # cos 0 = 1 and sin 0 = 0 exactly, so x + u - 0 v and y + 0 u + v are x + u and y + v: a point's row
            # depends on u alone and its column on v alone, and the cells are every (row, column) pair. They are
            # returned as a column and a row that index the same cells by broadcasting.
            i = np.floor((x + u - self.lo[0]) / self.cell).astype(np.int64)
            j = np.floor((y + v - self.lo[1]) / self.cell).astype(np.int64)
            return i, j
        c, s = math.cos(yaw), math.sin(yaw)
        px = (x + c * u) - s * v
        py = (y + s * u) + c * v
        i = np.floor((px.ravel() - self.lo[0]) / self.cell).astype(np.int64)
        j = np.floor((py.ravel() - self.lo[1]) / self.cell).astype(np.int64)
        return i, j

    def _inside(self, i, j) -> bool:
        return not (i.min() < 0 or j.min() < 0 or i.max() >= self.shape[0] or j.max() >= self.shape[1])

    def _free_cells(self, x, y, w, d, yaw, pad):
        """The rectangle's cells when it is inside the raster and free, else None (see ``free``)."""
        # cheap rejection on the centre and the corners first, in scalars: the same float64 operations
        # as on arrays of the five points, without building them
        c, s = math.cos(yaw), math.sin(yaw)
        a, b = w / 2 + pad, d / 2 + pad
        lo0, lo1, cell = float(self.lo[0]), float(self.lo[1]), self.cell
        nx, ny = self.shape[0], self.shape[1]
        occ = self.occ
        # (one pass: a point outside the raster or on a taken cell refuses the rectangle either way)
        for qx, qy in ((x, y), (x + c * a - s * b, y + s * a + c * b), (x - c * a - s * b, y - s * a + c * b),
                       (x + c * a + s * b, y + s * a - c * b), (x - c * a + s * b, y - s * a - c * b)):
            fi, fj = (qx - lo0) / cell, (qy - lo1) / cell
            if not (math.isfinite(fi) and math.isfinite(fj)):
                return None
            qi, qj = math.floor(fi), math.floor(fj)
            if qi < 0 or qj < 0 or qi >= nx or qj >= ny or occ[qi, qj]:
                return None
        i, j = self._rect_cells(x, y, w, d, yaw, pad)
        if not self._inside(i, j) or occ[i, j].any():
            return None
        return i, j

    def free(self, x, y, w, d, yaw, pad=0.5):
        return self._free_cells(x, y, w, d, yaw, pad) is not None

    def take(self, x, y, w, d, yaw, pad=0.5):
        cells = self._free_cells(x, y, w, d, yaw, pad)
        if cells is None:
            return False
        self.occ[cells] = True          # inside the raster, as _free_cells found
        return True


def road_area_points(static_parts, spacing=0.5):
    """Points covering every meshed lane triangle (vertices + barycentric samples), for the raster."""
    v, f, lab = static_parts
    tri = v[f]
    pts = [v[:, :2]]
    for a, b in ((1 / 3, 1 / 3), (0.5, 0.25), (0.25, 0.5), (0.25, 0.25), (0.5, 0.5), (0.0, 0.5), (0.5, 0.0)):
        pts.append((tri[:, 0] * (1 - a - b) + tri[:, 1] * a + tri[:, 2] * b)[:, :2])
    return np.concatenate(pts)


def _box_of(m: Body, x, y, z, yaw):
    """World (x, y, z, l, w, h, yaw) box of mesh ``m`` posed at (x, y, z, yaw); z = box centre."""
    lo, hi = m.bounds
    c = (lo + hi) / 2
    cs, sn = math.cos(yaw), math.sin(yaw)
    return [x + cs * c[0] - sn * c[1], y + sn * c[0] + cs * c[1], z + c[2], *(hi - lo).tolist(), yaw]


def roadside(T: Props, rng, raster: Raster, edges, lanes, height_at, opt, boxes, geometry=None):
    """Street furniture, buildings, trees and parked cars next to the outer lane edges (``geometry``: each
    edge's ``edge_geometry``, or None to make them here)."""
    parked = 0
    # parked cars on parking lanes
    for ltype, junc, pts, width, rid in lanes:
        if ltype != "parking" or junc:
            continue
        r = Route(pts)
        u = rng.uniform(1.0, 5.0)
        while u < r.length - 5.0:
            if rng.random() < 0.6:
                m, _ = vehicle_body(rng, "car" if rng.random() < 0.85 else "van")
                L = float(m.bounds[1, 0] - m.bounds[0, 0])
                p = r.poses([u + L / 2])[0]
                T.b.add_moved(m.vertices, m.faces, m.labels, p[0], p[1], p[2], yaw=p[5])
                boxes.append(_box_of(m, p[0], p[1], p[2], p[5]))
                parked += 1
                u += L + rng.uniform(0.8, 2.5)
            else:
                u += rng.uniform(4.0, 9.0)
    for k, e in enumerate(edges):
        frame = edge_frame(e, raster, None if geometry is None else geometry[k])
        if frame is None:
            continue
        s, pose, nrm = frame
        u = rng.uniform(2.0, 10.0)
        while u < s[-1] - 2.0:
            x, y, t = pose(u)
            yaw = math.atan2(t[1], t[0])
            n = (-t[1], t[0]) if np.dot([-t[1], t[0]], nrm) > 0 else (t[1], -t[0])
            out_yaw = math.atan2(-n[1], -n[0])  # facing the road
            r = rng.random()
            # the ground height at the edge point, looked up only for an object that is placed
            if r < 0.18:  # lamp just off the edge
                px, py = x + n[0] * 0.6, y + n[1] * 0.6
                if raster.take(px, py, 0.4, 0.4, 0.0, 0.1):
                    T.lamp(px, py, height_at(x, y), out_yaw)
            elif r < 0.26:
                px, py = x + n[0] * 0.5, y + n[1] * 0.5
                if raster.take(px, py, 0.4, 0.4, 0.0, 0.1):
                    T.sign(px, py, height_at(x, y), math.atan2(-t[1], -t[0]))
            elif r < 0.30:
                px, py = x + n[0] * 0.7, y + n[1] * 0.7
                if raster.take(px, py, 0.5, 0.5, 0.0, 0.1):
                    T.traffic_light(px, py, height_at(x, y), (-n[0], -n[1]), rng.uniform(3.5, 5.0))
            elif r < 0.55:  # a tree or hedge a little further out
                off = rng.uniform(2.5, 5.0)
                px, py = x + n[0] * off, y + n[1] * off
                if raster.take(px, py, 2.0, 2.0, 0.0, 0.5):
                    if rng.random() < 0.8:
                        T.tree(px, py, height_at(x, y), rng.uniform(0.8, 1.2))
                    else:
                        T.hedge(px, py, height_at(x, y), rng.uniform(2.0, 4.0), 1.0, rng.uniform(0.8, 1.6), yaw)
            elif r < 0.85:  # a building set back from the road
                w, dd = rng.uniform(8.0, 20.0), rng.uniform(8.0, 16.0)
                off = rng.uniform(4.0, 9.0) + dd / 2
                px, py = x + n[0] * off, y + n[1] * off
                if raster.take(px, py, w, dd, yaw, 1.0):
                    T.building(px, py, height_at(x, y), w, dd, rng.uniform(5.0, 22.0), yaw)
                    u += w / 2
            elif r < 0.9 and parked < 400:  # a car parked beside the road
                m, _ = vehicle_body(rng, "car")
                px, py = x + n[0] * 2.2, y + n[1] * 2.2
                if raster.take(px, py, 4.8, 2.0, yaw, 0.3):
                    z0 = height_at(x, y)
                    T.b.add_moved(m.vertices, m.faces, m.labels, px, py, z0, yaw=yaw)
                    boxes.append(_box_of(m, px, py, z0, yaw))
                    parked += 1
            u += rng.uniform(5.0, 12.0)
    return parked


def edge_geometry(e):
    """(segment vectors, their lengths, arc lengths) of an edge polyline, or None for fewer than 2 points: the
    part of ``edge_frame`` that depends on the edge alone (a town's base makes it once for all its routes)."""
    if len(e) < 2:
        return None
    d = np.diff(e[:, :2], axis=0)
    seg = np.linalg.norm(d, axis=1)
    return d, seg, np.r_[0.0, np.cumsum(seg)]


def edge_frame(e, raster: Raster, geometry=None):
    """Arc lengths, a pose function u -> (x, y, unit tangent) and the outward normal of an outer lane edge;
    None for an edge shorter than 6 m or an inner edge (road on both sides, per the raster). ``geometry``:
    ``edge_geometry(e)`` made already (None: made here)."""
    g = edge_geometry(e) if geometry is None else geometry
    if g is None:
        return None
    d, seg, s = g
    if s[-1] < 6.0:
        return None

    ex, ey = np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1])     # np.interp copies a strided column

    def pose(u):
        # Python floats out: the placement loops' scalar arithmetic on them is NumPy's on float64 scalars, faster
        x = float(np.interp(u, s, ex))
        y = float(np.interp(u, s, ey))
        k = min(int(np.searchsorted(s, u, side="right")) - 1, len(d) - 1)
        k = max(k, 0)
        t = d[k] / max(seg[k], 1e-9)
        return x, y, (float(t[0]), float(t[1]))

    # the outward side: edges are polylines of the outer lane border; the outward normal points
    # away from the road, found from the raster (the side that is free)
    x, y, t = pose(s[-1] / 2)
    nrm = np.array([-t[1], t[0]])
    probe = np.array([[x + nrm[0] * 2.0, y + nrm[1] * 2.0], [x - nrm[0] * 2.0, y - nrm[1] * 2.0]])
    ij = raster.idx(probe)
    ij = np.clip(ij, 0, np.array(raster.shape) - 1)
    occ = raster.occ[ij[:, 0], ij[:, 1]]
    if occ[0] and occ[1]:
        return None
    return s, pose, (-nrm if occ[0] else nrm)


def route_parking(T: Props, rng, raster: Raster, edges, route_xy, height_at, boxes, reach=60.0, geometry=None):
    """Cars parked beside the outer road edges within ``reach`` metres of the ego route.

    The roadside pass parks a car beside an edge rarely and anywhere on the map, so on a long map (Town06,
    7 km of road) the ego could drive past none; this pass parks one every 5-15 m along the route's
    stretch of each edge, where the raster is free (after buildings and trees took their places).

    ``geometry``: each edge's ``edge_geometry``, or None to make them here.

    Returns:
        the number of cars parked.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(route_xy)
    parked = 0
    for k, e in enumerate(edges):
        frame = edge_frame(e, raster, None if geometry is None else geometry[k])
        if frame is None:
            continue
        s, pose, nrm = frame
        near = tree.query(e[:, :2], distance_upper_bound=reach)[0] < reach
        if not near.any():
            continue
        u, u_end = s[np.argmax(near)], s[len(near) - 1 - np.argmax(near[::-1])]
        u += rng.uniform(0.0, 6.0)
        while u < u_end:
            x, y, t = pose(u)
            yaw = math.atan2(t[1], t[0])
            n = (-t[1], t[0]) if np.dot([-t[1], t[0]], nrm) > 0 else (t[1], -t[0])
            m, _ = vehicle_body(rng, "car" if rng.random() < 0.85 else "van")
            lo, hi = m.bounds
            px, py = x + n[0] * 2.2, y + n[1] * 2.2
            if rng.random() < 0.7 and raster.take(px, py, hi[0] - lo[0], hi[1] - lo[1], yaw, 0.3):
                z0 = height_at(px, py)
                T.b.add_moved(m.vertices, m.faces, m.labels, px, py, z0, yaw=yaw)
                boxes.append(_box_of(m, px, py, z0, yaw))
                parked += 1
            u += rng.uniform(5.0, 15.0)
    return parked


class RoadDistance:
    """The distance (in cells) from every raster cell to the nearest road cell and that cell's index, and the
    cells of distance bands: what ``fill`` draws from. A function of the road raster alone, so a town's base
    makes it once for all its routes (``opendrive._TownBase.road_distance``); read-only."""

    def __init__(self, road_mask: np.ndarray):
        from scipy import ndimage

        self.dist, (self.ni, self.nj) = ndimage.distance_transform_edt(~road_mask, return_indices=True)
        for a in (self.dist, self.ni, self.nj):
            a.setflags(write=False)
        self._bands: dict = {}

    def band(self, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
        """The cells (i, j) whose distance lies in [lo, hi] cells, in row-major order."""
        key = (lo, hi)
        if key not in self._bands:
            ii, jj = np.nonzero((self.dist >= lo) & (self.dist <= hi))
            ii.setflags(write=False)
            jj.setflags(write=False)
            self._bands[key] = (ii, jj)
        return self._bands[key]


def fill(T: Props, rng, raster: Raster, field: RoadDistance, heights_at, density: float):
    """Buildings and trees in the free space between the roads, facing the nearest road (``field``: the road
    raster's ``RoadDistance``; ``heights_at(x, y)``: the ground heights at arrays of points)."""
    dist, ni, nj = field.dist, field.ni, field.nj
    free_area = float((dist > 3.0).sum()) * raster.cell ** 2
    lo, cell = raster.lo, raster.cell

    def sample(dmin, dmax, n):
        """Cells drawn in the band, their centres and the ground heights there (all looked up in one query)."""
        ii, jj = field.band(dmin / cell, dmax / cell)
        if len(ii) == 0:
            return []
        k = rng.integers(0, len(ii), size=n)
        ii, jj = ii[k], jj[k]
        xs, ys = lo[0] + (ii + 0.5) * cell, lo[1] + (jj + 0.5) * cell
        return list(zip(ii, jj, xs.tolist(), ys.tolist(), heights_at(xs, ys).tolist()))

    for i, j, x, y, z0 in sample(5.0, 45.0, int(density * free_area / 250.0)):
        dx, dy = (ni[i, j] - i) * cell, (nj[i, j] - j) * cell
        yaw = math.atan2(dy, dx) + math.pi / 2  # the long side along the road
        w, dd = rng.uniform(10.0, 26.0), rng.uniform(8.0, 18.0)
        if dist[i, j] * cell < dd / 2 + 1.5:
            continue
        if raster.take(x, y, w, dd, yaw, 1.5):
            h = rng.uniform(4.0, 7.0) if rng.random() < 0.3 else rng.uniform(7.0, 30.0)
            T.building(x, y, z0, w, dd, h, yaw)
    for i, j, x, y, z0 in sample(3.0, 80.0, int(density * free_area / 200.0)):
        if raster.take(x, y, 2.0, 2.0, 0.0, 0.8):
            if rng.random() < 0.85:
                T.tree(x, y, z0, rng.uniform(0.8, 1.3))
            else:
                T.hedge(x, y, z0, rng.uniform(2.0, 5.0), rng.uniform(0.8, 1.5), rng.uniform(0.8, 1.8),
                        rng.uniform(0, math.pi))
