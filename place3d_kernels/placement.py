"""A placement: the poses of all LiDARs of a rig in the ego frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from place3d_kernels._toml import config_dir, read_toml, require, resolve_config

__all__ = ["Placement", "PAPER_PLACEMENTS", "BASELINES", "CARLA_PUBLIC_PLACEMENTS"]

#: The eleven placements of the Place3D paper, in the order of its table.
PAPER_PLACEMENTS = ("center", "line", "pyramid", "square", "trapezoid", "line-roll", "pyramid-roll",
                    "ours-det", "ours-seg", "corruption", "2d-plane")
#: The seven heuristic baselines among them.
BASELINES = PAPER_PLACEMENTS[:7]
#: The authors' public CARLA rigs (ywyeli/Place3D carla_nus/hyperparams/4x16.toml), a second set of the
#: five heuristic baselines; see place3d_kernels/placement_sources.py.
CARLA_PUBLIC_PLACEMENTS = tuple(f"carla_public/{n}" for n in ("center", "line", "pyramid", "square", "trapezoid"))

_KEYS = ("x", "y", "z", "roll_rad", "pitch_rad", "yaw_rad")


class Placement:
    """Poses of L LiDARs, rows (x, y, z, roll, pitch, yaw) in metres and radians, ego frame
    (x forward, y left, z up, z = 0 on the ground under the vehicle centre).

    Args:
        poses: (L, 6) array, or (L, 4) rows (x, y, z, roll) as in the paper.
        name: optional label.
    """

    def __init__(self, poses, name: str = ""):
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim == 1:
            p = p[None]
        if p.ndim != 2 or p.shape[1] not in (3, 4, 6):
            raise ValueError(f"Placement poses must be (L, 6) or (L, 4) rows, got shape {p.shape}")
        if p.shape[1] < 6:
            p = np.concatenate([p, np.zeros((len(p), 6 - p.shape[1]))], axis=1)
        if len(p) == 0:
            raise ValueError("Placement needs at least one LiDAR")
        if not np.all(np.isfinite(p)):
            raise ValueError(f"Placement poses must be finite, got {p.tolist()}")
        self.poses = p
        self.name = name

    def __len__(self) -> int:
        return len(self.poses)

    def __repr__(self) -> str:
        return f"Placement({self.name!r}, {len(self)} LiDARs)"

    def __eq__(self, other) -> bool:
        return isinstance(other, Placement) and np.array_equal(self.poses, other.poses)

    @classmethod
    def load(cls, path_or_name) -> "Placement":
        """Read a placement TOML (a path, or a shipped name such as ``"pyramid"`` or
        ``"carla_public/pyramid"``; ``shipped_names()`` lists them)."""
        path = resolve_config(path_or_name, "placements")
        d = read_toml(path)
        rows = d.get("lidar")
        if not isinstance(rows, list) or not rows:
            raise ValueError(f"{path}: a placement needs one or more [[lidar]] tables")
        poses = []
        for i, r in enumerate(rows):
            if not isinstance(r, dict):
                raise ValueError(f"{path}: [[lidar]] entry {i} is not a table")
            unknown = set(r) - set(_KEYS) - {"name"}
            if unknown:
                raise ValueError(f"{path}: [[lidar]] entry {i} has unknown keys {sorted(unknown)}; "
                                 f"allowed: {list(_KEYS)}")
            poses.append([float(require(r, k, path)) if k in ("x", "y", "z") else float(r.get(k, 0.0))
                          for k in _KEYS])
        return cls(poses, name=str(d.get("name", Path(path).stem)))

    def save(self, path, note: str = "") -> Path:
        path = Path(path)
        lines = []
        if note:
            lines += [f"# {ln}" for ln in note.splitlines()]
        lines += ["# Frame: ego, x forward, y left, z up, z = 0 on the ground under the vehicle centre.",
                  "# Units: metres and radians.", f'name = "{self.name}"', ""]
        for p in self.poses:
            lines.append("[[lidar]]")
            lines += [f"{k} = {float(v)!r}" for k, v in zip(_KEYS, p)]
            lines.append("")
        from place3d_kernels.atomic import atomic_write_text

        atomic_write_text(path, "\n".join(lines))
        return path

    @staticmethod
    def all_paper() -> dict[str, "Placement"]:
        return {n: Placement.load(n) for n in PAPER_PLACEMENTS}

    @staticmethod
    def shipped_names() -> list[str]:
        """Names ``load`` takes: the paper's (``"pyramid"``) and the authors' public CARLA rigs
        (``"carla_public/center"``, ``CARLA_PUBLIC_PLACEMENTS``)."""
        root = config_dir("placements")
        return sorted(p.relative_to(root).with_suffix("").as_posix() for p in root.rglob("*.toml"))

    def min_distance(self) -> float:
        if len(self) < 2:
            return math.inf
        d = np.linalg.norm(self.poses[:, None, :3] - self.poses[None, :, :3], axis=-1)
        return float(d[np.triu_indices(len(self), 1)].min())
