"""``Mesh.extended``: a mesh that begins with another one. It is the mesh of the concatenated arrays, and on a
backend that extends meshes (``Backend.extends_meshes``: OpenCL with doubles) its tree is the prefix's, built
once and kept on the prefix, joined under one root with the rest's (``bvh.join_bvh``): the hits of a plain build,
bit for bit, also where the prefix sits in another frame (another shift) and where rays hit shared edges."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.mesh import Mesh

from test_raycast import closed_meshes

BACKENDS = p3k.available_backends()
EXTENDING = [b for b in BACKENDS if getattr(p3k.get_backend(b), "extends_meshes", False)]
needs_extending = pytest.mark.skipif(not EXTENDING, reason="no backend extends meshes (OpenCL with doubles)")


def _parts(rng):
    """(prefix Mesh, the rest's vertices, faces, labels): the three closed meshes far apart, the first as the
    prefix, a zero-area face in each part; and rays at the parts' vertices and edge midpoints (ties between
    faces) and at random points near them."""
    meshes = list(closed_meshes().values())
    offsets = [(1000.3, -250.0, 7.0), (-17.3, 3.1, 0.0), (23.0, 14.1, 0.5)]
    vs = [tm.vertices + o for tm, o in zip(meshes, offsets)]
    fs = [np.asarray(tm.faces) for tm in meshes]
    fs[0] = np.concatenate([fs[0], [[0, 0, 1]]])                      # degenerate: never uploaded
    fs[2] = np.concatenate([fs[2], [[2, 2, 2]]])
    prefix = Mesh(vs[0], fs[0], labels=np.arange(len(fs[0])) % 22)
    rest_v = np.concatenate(vs[1:])
    rest_f = np.concatenate([fs[1], fs[2] + len(vs[1])])
    rest_l = (np.arange(len(rest_f)) * 7) % 22
    targets = []
    for v, tm, o in zip(vs, meshes, offsets):
        e = tm.edges_unique
        targets += [v, 0.5 * (v[e[:, 0]] + v[e[:, 1]]), v[rng.integers(0, len(v), 50)] + rng.normal(0, 0.2, (50, 3))]
    tgt = np.concatenate(targets)
    o = tgt + rng.normal(0, 6.0, tgt.shape)
    return prefix, rest_v, rest_f, rest_l, o, tgt - o


def test_extended_is_the_concatenated_mesh(rng):
    prefix, v, f, lab, _, _ = _parts(rng)
    m = Mesh.extended(prefix, v, f, lab)
    plain = Mesh(np.concatenate([prefix.vertices, v]), np.concatenate([prefix.faces, f + len(prefix.vertices)]),
                 np.concatenate([prefix.labels, lab]))
    for a in ("vertices", "faces", "labels", "valid_faces", "shift"):
        assert getattr(m, a).dtype == getattr(plain, a).dtype and np.array_equal(getattr(m, a), getattr(plain, a)), a
    assert m.prefix is prefix and plain.prefix is None
    assert not np.array_equal(prefix.shift, m.shift)                  # the test's point: another frame
    assert np.array_equal(Mesh.extended(prefix, v, f).labels[prefix.n_faces:], np.zeros(len(f), np.int32))
    with pytest.raises(ValueError, match="integer"):
        Mesh.extended(prefix, v, f.astype(float))
    import pickle

    back = pickle.loads(pickle.dumps(m))          # a scene sent between processes: the arrays, not the prefix
    assert back.prefix is None and np.array_equal(back.faces, m.faces) and np.array_equal(back.shift, m.shift)
    assert len(pickle.dumps(m)) < len(pickle.dumps(plain)) + 1000


@pytest.mark.parametrize("name", BACKENDS)
def test_extended_mesh_gives_the_plain_meshs_hits(name, rng):
    prefix, v, f, lab, o, d = _parts(rng)
    m = Mesh.extended(prefix, v, f, lab)
    plain = Mesh(m.vertices, m.faces, m.labels)
    got, want = p3k.raycast(m, o, d, 60.0, backend=name), p3k.raycast(plain, o, d, 60.0, backend=name)
    assert (want.face >= 0).sum() > len(o) // 2
    assert got.t.tobytes() == want.t.tobytes()
    assert np.array_equal(got.face, want.face) and np.array_equal(got.label, want.label)
    # where the backend extends meshes, the prefix's part was built and the handle's tree is the joined one
    b = p3k.get_backend(name)
    assert (b in prefix._parts) == (name in EXTENDING)


@needs_extending
@pytest.mark.parametrize("name", EXTENDING)
@pytest.mark.parametrize("width", [2, 4])
def test_joined_tree_is_valid_and_casts_like_a_whole_build(name, width, rng):
    from place3d_kernels.backends.opencl import OpenCLBackend
    from place3d_kernels.backends.opencl.bvh import validate_bvh

    b = OpenCLBackend(name.split(":", 1)[1], bvh_width=width)
    prefix, v, f, lab, o, d = _parts(rng)
    m = Mesh.extended(prefix, v, f, lab)
    plain = Mesh(m.vertices, m.faces, m.labels)
    h = m.handle(b)
    uv, uf, _, _ = m.upload_parts()
    validate_bvh(h.bvh, uv, uf)
    refs = h.bvh.child_refs()
    # the new root's two subtrees: the prefix's kept tree as node 1 onwards, the rest's after it
    part = prefix.part(b).bvh
    assert refs[0].tolist() == [1, 0, 1 + len(part.nodes), 0]
    assert np.array_equal(h.bvh.order[:len(part.order)], part.order) and h.bvh.depth > part.depth
    got, want = p3k.raycast(m, o, d, 60.0, backend=b), p3k.raycast(plain, o, d, 60.0, backend=b)
    assert got.t.tobytes() == want.t.tobytes() and np.array_equal(got.face, want.face)


@needs_extending
@pytest.mark.parametrize("name", EXTENDING)
def test_prefix_part_is_built_once_for_every_extension(name, rng, monkeypatch):
    b = p3k.get_backend(name)
    calls = []
    real = type(b).mesh_part

    def counted(self, vertices, faces):
        calls.append(len(faces))
        return real(self, vertices, faces)

    monkeypatch.setattr(type(b), "mesh_part", counted)
    prefix, v, f, lab, o, d = _parts(rng)
    for k in range(3):                                                 # three routes over one town
        m = Mesh.extended(prefix, v + k, f, lab)
        plain = Mesh(m.vertices, m.faces, m.labels)
        got, want = p3k.raycast(m, o, d, 60.0, backend=b), p3k.raycast(plain, o, d, 60.0, backend=b)
        assert got.t.tobytes() == want.t.tobytes() and np.array_equal(got.face, want.face)
    assert calls == [len(prefix.valid_faces)]


@needs_extending
@pytest.mark.parametrize("name", EXTENDING)
def test_upload_mesh_refuses_a_prefix_that_is_not_the_meshs_start(name, rng):
    b = p3k.get_backend(name)
    prefix, v, f, lab, _, _ = _parts(rng)
    m = Mesh.extended(prefix, v, f, lab)
    uv, uf, ids, ul = m.upload_parts()
    part = prefix.part(b)
    with pytest.raises(ValueError, match="prefix"):
        b.upload_mesh(uv, uf[::-1].copy(), ids, ul, prefix=(part, prefix.shift - m.shift))
    with pytest.raises(ValueError, match="prefix"):
        b.upload_mesh(uv, uf[:len(part.faces)], prefix=(part, prefix.shift - m.shift))


def test_join_bvh_takes_single_root_trees_only(rng):
    pytest.importorskip("pyopencl")
    from place3d_kernels.backends.opencl.bvh import build_bvh, join_bvh

    v = rng.normal(size=(30, 3))
    f = rng.integers(0, 30, (20, 3))
    one = build_bvh(v, f, max_depth=63)
    joined = join_bvh(one, one, np.zeros(3))
    assert joined.depth == one.depth + 1 and joined.max_depth == 64 and len(joined.tris) == 40
    assert np.array_equal(joined.order, np.r_[one.order, one.order + 20])
    with pytest.raises(ValueError, match="single-root"):
        join_bvh(build_bvh(v, f, groups=[10, 10]), one, np.zeros(3))


@needs_extending
def test_a_towns_routes_share_its_roads_tree(rng):
    """Two routes of an OpenDRIVE town: each static mesh extends the town's roads and ground (one Mesh per town
    and process), and a frame's rays meet each route's mesh as they meet the plain one."""
    from place3d_kernels.pooled import Drive
    from place3d_app.commands.reproduce import resolve_town

    b = p3k.get_backend(EXTENDING[0])
    s0, s1 = (Drive(resolve_town("Town01"), seed=s).build().static for s in (0, 1))
    assert s0.prefix is not None and s0.prefix is s1.prefix
    for m in (s0, s1):
        plain = Mesh(m.vertices, m.faces, m.labels)
        c = m.vertices[m.faces[rng.integers(0, m.n_faces, 3000)]].mean(axis=1)
        o = c + rng.normal(0, 15.0, c.shape) + [0, 0, 3.0]
        got, want = p3k.raycast(m, o, c - o, 120.0, backend=b), p3k.raycast(plain, o, c - o, 120.0, backend=b)
        assert (want.face >= 0).sum() > 2000
        assert got.t.tobytes() == want.t.tobytes() and np.array_equal(got.face, want.face)
