"""Ray-mesh intersection: watertightness at shared edges and vertices, agreement with the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

import place3d_kernels as p3k


def closed_meshes():
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.5)
    box = trimesh.creation.box(extents=(2.0, 1.0, 3.0))
    box = box.subdivide().subdivide()                  # many shared edges on flat faces
    cyl = trimesh.creation.cylinder(radius=0.7, height=2.0, sections=24)
    return {"icosphere": ico, "box": box, "cylinder": cyl}


@pytest.mark.parametrize("name", ["icosphere", "box", "cylinder"])
def test_no_leaks_through_shared_vertices_and_edges(backend, name, rng):
    tm = closed_meshes()[name]
    assert tm.is_watertight
    mesh = p3k.Mesh(tm.vertices + [3.0, -2.0, 1.0], tm.faces)
    v = mesh.vertices
    edges = tm.edges_unique
    targets = [v]                                                     # every vertex
    targets.append(0.5 * (v[edges[:, 0]] + v[edges[:, 1]]))          # every edge midpoint
    w = rng.uniform(0.05, 0.95, (len(edges), 1))
    targets.append(w * v[edges[:, 0]] + (1 - w) * v[edges[:, 1]])    # random points on edges
    tgt = np.concatenate(targets)
    if backend == "reference":
        tgt = tgt[rng.choice(len(tgt), min(len(tgt), 300), replace=False)]
    centre = v.mean(axis=0)
    # origins outside the (convex) mesh; each ray passes exactly through its target heading roughly at
    # the centre, so it must enter the body there: a miss is a leak, not a graze
    out = tgt - centre
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out += 0.1 * rng.normal(size=out.shape)
    origins = tgt + 10.0 * out
    d = tgt - origins
    hits = p3k.raycast(mesh, origins, d, 100.0, backend=backend)
    leaks = int((~hits.hit).sum())
    assert leaks == 0, f"{leaks} of {len(tgt)} rays aimed at shared vertices/edges slipped through"
    # and the hit is at or before the target (the first surface on the way in)
    dist = np.linalg.norm(tgt - origins, axis=1)
    excess = hits.t - dist * (1 + 1e-5) - 1e-6
    assert np.all(excess <= 0), f"{int((excess > 0).sum())} rays passed their target (max {excess.max():.3g} m): leaked into the body"


def test_hits_match_reference(device_backend, rng):
    tm = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    mesh = p3k.Mesh(tm.vertices, tm.faces, labels=np.arange(len(tm.faces)) % 22)
    o = rng.normal(size=(2000, 3)) * 4.0
    d = rng.normal(size=(2000, 3)) * 1.5 - o        # most rays aim at the sphere
    got = p3k.raycast(mesh, o, d, 20.0, backend=device_backend)
    want = p3k.raycast(mesh, o, d, 20.0, backend="reference")
    np.testing.assert_array_equal(got.hit, want.hit)
    h = want.hit
    assert h.sum() > 500
    if getattr(p3k.get_backend(device_backend), "fp64", True):
        # float64 decides the face (the reference's test, ties to the lower face) and gives its distance: the
        # reference's hits, bit for bit, so simulated points, and the P-SOGs built from them, are identical
        # across backends
        np.testing.assert_array_equal(got.face, want.face)
        np.testing.assert_array_equal(got.t, want.t)
        np.testing.assert_array_equal(got.label, want.label)
        return
    # float32 decides (OpenCL without doubles): a different face only where the distance ties
    np.testing.assert_allclose(got.t[h], want.t[h], rtol=1e-5, atol=1e-6)
    same_face = got.face[h] == want.face[h]
    assert same_face.mean() > 0.99
    np.testing.assert_array_equal(got.label[h][same_face], want.label[h][same_face])


def test_misses_are_inf_and_minus_one(backend):
    mesh = p3k.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], labels=[7])
    o = np.array([[0.2, 0.2, 1.0], [5.0, 5.0, 1.0], [0.2, 0.2, 1.0], [0.2, 0.2, 1.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]])
    t_max = np.array([10.0, 10.0, 10.0, 0.5])
    h = p3k.raycast(mesh, o, d, t_max, backend=backend)
    np.testing.assert_allclose(h.t[0], 1.0, rtol=1e-6)
    assert h.face[0] == 0 and h.label[0] == 7
    assert np.all(np.isinf(h.t[1:])) and np.all(h.face[1:] == -1) and np.all(h.label[1:] == -1)


def test_closest_of_stacked_planes(backend):
    quads = []
    for z in (3.0, 1.0, 2.0):
        quads.append(p3k.Mesh([[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]], [[0, 1, 2], [0, 2, 3]],
                              labels=[int(z)] * 2))
    mesh = p3k.Mesh.concatenate(quads)
    h = p3k.raycast(mesh, [[0.1, 0.3, 0.0]], [[0, 0, 1.0]], 10.0, backend=backend)
    np.testing.assert_allclose(h.t, [1.0], rtol=1e-6)
    assert h.label[0] == 1


def test_bvh_built_once_per_backend(device_backend):
    tm = trimesh.creation.icosphere(subdivisions=1)
    mesh = p3k.Mesh(tm.vertices, tm.faces)
    p3k.raycast(mesh, [[0, 0, 5.0]], [[0, 0, -1.0]], backend=device_backend)
    h1 = mesh._handles[p3k.get_backend(device_backend)]
    p3k.raycast(mesh, [[0, 0, 5.0]], [[0, 0, -1.0]], backend=device_backend)
    assert mesh._handles[p3k.get_backend(device_backend)] is h1 and len(mesh._handles) == 1


def test_far_from_origin_mesh(backend):
    off = np.array([2.0e5, -3.0e5, 10.0])
    tm = trimesh.creation.box(extents=(2, 2, 2))
    mesh = p3k.Mesh(tm.vertices + off, tm.faces)
    h = p3k.raycast(mesh, off + [-10.0, 0.25, 0.25], [[1.0, 0, 0]], 100.0, backend=backend)
    np.testing.assert_allclose(h.t, [9.0], atol=1e-4)


def _slow_check_directions(d):
    # the per-row rule check_rays implements (kept here as the test's oracle): errors for non-finite or
    # all-zero rows; a row whose squared norm overflows or underflows is first scaled by the power of two
    # that brings its largest component into [0.5, 1); then rows off unit by more than 1e-12 renormalised
    # and the others left as they are
    if not np.isfinite(d).all():
        return "non-finite"
    out = d.copy()
    norm = np.zeros(len(d))
    for i, row in enumerate(d):
        with np.errstate(over="ignore", under="ignore"):
            n = math.sqrt(min(row[0] * row[0] + row[1] * row[1] + row[2] * row[2], math.inf))
        if n == 0.0 or n == math.inf:
            if not np.any(row):
                return "zero-length"
            out[i] = row / 2.0 ** math.frexp(float(np.abs(row).max()))[1]
            n = math.sqrt(out[i, 0] * out[i, 0] + out[i, 1] * out[i, 1] + out[i, 2] * out[i, 2])
        norm[i] = n
    off = np.abs(norm - 1.0) > 1e-12
    out[off] /= norm[off, None]
    return out


@pytest.mark.parametrize("eps", [0.0, 1e-13, 9e-13, 1e-12, 1.1e-12, 2e-12, 3e-12, 1e-9])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_check_rays_fast_path_keeps_the_per_row_rule(eps, sign, rng):
    # check_rays skips its per-row checks when min and max of the norms are within 1e-12 of one; rows
    # right at that bound must come out exactly as the per-row rule gives them
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[5] = [1.0 + sign * eps, 0.0, 0.0]
    d[9] = [0.0, (1.0 + sign * eps) * 0.6, (1.0 + sign * eps) * 0.8]
    want = _slow_check_directions(d)
    _, got, _ = p3k.ops.check_rays(np.zeros((64, 3)), d, 1.0)
    assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("bad", [[np.nan, 0.0, 1.0], [np.inf, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-200, 0.0, 0.0],
                                 [1e200, 0.0, 0.0]])
def test_check_rays_fast_path_still_rejects(bad):
    d = np.tile([0.0, 0.0, 1.0], (8, 1))
    d[3] = bad
    want = _slow_check_directions(d)
    if isinstance(want, str):
        with pytest.raises(ValueError, match=f"ray 3 has a {want}"):
            p3k.ops.check_rays(np.zeros((8, 3)), d, 1.0)
    else:    # 1e200 squares to inf and 1e-200 to 0: scaled first, they become (1, 0, 0)
        _, got, _ = p3k.ops.check_rays(np.zeros((8, 3)), d, 1.0)
        assert got.tobytes() == want.tobytes() and got[3].tolist() == [1.0, 0.0, 0.0]


def test_shift_on_device_is_bit_identical(device_backend, rng):
    # backends that subtract the mesh shift themselves (raycast_takes_shift) must give the bits of
    # shifting on the host first
    b = p3k.get_backend(device_backend)
    if not b.raycast_takes_shift:
        pytest.skip(f"{b.name} takes shifted origins")
    tm = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    mesh = p3k.Mesh(tm.vertices + [12345.678, -9876.5, 321.25], tm.faces)
    o = mesh.vertices.mean(axis=0) + rng.normal(size=(4000, 3)) * 5.0 + rng.uniform(-1, 1, (4000, 3)) * 1e-7
    d = mesh.vertices.mean(axis=0) + rng.normal(size=(4000, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = mesh.handle(b)
    t1, f1 = b.raycast(h, o, d, 50.0, shift=mesh.shift)
    t2, f2 = b.raycast(h, o - mesh.shift, d, 50.0)
    assert np.isfinite(t1).sum() > 1000
    assert t1.tobytes() == t2.tobytes() and np.array_equal(f1, f2)


@pytest.mark.parametrize("tree", ["cubql", "sah"])
def test_warp_trees_leak_nothing_and_match_the_reference(tree, rng):
    """The Warp backend's BVH (WarpCore.upload_mesh) built by each builder it uses (cuBQL on CUDA, SAH on the
    CPU), walked by its ordered native walk (kernels.py, closest_hit), run here on Warp's CPU device: rays aimed
    at shared vertices and edges all hit, and the hits are the reference's, bit for bit (where faces tie,
    float64 picks the lower one, whatever the tree's order)."""
    pytest.importorskip("warp")
    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("no Warp CPU backend")
    from place3d_kernels.backends.warp.host import WarpBackend

    b = WarpBackend("cpu")
    b.bvh_constructor = tree
    for name, tm in closed_meshes().items():
        mesh = p3k.Mesh(tm.vertices + [3.0, -2.0, 1.0], tm.faces)
        v = mesh.vertices
        e = tm.edges_unique
        tgt = np.concatenate([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])
        out = tgt - v.mean(axis=0)
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        o = tgt + 10.0 * (out + 0.1 * rng.normal(size=out.shape))
        got = p3k.raycast(mesh, o, tgt - o, 100.0, backend=b)
        assert b.bvh_built == tree
        assert got.hit.all(), f"{name}: {int((~got.hit).sum())} rays slipped through a {tree} tree"
        want = p3k.raycast(mesh, o, tgt - o, 100.0, backend="reference")
        np.testing.assert_array_equal(got.face, want.face)
        np.testing.assert_array_equal(got.t, want.t)


def test_warp_hits_at_shared_edges_and_axis_rays_are_the_references():
    """The terraced grid of test_raycast_order (rays at every vertex and edge midpoint, and straight down:
    direction components exactly 0, which the walk's node test takes as parallel to those slabs) on Warp's CPU
    device: every ray's face and distance bits are the reference's."""
    pytest.importorskip("warp")
    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("no Warp CPU backend")
    from place3d_kernels.backends.geometry import brute_force_raycast
    from place3d_kernels.backends.warp.host import WarpBackend
    from test_raycast_order import _scene

    v, f, o, d = _scene()
    assert (d == 0).any(axis=1).sum() > 1000
    b = WarpBackend("cpu")
    tm = np.full(len(o), 1e30)
    t, face = b.raycast(b.upload_mesh(v, f), o, d, tm)
    want_t, want_face = brute_force_raycast(v, f, o, d, tm)
    np.testing.assert_array_equal(face, want_face)
    np.testing.assert_array_equal(t, want_t)


@pytest.mark.parametrize("tree", ["cubql", "sah"])
def test_warp_walk_on_trees_at_warps_depth_cap_is_the_references(tree, rng):
    """A chain of triangles whose sizes grow geometrically, which cuBQL builds as deep as Warp lets any builder
    go (a node at depth BVH_QUERY_STACK_SIZE - 1 becomes a leaf): the ordered walk's stack (kernels.py,
    _ORDERED_WALK) is sized by that cap, and every hit, down through the deepest leaves, is the reference's, bit
    for bit, on Warp's CPU device."""
    pytest.importorskip("warp")
    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("no Warp CPU backend")
    from _warp_bvh_depth import depth_and_cap
    from place3d_kernels.backends.geometry import brute_force_raycast
    from place3d_kernels.backends.warp.host import WarpBackend

    n = 400
    x = 1.05 ** np.arange(n)
    w = 0.3 * x
    v = np.zeros((3 * n, 3))
    v[0::3, 0], v[1::3, 0], v[2::3, 0], v[2::3, 1] = x, x + w, x, w
    f = np.arange(3 * n).reshape(n, 3)
    b = WarpBackend("cpu")
    b.bvh_constructor = tree
    m = b.upload_mesh(v, f)
    depth, cap = depth_and_cap(m.mesh.id)
    if tree == "cubql":
        assert depth == cap - 1, (depth, cap)          # the deepest tree a Warp builder makes
    # straight down onto every triangle's centroid and corners pulled inwards, and rays from random points
    c = v.reshape(n, 3, 3).mean(axis=1)
    tgt = np.concatenate([c, *(c + 0.9 * (v[k::3] - c) for k in range(3))])
    o = np.concatenate([tgt + np.array([0.0, 0.0, 1.0]) * w.max(), rng.uniform(-1, 1, (500, 3)) * x.max()])
    d = np.concatenate([np.tile([0.0, 0.0, -1.0], (len(tgt), 1)), tgt[rng.integers(0, len(tgt), 500)] - o[len(tgt):]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tm = np.full(len(o), 1e30)
    t, face = b.raycast(m, o, d, tm)
    want_t, want_face = brute_force_raycast(v, f, o, d, tm)
    assert (want_face >= 0).sum() > len(tgt)
    np.testing.assert_array_equal(face, want_face)
    np.testing.assert_array_equal(t, want_t)
