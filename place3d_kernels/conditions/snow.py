"""Snow: occlusion by and backscatter from snowflakes, after Hahner et al. (CVPR 2022) / Robo3D.

REFERENCE.md section 6 fixes the inputs (snowfall rate S in mm/h, terminal velocity v in m/s,
Gunn-Marshall particle sizes, beams partly occluded by flakes, returns scattered by flakes). The model,
per beam, as Hahner et al.'s snowfall simulation but with the flakes drawn per beam instead of from a
stored particle field:

* Snow occupies the area fraction ``phi = S / (3.6e6 rho_s v)`` of the scan plane (rho_s = 0.1 g/cm^3 snow
  density, water 1 g/cm^3). Flake diameters D follow Gunn and Marshall (1958), exponential with rate
  ``25.5 R^-0.48`` per cm, R the equivalent rainfall rate ``(S / (487 rho_s D_0 v))^1.5`` (D_0 = 3 mm),
  truncated at 20 mm; the plane cuts a flake at a uniform height, leaving a disk of radius
  ``a = D/2 sqrt(1 - s^2)``, s ~ U(-1, 1). Disk centres form a Poisson process of density
  ``phi / E[pi a^2]`` in the plane.
* A beam of divergence 3 mrad is a wedge of width ``w = 3e-3 r`` at range r; the flakes it meets before
  its target at R0 (a Poisson number, mean ``density (3e-3 R0^2 / 2 + 2 E[a] R0)``) are drawn on the host
  with their range, radius and lateral offset. A flake covers the fraction of the beam width its disk
  overlaps; nearer flakes occlude first (farther ones only block what is still open).
* Each flake returns ``0.9 q xi(r) / r^2`` (90 % reflectivity, not range-normalised, as Hahner et al.),
  the target ``I`` times the open fraction. The waveform is the sum of their sin^2 pulses
  (10 ns half-power width) sampled every 0.1 m; its peak wins. A peak within 0.1 m of R0 keeps the
  point with the peak intensity, and drops it if that falls below the noise threshold; any other peak
  turns the point into a snowflake return at the peak's range (marked in ``scattered``, label kept).
* The noise threshold per point is the wet-ground noise-floor fit (0.7 x the bottom of the ground
  intensity histogram, times cos theta) as a quadratic in range, as Hahner et al.; 0 without ground
  points. Only beams that met a flake can be dropped, so snowfall 0 is the identity.

Kernels see ranges only; moved points stay on their ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from place3d_kernels.backends.conditions_base import SPEED_OF_LIGHT
from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rays, rng, scattered
from place3d_kernels.conditions.wet_ground import ground_geometry, laser_parameters
from place3d_kernels.pointcloud import PointCloud

__all__ = ["snow", "snowflakes", "Snowflakes", "snow_occupancy", "equivalent_rainfall_rate", "gunn_marshall_rate",
           "flake_density", "SEVERITIES"]

#: (snowfall rate mm/h, terminal velocity m/s): Robo3D / Hahner et al. settings; the paper's is "moderate".
SEVERITIES = {
    "light": {"snowfall_rate": 0.5, "terminal_velocity": 2.0},
    "moderate": {"snowfall_rate": 1.0, "terminal_velocity": 1.6},
    "heavy": {"snowfall_rate": 2.5, "terminal_velocity": 1.6},
}


def snow_occupancy(snowfall_rate, terminal_velocity, snow_density: float = 0.1) -> float:
    """Fraction of space occupied by snow: S / (3.6e6 rho_s v) (S mm/h, v m/s, rho_s g/cm^3)."""
    return float(snowfall_rate) / (3.6e6 * snow_density * float(terminal_velocity))


def equivalent_rainfall_rate(snowfall_rate, terminal_velocity, snow_density: float = 0.1,
                             flake_diameter: float = 0.003) -> float:
    """Rainfall rate (mm/h) equivalent to a snowfall rate: (S / (487 rho_s D_0 v))^1.5."""
    return (float(snowfall_rate) / (487.0 * snow_density * flake_diameter * float(terminal_velocity))) ** 1.5


def gunn_marshall_rate(rainfall_rate) -> float:
    """Rate of the exponential flake-diameter distribution (1/cm): 25.5 R^-0.48 (Gunn and Marshall 1958)."""
    return 25.5 * float(rainfall_rate) ** -0.48


def _truncexp_moments(mu: float, dmax: float) -> tuple[float, float]:
    """E[D], E[D^2] of an exponential with mean mu truncated to [0, dmax]."""
    x = dmax / mu
    tail = np.exp(-x) / -np.expm1(-x)          # e^-x / (1 - e^-x)
    m1 = mu - dmax * tail
    m2 = 2.0 * mu * mu - (dmax * dmax + 2.0 * mu * dmax) * tail
    return float(m1), float(m2)


def flake_density(snowfall_rate, terminal_velocity, *, snow_density: float = 0.1, max_diameter: float = 0.02
                  ) -> tuple[float, float, float]:
    """(disk centres per m^2 of scan plane, mean diameter scale mu (m), mean disk radius E[a] (m))."""
    phi = snow_occupancy(snowfall_rate, terminal_velocity, snow_density)
    mu = 0.01 / gunn_marshall_rate(equivalent_rainfall_rate(snowfall_rate, terminal_velocity, snow_density))
    m1, m2 = _truncexp_moments(mu, max_diameter)
    density = phi / (np.pi * m2 / 6.0)          # E[pi a^2] = pi E[D^2] / 6 for a uniform cut height
    return float(density), float(mu), float(np.pi * m1 / 8.0)


@dataclass
class Snowflakes:
    """Flakes met by each beam before its target, as CSR: beam i owns ``offsets[i]:offsets[i+1]``,
    sorted by range. ``radius`` is the disk radius in the scan plane, ``offset`` the lateral distance of
    its centre from the beam axis (all metres)."""

    offsets: np.ndarray
    range: np.ndarray
    radius: np.ndarray
    offset: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


def snowflakes(ranges, snowfall_rate: float = 1.0, terminal_velocity: float = 1.6, seed=0, *,
               beam_divergence: float = 3e-3, snow_density: float = 0.1, max_diameter: float = 0.02) -> Snowflakes:
    """Draw the flakes each beam meets before its target (host side of ``snow``; see module docstring).

    The pairs (range r, radius a) have density ``density p(a) (beam_divergence r + 2 a)`` on [0, R0]: a
    mixture of r ~ R0 sqrt(U) with a ~ p, and r ~ U(0, R0) with a size-biased by a (D from a Gamma(2)
    truncated at ``max_diameter``, the cut from the semicircle law). The lateral offset is uniform over
    the band where the disk touches the beam.
    """
    r0 = np.asarray(ranges, dtype=np.float64).reshape(-1)
    n = len(r0)
    density, mu, mean_a = flake_density(snowfall_rate, terminal_velocity, snow_density=snow_density,
                                        max_diameter=max_diameter)
    g = rng(seed, 2)
    part_a = beam_divergence * r0 * r0 / 2.0
    part_b = 2.0 * mean_a * r0
    counts = g.poisson(density * (part_a + part_b)) if density > 0 else np.zeros(n, dtype=np.int64)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    m = int(offsets[-1])
    ray = np.repeat(np.arange(n), counts)
    R = r0[ray]
    with np.errstate(divide="ignore", invalid="ignore"):
        p_b = np.where(part_a + part_b > 0, part_b / (part_a + part_b), 0.0)[ray]
    biased = g.random(m) < p_b
    u = g.random(m)
    r = np.where(biased, R * u, R * np.sqrt(u))
    # diameters: truncated exponential (inverse CDF) or size-biased (Gamma(2), redrawn beyond max)
    u = g.random(m)
    d = -mu * np.log1p(-u * -np.expm1(-max_diameter / mu))
    nb = int(np.count_nonzero(biased))
    db = mu * g.standard_gamma(2.0, nb)
    while True:
        bad = db > max_diameter
        if not bad.any():
            break
        db[bad] = mu * g.standard_gamma(2.0, int(np.count_nonzero(bad)))
    d[biased] = db
    s = g.uniform(-1.0, 1.0, m)
    sb = np.sqrt(g.random(nb)) * np.cos(2.0 * np.pi * g.random(nb))     # semicircle law on [-1, 1]
    s[biased] = sb
    a = 0.5 * d * np.sqrt(np.clip(1.0 - s * s, 0.0, 1.0))
    half = 0.5 * beam_divergence * r + a
    y = (2.0 * g.random(m) - 1.0) * half
    order = np.lexsort((r, ray))
    return Snowflakes(offsets, r[order], a[order], y[order])


def _noise_threshold(cloud, seed, noise_floor, r):
    """Per-point noise threshold: quadratic in range through the ground noise floor times cos theta."""
    mask, cos_t, _ = ground_geometry(cloud, seed, None, None)
    gi = np.nonzero(mask & (r > 0) & (cos_t > 0))[0]
    if len(gi) < 3:
        return np.zeros(len(cloud))
    _, (c, e) = laser_parameters(r[gi], cos_t[gi], cloud.intensity[gi].astype(np.float64), noise_floor=noise_floor)
    thr_g = (c * r[gi] + e) * cos_t[gi]
    if np.ptp(r[gi]) > 0 and len(gi) >= 3:
        p = np.polyfit(r[gi], thr_g, 2)
        return np.maximum(np.polyval(p, r), 0.0)
    return np.full(len(cloud), max(float(np.mean(thr_g)), 0.0))


def _snow_arrays(cloud, snowfall_rate, terminal_velocity, seed, backend, beam_divergence, tau_h, range_step,
                 flake_intensity, noise_floor, threshold, intensity_max, snow_density, max_diameter, r1, r2):
    o, u, r0 = rays(cloud)
    flakes = snowflakes(r0, snowfall_rate, terminal_velocity, seed, beam_divergence=beam_divergence,
                        snow_density=snow_density, max_diameter=max_diameter)
    if threshold is None:
        thr = _noise_threshold(cloud, seed, noise_floor, r0)
    else:
        thr = np.broadcast_to(np.asarray(threshold, dtype=np.float64), (len(cloud),))
    new_r, new_i, scat, keep = kernels(backend).snow_points(
        r0, cloud.intensity.astype(np.float64), flakes.offsets, flakes.range, flakes.radius, flakes.offset, thr,
        beam_divergence, SPEED_OF_LIGHT * tau_h, range_step, flake_intensity, r1, r2, intensity_max)
    scat = np.asarray(scat, dtype=bool)
    pts = cloud.points.copy()
    pts[scat] = o[scat] + u[scat] * np.asarray(new_r)[scat, None]
    return pts, np.asarray(new_i), scat, np.asarray(keep, dtype=bool), flakes


def snow(cloud: PointCloud, snowfall_rate: float = 1.0, terminal_velocity: float = 1.6, seed=0, backend=None, *,
         beam_divergence: float = 3e-3, tau_h: float = 10e-9, range_step: float = 0.1, flake_intensity: float = 0.9,
         noise_floor: float = 0.7, threshold=None, intensity_max: float = 1.0, snow_density: float = 0.1,
         max_diameter: float = 0.02, r1: float = 0.9, r2: float = 1.0) -> PointCloud:
    """Snowfall: flakes along each beam occlude its target and may replace it by a snowflake return.

    Args:
        cloud: the clear frame; beams run from ``cloud.origins`` (or 0) to the points.
        snowfall_rate: S in mm/h water equivalent (paper: 1.0; Robo3D heavy 2.5).
        terminal_velocity: v in m/s (1.6 with S = 1.0 and 2.5; 2.0 for light snow).
        seed: int or numpy Generator; draws the flakes (and the RANSAC plane of unlabeled clouds).
        backend: backend name or instance (None: current default).
        beam_divergence: full beam opening (rad); tau_h: half-power pulse width (s); range_step: waveform
            sampling (m); flake_intensity: a fully covered beam's flake return at 1 m (x xi(r) / r^2).
        noise_floor: scale of the ground noise floor; threshold: per-point threshold instead of the fit.
        snow_density: g/cm^3; max_diameter: m; r1, r2: transmitter/receiver overlap ramp (m).

    Returns:
        A new PointCloud: dimmed points below the threshold dropped, snowflake returns moved along their
        rays and marked in ``scattered``.
    """
    cloud = check_cloud(cloud, "snow")
    check_range("snowfall_rate", snowfall_rate, lo=0.0)
    check_range("terminal_velocity", terminal_velocity, lo=0.0, lo_open=True)
    if snowfall_rate == 0.0 or len(cloud) == 0:
        return cloud.copy()
    pts, inten, scat, keep, _ = _snow_arrays(cloud, snowfall_rate, terminal_velocity, seed, backend,
                                             beam_divergence, tau_h, range_step, flake_intensity, noise_floor,
                                             threshold, intensity_max, snow_density, max_diameter, r1, r2)
    res = cloud.copy(points=pts, intensity=inten.astype(np.float32), scattered=scattered(cloud) | scat)
    return res if keep.all() else res.subset(keep)
