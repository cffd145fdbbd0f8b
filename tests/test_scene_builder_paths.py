"""The scene builder's batched paths against the one-at-a-time code they replaced, kept here as references: the
same arrays to the bit (a scene's cache key hashes them, so any difference would rebuild every cached P-SOG and
change every result)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh, _twice_areas
from place3d_kernels.scene import town
from place3d_kernels.scene.bodies import template, vehicle_body
from place3d_kernels.scene.paths import Path, _arcs, fillet
from place3d_kernels.scene.primitives import MeshBuilder, boxes, transform
from place3d_kernels.scene.town_actors import _axes, _obb_overlap

VEHICLE = CLASS_ID["vehicle"]


def same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


# ------------------------------------------------------------------ the references (the code before 2026-12-01)
def ref_transform(v, x=0.0, y=0.0, z=0.0, yaw=0.0, scale=1.0):
    v = np.asarray(v, float) * np.asarray(scale, float)
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.empty_like(v)
    out[:, 0] = c * v[:, 0] - s * v[:, 1] + x
    out[:, 1] = s * v[:, 0] + c * v[:, 1] + y
    out[:, 2] = v[:, 2] + z
    return out


def ref_arrays(parts, box_c, box_s, box_y, box_l):
    parts = [(np.asarray(v, float), np.asarray(f), np.broadcast_to(np.asarray(lab, dtype=np.int32), (len(f),)))
             for v, f, lab in parts]
    if box_c:
        v, f = boxes(np.array(box_c), np.array(box_s), np.array(box_y))
        parts.append((v, f, np.repeat(np.array(box_l, dtype=np.int32), 12)))
    offs = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] + o for p, o in zip(parts, offs)]),
            np.concatenate([p[2] for p in parts]))


def ref_vehicle(rng, kind):
    parts, bc, bs, by, bl = [], [], [], [], []

    def box(cx, cy, z0, sx, sy, sz):
        bc.append((cx, cy, z0 + sz / 2)), bs.append((sx, sy, sz)), by.append(0), bl.append(VEHICLE)

    if kind == "car":
        L, W, H = rng.uniform(4.0, 4.9), rng.uniform(1.75, 1.95), rng.uniform(1.4, 1.6)
        box(0, 0, 0.3, L, W, 0.65)
        cab = L * rng.uniform(0.45, 0.55)
        box(-0.05 * L, 0, 0.95, cab, W - 0.14, H - 0.95)
        r, ax = 0.32, L / 2 - 0.8
    elif kind == "van":
        L, W, H = rng.uniform(4.8, 5.6), 2.0, rng.uniform(1.9, 2.4)
        box(0, 0, 0.35, L, W, 0.9)
        box(-0.1, 0, 1.25, L - 0.8, W - 0.06, H - 1.25)
        r, ax = 0.35, L / 2 - 0.85
    elif kind == "truck":
        L, W, H = rng.uniform(6.5, 8.0), 2.3, rng.uniform(2.8, 3.4)
        box(L / 2 - 1.0, 0, 0.45, 2.0, W, 2.1)
        box(-0.9, 0, 0.6, L - 2.2, W, H - 0.6)
        r, ax = 0.45, L / 2 - 1.1
    else:
        L, W, H = rng.uniform(10.0, 12.0), 2.5, rng.uniform(2.9, 3.2)
        box(0, 0, 0.35, L, W, H - 0.35)
        r, ax = 0.5, L / 2 - 2.2
    y = W / 2 - 0.12
    v_unit, f_unit = template("prism6")
    v = v_unit.copy()
    v[:, :2] *= r
    v[:, 2] = (v[:, 2] - 0.5) * 0.24
    xs, ys = np.array([-ax, -ax, ax, ax])[:, None], np.array([-y, y, -y, y])[:, None]
    out = np.stack([v[None, :, 0] + xs, -v[None, :, 2] + ys, np.broadcast_to(v[None, :, 1] + r, (4, len(v)))], 2)
    faces = np.asarray(f_unit)[None] + len(v) * np.arange(4)[:, None, None]
    parts.append((out.reshape(-1, 3), faces.reshape(-1, 3), VEHICLE))
    return ref_arrays(parts, bc, bs, by, bl)


def ref_arcs(corners, radii, step):
    P = np.asarray(corners, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(P),))
    pts = [P[:1]]
    for i in range(1, len(P) - 1):
        u, w = P[i] - P[i - 1], P[i + 1] - P[i]
        lu, lw = np.linalg.norm(u), np.linalg.norm(w)
        u, w = u / lu, w / lw
        cross = u[0] * w[1] - u[1] * w[0]
        theta = math.acos(float(np.clip(u @ w, -1.0, 1.0)))
        if theta < 1e-6:
            pts.append(P[i:i + 1])
            continue
        t = min(radii[i] * math.tan(theta / 2), 0.49 * lu, 0.49 * lw)
        r = t / math.tan(theta / 2)
        A = P[i] - u * t
        sgn = 1.0 if cross > 0 else -1.0
        centre = A + sgn * r * np.array([-u[1], u[0]])
        a0 = math.atan2(A[1] - centre[1], A[0] - centre[0])
        k = max(2, int(math.ceil(r * theta / step)))
        a = a0 + sgn * theta * np.linspace(0, 1, k + 1)
        pts.append(np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)], 1))
    pts.append(P[-1:])
    return np.concatenate(pts)


def ref_obb_overlap(c1, yaw1, h1, c2, yaw2, h2):
    c1, c2 = np.asarray(c1, float), np.asarray(c2, float)
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


# ------------------------------------------------------------------ the tests
def test_moved_parts_are_the_parts_moved_one_by_one():
    rng = np.random.default_rng(3)
    iv, if_ = template("ico1")
    pv, pf = template("prism8")
    b, parts = MeshBuilder(), []
    for k in range(40):
        x, y, z, yaw = rng.uniform(-50, 50, 3).tolist() + [float(rng.uniform(0, 6.3))]
        scale = (1.5, 0.7, 2.0) if k % 3 == 0 else float(rng.uniform(0.5, 2))
        v, f = (iv, if_) if k % 2 else (pv, pf)
        label = k % 7 if k % 5 else np.arange(len(f)) % 9          # some parts carry a label per face
        b.add_moved(v, f, label, x, y, z, yaw=yaw, scale=scale)
        parts.append((ref_transform(v, x, y, z, yaw, scale), f, label))
        if k % 4 == 0:                                              # plain parts in between
            b.add(v + k, f, 3)
            parts.append((v + k, f, 3))
        if k % 6 == 0:
            b.add_box(x, y, z, 1.0, 2.0, 3.0, yaw, 5)
    want = ref_arrays(parts, b._box_c, b._box_s, b._box_y, b._box_l)
    got = b.arrays()
    assert all(same(g, w) for g, w in zip(got, want))
    assert same(transform(iv, 1.0, 2.0, 3.0, 0.4, (1.0, 2.0, 3.0)), ref_transform(iv, 1.0, 2.0, 3.0, 0.4, (1.0, 2.0, 3.0)))


def test_a_part_with_a_label_per_face_of_the_wrong_length_is_refused_when_added():
    v, f = template("prism6")
    with pytest.raises(ValueError, match="one per face"):
        MeshBuilder().add_moved(v, f, np.zeros(len(f) + 1, int))
    with pytest.raises(ValueError, match="one per face"):
        MeshBuilder().add(v, f, np.zeros(2, int))


@pytest.mark.parametrize("kind", ["car", "van", "truck", "bus"])
def test_a_vehicle_body_is_the_builders_vehicle(kind):
    for seed in range(5):
        body, got_kind = vehicle_body(np.random.default_rng(seed), kind)
        want = ref_vehicle(np.random.default_rng(seed), kind)
        assert got_kind == kind
        assert all(same(np.asarray(g), w) for g, w in zip(body, want))


def test_face_areas_and_extents_are_numpys_to_the_bit():
    mesh = town(seed=2, n_frames=2).static
    v, f = mesh.vertices, mesh.faces
    want = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert same(_twice_areas(np.ascontiguousarray(v.T), f), want)
    assert same(mesh.valid_faces, np.flatnonzero(want > 0).astype(np.int64))
    assert same(mesh.bounds, np.stack([v.min(axis=0), v.max(axis=0)]))
    degenerate = Mesh(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2], [0, 1, 3]]))
    assert degenerate.valid_faces.tolist() == [1]


def test_fillets_of_a_walkers_laps_are_the_corner_by_corner_arcs():
    rng = np.random.default_rng(0)
    for laps in (1, 3, 5):
        ring = np.array([(0, 0), (70.5, 0), (70.5, 71.2), (0, 71.2)]) + rng.uniform(-2, 2, 2)
        corners = np.concatenate([ring] * laps + [ring[:1]])
        assert same(_arcs(corners, 1.0, 0.2), ref_arcs(corners, 1.0, 0.2))
    lane = np.array([(0, 0), (40, 0), (40, 30), (80, 30), (120, 30), (120, 0.0)])   # turns and a straight corner
    assert same(_arcs(lane, [0, 8, 12, 0, 8, 0], 0.25), ref_arcs(lane, [0, 8, 12, 0, 8, 0], 0.25))


def test_a_path_through_repeated_points_drops_them():
    pts = np.array([(0, 0), (1, 0), (1, 0), (2, 1), (2, 1), (2, 1), (4, 1.0)])
    got, want = Path(pts), Path(pts[[0, 1, 3, 6]])
    assert same(got.points, want.points) and same(got.s, want.s) and same(got.yaw, want.yaw)
    assert not np.shares_memory(got.points, pts)
    walk = fillet(np.array([(0, 0), (30, 0), (30, 30.0)]), 8.0)
    assert np.all(np.diff(walk.s) > 0)


def test_overlap_with_axes_made_once_is_the_one_at_a_time_test():
    rng = np.random.default_rng(1)
    n = 500
    c1, c2 = rng.uniform(-6, 6, (n, 2)), rng.uniform(-6, 6, (n, 2))
    y1, y2 = rng.uniform(-3.2, 3.2, n), rng.uniform(-3.2, 3.2, n)
    h1, h2 = np.array([2.7, 1.3]), rng.uniform(0.3, 3, (n, 2))
    want = ref_obb_overlap(c1, y1, h1, c2, y2, h2)
    got = _obb_overlap(c1, _axes(y1), np.broadcast_to(h1, c1.shape), c2, _axes(y2), h2)
    assert same(got, want) and 0 < want.sum() < n
