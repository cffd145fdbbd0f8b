"""Wet ground: the water-film model of Hahner et al. (CVPR 2022), REFERENCE.md section 6.

Per ground point with incidence angle theta (from the ground normal) and intensity I:

* ground reflectivity ``rho = clip(I / (cos theta P_out), 0.05, 1)``, where ``P_out(d) = 15 (a d + b)`` and
  (a, b) is the least-squares line of the cos-normalised intensity ``I / cos theta`` over range d;
* Fresnel power coefficients at air -> water (theta) and water -> air (the refracted angle), refractive
  indices 1.0003 and 1.33; ``t = max_{s,p} T_aw rho T_wa / (1 - rho R_wa)``;
* film fraction ``f = clip(h_w / 1.2 mm, 0, 1)`` (pavement texture depth 1.2 mm);
* ``I' = clip(P_out cos theta ((1 - f) rho + f t / theta), 0, I)``; the point is dropped when
  ``I' < N(d) cos theta``, with the noise floor ``N(d) = 0.7 (c d + e)``: (c, e) the least-squares line
  through the lowest cos-normalised ground intensity of each of 50 range bins over 10-70 m (the bottom
  of the intensity histogram), lowered until it passes under every bin's lowest value, so that the
  floor never cuts into the dry returns it was fitted to (a constant, the lowest value, when fewer than
  two bins are filled). Hahner et al. fit through the least-populated histogram bin of each range bin,
  which on real scans is a low-tail value; on clean simulated intensities a plain fit through the
  minima rises above the darkest class and would drop dry road.

Points are only dimmed or dropped, never moved; non-ground points are untouched. Ground points come from
the labels (road 7, road line 6, sidewalk 8, ground 13, terrain 21) with the flat-earth normal (0, 0, 1),
or, when the cloud carries no labels, from a RANSAC plane fit (the plane's normal; points within 0.5 m).
A water height of 0 is the identity.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.conditions_base import fresnel_film
from place3d_kernels.classes import GROUND_CLASSES
from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rays, rng
from place3d_kernels.pointcloud import PointCloud

__all__ = ["wet_ground", "film_transmission", "ground_points", "laser_parameters", "SEVERITIES"]

#: Robo3D levels (water height in mm); "moderate" is the paper's 1.0 mm. Light is Robo3D's 0.2 mm; heavy
#: (1.2 mm, a film filling the pavement texture) is this project's choice.
SEVERITIES = {"light": {"water_height_mm": 0.2}, "moderate": {"water_height_mm": 1.0},
              "heavy": {"water_height_mm": 1.2}}


def legacy_water_height(water_height_mm, water_height):
    """``water_height_mm``, taking the pre-rename keyword ``water_height`` (also mm) with a warning."""
    if water_height is None:
        return water_height_mm
    import warnings

    warnings.warn("wet_ground: 'water_height' is now 'water_height_mm' (the film height in millimetres, the "
                  "package's one exception to metres)", DeprecationWarning, stacklevel=3)
    return water_height


def film_transmission(theta, rho, water_height_mm=1.0, *, pavement_depth: float = 1.2, n_air: float = 1.0003,
                      n_water: float = 1.33, water_height=None):
    """Wet / dry intensity ratio I'/I of the water-film model before clipping and the noise floor.

    ``((1 - f) rho + f t / theta) / rho`` with ``f = clip(water_height_mm / pavement_depth, 0, 1)`` and t the
    Fresnel film term (module docstring). Vectorised over theta and rho.

    Args:
        theta: incidence angle from the ground normal (rad).
        rho: ground reflectivity in (0, 1].
        water_height_mm, pavement_depth: film height and pavement texture depth, both in millimetres (the
            model's unit, Hahner et al. 2022); ``water_height`` is the deprecated name of the former.
    """
    water_height_mm = legacy_water_height(water_height_mm, water_height)
    f = float(np.clip(float(water_height_mm) / float(pavement_depth), 0.0, 1.0))
    rho = np.asarray(rho, dtype=np.float64)
    return fresnel_film(theta, rho, f, n_air, n_water) / rho


def _plane_ransac(points: np.ndarray, seed, iterations: int, threshold: float, min_normal_z: float):
    """(unit normal with n_z >= 0, offset h) of the plane n.x + h = 0 with most inliers, refined by SVD."""
    g = rng(seed, 0)
    n = len(points)
    best, best_count = None, -1
    for _ in range(iterations):
        p = points[g.choice(n, 3, replace=False)]
        nrm = np.cross(p[1] - p[0], p[2] - p[0])
        ln = np.linalg.norm(nrm)
        if ln == 0:
            continue
        nrm = nrm / ln
        if nrm[2] < 0:
            nrm = -nrm
        if nrm[2] < min_normal_z:     # only near-horizontal planes can be ground
            continue
        h = -nrm @ p[0]
        count = int(np.count_nonzero(np.abs(points @ nrm + h) < threshold))
        if count > best_count:
            best, best_count = (nrm, h), count
    if best is None:
        return np.array([0.0, 0.0, 1.0]), -float(np.median(points[:, 2]))
    nrm, h = best
    inl = points[np.abs(points @ nrm + h) < threshold]
    if len(inl) >= 3:
        c = inl.mean(axis=0)
        nrm = np.linalg.svd(inl - c, full_matrices=False)[2][-1]
        if nrm[2] < 0:
            nrm = -nrm
        h = -nrm @ c
    return nrm, float(h)


def ground_points(cloud: PointCloud, seed=0, *, classes=GROUND_CLASSES, ransac_iterations: int = 100,
                  ransac_threshold: float = 0.1, band: float = 0.5, min_normal_z: float = 0.8
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Ground mask and ground normal of a cloud.

    With labels (any label > 0): points whose label is in ``classes``, normal (0, 0, 1) (flat earth).
    Without: a RANSAC plane (``ransac_iterations`` tries, inliers within ``ransac_threshold`` m, normals
    with n_z >= ``min_normal_z``), refined by least squares; ground = points within ``band`` m of it.

    Returns:
        mask (N,) bool and normal (3,).
    """
    if np.any(cloud.labels > 0):
        return np.isin(cloud.labels, np.asarray(classes)), np.array([0.0, 0.0, 1.0])
    if len(cloud) < 3:
        return np.zeros(len(cloud), dtype=bool), np.array([0.0, 0.0, 1.0])
    nrm, h = _plane_ransac(cloud.points, seed, ransac_iterations, ransac_threshold, min_normal_z)
    return np.abs(cloud.points @ nrm + h) < band, nrm


def _line(x, y):
    if len(x) >= 2 and np.ptp(x) > 0:
        a, b = np.polyfit(x, y, 1)
        return float(a), float(b)
    return 0.0, float(np.mean(y)) if len(y) else 0.0


def laser_parameters(distance, cos_theta, intensity, *, power_factor: float = 15.0, noise_floor: float = 0.7,
                     bins=(10.0, 70.0, 50)) -> tuple[tuple[float, float], tuple[float, float]]:
    """Fits of the emitted power and the noise floor from ground returns (Hahner et al. 2022).

    Returns:
        (a, b) with ``P_out(d) = a d + b`` (power factor included) and (c, e) with noise floor
        ``N(d) = c d + e`` (scale ``noise_floor`` included).
    """
    d = np.asarray(distance, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.asarray(intensity, dtype=np.float64) / np.asarray(cos_theta, dtype=np.float64)
    ok = np.isfinite(y)
    d, y = d[ok], y[ok]
    a, b = _line(d, y)
    lo, hi, nb = bins
    edges = np.linspace(lo, hi, int(nb) + 1)
    which = np.digitize(d, edges) - 1
    inside = (which >= 0) & (which < nb) & (y > 0)
    mins = np.full(int(nb), np.inf)
    np.minimum.at(mins, which[inside], y[inside])
    filled = np.isfinite(mins)
    if np.count_nonzero(filled) >= 2:
        centres = 0.5 * (edges[:-1] + edges[1:])
        c, e = _line(centres[filled], mins[filled])
        # lower the line under every bin's minimum: the floor must not cut into dry returns
        e -= max(0.0, float(np.max(c * centres[filled] + e - mins[filled])))
    else:
        pos = y[y > 0]
        c, e = 0.0, float(pos.min()) if len(pos) else 0.0
    return (power_factor * a, power_factor * b), (noise_floor * c, noise_floor * e)


def ground_geometry(cloud, seed, ground, normal):
    """(ground mask, cos theta of every point (N,), ranges (N,))."""
    if ground is None:
        mask, nrm = ground_points(cloud, seed)
    else:
        mask = np.asarray(ground, dtype=bool).reshape(-1)
        if mask.shape != (len(cloud),):
            raise ValueError(f"ground mask must have one entry per point ({len(cloud)}), got {mask.shape}")
        nrm = np.array([0.0, 0.0, 1.0])
    if normal is not None:
        nrm = np.asarray(normal, dtype=np.float64)
        if nrm.shape not in ((3,), (len(cloud), 3)):
            raise ValueError(f"normal must be (3,) or ({len(cloud)}, 3), got {nrm.shape}")
    nrm = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
    _, u, r = rays(cloud)
    cos_t = np.abs(np.sum(u * nrm, axis=-1)) if nrm.ndim == 2 else np.abs(u @ nrm)
    return mask, np.clip(cos_t, 0.0, 1.0), r


def wet_arrays(cloud, water_height_mm, seed, backend, ground, normal, p_out, noise_level, pavement_depth,
               power_factor, noise_floor, n_air, n_water):
    """(new intensity (N,), keep (N,), ground mask (N,)) behind ``wet_ground``."""
    n = len(cloud)
    f = float(np.clip(water_height_mm / pavement_depth, 0.0, 1.0))
    mask, cos_t, r = ground_geometry(cloud, seed, ground, normal)
    inten = cloud.intensity.astype(np.float64)
    keep = np.ones(n, dtype=bool)
    out = inten.copy()
    if f == 0.0 or not mask.any():
        return out, keep, mask
    gi = np.nonzero(mask)[0]
    (a, b), (c, e) = laser_parameters(r[gi], cos_t[gi], inten[gi], power_factor=power_factor,
                                      noise_floor=noise_floor)
    po = a * r[gi] + b if p_out is None else np.broadcast_to(np.asarray(p_out, dtype=np.float64), (n,))[gi]
    nl = c * r[gi] + e if noise_level is None else \
        np.broadcast_to(np.asarray(noise_level, dtype=np.float64), (n,))[gi]
    new, kp = kernels(backend).wet_ground_points(inten[gi], cos_t[gi], po, nl, f, n_air, n_water, 0.05, 1.0)
    out[gi] = new
    keep[gi] = np.asarray(kp, dtype=bool)
    return out, keep, mask


def wet_ground(cloud: PointCloud, water_height_mm: float = 1.0, seed=0, backend=None, *, ground=None, normal=None,
               p_out=None, noise_level=None, pavement_depth: float = 1.2, power_factor: float = 15.0,
               noise_floor: float = 0.7, n_air: float = 1.0003, n_water: float = 1.33,
               water_height=None) -> PointCloud:
    """Wet ground (Hahner et al. 2022): a water film dims ground returns and drops those below the noise floor.

    Args:
        cloud: the dry frame; incidence angles are taken along origin -> point.
        water_height_mm: film height h_w in millimetres (not metres: the model's unit); the paper uses 1.0.
            ``water_height`` is its deprecated name.
        seed: seeds the RANSAC plane fit (used only for clouds without labels).
        backend: backend name or instance (None: current default).
        ground: optional (N,) bool ground mask instead of labels / RANSAC.
        normal: ground normal, (3,) or one per point (N, 3), instead of the default.
        p_out, noise_level: emitted power and noise floor (scalars or (N,)) instead of the fits.
        pavement_depth: mm; power_factor, noise_floor: the fits' scales (15 and 0.7).

    Returns:
        A new PointCloud without the dropped points; other ground points dimmed, the rest unchanged.
    """
    cloud = check_cloud(cloud, "wet_ground")
    water_height_mm = check_range("water_height_mm", legacy_water_height(water_height_mm, water_height), lo=0.0)
    check_range("pavement_depth", pavement_depth, lo=0.0, lo_open=True)
    out, keep, _ = wet_arrays(cloud, water_height_mm, seed, backend, ground, normal, p_out, noise_level,
                               pavement_depth, power_factor, noise_floor, n_air, n_water)
    if keep.all() and np.array_equal(out, cloud.intensity.astype(np.float64)):
        return cloud.copy()
    res = cloud.copy(intensity=out.astype(np.float32))
    return res if keep.all() else res.subset(keep)
