/* Condition kernels (fog, wet ground, snow, Robo3D corruptions): one work-item per point.
 *
 * Built after common.cl, so `real` is double when the host passes HAVE_FP64 (devices with cl_khr_fp64,
 * unless the backend was made with fp64=False) and float otherwise. Every random number comes from the
 * host (see backends/conditions_base.py); these kernels are pure functions of their inputs, and equal the
 * reference (NumPy float64) up to the rounding of `real`.
 */

#define THETA_MIN ((real)1.0e-6)
#define PI_R ((real)3.14159265358979323846)

/* --------------------------------------------------------------------------------------------- fog */
__kernel void cond_fog(__global const real *ranges, __global const real *intensity,
                       __global const real *i_table, __global const real *d_table, const int n_table,
                       const real table_step, const real alpha, const real beta_ratio,
                       __global const real *uniform, const real noise, const real intensity_max,
                       __global real *out_r, __global real *out_i, __global uchar *out_fog, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const real r0 = ranges[i];
    const real inten = intensity[i];
    int k = (int)floor(r0 / table_step + (real)0.5);
    k = clamp(k, 0, n_table - 1);
    const real i_hard = inten * exp((real)-2.0 * alpha * r0);
    const real i_soft = i_table[k] * inten * r0 * r0 * beta_ratio;
    if (i_soft > i_hard) {
        const real u = fmax(r0 + noise * ((real)2.0 * uniform[i] - (real)1.0), (real)0.5 * r0);
        out_r[i] = d_table[k] * r0 / u;
        out_i[i] = fmin(i_soft, intensity_max);
        out_fog[i] = 1;
    } else {
        out_r[i] = r0;
        out_i[i] = i_hard;
        out_fog[i] = 0;
    }
}

/* --------------------------------------------------------------------------------------------- wet ground */
/* Power reflectance and transmittance (pol 0: s, 1: p) of an n1 -> n2 interface at cos_i. */
inline void fresnel_power(real cos_i, real n1, real n2, int pol, real *R, real *T)
{
    const real sin_i = sqrt(clamp((real)1.0 - cos_i * cos_i, (real)0.0, (real)1.0));
    const real sin_t = clamp(sin_i * n1 / n2, (real)-1.0, (real)1.0);
    const real cos_t = sqrt((real)1.0 - sin_t * sin_t);
    const real k = (n2 * cos_t) / (n1 * cos_i);
    real r, t;
    if (pol == 0) {
        r = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
        t = (real)2.0 * n1 * cos_i / (n1 * cos_i + n2 * cos_t);
    } else {
        r = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t);
        t = (real)2.0 * n1 * cos_i / (n2 * cos_i + n1 * cos_t);
    }
    *R = r * r;
    *T = t * t * k;
}

__kernel void cond_wet(__global const real *intensity, __global const real *cos_theta,
                       __global const real *p_out, __global const real *noise_level,
                       const real f, const real n_air, const real n_water, const real rho_min, const real rho_max,
                       __global real *out_i, __global uchar *out_keep, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const real inten = intensity[i];
    const real ct = clamp(cos_theta[i], (real)0.0, (real)1.0);
    const real po = p_out[i];
    const real den = ct * po;
    real rho = rho_min;
    if (den != (real)0.0) {
        const real q = inten / den;
        if (!isnan(q)) rho = clamp(q, rho_min, rho_max);
    }
    const real theta = fmax(acos(ct), THETA_MIN);
    /* cos theta as given (cos(acos(x)) loses digits at grazing incidence); the reference uses cos(theta),
       which differs only where theta was floored at THETA_MIN (ct within 5e-13 of 1) */
    const real cos_i = ct;
    const real sin_w = sqrt(clamp((real)1.0 - ct * ct, (real)0.0, (real)1.0)) * n_air / n_water;
    const real cos_w = sqrt((real)1.0 - sin_w * sin_w);
    real t_best = (real)0.0;
    for (int pol = 0; pol < 2; ++pol) {
        real r_aw, t_aw, r_wa, t_wa;
        fresnel_power(cos_i, n_air, n_water, pol, &r_aw, &t_aw);
        fresnel_power(cos_w, n_water, n_air, pol, &r_wa, &t_wa);
        t_best = fmax(t_best, t_aw * rho * t_wa / ((real)1.0 - rho * r_wa));
    }
    const real tw = ((real)1.0 - f) * rho + f * t_best / theta;
    const real v = clamp(po * ct * tw, (real)0.0, inten);
    out_i[i] = v;
    out_keep[i] = (v >= noise_level[i] * ct) ? 1 : 0;
}

/* --------------------------------------------------------------------------------------------- snow */
inline real bump(real d, real r, real half_len, real pulse_length)
{
    const real x = d - r;
    if (fabs(x) > half_len) return (real)0.0;
    const real c = cos(PI_R * x / pulse_length);
    return c * c;
}

__kernel void cond_snow(__global const real *ranges, __global const real *intensity,
                        __global const long *offsets, __global const real *fr, __global const real *fa,
                        __global const real *fy, __global const real *threshold,
                        const real beam_divergence, const real pulse_length, const real step,
                        const real flake_intensity, const real r1, const real r2, const real intensity_max,
                        __global real *power,
                        __global real *out_r, __global real *out_i, __global uchar *out_scat,
                        __global uchar *out_keep, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const real r0 = ranges[i];
    const real inten = intensity[i];
    const long s = offsets[i];
    const long e = offsets[i + 1];
    out_r[i] = r0;
    out_i[i] = inten;
    out_scat[i] = 0;
    out_keep[i] = 1;
    if (e == s) return;
    /* flake powers, nearer flakes occluding first */
    real clear = (real)1.0;
    for (long j = s; j < e; ++j) {
        const real r = fr[j], a = fa[j], y = fy[j];
        const real w = beam_divergence * r;
        real q0 = (real)0.0;
        if (w > (real)1.0e-12) {
            const real lo = fmax(y - a, (real)-0.5 * w);
            const real hi = fmin(y + a, (real)0.5 * w);
            q0 = fmin(fmax(hi - lo, (real)0.0) / w, (real)1.0);
        } else if (fabs(y) < a) {
            q0 = (real)1.0;
        }
        const real xi = clamp((r - r1) / (r2 - r1), (real)0.0, (real)1.0);
        power[j] = (r > (real)0.0) ? flake_intensity * q0 * clear * xi / (r * r) : (real)0.0;
        clear *= (real)1.0 - q0;
    }
    const real p_t = inten * clear;
    const real half_len = (real)0.5 * pulse_length;
    /* w0: the waveform at the target's own peak (k = 0); the maximum is at least this */
    real w0 = p_t;
    for (long jj = s; jj < e; ++jj) w0 += power[jj] * bump(r0, fr[jj], half_len, pulse_length);
    const int n_samples = (int)floor(pulse_length / step) + 2;
    real best = (real)-1.0;
    long best_k = 0;
    int found = 0;
    /* candidate samples d = r0 + k step inside each scatterer's pulse (index e stands for the target) */
    for (long j = s; j <= e; ++j) {
        real rj = r0;
        if (j < e) {
            rj = fr[j];
            /* exact pruning: pulses within one pulse length of r_j bound every sample of this window */
            real bound = (r0 - rj <= pulse_length) ? p_t : (real)0.0;
            for (long jj = s; jj < e; ++jj)
                if (fabs(fr[jj] - rj) <= pulse_length) bound += power[jj];
            if (bound < w0) continue;
        }
        const long k_lo = (long)ceil((rj - half_len - r0) / step);
        for (int m = 0; m < n_samples; ++m) {
            const long k = k_lo + m;
            const real d = r0 + (real)k * step;
            if (fabs(d - rj) <= half_len) {
                real v = p_t * bump(d, r0, half_len, pulse_length);
                for (long jj = s; jj < e; ++jj) v += power[jj] * bump(d, fr[jj], half_len, pulse_length);
                if (!found || v > best || (v == best && k < best_k)) {
                    best = v;
                    best_k = k;
                    found = 1;
                }
            }
        }
    }
    const real peak = clamp(best, (real)0.0, intensity_max);
    out_i[i] = peak;
    if (best <= (real)0.0) {
        out_keep[i] = 0;               /* beam blocked before the overlap range R1: no return at all */
    } else if (best_k >= -1 && best_k <= 1) {
        if (peak < threshold[i]) out_keep[i] = 0;
    } else {
        out_r[i] = fmax(r0 + (real)best_k * step, (real)0.0);
        out_scat[i] = 1;
    }
}

/* --------------------------------------------------------------------------------------------- Robo3D */
__kernel void cond_motion_blur(__global const real *normals, const real ox, const real oy, const real oz,
                               const real sigma, __global real *out, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const real lim = (real)3.0 * sigma;
    out[3 * i + 0] = ox + clamp(normals[3 * i + 0] * ((real)0.1 * sigma), -lim, lim);
    out[3 * i + 1] = oy + clamp(normals[3 * i + 1] * ((real)0.1 * sigma), -lim, lim);
    out[3 * i + 2] = oz + clamp(normals[3 * i + 2] * ((real)0.05 * sigma), -lim, lim);
}

__kernel void cond_crosstalk(__global const long *index, __global const real *noise, __global real *out,
                             const int k)
{
    const int j = get_global_id(0);
    if (j >= k) return;
    const long p = index[j];
    out[3 * p + 0] = noise[3 * j + 0];
    out[3 * p + 1] = noise[3 * j + 1];
    out[3 * p + 2] = noise[3 * j + 2];
}

__kernel void cond_echo(__global const long *instance, __global const long *rank, __global const long *n_drop,
                        __global uchar *out_keep, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const long g = instance[i];
    out_keep[i] = (g >= 0 && rank[i] < n_drop[g]) ? 0 : 1;
}
