"""Scenes: the embedded procedural town and loaders."""

from place3d_kernels.scene.base import Actor, Scene
from place3d_kernels.scene.city import box_city
from place3d_kernels.scene.town import town

__all__ = ["Scene", "Actor", "town", "box_city"]
