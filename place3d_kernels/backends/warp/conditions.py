"""Warp kernels of the adverse-condition models (float32, one thread per point).

Same contract as ``place3d_kernels/backends/conditions_base.py``; random numbers come from the host, so a Warp result
equals the reference one up to float32 rounding (a decision taken within rounding of its threshold may
differ). Mixed into ``WarpBackend``, which provides ``self.device``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from place3d_kernels.backends.conditions_base import THETA_MIN, ConditionKernels

# no fused multiply-add, as in kernels.py: the reference rounds each product and sum separately
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["WarpConditions"]

_THETA_MIN = wp.constant(THETA_MIN)   # the shared floor of conditions_base.py
_PI = wp.constant(3.14159265358979323846)


# --------------------------------------------------------------------------------------- fog
@wp.kernel
def _fog_kernel(ranges: wp.array(dtype=wp.float32), intensity: wp.array(dtype=wp.float32),
                i_table: wp.array(dtype=wp.float32), d_table: wp.array(dtype=wp.float32),
                table_step: float, alpha: float, beta_ratio: float, uniform: wp.array(dtype=wp.float32),
                noise: float, intensity_max: float,
                out_r: wp.array(dtype=wp.float32), out_i: wp.array(dtype=wp.float32),
                out_fog: wp.array(dtype=wp.uint8)):
    tid = wp.tid()
    r0 = ranges[tid]
    inten = intensity[tid]
    k = int(wp.floor(r0 / table_step + 0.5))
    k = wp.clamp(k, 0, i_table.shape[0] - 1)
    i_hard = inten * wp.exp(-2.0 * alpha * r0)
    i_soft = i_table[k] * inten * r0 * r0 * beta_ratio
    if i_soft > i_hard:
        u = wp.max(r0 + noise * (2.0 * uniform[tid] - 1.0), 0.5 * r0)
        out_r[tid] = d_table[k] * r0 / u
        out_i[tid] = wp.min(i_soft, intensity_max)
        out_fog[tid] = wp.uint8(1)
    else:
        out_r[tid] = r0
        out_i[tid] = i_hard
        out_fog[tid] = wp.uint8(0)


# --------------------------------------------------------------------------------------- wet ground
@wp.func
def _fresnel_t(cos_i: float, n1: float, n2: float, pol: int):
    """Power transmittance (pol 0: s, 1: p) of an n1 -> n2 interface."""
    sin_i = wp.sqrt(wp.clamp(1.0 - cos_i * cos_i, 0.0, 1.0))
    sin_t = wp.clamp(sin_i * n1 / n2, -1.0, 1.0)
    cos_t = wp.sqrt(1.0 - sin_t * sin_t)
    k = (n2 * cos_t) / (n1 * cos_i)
    t = float(0.0)
    if pol == 0:
        t = 2.0 * n1 * cos_i / (n1 * cos_i + n2 * cos_t)
    else:
        t = 2.0 * n1 * cos_i / (n2 * cos_i + n1 * cos_t)
    return t * t * k


@wp.func
def _fresnel_r(cos_i: float, n1: float, n2: float, pol: int):
    """Power reflectance (pol 0: s, 1: p) of an n1 -> n2 interface."""
    sin_i = wp.sqrt(wp.clamp(1.0 - cos_i * cos_i, 0.0, 1.0))
    sin_t = wp.clamp(sin_i * n1 / n2, -1.0, 1.0)
    cos_t = wp.sqrt(1.0 - sin_t * sin_t)
    r = float(0.0)
    if pol == 0:
        r = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    else:
        r = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return r * r


@wp.kernel
def _wet_kernel(intensity: wp.array(dtype=wp.float32), cos_theta: wp.array(dtype=wp.float32),
                p_out: wp.array(dtype=wp.float32), noise_level: wp.array(dtype=wp.float32),
                f: float, n_air: float, n_water: float, rho_min: float, rho_max: float,
                out_i: wp.array(dtype=wp.float32), out_keep: wp.array(dtype=wp.uint8)):
    tid = wp.tid()
    inten = intensity[tid]
    ct = wp.clamp(cos_theta[tid], 0.0, 1.0)
    po = p_out[tid]
    rho = rho_min
    den = ct * po
    if den != 0.0:
        rho = wp.clamp(inten / den, rho_min, rho_max)
    theta = wp.max(wp.acos(ct), _THETA_MIN)
    # use cos theta as given: cos(acos(x)) in float32 loses digits at grazing incidence
    cos_i = ct
    sin_w = wp.sqrt(wp.clamp(1.0 - ct * ct, 0.0, 1.0)) * n_air / n_water
    cos_w = wp.sqrt(1.0 - sin_w * sin_w)
    t_best = float(0.0)
    for pol in range(2):
        t_aw = _fresnel_t(cos_i, n_air, n_water, pol)
        t_wa = _fresnel_t(cos_w, n_water, n_air, pol)
        r_wa = _fresnel_r(cos_w, n_water, n_air, pol)
        t_best = wp.max(t_best, t_aw * rho * t_wa / (1.0 - rho * r_wa))
    tw = (1.0 - f) * rho + f * t_best / theta
    new = wp.clamp(po * ct * tw, 0.0, inten)
    out_i[tid] = new
    if new >= noise_level[tid] * ct:
        out_keep[tid] = wp.uint8(1)
    else:
        out_keep[tid] = wp.uint8(0)


# --------------------------------------------------------------------------------------- snow
@wp.func
def _bump(d: float, r: float, half: float, pulse_length: float):
    x = d - r
    v = float(0.0)
    if wp.abs(x) <= half:
        c = wp.cos(_PI * x / pulse_length)
        v = c * c
    return v


@wp.kernel
def _snow_kernel(ranges: wp.array(dtype=wp.float32), intensity: wp.array(dtype=wp.float32),
                 offsets: wp.array(dtype=wp.int32), fr: wp.array(dtype=wp.float32),
                 fa: wp.array(dtype=wp.float32), fy: wp.array(dtype=wp.float32),
                 threshold: wp.array(dtype=wp.float32), beam_divergence: float, pulse_length: float,
                 step: float, flake_intensity: float, r1: float, r2: float, intensity_max: float,
                 power: wp.array(dtype=wp.float32),
                 out_r: wp.array(dtype=wp.float32), out_i: wp.array(dtype=wp.float32),
                 out_scat: wp.array(dtype=wp.uint8), out_keep: wp.array(dtype=wp.uint8)):
    tid = wp.tid()
    r0 = ranges[tid]
    inten = intensity[tid]
    s = offsets[tid]
    e = offsets[tid + 1]
    out_r[tid] = r0
    out_i[tid] = inten
    out_scat[tid] = wp.uint8(0)
    out_keep[tid] = wp.uint8(1)
    if e == s:
        return
    # flake powers, nearer flakes occluding first
    clear = float(1.0)
    for j in range(s, e):
        r = fr[j]
        a = fa[j]
        y = fy[j]
        w = beam_divergence * r
        q0 = float(0.0)
        if w > 1.0e-12:
            lo = wp.max(y - a, -0.5 * w)
            hi = wp.min(y + a, 0.5 * w)
            q0 = wp.min(wp.max(hi - lo, 0.0) / w, 1.0)
        elif wp.abs(y) < a:
            q0 = 1.0
        xi = wp.clamp((r - r1) / (r2 - r1), 0.0, 1.0)
        p = float(0.0)
        if r > 0.0:
            p = flake_intensity * q0 * clear * xi / (r * r)
        power[j] = p
        clear = clear * (1.0 - q0)
    p_t = inten * clear
    half = 0.5 * pulse_length
    # w0: the waveform at the target's own peak (k = 0); the maximum is at least this
    w0 = p_t
    for jj in range(s, e):
        w0 = w0 + power[jj] * _bump(r0, fr[jj], half, pulse_length)
    n_samples = int(wp.floor(pulse_length / step)) + 2
    best = float(-1.0)
    best_k = int(0)
    found = int(0)
    # candidate samples d = r0 + k step inside each scatterer's pulse (index e stands for the target)
    for j in range(s, e + 1):
        rj = r0
        if j < e:
            rj = fr[j]
            # exact pruning: pulses within one pulse length of r_j bound every sample of this window
            bound = float(0.0)
            if r0 - rj <= pulse_length:
                bound = p_t
            for jj in range(s, e):
                if wp.abs(fr[jj] - rj) <= pulse_length:
                    bound = bound + power[jj]
            if bound < w0:
                continue
        k_lo = int(wp.ceil((rj - half - r0) / step))
        for m in range(n_samples):
            k = k_lo + m
            d = r0 + float(k) * step
            if wp.abs(d - rj) <= half:
                v = p_t * _bump(d, r0, half, pulse_length)
                for jj in range(s, e):
                    v = v + power[jj] * _bump(d, fr[jj], half, pulse_length)
                if found == 0 or v > best or (v == best and k < best_k):
                    best = v
                    best_k = k
                    found = 1
    peak = wp.clamp(best, 0.0, intensity_max)
    out_i[tid] = peak
    if best <= 0.0:
        # beam blocked before the overlap range R1: no return at all
        out_keep[tid] = wp.uint8(0)
    elif wp.abs(best_k) <= 1:
        if peak < threshold[tid]:
            out_keep[tid] = wp.uint8(0)
    else:
        out_r[tid] = wp.max(r0 + float(best_k) * step, 0.0)
        out_scat[tid] = wp.uint8(1)


# --------------------------------------------------------------------------------------- Robo3D
@wp.kernel
def _motion_blur_kernel(normals: wp.array(dtype=wp.vec3), offset: wp.vec3, sigma: float,
                        out: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    z = normals[tid]
    lim = 3.0 * sigma
    out[tid] = offset + wp.vec3(wp.clamp(0.1 * sigma * z[0], -lim, lim),
                                wp.clamp(0.1 * sigma * z[1], -lim, lim),
                                wp.clamp(0.05 * sigma * z[2], -lim, lim))


@wp.kernel
def _crosstalk_kernel(index: wp.array(dtype=wp.int32), noise: wp.array(dtype=wp.vec3),
                      out: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    out[index[tid]] = noise[tid]


@wp.kernel
def _echo_kernel(instance: wp.array(dtype=wp.int32), rank: wp.array(dtype=wp.int32),
                 n_drop: wp.array(dtype=wp.int32), out_keep: wp.array(dtype=wp.uint8)):
    tid = wp.tid()
    g = instance[tid]
    out_keep[tid] = wp.uint8(1)
    if g >= 0:
        if rank[tid] < n_drop[g]:
            out_keep[tid] = wp.uint8(0)


class WarpConditions(ConditionKernels):
    """Mixin of condition kernels for the Warp backend (needs ``self.device``)."""

    def _wf32(self, a, n=None):
        a = np.asarray(a, dtype=np.float32)
        if n is not None:
            a = np.broadcast_to(a, (n,))
        return wp.array(np.ascontiguousarray(a), dtype=wp.float32, device=self.device)

    def _wi32(self, a):
        return wp.array(np.ascontiguousarray(np.asarray(a, dtype=np.int32)), dtype=wp.int32, device=self.device)

    def _wv3(self, a):
        return wp.array(np.ascontiguousarray(np.asarray(a, dtype=np.float32).reshape(-1, 3)), dtype=wp.vec3,
                        device=self.device)

    def fog_points(self, ranges, intensity, i_table, d_table, table_step, alpha, beta_ratio, uniform, noise,
                   intensity_max):
        n = len(ranges)
        out_r = wp.empty(n, dtype=wp.float32, device=self.device)
        out_i = wp.empty(n, dtype=wp.float32, device=self.device)
        out_f = wp.empty(n, dtype=wp.uint8, device=self.device)
        if n:
            wp.launch(_fog_kernel, dim=n, device=self.device,
                      inputs=[self._wf32(ranges), self._wf32(intensity), self._wf32(i_table), self._wf32(d_table),
                              float(table_step), float(alpha), float(beta_ratio), self._wf32(uniform),
                              float(noise), float(intensity_max)],
                      outputs=[out_r, out_i, out_f])
        return (out_r.numpy().astype(np.float64), out_i.numpy().astype(np.float64),
                out_f.numpy().astype(bool))

    def wet_ground_points(self, intensity, cos_theta, p_out, noise_level, film_fraction, n_air, n_water,
                          rho_min, rho_max):
        n = len(intensity)
        out_i = wp.empty(n, dtype=wp.float32, device=self.device)
        out_k = wp.empty(n, dtype=wp.uint8, device=self.device)
        if n:
            wp.launch(_wet_kernel, dim=n, device=self.device,
                      inputs=[self._wf32(intensity), self._wf32(cos_theta), self._wf32(p_out, n),
                              self._wf32(noise_level, n), float(film_fraction), float(n_air), float(n_water),
                              float(rho_min), float(rho_max)],
                      outputs=[out_i, out_k])
        return out_i.numpy().astype(np.float64), out_k.numpy().astype(bool)

    def snow_points(self, ranges, intensity, offsets, flake_range, flake_radius, flake_offset, threshold,
                    beam_divergence, pulse_length, range_step, flake_intensity, r1, r2, intensity_max):
        n = len(ranges)
        nf = len(flake_range)
        out_r = wp.empty(n, dtype=wp.float32, device=self.device)
        out_i = wp.empty(n, dtype=wp.float32, device=self.device)
        out_s = wp.empty(n, dtype=wp.uint8, device=self.device)
        out_k = wp.empty(n, dtype=wp.uint8, device=self.device)
        if n:
            power = wp.empty(max(nf, 1), dtype=wp.float32, device=self.device)
            wp.launch(_snow_kernel, dim=n, device=self.device,
                      inputs=[self._wf32(ranges), self._wf32(intensity), self._wi32(offsets),
                              self._wf32(flake_range), self._wf32(flake_radius), self._wf32(flake_offset),
                              self._wf32(threshold, n), float(beam_divergence), float(pulse_length),
                              float(range_step), float(flake_intensity), float(r1), float(r2),
                              float(intensity_max), power],
                      outputs=[out_r, out_i, out_s, out_k])
        return (out_r.numpy().astype(np.float64), out_i.numpy().astype(np.float64),
                out_s.numpy().astype(bool), out_k.numpy().astype(bool))

    def motion_blur_points(self, normals, offset, sigma):
        n = len(normals)
        out = wp.empty(n, dtype=wp.vec3, device=self.device)
        if n:
            off = wp.vec3(*[float(x) for x in np.asarray(offset, dtype=np.float64)])
            wp.launch(_motion_blur_kernel, dim=n, device=self.device,
                      inputs=[self._wv3(normals), off, float(sigma)], outputs=[out])
        return out.numpy().astype(np.float64).reshape(-1, 3)

    def crosstalk_points(self, n_points, index, noise):
        out = wp.zeros(int(n_points), dtype=wp.vec3, device=self.device)
        k = len(index)
        if k:
            wp.launch(_crosstalk_kernel, dim=k, device=self.device,
                      inputs=[self._wi32(index), self._wv3(noise)], outputs=[out])
        return out.numpy().astype(np.float64).reshape(-1, 3)

    def incomplete_echo_points(self, instance, rank, n_drop):
        n = len(instance)
        out = wp.empty(n, dtype=wp.uint8, device=self.device)
        if n:
            nd = np.asarray(n_drop, dtype=np.int32)
            wp.launch(_echo_kernel, dim=n, device=self.device,
                      inputs=[self._wi32(instance), self._wi32(rank), self._wi32(nd if len(nd) else [0])],
                      outputs=[out])
        return out.numpy().astype(bool)
