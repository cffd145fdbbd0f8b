"""The kernel contract of the adverse-condition models (``place3d_kernels.conditions``).

Every backend that runs conditions mixes in a subclass of :class:`ConditionKernels`. Kernels see plain
NumPy arrays (float64 from the host; a float32 backend converts on entry) and return NumPy arrays.

Division of work, so that every backend gives the same answer for the same seed:

* **Randomness lives on the host.** The domain draws every random number with
  ``numpy.random.Generator(PCG64(seed))`` and hands the draws to the kernel. Kernels are pure functions
  of their inputs; a float32 backend differs from ``reference`` (float64) only by rounding.
* **Geometry that needs float64 stays on the host.** Kernels get ranges along rays or displacements,
  never world coordinates; the domain rebuilds points as ``origin + unit_direction * range`` or
  ``point + displacement`` in float64, so a point that a kernel leaves alone is bit-identical.
* Model constants (tables, sensor constants) are computed by the domain and passed in.

``reference`` (NumPy float64) is the executable specification of each kernel.
"""

from __future__ import annotations

import abc

import numpy as np

__all__ = ["ConditionKernels", "SPEED_OF_LIGHT", "THETA_MIN", "fresnel_film"]

#: m/s; used by the domain for pulse lengths (c * tau_h).
SPEED_OF_LIGHT = 299_792_458.0


# ------------------------------------------------------------------ shared formulas (NumPy float64)
#: Smallest incidence angle (rad) used in the film term t / theta (theta = 0 only for a beam straight down).
THETA_MIN = 1e-6


def _fresnel_power(cos_i: np.ndarray, n1: float, n2: float):
    """Power reflection / transmission coefficients (R_s, T_s, R_p, T_p) and cos of the refracted angle."""
    sin_i = np.sqrt(np.clip(1.0 - cos_i * cos_i, 0.0, 1.0))
    sin_t = np.clip(sin_i * n1 / n2, -1.0, 1.0)
    cos_t = np.sqrt(1.0 - sin_t * sin_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    ts = 2.0 * n1 * cos_i / (n1 * cos_i + n2 * cos_t)
    tp = 2.0 * n1 * cos_i / (n2 * cos_i + n1 * cos_t)
    k = (n2 * cos_t) / (n1 * cos_i)  # power transmittance = |t|^2 n2 cos_t / (n1 cos_i)
    return rs * rs, ts * ts * k, rp * rp, tp * tp * k, cos_t


def fresnel_film(theta, rho, film_fraction, n_air: float = 1.0003, n_water: float = 1.33):
    """``(1 - f) rho + f t / theta`` of the water-film model (Hahner et al. 2022), NumPy float64, vectorised.

    ``t = max_{s,p} T_aw rho T_wa / (1 - rho R_wa)``: the power that enters the film (air -> water at theta),
    is reflected by the ground with reflectivity rho, and leaves it (water -> air at the refracted angle),
    summed over the multiple reflections inside the film.
    """
    theta = np.maximum(np.asarray(theta, dtype=np.float64), THETA_MIN)
    rho = np.asarray(rho, dtype=np.float64)
    _, ts_aw, _, tp_aw, cos_w = _fresnel_power(np.cos(theta), n_air, n_water)
    rs_wa, ts_wa, rp_wa, tp_wa, _ = _fresnel_power(cos_w, n_water, n_air)
    t_s = ts_aw * rho * ts_wa / (1.0 - rho * rs_wa)
    t_p = tp_aw * rho * tp_wa / (1.0 - rho * rp_wa)
    t = np.maximum(t_s, t_p)
    return (1.0 - film_fraction) * rho + film_fraction * t / theta


class ConditionKernels(abc.ABC):
    """Per-point kernels of the condition models. All arrays NumPy; N points, F flakes."""

    # ----------------------------------------------------------------- fog (Hahner et al. 2021)
    @abc.abstractmethod
    def fog_points(self, ranges: np.ndarray, intensity: np.ndarray, i_table: np.ndarray, d_table: np.ndarray,
                   table_step: float, alpha: float, beta_ratio: float, uniform: np.ndarray, noise: float,
                   intensity_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hard/soft target decision per point.

        With ``k = clip(floor(R0 / table_step + 0.5), 0, len(i_table) - 1)``,
        ``I_hard = I exp(-2 alpha R0)``, ``I_soft = i_table[k] I R0^2 beta_ratio`` (beta_ratio = beta / beta_0):
        where ``I_soft > I_hard`` the point becomes a fog return at range
        ``d_table[k] R0 / u`` with ``u = max(R0 + noise (2 uniform - 1), R0 / 2)`` and intensity
        ``min(I_soft, intensity_max)``; otherwise it keeps its range with intensity ``I_hard``.

        Args:
            ranges: (N,) R0 per point (> 0).
            intensity: (N,) I per point.
            i_table, d_table: (K,) peak soft-target integral i(R0) and its range d_fog(R0) on R0 = k * table_step.
            uniform: (N,) host draws in [0, 1).

        Returns:
            ranges (N,), intensity (N,), scattered (N,) bool.
        """

    # ----------------------------------------------------------------- wet ground (Hahner et al. 2022)
    @abc.abstractmethod
    def wet_ground_points(self, intensity: np.ndarray, cos_theta: np.ndarray, p_out: np.ndarray,
                          noise_level: np.ndarray, film_fraction: float, n_air: float, n_water: float,
                          rho_min: float, rho_max: float) -> tuple[np.ndarray, np.ndarray]:
        """Water-film model on ground points.

        ``theta = arccos(cos_theta)`` (floored at 1e-6 rad), ``rho = clip(I / (cos_theta p_out), rho_min, rho_max)``,
        Fresnel power coefficients air->water at theta and water->air at the refracted angle,
        ``t = max_{s,p} T_aw rho T_wa / (1 - rho R_wa)``,
        ``I' = clip(p_out cos_theta ((1 - f) rho + f t / theta), 0, I)``; keep where ``I' >= noise_level cos_theta``.

        Returns:
            intensity (N,), keep (N,) bool.
        """

    # ----------------------------------------------------------------- snow (after Hahner et al. 2022)
    @abc.abstractmethod
    def snow_points(self, ranges: np.ndarray, intensity: np.ndarray, offsets: np.ndarray, flake_range: np.ndarray,
                    flake_radius: np.ndarray, flake_offset: np.ndarray, threshold: np.ndarray,
                    beam_divergence: float, pulse_length: float, range_step: float, flake_intensity: float,
                    r1: float, r2: float, intensity_max: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Occlusion by and scattering from snowflakes along each beam.

        Flakes of point i are ``offsets[i]:offsets[i+1]``, sorted by range. A flake (range r, disk radius a,
        lateral offset y of its centre from the beam axis, all metres) covers
        ``q0 = min(|[y-a, y+a] & [-w/2, w/2]| / w, 1)`` of the beam width ``w = beam_divergence r``; nearer flakes
        occlude first: ``q_j = q0_j prod_{k<j} (1 - q0_k)``. Flake power ``P_j = flake_intensity q_j xi(r_j) / r_j^2``,
        target power ``P_t = I prod_j (1 - q0_j)``. The return waveform is the sum of pulses
        ``P cos^2(pi (d - r) / pulse_length)`` for ``|d - r| <= pulse_length / 2``, sampled at
        ``d = R0 + k range_step`` (integer k); its maximum (ties: smallest k) wins. ``|k| <= 1`` keeps the target at
        R0 with the peak as intensity and drops it when that falls below ``threshold``; otherwise the point
        becomes a flake return at ``R0 + k range_step``. A waveform that is zero everywhere (the beam blocked
        inside the blind zone r < r1) drops the point. Points without flakes are returned unchanged.
        Intensities are clipped to ``[0, intensity_max]``.

        Returns:
            ranges (N,), intensity (N,), scattered (N,) bool, keep (N,) bool.
        """

    # ----------------------------------------------------------------- Robo3D corruptions
    @abc.abstractmethod
    def motion_blur_points(self, normals: np.ndarray, offset: np.ndarray, sigma: float) -> np.ndarray:
        """Displacement per point: ``offset + (clip(0.1 s z_x), clip(0.1 s z_y), clip(0.05 s z_z))``, clip to +-3 s.

        Args:
            normals: (N, 3) standard normal host draws z.
            offset: (3,) global offset (already scaled).

        Returns:
            (N, 3) displacement.
        """

    @abc.abstractmethod
    def crosstalk_points(self, n_points: int, index: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """Displacement per point: ``noise[j]`` at ``index[j]`` (distinct indices), zero elsewhere. (N, 3)."""

    @abc.abstractmethod
    def incomplete_echo_points(self, instance: np.ndarray, rank: np.ndarray, n_drop: np.ndarray) -> np.ndarray:
        """Keep mask: a point of instance ``g >= 0`` with rank ``< n_drop[g]`` inside its instance is dropped.

        Args:
            instance: (N,) int instance id, -1 for points outside any instance.
            rank: (N,) int position of the point in a random order of its instance.
            n_drop: (G,) int points to drop per instance.

        Returns:
            (N,) bool.
        """
