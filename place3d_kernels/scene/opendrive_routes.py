"""Routes on OpenDRIVE lane centre lines: poses by arc length and lanes chained end to start."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Route", "LaneGraph", "polylen"]


class Route:
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


class LaneGraph:
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
        total = polylen(pts[0])
        cur = i
        while total < length:
            nxt = self.next(cur, rng)
            if nxt is None:
                break
            pts.append(self.lanes[nxt][2][1:])
            total += polylen(self.lanes[nxt][2])
            cur = nxt
        return Route(np.concatenate(pts))


def _heading(p, i):
    d = p[1] - p[0] if i == 0 else p[-1] - p[-2]
    return math.atan2(d[1], d[0])


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def polylen(p):
    return float(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum())
