"""The ego vehicle's body: a triangle mesh in the ego frame that blocks LiDAR rays.

Ego frame as everywhere in the package: x forward, y left, z up, z = 0 on the ground under the vehicle
centre (see ``Placement``). A body is a labelled ``Mesh`` (class "vehicle") plus, for parametric bodies,
the boxes it was built from (exact inside tests). Rays of a rig end where they first hit the body
(``place3d_kernels.rig_metrics``); a LiDAR whose origin lies inside the body is infeasible.

Parametric presets (``VehicleBody.preset``) are two boxes, a lower body and a cabin, sized from published
exterior dimensions of one named model per class (rounded to 1 cm; the shapes are envelopes, not styling):

* ``car``: Lincoln MKZ 2017 (the CARLA blueprint ``vehicle.lincoln.mkz_2017`` often used as the ego
  vehicle): 4.93 m x 1.86 m x 1.48 m (Lincoln, 2017 MKZ specifications).
* ``suv``: Toyota RAV4 2019: 4.60 m x 1.86 m x 1.70 m (Toyota, 2019 RAV4 specifications).
* ``van``: Ford Transit 2020, regular length, medium roof: 5.53 m x 2.06 m x 2.47 m (Ford, 2020 Transit
  specifications; width without mirrors).
* ``truck``: Ford F-150 2021 SuperCrew, 5.5 ft box: 5.89 m x 2.03 m x 1.96 m (Ford, 2021 F-150
  specifications; width without mirrors).

The cabin and hood proportions below are illustrative (about 55 % of the length for a car's cabin),
chosen so the roof is where a roof rack would go; use ``VehicleBody.load`` for a real shape.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh

__all__ = ["VehicleBody", "PRESETS", "box_mesh"]


@dataclass(frozen=True)
class _Preset:
    length: float
    width: float
    height: float
    shoulder: float        # top of the lower body (hood / belt line), metres above ground
    cabin_front: float     # cabin extent along x, as fractions of the length from the rear (0) to the front (1)
    cabin_rear: float
    cabin_width: float     # cabin width as a fraction of the width
    clearance: float       # ground clearance
    source: str


#: Parametric bodies (see the module docstring for the sources of the exterior dimensions).
PRESETS: dict[str, _Preset] = {
    "car": _Preset(4.93, 1.86, 1.48, 0.95, 0.70, 0.18, 0.86, 0.14, "Lincoln MKZ 2017"),
    "suv": _Preset(4.60, 1.86, 1.70, 1.05, 0.78, 0.08, 0.90, 0.20, "Toyota RAV4 2019"),
    "van": _Preset(5.53, 2.06, 2.47, 1.10, 0.82, 0.00, 0.96, 0.17, "Ford Transit 2020 (medium roof)"),
    "truck": _Preset(5.89, 2.03, 1.96, 1.15, 0.72, 0.36, 0.94, 0.22, "Ford F-150 2021 SuperCrew"),
}

_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]], dtype=np.int32)


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward-wound faces (12, 3) of the axis-aligned box [lo, hi]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ValueError(f"box needs lower < upper corner on every axis, got {lo.tolist()} and {hi.tolist()}")
    x = [lo[0], hi[0], hi[0], lo[0]]
    y = [lo[1], lo[1], hi[1], hi[1]]
    v = np.array([[x[i], y[i], lo[2]] for i in range(4)] + [[x[i], y[i], hi[2]] for i in range(4)])
    return v, _BOX_FACES.copy()


# three skewed directions for the parity test (majority vote): a ray through a shared edge or vertex of a
# loaded mesh, which could count one crossing twice, is then outvoted
_PARITY_DIRS = np.array([[0.5773, 0.6211, 0.5301], [-0.3411, 0.8127, -0.4723], [0.7071, -0.1173, -0.6973]])


def _parity_inside(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Inside test for a closed mesh: a point is inside when rays from it cross the surface an odd number
    of times (the watertight ray/triangle test, float64, every face)."""
    from place3d_kernels.backends.geometry import watertight_intersect

    v, f = mesh.vertices, mesh.faces
    v0, v1, v2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    votes = np.zeros(len(points), dtype=np.int64)
    chunk = max(1, 200_000 // max(len(f), 1))
    for d in _PARITY_DIRS / np.linalg.norm(_PARITY_DIRS, axis=1, keepdims=True):
        for s in range(0, len(points), chunk):
            o = points[s:s + chunk]
            t = watertight_intersect(o, np.tile(d, (len(o), 1)), v0, v1, v2, np.full(len(o), np.inf))
            votes[s:s + chunk] += (np.isfinite(t).sum(axis=1) % 2).astype(np.int64)
    return votes >= 2


class VehicleBody:
    """The ego vehicle as a mesh in the ego frame.

    Args:
        mesh: the body's triangles (ego frame, metres, z = 0 on the ground).
        name: label (preset name or file name).
        boxes: optional (K, 2, 3) axis-aligned boxes whose union is the body (parametric bodies); when
            given, ``contains`` is exact, otherwise a ray-parity test (the mesh should be closed).
    """

    def __init__(self, mesh: Mesh, name: str = "", boxes=None):
        if not isinstance(mesh, Mesh):
            raise TypeError(f"VehicleBody needs a place3d_kernels.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.name = name
        self.boxes = None if boxes is None else np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_boxes(cls, boxes, name: str = "") -> "VehicleBody":
        """A body made of axis-aligned boxes ((K, 2, 3): lower and upper corners), labelled "vehicle"."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
        vs, fs = [], []
        for k, (lo, hi) in enumerate(boxes):
            v, f = box_mesh(lo, hi)
            vs.append(v)
            fs.append(f + 8 * k)
        faces = np.concatenate(fs)
        mesh = Mesh(np.concatenate(vs), faces, np.full(len(faces), CLASS_ID["vehicle"]))
        return cls(mesh, name, boxes)

    @classmethod
    def box(cls, length: float, width: float, height: float, clearance: float = 0.0, x_center: float = 0.0,
            name: str = "box") -> "VehicleBody":
        """One box: ``length`` along x, ``width`` along y, from ``clearance`` up to ``height``, centred on
        ``x_center``, y = 0.

        Raises:
            ValueError: a dimension is not positive, or the clearance is not below the height.
        """
        for what, v in (("length", length), ("width", width), ("height", height)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"VehicleBody.box {what} must be a positive number of metres, got {v!r}")
        if not 0.0 <= clearance < height:
            raise ValueError(f"VehicleBody.box clearance must lie in [0, height={height}), got {clearance!r}")
        lo = [x_center - length / 2, -width / 2, clearance]
        hi = [x_center + length / 2, width / 2, height]
        return cls.from_boxes([[lo, hi]], name)

    @classmethod
    def preset(cls, name: str) -> "VehicleBody":
        """A parametric body by class name: ``car``, ``suv``, ``van`` or ``truck`` (see ``PRESETS``)."""
        key = str(name).strip().lower()
        if key not in PRESETS:
            raise ValueError(f"unknown vehicle preset {name!r}; choose one of {sorted(PRESETS)}, or load a "
                             f"mesh with VehicleBody.load(path)")
        p = PRESETS[key]
        L, W = p.length, p.width
        lower = [[-L / 2, -W / 2, p.clearance], [L / 2, W / 2, p.shoulder]]
        cw = p.cabin_width * W
        cabin = [[-L / 2 + p.cabin_rear * L, -cw / 2, p.shoulder], [-L / 2 + p.cabin_front * L, cw / 2, p.height]]
        return cls.from_boxes([lower, cabin], key)

    @classmethod
    def load(cls, path, name: str | None = None, up: str | None = None) -> "VehicleBody":
        """A body from a mesh file trimesh reads (OBJ, GLB, PLY, STL, ...), in the ego frame once turned
        Z-up: glTF (.glb, .gltf) is Y-up by its specification and is turned to Z-up by default
        (``scene.loaders.to_z_up``; ``up`` "z" or "y" overrides the format's axis, see
        ``scene.loaders.up_axis_for``). glTF's forward axis is not turned to +x: check the body's bounds.

        Raises:
            FileNotFoundError: no such file.
            ValueError: the file holds no triangles, or ``up`` is not "z", "y" or None.
        """
        import trimesh

        from place3d_kernels.scene.loaders import to_z_up, up_axis_for

        path = Path(path)
        axis = up_axis_for(path, up)
        if not path.is_file():
            raise FileNotFoundError(f"vehicle mesh {str(path)!r} not found")
        loaded = trimesh.load(str(path), force="mesh")
        if len(getattr(loaded, "faces", [])) == 0:
            raise ValueError(f"vehicle mesh {str(path)!r} holds no triangles")
        faces = np.asarray(loaded.faces)
        mesh = Mesh(to_z_up(np.asarray(loaded.vertices), axis), faces, np.full(len(faces), CLASS_ID["vehicle"]))
        return cls(mesh, name or path.stem)

    # ------------------------------------------------------------------ queries
    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) lower and upper corners of the body."""
        return self.mesh.bounds

    def footprint(self) -> np.ndarray:
        """(K, 2, 2) ground-plane rectangles (x, y lower and upper) of the body's boxes; the bounding
        rectangle for a loaded mesh."""
        if self.boxes is not None:
            return self.boxes[:, :, :2].copy()
        return self.bounds[None, :, :2]

    def contains(self, points) -> np.ndarray:
        """(N,) bool: the point lies inside the body or on its surface (where a LiDAR cannot sit)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.boxes is not None:
            lo, hi = self.boxes[:, 0], self.boxes[:, 1]
            return np.any(np.all((p[:, None] >= lo[None]) & (p[:, None] <= hi[None]), axis=2), axis=1)
        return _parity_inside(self.mesh, p)

    @property
    def key(self) -> str:
        """A short content hash (vertices, faces, boxes) for cache keys: equal bodies give equal keys."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
        if self.boxes is not None:
            h.update(np.ascontiguousarray(self.boxes).tobytes())
        return h.hexdigest()[:16]

    def __repr__(self) -> str:
        (x0, y0, z0), (x1, y1, z1) = self.bounds
        return (f"VehicleBody({self.name!r}, {x1 - x0:.2f} x {y1 - y0:.2f} x {z1:.2f} m, "
                f"{self.mesh.n_faces} faces)")
