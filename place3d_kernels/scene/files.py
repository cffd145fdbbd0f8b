"""One entry point for scene files: a mesh file through trimesh or a Mitsuba 3 XML scene.

It sits above both readers (``loaders`` for mesh files, ``mitsuba_xml`` for XML scenes, which itself reads
the mesh files its shapes reference), so neither imports the other's dispatcher.
"""

from __future__ import annotations

from pathlib import Path

from place3d_kernels.scene.base import Scene
from place3d_kernels.scene.loaders import combine, load_mesh
from place3d_kernels.scene.mitsuba_xml import load_mitsuba_scene

__all__ = ["load_scene", "load_mitsuba"]


def load_scene(path, labels=None, ego_poses=None, **kw) -> Scene:
    """A static Scene from one mesh file or a Mitsuba XML file (``ego_poses`` default: one frame at the
    origin)."""
    if Path(path).suffix.lower() == ".xml":
        return load_mitsuba(path, labels=labels, ego_poses=ego_poses, **kw)
    m = load_mesh(path, labels=labels, **kw)
    return combine([m], name=f"mesh-{Path(path).stem}", ego_poses=ego_poses)


def load_mitsuba(path, labels=None, ego_poses=None, **kw) -> Scene:
    """A static Scene from a Mitsuba 3 XML file (shapes referencing PLY/OBJ files, primitives);
    see place3d_kernels.scene.mitsuba_xml. Mitsuba itself is not needed."""
    return load_mitsuba_scene(path, labels=labels, ego_poses=ego_poses, **kw)
