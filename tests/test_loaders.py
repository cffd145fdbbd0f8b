"""Mesh files through trimesh: labelled round trips, label maps, combine, errors."""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.mesh import Mesh
from place3d_kernels.scene import Scene, Actor
from place3d_kernels.scene.files import load_scene
from place3d_kernels.scene.loaders import combine, load_mesh, resolve_class, save_mesh
from place3d_kernels.scene.primitives import boxes


def labelled_mesh():
    v, f = boxes([(0, 0, 0.5), (5, 1, 1.0), (-4, 2, 2.0)], [(1, 2, 1), (2, 2, 2), (1, 1, 4)], [0.0, 0.3, 1.0])
    lab = np.repeat([7, 10, 12], 12)
    return Mesh(v, f, lab)


def canon(m: Mesh):
    """Faces as sorted (corner coordinates, label) rows: independent of vertex order and splitting."""
    tri = np.round(m.vertices[m.faces], 5)
    rows = np.concatenate([np.sort(tri.reshape(len(tri), 3, 3), axis=1).reshape(len(tri), 9),
                           m.labels[:, None]], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def test_ply_round_trip_exact(tmp_path):
    m = labelled_mesh()
    p = save_mesh(m, tmp_path / "m.ply")
    r = load_mesh(p)
    assert np.array_equal(r.vertices, m.vertices) and np.array_equal(r.faces, m.faces)
    assert np.array_equal(r.labels, m.labels)


@pytest.mark.parametrize("ext", ["obj", "glb", "gltf"])
def test_named_object_round_trip(tmp_path, ext):
    m = labelled_mesh()
    p = save_mesh(m, tmp_path / f"m.{ext}")
    r = load_mesh(p)
    assert r.n_faces == m.n_faces
    assert np.array_equal(canon(r), canon(m))


def test_label_map_dict_toml_and_transforms(tmp_path):
    import trimesh

    v, f = boxes([(0, 0, 0)], [(1, 1, 1)])
    s = trimesh.Scene()
    T = np.eye(4)
    T[:3, 3] = (10, 0, 0)
    s.add_geometry(trimesh.Trimesh(v, f, process=False), node_name="Tree_01", geom_name="g1")
    s.add_geometry(trimesh.Trimesh(v, f, process=False), node_name="car body", geom_name="g2", transform=T)
    s.add_geometry(trimesh.Trimesh(v, f, process=False), node_name="thing", geom_name="g3")
    p = tmp_path / "s.glb"
    s.export(p)
    r = load_mesh(p, labels={"Tree_01": "vegetation", "car body": 10, "*": "static"})
    assert sorted(np.unique(r.labels).tolist()) == [9, 10, 18]
    assert np.allclose(r.vertices[r.faces[r.labels == 10]].mean(axis=(0, 1)), (10, 0, 0))
    toml = tmp_path / "labels.toml"
    toml.write_text('[labels]\n"Tree_01" = "vegetation"\n"g2" = "vehicle"\n')
    r2 = load_mesh(p, labels=toml, default="other")
    assert sorted(np.unique(r2.labels).tolist()) == [3, 9, 10]
    assert set(load_mesh(p, labels="building").labels.tolist()) == {1}


def test_stl_whole_file_label_and_scene(tmp_path):
    m = labelled_mesh()
    p = save_mesh(m, tmp_path / "m.stl")
    r = load_mesh(p, labels="building")
    assert r.n_faces == m.n_faces and set(r.labels.tolist()) == {1}
    sc = load_scene(p, labels=1)
    assert sc.n_frames == 1 and sc.static.n_faces == m.n_faces


def test_combine_scenes_and_meshes():
    m = labelled_mesh()
    ego = np.zeros((3, 6))
    ego[:, 0] = [0, 1, 2]
    a = Actor(m, np.zeros((3, 6)), "vehicle")
    s = Scene(static=m, ego_poses=ego, actors=[a], name="a")
    c = combine([s, m], name="both")
    assert c.static.n_faces == 2 * m.n_faces and c.n_frames == 3 and len(c.actors) == 1
    assert np.array_equal(c.static.labels, np.concatenate([m.labels, m.labels]))
    with pytest.raises(ValueError, match="poses for a route of 1 frames"):
        combine([s], ego_poses=np.zeros(6))
    with pytest.raises(ValueError, match="expected a Scene or a Mesh"):
        combine([m, "x"])
    with pytest.raises(ValueError, match="at least one"):
        combine([])


def test_resolve_class():
    assert resolve_class("traffic_sign") == 12 and resolve_class("Road") == 7 and resolve_class(21) == 21
    with pytest.raises(ValueError, match="unknown class name"):
        resolve_class("spaceship")
    with pytest.raises(ValueError, match="outside"):
        resolve_class(22)


@pytest.mark.parametrize("name, data, msg", [
    ("bad.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n\x00",
     "cannot read as PLY"),
    ("bad.glb", b"glTF garbage", "cannot read as GLB"),
    ("bad.obj", b"this is not an obj\n", "holds no triangles|cannot read as OBJ|no triangle mesh"),
    ("bad.xyz", b"1 2 3", "unsupported mesh format"),
])
def test_malformed_files(tmp_path, name, data, msg):
    p = tmp_path / name
    p.write_bytes(data)
    with pytest.raises(ValueError, match=msg) as e:
        load_mesh(p)
    assert name in str(e.value)


def test_missing_and_bad_label_maps(tmp_path):
    with pytest.raises(ValueError, match="no such mesh file"):
        load_mesh(tmp_path / "none.obj")
    p = save_mesh(labelled_mesh(), tmp_path / "m.obj")
    with pytest.raises(ValueError, match="unknown class name 'lava'"):
        load_mesh(p, labels={"road": "lava"})
    bad = tmp_path / "bad.toml"
    bad.write_text("[labels\n")
    with pytest.raises(ValueError, match="bad.toml: not a valid TOML"):
        load_mesh(p, labels=bad)


# ---------------------------------------------------------------------------- point-cloud formats
from place3d_kernels import io as p3k_io  # noqa: E402
from place3d_kernels import io as iof  # noqa: E402
from place3d_kernels.pointcloud import PointCloud  # noqa: E402
from place3d_kernels.sog import PSOG  # noqa: E402
from place3d_kernels.grid import Grid  # noqa: E402
from place3d_kernels.pose import pose_matrix, transform_points  # noqa: E402


def synthetic_frames(n=6, seed=0):
    """Frames whose points sit at voxel centres of the ego grid (robust to float32 storage)."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        ego = np.array([2.0 * i, 0.5 * i, 0.3, 0.0, 0.01 * i, 0.1 * i])
        ijk = rng.integers(0, 10, size=(300, 3))
        local = (ijk + 0.5) * 1.0 + np.array([-5.0, -5.0, 0.0])
        world = transform_points(pose_matrix(ego), local)
        lab = rng.integers(0, 22, size=300).astype(np.int32)
        origin = transform_points(pose_matrix(ego), np.array([[0.0, 0.0, 2.5]]))[0]
        frames.append(PointCloud(world, lab, rng.random(300).astype(np.float32), origin[None], ego_pose=ego))
    return frames


def test_sequence_round_trip_psog(tmp_path):
    frames = synthetic_frames()
    p3k_io.write_semantickitti_sequence(frames, tmp_path / "seq")
    back = iof.read_sequence(tmp_path / "seq", labels="place3d")
    assert len(back) == len(frames)
    for a, b in zip(frames, back):
        assert np.allclose(a.points, b.points, atol=1e-4)
        assert np.array_equal(a.labels, b.labels)
        assert np.allclose(a.ego_pose, b.ego_pose, atol=1e-6)
    grid = Grid(lower=(-5, -5, 0), upper=(5, 5, 10), voxel_size=1.0)
    ref = PSOG.from_frames(frames, grid, frames_per_subset=2, backend="reference")
    got = iof.psog_from_semantickitti(tmp_path / "seq", grid, 2, labels="place3d", backend="reference")
    assert np.array_equal(ref.voxels, got.voxels) and np.array_equal(ref.probs, got.probs)


def test_semantickitti_remap(tmp_path):
    pts = np.zeros((5, 4), np.float32)
    (tmp_path / "a.bin").write_bytes(pts.tobytes())
    raw = np.array([10, 40 | (7 << 16), 254, 72, 1], np.uint32)
    (tmp_path / "a.label").write_bytes(raw.tobytes())
    _, _, lab = iof.read_semantickitti(tmp_path / "a.bin", tmp_path / "a.label")
    assert lab.tolist() == [10, 7, 4, 21, 0]
    (tmp_path / "b.label").write_bytes(np.array([10, 40, 5, 72, 1], np.uint32).tobytes())
    with pytest.raises(ValueError, match=r"b.label: SemanticKITTI label ids \[5\]"):
        iof.read_semantickitti(tmp_path / "a.bin", tmp_path / "b.label")
    assert iof.read_semantickitti(tmp_path / "a.bin", tmp_path / "b.label", strict=False)[2][2] == 0
    assert set(iof.SEMANTICKITTI_TO_PLACE3D.values()) <= set(range(22))


def test_semantickitti_malformed(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"\x00" * 17)
    with pytest.raises(ValueError, match="a.bin: size 17 bytes"):
        iof.read_semantickitti(tmp_path / "a.bin")
    (tmp_path / "c.bin").write_bytes(np.zeros((3, 4), np.float32).tobytes())
    (tmp_path / "c.label").write_bytes(np.zeros(2, np.uint32).tobytes())
    with pytest.raises(ValueError, match="c.label: 2 labels for 3 points"):
        iof.read_semantickitti(tmp_path / "c.bin", tmp_path / "c.label")
    seq = tmp_path / "seq"
    p3k_io.write_semantickitti_sequence(synthetic_frames(2), seq)
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="poses.txt: line 1 has 11 numbers"):
        iof.read_sequence(seq, labels="place3d")
    with pytest.raises(ValueError, match="no velodyne/ folder"):
        iof.read_sequence(tmp_path)


def carla_ply(path, rows, fmt="ascii"):
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(rows)}\nproperty float32 x\nproperty float32 y\n"
            "property float32 z\nproperty float32 CosAngle\nproperty uint32 ObjIdx\nproperty uint32 ObjTag\nend_header\n")
    if fmt == "ascii":
        path.write_text(head + "".join(" ".join(str(v) for v in r) + "\n" for r in rows))
    else:
        dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("c", "<f4"), ("o", "<u4"), ("t", "<u4")])
        a = np.array([tuple(r) for r in rows], dtype=dt)
        path.write_bytes(head.encode() + a.tobytes())


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_carla_ply(tmp_path, fmt):
    rows = [(1.5, -2.0, 0.25, 0.9, 17, 7), (3.0, 1.0, 1.0, 0.5, 42, 10), (0.0, 0.0, 5.0, 0.1, 0, 13),
            (2.0, 2.0, 0.0, 0.3, 3, 22)]
    carla_ply(tmp_path / "f.ply", rows, fmt)
    c = iof.read_carla_ply(tmp_path / "f.ply")
    assert np.allclose(c.points, [(r[0], -r[1], r[2]) for r in rows])   # CARLA's y right -> y left
    assert c.labels.tolist() == [7, 10, 0, 21] and c.object_id.tolist() == [17, 42, 0, 3]
    assert np.allclose(c.cos_angle, [0.9, 0.5, 0.1, 0.3])
    c2 = iof.read_carla_ply(tmp_path / "f.ply", tags="cityscapes")
    assert c2.labels.tolist() == [17, 21, 4, 3]  # cityscapes tags: 7 light, 10 terrain, 13 rider, 22 other -> 3


def test_carla_ply_malformed(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n")
    with pytest.raises(ValueError, match=r"x.ply: vertex properties \['ObjTag'\] missing"):
        iof.read_carla_ply(p)
    carla_ply(p, [(1, 2, 3, 0.5, 1, 99)])
    with pytest.raises(ValueError, match="x.ply: ObjTag 99 outside"):
        iof.read_carla_ply(p)
    carla_ply(p, [(1, 2, 3, 0.5, 1, 9)] * 3, "binary_little_endian")
    p.write_bytes(p.read_bytes()[:-5])
    with pytest.raises(ValueError, match="x.ply: truncated"):
        iof.read_carla_ply(p)
    p.write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="x.ply: not a PLY file"):
        iof.read_carla_ply(p)


def _y_up_truck_glb(path, ext="glb"):
    """A glTF truck as glTF 2.0 lays it out: +Y up (2.5 m tall), 6 m long along X, 2 m wide along Z,
    wheels on y = 0; made and written by trimesh (which writes coordinates as they are)."""
    import trimesh

    box = trimesh.creation.box(extents=(6.0, 2.5, 2.0),
                               transform=trimesh.transformations.translation_matrix([0.0, 1.25, 0.0]))
    s = trimesh.Scene()
    s.add_geometry(box, node_name="vehicle", geom_name="vehicle")
    p = path / f"truck.{ext}"
    s.export(p)
    return p


@pytest.mark.parametrize("ext", ["glb", "gltf"])
def test_gltf_is_read_y_up_and_turned_z_up(tmp_path, ext):
    # a Y-up glTF used as-is lay on its side: 2 m tall and 2.5 m wide, half under the ground
    p = _y_up_truck_glb(tmp_path, ext)
    m = load_mesh(p)
    lo, hi = m.bounds
    np.testing.assert_allclose(lo, [-3.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(hi, [3.0, 1.0, 2.5], atol=1e-12)
    assert set(m.labels.tolist()) == {10}
    # the axis can be given for a file that breaks the specification
    np.testing.assert_allclose(load_mesh(p, up="z").bounds, [[-3.0, 0.0, -1.0], [3.0, 2.5, 1.0]], atol=1e-12)
    with pytest.raises(ValueError, match="up must be"):
        load_mesh(p, up="x")


def test_formats_without_an_up_axis_stay_z_up(tmp_path):
    m = labelled_mesh()
    for ext in ("obj", "ply", "stl"):
        r = load_mesh(save_mesh(m, tmp_path / f"m.{ext}"), labels=0 if ext == "stl" else None)
        np.testing.assert_allclose(r.bounds, m.bounds, atol=1e-5)
    # and glTF written by save_mesh is Y-up in the file, Z-up again when read
    import trimesh

    p = save_mesh(m, tmp_path / "m.glb")
    raw = trimesh.load(p, force="mesh")
    np.testing.assert_allclose(raw.bounds[:, 1], m.bounds[:, 2], atol=1e-6)       # file's y is our z
    assert np.array_equal(canon(load_mesh(p)), canon(m))
