"""The scene builder's batched paths against the one-at-a-time code they replaced, kept here as references: the
same arrays to the bit (a scene's cache key hashes them, so any difference would rebuild every cached P-SOG and
change every result)."""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh, _twice_areas
from place3d_kernels.scene import town
from place3d_kernels.scene.bodies import template, vehicle_body
from place3d_kernels.scene.paths import Path, fillet
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


def test_a_path_through_repeated_points_drops_them():
    pts = np.array([(0, 0), (1, 0), (1, 0), (2, 1), (2, 1), (2, 1), (4, 1.0)])
    got, want = Path(pts), Path(pts[[0, 1, 3, 6]])
    assert same(got.points, want.points) and same(got.s, want.s) and same(got.yaw, want.yaw)
    assert not np.shares_memory(got.points, pts)
    walk = fillet(np.array([(0, 0), (30, 0), (30, 30.0)]), 8.0)
    assert np.all(np.diff(walk.s) > 0)


def test_overlap_with_axes_made_once_is_the_one_at_a_time_test():
    # the axes as the test made them inline before, and a candidate checked against many boxes in one call
    # (try_add's batch over every accepted vehicle) gives each row's answer of one call per box
    rng = np.random.default_rng(1)
    n = 500
    c1, c2 = rng.uniform(-6, 6, (n, 2)), rng.uniform(-6, 6, (n, 2))
    y1, y2 = rng.uniform(-3.2, 3.2, n), rng.uniform(-3.2, 3.2, n)
    h1, h2 = np.broadcast_to(np.array([2.7, 1.3]), (n, 2)), rng.uniform(0.3, 3, (n, 2))
    inline = np.stack([np.stack([np.cos(y1), np.sin(y1)], -1), np.stack([-np.sin(y1), np.cos(y1)], -1)], 1)
    assert same(_axes(y1), inline)
    a1, a2 = _axes(y1), _axes(y2)
    batched = _obb_overlap(c1, a1, h1, c2, a2, h2)
    one_by_one = np.concatenate([_obb_overlap(c1[i:i + 1], a1[i:i + 1], h1[i:i + 1], c2[i:i + 1], a2[i:i + 1],
                                              h2[i:i + 1]) for i in range(n)])
    assert same(batched, one_by_one) and 0 < batched.sum() < n
