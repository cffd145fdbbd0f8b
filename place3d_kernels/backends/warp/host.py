"""Warp backend: the kernels of ``kernels.py`` on Warp's CPU device or a CUDA GPU. Host code here: device
start-up, the launch plumbing, rays, ray-mesh, traversal, coverage and votes; the prepared grids and the
M-SOG scores are the mixin ``WarpScoring`` (scoring.py), the condition models ``WarpConditions``
(conditions.py), the CPU thread count and chunk sizes cpu_split.py.

Warp's CPU device runs each kernel launch on one thread (NVIDIA/warp#1309). On the CPU this backend
therefore splits the launches of its heavy kernels (ray-mesh, traversal, coverage, scores) into chunks
and runs them on a pool of Python threads, one per usable core (``PLACE3D_WARP_CPU_THREADS`` overrides):
a CPU launch is a ctypes call, which releases the GIL, and Warp 1.x passes the task index as an argument
(no shared static state). Only kernels whose chunks write disjoint outputs, or store the same value to a
shared one (coverage's byte mask), are split that way; Warp's CPU "atomics" are plain read-modify-writes,
so the score kernel is split by candidate (each candidate owns its bitset and sum), never inside one.
CUDA devices run each kernel as one launch on the GPU.
Meshes use Warp's BVH (``wp.Mesh``): a walk of its tree in native code, nearest child first, gives every
triangle that could be hit first to the reference's float64 test (kernels.py, ``closest_hit``).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from place3d_kernels.backends.base import (Backend, BackendUnavailable, DirectionCache, mesh_face_tables,
                                           group_blocks, mesh_group_parts, rotation_matrices, sensor_directions)
from place3d_kernels.backends.warp.cpu_split import CHUNKS_PER_THREAD, MIN_CHUNK, cpu_threads

try:
    import warp as wp
except ImportError as e:  # pragma: no cover - exercised only without warp installed
    raise ImportError(f"warp-lang is not installed ({e})") from None

from place3d_kernels.backends.warp.conditions import WarpConditions
from place3d_kernels.backends.warp.scoring import WarpScoring

_initialised = False
_init_output = ""     # what Warp's native init printed (kept quiet; quoted when a CUDA device is missing)


def _init() -> None:
    global _initialised, _init_output
    if not _initialised:
        import logging

        from place3d_kernels.backends import cuda_early

        waiting = cuda_early.pending()
        if waiting:
            # the driver is making the context on another thread (cuda_early): the kernels' modules, Python
            # that would otherwise follow Warp's init, are imported meanwhile; then Warp finds the context made
            import importlib

            for module in ("kernels", "score_gpu", "left_out_kernels"):
                importlib.import_module(f"place3d_kernels.backends.warp.{module}")
            for t in waiting:
                t.join()

        if os.environ.get("PLACE3D_WARP_VERBOSE") is None:
            wp.config.log_level = logging.WARNING   # no init banner unless asked for
            # Warp's native library prints "Could not find or load the NVIDIA CUDA driver" straight to
            # file descriptor 1 on every machine without one, CPU-only runs included; it is captured here
            # and repeated only in the error for a CUDA device that is not available
            _init_output = _quiet_call(wp.init)
        else:
            wp.init()
        _initialised = True


def _quiet_call(fn) -> str:
    """Run ``fn()`` with file descriptors 1 and 2 redirected to a temporary file; return what it wrote.
    (Native code writes to the descriptors, not to ``sys.stdout``; output of other threads in that
    window goes to the file too.)"""
    import sys
    import tempfile

    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    with tempfile.TemporaryFile() as tmp:
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            fn()
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        tmp.seek(0)
        return tmp.read().decode(errors="replace").strip()


def warp_devices() -> list[str]:
    """Warp device names usable here, e.g. ``['cpu', 'cuda:0']``."""
    _init()
    return [str(d) for d in wp.get_devices()]


def startup_note() -> str:
    """What Warp's native library printed at initialisation (quiet unless ``PLACE3D_WARP_VERBOSE`` is set),
    e.g. that no CUDA driver was found; empty if nothing or not initialised yet."""
    return _init_output


class _WarpMesh:
    def __init__(self, mesh, points, indices, corners64, reach, face_ids, face_labels):
        self.mesh = mesh          # keep the arrays alive with the BVH
        self.points = points
        self.indices = indices
        self.corners64 = corners64
        self.reach = reach        # largest |coordinate| of a corner (kernels.py, closest_hit)
        self.face_ids = face_ids          # int64 caller's face id per uploaded face (raycast_checked)
        self.face_labels = face_labels    # int32 label per uploaded face (raycast_checked)
        self.t_const = None       # (n, t_max) and its (n,) device array, for repeated scalar bounds


class WarpCore(WarpScoring, Backend):
    """Core kernels on one Warp device."""

    dtype = np.float32
    resident_kernels = True

    def __init__(self, device: str = "cpu"):
        _init()
        try:
            self.device = wp.get_device(device)
        except Exception as e:  # noqa: BLE001 - Warp raises several types here
            said = f" (Warp at start-up: {_init_output})" if _init_output and "cuda" in str(device) else ""
            raise BackendUnavailable(f"Warp device {device!r} is not available: {e}{said}") from None
        self.name = f"warp:{self.device}"
        from place3d_kernels.backends.warp import kernels, score_gpu

        self.k = kernels
        self.score_gpu = score_gpu       # the CUDA score kernel's module of its own
        self._empty_u8 = wp.zeros(1, dtype=wp.uint8, device=self.device)
        self._directions = DirectionCache(lambda sd: (sd, self._vec3d(sd)))
        self.threads = 1 if self.device.is_cuda else cpu_threads()
        self._pool = None
        self._pool_lock = threading.Lock()
        self._bits = None         # the kept bitset buffer (CUDA; _take_bits)
        self._loaded = set()      # kernels launched once already (module compiled and loaded)
        self._pinned = None       # HostBlockPool for large device-to-host copies (CUDA only; created on first use)
        #: what ``aot.load`` did: the shipped CUDA binaries loaded (e.g. "cubin sm90"), or why not (Warp then
        #: compiles on first launch); None on the CPU. PLACE3D_WARP_AOT=0 skips them (to time the JIT).
        self.aot = None
        if self.device.is_cuda:
            if os.environ.get("PLACE3D_WARP_AOT", "1") == "0":
                self.aot = "off (PLACE3D_WARP_AOT=0)"
            else:
                from place3d_kernels.backends.warp import aot

                try:
                    self.aot = aot.load(self.device)
                except Exception as e:  # noqa: BLE001 - a damaged file, a driver too old for the CUBIN, a
                    # Warp whose loader differs: none may cost the backend, which then compiles as before
                    self.aot = f"failed, compiling instead: {type(e).__name__}: {e}"

    # ------------------------------------------------------------------ launches
    def _launch(self, kernel, n: int, inputs) -> None:
        """Launch ``kernel`` over ``n`` independent items; ``inputs(lo, hi)`` gives its inputs for items
        ``lo..hi-1`` (array views of that range plus the shared arguments). On the GPU, or for small ``n``,
        one launch; on the CPU with several threads, chunks of the range run on the thread pool."""
        self._prepare(kernel, n, inputs)()

    def _prepare(self, kernel, n: int, inputs):
        """``_launch`` split in two: builds the (chunks') inputs now and returns the zero-argument launch
        (benchmarks time the launch alone)."""
        if n <= 0:
            return lambda: None
        if self.threads <= 1 or n < 2 * MIN_CHUNK:
            args = inputs(0, n)
            return lambda: wp.launch(kernel, dim=n, device=self.device, inputs=args)
        n_chunks = min(self.threads * CHUNKS_PER_THREAD, n // MIN_CHUNK)
        edges = [n * c // n_chunks for c in range(n_chunks + 1)]
        chunks = [(lo, hi, inputs(lo, hi)) for lo, hi in zip(edges[:-1], edges[1:])]
        return lambda: self._run_chunks(kernel, chunks)

    def _launch_groups(self, kernel, groups: int, per_group: int, inputs) -> None:
        """CPU only: launch ``kernel`` over ``groups`` blocks of ``per_group`` items, whole groups per thread
        (``inputs(g0, g1)`` gives the inputs for groups ``g0..g1-1``)."""
        k = min(groups, self.threads * CHUNKS_PER_THREAD)
        bounds = [groups * c // k for c in range(k + 1)]
        self._run_chunks(kernel, [(g0 * per_group, g1 * per_group, inputs(g0, g1))
                                  for g0, g1 in zip(bounds[:-1], bounds[1:])])

    def _run_chunks(self, kernel, chunks) -> None:
        # chunks: (first item, end item, inputs); the first launch of a kernel compiles and loads its
        # module, which must not happen on two threads at once, so it runs here before the others
        chunks = list(chunks)
        if kernel not in self._loaded:
            lo, hi, args = chunks.pop(0)
            wp.launch(kernel, dim=hi - lo, device=self.device, inputs=args)
            self._loaded.add(kernel)
        with self._pool_lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="place3d-warp-cpu")
        futures = [self._pool.submit(wp.launch, kernel, dim=hi - lo, device=self.device, inputs=args)
                   for lo, hi, args in chunks]
        for f in futures:
            f.result()

    # ------------------------------------------------------------------ helpers
    def _vec3(self, a) -> "wp.array":
        return wp.array(np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)

    def _vec3d(self, a) -> "wp.array":
        return wp.array(np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3), dtype=wp.vec3d, device=self.device)

    def _f64(self, a, n) -> "wp.array":
        return wp.array(np.ascontiguousarray(np.broadcast_to(np.asarray(a, np.float64), (n,))), dtype=wp.float64,
                        device=self.device)

    def _stop(self, stop):
        if stop is None:
            return self._empty_u8, 0
        if isinstance(stop, wp.array):
            return stop, 1
        return wp.array(np.ascontiguousarray(stop, dtype=np.uint8), dtype=wp.uint8, device=self.device), 1

    def synchronize(self) -> None:
        wp.synchronize_device(self.device)

    # ------------------------------------------------------------------ rays
    def lidar_rays(self, elevations, azimuths, poses):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
        sd = sensor_directions(elevations, azimuths)
        n = len(sd) * len(poses)
        out_o = wp.empty(n, dtype=wp.vec3d, device=self.device)
        out_d = wp.empty(n, dtype=wp.vec3d, device=self.device)
        rot = wp.array(rotation_matrices(poses), dtype=wp.mat33d, device=self.device)
        wp.launch(self.k.lidar_rays_kernel, dim=n, device=self.device,
                  inputs=[self._vec3d(sd), rot, self._vec3d(poses[:, :3]), out_o, out_d])
        return out_o.numpy(), out_d.numpy()

    # ------------------------------------------------------------------ ray-mesh
    # The BVH builder: on CUDA cuBQL (Warp >= 1.19, "experimental" there), whose trees Warp's own query walked
    # clearly faster than its SAH trees on the 1M-triangle city with the same hits, which put this backend's two
    # passes ahead of a plain Warp kernel on a default (SAH) tree; SAH where cuBQL is missing, and on the CPU
    # (bench/README.md, "What the studies found", ray-mesh, Warp (CUDA)). None: that choice; a name forces one
    # (bench/raymesh_bvh.py at tag lab-2026-11-27 timed the others). bvh_leaf_size None is the builder's default.
    bvh_constructor = None
    bvh_leaf_size = None
    #: the builder the last uploaded mesh got, and why when it is not the one asked for
    bvh_built = None

    def upload_mesh(self, vertices, faces, face_ids=None, labels=None):
        # each triangle gets its own three points (face f uses points 3f..3f+2), so the float64 corners of face f
        # are corners64[3f..3f+2]; the tree's boxes are float32 and the walk grows them (kernels.py, closest_hit)
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        ids, lab = mesh_face_tables(len(f), face_ids, labels)
        return self._upload_triangles(v[f], ids, lab)

    def _upload_triangles(self, tri, ids, lab, groups=None, cons=None):
        """``upload_mesh`` of (F, 3, 3) float64 triangles with their face tables (``groups``: (F,) int32
        group of each triangle, for ``upload_mesh_groups``)."""
        corners = tri.reshape(-1, 3)
        pts = self._vec3(corners)
        idx = wp.array(np.arange(len(corners), dtype=np.int32), dtype=wp.int32, device=self.device)
        gr = None if groups is None else wp.array(groups, dtype=wp.int32, device=self.device)
        mesh = self._build_tree(pts, idx, gr, cons)
        reach = float(np.abs(corners).max()) if len(tri) else 0.0
        return _WarpMesh(mesh, pts, idx, self._vec3d(corners), reach, wp.array(ids, dtype=wp.int64, device=self.device),
                         wp.array(lab, dtype=wp.int32, device=self.device))

    # Grouped builds: cuBQL builds no grouped trees (Warp 1.19), so a grouped mesh gets Warp's LBVH on CUDA
    # and SAH on the CPU; a ray confined to its group's subtree is proposed the triangles of that mesh alone,
    # and float64 decides among them as in that mesh's own tree, so the hits are the same bits.
    GROUP_BVH = {"cuda": "lbvh", "cpu": "sah"}

    def upload_mesh_groups(self, parts):
        """One acceleration structure over several meshes, each in a group of its own, for
        ``raycast_groups``.

        Args:
            parts: one (vertices (V, 3) float64 already shifted, faces (F, 3), face_ids (F,) or None, labels
                (F,) or None) per group, as ``upload_mesh`` takes them; every part needs a face.
        """
        tri, ids, lab, grp = [], [], [], []
        for g, (v, f, i, lb) in enumerate(mesh_group_parts(parts)):
            tri.append(v[f])
            ids.append(i)
            lab.append(lb)
            grp.append(np.full(len(f), g, dtype=np.int32))
        return self._upload_triangles(np.concatenate(tri), np.concatenate(ids), np.concatenate(lab),
                                      np.concatenate(grp), self.group_builder())

    def group_builder(self) -> str:
        """The builder of this device's grouped trees (``GROUP_BVH``)."""
        return self.GROUP_BVH["cuda" if self.device.is_cuda else "cpu"]

    def raycast_groups(self, mesh, origins, directions, t_max, shifts, rays_per_group: int, first: int = 0):
        """``raycast_checked`` into meshes uploaded together by ``upload_mesh_groups``: ray block k
        (``rays_per_group`` rays of float64 (N, 3) world origins and directions) into mesh ``first + k``,
        whose shift is ``shifts[first + k]``; one scalar ``t_max``. (t float64, caller's face id int64, label
        int32), or None where a ray fails ops.raycast's checks."""
        r, n = int(rays_per_group), len(origins)
        groups = group_blocks(n, len(directions), r, first, len(shifts))
        o, d = self._rays_in(origins), self._rays_in(directions)
        tm = self._t_in(mesh, t_max, 1)
        sh = self._vec3d(shifts)
        buf, (out_t, out_f, out_l, flags) = self._checked_outputs(n)

        def args(g0, g1):
            a, b = g0 * r, g1 * r
            return [mesh.mesh.id, mesh.corners64, mesh.reach, mesh.face_ids, mesh.face_labels, o[a:b], sh, d[a:b],
                    tm, r, first + g0, out_t[a:b], out_f[a:b], out_l[a:b], flags]

        self._launch_by_group(self.k.raycast_groups_kernel, groups, r, args)
        return self._checked_results(buf, n)

    def _launch_by_group(self, kernel, groups: int, per_group: int, inputs) -> None:
        # whole groups per launch: the kernels find a ray's group from its index and the first group
        if self.device.is_cuda or self.threads <= 1 or groups == 1:
            wp.launch(kernel, dim=groups * per_group, device=self.device, inputs=inputs(0, groups))
        else:
            self._launch_groups(kernel, groups, per_group, inputs)

    def _build_tree(self, pts, idx, groups=None, cons=None):
        cons = cons or self.bvh_constructor or ("cubql" if self.device.is_cuda else "sah")
        leaf = {} if self.bvh_leaf_size is None else {"bvh_leaf_size": self.bvh_leaf_size}
        if groups is not None:
            return wp.Mesh(points=pts, indices=idx, bvh_constructor=cons, groups=groups, **leaf)
        try:
            mesh = wp.Mesh(points=pts, indices=idx, bvh_constructor=cons, **leaf)
            self.bvh_built = cons
        except (ValueError, RuntimeError, TypeError, KeyError) as e:
            if cons != "cubql" or self.bvh_constructor is not None:
                raise
            mesh = wp.Mesh(points=pts, indices=idx, bvh_constructor="sah", **leaf)   # a Warp without cuBQL
            self.bvh_built = f"sah (cubql: {type(e).__name__}: {e})"
        return mesh

    raycast_takes_shift = True

    def raycast(self, mesh, origins, directions, t_max, shift=None):
        n = len(origins)
        out_t = wp.empty(n, dtype=wp.float64, device=self.device)
        out_f = wp.empty(n, dtype=wp.int32, device=self.device)
        o, d, tm = self._rays_in(origins), self._rays_in(directions), self._t_in(mesh, t_max, n)
        s = wp.vec3d(*(np.zeros(3) if shift is None else np.asarray(shift, dtype=np.float64).reshape(3)).tolist())
        self._raycast_query(mesh, o, s, d, tm, out_t, out_f)()
        return out_t.numpy(), out_f.numpy()

    def _raycast_query(self, mesh, o, s, d, tm, out_t, out_f):
        """The ray-mesh query (kernels.py, raycast_query_kernel) on device arrays, as one zero-argument
        launch."""
        return self._prepare(self.k.raycast_query_kernel, len(out_t), lambda a, b: [
            mesh.mesh.id, mesh.corners64, mesh.reach, o[a:b], s, d[a:b], tm[a:b], out_t[a:b],
            out_f[a:b]])

    raycast_checks_rays = True

    def raycast_checked(self, mesh, origins, directions, t_max, shift):
        n = len(directions)
        f32 = origins.dtype == np.float32
        vec = wp.vec3f if f32 else wp.vec3d
        o, d = self._rays_as_given(origins, vec), self._rays_as_given(directions, vec)
        o_step = 1 if len(origins) == n else 0
        t_step = 1 if np.ndim(t_max) else 0
        tm = self._f64(t_max, n) if t_step else self._t_in(mesh, t_max, 1)
        buf, (out_t, out_f, out_l, flags) = self._checked_outputs(n)
        s = wp.vec3d(*np.asarray(shift, dtype=np.float64).reshape(3).tolist())
        kernel = self.k.RAYCAST_CHECKED[vec]
        self._launch(kernel, n, lambda a, b: [
            mesh.mesh.id, mesh.corners64, mesh.reach, mesh.face_ids, mesh.face_labels,
            o[a:b] if o_step else o, o_step, s, d[a:b], tm[a:b] if t_step else tm, t_step,
            out_t[a:b], out_f[a:b], out_l[a:b], flags])
        return self._checked_results(buf, n)

    def sweep_returns(self, static, static_shift, groups, group_shifts, elevations, azimuths, sensor_poses, t_max,
                      first: int = 0):
        """``simulate``'s returns (no intensities) of one sweep from each of ``sensor_poses`` ((F, 6) world poses),
        computed on the device: the rays made there, cast into ``static`` (an ``upload_mesh`` handle, the mesh's
        shift ``static_shift``) and, with ``groups`` (an ``upload_mesh_groups`` handle, its meshes' (G, 3) shifts),
        sweep k's rays into mesh ``first + k``; only the returns come back (returns_kernels.py says why they are
        the host's bits). Returns one (points (H, 3) float64, labels (H,) int32, origin (3,)) per sweep, or None
        where a ray fails ``ops.raycast``'s checks (the caller then casts the usual way, which reports it)."""
        from place3d_kernels.backends.warp import returns_kernels as rk

        poses = np.ascontiguousarray(sensor_poses, dtype=np.float64).reshape(-1, 6)
        F = len(poses)
        sd, sd_a = self._directions.get(elevations, azimuths)
        R = len(sd)
        n = F * R
        if n == 0:
            return [(np.zeros((0, 3)), np.zeros(0, np.int32), p[:3].copy()) for p in poses]
        dev = self.device
        o = wp.empty(n, dtype=wp.vec3d, device=dev)
        d = wp.empty(n, dtype=wp.vec3d, device=dev)
        rot = wp.array(rotation_matrices(poses), dtype=wp.mat33d, device=dev)
        wp.launch(self.k.lidar_rays_kernel, dim=n, device=dev, inputs=[sd_a, rot, self._vec3d(poses[:, :3]), o, d])
        # the outputs are views of one buffer each, which must live as long as they are read
        buf_s, (ts, fs, ls, flags) = self._checked_outputs(n)
        s = wp.vec3d(*np.asarray(static_shift, dtype=np.float64).reshape(3).tolist())
        tm = self._t_in(static, t_max, 1)
        self._launch(self.k.RAYCAST_CHECKED[wp.vec3d], n, lambda a, b: [
            static.mesh.id, static.corners64, static.reach, static.face_ids, static.face_labels, o[a:b], 1, s,
            d[a:b], tm, 0, ts[a:b], fs[a:b], ls[a:b], flags])
        ta, la, has, buf_g = ts, ls, 0, None
        if groups is not None:
            buf_g, (ta, fa, la, flags_g) = self._checked_outputs(n)
            sh = self._vec3d(group_shifts)
            tg = self._t_in(groups, t_max, 1)
            self._launch_by_group(self.k.raycast_groups_kernel, F, R, lambda g0, g1: [
                groups.mesh.id, groups.corners64, groups.reach, groups.face_ids, groups.face_labels,
                o[g0 * R:g1 * R], sh, d[g0 * R:g1 * R], tg, R, first + g0, ta[g0 * R:g1 * R], fa[g0 * R:g1 * R],
                la[g0 * R:g1 * R], flags_g])
            has = 1
        hit = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(rk.returns_hit_kernel, dim=n, device=dev, inputs=[ts, ta, has, hit])
        at = wp.empty(n, dtype=wp.int32, device=dev)
        wp.utils.array_scan(hit, at, inclusive=False)
        starts = wp.empty(F + 1, dtype=wp.int32, device=dev)
        wp.launch(rk.sweep_starts_kernel, dim=F + 1, device=dev, inputs=[hit, at, R, F, starts])
        st = starts.numpy().astype(np.int64)
        if flags.numpy().any() or (groups is not None and flags_g.numpy().any()):
            return None
        H = int(st[-1])
        pts = wp.empty(max(H, 1), dtype=wp.vec3d, device=dev)
        lab = wp.empty(max(H, 1), dtype=wp.int32, device=dev)
        wp.launch(rk.returns_write_kernel, dim=n, device=dev, inputs=[o, d, ts, ls, ta, la, has, hit, at, pts, lab])
        P = pts.numpy().reshape(-1, 3)[:H]
        L = lab.numpy()[:H]
        del buf_s, buf_g
        return [(P[st[k]:st[k + 1]], L[st[k]:st[k + 1]], poses[k, :3].copy()) for k in range(F)]

    def _checked_outputs(self, n: int):
        """The outputs of a checked cast of n rays in one allocation (t float64 | face int64 | label int32 |
        flags int32, the flags zeroed), so that they come back in one copy: one allocation and one
        synchronising copy instead of four. Returns (buffer, (t, face, label, flags))."""
        buf = wp.empty(20 * n + 4 * self.k.N_FLAGS, dtype=wp.uint8, device=self.device)
        views = tuple(wp.array(ptr=buf.ptr + at, dtype=dt, shape=(m,), device=self.device)
                      for at, dt, m in ((0, wp.float64, n), (8 * n, wp.int64, n), (16 * n, wp.int32, n),
                                        (20 * n, wp.int32, self.k.N_FLAGS)))
        views[3].zero_()
        return buf, views

    def _checked_results(self, buf, n: int):
        """(t, face, label) on the host from ``_checked_outputs``' buffer, or None where a flag is set."""
        host = self._to_host(buf, 20 * n + 4 * self.k.N_FLAGS)
        if host[20 * n:].view(np.int32).any():
            return None
        return host[:8 * n].view(np.float64), host[8 * n:16 * n].view(np.int64), host[16 * n:20 * n].view(np.int32)

    def _to_host(self, buf, nbytes: int) -> np.ndarray:
        """(nbytes,) uint8 host copy of a uint8 device array: on the CPU device a view of ``buf`` (which it
        keeps alive); on a GPU one DMA into a pooled pinned block that the returned view owns."""
        if not self.device.is_cuda:
            return buf.numpy()
        if self._pinned is None:
            from place3d_kernels.backends.pinned import HostBlockPool, warp_pinned_alloc

            self._pinned = HostBlockPool(warp_pinned_alloc(wp))
        block, host = self._pinned.take(nbytes)
        wp.copy(block, buf, count=nbytes)
        wp.synchronize_device(self.device)
        return host

    def _rays_as_given(self, a, vec) -> "wp.array":
        """(N, 3) contiguous float32 or float64 rays as a vec3f/vec3d array: on the CPU the NumPy memory
        itself (no copy; the caller's array outlives the launch), on a GPU one upload, no conversion."""
        return wp.array(a, dtype=vec, device=self.device, copy=self.device.is_cuda)

    def _rays_in(self, a) -> "wp.array":
        """(N, 3) float64 rays as a vec3d array: on the CPU the NumPy memory itself when it is already
        contiguous float64 (no copy; the caller's array outlives the launch), else a copy."""
        if not self.device.is_cuda:
            a = np.asarray(a)
            if a.dtype == np.float64 and a.ndim == 2 and a.flags.c_contiguous:
                return wp.array(a, dtype=wp.vec3d, device=self.device, copy=False)
        return self._vec3d(a)

    def _t_in(self, mesh, t, n) -> "wp.array":
        # a scalar bound becomes an (n,) array once per (n, value) and stays on the mesh handle (read-only);
        # per-ray bounds are copied as before
        if np.ndim(t) != 0:
            return self._f64(t, n)
        key = (int(n), float(t))
        cached = getattr(mesh, "t_const", None)
        if cached is None or cached[0] != key:
            cached = mesh.t_const = (key, self._f64(key[1], n))
        return cached[1]

    def resident_raycast(self, mesh, origins, directions, t_max):
        """For benchmarks: a zero-argument callable that launches the ray-mesh kernel on rays already on
        the device (no host transfers), so kernel throughput can be timed apart from data movement."""
        n = len(origins)
        o, d, tm = self._vec3d(origins), self._vec3d(directions), self._f64(t_max, n)
        out_t = wp.empty(n, dtype=wp.float64, device=self.device)
        out_f = wp.empty(n, dtype=wp.int32, device=self.device)
        return self._raycast_query(mesh, o, wp.vec3d(0.0, 0.0, 0.0), d, tm, out_t, out_f)

    def resident_traverse(self, grid, origins, directions, t_end, stop=None):
        """For benchmarks: launch the traversal count kernel on resident rays (see ``resident_raycast``)."""
        n, args = self._walk_args(grid, origins, directions, t_end)
        stop_a, use = self._stop(stop)
        counts = wp.zeros(n, dtype=wp.int64, device=self.device)
        return self._prepare(self.k.traverse_count_kernel, n,
                             lambda a, b: self._ray_range(args, a, b) + [stop_a, use, counts[a:b]])

    # ------------------------------------------------------------------ traversal
    def _walk_args(self, grid, origins, directions, t_end):
        n = len(origins)
        nx, ny, nz = grid.shape
        return n, [self._vec3d(origins), self._vec3d(directions), self._f64(t_end, n),
                   float(grid.voxel_size), int(nx), int(ny), int(nz)]

    @staticmethod
    def _ray_range(args, a, b):
        # _walk_args for rays a..b-1: views of the three per-ray arrays, the grid arguments as they are
        return [x[a:b] for x in args[:3]] + args[3:]

    def traverse(self, grid, origins, directions, t_end, stop=None):
        n, args = self._walk_args(grid, origins, directions, t_end)
        stop_a, use = self._stop(stop)
        counts = wp.zeros(n, dtype=wp.int64, device=self.device)
        self._launch(self.k.traverse_count_kernel, n,
                     lambda a, b: self._ray_range(args, a, b) + [stop_a, use, counts[a:b]])
        offsets = np.zeros(n + 1, dtype=np.int64)
        offsets[1:] = np.cumsum(counts.numpy())
        total = int(offsets[-1])
        voxels = wp.empty(max(total, 1), dtype=wp.int64, device=self.device)
        if total:
            off = wp.array(offsets, dtype=wp.int64, device=self.device)
            # each ray writes only its own range voxels[offsets[i]:offsets[i + 1]]
            self._launch(self.k.traverse_fill_kernel, n,
                         lambda a, b: self._ray_range(args, a, b) + [stop_a, use, off[a:b + 1], voxels])
        return offsets, voxels.numpy()[:total]

    def coverage(self, grid, origins, directions, t_end, stop=None):
        n, args = self._walk_args(grid, origins, directions, t_end)
        stop_a, use = self._stop(stop)
        mask = wp.zeros(grid.n_voxels, dtype=wp.uint8, device=self.device)
        # chunks may share voxels: every write stores the same byte 1, so the order does not matter
        self._launch(self.k.coverage_kernel, n, lambda a, b: self._ray_range(args, a, b) + [stop_a, use, mask])
        return mask.numpy().view(bool)

    # ------------------------------------------------------------------ occupancy
    def voxel_keys(self, grid, points):
        n = len(points)
        out = wp.empty(max(n, 1), dtype=wp.int64, device=self.device)
        nx, ny, nz = grid.shape
        if n:
            wp.launch(self.k.voxel_keys_kernel, dim=n, device=self.device,
                      inputs=[wp.array(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), dtype=wp.vec3d,
                                       device=self.device), float(grid.voxel_size), int(nx), int(ny), int(nz), out])
        return out.numpy()[:n]

    def vote(self, keys, labels, n_classes):
        k = np.asarray(keys, dtype=np.int64)
        lab = np.asarray(labels, dtype=np.int64)
        ok = (k >= 0) & (lab > 0)
        combo = k[ok] * n_classes + lab[ok]
        n = len(combo)
        if n == 0:
            return np.empty(0, np.int64), np.empty(0, np.int32)
        buf = np.zeros(2 * n, dtype=np.int64)
        buf[:n] = combo
        keys_d = wp.array(buf, dtype=wp.int64, device=self.device)
        vals_d = wp.zeros(2 * n, dtype=wp.int32, device=self.device)
        wp.utils.radix_sort_pairs(keys_d, vals_d, n)
        out = wp.empty(n, dtype=wp.int32, device=self.device)
        wp.launch(self.k.vote_kernel, dim=n, device=self.device, inputs=[keys_d, int(n), int(n_classes), out])
        lead = out.numpy()
        sel = np.flatnonzero(lead >= 0)
        return keys_d.numpy()[sel] // n_classes, lead[sel].astype(np.int32)


class WarpBackend(WarpCore, WarpConditions):
    """Warp backend on one device (``"cpu"``, ``"cuda:0"``, ...)."""


__all__ = ["WarpBackend", "WarpCore", "warp_devices", "cpu_threads", "startup_note"]
