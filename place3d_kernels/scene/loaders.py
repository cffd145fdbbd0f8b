"""Mesh scenes from files through trimesh (OBJ, PLY, GLB/GLTF, STL, and whatever else trimesh reads).

Labels: every face gets a Place3D class (``place3d_kernels.classes``), resolved per mesh in this order:

1. ``labels`` given as a mapping (a dict, or a TOML file path whose top-level keys or ``[labels]`` table
   map names to classes): the scene-graph node name, then the geometry name, is looked up; values are
   class ids (int) or class names ("road", "traffic sign", also "traffic_sign"); the key ``"*"`` is the
   fallback for unnamed meshes;
2. a per-face ``label`` property in a PLY file (as :func:`save_mesh` writes);
3. a node or geometry name that is a Place3D class name, optionally with a suffix (``road``,
   ``road.001``, ``traffic_sign_3``): what :func:`save_mesh` writes to OBJ / GLB / GLTF;
4. ``default`` (0, unlabeled).

``labels`` may also be a single int or class name for the whole file (the only option for STL).
Node transforms of GLB/GLTF scene graphs are applied. Vertices come back as float64 in the file's units
(metres) in this package's Z-up frame.

Up axes (``up_axis_for``): glTF (.glb, .gltf) is Y-up by the glTF 2.0 specification ("Coordinate System
and Units": +Y up, +Z forward, -X right), and trimesh reads and writes its coordinates as they are, so
``load_mesh`` rotates glTF meshes to Z-up by default: (x, y, z) -> (x, -z, y), a +90 degree turn about x,
the inverse of what Blender's glTF exporter applies, so a model built Z-up in Blender comes back as it
was built; ``save_mesh`` writes glTF Y-up by the opposite turn, so a round trip is exact. The other
formats carry no up axis and are read as Z-up. Pass ``up="z"`` or ``up="y"`` to override for one file.
The glTF forward axis (+Z, which becomes -y) is not turned to this package's forward (+x): check a
vehicle's orientation after loading.

:func:`combine` joins Scenes and Meshes into one Scene (static meshes concatenated, actors kept).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from place3d_kernels.classes import CLASSES
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.base import Scene
from place3d_kernels.scene.labels import class_from_name, load_label_map, resolve_class

__all__ = ["load_mesh", "save_mesh", "combine", "resolve_class", "load_label_map", "up_axis_for", "to_z_up"]

_FORMATS = ("obj", "ply", "glb", "gltf", "stl", "off")
#: formats whose specification fixes the up axis (glTF 2.0: +Y)
_Y_UP_FORMATS = ("glb", "gltf")


def up_axis_for(path, up: str | None = None) -> str:
    """``up`` ("z" or "y") when given, else the up axis of the file's format: "y" for glTF (.glb, .gltf),
    "z" for the rest.

    Raises:
        ValueError: ``up`` is neither None, "z" nor "y".
    """
    if up is None:
        return "y" if Path(path).suffix.lower().lstrip(".") in _Y_UP_FORMATS else "z"
    if str(up).lower() not in ("z", "y"):
        raise ValueError(f"up must be 'z' or 'y' (or None: from the file format), got {up!r}")
    return str(up).lower()


def to_z_up(vertices: np.ndarray, up: str) -> np.ndarray:
    """(N, 3) vertices of a file whose up axis is ``up`` in this package's Z-up frame: unchanged for "z";
    for "y", (x, y, z) -> (x, -z, y), a +90 degree turn about x (exact: a sign change and a swap)."""
    v = np.asarray(vertices, np.float64)
    if up == "y":
        return np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)
    return v


def _load_trimesh(path: Path, kind: str):
    import trimesh

    try:
        if kind in ("obj",):
            return trimesh.load(path, force="scene", process=False, split_objects=True, group_material=False,
                                maintain_order=True)
        return trimesh.load(path, process=False, file_type=kind)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise ValueError(f"{path}: cannot read as {kind.upper()} ({type(e).__name__}: {e})") from None


def _ply_face_labels(geom):
    raw = getattr(geom, "metadata", {}).get("_ply_raw")
    try:
        data = raw["face"]["data"]
        if "label" in data.dtype.names:
            return np.asarray(data["label"]).astype(np.int64).reshape(-1)
    except (KeyError, TypeError, AttributeError):
        pass
    return None


def load_mesh(path, labels=None, default=None, up: str | None = None, strict: bool = False) -> Mesh:
    """Read a mesh file into one labelled :class:`Mesh` (see the module docstring for label rules).

    Args:
        default: class of parts no rule labels. None (the default) means 0 (unlabeled) with a warning
            listing those parts (or ``ValueError`` when ``strict``); an explicit class is used silently.
        up: the file's up axis, "z" or "y"; None (the default) takes the format's (``up_axis_for``: Y for
            glTF, Z otherwise). Y-up vertices are turned to Z-up (``to_z_up``).
        strict: unlabelled parts are an error instead of a warning.

    Raises:
        ValueError: missing / unreadable / empty file, unknown class names, labels out of range, unlabelled
            parts with ``strict``.
    """
    import warnings

    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such mesh file")
    kind = path.suffix.lower().lstrip(".")
    if kind not in _FORMATS:
        raise ValueError(f"{path}: unsupported mesh format {path.suffix!r}; use one of {', '.join(_FORMATS)}")
    up = up_axis_for(path, up)
    explicit_default = default is not None
    default = resolve_class(0 if default is None else default, f"{path}: default ")
    whole = None
    mapping: dict[str, int] = {}
    if isinstance(labels, (int, np.integer, str)) and not (isinstance(labels, str) and Path(labels).suffix == ".toml"):
        whole = resolve_class(labels, f"{path}: ")
    elif labels is not None:
        mapping = load_label_map(labels)
    obj = _load_trimesh(path, kind)
    pieces = []  # (vertices, faces, names, face_labels or None)
    if isinstance(obj, trimesh.Scene):
        for node in obj.graph.nodes_geometry:
            T, gname = obj.graph[node]
            g = obj.geometry[gname]
            if not isinstance(g, trimesh.Trimesh) or len(g.faces) == 0:
                continue
            v = np.asarray(g.vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
            pieces.append((v, np.asarray(g.faces), (str(node), str(gname)), _ply_face_labels(g)))
    elif isinstance(obj, trimesh.Trimesh):
        name = obj.metadata.get("name") or obj.metadata.get("file_name") or path.stem
        pieces.append((np.asarray(obj.vertices, np.float64), np.asarray(obj.faces), (str(name),),
                       _ply_face_labels(obj)))
    else:
        raise ValueError(f"{path}: holds no triangle mesh (trimesh gave {type(obj).__name__})")
    if not pieces:
        raise ValueError(f"{path}: holds no triangles")
    verts, faces, labs = [], [], []
    unmapped: list[str] = []
    n = 0
    for v, f, names, flab in pieces:
        if whole is not None:
            lab = np.full(len(f), whole)
        else:
            cls = next((mapping[nm] for nm in names if nm in mapping), None)
            if cls is None and flab is not None:
                lab = flab
                if len(lab) != len(f) or lab.min() < 0 or lab.max() >= len(CLASSES):
                    raise ValueError(f"{path}: per-face labels must be {len(f)} values in 0..{len(CLASSES) - 1}")
            else:
                if cls is None:
                    cls = next((c for c in map(class_from_name, names) if c is not None), None)
                if cls is None and "*" not in mapping and not explicit_default:
                    unmapped.append("/".join(dict.fromkeys(names)))
                if cls is None:
                    cls = mapping.get("*", default)
                lab = np.full(len(f), cls)
        verts.append(v)
        faces.append(np.asarray(f, np.int64) + n)
        labs.append(lab)
        n += len(v)
    if unmapped:
        msg = (f"{path}: {len(unmapped)} mesh part(s) match no label rule and become class 0 (unlabeled): "
               f"{', '.join(sorted(set(unmapped)))}; map them in the labels file (or '*'), or pass default=")
        if strict:
            raise ValueError(msg)
        warnings.warn(msg, UserWarning, stacklevel=2)
    v = to_z_up(np.concatenate(verts), up)
    try:
        return Mesh(v, np.concatenate(faces), np.concatenate(labs))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def save_mesh(mesh: Mesh, path) -> Path:
    """Write a labelled Mesh so that :func:`load_mesh` reads the same labels back.

    PLY: one mesh with a per-face ``label`` property (face order kept). OBJ / GLB / GLTF: one object or
    node per class, named by the class (``road``, ``traffic_sign``); glTF Y-up as its specification says
    ((x, y, z) -> (x, z, -y), the inverse of ``to_z_up``). STL: geometry only (no labels).
    """
    import trimesh

    from place3d_kernels.atomic import atomic_write

    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in _FORMATS:
        raise ValueError(f"{path}: unsupported mesh format {path.suffix!r}; use one of {', '.join(_FORMATS)}")
    if kind in ("ply",):
        # written here (trimesh's writer stores float32 vertices): float64 vertices, int32 labels
        head = (f"ply\nformat binary_little_endian 1.0\ncomment place3d-kernels labelled mesh\n"
                f"element vertex {len(mesh.vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
                f"element face {mesh.n_faces}\nproperty list uchar int vertex_indices\nproperty int label\n"
                "end_header\n").encode()
        fd = np.zeros(mesh.n_faces, dtype=[("n", "u1"), ("v", "<i4", (3,)), ("label", "<i4")])
        fd["n"], fd["v"], fd["label"] = 3, mesh.faces, mesh.labels
        atomic_write(path, head + mesh.vertices.astype("<f8").tobytes() + fd.tobytes())
        return path
    if kind in ("stl", "off"):
        atomic_write(path, trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type=kind))
        return path
    verts = mesh.vertices
    if kind in _Y_UP_FORMATS:
        verts = np.stack([verts[:, 0], verts[:, 2], -verts[:, 1]], 1)
    scene = trimesh.Scene()
    for c in np.unique(mesh.labels):
        sel = mesh.labels == c
        f = mesh.faces[sel]
        used, inv = np.unique(f, return_inverse=True)
        name = CLASSES[int(c)].replace(" ", "_")
        scene.add_geometry(trimesh.Trimesh(verts[used], inv.reshape(-1, 3), process=False),
                           node_name=name, geom_name=name)
    out = scene.export(file_type=kind)
    if isinstance(out, dict):
        # glTF (.gltf) is a JSON file and the buffers it names beside it: each file written atomically, the
        # buffers first, so the JSON never names a missing one
        main = [k for k in out if k.endswith(".gltf")]
        for name, data in sorted(out.items(), key=lambda kv: kv[0] in main):
            atomic_write(path if name in main else path.parent / name, data)
        return path
    atomic_write(path, out)
    return path


def combine(parts, name: str = "combined", ego_poses=None, seed: int = 0) -> Scene:
    """One Scene from Scenes and Meshes.

    Static meshes are concatenated (Scenes' statics and plain Meshes); actors of every Scene are kept.
    The ego route is ``ego_poses`` if given, else the first Scene's, else one frame at the origin.
    All Scenes with actors must have the same number of frames as the route.
    """
    parts = list(parts)
    if not parts:
        raise ValueError("combine needs at least one Scene or Mesh")
    statics, actors, first = [], [], None
    meta = {"parts": []}
    for i, p in enumerate(parts):
        if isinstance(p, Scene):
            statics.append(p.static)
            actors.extend(p.actors)
            first = first or p
            meta["parts"].append(p.name)
        elif isinstance(p, Mesh):
            statics.append(p)
            meta["parts"].append(f"mesh{i}")
        else:
            raise ValueError(f"combine: part {i} is a {type(p).__name__}, expected a Scene or a Mesh")
    if ego_poses is None:
        ego_poses = first.ego_poses if first is not None else np.zeros((1, 6))
    ego_poses = np.asarray(ego_poses, np.float64).reshape(-1, 6)
    for a in actors:
        if len(a.poses) != len(ego_poses):
            raise ValueError(f"combine: actor {a.kind!r} has {len(a.poses)} poses for a route of {len(ego_poses)} frames")
    return Scene(static=Mesh.concatenate(statics), ego_poses=ego_poses, actors=actors, name=name, seed=seed,
                 frame_interval=first.frame_interval if first is not None else 0.5, meta=meta)
