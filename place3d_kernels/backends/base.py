"""The kernel contract every backend implements.

Backends never import the domain (``place3d_kernels``); they see plain NumPy arrays and a few small
value types defined here. The domain prepares inputs so that kernels stay simple:

* Coordinates handed to grid kernels are **grid-local**: the grid's lower corner has already been
  subtracted on the host in float64, so voxel ``(i, j, k)`` spans ``[i*s, (i+1)*s) x ...``.
* Directions are unit length, finite, non-zero (validated by the domain).
* Coordinates as kernels see them (mesh vertices and ray origins relative to the mesh shift, grid-local
  origins, grid extents) lie within ``COORDINATE_LIMIT`` of zero on every axis; the domain refuses
  anything farther before any backend runs, so every backend refuses the same inputs
  (``first_far_row``).
* Voxel flat index is ``(i * ny + j) * nz + k``.

Semantics (``reference`` is the executable specification):

* **lidar rays**: one ray per (LiDAR, channel, azimuth step), in that order. Sensor-frame direction
  ``(cos e cos a, cos e sin a, sin e)``, rotated by ``R = Rz(yaw) Ry(pitch) Rx(roll)``; origin = pose xyz.
* **raycast**: closest hit with ``t`` in ``[0, t_max]`` (watertight test); miss = ``(inf, -1)``.
* **traverse / coverage**: the segment ``[0, t_end]`` is clipped to the grid box; a voxel is visited when
  the open segment passes through its interior. With a ``stop`` mask (uint8 per voxel), a ray ends after
  the first visited voxel whose mask is non-zero (that voxel is visited). Visit order along the ray.
* **score**: sums of fixed-point int64 weights over the union of visited voxels, and the union's size:
  exact integer arithmetic, so identical on every backend for identical visit sets.
* **vote**: per voxel key, the label with most points among labels > 0 (ties -> lowest label);
  keys < 0 are ignored; voxels whose points are all label 0 get no entry.
"""

from __future__ import annotations

import abc
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["unique_ints", "host_vote", "cache_dir", "cache_folder", "Backend", "GridSpec", "BackendUnavailable", "ENTROPY_SCALE",
           "COORDINATE_LIMIT", "rotation_matrices", "sensor_directions", "check_ray_batch", "mesh_face_tables", "mesh_group_parts", "group_blocks",
           "first_far_row", "dense_rows", "check_voxel_rows", "resident_copy"]

#: Fixed-point scale for entropy weights: weight = round(H * ENTROPY_SCALE) as int64. ln(22) * 2**32 is
#: about 1.3e10, so 7e8 fully uncertain voxels still fit in int64 without overflow.
ENTROPY_SCALE = float(2**32)


#: Largest distance in metres, on any axis, of a coordinate from the frame kernels work in: a mesh
#: vertex or ray origin from the mesh's shift (its rounded centre), a ray origin from a grid's lower
#: corner, a grid's extent. Warp and OpenCL keep these in float32 (24-bit significands), whose spacing
#: is 2**-7 m (7.8 mm) between 65,536 m and 131,072 m, so 1e5 m keeps every float32 rounding below 4 mm,
#: under the smallest voxel the package tests (1 cm). The 0.1 mm contract of docs/architecture.md holds
#: within 1,024 m (spacing 2**-13 m, rounding 0.06 mm); between that and this limit float32 backends
#: agree with the reference to float32 rounding of the coordinates (about 6e-8 of their size). Beyond
#: it, their products overflow or cancel (a triangle at 1e30 m was hit by the reference and missed by
#: Warp and OpenCL), so the domain refuses such inputs on every backend alike. World coordinates may be
#: anything finite: the shifts are subtracted in float64 before a kernel runs.
COORDINATE_LIMIT = 1e5


def cache_dir() -> Path:
    """Where place3d keeps what it built (P-SOGs, OpenCL build markers): ``$PLACE3D_CACHE`` or
    ``~/.cache/place3d``. Here so the backends can find it without importing the domain."""
    return Path(os.environ.get("PLACE3D_CACHE", Path.home() / ".cache" / "place3d"))


def cache_folder(cache) -> Path:
    """The folder a ``cache`` argument names (``scene_psog``'s and the specs'): a path (str or Path) as given,
    anything else (True) ``cache_dir()``. Callers decide first whether there is a cache at all."""
    return Path(cache) if isinstance(cache, (str, Path)) else cache_dir()


def first_far_row(points: np.ndarray, centre) -> int:
    """Index of the first finite (N, 3) row of ``points`` more than ``COORDINATE_LIMIT`` from ``centre``
    ((3,)) on some axis, in float64; -1 when there is none. Non-finite rows are left to the callers' own
    checks. One pass over the values when all lie within the limit of every centre component."""
    p = np.asarray(points)
    if p.size == 0:
        return -1
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    lim = COORDINATE_LIMIT
    # whole-array min and max are fast (per-axis reductions of an (N, 3) array are not); NaN fails both
    if float(np.min(p)) >= float(c.max()) - lim and float(np.max(p)) <= float(c.min()) + lim:
        return -1
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        far = np.any(np.abs(p - c) > lim, axis=1) & np.all(np.isfinite(p), axis=1)
    return int(np.argmax(far)) if far.any() else -1


class BackendUnavailable(RuntimeError):
    """Raised by a backend constructor when its runtime or device cannot be used here."""


@dataclass(frozen=True)
class GridSpec:
    """A grid as kernels see it: grid-local coordinates, cubic voxels."""

    voxel_size: float
    shape: tuple[int, int, int]

    @property
    def n_voxels(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz


class Backend(abc.ABC):
    """One compute device running the project's kernels.

    Implementations: ``reference`` (NumPy float64), ``warp:<device>``, ``opencl:<platform>``.
    Arrays in and out are NumPy; implementations may cache device copies of large inputs keyed by the
    handle objects they return (``upload_mesh``, ``prepare_grid``).
    """

    #: Full name, e.g. ``"warp:cpu"``.
    name: str = "abstract"
    #: Floating-point width of the kernels (``np.float32`` or ``np.float64``).
    dtype: type = np.float32

    # ----------------------------------------------------------------- rays
    @abc.abstractmethod
    def lidar_rays(self, elevations: np.ndarray, azimuths: np.ndarray, poses: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Rays of several LiDARs.

        Args:
            elevations: (C,) float64 radians.
            azimuths: (A,) float64 radians.
            poses: (L, 6) float64 rows (x, y, z, roll, pitch, yaw) in any frame.

        Returns:
            origins (L*C*A, 3) and unit directions (L*C*A, 3), ordered (lidar, channel, azimuth).
        """

    # ----------------------------------------------------------------- ray-mesh
    @abc.abstractmethod
    def upload_mesh(self, vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray | None = None,
                    labels: np.ndarray | None = None) -> object:
        """Build the acceleration structure for a triangle mesh and return an opaque handle.

        Args:
            vertices: (V, 3) float64, already shifted near the origin by the domain.
            faces: (F, 3) int32 vertex indices.
            face_ids: (F,) the caller's id of each face, reported by ``raycast_checked`` (default: 0..F-1).
            labels: (F,) int32 label of each face, reported by ``raycast_checked`` (default: 0).

        Backends with ``extends_meshes`` also take ``prefix=(part, offset)``: a ``mesh_part`` of this mesh's first
        faces (built once, reused by every mesh extending it) and the (3,) float64 offset from its frame to this
        one's; they build only the other faces' structure (``Mesh.extended``). The hits are the same.
        """

    #: True where ``upload_mesh`` takes a ``prefix`` made by ``mesh_part(vertices, faces)`` (OpenCL with
    #: doubles): a mesh that extends another (``Mesh.extended``) is uploaded without building the shared
    #: faces' structure again.
    extends_meshes: bool = False

    #: True where ``raycast`` takes a ``shift`` keyword: the (3,) float64 mesh shift, subtracted from the
    #: world-frame origins in float64 on the device (the same IEEE subtraction as on the host, so the same
    #: bits), which saves the caller a host pass over the origins. Where False, callers pass shifted origins.
    raycast_takes_shift: bool = False

    @abc.abstractmethod
    def raycast(self, mesh: object, origins: np.ndarray, directions: np.ndarray, t_max: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Closest hit per ray.

        Origins are in the mesh's shifted frame; where ``raycast_takes_shift`` is True, a ``shift=``
        keyword may instead give the float64 shift to subtract from world-frame origins.

        Returns:
            t (N,) float64 (inf on miss) and face (N,) int32 (-1 on miss).
        """

    #: True where ``raycast_checked`` is implemented: the ray-mesh call that takes the caller's rays as
    #: given and checks them on the device (no host pass over the rays).
    raycast_checks_rays: bool = False

    def raycast_checked(self, mesh: object, origins: np.ndarray, directions: np.ndarray, t_max, shift: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Closest hit per ray on unchecked world-frame rays, checked and normalised on the device.

        Args:
            mesh: handle from ``upload_mesh`` (its ``face_ids`` and ``labels`` are reported).
            origins: (N, 3), or (1, 3) for one origin shared by all rays; C-contiguous, float32 or float64,
                the same dtype as ``directions``. float32 values widen to float64 exactly.
            directions: (N, 3) C-contiguous, any length (normalised as the domain's host check does).
            t_max: a Python float or an (N,) float64 array (not yet checked).
            shift: (3,) float64, subtracted from the origins in float64 on the device.

        Returns:
            ``(t float64, face int64, label int32)``, each (N,), as the domain reports them (inf, -1, -1 on
            a miss); or None when a ray has a non-finite origin, a non-finite or zero direction, a
            direction norm that is not finite, or a negative or NaN ``t_max``: the caller then checks the
            rays on the host (and raises, or normalises and calls again).

        Raises:
            NotImplementedError: ``raycast_checks_rays`` is False for this backend.
        """
        raise NotImplementedError(f"backend {self.name} does not check rays on the device (raycast_checks_rays "
                                  f"is False); validate the rays and call raycast")

    # ----------------------------------------------------------------- voxel traversal
    @abc.abstractmethod
    def traverse(self, grid: GridSpec, origins: np.ndarray, directions: np.ndarray, t_end: np.ndarray,
                 stop: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Voxels visited by each ray, in visit order, as CSR.

        Args:
            grid: grid spec; origins are grid-local.
            origins, directions: (N, 3) float64.
            t_end: (N,) float64 segment lengths (>= 0).
            stop: optional (n_voxels,) uint8 occlusion mask.

        Returns:
            offsets (N+1,) int64 and voxels (offsets[-1],) int64 flat indices.
        """

    @abc.abstractmethod
    def coverage(self, grid: GridSpec, origins: np.ndarray, directions: np.ndarray, t_end: np.ndarray,
                 stop: np.ndarray | None = None) -> np.ndarray:
        """Union of visited voxels as a (n_voxels,) bool array (same rules as ``traverse``)."""

    @abc.abstractmethod
    def prepare_grid(self, grid: GridSpec, weights: np.ndarray, stop: np.ndarray | None) -> object:
        """Upload per-voxel int64 fixed-point weights and an optional uint8 stop mask once.

        Returns an opaque handle for ``score_placements``. The handle holds its own copy: the caller may
        change or reuse ``weights`` and ``stop`` afterwards (the jackknife keeps handles of grids it patched
        in one working array).
        """

    def prepare_indicator(self, grid: GridSpec, weights: np.ndarray, stop: np.ndarray | None) -> object:
        """``prepare_grid`` for a grid whose weights are all 0 or 1, as the caller promises (the denominators'
        indicator grids, ``indicators.indicator_weights``): its sums are the covered voxels it marks, which a
        backend may count from another grid's walk in ``score_placements_many`` (Warp, OpenCL). Weights other
        than 0 and 1 here give wrong sums there. Here: ``prepare_grid``."""
        return self.prepare_grid(grid, weights, stop)

    def grid_from_rows(self, grid: GridSpec, voxels: np.ndarray, weights: np.ndarray,
                       stop: np.ndarray | None) -> object:
        """The handle ``prepare_grid`` gives for weight 0 and no stop at every voxel but ``voxels`` (distinct
        flat indices), which get ``weights`` (int64) and ``stop`` (bool; None: no stop mask): a P-SOG's grid
        from its stored voxels alone. Here a ``working_grid`` where the backend writes grids in place, else the
        dense arrays made on the host; backends that can fill a grid on the device do so without them."""
        if self.writes_grids:
            return self.working_grid(grid, voxels, weights, stop)
        w, s = dense_rows(grid, voxels, weights, stop)
        return self.prepare_grid(grid, w, s)

    def indicator_from_rows(self, grid: GridSpec, voxels: np.ndarray, weights: np.ndarray,
                            stop: np.ndarray | None) -> object:
        """``grid_from_rows`` for rows of 0/1 weights, as the caller promises: what ``prepare_indicator`` is to
        ``prepare_grid`` (a P-SOG's indicator grids from its stored voxels, ``indicators.indicator_handle``).
        Here: ``grid_from_rows``."""
        return self.grid_from_rows(grid, voxels, weights, stop)

    def grid_base_from_rows(self, grid: GridSpec, voxels: np.ndarray, weights: np.ndarray,
                            stop: np.ndarray | None) -> object:
        """``grid_base`` of the dense arrays that ``grid_from_rows`` describes (backends that patch grids)."""
        w, s = dense_rows(grid, voxels, weights, stop)
        return self.grid_base(grid, w, s)

    #: True where the jackknife's left-out grids are best made by ``grid_base`` and ``patched_grid``, a base
    #: and a few changed voxels per grid (``left_out.prepared_grids``); elsewhere the caller patches a dense
    #: copy on the host and calls ``prepare_grid``. A backend may implement the two where this is False
    #: (Warp's CPU device: slower there than the host's copy).
    patches_grids: bool = False

    def grid_base(self, grid: GridSpec, weights: np.ndarray, stop: np.ndarray | None) -> object:
        """Keep dense per-voxel weights and an optional stop mask for ``patched_grid`` (the backend's own copy).

        Raises:
            NotImplementedError: this backend does not patch grids.
        """
        raise NotImplementedError(f"backend {self.name} does not patch grids; patch the dense arrays on the host "
                                  f"and call prepare_grid")

    def patched_grid(self, base: object, voxels: np.ndarray, weights: np.ndarray, stop: np.ndarray | None) -> object:
        """The handle ``prepare_grid`` gives for the base's arrays with voxels ``voxels`` (distinct flat
        indices) set to ``weights`` and ``stop`` (``stop`` unused where the base has no stop mask). The base
        is left as it was.

        Raises:
            NotImplementedError: this backend does not patch grids.
        """
        raise NotImplementedError(f"backend {self.name} does not patch grids; patch the dense arrays on the host "
                                  f"and call prepare_grid")

    #: True where ``working_grid`` and ``write_voxels`` keep one grid handle and change it in place: the
    #: jackknife's left-out grids, scored one after the other, then cost a write of the voxels that changed
    #: instead of a dense copy and a whole upload each (``left_out.patched_in_place``).
    writes_grids: bool = False

    def working_grid(self, grid: GridSpec, voxels: np.ndarray, weights: np.ndarray,
                     stop: np.ndarray | None) -> object:
        """A handle for ``score_placements`` that ``write_voxels`` may change: weight 0 and no stop at every
        voxel but ``voxels`` (distinct flat indices), which get ``weights`` (int64) and ``stop`` (bool; None:
        no stop mask at all, occlusion "none").

        Raises:
            NotImplementedError: this backend does not write grids in place.
        """
        raise NotImplementedError(f"backend {self.name} does not write grids in place; use prepare_grid")

    def write_voxels(self, handle: object, voxels: np.ndarray, weights: np.ndarray, stop: np.ndarray | None) -> None:
        """Set voxels ``voxels`` (distinct flat indices) of a ``working_grid`` handle to ``weights`` and ``stop``
        (``stop`` unused where the handle has no stop mask), in place: scores on the handle from then on are
        those of ``prepare_grid`` on the dense arrays so changed.

        Raises:
            NotImplementedError: this backend does not write grids in place.
        """
        raise NotImplementedError(f"backend {self.name} does not write grids in place; use prepare_grid")

    @abc.abstractmethod
    def score_placements(self, handle: object, elevations: np.ndarray, azimuths: np.ndarray,
                         t_max: float, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batched evaluation: rays of each candidate rig -> union of visited voxels -> sums.

        Args:
            handle: from ``prepare_grid``.
            elevations, azimuths: as in ``lidar_rays``.
            t_max: ray length (max range), metres.
            poses: (P, L, 6) float64 grid-local poses, P candidates of L LiDARs each.

        Returns:
            sums (P,) int64 of weights over each candidate's covered voxels, counts (P,) int64 of them.
        """

    def score_placements_many(self, handles, elevations: np.ndarray, azimuths: np.ndarray, t_max: float,
                              poses: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """``score_placements`` of the same rigs on several grids that share one stop mask (or none), such
        as the seg and det views of one P-SOG and their indicator grids: the covered voxels are the same on
        each, so a backend may walk the rays once and sum each grid's weights over them. Here, one call per
        grid.

        Returns:
            one (sums, counts) pair per handle, what ``score_placements`` gives for it.
        """
        return [self.score_placements(h, elevations, azimuths, t_max, poses) for h in handles]

    @abc.abstractmethod
    def score_rays(self, handle: object, origins: np.ndarray, directions: np.ndarray, t_end: np.ndarray,
                   ray_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batched evaluation over explicit rays: candidate p owns rays ``ray_offsets[p]:ray_offsets[p+1]``.

        The general form of ``score_placements``: candidates may have different ray counts (rigs of
        different sensors or sizes) and each ray its own segment length (e.g. clipped where the ego
        vehicle's body blocks it). Same occlusion (stop mask of ``handle``) and exact fixed-point sums.

        Args:
            handle: from ``prepare_grid``.
            origins, directions: (N, 3) float64, grid-local, unit directions.
            t_end: (N,) float64 segment lengths (>= 0).
            ray_offsets: (P+1,) int64 non-decreasing CSR offsets, ``ray_offsets[0] == 0`` and
                ``ray_offsets[-1] == N``; an empty candidate covers nothing.

        Returns:
            sums (P,) int64 of weights over each candidate's covered voxels, counts (P,) int64 of them.
        """

    # ----------------------------------------------------------------- occupancy grids
    @abc.abstractmethod
    def voxel_keys(self, grid: GridSpec, points: np.ndarray) -> np.ndarray:
        """Flat voxel index per grid-local point, -1 outside the grid. (N,) int64."""

    @abc.abstractmethod
    def vote(self, keys: np.ndarray, labels: np.ndarray, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
        """Majority label per voxel.

        Args:
            keys: (N,) int64 flat voxel indices; negative = ignore.
            labels: (N,) int32 in [0, n_classes); 0 = unlabeled, does not vote.

        Returns:
            voxels (M,) int64 ascending and their winning labels (M,) int32.
        """

    # ----------------------------------------------------------------- misc
    def synchronize(self) -> None:  # pragma: no cover - trivial for host backends
        """Wait for queued work (used by benchmarks)."""

    def warmup(self) -> None:
        """Compile or load every kernel now, so that benchmarks keep compile time out of timings.

        Backends that compile nothing ahead (``reference``) keep this default, which does nothing.
        """

    # ----------------------------------------------------------------- benchmark hooks (optional)
    #: True where ``resident_raycast`` and ``resident_traverse`` are implemented: kernel-only timers
    #: for benchmarks (rays uploaded once, the timed call launches the kernel and waits).
    resident_kernels: bool = False

    def resident_raycast(self, mesh: object, origins: np.ndarray, directions: np.ndarray, t_max: float):
        """For benchmarks: a zero-argument callable that launches the ray-mesh kernel on rays already on
        the device (uploaded by this call); only where ``resident_kernels`` is True.

        Raises:
            NotImplementedError: this backend has no resident kernels (``resident_kernels`` is False).
        """
        raise NotImplementedError(f"backend {self.name} has no resident kernels (resident_kernels is False); "
                                  f"check resident_kernels before calling resident_raycast")

    def resident_traverse(self, grid: GridSpec, origins: np.ndarray, directions: np.ndarray, t_end,
                          stop: np.ndarray | None = None):
        """For benchmarks: a zero-argument callable that launches the traversal count kernel on rays
        already on the device (see ``resident_raycast``); only where ``resident_kernels`` is True.

        Raises:
            NotImplementedError: this backend has no resident kernels (``resident_kernels`` is False).
        """
        raise NotImplementedError(f"backend {self.name} has no resident kernels (resident_kernels is False); "
                                  f"check resident_kernels before calling resident_traverse")

    def __repr__(self) -> str:
        return f"<Backend {self.name}>"


def rotation_matrices(poses: np.ndarray) -> np.ndarray:
    """(L, 3, 3) float64 rotations R = Rz(yaw) Ry(pitch) Rx(roll) of (L, 6) poses."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    cr, sr = np.cos(p[:, 3]), np.sin(p[:, 3])
    cp, sp = np.cos(p[:, 4]), np.sin(p[:, 4])
    cy, sy = np.cos(p[:, 5]), np.sin(p[:, 5])
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], axis=1)


def sensor_directions(elevations: np.ndarray, azimuths: np.ndarray) -> np.ndarray:
    """(C*A, 3) float64 unit directions in the sensor frame, ordered (channel, azimuth)."""
    e = np.asarray(elevations, dtype=np.float64)[:, None]
    a = np.asarray(azimuths, dtype=np.float64)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)), -1)
    return d.reshape(-1, 3)


class DirectionCache:
    """The last few sensor-direction tables of a backend, uploaded: ``get(elevations, azimuths)`` returns
    ``upload(sensor_directions(elevations, azimuths))``, computed once per (elevations, azimuths).

    A search scores every generation with the same LiDAR model; building its (C*A, 3) table and copying it
    to the device took a large share of a generation's host time on a GPU (``bench/README.md``, "What the
    studies found", warm command and place3d serve). Keyed by the arrays' bytes, so a changed model is a new
    entry; the oldest of ``size`` entries is dropped."""

    def __init__(self, upload, size: int = 4):
        self._upload = upload
        self._size = int(size)
        self._entries: dict = {}
        self._lock = threading.Lock()        # scoring threads (the jackknife's) share a backend

    def get(self, elevations, azimuths):
        e = np.ascontiguousarray(elevations, dtype=np.float64).reshape(-1)
        a = np.ascontiguousarray(azimuths, dtype=np.float64).reshape(-1)
        key = (e.tobytes(), a.tobytes())
        with self._lock:
            hit = self._entries.pop(key, None)
            if hit is None:
                hit = self._upload(sensor_directions(e, a))
            self._entries[key] = hit                      # most recent last
            while len(self._entries) > self._size:
                self._entries.pop(next(iter(self._entries)))
        return hit


def mesh_group_parts(parts) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``upload_mesh_groups``' parts checked, per group: (vertices (V, 3) float64, faces (F, 3) int64, and the face
    ids and labels of ``mesh_face_tables``).

    Raises:
        ValueError: no parts, or a part without a face.
    """
    if not parts or any(len(f) == 0 for _, f, _, _ in parts):
        raise ValueError("upload_mesh_groups needs one or more meshes, each with a face")
    out = []
    for v, f, face_ids, labels in parts:
        f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
        out.append((np.asarray(v, dtype=np.float64).reshape(-1, 3), f, *mesh_face_tables(len(f), face_ids, labels)))
    return out


def group_blocks(n_origins: int, n_directions: int, rays_per_group: int, first: int, n_meshes: int) -> int:
    """The number of ray blocks of a ``raycast_groups`` call (``rays_per_group`` rays each, block k into mesh
    ``first + k`` of ``n_meshes``).

    Raises:
        ValueError: the rays are not whole blocks, or the blocks run past the last mesh.
    """
    r = int(rays_per_group)
    groups = n_origins // r if r > 0 else 0
    if r <= 0 or groups * r != n_origins or n_directions != n_origins or not 0 <= first <= n_meshes - groups:
        raise ValueError(f"raycast_groups needs whole blocks of {r} rays for meshes {first}.. of {n_meshes}, "
                         f"got {n_origins} origins and {n_directions} directions")
    return groups


def mesh_face_tables(n_faces: int, face_ids=None, labels=None) -> tuple[np.ndarray, np.ndarray]:
    """Per uploaded face: the caller's face id (int64, default 0..F-1) and label (int32, default 0).

    Raises:
        ValueError: a table does not have one entry per face.
    """
    ids = np.arange(n_faces, dtype=np.int64) if face_ids is None else np.asarray(face_ids, dtype=np.int64).reshape(-1)
    lab = np.zeros(n_faces, dtype=np.int32) if labels is None else np.asarray(labels, dtype=np.int32).reshape(-1)
    for name, a in (("face_ids", ids), ("labels", lab)):
        if a.shape != (n_faces,):
            raise ValueError(f"upload_mesh {name} must have one entry per face ({n_faces}), got shape {a.shape}")
    return np.ascontiguousarray(ids), np.ascontiguousarray(lab)


def check_ray_batch(origins, directions, t_end, ray_offsets) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validate and normalise the inputs of ``Backend.score_rays``: float64 (N, 3), (N, 3), (N,) and
    int64 (P+1,) CSR offsets.

    Raises:
        ValueError: shapes disagree or the offsets are not a CSR partition of the N rays.
    """
    o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    n = len(o)
    if d.shape != (n, 3):
        raise ValueError(f"score_rays: directions must have shape ({n}, 3) like origins, got {d.shape}")
    te = np.ascontiguousarray(np.broadcast_to(np.asarray(t_end, dtype=np.float64), (n,)))
    off = np.ascontiguousarray(ray_offsets, dtype=np.int64).reshape(-1)
    if len(off) < 1 or off[0] != 0 or off[-1] != n or np.any(np.diff(off) < 0):
        raise ValueError(f"score_rays: ray_offsets must be non-decreasing CSR offsets from 0 to the ray count "
                         f"{n}; got {len(off)} offsets from {off[:1].tolist()} to {off[-1:].tolist()}")
    return o, d, te, off


def dense_rows(grid: GridSpec, voxels, weights, stop) -> tuple[np.ndarray, np.ndarray | None]:
    """(weights (n,) int64, stop (n,) uint8 or None) over the whole grid: the rows at ``voxels``, 0 elsewhere."""
    ids, w_rows, s_rows = check_voxel_rows(voxels, weights, stop, grid.n_voxels, stop is not None)
    w = np.zeros(grid.n_voxels, dtype=np.int64)
    w[ids] = w_rows
    if stop is None:
        return w, None
    s = np.zeros(grid.n_voxels, dtype=np.uint8)
    s[ids] = s_rows
    return w, s


def resident_copy(memo: dict, x, dtype, send):
    """``send(x)`` kept in ``memo`` while ``x`` lives, for a read-only NumPy array of ``dtype`` that owns its
    memory (the pool's counts table, the jackknife's entry tables: read-only from where they are made), so a
    backend sends it to its device once; for anything else (a writable array, a view, another type) ``send`` of
    a contiguous ``dtype`` copy, each call. A jackknife otherwise sent the pool's counts (0.6 GB on the default
    grid of 32 drives) for each task's left-out rows, each task's bases and each task's point grid."""
    if not (isinstance(x, np.ndarray) and x.base is None and not x.flags.writeable and x.dtype == np.dtype(dtype)
            and x.flags.c_contiguous):
        return send(np.ascontiguousarray(x, dtype=dtype))
    key = id(x)
    hit = memo.get(key)
    if hit is not None and hit[0]() is x:
        return hit[1]
    import weakref

    d = send(x)
    # dropped with the host array (its id is free for another array only once it is gone)
    memo[key] = (weakref.ref(x, lambda _, key=key: memo.pop(key, None)), d)
    return d


def check_voxel_rows(voxels, weights, stop, n_voxels: int, has_stop: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(voxels int64, weights int64, stop uint8 0/1) of a ``working_grid`` or ``write_voxels`` call, flat and
    contiguous (stop all 0 where the grid has no stop mask).

    Raises:
        ValueError: rows of mismatched lengths, a missing stop where the grid has a mask, or a voxel outside
            the grid's ``n_voxels``.
    """
    ids = np.ascontiguousarray(voxels, dtype=np.int64).reshape(-1)
    w = np.ascontiguousarray(weights, dtype=np.int64).reshape(-1)
    if has_stop and stop is None:
        raise ValueError("a grid with a stop mask needs a stop value per written voxel")
    s = (np.zeros(len(ids), dtype=np.uint8) if not has_stop
         else (np.asarray(stop).reshape(-1) != 0).view(np.uint8))
    if w.shape != ids.shape or s.shape != ids.shape:
        raise ValueError(f"writing {len(ids)} voxels needs one weight and one stop value per voxel, got "
                         f"{w.shape[0]} and {s.shape[0]}")
    if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= n_voxels):
        raise ValueError(f"voxel indices must lie in [0, {n_voxels}), got [{int(ids.min())}, {int(ids.max())}]")
    return ids, w, s


def unique_ints(a) -> np.ndarray:
    """The distinct values of a 1-D integer array, ascending: ``np.unique(a)``'s result.

    NumPy 2.3 and later find the values of a bare ``np.unique`` through a hash table and then sort them;
    on millions of voxel ids (a pooled P-SOG's union, a rig's traversed voxels) that measured about ten
    times slower than one sort and a comparison of neighbours (NumPy 2.4, dev VM), which this does."""
    s = np.sort(np.asarray(a).ravel())
    if len(s) < 2:
        return s
    keep = np.empty(len(s), dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def host_vote(keys, labels, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """``Backend.vote`` with NumPy: one sort of the voting (voxel, label) pairs, the count of each, and per voxel
    the label with the most points (ties: the lowest label); keys < 0 and label 0 (unlabeled) do not vote.
    The reference backend's vote, and the OpenCL backend's host path (CPU devices, keys beyond 32 bits).

    Returns:
        voxels (M,) int64 ascending, winning labels (M,) int32.
    """
    k = np.asarray(keys, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64)
    ok = (k >= 0) & (lab > 0)
    combo, counts = np.unique(k[ok] * n_classes + lab[ok], return_counts=True)
    vox, cls = combo // n_classes, combo % n_classes
    order = np.lexsort((cls, -counts, vox))          # voxel ascending, count descending, label ascending
    vox, cls = vox[order], cls[order]
    first = np.concatenate([[True], vox[1:] != vox[:-1]]) if len(vox) else np.zeros(0, bool)
    return vox[first].astype(np.int64), cls[first].astype(np.int32)
