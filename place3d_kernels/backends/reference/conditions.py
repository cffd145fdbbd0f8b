"""Reference (NumPy float64) kernels of the adverse-condition models: the executable specification.

The contract, formulas and the host/kernel split are documented in ``place3d_kernels/backends/conditions_base.py``.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.conditions_base import ConditionKernels, fresnel_film

__all__ = ["ReferenceConditions"]


def _overlap_fraction(y, a, w):
    """Fraction of a beam of width w (centred on 0) covered by the interval [y - a, y + a]."""
    lo = np.maximum(y - a, -0.5 * w)
    hi = np.minimum(y + a, 0.5 * w)
    length = np.maximum(hi - lo, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(w > 1e-12, length / w, (np.abs(y) < a).astype(np.float64))
    return np.minimum(q, 1.0)


def _xi(r, r1, r2):
    return np.clip((r - r1) / (r2 - r1), 0.0, 1.0)


class ReferenceConditions(ConditionKernels):
    """Mixin of condition kernels for the reference backend (NumPy float64)."""

    def fog_points(self, ranges, intensity, i_table, d_table, table_step, alpha, beta_ratio, uniform, noise,
                   intensity_max):
        r0 = np.asarray(ranges, dtype=np.float64)
        inten = np.asarray(intensity, dtype=np.float64)
        k = np.clip(np.floor(r0 / table_step + 0.5), 0, len(i_table) - 1).astype(np.int64)
        i_hard = inten * np.exp(-2.0 * alpha * r0)
        i_soft = np.asarray(i_table, dtype=np.float64)[k] * inten * r0 * r0 * beta_ratio
        fog = i_soft > i_hard
        u = np.maximum(r0 + noise * (2.0 * np.asarray(uniform, dtype=np.float64) - 1.0), 0.5 * r0)
        with np.errstate(divide="ignore", invalid="ignore"):
            moved = np.asarray(d_table, dtype=np.float64)[k] * r0 / u
        out_r = np.where(fog, moved, r0)
        out_i = np.where(fog, np.minimum(i_soft, intensity_max), i_hard)
        return out_r, out_i, fog

    def wet_ground_points(self, intensity, cos_theta, p_out, noise_level, film_fraction, n_air, n_water,
                          rho_min, rho_max):
        inten = np.asarray(intensity, dtype=np.float64)
        cos_t = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
        p_out = np.broadcast_to(np.asarray(p_out, dtype=np.float64), inten.shape)
        noise = np.broadcast_to(np.asarray(noise_level, dtype=np.float64), inten.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.clip(inten / (cos_t * p_out), rho_min, rho_max)
        rho = np.where(np.isnan(rho), rho_min, rho)
        theta = np.arccos(cos_t)
        tw = fresnel_film(theta, rho, film_fraction, n_air, n_water)
        new = np.clip(p_out * cos_t * tw, 0.0, inten)
        keep = new >= noise * cos_t
        return new, keep

    def snow_points(self, ranges, intensity, offsets, flake_range, flake_radius, flake_offset, threshold,
                    beam_divergence, pulse_length, range_step, flake_intensity, r1, r2, intensity_max):
        r0 = np.asarray(ranges, dtype=np.float64)
        inten = np.asarray(intensity, dtype=np.float64)
        offsets = np.asarray(offsets, dtype=np.int64)
        fr = np.asarray(flake_range, dtype=np.float64)
        fa = np.asarray(flake_radius, dtype=np.float64)
        fy = np.asarray(flake_offset, dtype=np.float64)
        thr = np.broadcast_to(np.asarray(threshold, dtype=np.float64), r0.shape)
        n = len(r0)
        out_r, out_i = r0.copy(), inten.copy()
        scattered = np.zeros(n, dtype=bool)
        keep = np.ones(n, dtype=bool)
        counts = np.diff(offsets)
        if len(fr) == 0:
            return out_r, out_i, scattered, keep
        half = 0.5 * pulse_length
        ray = np.repeat(np.arange(n), counts)                    # owner of each flake
        # occlusion, nearest flake first: slot t of every ray at once
        q0 = _overlap_fraction(fy, fa, beam_divergence * fr)
        before = np.empty(len(fr))
        clear = np.ones(n)
        for t in range(int(counts.max())):
            rays_t = np.nonzero(counts > t)[0]
            j = offsets[rays_t] + t
            before[j] = clear[rays_t]
            clear[rays_t] *= 1.0 - q0[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            p_flake = np.where(fr > 0, flake_intensity * q0 * before * _xi(fr, r1, r2) / (fr * fr), 0.0)
        p_t = inten * clear

        def bump(x):
            return np.where(np.abs(x) <= half, np.cos(np.pi * x / pulse_length) ** 2, 0.0)

        # w0: the waveform at the target's own peak (k = 0); the maximum is at least this
        w0 = p_t + np.bincount(ray, p_flake * bump(r0[ray] - fr), minlength=n)
        # Exact pruning: every sample in flake j's window sums pulses of scatterers within one pulse length
        # of r_j, so their total power bounds it; windows whose bound is below w0 cannot hold the maximum.
        span = float(np.max(r0)) + 4.0 * pulse_length + 1.0
        key = ray * span + fr
        cum = np.concatenate([[0.0], np.cumsum(p_flake)])
        lo = np.searchsorted(key, key - pulse_length, side="left")
        hi = np.searchsorted(key, key + pulse_length, side="right")
        bound = cum[hi] - cum[lo] + np.where(r0[ray] - fr <= pulse_length, p_t[ray], 0.0)
        win_flake = np.nonzero(bound >= w0[ray])[0]
        rays_f = np.nonzero(counts > 0)[0]
        win_ray = np.concatenate([rays_f, ray[win_flake]])         # target windows, then surviving flakes
        win_r = np.concatenate([r0[rays_f], fr[win_flake]])
        n_s = int(np.floor(pulse_length / range_step)) + 2
        R = r0[win_ray]
        k = np.ceil((win_r - half - R) / range_step)[:, None] + np.arange(n_s)[None, :]
        d = R[:, None] + k * range_step
        valid = np.abs(d - win_r[:, None]) <= half
        w = p_t[win_ray, None] * bump(d - R[:, None])
        # only flakes within one pulse length of a window's centre reach its samples
        key_w = win_ray * span + win_r
        lo_w = np.searchsorted(key, key_w - pulse_length, side="left")
        cw = np.searchsorted(key, key_w + pulse_length, side="right") - lo_w
        for t in range(int(cw.max()) if len(cw) else 0):
            sel = np.nonzero(cw > t)[0]
            j = lo_w[sel] + t
            w[sel] += p_flake[j, None] * bump(d[sel] - fr[j, None])
        cand_ray = np.broadcast_to(win_ray[:, None], k.shape)[valid]
        cand_w, cand_k = w[valid], k[valid]
        best = np.full(n, -np.inf)
        np.maximum.at(best, cand_ray, cand_w)
        k_best = np.full(n, np.inf)
        top = cand_w == best[cand_ray]
        np.minimum.at(k_best, cand_ray[top], cand_k[top])
        rays = rays_f
        peak = np.clip(best[rays], 0.0, intensity_max)
        is_target = np.abs(k_best[rays]) <= 1
        out_i[rays] = peak
        out_r[rays] = np.where(is_target, r0[rays], np.maximum(r0[rays] + k_best[rays] * range_step, 0.0))
        scattered[rays] = ~is_target
        keep[rays] = ~is_target | (peak >= thr[rays])
        dark = best[rays] <= 0.0              # beam blocked before the overlap range R1: no return at all
        out_r[rays[dark]] = r0[rays[dark]]
        scattered[rays[dark]] = False
        keep[rays[dark]] = False
        return out_r, out_i, scattered, keep

    def motion_blur_points(self, normals, offset, sigma):
        z = np.asarray(normals, dtype=np.float64)
        scale = np.array([0.1, 0.1, 0.05]) * sigma
        jitter = np.clip(z * scale, -3.0 * sigma, 3.0 * sigma)
        return np.asarray(offset, dtype=np.float64)[None, :] + jitter

    def crosstalk_points(self, n_points, index, noise):
        out = np.zeros((int(n_points), 3), dtype=np.float64)
        out[np.asarray(index, dtype=np.int64)] = np.asarray(noise, dtype=np.float64)
        return out

    def incomplete_echo_points(self, instance, rank, n_drop):
        inst = np.asarray(instance, dtype=np.int64)
        rank = np.asarray(rank, dtype=np.int64)
        n_drop = np.asarray(n_drop, dtype=np.int64)
        inside = inst >= 0
        drop = np.zeros(len(inst), dtype=bool)
        drop[inside] = rank[inside] < n_drop[inst[inside]]
        return ~drop
