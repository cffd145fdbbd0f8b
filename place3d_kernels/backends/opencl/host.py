"""The OpenCL backend: kernels in ``*.cl`` next to this file, host code here (PyOpenCL)."""

from __future__ import annotations

import math
import re
import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from place3d_kernels.backends.base import (Backend, BackendUnavailable, DirectionCache, GridSpec, host_vote,
                                           mesh_face_tables, group_blocks, mesh_group_parts, rotation_matrices,
                                           sensor_directions)
from place3d_kernels.backends.geometry import brute_force_raycast
from place3d_kernels.backends.opencl import _runtime as rt
from place3d_kernels.backends.opencl.bvh import DEFAULT_MAX_DEPTH, BVH, build_bvh, collapse_bvh4, join_bvh
from place3d_kernels.backends.opencl.lbvh import build_lbvh
from place3d_kernels.backends.opencl.conditions import OpenCLConditions
from place3d_kernels.backends.opencl.fields import OpenCLFields
from place3d_kernels.backends.opencl.scoring import CLGrid, OpenCLScoring

__all__ = ["OpenCLBackend", "CLMesh", "CLGrid", "opencl_devices"]

_MF = cl.mem_flags
#: largest dense (voxel, class) count table of ``vote``; larger problems use hash tables
_DENSE_VOTE_BYTES = 256 * 2**20
#: work-group size on CPU devices
_CPU_GROUP = 8
#: flag slots of the raycast kernels (load_ray and RAY_STORE in raycast.cl: origin, direction, t_max, stack
#: overflow)
N_RAY_FLAGS = 4


def opencl_devices() -> list[str]:
    """Short names of the OpenCL platforms that have a usable device, e.g. ``['pocl']``; ``[]`` if none.

    Raises:
        ImportError: PyOpenCL is not installed (raised when this module is imported).
    """
    return list(rt.platform_table())


@dataclass(frozen=True)
class MeshPart:
    """A mesh part's tree (``OpenCLBackend.mesh_part``) and the faces it was built over (read-only), which a
    mesh extending the part must begin with."""

    bvh: BVH
    faces: np.ndarray


class CLMesh:
    """Handle of an uploaded mesh: the BVH on the host and its device buffers."""

    def __init__(self, backend: "OpenCLBackend", vertices: np.ndarray, faces: np.ndarray, bvh: BVH,
                 face_ids: np.ndarray, labels: np.ndarray):
        self.vertices = vertices
        self.faces = faces
        self.bvh = bvh
        ctx = backend.ctx
        self.width = backend.bvh_width
        self.bvh4 = collapse_bvh4(bvh) if self.width == 4 else None
        nodes = self.bvh4.nodes if self.width == 4 else bvh.nodes
        self.nodes = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=nodes)
        self.tris = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=bvh.tris)
        # the caller's face id and label of each uploaded face, for raycast_checked
        if len(face_ids) and (face_ids.min() < 0 or face_ids.max() >= 2**31):
            raise ValueError(f"face ids must lie in [0, 2**31), got [{face_ids.min()}, {face_ids.max()}]")
        self.face_ids = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=face_ids.astype(np.int32))
        self.face_labels = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=labels)
        if backend.fp64:  # the float64 mesh that decides the hits, and its reach (raycast.cl, ray_init)
            self.verts64 = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=vertices)
            self.faces32 = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=faces)
            self.reach = float(np.abs(vertices).max()) if vertices.size else 0.0

    def __repr__(self) -> str:
        tree = self.bvh4 if self.width == 4 else self.bvh
        return f"<CLMesh {len(self.faces)} faces, BVH{self.width} of {tree.n_nodes} nodes, depth {tree.depth}>"


class OpenCLBackend(OpenCLScoring, OpenCLFields, Backend, OpenCLConditions):
    """Kernels of the contract on one OpenCL device.

    Args:
        platform: short platform name as listed by ``opencl_devices()`` (``"pocl"``, ``"nvidia"``, ...),
            optionally ``"<platform>:<device index>"``; the first GPU of the platform by default.
        fp64: use double precision where the kernels refine float32 decisions (default: when the device
            has ``cl_khr_fp64``). ``False`` runs the pure float32 path (as on devices without doubles).
        stack_size: BVH traversal stack entries; defaults to the builder's depth cap. Smaller values exist
            to exercise the overflow fallback in tests.
        rays_per_item: rays walked by one work-item of the atomic ``score_placements`` strategy (default 1).
        bvh_width: 4 (a 4-wide tree: SIMD box tests on CPUs, fewer nodes visited on GPUs; the default) or 2
            (binary, the smaller traversal stack). On an NVIDIA GPU the 4-wide kernel was faster than the
            binary one in every run, with identical hits (bench/README.md, "What the studies found", ray-mesh,
            OpenCL on NVIDIA).
        score_strategy: ``"private"`` (a bitset per work-item, OR-reduced; default on CPUs) or ``"atomic"``
            (one shared bitset per candidate, atomic_or; default on GPUs). Both give identical results.
        score_kernel: the atomic strategy's kernel: ``"gpu"`` (``score_gpu.cl``: one ray per work-item, the
            Warp CUDA kernel's step; default on GPUs with 64-bit atomics) or ``"flat"`` (``score_rays_flat``:
            ``rays_per_item`` rays per work-item). Identical results.

    Raises:
        BackendUnavailable: no OpenCL platform/device, or the named one is absent.
    """

    dtype = np.float32
    resident_kernels = True

    def __init__(self, platform: str = "pocl", *, fp64: bool | None = None, stack_size: int | None = None,
                 rays_per_item: int | None = None, score_strategy: str | None = None, bvh_width: int | None = None,
                 score_kernel: str | None = None):
        plat, _, dev_index = str(platform).strip().lower().partition(":")
        # the named vendor's platforms alone (no other driver started); all of them where that names none
        table = rt.platform_table(re.sub(r"\d+$", "", plat))
        if plat not in table:
            table = rt.platform_table()
        if not table:
            raise BackendUnavailable(
                "no CL platforms available to the ICD loader (or none with a usable device). Install a CL "
                f"driver such as PoCL for the CPU: {rt.INSTALL_HINT}")
        if plat not in table:
            raise BackendUnavailable(
                f"OpenCL platform {platform!r} not found; platforms with a device here: {sorted(table)} "
                f"(use 'opencl:<name>'). For a CPU device install PoCL: {rt.INSTALL_HINT}")
        _, devices = table[plat]
        if dev_index:
            if not dev_index.isdigit() or int(dev_index) >= len(devices):
                raise BackendUnavailable(
                    f"OpenCL device index {dev_index!r} is not valid for platform {plat!r}, which has "
                    f"{len(devices)} device(s): " + ", ".join(f"{i}: {d.name}" for i, d in enumerate(devices)))
            self.device = devices[int(dev_index)]
        else:
            gpus = [d for d in devices if d.type & cl.device_type.GPU]
            self.device = (gpus or devices)[0]
        self.name = f"opencl:{str(platform).strip().lower()}"
        try:
            self.ctx = rt.probe_context(self.device) or rt.new_context(self.device)
            self.queue = cl.CommandQueue(self.ctx)
        except cl.Error as e:  # pragma: no cover - driver trouble
            raise BackendUnavailable(f"cannot create an OpenCL context on {self.device.name!r}: {e}") from e
        has_fp64 = "cl_khr_fp64" in self.device.extensions
        if fp64 and not has_fp64:
            raise BackendUnavailable(f"device {self.device.name!r} has no cl_khr_fp64; use fp64=None or False")
        self.fp64 = has_fp64 if fp64 is None else bool(fp64)
        self.real = np.float64 if self.fp64 else np.float32
        #: rays are checked and normalised on the device where it has doubles (the host's rule needs them)
        self.raycast_checks_rays = self.fp64
        self.stack_size = int(stack_size) if stack_size is not None else DEFAULT_MAX_DEPTH
        self.is_cpu = bool(self.device.type & cl.device_type.CPU)
        self.bvh_options = {"builder": "lbvh", "full_sah_limit": 0} if self.is_cpu else {"builder": "lbvh"}
        self.rays_per_item = int(rays_per_item) if rays_per_item else 1
        if score_strategy not in (None, "private", "atomic"):
            raise ValueError(f"score_strategy must be 'private' or 'atomic', got {score_strategy!r}")
        self.score_strategy = score_strategy or ("private" if self.is_cpu else "atomic")
        if score_kernel not in (None, "gpu", "flat"):
            raise ValueError(f"score_kernel must be 'gpu' or 'flat', got {score_kernel!r}")
        has_atom64 = "cl_khr_int64_base_atomics" in self.device.extensions
        if score_kernel == "gpu" and not has_atom64:
            raise BackendUnavailable(f"device {self.device.name!r} has no cl_khr_int64_base_atomics, which "
                                     "score_kernel='gpu' needs; use 'flat'")
        self.score_kernel = score_kernel or ("gpu" if has_atom64 and not self.is_cpu else "flat")
        #: on CPUs the private strategy walks 16 rays per work-item in vector lanes (walk_lanes.cl); False: one
        #: at a time (score_walk). Same bitsets; bench/bench_pocl_walk.py (tag lab-2026-11-27) compared the two.
        self.walk_lanes = self.is_cpu
        #: on CPUs ``vote`` is the host's sort (``base.host_vote``, the reference backend's vote, without the
        #: kernels' passes over their tables and buffers: a drive's ten subset votes 0.34-0.40 -> 0.18-0.22 s with
        #: PoCL on the 2-core dev VM, 2026-11-30); False: the kernels (the tests hold them to the reference)
        self.vote_on_host = self.is_cpu
        if bvh_width not in (None, 2, 4):
            raise ValueError(f"bvh_width must be 2 or 4, got {bvh_width!r}")
        self.bvh_width = bvh_width or 4
        self._kernels: dict[str, cl.Kernel] = {}
        self._lock = threading.Lock()   # a Kernel's arguments are set and enqueued in two steps
        #: counters of the last calls (``retraced_rays``: rays the ray caster handed back to the host)
        self.stats: dict[str, int] = {"retraced_rays": 0}
        self._dummy = cl.Buffer(self.ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=np.zeros(8, np.uint8))
        self._directions = DirectionCache(self._direction_table)
        self._pinned = None      # HostBlockPool of mapped pinned buffers (GPUs; created on first use)
        self._scratch: dict[int, list] = {}     # capacity -> free pooled device buffers (_scratch_take)
        self._scratch_lock = threading.Lock()
        #: sub-buffer offsets must be multiples of this many bytes (CL_DEVICE_MEM_BASE_ADDR_ALIGN is in bits)
        self._sub_align = max(8, int(self.device.mem_base_addr_align) // 8)

    # ----------------------------------------------------------------- plumbing
    def _options(self) -> tuple[str, ...]:
        return ("-DHAVE_FP64",) if self.fp64 else ()

    def _kernel(self, name: str) -> cl.Kernel:
        k = self._kernels.get(name)
        if k is None:  # first use: build (or fetch from the per-context cache) the program holding it
            if name in ("raycast", "raycast4"):
                files, opts = ("common.cl", "raycast.cl"), self._options() + (f"-DSTACK_SIZE={self.stack_size}",)
            elif name.startswith("vote_"):
                files, opts = ("common.cl", "vote.cl"), self._options()
            elif name.startswith("patch_"):
                files, opts = ("patch.cl",), ()
            elif name == "left_out_fields":
                files, opts = ("left_out.cl",), ()
            elif self.walk_lanes:   # walk_lanes.cl: the CPU walk, 32-bit voxel indices (see score_placements)
                files, opts = ("common.cl", "grid.cl", "walk_lanes.cl"), self._options() + ("-DFLAT32",)
            else:
                files, opts = ("common.cl", "grid.cl"), self._options()
            prg = rt.build_program(self.ctx, files, opts)
            for kk in prg.all_kernels():
                self._kernels[kk.function_name] = kk
            k = self._kernels[name]
        return k

    def _in(self, a: np.ndarray, keep: bool = False) -> cl.Buffer:
        """A read-only input buffer. Per-call inputs on CPU devices use the NumPy memory in place (no copy;
        PyOpenCL keeps the array alive); ``keep=True`` copies, for buffers that outlive the call."""
        a = np.ascontiguousarray(a)
        if a.nbytes == 0:
            return self._dummy
        flag = _MF.USE_HOST_PTR if (self.is_cpu and not keep) else _MF.COPY_HOST_PTR
        return cl.Buffer(self.ctx, _MF.READ_ONLY | flag, hostbuf=a)

    #: per-call device buffers of the ray caster come from a pool kept between calls (False: a new
    #: cl.Buffer each time; bench/opencl_raycast_parts.py, tag lab-2026-11-27, compared the two)
    reuse_device_buffers = True
    #: largest pooled device buffer (bytes); larger ones are made and freed per call
    _SCRATCH_MAX = 256 * 2**20

    def _scratch_take(self, nbytes: int) -> cl.Buffer:
        """A device buffer of at least ``nbytes`` bytes for one call: from the pool (capacities are powers of
        two from 64 KiB), or new. Hand it back with ``_scratch_give`` once the call has waited for its work."""
        cap = 1 << max(16, (max(int(nbytes), 1) - 1).bit_length())
        if self.reuse_device_buffers and cap <= self._SCRATCH_MAX:
            with self._scratch_lock:
                free = self._scratch.get(cap)
                if free:
                    return free.pop()
        return cl.Buffer(self.ctx, _MF.READ_WRITE, size=cap)

    def _scratch_give(self, bufs) -> None:
        """Return ``_scratch_take`` buffers whose commands have finished (two kept per capacity)."""
        if not self.reuse_device_buffers:
            return
        with self._scratch_lock:
            for b in bufs:
                if b.size <= self._SCRATCH_MAX:
                    free = self._scratch.setdefault(b.size, [])
                    if len(free) < 2:
                        free.append(b)

    def _upload(self, a: np.ndarray, scratch: list | None = None) -> cl.Buffer:
        """A read-only input buffer filled by an explicit copy on GPUs (``_in`` on CPU devices). NVIDIA's
        OpenCL moved a ``COPY_HOST_PTR`` buffer to the device only when the first kernel using it was
        enqueued, and that took longer than the copy itself (bench/README.md, "What the studies found",
        ray-mesh, OpenCL on NVIDIA). The copy waits for the queue: for inputs of a call whose queue is idle
        (the ray caster's)."""
        a = np.ascontiguousarray(a)
        if self.is_cpu or a.nbytes == 0:
            return self._in(a)
        if scratch is None:
            buf = cl.Buffer(self.ctx, _MF.READ_ONLY, size=a.nbytes)
        else:                   # a pooled buffer, listed in ``scratch`` for the caller to give back
            buf = self._scratch_take(a.nbytes)
            scratch.append(buf)
        cl.enqueue_copy(self.queue, buf, a)
        return buf

    def _out(self, nbytes: int) -> cl.Buffer:
        return cl.Buffer(self.ctx, _MF.READ_WRITE, size=max(int(nbytes), 8))

    def _host_out(self, dtype, n: int) -> tuple[np.ndarray, cl.Buffer]:
        """Output written by a kernel straight into a NumPy array on CPU devices (no copy back)."""
        arr = np.empty(max(int(n), 1), dtype=dtype)
        if self.is_cpu:
            return arr[:n], cl.Buffer(self.ctx, _MF.READ_WRITE | _MF.USE_HOST_PTR, hostbuf=arr)
        return arr[:n], self._out(arr.nbytes)

    def _fetch(self, arr: np.ndarray, buf: cl.Buffer) -> np.ndarray:
        """Make the kernel's writes to ``buf`` visible in ``arr`` (a map/unmap on CPU, a copy on GPUs)."""
        if arr.size == 0:
            return arr
        if self.is_cpu:
            mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, (buf.size,), np.uint8)
            mapped.base.release(self.queue)
            self.queue.finish()
        else:
            cl.enqueue_copy(self.queue, arr, buf)
        return arr

    def _read(self, buf: cl.Buffer, dtype, n: int) -> np.ndarray:
        out = np.empty(n, dtype=dtype)
        if n:
            cl.enqueue_copy(self.queue, out, buf)
        return out

    #: work-group size of the ray casters on GPUs (None: the driver's choice). 128 was a little faster than the
    #: driver's choice on an NVIDIA GPU in each run (bench/raymesh_bvh.py's ``:l<N>`` variants, tag
    #: lab-2026-11-27; bench/README.md, "What the studies found", ray-mesh, OpenCL on NVIDIA)
    ray_group_size: int | None = 128

    def _launch(self, name: str, n, *args):
        gsize = [int(n)] if np.isscalar(n) else [int(x) for x in n]
        if min(gsize) == 0:
            return
        lsize = None
        if self.ray_group_size and not self.is_cpu and name in ("raycast", "raycast4"):
            lsize = [int(self.ray_group_size)]
            gsize[0] = -(-gsize[0] // lsize[0]) * lsize[0]     # the kernels return for ids >= n
        elif self.is_cpu:
            # CPU drivers run one work-group per thread; small groups balance the uneven ray costs
            lsize = [_CPU_GROUP] + [1] * (len(gsize) - 1)
            gsize[0] = -(-gsize[0] // _CPU_GROUP) * _CPU_GROUP
        k = self._kernel(name)
        with self._lock:
            k(self.queue, tuple(gsize), None if lsize is None else tuple(lsize), *args)

    def _stop_buffer(self, stop, spec: GridSpec, keep: bool = False) -> cl.Buffer:
        if stop is None:
            return self._dummy
        s = np.ascontiguousarray(stop, dtype=np.uint8).reshape(-1)
        if s.shape != (spec.n_voxels,):
            raise ValueError(f"stop mask must have one uint8 per voxel ({spec.n_voxels}), got shape {s.shape}")
        return self._in(s, keep=keep)

    def _rays(self, origins, directions, t):
        r = self.real
        o = np.ascontiguousarray(origins, dtype=r).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=r).reshape(-1, 3)
        tt = np.ascontiguousarray(np.broadcast_to(np.asarray(t, dtype=r), (len(o),)))
        return o, d, tt

    def _grid_args(self, grid: GridSpec, stop_buf: cl.Buffer, use_stop: bool) -> tuple:
        nx, ny, nz = (int(v) for v in grid.shape)
        if grid.n_voxels >= 2**62:  # pragma: no cover
            raise ValueError(f"grid of {grid.n_voxels} voxels is too large")
        return (self.real(grid.voxel_size), np.int32(nx), np.int32(ny), np.int32(nz), stop_buf,
                np.int32(1 if use_stop else 0))

    def synchronize(self) -> None:
        self.queue.finish()

    def warmup(self) -> None:
        """Compile every program now (benchmarks call this so that compile time stays out of timings)."""
        for name in ("dda_count", "raycast", "vote_insert"):
            self._kernel(name)

    # ----------------------------------------------------------------- rays
    def lidar_rays(self, elevations, azimuths, poses):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
        rig, local = self._rig(poses, elevations, azimuths)
        L, CA = len(poses), len(local)
        n = L * CA
        # on CPU devices the kernel writes the returned arrays themselves, and float64 ones are not copied again:
        # a drive's 2.6 M rays were read back and copied twice more, about 0.2 s a drive on the dev VM
        (o, ob), (d, db) = self._host_out(self.real, n * 3), self._host_out(self.real, n * 3)
        self._launch("lidar_rays", n, self._in(rig), self._in(local), np.int32(L), np.int32(CA), ob, db)
        o = self._fetch(o, ob).reshape(-1, 3).astype(np.float64, copy=False)
        d = self._fetch(d, db).reshape(-1, 3).astype(np.float64, copy=False)
        return o, d

    def _rig(self, poses: np.ndarray, elevations, azimuths) -> tuple[np.ndarray, np.ndarray]:
        """(P*L, 12) origin + row-major rotation, and (C*A, 3) sensor-frame directions, in `real`."""
        local = sensor_directions(elevations, azimuths)
        return self._rig_poses(poses), np.ascontiguousarray(local, dtype=self.real)

    def _rig_poses(self, poses: np.ndarray) -> np.ndarray:
        """(P*L, 12) origin + row-major rotation of (P*L, 6) poses, in `real`."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
        rig = np.concatenate([poses[:, :3], rotation_matrices(poses).reshape(-1, 9)], axis=1)
        return np.ascontiguousarray(rig, dtype=self.real)

    def _direction_table(self, sd: np.ndarray) -> tuple[np.ndarray, "cl.Buffer"]:
        """DirectionCache's entry: the table in `real` and a buffer of its own (kept across calls)."""
        local = np.ascontiguousarray(sd, dtype=self.real)
        return local, self._in(local, keep=True)

    # ----------------------------------------------------------------- ray-mesh
    #: how meshes uploaded from now on get their trees (``_tree``): the builder and its keyword arguments
    #: (leaf_size, bins, full_sah_limit); set per device in ``__init__``. Every device builds Morton-order trees
    #: (``lbvh.build_lbvh``), since a drive waits for its static mesh's trees more than for their 40 sweeps; where
    #: that builder falls back to SAH, CPUs split on the widest axis (``full_sah_limit=0``), GPUs try all three.
    #: 2026-11-30, SAH -> Morton, 3 pairs each: two Town03 drives simulated on the dev VM's PoCL 4.52-4.56 ->
    #: 3.68-3.74 s (casts 1.28-1.44 -> 1.56-1.62 s), on an H200's opencl:nvidia 3.31-3.54 -> 1.66-1.84 s (casts
    #: 0.15-0.16 s both), a 1M-triangle city built there in 4.4-5.5 -> 1.6-2.0 s (its 524k-ray cast 5.1-6.5 /
    #: 4.7-6.6 ms); `reproduce --routes 8`'s pool on the dev VM 74.8 -> 61.0 s (3 runs each, alternated). Every
    #: choice gives the same hits.
    bvh_options: dict = {}

    def _tree(self, vertices, faces, **kw) -> BVH:
        """A mesh's binary tree, built as ``bvh_options`` say (``builder``: ``"lbvh"``, ``lbvh.build_lbvh``, or
        ``"sah"``, ``bvh.build_bvh``; the other keys are the builder's arguments)."""
        opts = dict(self.bvh_options)
        builder = opts.pop("builder", "sah")
        if builder not in ("sah", "lbvh"):
            raise ValueError(f"bvh_options' builder must be 'sah' or 'lbvh', got {builder!r}")
        return (build_lbvh if builder == "lbvh" else build_bvh)(vertices, faces, **kw, **opts)

    def upload_mesh(self, vertices, faces, face_ids=None, labels=None, prefix=None):
        """``Backend.upload_mesh``; ``prefix``: (a ``mesh_part`` of this mesh's first faces, the (3,) float64
        offset from that part's frame to this one's), where ``extends_meshes``: only the other faces' tree is
        built, joined under one root with the part's (``bvh.join_bvh``)."""
        # private copies: the handle must not change if the caller edits its arrays later
        v = np.array(vertices, dtype=np.float64, copy=True).reshape(-1, 3)
        f = np.array(faces, dtype=np.int32, copy=True).reshape(-1, 3)
        ids, lab = mesh_face_tables(len(f), face_ids, labels)
        part = None if prefix is None else prefix[0]
        if part is not None and not self.extends_meshes:
            raise NotImplementedError(f"{self.name} has no doubles: it does not extend mesh parts (extends_meshes)")
        if part is not None and (len(part.faces) >= len(f) or not np.array_equal(f[:len(part.faces)], part.faces)):
            raise ValueError("upload_mesh's prefix part is not this mesh's first faces (or leaves none to add)")
        if part is None:
            bvh = self._tree(v, f, max_depth=DEFAULT_MAX_DEPTH)
        else:
            rest = self._tree(v, f[len(part.faces):], max_depth=DEFAULT_MAX_DEPTH - 1)
            bvh = join_bvh(part.bvh, rest, prefix[1])
        return CLMesh(self, v, f, bvh, ids, lab)

    @property
    def extends_meshes(self) -> bool:
        """Whether ``upload_mesh`` takes a ``prefix`` (``Mesh.extended``): on devices with doubles, where the
        float64 test decides every hit whatever the tree, so a joined tree gives a whole build's hits."""
        return self.fp64

    def mesh_part(self, vertices, faces) -> "MeshPart":
        """The tree of a mesh's faces that meshes extending it reuse (``upload_mesh(prefix=...)``): built one
        level short of the depth cap, which the joined tree's new root then takes."""
        f = np.array(faces, dtype=np.int32, copy=True).reshape(-1, 3)
        f.setflags(write=False)
        return MeshPart(self._tree(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), f,
                                   max_depth=DEFAULT_MAX_DEPTH - 1), f)

    def _ray_args(self, mesh, o, o_step, d, tm, t_step, shift, tb, fb, lb, map_faces, flags,
                  scratch: list | None = None, groups: tuple | None = None) -> list:
        """Arguments of the raycast/raycast4 kernels (RAY_ARGS in raycast.cl) and the mesh's; with ``scratch``
        the rays go to pooled buffers listed there (see ``_upload``). ``groups``: (shifts (G, 3) float64,
        rays per group, first group) for a grouped tree (``raycast_groups``)."""
        f32 = o.dtype == np.float32
        if not f32 and not self.fp64:
            raise TypeError(f"{self.name} has no doubles: rays must be float32 here, got {o.dtype}")
        shifts, per_group, first = (self._dummy, 0, 0) if groups is None else (
            self._upload(np.ascontiguousarray(groups[0], dtype=self.real), scratch), groups[1], groups[2])
        args = [mesh.nodes, mesh.tris, self._upload(o, scratch), np.int32(o_step), self._upload(d, scratch),
                np.int32(f32), self._upload(tm, scratch),
                np.int32(t_step), *(self.real(x) for x in shift), shifts, np.int32(per_group), np.int32(first),
                tb, fb, lb, mesh.face_ids, mesh.face_labels, np.int32(map_faces), flags, np.int32(len(d))]
        if self.fp64:
            args += [mesh.verts64, mesh.faces32, np.float64(mesh.reach)]
        return args

    def raycast(self, mesh, origins, directions, t_max):
        if not isinstance(mesh, CLMesh):
            raise TypeError(f"raycast needs the handle returned by {self.name}.upload_mesh, got {type(mesh).__name__}")
        o, d, tm = self._rays(origins, directions, t_max)
        n = len(o)
        if n == 0:
            return np.empty(0, np.float64), np.empty(0, np.int32)
        (t, tb), (face, fb) = self._host_out(self.real, n), self._host_out(np.int32, n)
        # checked rays: the kernel's checks pass and its normalisation leaves them as they are
        flags = self._out(4 * N_RAY_FLAGS)
        args = self._ray_args(mesh, o, 1, d, tm, 1, (0.0, 0.0, 0.0), tb, fb, self._dummy, 0, flags)
        self._launch("raycast4" if mesh.width == 4 else "raycast", n, *args)
        t = self._fetch(t, tb).astype(np.float64, copy=False)
        face = self._fetch(face, fb)
        o64 = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d64 = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        tm64 = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,))
        if not self.fp64:
            t, face = _refine_on_host(mesh, o64, d64, tm64, t, face)
        over = np.flatnonzero(face == -2)
        self.stats["retraced_rays"] = len(over)
        if len(over):  # stack overflow (cannot happen for builder trees): trace these on the host
            t[over], face[over] = brute_force_raycast(mesh.vertices, mesh.faces, o64[over], d64[over], tm64[over])
        return t, face

    def raycast_checked(self, mesh, origins, directions, t_max, shift):
        """The four outputs (t float64 | face int64 | label int32 | flags) are sub-buffers of one buffer, so
        that they come back in one copy: on GPUs into a pooled pinned host block that the returned arrays
        view (as the Warp backend does), on CPUs the kernel writes the host block itself."""
        if not isinstance(mesh, CLMesh):
            raise TypeError(f"raycast_checked needs the handle returned by {self.name}.upload_mesh, "
                            f"got {type(mesh).__name__}")
        if not self.fp64:
            raise NotImplementedError(f"{self.name} has no doubles (raycast_checks_rays is False); validate the "
                                      f"rays and call raycast")
        return self._cast_checked(mesh, origins, directions, t_max, np.asarray(shift, dtype=np.float64).reshape(3))

    @property
    def casts_groups(self) -> bool:
        """Whether ``upload_mesh_groups`` / ``raycast_groups`` serve ``ops.MeshGroups`` here: devices with
        doubles (the checked path the groups share with ``raycast_checked``)."""
        return self.fp64

    def upload_mesh_groups(self, parts):
        """One BVH over several meshes, a tree of its own per mesh (``build_bvh``'s ``groups``), for
        ``raycast_groups``.

        Args:
            parts: one (vertices (V, 3) float64 already shifted, faces (F, 3), face_ids (F,) or None, labels
                (F,) or None) per group, as ``upload_mesh`` takes them; every part needs a face.
        """
        groups = mesh_group_parts(parts)
        base = np.cumsum([0] + [len(v) for v, *_ in groups[:-1]])
        v = np.concatenate([g[0] for g in groups])
        f = np.concatenate([g[1] + b for g, b in zip(groups, base)]).astype(np.int32)   # into the joined vertices
        bvh = self._tree(v, f, max_depth=DEFAULT_MAX_DEPTH, groups=[len(g[1]) for g in groups])
        return CLMesh(self, v, f, bvh, np.concatenate([g[2] for g in groups]), np.concatenate([g[3] for g in groups]))

    def raycast_groups(self, mesh, origins, directions, t_max, shifts, rays_per_group: int, first: int = 0):
        """Warp's ``raycast_groups`` here: ray block k into mesh ``first + k`` of a tree from ``upload_mesh_groups``
        with that mesh's shift; (t, face id int64, label int32), or None where a ray fails ops.raycast's checks
        (or the device has no doubles)."""
        if not isinstance(mesh, CLMesh):
            raise TypeError(f"raycast_groups needs the handle returned by {self.name}.upload_mesh_groups, "
                            f"got {type(mesh).__name__}")
        r = int(rays_per_group)
        group_blocks(len(origins), len(directions), r, first, min(len(shifts), mesh.bvh.roots))
        if not self.fp64:
            return None
        return self._cast_checked(mesh, np.ascontiguousarray(origins, dtype=np.float64),
                                  np.ascontiguousarray(directions, dtype=np.float64), t_max, (0.0, 0.0, 0.0),
                                  (np.asarray(shifts, dtype=np.float64).reshape(-1, 3), r, int(first)))

    def _cast_checked(self, mesh, origins, directions, t_max, shift, groups=None):
        n = len(directions)
        t_step = 1 if np.ndim(t_max) else 0
        tm = np.ascontiguousarray(t_max, dtype=np.float64) if t_step else np.full(1, float(t_max))
        scratch: list = []
        at, host, dev = self._checked_block(n, scratch)
        tb, fb, lb, fl = (dev.get_sub_region(a, m) for a, m in zip(at, (8 * n, 8 * n, 4 * n, 4 * N_RAY_FLAGS)))
        args = self._ray_args(mesh, origins, 1 if len(origins) == n else 0, directions, tm, t_step,
                              shift, tb, fb, lb, 1, fl, scratch, groups)
        self._launch("raycast4" if mesh.width == 4 else "raycast", n, *args)
        self._fetch(host, dev)          # a blocking copy: the kernel and the uploads are done
        del tb, fb, lb, fl, args
        self._scratch_give(scratch)
        # a failed check, or a BVH stack overflow (not for builder trees): the host path redoes the call
        if host[at[3]:at[3] + 4 * N_RAY_FLAGS].view(np.int32).any():
            return None
        return (host[:8 * n].view(np.float64), host[at[1]:at[1] + 8 * n].view(np.int64),
                host[at[2]:at[2] + 4 * n].view(np.int32))

    def _checked_block(self, n: int, scratch: list) -> tuple[tuple[int, int, int, int], np.ndarray, cl.Buffer]:
        """(offsets of t, face, label and flags; the host block; the device buffer) for ``raycast_checked``
        of n rays, the flags zeroed. Offsets are multiples of the device's sub-buffer alignment. A pooled
        device buffer is listed in ``scratch``."""
        def up(x: int) -> int:
            return -(-x // self._sub_align) * self._sub_align

        at = (0, up(8 * n), up(up(8 * n) + 8 * n), up(up(up(8 * n) + 8 * n) + 4 * n))
        total = at[3] + 4 * N_RAY_FLAGS
        if self.is_cpu:
            # the kernel writes host memory in place (USE_HOST_PTR), aligned for the sub-buffers
            raw = np.empty(total + self._sub_align, np.uint8)
            skip = -raw.ctypes.data % self._sub_align
            host = raw[skip:skip + total]
            host[at[3]:] = 0
            return at, host, cl.Buffer(self.ctx, _MF.READ_WRITE | _MF.USE_HOST_PTR, hostbuf=host)
        if self._pinned is None:
            from place3d_kernels.backends.pinned import HostBlockPool

            self._pinned = HostBlockPool(self._pinned_block)
        host = self._pinned.take(total)[1]
        dev = self._scratch_take(total)
        scratch.append(dev)
        cl.enqueue_fill_buffer(self.queue, dev, np.int32(0), at[3], 4 * N_RAY_FLAGS)
        return at, host, dev

    def _pinned_block(self, cap: int):
        """``HostBlockPool`` allocator: a host-allocated (pinned on GPU drivers) buffer, mapped for good;
        copies from the device into the mapped memory are one DMA (NVIDIA's OpenCL best-practice pattern)."""
        buf = cl.Buffer(self.ctx, _MF.READ_WRITE | _MF.ALLOC_HOST_PTR, size=cap)
        mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ | cl.map_flags.WRITE, 0, (cap,),
                                          np.uint8)
        return (buf, mapped), mapped.ctypes.data

    # ----------------------------------------------------------------- voxel traversal
    def count_visits(self, grid, origins, directions, t_end, stop=None) -> np.ndarray:
        """Voxels each ray visits (the first pass of ``traverse``); (N,) int64. Benchmarks count steps with it."""
        o, d, te = self._rays(origins, directions, t_end)
        n = len(o)
        counts, cb = self._host_out(np.int64, n)
        if n:
            ga = self._grid_args(grid, self._stop_buffer(stop, grid), stop is not None)
            self._launch("dda_count", n, self._in(o), self._in(d), self._in(te), *ga, cb, np.int32(n))
        return self._fetch(counts, cb)

    def traverse(self, grid, origins, directions, t_end, stop=None):
        o, d, te = self._rays(origins, directions, t_end)
        n = len(o)
        offsets = np.zeros(n + 1, dtype=np.int64)
        if n == 0:
            return offsets, np.empty(0, np.int64)
        ob, db, tb = self._in(o), self._in(d), self._in(te)
        ga = self._grid_args(grid, self._stop_buffer(stop, grid), stop is not None)
        cb = self._out(n * 8)
        self._launch("dda_count", n, ob, db, tb, *ga, cb, np.int32(n))
        np.cumsum(self._read(cb, np.int64, n), out=offsets[1:])
        total = int(offsets[-1])
        if total == 0:
            return offsets, np.empty(0, np.int64)
        voxels, vb = self._host_out(np.int64, total)
        self._launch("dda_fill", n, ob, db, tb, *ga, self._in(offsets), vb, np.int32(n))
        return offsets, self._fetch(voxels, vb)

    def coverage(self, grid, origins, directions, t_end, stop=None):
        o, d, te = self._rays(origins, directions, t_end)
        n, nv = len(o), grid.n_voxels
        out, mask = self._host_out(np.uint8, nv)
        cl.enqueue_fill_buffer(self.queue, mask, np.uint8(0), 0, mask.size)
        if n:
            ga = self._grid_args(grid, self._stop_buffer(stop, grid), stop is not None)
            self._launch("dda_coverage", n, self._in(o), self._in(d), self._in(te), *ga, mask, np.int32(n))
        return self._fetch(out, mask).view(bool)

    # ----------------------------------------------------------------- benchmark hooks (kernel-only timers)
    def resident_raycast(self, mesh, origins, directions, t_max):
        """For benchmarks: a zero-argument callable that runs the ray-mesh kernel on rays already on the
        device and waits for it (no host transfers), so kernel throughput can be timed apart from data
        movement (as ``WarpCore.resident_raycast``). Rays are in the mesh's frame with unit directions,
        as ``raycast`` receives them. ``run.read()`` copies the results of the last run back once and
        returns ``(t, face)`` as ``raycast`` does (devices without fp64 refine on the host there too;
        rays of a BVH stack overflow stay ``face == -2``: this is the kernel alone)."""
        if not isinstance(mesh, CLMesh):
            raise TypeError(f"resident_raycast needs the handle returned by {self.name}.upload_mesh, "
                            f"got {type(mesh).__name__}")
        o, d, tm = self._rays(origins, directions, t_max)
        n = len(o)
        tb, fb = self._out(n * np.dtype(self.real).itemsize), self._out(n * 4)
        o, d, tm = (np.array(a, copy=True) for a in (o, d, tm))   # the buffers outlive this call
        args = self._ray_args(mesh, o, 1, d, tm, 1, (0.0, 0.0, 0.0), tb, fb, self._dummy, 0,
                              self._out(4 * N_RAY_FLAGS))
        kernel = "raycast4" if mesh.width == 4 else "raycast"
        self._kernel(kernel)   # compile now, not inside the first timed call

        def run() -> None:
            self._launch(kernel, n, *args)
            self.queue.finish()

        def read() -> tuple[np.ndarray, np.ndarray]:
            t = self._read(tb, self.real, n).astype(np.float64)
            face = self._read(fb, np.int32, n)
            if not self.fp64:   # as raycast: the float64 inputs, not their float32 copies on the device
                o64 = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
                d64 = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
                tm64 = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,))
                t, face = _refine_on_host(mesh, o64, d64, tm64, t, face)
            return t, face

        run.read = read
        return run

    def resident_traverse(self, grid, origins, directions, t_end, stop=None):
        """For benchmarks: a zero-argument callable that runs the traversal count kernel (``dda_count``, the
        first pass of ``traverse``) on rays already on the device and waits for it (see
        ``resident_raycast``). Rays are in the grid's local frame. ``run.read()`` copies the per-ray voxel
        counts of the last run back once ((N,) int64, ``np.diff`` of ``traverse``'s offsets)."""
        o, d, te = self._rays(origins, directions, t_end)
        n = len(o)
        cb = self._out(n * 8)
        ga = self._grid_args(grid, self._stop_buffer(stop, grid, keep=True), stop is not None)
        args = [self._in(o, keep=True), self._in(d, keep=True), self._in(te, keep=True), *ga, cb, np.int32(n)]
        self._kernel("dda_count")

        def run() -> None:
            self._launch("dda_count", n, *args)
            self.queue.finish()

        run.read = lambda: self._read(cb, np.int64, n)
        return run

    # ----------------------------------------------------------------- occupancy grids
    def voxel_keys(self, grid, points):
        p = np.ascontiguousarray(points, dtype=self.real).reshape(-1, 3)
        n = len(p)
        out = self._out(n * 8)
        nx, ny, nz = (int(v) for v in grid.shape)
        self._launch("voxel_keys", n, self._in(p), self.real(grid.voxel_size), np.int32(nx), np.int32(ny),
                     np.int32(nz), out, np.int32(n))
        return self._read(out, np.int64, n)

    def vote(self, keys, labels, n_classes):
        k = np.ascontiguousarray(keys, dtype=np.int64).reshape(-1)
        lab = np.ascontiguousarray(labels, dtype=np.int32).reshape(-1)
        if k.shape != lab.shape:
            raise ValueError(f"keys {k.shape} and labels {lab.shape} must have the same length")
        n_classes = int(n_classes)
        if len(lab) and (lab.min() < 0 or lab.max() >= n_classes):
            raise ValueError(f"labels must lie in [0, {n_classes}), got range [{lab.min()}, {lab.max()}]")
        if self.vote_on_host:
            return host_vote(k, lab, n_classes)     # its own voting mask (empty votes included)
        voting = (k >= 0) & (lab > 0)
        n_vote = int(voting.sum())
        if n_vote == 0:
            return np.empty(0, np.int64), np.empty(0, np.int32)
        kmax = int(k.max())
        n = len(k)
        lab_b = self._in(lab)
        keys_b = self._in(k)
        if kmax < 16 * n_vote + 2**22:
            # dense: flags per key, ranks by a prefix sum (ascending order for free), counts per (rank, label)
            flags, fb = self._host_out(np.uint8, kmax + 1)
            cl.enqueue_fill_buffer(self.queue, fb, np.uint8(0), 0, fb.size)
            self._launch("vote_mark", n, keys_b, lab_b, fb, np.int32(n))
            flags = self._fetch(flags, fb)
            voxels = np.flatnonzero(flags)
            M = len(voxels)
            if M * n_classes * 4 <= _DENSE_VOTE_BYTES:
                rank = np.empty(kmax + 1, dtype=np.int32)   # read only where flagged
                rank[voxels] = np.arange(M, dtype=np.int32)
                cnt = self._out(M * n_classes * 4)
                cl.enqueue_fill_buffer(self.queue, cnt, np.int32(0), 0, M * n_classes * 4)
                self._launch("vote_count_dense", n, keys_b, lab_b, self._in(rank), np.int32(n_classes), cnt,
                             np.int32(n))
                best, bb = self._host_out(np.int32, M)
                self._launch("vote_argmax", M, cnt, np.int32(n_classes), bb, np.int32(M))
                return voxels.astype(np.int64, copy=False), self._fetch(best, bb)
        if kmax >= 2**31 - 1 or n_vote * n_classes >= 2**31 - 1:
            return host_vote(k, lab, n_classes)  # beyond 32-bit hash keys: exact host path
        H = 1 << max(4, int(math.ceil(math.log2(2 * n_vote))))
        table = self._out(H * 4)
        cl.enqueue_fill_buffer(self.queue, table, np.int32(-1), 0, H * 4)
        slot = self._out(n * 4)
        self._launch("vote_insert", n, keys_b, lab_b, table, np.uint32(H - 1), slot, np.int32(n))
        tab = self._read(table, np.int32, H)
        occ = np.flatnonzero(tab >= 0)
        order = np.argsort(tab[occ], kind="stable")
        voxels = tab[occ][order].astype(np.int64)
        M = len(voxels)
        rank = np.full(H, -1, dtype=np.int32)
        rank[occ[order]] = np.arange(M, dtype=np.int32)
        t2 = self._out(H * 4)
        c2 = self._out(H * 4)
        cl.enqueue_fill_buffer(self.queue, t2, np.int32(-1), 0, H * 4)
        cl.enqueue_fill_buffer(self.queue, c2, np.int32(0), 0, H * 4)
        self._launch("vote_pairs", n, slot, lab_b, self._in(rank), np.int32(n_classes), t2, c2,
                     np.uint32(H - 1), np.int32(n))
        bc = self._out(M * 4)
        bl = self._out(M * 4)
        cl.enqueue_fill_buffer(self.queue, bc, np.int32(0), 0, M * 4)
        cl.enqueue_fill_buffer(self.queue, bl, np.int32(2**31 - 1), 0, M * 4)
        self._launch("vote_best_count", H, t2, c2, np.int32(n_classes), bc, np.int32(H))
        self._launch("vote_best_label", H, t2, c2, np.int32(n_classes), bc, bl, np.int32(H))
        return voxels, self._read(bl, np.int32, M)

def _refine_on_host(mesh: CLMesh, o, d, tm, t, face):
    """Float64 hit distance of the reported face (devices without fp64), as the kernel does otherwise."""
    hit = np.flatnonzero(face >= 0)
    if len(hit) == 0:
        return t, face
    f = mesh.faces[face[hit]]
    v = mesh.vertices
    oo, dd = o[hit], d[hit]
    r = np.arange(len(hit))
    kz = np.argmax(np.abs(dd), axis=1)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    neg = dd[r, kz] < 0
    kx, ky = np.where(neg, ky, kx), np.where(neg, kx, ky)
    dz = dd[r, kz]
    sx, sy, sz = dd[r, kx] / dz, dd[r, ky] / dz, 1.0 / dz
    P = []
    for j in range(3):
        rel = v[f[:, j]] - oo
        rz = rel[r, kz]
        P.append((rel[r, kx] - sx * rz, rel[r, ky] - sy * rz, sz * rz))
    (ax, ay, az), (bx, by, bz), (cx, cy, cz) = P
    u = cx * by - cy * bx
    vv = ax * cy - ay * cx
    w = bx * ay - by * ax
    det = u + vv + w
    with np.errstate(divide="ignore", invalid="ignore"):
        td = np.where(det != 0, (u * az + vv * bz + w * cz) / det, t[hit])
    td = np.maximum(td, 0.0)
    over = td > tm[hit]
    t = t.copy()
    face = face.copy()
    t[hit] = np.where(over, np.inf, td)
    face[hit] = np.where(over, -1, face[hit])
    return t, face
