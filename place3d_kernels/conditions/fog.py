"""Fog: the LiDAR fog model of Hahner et al. (ICCV 2021), REFERENCE.md section 6.

Per point at range R0 with intensity I: the hard-target return is attenuated to
``I_hard = I exp(-2 alpha R0)``; the fog itself returns ``I_soft = i(R0) I R0^2 beta / beta_0``, where
``i(R0)`` is the peak over R of the normalised soft-target power

    P_soft(R) / (C_A P0 beta) = int_0^{2 tau_H} sin^2(pi t / (2 tau_H)) exp(-2 alpha r) xi(r) / r^2 U(R0 - r) dt,
    r = R - c t / 2,

and ``d_fog(R0)`` its position. Where ``I_soft > I_hard`` the point becomes a fog return: it moves along its
ray to ``d_fog R0 / u``, ``u ~ U(R0 - 10, R0 + 10)``, with intensity ``I_soft``; otherwise it keeps its place
with ``I_hard``. No point is deleted.

Choices beyond REFERENCE.md (documented, each with a keyword to change it):

* ``i`` and ``d_fog`` are integrated here (``fog_lookup``: 1 mm trapezoid in range, FFT convolution),
  once per (alpha, tau_H, R1, R2), on R0 = 0, 0.1, ..., 200 m, and cached; the lookup index is
  ``floor(R0 / 0.1 + 0.5)`` capped at 200 m, as in Hahner et al.'s tables.
* ``d_fog`` is put on the hard-target range scale (shifted by -c tau_H / 2), as in the original tables;
  ``fog_lookup(..., shift=False)`` gives the raw peak position.
* ``I_soft`` is clipped to ``intensity_max`` (1.0, the top of PointCloud's intensity scale) as the
  original clips to 255; the decision uses the unclipped value.
* ``u`` is floored at ``R0 / 2`` so that a fog return never jumps far beyond ``d_fog`` or behind the
  sensor (only fog returns closer than 2 x 10 m can reach the floor; the paper settings give none).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from place3d_kernels.backends.conditions_base import SPEED_OF_LIGHT
from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rays, rng, scattered
from place3d_kernels.pointcloud import PointCloud

__all__ = ["fog", "fog_lookup", "FogTable", "FogSensor", "mor", "alpha_from_mor", "FOG_ALPHAS", "SEVERITIES"]

#: Attenuation coefficients (1/m) the paper draws from per frame (Place3D appendix, Robo3D nuScenes-C).
FOG_ALPHAS = (0.0, 0.005, 0.01, 0.02, 0.03, 0.06)
#: Robo3D's three levels change the backscatter coefficient; "moderate" is the paper's setting.
SEVERITIES = {"light": {"beta": 0.008}, "moderate": {"beta": 0.05}, "heavy": {"beta": 0.2}}


@dataclass(frozen=True)
class FogSensor:
    """Sensor constants of Hahner et al. 2021 (REFERENCE.md section 6)."""

    p0: float = 80.0          #: pulse peak power, W
    tau_h: float = 20e-9      #: half-power pulse width, s
    a_r: float = 0.25         #: receiver aperture area, m^2
    l_r: float = 0.05         #: receiver optics loss
    gamma: float = 1e-6       #: hard-target reflectivity Gamma
    r1: float = 0.9           #: overlap xi = 0 up to R1 (m)
    r2: float = 1.0           #: overlap xi = 1 from R2 (m)

    @property
    def c_a(self) -> float:
        """System constant C_A = c L_R A_R / 2."""
        return SPEED_OF_LIGHT * self.l_r * self.a_r / 2.0

    @property
    def beta_0(self) -> float:
        """Differential reflectivity of the hard target, Gamma / pi."""
        return self.gamma / math.pi


def mor(alpha):
    """Meteorological optical range ln(20) / alpha (m) for attenuation alpha (1/m); inf for alpha = 0."""
    a = np.asarray(alpha, dtype=np.float64)
    with np.errstate(divide="ignore"):
        out = np.log(20.0) / a
    return float(out) if out.ndim == 0 else out


def alpha_from_mor(m):
    """Attenuation coefficient ln(20) / MOR (1/m)."""
    return np.log(20.0) / np.asarray(m, dtype=np.float64) if np.ndim(m) else math.log(20.0) / float(m)


@dataclass(frozen=True)
class FogTable:
    """Peak soft-target integral ``i`` (s / m^2) and its range ``d`` (m) on ``r0 = k * step``."""

    step: float
    r0: np.ndarray
    i: np.ndarray
    d: np.ndarray

    def index(self, r0) -> np.ndarray:
        k = np.floor(np.asarray(r0, dtype=np.float64) / self.step + 0.5)
        return np.clip(k, 0, len(self.i) - 1).astype(np.int64)

    def lookup(self, r0) -> tuple[np.ndarray, np.ndarray]:
        """(i(R0), d_fog(R0)) with the kernels' index rule."""
        k = self.index(r0)
        return self.i[k], self.d[k]


def _fftconv(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = len(a) + len(b) - 1
    size = 1 << (n - 1).bit_length()
    return np.fft.irfft(np.fft.rfft(a, size) * np.fft.rfft(b, size), size)[:n]


@functools.lru_cache(maxsize=64)
def _fog_lookup(alpha: float, tau_h: float, r1: float, r2: float, step: float, r0_max: float,
                dr: float, shift: bool) -> FogTable:
    pulse = SPEED_OF_LIGHT * tau_h               # the pulse spans [R - c tau_H, R] in r (2 tau_H in time)
    n_s = int(round(pulse / dr)) + 1
    s = np.arange(n_s) * dr
    w = np.sin(np.pi * s / pulse) ** 2 * dr       # trapezoid weights (w = 0 at both ends)
    w *= 2.0 / SPEED_OF_LIGHT                    # dt = 2 dr / c
    k_max = int(round(r0_max / step))
    per = int(round(step / dr))                  # fine samples per table step
    n_r = k_max * per + n_s + 1
    r = np.arange(n_r) * dr
    xi = np.clip((r - r1) / (r2 - r1), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(xi > 0, np.exp(-2.0 * alpha * r) * xi / (r * r), 0.0)
    # Untruncated P_soft(R) = sum_m w[m] g(R - s_m); for R <= R0 the step U(R0 - r) is 1 throughout.
    full = _fftconv(g, w)[:n_r]
    prefix_arg = np.zeros(n_r, dtype=np.int64)
    best = np.maximum.accumulate(full)
    # index of the first maximum of full[:k+1] for every k
    is_new = np.concatenate([[True], full[1:] > best[:-1]])
    prefix_arg = np.maximum.accumulate(np.where(is_new, np.arange(n_r), 0))
    suffix_max = np.maximum.accumulate(full[::-1])[::-1]
    i_tab = np.zeros(k_max + 1)
    d_tab = np.zeros(k_max + 1)
    for k in range(k_max + 1):
        j = k * per                               # fine index of R0
        if j + 1 < n_r and suffix_max[j + 1] > best[j]:
            # Some R > R0 could beat the prefix maximum: evaluate the truncated integral exactly.
            part = _fftconv(g[:j + 1], w)
            a = int(np.argmax(part))
            i_tab[k], d_tab[k] = part[a], a * dr
        else:
            i_tab[k], d_tab[k] = best[j], prefix_arg[j] * dr
    i_tab = np.maximum(i_tab, 0.0)               # FFT round-off can leave -1e-30 where the integral is 0
    if shift:
        d_tab = np.maximum(d_tab - pulse / 2.0, 0.0)
    r0 = np.arange(k_max + 1) * step
    for arr in (r0, i_tab, d_tab):
        arr.flags.writeable = False
    return FogTable(step, r0, i_tab, d_tab)


def fog_lookup(alpha: float, tau_h: float = 20e-9, r1: float = 0.9, r2: float = 1.0, step: float = 0.1,
               r0_max: float = 200.0, dr: float = 1e-3, shift: bool = True) -> FogTable:
    """Peak soft-target integral i(R0) and its range d_fog(R0), integrated numerically and cached.

    R in the integral is the range of the pulse's *start*; a hard target at R0 peaks at R = R0 + c tau_h / 2.
    With ``shift`` (default, as Hahner et al.'s published tables) d_fog is moved by -c tau_h / 2 onto the
    scale on which hard targets are ranged (floored at 0), so fog returns land at about 1.7 m rather
    than 4.7 m for tau_h = 20 ns. ``i`` does not depend on it.

    Args:
        alpha: attenuation coefficient (1/m).
        tau_h: half-power pulse width (s); the pulse lasts 2 tau_h.
        r1, r2: overlap function xi ramps from 0 at r1 to 1 at r2 (m).
        step: R0 grid step (m); r0_max: last R0 (m).
        dr: integration step in range (m).
    """
    alpha = check_range("alpha", alpha, lo=0.0)
    return _fog_lookup(alpha, float(tau_h), float(r1), float(r2), float(step), float(r0_max), float(dr),
                       bool(shift))


def fog_arrays(cloud: PointCloud, alpha: float, beta: float, seed, backend, noise: float, sensor: FogSensor,
               intensity_max: float):
    """(new points, new intensity, fog mask, ranges R0) for a cloud; the kernel call behind ``fog``."""
    o, u, r0 = rays(cloud)
    table = fog_lookup(alpha, sensor.tau_h, sensor.r1, sensor.r2)
    uniform = rng(seed, 1).random(len(cloud))
    k = kernels(backend)
    new_r, new_i, is_fog = k.fog_points(r0, cloud.intensity.astype(np.float64), table.i, table.d, table.step,
                                        alpha, beta / sensor.beta_0, uniform, float(noise), float(intensity_max))
    is_fog = np.asarray(is_fog, dtype=bool) & (r0 > 0)
    pts = cloud.points.copy()
    pts[is_fog] = o[is_fog] + u[is_fog] * np.asarray(new_r)[is_fog, None]
    return pts, np.asarray(new_i), is_fog, r0


def fog(cloud: PointCloud, alpha: float | None = None, beta: float = 0.05, seed=0, backend=None, *,
        noise: float = 10.0, sensor: FogSensor = FogSensor(), intensity_max: float = 1.0,
        alphas=FOG_ALPHAS) -> PointCloud:
    """Fog (Hahner et al. 2021): attenuate every return and replace the weak ones by fog backscatter.

    Args:
        cloud: the clear-weather frame; ranges are measured from ``cloud.origins`` (or 0).
        alpha: attenuation coefficient (1/m); ``None`` draws one of ``alphas`` with the seed (the paper
            draws alpha per frame from {0, 0.005, 0.01, 0.02, 0.03, 0.06}). MOR = ln(20) / alpha.
        beta: backscattering coefficient (1/(m sr)); the paper uses 0.05.
        seed: int or numpy Generator; draws alpha (if None) and the fog returns' range noise.
        backend: backend name or instance (None: current default).
        noise: half-width (m) of the uniform range noise u ~ U(R0 - noise, R0 + noise).
        sensor: sensor constants (pulse width, overlap R1/R2, hard-target reflectivity).
        intensity_max: fog intensities are clipped to this.

    Returns:
        A new PointCloud of the same length: fog returns moved along their rays and marked in ``scattered``.
    """
    cloud = check_cloud(cloud, "fog")
    if alpha is None:
        alpha = float(alphas[int(rng(seed, 0).integers(len(alphas)))])
    alpha = check_range("alpha", alpha, lo=0.0)
    beta = check_range("beta", beta, lo=0.0)
    noise = check_range("noise", noise, lo=0.0)
    if alpha == 0.0 and beta == 0.0 or len(cloud) == 0:
        return cloud.copy()
    pts, inten, is_fog, _ = fog_arrays(cloud, alpha, beta, seed, backend, noise, sensor, intensity_max)
    return cloud.copy(points=pts, intensity=inten.astype(np.float32), scattered=scattered(cloud) | is_fog)
