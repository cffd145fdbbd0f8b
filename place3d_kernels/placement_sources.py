"""Where the shipped placement files come from: the sources' own numbers in CARLA's frame, and the one
conversion (``carla_frame.pose_from_carla``) that turns them into ``configs/placements/*.toml``.

Two sets:

- ``PAPER_TABLE``: the Place3D paper's appendix Table ``tab:placement`` (Li et al., NeurIPS 2024; also
  REFERENCE.md section 2), rows (x, y, z, roll) per LiDAR in CARLA's frame (y right). The roll column is
  read as radians (docs/assumptions.md, "Roll units"). Files: ``configs/placements/<name>.toml``.
- ``CARLA_PUBLIC``: the rigs of the authors' public collection code, ywyeli/Place3D
  ``carla_nus/hyperparams/4x16.toml`` (commit aafe9aabeb4acc48fd991b8e34f2dde168c27b63), sets 1-5 (its
  set 0 is a two-unit 32-channel rig, not a four-LiDAR placement). Its x, y, z, roll and pitch go
  unchanged into CARLA sensor specs (``carla_nus/scenario_runner/lidar.py``, yaw 0), so the angles are
  CARLA degrees (all zero in the file). Each rig mixes two sensors (``CARLA_PUBLIC_FOV``): LiDARs with
  lower/upper FOV -14/+2 deg (preset ``place3d_16ch_carla_narrow``) and -25/+5 deg
  (``place3d_16ch_carla``). Files: ``configs/placements/carla_public/<name>.toml``, loaded as
  ``Placement.load("carla_public/center")``.

``python -m place3d_kernels.placement_sources`` rewrites every file; ``tests/test_carla_frame.py``
checks that the shipped files equal what this module derives.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from place3d_kernels._toml import config_dir
from place3d_kernels.carla_frame import pose_from_carla
from place3d_kernels.placement import Placement

__all__ = ["PAPER_TABLE", "CARLA_PUBLIC", "CARLA_PUBLIC_FOV", "PUBLIC_PREFIX", "paper_placement",
           "public_placement", "write_all"]

#: Appendix tab:placement, CARLA frame: per placement four LiDARs (x m, y m (right), z m, roll rad).
PAPER_TABLE = {
    "center": ((0, 0, 2.2, 0), (0, 0, 2.4, 0), (0, 0, 2.6, 0), (0, 0, 2.8, 0)),
    "line": ((0, -0.6, 2.2, 0), (0, -0.4, 2.2, 0), (0, 0.4, 2.2, 0), (0, 0.6, 2.2, 0)),
    "pyramid": ((-0.2, -0.6, 2.2, 0), (0.4, 0, 2.4, 0), (-0.2, 0, 2.6, 0), (-0.2, 0.6, 2.2, 0)),
    "square": ((-0.5, 0.5, 2.2, 0), (-0.5, -0.5, 2.2, 0), (0.5, 0.5, 2.2, 0), (0.5, -0.5, 2.2, 0)),
    "trapezoid": ((-0.4, 0.2, 2.2, 0), (-0.4, -0.2, 2.2, 0), (0.2, 0.5, 2.2, 0), (0.2, -0.5, 2.2, 0)),
    "line-roll": ((0, -0.6, 2.2, -0.3), (0, -0.4, 2.2, 0), (0, 0.4, 2.2, 0), (0, 0.6, 2.2, -0.3)),
    "pyramid-roll": ((-0.2, -0.6, 2.2, -0.3), (0.4, 0, 2.4, 0), (-0.2, 0, 2.6, 0), (-0.2, 0.6, 2.2, -0.3)),
    "ours-det": ((0.5, 0.5, 2.5, -0.3), (-0.4, 0.1, 2.6, -0.2), (0, 0, 2.8, 0), (-0.1, -0.5, 2.7, 0)),
    "ours-seg": ((0, 0.5, 2.6, -0.3), (0.6, 0.3, 2.8, 0), (0.4, 0, 2.5, 0), (0.1, -0.6, 2.8, 0.2)),
    "corruption": ((0.4, 0.5, 2.6, -0.3), (0.5, -0.4, 2.7, 0), (-0.4, -0.3, 2.7, 0.1), (-0.3, 0.5, 2.7, 0)),
    "2d-plane": ((0.6, 0.6, 2.2, 0), (0.5, -0.4, 2.2, 0), (-0.5, -0.6, 2.2, 0), (-0.6, 0.3, 2.2, 0)),
}
_KIND = {"ours-det": "optimised for detection", "ours-seg": "optimised for segmentation",
         "corruption": "optimised on corrupted data", "2d-plane": "optimised at one height"}

#: 4x16.toml sets 1-5, CARLA frame: per placement four LiDARs (x m, y m (right), z m, roll deg, pitch deg).
CARLA_PUBLIC = {
    "center": ((0.0, 0.0, 1.8, 0, 0), (0.0, 0.0, 2.0, 0, 0), (0.0, 0.0, 2.2, 0, 0), (0.0, 0.0, 2.4, 0, 0)),
    "line": ((0.0, -0.6, 1.8, 0, 0), (0.0, -0.4, 2.2, 0, 0), (0.0, 0.4, 2.2, 0, 0), (0.0, 0.6, 1.8, 0, 0)),
    "pyramid": ((-0.8, -0.6, 1.8, 0, 0), (0.2, 0.0, 2.0, 0, 0), (-0.6, 0.0, 2.4, 0, 0), (-0.8, 0.6, 1.8, 0, 0)),
    "square": ((-1.0, 0.5, 2.0, 0, 0), (-1.0, -0.5, 2.0, 0, 0), (0.2, 0.5, 2.2, 0, 0), (0.2, -0.5, 2.2, 0, 0)),
    "trapezoid": ((-0.6, 0.6, 2.0, 0, 0), (-0.6, -0.6, 2.0, 0, 0), (0.2, 0.4, 1.8, 0, 0), (0.2, -0.4, 1.8, 0, 0)),
}
#: 4x16.toml lower_fov / upper_fov of each LiDAR of sets 1-5 (degrees).
CARLA_PUBLIC_FOV = {
    "center": ((-14.0, 2.0), (-14.0, 2.0), (-25.0, 5.0), (-25.0, 5.0)),
    "line": ((-14.0, 2.0), (-25.0, 5.0), (-25.0, 5.0), (-14.0, 2.0)),
    "pyramid": ((-14.0, 2.0), (-25.0, 5.0), (-25.0, 5.0), (-14.0, 2.0)),
    "square": ((-14.0, 2.0), (-25.0, 5.0), (-25.0, 5.0), (-14.0, 2.0)),
    "trapezoid": ((-25.0, 5.0), (-25.0, 5.0), (-14.0, 2.0), (-14.0, 2.0)),
}
#: The folder (and name prefix) of the public set under configs/placements/.
PUBLIC_PREFIX = "carla_public"

_CONVENTION = ("CARLA's frame (x forward, y RIGHT, z up, degrees) -> this package's (y LEFT, radians) by\n"
               "place3d_kernels.carla_frame.pose_from_carla: flip y, pitch and yaw; keep roll.")


def paper_placement(name: str) -> Placement:
    """The paper's placement ``name`` in this package's frame (roll column read as radians)."""
    rows = PAPER_TABLE[name]
    return Placement(np.stack([pose_from_carla(x, y, z, roll=r, unit="rad") for x, y, z, r in rows]), name)


def public_placement(name: str) -> Placement:
    """The authors' public CARLA rig ``name`` (``CARLA_PUBLIC``) in this package's frame."""
    rows = CARLA_PUBLIC[name]
    return Placement(np.stack([pose_from_carla(x, y, z, roll=r, pitch=p, unit="deg") for x, y, z, r, p in rows]),
                     f"{PUBLIC_PREFIX}/{name}")


def _paper_note(name: str) -> str:
    kind = _KIND.get(name, "heuristic baseline")
    return "\n".join([
        f'Place3D paper placement "{name}" ({kind}); Li et al., NeurIPS 2024, appendix Table tab:placement.',
        "Source rows (CARLA frame, y right; roll as printed, read as radians, see docs/assumptions.md):",
        *(f"  LiDAR {i + 1}: x {x}, y {y}, z {z}, roll {r}" for i, (x, y, z, r) in enumerate(PAPER_TABLE[name])),
        _CONVENTION,
        "Generated by python -m place3d_kernels.placement_sources; edit the table there, not this file."])


def _public_note(name: str) -> str:
    return "\n".join([
        f'The authors\' public CARLA rig "{name}": github.com/ywyeli/Place3D, carla_nus/hyperparams/4x16.toml',
        "(commit aafe9aabeb4acc48fd991b8e34f2dde168c27b63), the set commented '" + name + "'.",
        "Source rows (CARLA frame, y right, z above the vehicle origin near the ground; roll, pitch in degrees):",
        *(f"  LiDAR {i + 1}: x {x}, y {y}, z {z}, roll {r}, pitch {p}; lower_fov {lo}, upper_fov {hi}"
          for i, ((x, y, z, r, p), (lo, hi)) in enumerate(zip(CARLA_PUBLIC[name], CARLA_PUBLIC_FOV[name]))),
        "Sensors: -14/+2 deg is preset place3d_16ch_carla_narrow, -25/+5 deg is place3d_16ch_carla (a",
        "placement shares one LiDAR model, so scoring with either preset approximates this mixed rig).",
        _CONVENTION,
        "Generated by python -m place3d_kernels.placement_sources; edit the table there, not this file."])


def write_all(root: Path | None = None) -> list[Path]:
    """Write every paper and public placement file under ``root`` (default: the shipped folder)."""
    root = Path(root) if root is not None else config_dir("placements")
    (root / PUBLIC_PREFIX).mkdir(parents=True, exist_ok=True)
    out = [paper_placement(n).save(root / f"{n}.toml", _paper_note(n)) for n in PAPER_TABLE]
    out += [public_placement(n).save(root / PUBLIC_PREFIX / f"{n}.toml", _public_note(n)) for n in CARLA_PUBLIC]
    return out


if __name__ == "__main__":
    for p in write_all():
        print(p)
