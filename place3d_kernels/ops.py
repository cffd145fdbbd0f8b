"""Public kernel entry points: ray-mesh intersection, voxel traversal and coverage.

Inputs are validated here (once, on the host) so kernels can assume finite unit directions; world
coordinates are shifted to the grid or mesh origin in float64 before they reach a device. ``raycast`` on
backends with ``raycast_checks_rays`` is the exception: the device makes the same checks (see
``Backend.raycast_checked``) and the host path runs only for rays they reject.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from place3d_kernels.backends.base import COORDINATE_LIMIT, first_far_row
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.grid import Grid
from place3d_kernels.mesh import Mesh
from place3d_kernels.profiling import section

__all__ = ["Hits", "Traversal", "raycast", "MeshGroups", "traverse", "coverage", "check_rays"]


@dataclass
class Hits:
    """Closest hits: ``t`` (inf on miss), ``face`` (-1 on miss), ``label`` of the face (-1 on miss)."""

    t: np.ndarray
    face: np.ndarray
    label: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.face >= 0


@dataclass
class Traversal:
    """Visited voxels per ray as CSR: ray i visited ``voxels[offsets[i]:offsets[i+1]]`` in order."""

    offsets: np.ndarray
    voxels: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def ray(self, i: int) -> np.ndarray:
        return self.voxels[self.offsets[i]:self.offsets[i + 1]]


def _row_norm(a: np.ndarray) -> np.ndarray:
    # Euclidean norm of each row of an (N, 3) array: the same sum order as np.linalg.norm(a, axis=1)
    # (x^2 + y^2, then + z^2; bit-identical), faster than its reduction over a length-3 axis
    return np.sqrt(a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] + a[:, 2] * a[:, 2])


def _bad_row(a: np.ndarray) -> int:
    return int(np.argmax(~np.all(np.isfinite(a), axis=1)))


def _check_od(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 (N, 3) origins (possibly a broadcast view) and unit directions (contiguous)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim == 1:
        o = o[None]
    if d.ndim == 1:
        d = d[None]
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,):
        raise ValueError(f"origins and directions must be (N, 3) arrays, got {o.shape} and {d.shape}")
    if len(o) == 1 and len(d) > 1:
        o = np.broadcast_to(o, d.shape)
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} must have the same shape")
    if not np.isfinite(o[:1] if o.strides[0] == 0 else o).all():   # whole array first; the row on failure
        i = _bad_row(o)
        raise ValueError(f"ray {i} has a non-finite origin {o[i].tolist()}; drop or fix such rays first")
    with np.errstate(over="ignore", under="ignore"):     # handled below: such rows are rescaled
        norm = _row_norm(d)
    # Fast path, one pass over the norms: every row unit to rounding (the common case) needs no further
    # check. Exactly the slow path's test: x - 1.0 is monotone in x, so max(norm) - 1.0 is the largest
    # norm - 1.0 (likewise for the min); a zero norm fails it, and a non-finite direction makes its norm
    # NaN or inf, which min/max propagate and the comparisons reject.
    lo, hi = norm.min(initial=1.0), norm.max(initial=1.0)
    if 1.0 - lo <= 1e-12 and hi - 1.0 <= 1e-12:
        return o, np.ascontiguousarray(d)
    if not np.isfinite(d).all():
        i = _bad_row(d)
        raise ValueError(f"ray {i} has a non-finite direction {d[i].tolist()}; drop or fix such rays first")
    d = d.copy()
    rescale = (norm == 0.0) | (norm == np.inf)
    if rescale.any():
        norm = norm.copy()
        d[rescale], norm[rescale] = _rescaled(d[rescale])
    if not norm.all():
        i = int(np.argmax(norm == 0))
        raise ValueError(f"ray {i} has a zero-length direction; every ray needs a non-zero direction")
    # normalise, but leave directions that are unit to rounding untouched: renormalising them would nudge
    # rays that pass exactly through voxel edges to one side, and the same rays must give the same voxels
    # whichever entry point (traverse, coverage, msog_batch) they come through
    off = np.abs(norm - 1.0) > 1e-12
    if off.any():
        d[off] /= norm[off, None]
    return o, np.ascontiguousarray(d)


def _rescaled(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of finite directions whose squared norm overflows to inf (a component beyond about 1.3e154) or
    underflows to 0 (every component below about 1e-162), scaled by a power of two (exact) that brings the
    largest component into [0.5, 1), and the norms of the scaled rows. An all-zero row stays zero (norm 0).
    Rows the device checks pass (finite, non-zero norm) never come here, so device and host normalise
    every ray alike."""
    m = np.max(np.abs(d), axis=1)
    _, e = np.frexp(m)                     # m = f * 2**e with f in [0.5, 1); e = 0 for m = 0
    ds = np.ldexp(d, -e[:, None])
    return ds, _row_norm(ds)


def _check_near(o: np.ndarray, centre, what: str) -> None:
    """Refuse finite origins more than ``COORDINATE_LIMIT`` from ``centre`` on some axis: float32 backends
    cannot represent them (``backends/base.py``), so no backend takes them."""
    i = first_far_row(o, centre)
    if i >= 0:
        row = np.asarray(o[i], dtype=np.float64)
        far = float(np.max(np.abs(row - np.asarray(centre, dtype=np.float64))))
        raise ValueError(f"ray {i} starts at {row.tolist()}, {far:.6g} m from {what} on an axis, beyond the "
                         f"{COORDINATE_LIMIT:g} m every backend accepts (float32 backends cannot place it to a "
                         f"voxel; backends/base.py COORDINATE_LIMIT); express the rays and the scene in a frame "
                         f"near the rays")


def _check_t(t, n: int, what: str, scalar: bool = False):
    """Validated ``t``: (n,) float64, or a Python float when ``scalar`` and ``t`` is one."""
    tt = np.asarray(t, dtype=np.float64)
    if tt.ndim == 0:
        if n and not tt >= 0:             # NaN fails this too
            raise ValueError(f"{what} of ray 0 is {float(tt)}; it must be >= 0 (inf allowed)")
        return float(tt) if scalar else np.full(n, float(tt))
    if tt.shape != (n,):
        raise ValueError(f"{what} must be a scalar or one value per ray ({n}), got shape {tt.shape}")
    if not (tt >= 0).all():
        i = int(np.argmax(~(tt >= 0)))
        raise ValueError(f"{what} of ray {i} is {tt[i]}; it must be >= 0 (inf allowed)")
    return tt


def check_rays(origins, directions, t, what: str = "t_end") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and normalise ray inputs; raise ValueError naming the first bad value and the fix.

    Returns contiguous float64 (N, 3) origins, unit directions and (N,) ``t``.
    """
    o, d = _check_od(origins, directions)
    tt = _check_t(t, len(o), what)
    return np.ascontiguousarray(o), d, tt


def raycast(mesh: Mesh, origins, directions, t_max=np.inf, backend=None) -> Hits:
    """Closest hit of each ray with a mesh, for t in [0, t_max].

    Args:
        mesh: the triangle mesh; its BVH is built once per backend and cached on the mesh.
        origins, directions: (N, 3) rays (directions need not be normalised; t is in metres along the
            normalised direction, which is computed without overflow or underflow for any finite non-zero
            direction). float32 rays give the hits of the same rays widened to float64.
        t_max: scalar or (N,) maximum distance.
        backend: backend name or instance (default: the current one).

    Raises:
        ValueError: a shape is wrong, or a ray has a non-finite origin, a non-finite or zero direction, or
            a negative or NaN ``t_max`` (the message names the first such ray); or a ray origin or a vertex
            lies more than ``COORDINATE_LIMIT`` (1e5 m) from the mesh's centre on some axis, beyond what
            float32 backends represent (``backends/base.py``; refused on every backend alike).
    """
    b = get_backend(backend)
    if b.raycast_checks_rays:
        # the device checks and normalises the rays as _check_od/_check_t would; only when it raises a
        # flag (a ray those would reject) does the host path below run, for today's error or result
        with section("raycast: prepare"):
            rays = _device_rays(origins, directions, t_max)
            if rays is not None and first_far_row(rays[0], mesh.shift) >= 0:
                rays = None           # the host path raises the error, after the checks that come first
        if rays is not None:
            handle = mesh.handle(b)
            with section("raycast: backend"):
                out = b.raycast_checked(handle, *rays, shift=mesh.shift)
            if out is not None:
                return Hits(*out)
    with section("raycast: validate"):
        o, d = _check_od(origins, directions)
        tm = _check_t(t_max, len(o), "t_max", scalar=True)
        _check_near(o, mesh.shift, "the mesh's centre (Mesh.shift)")
    # float32 kernels need a finite bound; a scalar stays a scalar (backends broadcast it)
    tm32 = min(tm, 1e30) if isinstance(tm, float) else np.minimum(tm, 1e30)
    handle = mesh.handle(b)
    if b.raycast_takes_shift:
        # the backend subtracts the shift in float64 on the device (same bits); no host pass over origins
        with section("raycast: backend"):
            t, face = b.raycast(handle, o, d, tm32, shift=mesh.shift)
    else:
        with section("raycast: shift"):
            local = np.subtract(o, mesh.shift)     # a new contiguous array, also when o is a broadcast view
        with section("raycast: backend"):
            t, face = b.raycast(handle, local, d, tm32)
    with section("raycast: outputs"):
        face = mesh.original_face(face)
        # face -1 reads the last label (NumPy's negative index) and is then overwritten: one gather
        label = mesh.labels[face]
        label[face < 0] = -1
    return Hits(np.asarray(t, dtype=np.float64), face, label)


class MeshGroups:
    """Meshes cast through one acceleration structure with a subtree per mesh (``cast``): one build for them
    all, and one launch for the rays of several, instead of one of each per mesh. A ray meets only its own
    mesh's triangles, with that mesh's shift, so its hit is that mesh's ``raycast`` hit, bit for bit (float64
    decides among tied faces, whatever the tree; tests/test_raycast_groups.py).

    ``available`` is False on backends without grouped casts (``upload_mesh_groups``); cast with
    ``raycast`` per mesh there.
    """

    def __init__(self, meshes: list[Mesh], backend=None):
        self.meshes = list(meshes)
        self.b = get_backend(backend)
        self.available = bool(self.meshes) and self.supported(self.b)
        self._handle = None
        self._shifts = np.stack([m.shift for m in self.meshes]) if self.meshes else np.zeros((0, 3))

    @staticmethod
    def supported(backend) -> bool:
        """Whether ``backend`` (a name or instance) casts through grouped trees (``upload_mesh_groups``, and
        ``casts_groups`` where the backend says per device)."""
        b = get_backend(backend)
        return hasattr(b, "upload_mesh_groups") and bool(getattr(b, "casts_groups", True))

    def cast(self, origins, directions, t_max: float, rays_per_mesh: int, first: int = 0) -> Hits | None:
        """Hits of blocks of ``rays_per_mesh`` rays, block k into mesh ``first + k``: float64 (N, 3) world
        origins and directions, one scalar ``t_max``. None where the backend has no grouped casts, the rays
        are not such blocks of these meshes, or a ray fails ``raycast``'s checks: cast each block with
        ``raycast`` then (which raises that error)."""
        o, d = np.asarray(origins), np.asarray(directions)
        r = int(rays_per_mesh)
        if (not self.available or o.dtype != np.float64 or d.dtype != np.float64 or o.shape != d.shape
                or o.ndim != 2 or o.shape[1] != 3 or np.ndim(t_max) != 0 or r <= 0 or len(o) == 0
                or len(o) % r or not 0 <= first <= len(self.meshes) - len(o) // r):
            return None
        if self.handle_near(o) is None:
            return None
        with section("raycast: backend"):
            out = self.b.raycast_groups(self._handle, o, d, float(t_max), self._shifts, r, first)
        return None if out is None else Hits(*out)

    def handle_near(self, origins):
        """The backend's grouped tree of the meshes (built on first use), or None where the backend has no
        grouped casts or an origin lies more than COORDINATE_LIMIT from a mesh's shift (``cast`` then leaves
        the rays to ``raycast``, which checks each block)."""
        o = np.asarray(origins, dtype=np.float64)
        lim, shifts = COORDINATE_LIMIT, self._shifts
        if not self.available or not len(o) or not (float(np.min(o)) >= float(shifts.max()) - lim
                                                    and float(np.max(o)) <= float(shifts.min()) + lim):
            return None
        if self._handle is None:
            with section("raycast: grouped build"):
                self._handle = self.b.upload_mesh_groups([m.upload_parts() for m in self.meshes])
        return self._handle

    @property
    def shifts(self) -> np.ndarray:
        """(G, 3) each mesh's shift."""
        return self._shifts


def _device_rays(origins, directions, t_max):
    """Rays for ``Backend.raycast_checked`` without a pass over their values, or None for the host path.

    Takes (N, 3) C-contiguous float32 or float64 arrays of one dtype as they are (origins may be one
    (1, 3) row), and a scalar or (N,) numeric ``t_max``; anything else (lists, other dtypes or layouts,
    wrong shapes, no rays) goes to the host path, which converts it or raises today's error.
    """
    o, d = np.asarray(origins), np.asarray(directions)
    if o.ndim == 1:
        o = o[None]
    if d.ndim == 1:
        d = d[None]
    if o.ndim == 2 and d.ndim == 2 and len(o) == len(d) > 1 and o.strides[0] == 0:
        o = np.ascontiguousarray(o[:1])     # a broadcast view of one origin: that origin (24 bytes)
    if (o.dtype != d.dtype or o.dtype not in (np.float32, np.float64) or o.ndim != 2 or d.ndim != 2
            or o.shape[1] != 3 or d.shape[1] != 3 or len(d) == 0 or len(o) not in (1, len(d))
            or not (o.flags.c_contiguous and d.flags.c_contiguous)):
        return None
    tt = np.asarray(t_max)
    if tt.dtype.kind not in "fiu":
        return None
    if tt.ndim == 0:
        tm = float(np.asarray(tt, dtype=np.float64))
    elif tt.shape == (len(d),):
        tm = np.ascontiguousarray(tt, dtype=np.float64)
    else:
        return None
    return o, d, tm


def _grid_inputs(grid: Grid, origins, directions, t_end, stop):
    o, d, te = check_rays(origins, directions, t_end)
    local = grid.to_local(o)
    _check_near(local, (0.0, 0.0, 0.0), "the grid's lower corner")
    # a ray cannot pass more than the grid's diagonal; this keeps inf finite for float32 kernels
    extent = np.asarray(grid.upper) - np.asarray(grid.lower)
    diag = float(np.linalg.norm(extent))
    te = np.minimum(te, _row_norm(local - extent / 2) + diag)
    if stop is not None:
        stop = np.ascontiguousarray(np.asarray(stop).reshape(-1), dtype=np.uint8)
        if stop.shape != (grid.n_voxels,):
            raise ValueError(f"stop mask must have one entry per voxel ({grid.n_voxels}), got {stop.shape}")
    return local, d, te, stop


def traverse(grid: Grid, origins, directions, t_end, backend=None, stop=None) -> Traversal:
    """Voxels each ray segment [0, t_end] passes through, in visit order (Amanatides-Woo traversal).

    Args:
        grid: the voxel grid.
        origins, directions: (N, 3) rays in the grid's frame.
        t_end: scalar or (N,) segment lengths in metres.
        backend: backend name or instance.
        stop: optional per-voxel occlusion mask; a ray ends after the first voxel where it is set.
    """
    o, d, te, stop = _grid_inputs(grid, origins, directions, t_end, stop)
    b = get_backend(backend)
    offsets, voxels = b.traverse(grid.spec, o, d, te, stop)
    return Traversal(np.asarray(offsets, dtype=np.int64), np.asarray(voxels, dtype=np.int64))


def coverage(grid: Grid, origins, directions, t_end, backend=None, stop=None) -> np.ndarray:
    """Boolean array of ``grid.shape``: the union of voxels visited by the ray segments."""
    o, d, te, stop = _grid_inputs(grid, origins, directions, t_end, stop)
    b = get_backend(backend)
    return np.asarray(b.coverage(grid.spec, o, d, te, stop), dtype=bool).reshape(grid.shape)
