"""Backend-neutral float64 geometry in NumPy: the watertight ray/triangle test and brute-force closest hits.

The reference backend's ray-mesh kernel is ``closest_hits``; the OpenCL backend re-traces the rays its BVH
kernel flags with it, and the vehicle body's inside test (``place3d_kernels.vehicle``) counts crossings
with ``watertight_intersect``. They live here, not in the reference backend, so that no backend and no
domain module reaches into another backend's internals (issue 32: backends behind their contract only).
"""

from __future__ import annotations

import numpy as np

__all__ = ["watertight_intersect", "closest_hits", "brute_force_raycast"]


def watertight_intersect(o: np.ndarray, d: np.ndarray, v0: np.ndarray, v1: np.ndarray, v2: np.ndarray,
                         t_max: np.ndarray) -> np.ndarray:
    """Woop, Benthin & Wald (JCGT 2013) watertight ray/triangle test, float64, all pairs.

    Args:
        o, d: (R, 3) ray origins and directions.
        v0, v1, v2: (F, 3) triangle corners.
        t_max: (R,) upper bound of t.

    Returns:
        (R, F) hit distances (inf where no hit) and nothing else; both faces count.
    """
    kz = np.argmax(np.abs(d), axis=1)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = d[np.arange(len(d)), kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)
    r = np.arange(len(d))
    dz = d[r, kz]
    sx, sy, sz = d[r, kx] / dz, d[r, ky] / dz, 1.0 / dz

    def project(v):
        rel = v[None, :, :] - o[:, None, :]                       # (R, F, 3)
        px = np.take_along_axis(rel, kx[:, None, None], 2)[..., 0]
        py = np.take_along_axis(rel, ky[:, None, None], 2)[..., 0]
        pz = np.take_along_axis(rel, kz[:, None, None], 2)[..., 0]
        return px - sx[:, None] * pz, py - sy[:, None] * pz, sz[:, None] * pz

    ax, ay, az = project(v0)
    bx, by, bz = project(v1)
    cx, cy, cz = project(v2)
    u = cx * by - cy * bx
    v = ax * cy - ay * cx
    w = bx * ay - by * ax
    inside = ~(((u < 0) | (v < 0) | (w < 0)) & ((u > 0) | (v > 0) | (w > 0)))
    det = u + v + w
    tt = u * az + v * bz + w * cz
    with np.errstate(divide="ignore", invalid="ignore"):
        t = tt / det
    ok = inside & (det != 0) & (t >= 0) & (t <= t_max[:, None])
    return np.where(ok, t, np.inf)


def closest_hits(v0: np.ndarray, v1: np.ndarray, v2: np.ndarray, o: np.ndarray, d: np.ndarray, t_max: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Closest hit of each ray among all triangles, by ``watertight_intersect`` in chunks of rays.

    Args:
        v0, v1, v2: (F, 3) float64 triangle corners.
        o, d: (R, 3) float64 ray origins and directions.
        t_max: (R,) float64 upper bounds of t.

    Returns:
        ``(t float64, face int32)``, each (R,): the smallest t and its face (ties in t go to the lowest face
        index); ``(inf, -1)`` on a miss.
    """
    t_out = np.full(len(o), np.inf)
    f_out = np.full(len(o), -1, dtype=np.int32)
    chunk = max(1, 400_000 // max(len(v0), 1))
    for s in range(0, len(o), chunk):
        e = min(s + chunk, len(o))
        t = watertight_intersect(o[s:e], d[s:e], v0, v1, v2, t_max[s:e])
        best = np.argmin(t, axis=1)
        tb = t[np.arange(e - s), best]
        hit = np.isfinite(tb)
        t_out[s:e] = tb
        f_out[s:e] = np.where(hit, best, -1)
    return t_out, f_out


def brute_force_raycast(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray, directions: np.ndarray,
                        t_max) -> tuple[np.ndarray, np.ndarray]:
    """``closest_hits`` on an indexed mesh: (V, 3) vertices, (F, 3) integer faces, (R, 3) rays and a scalar
    or (R,) ``t_max``. Returns ``(t float64, face int32)``, each (R,)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    tm = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (len(o),))
    return closest_hits(v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], o, d, tm)
