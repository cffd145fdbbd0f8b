"""Closed, outward-oriented mesh primitives in plain NumPy.

Every builder returns ``(vertices (V, 3) float64, faces (F, 3) int64)``; callers attach labels. Faces are
wound counter-clockwise seen from outside (normals point out), and every solid is closed (watertight,
Euler characteristic 2), so a watertight ray-triangle test never leaks through a shared edge.

Vectorised builders (:func:`boxes`, :func:`instances`) make thousands of solids in one call.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "boxes", "box", "prism", "icosphere", "gable_roof", "slab_grid", "plane_grid", "instances",
    "transform", "BOX_TRIANGLES", "MeshBuilder",
]

#: triangles in one box
BOX_TRIANGLES = 12

# unit cube corners, index = ix + 2 iy + 4 iz, centred at the origin
_CUBE_V = np.array([[ix - 0.5, iy - 0.5, iz - 0.5] for iz in (0, 1) for iy in (0, 1) for ix in (0, 1)])
_CUBE_F = np.array([
    [0, 2, 1], [1, 2, 3],  # bottom (-z)
    [4, 5, 6], [5, 7, 6],  # top (+z)
    [0, 1, 4], [1, 5, 4],  # front (-y)
    [2, 6, 3], [3, 6, 7],  # back (+y)
    [0, 4, 2], [2, 4, 6],  # left (-x)
    [1, 3, 5], [3, 7, 5],  # right (+x)
], dtype=np.int64)


def boxes(centers, sizes, yaws=None) -> tuple[np.ndarray, np.ndarray]:
    """N closed boxes (8 vertices, 12 triangles each).

    Args:
        centers: (N, 3) box centres.
        sizes: (N, 3) edge lengths along the box's own x, y, z.
        yaws: (N,) rotation about +z in radians (None: axis-aligned).
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    s = np.broadcast_to(np.asarray(sizes, dtype=np.float64), c.shape)
    n = len(c)
    local = _CUBE_V[None, :, :] * s[:, None, :]  # (N, 8, 3)
    if yaws is not None:
        y = np.broadcast_to(np.asarray(yaws, dtype=np.float64), (n,))
        cy, sy = np.cos(y)[:, None], np.sin(y)[:, None]
        x0, y0 = local[..., 0].copy(), local[..., 1].copy()
        local[..., 0] = cy * x0 - sy * y0
        local[..., 1] = sy * x0 + cy * y0
    v = (local + c[:, None, :]).reshape(-1, 3)
    f = (_CUBE_F[None, :, :] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return v, f


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """One axis-aligned closed box between corners ``lo`` and ``hi``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return boxes(((lo + hi) / 2)[None], (hi - lo)[None])


def prism(n_sides: int, radius: float = 1.0, z0: float = 0.0, z1: float = 1.0,
          phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed regular n-gon prism (a low-poly cylinder) along z, 4n - 4 triangles."""
    a = phase + 2 * np.pi * np.arange(n_sides) / n_sides
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    v = np.concatenate([np.c_[ring, np.full(n_sides, z0)], np.c_[ring, np.full(n_sides, z1)]])
    i = np.arange(n_sides)
    j = (i + 1) % n_sides
    side = np.concatenate([np.stack([i, j, n_sides + j], 1), np.stack([i, n_sides + j, n_sides + i], 1)])
    k = np.arange(1, n_sides - 1)
    bottom = np.stack([np.zeros_like(k), k + 1, k], 1)
    top = np.stack([np.full_like(k, n_sides), n_sides + k, n_sides + k + 1], 1)
    return v, np.concatenate([side, bottom, top]).astype(np.int64)


def icosphere(subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere: 20 * 4**subdivisions triangles."""
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        verts = list(v)
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (a, b) if a < b else (b, a)
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        nf = []
        for a, b, c in f.tolist():
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        v, f = np.array(verts), np.array(nf, dtype=np.int64)
    return v, f


def gable_roof(length: float, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangular prism (8 triangles): base [-l/2, l/2] x [-w/2, w/2] at z = 0, ridge along x."""
    l2, w2 = length / 2, width / 2
    v = np.array([[-l2, -w2, 0], [l2, -w2, 0], [l2, w2, 0], [-l2, w2, 0], [-l2, 0, height], [l2, 0, height]])
    f = np.array([[0, 2, 1], [0, 3, 2],  # base (-z)
                  [0, 1, 5], [0, 5, 4],  # -y slope
                  [2, 3, 4], [2, 4, 5],  # +y slope
                  [0, 4, 3], [1, 2, 5]], dtype=np.int64)  # gable ends
    return v, f


def plane_grid(xs, ys, z: float, keep=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An upward-facing rectilinear grid of quads at height ``z`` (an open surface).

    Args:
        xs, ys: increasing cell boundaries (nx+1,), (ny+1,).
        keep: (nx, ny) bool, cells to emit (default all).

    Returns:
        vertices, faces, cell (F, 2) (i, j) of each face's cell.
    """
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    nx, ny = len(xs) - 1, len(ys) - 1
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    if keep is not None:
        keep = np.asarray(keep, bool)
        I, J = I[keep], J[keep]
    I, J = I.ravel(), J.ravel()
    a = I * (ny + 1) + J
    b = (I + 1) * (ny + 1) + J
    c = (I + 1) * (ny + 1) + J + 1
    d = I * (ny + 1) + J + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    cell = np.concatenate([np.stack([I, J], 1)] * 2)
    return v, f.astype(np.int64), cell


def slab_grid(xs, ys, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed rectangular slab between z0 and z1 whose top and bottom are split on a rectilinear grid.

    The side walls are split at the same boundary vertices, so the slab is watertight (no T-junctions).

    Returns:
        vertices, faces, part (F,) int: 0 top, 1 bottom, 2 side; and the top faces come first with the
        cell of each in the order of :func:`plane_grid` (use ``top_cells`` from :func:`plane_grid`).
    """
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    vt, ft, _ = plane_grid(xs, ys, z1)
    vb = vt.copy()
    vb[:, 2] = z0
    nv = len(vt)
    fb = ft[:, ::-1] + nv
    nx, ny = len(xs) - 1, len(ys) - 1

    def vid(i, j):
        return i * (ny + 1) + j

    # boundary loop counter-clockwise seen from above
    loop = ([vid(i, 0) for i in range(nx)] + [vid(nx, j) for j in range(ny)]
            + [vid(i, ny) for i in range(nx, 0, -1)] + [vid(0, j) for j in range(ny, 0, -1)])
    loop = np.array(loop)
    nxt = np.roll(loop, -1)
    # outward side quad: bottom a -> bottom b -> top b -> top a (CCW seen from outside)
    side = np.concatenate([np.stack([loop + nv, nxt + nv, nxt], 1), np.stack([loop + nv, nxt, loop], 1)])
    v = np.concatenate([vt, vb])
    f = np.concatenate([ft, fb, side])
    part = np.concatenate([np.zeros(len(ft), int), np.ones(len(fb), int), np.full(len(side), 2)])
    return v, f, part


def transform(v, x=0.0, y=0.0, z=0.0, yaw=0.0, scale=1.0) -> np.ndarray:
    """Scale (scalar or per-axis), rotate about +z by ``yaw`` and translate vertices."""
    return _Moved.apply([_Moved(v, x, y, z, yaw, scale)], np.array([len(v)]))


class _Moved:
    """A part's vertices ``v`` and the ``transform`` that moves them, kept until ``MeshBuilder.arrays``."""

    __slots__ = ("v", "x", "y", "z", "yaw", "scale")

    def __init__(self, v, x, y, z, yaw, scale):
        self.v, self.x, self.y, self.z, self.yaw, self.scale = v, x, y, z, yaw, scale

    def __len__(self) -> int:
        return len(self.v)

    @staticmethod
    def apply(moved: list, counts: np.ndarray) -> np.ndarray:
        """Every part's moved vertices, one after the other: ``transform``'s products, sums and differences,
        element for element (scaled, then turned, then shifted), for all parts in one pass."""
        v = np.concatenate([np.asarray(m.v, float) for m in moved])
        scale = np.array([(m.scale,) * 3 if np.ndim(m.scale) == 0 else m.scale for m in moved], float)
        v = v * np.repeat(scale, counts, axis=0)
        yaw = np.array([m.yaw for m in moved], float)
        c, s = np.repeat(np.cos(yaw), counts), np.repeat(np.sin(yaw), counts)
        x, y, z = (np.repeat(np.array([getattr(m, k) for m in moved], float), counts) for k in "xyz")
        out = np.empty_like(v)
        out[:, 0] = c * v[:, 0] - s * v[:, 1] + x
        out[:, 1] = s * v[:, 0] + c * v[:, 1] + y
        out[:, 2] = v[:, 2] + z
        return out


def instances(v, f, positions, yaws=None, scales=None) -> tuple[np.ndarray, np.ndarray]:
    """Many copies of one template: scaled per axis, rotated about z, translated (all vectorised).

    Args:
        positions: (N, 3); yaws: (N,); scales: (N,) or (N, 3).
    """
    v = np.asarray(v, float)
    p = np.asarray(positions, float).reshape(-1, 3)
    n = len(p)
    s = np.ones((n, 3)) if scales is None else np.asarray(scales, float)
    if s.ndim == 1:
        s = np.repeat(s[:, None], 3, axis=1)
    local = v[None] * s[:, None, :]
    if yaws is not None:
        y = np.asarray(yaws, float).reshape(n)
        c, sn = np.cos(y)[:, None], np.sin(y)[:, None]
        x0, y0 = local[..., 0].copy(), local[..., 1].copy()
        local[..., 0] = c * x0 - sn * y0
        local[..., 1] = sn * x0 + c * y0
    out_v = (local + p[:, None, :]).reshape(-1, 3)
    out_f = (np.asarray(f)[None] + len(v) * np.arange(n)[:, None, None]).reshape(-1, 3)
    return out_v, out_f


def _checked_label(label, f: np.ndarray):
    """``label`` as a part keeps it: one value, or one per face (checked here, where the part is added)."""
    if np.ndim(label) == 0:
        return label
    label = np.asarray(label)
    if label.size == 1:
        return label.reshape(()).item()
    if label.shape != (len(f),):
        raise ValueError(f"a part's labels must be one value or one per face ({len(f)}), got shape {label.shape}")
    return label


class MeshBuilder:
    """Collects labelled parts, moved parts and batched boxes, then emits one Mesh."""

    def __init__(self) -> None:
        # (vertices, faces, label) in order; a moved part's vertices are a _Moved, made in arrays()
        self._parts: list[tuple] = []
        self._box_c: list = []
        self._box_s: list = []
        self._box_y: list = []
        self._box_l: list = []

    def add(self, v, f, label) -> None:
        """A part: vertices, faces and its label (one for all faces, or one per face)."""
        f = np.asarray(f)
        self._parts.append((np.asarray(v, float), f, _checked_label(label, f)))

    def add_moved(self, v, f, label, x=0.0, y=0.0, z=0.0, yaw=0.0, scale=1.0) -> None:
        """``add(transform(v, x, y, z, yaw, scale), f, label)``, the same arrays, with the transforms of all parts
        added so made in one pass (``arrays``): a town adds about 1,300 small parts (trees, poles, parked cars),
        each a dozen NumPy calls on a few dozen vertices when moved one by one. ``v`` must not change
        before ``arrays`` (templates and bodies never do)."""
        f = np.asarray(f)
        self._parts.append((_Moved(v, x, y, z, yaw, scale), f, _checked_label(label, f)))

    def add_box(self, cx, cy, z0, sx, sy, sz, yaw=0.0, label=0) -> None:
        """A box standing on ``z0`` (bottom), centred at (cx, cy), size (sx, sy, sz), rotated by yaw."""
        self._box_c.append((cx, cy, z0 + sz / 2))
        self._box_s.append((sx, sy, sz))
        self._box_y.append(yaw)
        self._box_l.append(label)

    def add_segment_box(self, p0, p1, width, z0, z1, label) -> None:
        """A box along the horizontal segment p0 -> p1 (its length), ``width`` across, from z0 to z1."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        d = p1 - p0
        length = float(np.hypot(d[0], d[1]))
        if length <= 1e-6:
            return
        c = (p0 + p1) / 2
        self.add_box(c[0], c[1], z0, length, width, z1 - z0, float(np.arctan2(d[1], d[0])), label)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices, faces, labels) of everything added: the parts in order, then the boxes; not validated
        (``build`` makes the checked ``Mesh`` of the same arrays)."""
        parts = list(self._parts)
        if self._box_c:
            v, f = boxes(np.array(self._box_c), np.array(self._box_s), np.array(self._box_y))
            parts.append((v, f, np.repeat(np.array(self._box_l, dtype=np.int32), BOX_TRIANGLES)))
        nv = np.array([len(p[0]) for p in parts])
        nf = np.array([len(p[1]) for p in parts])
        first = np.cumsum(nv) - nv
        verts = np.empty((int(nv.sum()), 3))
        moved = [i for i, p in enumerate(parts) if isinstance(p[0], _Moved)]
        for i, p in enumerate(parts):
            if not isinstance(p[0], _Moved):
                verts[first[i]:first[i] + nv[i]] = p[0]
        if moved:
            # the moved parts' vertices come out of apply one part after the other; row r of part j goes to
            # first[j] + (r - where part j starts in apply's output)
            rows = np.repeat(first[moved] - np.cumsum(nv[moved]) + nv[moved], nv[moved]) + np.arange(nv[moved].sum())
            verts[rows] = _Moved.apply([parts[i][0] for i in moved], nv[moved])
        faces = np.concatenate([p[1] for p in parts]) + np.repeat(first, nf)[:, None]
        one = [np.ndim(p[2]) == 0 for p in parts]
        labels = np.repeat(np.array([p[2] if o else 0 for p, o in zip(parts, one)], dtype=np.int32), nf)
        start = np.cumsum(nf) - nf
        for i in np.flatnonzero(~np.array(one)):
            labels[start[i]:start[i] + nf[i]] = parts[i][2]
        return verts, faces, labels

    def build(self):
        from place3d_kernels.mesh import Mesh

        return Mesh(*self.arrays())
