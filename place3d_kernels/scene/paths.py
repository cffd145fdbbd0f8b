"""Planar paths for the procedural town: arc-length curves, filleted lane centrelines and junction walks."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Path", "fillet", "lane_path", "walk", "DIRS"]

_RIGHT_TURN_RADIUS = 8.0
_LEFT_TURN_RADIUS = 12.0


class Path:
    """A planar curve sampled densely; poses by arc length (linear extrapolation past both ends)."""

    def __init__(self, points: np.ndarray):
        p = np.array(points, float)        # a copy: the path never shares the caller's array
        d = np.diff(p, axis=0)
        seg = np.linalg.norm(d, axis=1)
        keep = seg > 1e-9
        if not keep.all():          # repeated points dropped, the rest measured again
            p = p[np.r_[True, keep]]
            d = np.diff(p, axis=0)
            seg = np.linalg.norm(d, axis=1)
        self.points = p
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


def fillet(corners: np.ndarray, radii, step: float = 0.25) -> Path:
    """Polyline through ``corners`` with circular fillets of ``radii`` at interior corners."""
    return Path(_densify(_arcs(corners, radii, step), step))


def _arcs(corners: np.ndarray, radii, step: float) -> np.ndarray:
    """``corners`` with each interior corner replaced by its fillet's arc, sampled about every ``step`` metres."""
    P = np.asarray(corners, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(P),))
    pts = [P[:1]]                 # blocks of rows, joined once
    made = {}                     # a corner met again (a walker's next lap) gives the same arc: made once
    for i in range(1, len(P) - 1):
        seen = (P[i - 1:i + 2].tobytes(), float(radii[i]))
        if seen in made:
            pts.append(made[seen])
            continue
        u, w = P[i] - P[i - 1], P[i + 1] - P[i]
        lu, lw = np.linalg.norm(u), np.linalg.norm(w)
        u, w = u / lu, w / lw
        cross = u[0] * w[1] - u[1] * w[0]
        theta = math.acos(float(np.clip(u @ w, -1.0, 1.0)))
        if theta < 1e-6:
            pts.append(made.setdefault(seen, P[i:i + 1]))
            continue
        t = min(radii[i] * math.tan(theta / 2), 0.49 * lu, 0.49 * lw)
        r = t / math.tan(theta / 2)
        A = P[i] - u * t
        sgn = 1.0 if cross > 0 else -1.0
        centre = A + sgn * r * np.array([-u[1], u[0]])
        a0 = math.atan2(A[1] - centre[1], A[0] - centre[0])
        k = max(2, int(math.ceil(r * theta / step)))
        a = a0 + sgn * theta * np.linspace(0, 1, k + 1)
        pts.append(made.setdefault(seen, np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)], 1)))
    pts.append(P[-1:])
    return np.concatenate(pts)


def _densify(pts: np.ndarray, step: float) -> np.ndarray:
    """``pts`` with rows added along each stretch, at most ``step`` metres apart."""
    # densify straight stretches: stretch i from a = pts[i] to b = pts[i + 1] gets n_i = ceil(|b - a| / step)
    # rows a + (b - a) * j / n_i, j = 1..n_i, all stretches at once (the same IEEE operations, row for row, as
    # the per-stretch loop this replaced, which took about a third of a town's build)
    a, d = pts[:-1], pts[1:] - pts[:-1]
    q = np.sqrt(np.einsum("ij,ij->i", d, d)) / step
    # the loop measured a stretch as np.linalg.norm measures one vector (BLAS's dot, which may fuse a multiply
    # and an add), so a length may differ here in its last bit; that changes the row count only where q lies
    # next to a whole number, and those few stretches are measured as the loop measured them
    for i in np.flatnonzero(np.abs(q - np.rint(q)) <= 1e-9 * np.maximum(q, 1.0)):
        q[i] = np.linalg.norm(d[i]) / step
    n = np.maximum(1, np.ceil(q).astype(np.int64))
    first = np.repeat(np.cumsum(n) - n, n)
    j = (np.arange(int(n.sum())) - first + 1).astype(float)
    rows = np.repeat(a, n, axis=0) + np.repeat(d, n, axis=0) * (j / np.repeat(n, n))[:, None]
    return np.concatenate([pts[:1], rows])


def lane_path(nodes, centres, offset, step=0.25) -> Path:
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
    return fillet(np.array(corners), radii, step)


DIRS = ((1, 0), (0, 1), (-1, 0), (0, -1))


def walk(rng, start, d0, n_seg, nmax, force_turn_at=None, p_straight=0.55, avoid_border=False):
    """A random node walk on the (nmax+1)^2 junction grid without U-turns."""
    nodes = [start, (start[0] + d0[0], start[1] + d0[1])]
    d = d0
    while len(nodes) < n_seg + 1:
        cur = nodes[-1]
        opts = [e for e in DIRS if e != (-d[0], -d[1])
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
