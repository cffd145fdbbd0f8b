"""``ops.MeshGroups``: several meshes in one grouped tree, each block of rays confined to its own mesh, gives
each block's ``raycast`` hits bit for bit (float64 decides among tied faces, so the tree's order does not
matter); ``simulate`` through it gives the frames of the per-frame casts."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.ops import MeshGroups
from place3d_kernels.profiling import profile

from test_raycast import closed_meshes

GROUPED = [b for b in p3k.available_backends() if MeshGroups.supported(b)]
OTHERS = [b for b in p3k.available_backends() if b not in GROUPED]
needs_grouped = pytest.mark.skipif(not GROUPED, reason="no backend with grouped casts (Warp, OpenCL with doubles)")


def raycast_groups(meshes, o, d, t_max, backend, first=0):
    return MeshGroups(meshes, backend).cast(o, d, t_max, len(o) // max(len(meshes) - first, 1), first)


def _meshes_and_rays(rng, per_mesh=600):
    """The three closed meshes far apart (so each has its own shift), and per mesh rays aimed at its shared
    vertices and edges (ties) and at random points on its surface."""
    meshes, o_all, d_all = [], [], []
    for k, (name, tm) in enumerate(closed_meshes().items()):
        m = p3k.Mesh(tm.vertices + [40.0 * k - 17.3, 11.0 * k + 3.1, 0.5 * k], tm.faces, labels=np.arange(len(tm.faces)) % 22)
        v = m.vertices
        e = tm.edges_unique
        tgt = np.concatenate([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]]), trimesh_surface(tm, rng, 200) + (m.vertices[0] - tm.vertices[0])])
        tgt = tgt[rng.choice(len(tgt), per_mesh, replace=len(tgt) < per_mesh)]
        out = tgt - v.mean(axis=0)
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        o = tgt + 8.0 * (out + 0.2 * rng.normal(size=out.shape))
        meshes.append(m)
        o_all.append(o)
        d_all.append(tgt - o)
    return meshes, np.concatenate(o_all), np.concatenate(d_all)


def trimesh_surface(tm, rng, n):
    import trimesh

    pts, _ = trimesh.sample.sample_surface(tm, n, seed=int(rng.integers(1 << 30)))
    return np.asarray(pts, dtype=np.float64)


@needs_grouped
@pytest.mark.parametrize("name", GROUPED)
def test_blocks_get_their_own_meshes_hits(name, rng):
    meshes, o, d = _meshes_and_rays(rng)
    got = raycast_groups(meshes, o, d, 50.0, backend=name)
    assert got is not None
    r = len(o) // len(meshes)
    for g, m in enumerate(meshes):
        blk = slice(g * r, (g + 1) * r)
        want = p3k.raycast(m, o[blk], d[blk], 50.0, backend=name)
        t, f, lab = got.t[blk], got.face[blk], got.label[blk]
        assert t.dtype == want.t.dtype and f.dtype == want.face.dtype and lab.dtype == want.label.dtype
        np.testing.assert_array_equal(np.isfinite(t), want.hit)
        assert want.hit.sum() > 0.9 * r
        # rays aimed at shared edges and vertices too: the same face, distance bits and label
        np.testing.assert_array_equal(f, want.face)
        np.testing.assert_array_equal(t, want.t)
        np.testing.assert_array_equal(lab, want.label)


@needs_grouped
@pytest.mark.parametrize("name", GROUPED)
def test_a_block_never_sees_another_blocks_mesh(name, rng):
    meshes, o, d = _meshes_and_rays(rng, per_mesh=200)
    r = len(o) // len(meshes)
    # block 0's rays aimed at mesh 1, block 1's at mesh 2, block 2's at mesh 0: each mesh only in its own
    # block's subtree, so every ray misses
    rolled_o, rolled_d = np.roll(o, -r, axis=0), np.roll(d, -r, axis=0)
    got = raycast_groups(meshes, rolled_o, rolled_d, 50.0, backend=name)
    assert got is not None and not np.isfinite(got.t).any() and (got.face == -1).all() and (got.label == -1).all()
    # while through the whole tree (raycast per block into the mesh they aim at) they hit
    assert p3k.raycast(meshes[1], rolled_o[:r], rolled_d[:r], 50.0, backend=name).hit.mean() > 0.9


@needs_grouped
@pytest.mark.parametrize("name", GROUPED)
def test_a_bad_ray_falls_back_to_raycasts_error(name, rng):
    meshes, o, d = _meshes_and_rays(rng, per_mesh=50)
    o[70, 1] = np.nan
    assert raycast_groups(meshes, o, d, 50.0, backend=name) is None
    with pytest.raises(ValueError, match="origin"):
        p3k.raycast(meshes[1], o[50:100], d[50:100], 50.0, backend=name)


@needs_grouped
def test_uneven_blocks_and_empty_meshes_are_refused(rng):
    meshes, o, d = _meshes_and_rays(rng, per_mesh=50)
    g = MeshGroups(meshes, GROUPED[0])
    assert g.cast(o[:-1], d[:-1], 50.0, 50) is None                  # 149 rays in blocks of 50
    assert g.cast(o, d, np.full(len(o), 50.0), 50) is None           # per-ray bounds
    assert g.cast(o, d, 50.0, 50, first=1) is None                   # blocks for meshes 1, 2 and a fourth
    assert g.cast(o.astype(np.float32), d.astype(np.float32), 50.0, 50) is None
    b = p3k.get_backend(GROUPED[0])
    with pytest.raises(ValueError, match="each with a face"):
        b.upload_mesh_groups([meshes[0].upload_parts(), (np.zeros((3, 3)), np.zeros((0, 3), int), None, None)])


@needs_grouped
@pytest.mark.parametrize("name", GROUPED)
def test_a_later_block_of_meshes(name, rng):
    # rays for meshes 1 and 2 only (first=1): mesh g's hits, as in one call for all three
    meshes, o, d = _meshes_and_rays(rng, per_mesh=100)
    whole = raycast_groups(meshes, o, d, 50.0, backend=name)
    later = MeshGroups(meshes, name).cast(o[100:], d[100:], 50.0, 100, first=1)
    assert later is not None
    np.testing.assert_array_equal(later.t, whole.t[100:])
    np.testing.assert_array_equal(later.face, whole.face[100:])


@pytest.mark.parametrize("name", OTHERS)
def test_backends_without_grouped_casts_say_so(name, rng):
    meshes, o, d = _meshes_and_rays(rng, per_mesh=20)
    assert not MeshGroups(meshes, name).available
    assert raycast_groups(meshes, o, d, 50.0, backend=name) is None


@needs_grouped
@pytest.mark.parametrize("name", GROUPED)
def test_simulated_frames_equal_the_per_frame_casts(name, monkeypatch):
    from place3d_kernels import scene as scenes
    from place3d_kernels.lidar import LidarModel

    sim = sys.modules["place3d_kernels.simulate"]     # the package exports a function of that name
    town = scenes.town(seed=4, n_frames=7)
    assert town.actors
    full = LidarModel.load("collection_64ch")
    lidar = LidarModel(name="sparse", elevations=full.elevations[::2], azimuths=full.azimuths[::4],
                       max_range=full.max_range)
    monkeypatch.setattr(sim, "SWEEP_BATCH_RAYS", 3 * len(lidar.elevations) * len(lidar.azimuths))  # 3 calls
    runs = {}
    for mode in ("0", "1"):
        monkeypatch.setenv(sim.ACTOR_GROUPS_ENV, mode)
        with profile(print_table=False) as p:
            runs[mode] = sim.simulate(town, lidar, backend=name)
        runs[mode + "rows"] = p.totals
    cast, build = ("simulate: actors, grouped",), ("simulate: actors, grouped", "raycast: grouped build")
    assert runs["1rows"][cast][1] == 3 and runs["1rows"][build][1] == 1      # one tree, one cast per call
    assert cast not in runs["0rows"] and runs["0rows"][("simulate: actors' BVH",)][1] == 7
    differ = 0
    for a, b in zip(runs["0"], runs["1"]):
        assert a.points.shape == b.points.shape
        np.testing.assert_array_equal(a.labels, b.labels)
        differ += int(np.any(a.points != b.points, axis=1).sum())
        # a tie may move a point by the float64 rounding of another face's distance, no more
        np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-9)
    if not getattr(p3k.get_backend(name).device, "is_cuda", False):
        # Warp's CPU builds the per-frame and the grouped trees alike (SAH); OpenCL's kernel keeps the least
        # float64 distance and, among equal ones, the lowest face, whatever the tree
        assert differ == 0
