"""The procedural town (embedded default scene) and the benchmark box city."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.pose import invert, pose_matrix
from place3d_kernels.scene import Scene, town
from place3d_kernels.scene.city import box_city
from place3d_kernels.scene.town import EGO_LENGTH, EGO_WIDTH

C = CLASS_ID
EGO_HALF = np.array([EGO_LENGTH / 2, EGO_WIDTH / 2])
EGO_Z = (0.05, 2.0)  # above painted lines, up to roof height


@pytest.fixture(scope="module")
def scene0() -> Scene:
    return town(0)


# ------------------------------------------------------------------------------------------ helpers
def _tri_box_overlap(tri: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Separating-axis test of triangles (N, 3, 3) against the box [-half, half] (Akenine-Moller)."""
    if len(tri) == 0:
        return np.zeros(0, bool)
    e = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], 1)  # (N, 3, 3)
    axes = [np.broadcast_to(np.eye(3)[k], (len(tri), 3)) for k in range(3)]
    axes.append(np.cross(e[:, 0], e[:, 1]))
    for i in range(3):
        for k in range(3):
            axes.append(np.cross(np.eye(3)[k][None], e[:, i]))
    sep = np.zeros(len(tri), bool)
    for a in axes:
        p = np.einsum("nvk,nk->nv", tri, a)
        r = np.abs(a) @ half
        sep |= (p.min(1) > r + 1e-9) | (p.max(1) < -r - 1e-9)
    return ~sep


def _ego_hits(vertices, faces, pose) -> int:
    """Triangles intersecting the ego box (footprint x [EGO_Z]) at one ego pose."""
    Ti = invert(pose_matrix(pose))
    v = vertices @ Ti[:3, :3].T + Ti[:3, 3]
    lo = np.array([-EGO_HALF[0], -EGO_HALF[1], EGO_Z[0]])
    hi = np.array([EGO_HALF[0], EGO_HALF[1], EGO_Z[1]])
    tri = v[faces]
    cand = np.all(tri.max(1) >= lo, axis=1) & np.all(tri.min(1) <= hi, axis=1)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    return int(_tri_box_overlap(tri[cand] - centre, half).sum())


def _closed_components(vertices, faces):
    """Per connected component (by shared vertex indices): closed & consistently wound, and signed volume."""
    nf = len(faces)
    # directed edges must pair with their reverse exactly once
    d = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = d[:, 0].astype(np.int64) * (len(vertices) + 1) + d[:, 1]
    rkey = d[:, 1].astype(np.int64) * (len(vertices) + 1) + d[:, 0]
    uk, counts = np.unique(key, return_counts=True)
    has_rev = np.isin(rkey, uk)
    dup = counts[np.searchsorted(uk, key)] > 1
    edge_ok = has_rev & ~dup
    face_ok = edge_ok.reshape(3, nf).all(0)
    _, lab_v = connected_components(_face_vertex_graph(faces, len(vertices)), directed=False)
    comp = lab_v[faces[:, 0]]
    tri = vertices[faces]
    tri = tri - tri.reshape(-1, 3).mean(0)
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    comp_vol = np.bincount(comp, weights=vol)
    comp_ok = np.bincount(comp, weights=~face_ok) == 0
    return comp, comp_ok, comp_vol


def _face_vertex_graph(faces, nv):
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nv, nv))


# --------------------------------------------------------------------------------------------- town
def test_deterministic_and_fast():
    t0 = time.perf_counter()
    a = town(7)
    dt = time.perf_counter() - t0
    b = town(7)
    assert np.array_equal(a.static.vertices, b.static.vertices)
    assert np.array_equal(a.static.faces, b.static.faces)
    assert np.array_equal(a.static.labels, b.static.labels)
    assert np.array_equal(a.ego_poses, b.ego_poses)
    assert len(a.actors) == len(b.actors)
    for x, y in zip(a.actors, b.actors):
        assert x.kind == y.kind
        assert np.array_equal(x.poses, y.poses)
        assert np.array_equal(x.mesh.vertices, y.mesh.vertices)
    assert a.key == b.key
    assert dt < 2.0, f"town generation took {dt:.2f} s"


def test_seeds_differ(scene0):
    s1 = town(1)
    assert scene0.key != s1.key or not np.array_equal(scene0.static.vertices, s1.static.vertices)
    assert not np.allclose(scene0.ego_poses, s1.ego_poses)
    assert s1.name == "town" and s1.seed == 1 and scene0.seed == 0


def test_static_independent_of_frames(scene0):
    s = town(0, n_frames=10)
    assert np.array_equal(s.static.vertices, scene0.static.vertices)
    assert s.n_frames == 10 and all(a.poses.shape == (10, 6) for a in s.actors)


def test_classes_and_budget(scene0):
    m = scene0.static
    assert 20_000 <= m.n_faces <= 150_000, m.n_faces
    present = set(np.unique(m.labels).tolist())
    required = ["road", "road line", "sidewalk", "building", "vegetation", "terrain", "pole", "traffic sign",
                "traffic light", "vehicle"]
    missing = [n for n in required if C[n] not in present]
    assert not missing, f"missing classes {missing}"
    assert C["wall"] in present or C["fence"] in present
    assert 0 not in present, "unlabelled faces in the town"
    # ground at z = 0, sidewalks raised, road lines just above the road
    assert np.isclose(m.vertices[:, 2].min(), 0.0)
    rl = m.vertices[m.faces[m.labels == C["road line"]]]
    assert 0.005 <= rl[..., 2].max() <= 0.03
    sw = m.vertices[m.faces[m.labels == C["sidewalk"]]][..., 2]
    assert np.isclose(sw.max(), scene0.meta["roads"]["curb_height"])
    # buildings: many taller than 5 m
    comp, _, _ = _closed_components(m.vertices, m.faces)
    bl = m.labels == C["building"]
    tops = np.zeros(comp.max() + 1)
    np.maximum.at(tops, comp[bl], m.vertices[m.faces[bl]][..., 2].max(1))
    assert (tops > 5.0).sum() >= 30


def test_solids_closed(scene0):
    m = scene0.static
    comp, comp_ok, comp_vol = _closed_components(m.vertices, m.faces)
    z = m.vertices[m.faces][..., 2]
    ground = np.isin(m.labels, [C["road"], C["terrain"], C["water"], C["ground"]]) & np.all(z == 0.0, axis=1)
    open_comps = np.unique(comp[ground])
    closed = np.setdiff1d(np.arange(len(comp_ok)), open_comps)
    assert len(closed) > 1000
    assert comp_ok[closed].all(), f"{(~comp_ok[closed]).sum()} solids are open or badly wound"
    assert (comp_vol[closed] > 0).all(), "some solids face inward"
    # the open ground surface faces up
    n = np.cross(m.vertices[m.faces[ground, 1]] - m.vertices[m.faces[ground, 0]],
                 m.vertices[m.faces[ground, 2]] - m.vertices[m.faces[ground, 0]])
    assert (n[:, 2] > 0).all()


def test_ego_route(scene0):
    s = scene0
    p = s.ego_poses
    assert p.shape == (40, 6) and s.frame_interval == 0.5
    assert np.all(p[:, 2] == 0) and np.all(p[:, 3:5] == 0)
    v = s.meta["ego_speed"]
    assert 6.0 <= v <= 10.0
    step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    assert np.allclose(step, v * s.frame_interval, rtol=0.03), step
    yaw = np.unwrap(p[:, 5])
    assert np.ptp(yaw) > 1.2, "the ego never turns"
    assert np.abs(np.diff(yaw)).max() < 0.8, "yaw jumps between frames"
    # heading follows the direction of travel
    dirn = np.arctan2(np.diff(p[:, 1]), np.diff(p[:, 0]))
    mid = (yaw[:-1] + yaw[1:]) / 2
    assert np.abs(np.angle(np.exp(1j * (dirn - mid)))).max() < 0.1
    # every ego pose stands on a road face of the static mesh
    m = s.static
    road = m.vertices[m.faces[m.labels == C["road"]]]
    for x, y in p[:, :2]:
        a, b, c = road[:, 0, :2], road[:, 1, :2], road[:, 2, :2]

        def cr(u, w):
            return (w[:, 0] - u[:, 0]) * (y - u[:, 1]) - (w[:, 1] - u[:, 1]) * (x - u[:, 0])

        inside = (cr(a, b) >= 0) & (cr(b, c) >= 0) & (cr(c, a) >= 0)
        assert inside.any(), f"ego at ({x:.1f}, {y:.1f}) is not on the road"


@pytest.mark.parametrize("seed", [0, 3])
def test_ego_footprint_free(seed, scene0):
    s = scene0 if seed == 0 else town(seed)
    for f in range(s.n_frames):
        n = _ego_hits(s.static.vertices, s.static.faces, s.ego_poses[f])
        assert n == 0, f"seed {seed} frame {f}: {n} static triangles inside the ego footprint"
        dyn = s.dynamic(f)
        n = _ego_hits(dyn.vertices, dyn.faces, s.ego_poses[f])
        assert n == 0, f"seed {seed} frame {f}: {n} actor triangles inside the ego footprint"


def test_footprint_check_detects_intrusion(scene0):
    """The footprint test itself must fail when something stands in the way."""
    from place3d_kernels.scene.primitives import boxes
    pose = scene0.ego_poses[5]
    v, f = boxes([[pose[0] + 1.0, pose[1], 1.0]], [[0.3, 0.3, 0.3]])
    assert _ego_hits(v, f, pose) > 0
    # a huge thin wall crossing the footprint without any vertex inside
    v, f = boxes([[pose[0], pose[1], 1.0]], [[0.1, 50.0, 50.0]], [pose[5]])
    assert _ego_hits(v, f, pose) > 0
    v, f = boxes([[pose[0], pose[1], 10.0]], [[0.1, 50.0, 1.0]], [pose[5]])
    assert _ego_hits(v, f, pose) == 0


def test_actors(scene0):
    s = scene0
    kinds = [a.kind for a in s.actors]
    assert kinds.count("pedestrian") >= 10
    vehicles = [a for a in s.actors if a.kind != "pedestrian"]
    assert len(vehicles) >= 8
    for a in s.actors:
        assert a.poses.shape == (s.n_frames, 6)
        lab = np.unique(a.mesh.labels)
        assert lab.tolist() == [C["pedestrian"] if a.kind == "pedestrian" else C["vehicle"]]
        moved = np.linalg.norm(a.poses[-1, :2] - a.poses[0, :2])
        assert moved > 5.0, f"{a.kind} barely moves ({moved:.2f} m)"
        assert np.abs(np.diff(a.poses[:, :2], axis=0)).max() < 8.0  # no teleporting
    # dynamic geometry changes between frames, the static part does not
    d0, d1 = s.dynamic(0), s.dynamic(10)
    assert d0.n_faces == d1.n_faces and not np.allclose(d0.vertices, d1.vertices)
    assert s.mesh(3).n_faces == s.static.n_faces + d0.n_faces
    # traffic near the ego: some vehicle within 40 m in most frames, oncoming traffic in several
    dist = np.array([np.linalg.norm(a.poses[:, :2] - s.ego_poses[:, :2], axis=1) for a in vehicles])
    assert np.mean((dist < 40).any(0)) >= 0.9
    onc = [a for a in vehicles if a.kind == "oncoming"]
    assert onc
    d_onc = np.array([np.linalg.norm(a.poses[:, :2] - s.ego_poses[:, :2], axis=1) for a in onc])
    assert (d_onc < 40).any(0).sum() >= 10


def test_pedestrians_on_sidewalks(scene0):
    s = scene0
    ch = s.meta["roads"]["curb_height"]
    rects = [(b["rect"], b["inner"]) for b in s.meta["blocks"]]
    for a in s.actors:
        if a.kind != "pedestrian":
            continue
        assert np.allclose(a.poses[:, 2], ch)
        for x, y in a.poses[:, :2]:
            on = any(o[0] < x < o[2] and o[1] < y < o[3] and not (i[0] < x < i[2] and i[1] < y < i[3])
                     for o, i in rects)
            assert on, f"pedestrian at ({x:.1f}, {y:.1f}) is off the sidewalk"


def test_vehicles_do_not_collide(scene0):
    s = scene0
    veh = [a for a in s.actors if a.kind != "pedestrian"]
    for f in range(0, s.n_frames, 3):
        boxes = []
        for a in veh:
            lo, hi = a.mesh.vertices.min(0), a.mesh.vertices.max(0)
            T = pose_matrix(a.poses[f])
            corners = np.array([[x, y, 0.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]) @ T[:3, :3].T
            boxes.append(corners[:, :2] + T[:2, 3])
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                assert not _poly_overlap(boxes[i], boxes[j]), f"vehicles {i} and {j} overlap at frame {f}"


def _poly_overlap(a, b) -> bool:
    """Overlap of two rectangles given by 4 corners each (SAT on their edge normals)."""
    for poly in (a, b):
        hull = poly[[0, 1, 3, 2]]
        for k in range(4):
            e = hull[(k + 1) % 4] - hull[k]
            n = np.array([-e[1], e[0]])
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def test_options():
    with pytest.raises(TypeError, match="unknown options"):
        town(0, lanes=3)
    s = town(2, n_frames=6, blocks=2, n_traffic=2, n_pedestrians=3, n_oncoming=1, ego_speed=9.0)
    assert s.n_frames == 6 and s.meta["ego_speed"] == 9.0
    assert np.allclose(np.linalg.norm(np.diff(s.ego_poses[:, :2], axis=0), axis=1), 4.5, rtol=0.03)
    assert sum(a.kind == "pedestrian" for a in s.actors) <= 3


# ----------------------------------------------------------------------------------------- box city
@pytest.mark.parametrize("n", [5_000, 60_000, 1_000_000])
def test_box_city_budget(n):
    m = box_city(n, seed=1)
    assert abs(m.n_faces - n) <= 0.01 * n
    assert set(np.unique(m.labels).tolist()) <= {C["building"], C["road"], C["ground"]}
    assert C["building"] in m.labels and C["road"] in m.labels
    ext = m.bounds[1] - m.bounds[0]
    assert 200 <= ext[0] <= 600 and 200 <= ext[1] <= 600


def test_box_city_boxes_closed():
    m = box_city(120_000, seed=2)
    box = m.labels == C["building"]
    first = int(np.argmax(box))
    assert box[first:].all(), "boxes must come after the ground"
    f = m.faces[first:].reshape(-1, 12, 3)
    nb = len(f)
    # each box: 8 own vertices, every directed edge paired with its reverse, positive volume
    vid = np.sort(f.reshape(nb, -1), axis=1)
    assert (np.diff(vid, axis=1) != 0).sum(1).tolist() == [7] * nb
    assert np.all(vid[1:, 0] > vid[:-1, -1]), "boxes must not share vertices"
    e = np.concatenate([f[:, :, [0, 1]], f[:, :, [1, 2]], f[:, :, [2, 0]]], axis=1)  # (nb, 36, 2)
    fwd = e[..., 0] * (len(m.vertices) + 1) + e[..., 1]
    rev = e[..., 1] * (len(m.vertices) + 1) + e[..., 0]
    fwd_s = np.sort(fwd, axis=1)
    rev_s = np.sort(rev, axis=1)
    assert np.array_equal(fwd_s, rev_s), "a box is not closed or is inconsistently wound"
    assert (np.diff(fwd_s, axis=1) != 0).all(), "a directed edge appears twice"
    tri = m.vertices[f]  # (nb, 12, 3, 3)
    tri = tri - tri.mean(axis=(1, 2), keepdims=True)
    vol = np.einsum("bij,bij->b", tri[:, :, 0], np.cross(tri[:, :, 1], tri[:, :, 2])) / 6.0
    assert (vol > 0).all()
    # a rig near the centre stands in a street, not inside a building
    lo, hi = tri.min(axis=(1, 2)), tri.max(axis=(1, 2))
    centre = m.vertices[f].mean(axis=(1, 2))
    inside = np.all(np.abs(centre[:, :2]) < (hi - lo)[:, :2] / 2 + 1.0, axis=1)
    assert not inside.any()


def test_box_city_deterministic():
    a, b, c = box_city(30_000, seed=4), box_city(30_000, seed=4), box_city(30_000, seed=5)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)
