"""place3d-kernels: fast, exact kernels for multi-LiDAR placement (Place3D, NeurIPS 2024).

Score a rig by M-SOG on the embedded town (the first call simulates 40 frames and caches the P-SOG in
``$PLACE3D_CACHE`` or ~/.cache/place3d; higher is better):

>>> import place3d_kernels as p3k
>>> p3k.available_backends()                            # doctest: +SKIP
['reference', 'warp:cpu', 'opencl:pocl']
>>> psog = p3k.scene_psog(p3k.scene.town(seed=0))
>>> lidar = p3k.LidarModel.load("place3d_16ch")
>>> round(p3k.msog(psog, lidar, p3k.Placement.load("pyramid"), task="seg"), 6)
-0.014106

The API by topic (each name has its own docstring):

- scenes and data: ``scene`` (``town``, ``from_opendrive``, ``load_mesh``, ``load_mitsuba_xml``), ``simulate``,
  ``PointCloud``, ``conditions`` (fog, wet_ground, snow, ...), ``place3d_kernels.io`` (SemanticKITTI);
- the metric: ``scene_psog`` / ``PSOG``, ``Grid`` / ``DEFAULT_GRID``, ``LidarModel``, ``Placement``
  (``PAPER_PLACEMENTS``, ``BASELINES``), ``msog``, ``msog_batch``, ``covered_voxels``; the S-MIG baseline
  ``smig`` / ``smig_batch``;
- optimisation: ``optimize`` with ``SearchSpace``, ``Bounds``, ``MinDistance``, ``FixedHeight``,
  ``FunctionConstraint`` -> ``OptimizeResult``;
- kernels: ``raycast`` (-> ``Hits``), ``traverse`` (-> ``Traversal``), ``coverage``, ``lidar_rays``, ``Mesh``;
- backends: ``available_backends``, ``backend_report``, ``get_backend``, ``use_backend``.

The same work from the shell is the ``place3d`` command (``docs/commands.md``: one section per
subcommand with a worked example); the README's Python snippet is run by ``tests/test_docs.py``.
"""

from place3d_kernels.backends.registry import available_backends, backend_report, get_backend, use_backend
from place3d_kernels.classes import CLASSES
from place3d_kernels.grid import DEFAULT_GRID, Grid
from place3d_kernels.lidar import LidarModel, lidar_rays
from place3d_kernels.mesh import Mesh
from place3d_kernels.metrics import covered_voxels, msog, msog_batch
from place3d_kernels.optimize import (Bounds, FixedHeight, FunctionConstraint, MinDistance, OptimizeResult,
                                      SearchSpace, optimize)
from place3d_kernels.ops import Hits, Traversal, coverage, raycast, traverse
from place3d_kernels.pipeline import scene_psog
from place3d_kernels.placement import BASELINES, PAPER_PLACEMENTS, Placement
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.simulate import simulate
from place3d_kernels.smig import BernoulliGrid, scene_boxes, smig, smig_batch
from place3d_kernels.sog import PSOG

from place3d_kernels.version import VERSION as __version__


def __getattr__(name):
    # ``p3k.scene`` and ``p3k.conditions`` load on first use: a run without adverse conditions, or one that
    # brings its own frames, never imports the condition models or the scene loaders
    if name in ("scene", "conditions"):
        import importlib

        return importlib.import_module(f"place3d_kernels.{name}")
    raise AttributeError(f"module 'place3d_kernels' has no attribute {name!r}")


__all__ = [
    "available_backends", "backend_report", "get_backend", "use_backend",
    "Grid", "DEFAULT_GRID", "Mesh", "PointCloud", "CLASSES",
    "LidarModel", "lidar_rays", "Placement", "PAPER_PLACEMENTS", "BASELINES",
    "raycast", "traverse", "coverage", "Hits", "Traversal",
    "PSOG", "msog", "msog_batch", "covered_voxels", "simulate", "scene_psog", "scene", "conditions",
    "smig", "smig_batch", "BernoulliGrid", "scene_boxes",
    "optimize", "SearchSpace", "OptimizeResult", "MinDistance", "FixedHeight", "Bounds", "FunctionConstraint",
]
