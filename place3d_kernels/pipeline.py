"""The end-to-end path: scene -> semantic frames -> P-SOG, cached on disk by its inputs."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from place3d_kernels.grid import DEFAULT_GRID, Grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.simulate import DEFAULT_MOUNT, simulate
from place3d_kernels.sog import PSOG, cache_dir, cache_key

__all__ = ["scene_psog", "DEFAULT_FRAMES_PER_SUBSET"]

log = logging.getLogger(__name__)

#: Frames merged into one SOG: 40 frames -> T = 10 subsets, each spanning 2 s of driving.
DEFAULT_FRAMES_PER_SUBSET = 4


def scene_psog(scene, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
               frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT, backend=None,
               cache: bool | str | Path = True, progress: bool = False, condition=None) -> PSOG:
    """The P-SOG of a scene: simulate its frames with the collection LiDAR, vote, aggregate.

    The result is cached on disk (``$PLACE3D_CACHE`` or ~/.cache/place3d) under a key made of every
    input (scene identity, grid, sensor, mount, subset size, condition), so a second call skips the
    simulation. ``cache=False`` disables it; a path chooses the folder.

    Args:
        condition: optional callable ``frame_cloud -> frame_cloud`` applied to each simulated frame
            (adverse conditions); it must carry a ``key`` attribute for the cache.
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    path = None
    if cache:
        folder = Path(cache) if isinstance(cache, (str, Path)) else cache_dir()
        key = cache_key(scene=scene.key, grid=grid.to_dict(), lidar=[lidar.name, lidar.elevations.tolist(),
                        lidar.azimuths.size, lidar.max_range], mount=np.asarray(mount).tolist(),
                        k=frames_per_subset, condition=getattr(condition, "key", None))
        path = folder / f"psog-{scene.name}-{key}.npz"
        if path.exists():
            try:
                return PSOG.load(path)
            except Exception as e:  # noqa: BLE001 - a broken cache file is rebuilt, not fatal
                log.warning("ignoring unreadable P-SOG cache %s: %s", path, e)
    frames = simulate(scene, lidar, mount=mount, backend=backend, progress=progress)
    if condition is not None:
        frames = [condition(f) for f in frames]
    psog = PSOG.from_frames(frames, grid, frames_per_subset, backend=backend, progress=progress)
    if path is not None:
        psog.save(path)
    return psog
