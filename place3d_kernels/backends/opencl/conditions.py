"""OpenCL kernels of the adverse-condition models (``conditions.cl``; one work-item per point).

Same contract as ``place3d_kernels/backends/conditions_base.py``: random numbers come from the host, so an OpenCL result
equals the reference one up to rounding. The kernels compute in the backend's ``real`` type: double where
the device has ``cl_khr_fp64`` (PoCL, NVIDIA; then results agree with the reference to ~1e-15 and every
threshold decision is the reference's except exact ties), float32 with ``fp64=False`` or on devices without
doubles (then, as for Warp, a decision taken within float32 rounding of its threshold may differ).

Mixed into ``OpenCLBackend``, which provides ``ctx``, ``queue``, ``real``, ``is_cpu``, ``_options()``,
``_in``, ``_host_out`` and ``_fetch``. The program is built through ``_runtime.build_program`` (cached per
context, sources and options) on the first condition call.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl

from place3d_kernels.backends.conditions_base import ConditionKernels
from place3d_kernels.backends.opencl import _runtime as rt

__all__ = ["OpenCLConditions"]

_FILES = ("common.cl", "conditions.cl")
#: work-group size on CPU devices (the kernels are cheap per point except snow's)
_CPU_GROUP = 64


class OpenCLConditions(ConditionKernels):
    """Mixin of condition kernels for the OpenCL backend."""

    # ----------------------------------------------------------------- plumbing
    def _cond_kernel(self, name: str) -> "cl.Kernel":
        cache = self.__dict__.setdefault("_cond_kernels", {})
        k = cache.get(name)
        if k is None:
            prg = rt.build_program(self.ctx, _FILES, self._options())
            for kk in prg.all_kernels():
                cache[kk.function_name] = kk
            k = cache[name]
        return k

    def _cond_launch(self, name: str, n: int, *args) -> None:
        if n <= 0:
            return
        g = int(n)
        lsize = None
        if self.is_cpu:
            lsize = (_CPU_GROUP,)
            g = -(-g // _CPU_GROUP) * _CPU_GROUP
        k = self._cond_kernel(name)
        with self._lock:       # a Kernel's arguments are set and enqueued in two steps
            k(self.queue, (g,), lsize, *args)
        # On CPU devices inputs are USE_HOST_PTR views of NumPy arrays that are often temporaries (a
        # float32 conversion): ``args`` keeps them alive until the kernel is done.
        self.queue.finish()

    def _r(self, a, n: int | None = None) -> np.ndarray:
        a = np.asarray(a, dtype=self.real)
        if n is not None:
            a = np.broadcast_to(a, (n,))
        return np.ascontiguousarray(a)

    def _i64(self, a) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(a, dtype=np.int64))

    def _outs(self, *specs):
        """(array, buffer) pairs of kernel outputs; on CPU devices the kernel writes the arrays in place."""
        return [self._host_out(dtype, n) for dtype, n in specs]

    def _get(self, *pairs):
        return [self._fetch(a, b) for a, b in pairs]

    # ----------------------------------------------------------------- fog
    def fog_points(self, ranges, intensity, i_table, d_table, table_step, alpha, beta_ratio, uniform, noise,
                   intensity_max):
        n = len(ranges)
        r = self.real
        o_r, o_i, o_f = self._outs((r, n), (r, n), (np.uint8, n))
        if n:
            self._cond_launch("cond_fog", n, self._in(self._r(ranges)), self._in(self._r(intensity)),
                              self._in(self._r(i_table)), self._in(self._r(d_table)), np.int32(len(i_table)),
                              r(table_step), r(alpha), r(beta_ratio), self._in(self._r(uniform, n)), r(noise),
                              r(intensity_max), o_r[1], o_i[1], o_f[1], np.int32(n))
        out_r, out_i, out_f = self._get(o_r, o_i, o_f)
        return out_r.astype(np.float64), out_i.astype(np.float64), out_f.astype(bool)

    # ----------------------------------------------------------------- wet ground
    def wet_ground_points(self, intensity, cos_theta, p_out, noise_level, film_fraction, n_air, n_water,
                          rho_min, rho_max):
        n = len(intensity)
        r = self.real
        o_i, o_k = self._outs((r, n), (np.uint8, n))
        if n:
            self._cond_launch("cond_wet", n, self._in(self._r(intensity)), self._in(self._r(cos_theta, n)),
                              self._in(self._r(p_out, n)), self._in(self._r(noise_level, n)), r(film_fraction),
                              r(n_air), r(n_water), r(rho_min), r(rho_max), o_i[1], o_k[1], np.int32(n))
        out_i, out_k = self._get(o_i, o_k)
        return out_i.astype(np.float64), out_k.astype(bool)

    # ----------------------------------------------------------------- snow
    def snow_points(self, ranges, intensity, offsets, flake_range, flake_radius, flake_offset, threshold,
                    beam_divergence, pulse_length, range_step, flake_intensity, r1, r2, intensity_max):
        n = len(ranges)
        nf = len(flake_range)
        r = self.real
        o_r, o_i, o_s, o_k = self._outs((r, n), (r, n), (np.uint8, n), (np.uint8, n))
        if n:
            power = self._out(max(nf, 1) * np.dtype(r).itemsize)
            self._cond_launch("cond_snow", n, self._in(self._r(ranges)), self._in(self._r(intensity)),
                              self._in(self._i64(offsets)), self._in(self._r(flake_range)),
                              self._in(self._r(flake_radius)), self._in(self._r(flake_offset)),
                              self._in(self._r(threshold, n)), r(beam_divergence), r(pulse_length),
                              r(range_step), r(flake_intensity), r(r1), r(r2), r(intensity_max), power,
                              o_r[1], o_i[1], o_s[1], o_k[1], np.int32(n))
        out_r, out_i, out_s, out_k = self._get(o_r, o_i, o_s, o_k)
        return out_r.astype(np.float64), out_i.astype(np.float64), out_s.astype(bool), out_k.astype(bool)

    # ----------------------------------------------------------------- Robo3D
    def motion_blur_points(self, normals, offset, sigma):
        z = self._r(np.asarray(normals).reshape(-1, 3))
        n = len(z)
        r = self.real
        (o,) = self._outs((r, 3 * n))
        if n:
            ox, oy, oz = (r(v) for v in np.asarray(offset, dtype=np.float64).reshape(3))
            self._cond_launch("cond_motion_blur", n, self._in(z), ox, oy, oz, r(sigma), o[1], np.int32(n))
        (out,) = self._get(o)
        return out.astype(np.float64).reshape(-1, 3)

    def crosstalk_points(self, n_points, index, noise):
        n = int(n_points)
        k = len(index)
        if k == 0 or n == 0:
            return np.zeros((n, 3), dtype=np.float64)
        out = np.zeros(3 * n, dtype=self.real)
        flag = cl.mem_flags.USE_HOST_PTR if self.is_cpu else cl.mem_flags.COPY_HOST_PTR
        buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE | flag, hostbuf=out)
        self._cond_launch("cond_crosstalk", k, self._in(self._i64(index)),
                          self._in(self._r(np.asarray(noise).reshape(-1, 3))), buf, np.int32(k))
        out = self._fetch(out, buf)
        return out.astype(np.float64).reshape(-1, 3)

    def incomplete_echo_points(self, instance, rank, n_drop):
        n = len(instance)
        (o,) = self._outs((np.uint8, n))
        if n:
            nd = self._i64(n_drop)
            self._cond_launch("cond_echo", n, self._in(self._i64(instance)), self._in(self._i64(rank)),
                              self._in(nd if len(nd) else np.zeros(1, np.int64)), o[1], np.int32(n))
        (out,) = self._get(o)
        return out.astype(bool)
