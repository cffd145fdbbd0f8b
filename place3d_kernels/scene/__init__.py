"""Scenes: the embedded procedural town, CARLA OpenDRIVE towns, mesh files, and a box city for benchmarks."""

from place3d_kernels.scene.base import Actor, Scene
from place3d_kernels.scene.city import box_city
from place3d_kernels.scene.files import load_mitsuba, load_scene
from place3d_kernels.scene.loaders import combine, load_mesh
from place3d_kernels.scene.mitsuba_xml import load_mitsuba_scene, load_mitsuba_xml
from place3d_kernels.scene.opendrive import from_opendrive
from place3d_kernels.scene.town import town

__all__ = ["Scene", "Actor", "town", "box_city", "from_opendrive", "load_mesh", "load_scene", "combine",
           "load_mitsuba", "load_mitsuba_xml", "load_mitsuba_scene"]
