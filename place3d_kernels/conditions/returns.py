"""Per-ray LiDAR returns in a mesh under a condition: ``lidar_returns``.

``model="analytic"`` casts the rays with ``place3d_kernels.raycast``, gives each hit the Lambertian
intensity of the simulator (class reflectivity x |cos incidence|, ``place3d_kernels.simulate``) and runs
the point-cloud condition model on the hits, so its returns agree with ``fog`` / ``wet_ground``.

Powers are received power over C_A P0 in the convention of Hahner et al.'s point model, where a point's
intensity I acts as its gain: a surface at R0 returns ``P_hard = I beta_0 T / R0^2`` (T the condition's
factor: exp(-2 alpha R0) in fog, I'/I on wet ground; beta_0 = Gamma / pi) and fog returns its peak
backscatter ``P_fog = I beta i(R0)``; the stronger one is the return (kind 2 for fog), and the reported
intensity is ``P R0^2 / beta_0`` (fog intensities clipped to 1, as in ``fog``). A ray that hits nothing
has no return (kind 0); its ``fog_power`` is the backscatter for unit gain, ``beta i(t_max)``.

``model="mitsuba"`` renders the same quantities with Mitsuba 3 (``mitsuba_returns``).
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.classes import REFLECTIVITY
from place3d_kernels.conditions._common import rng
from place3d_kernels.conditions.return_types import FOG, NONE, SURFACE, Returns
from place3d_kernels.pointcloud import PointCloud

__all__ = ["lidar_returns", "Returns", "NONE", "SURFACE", "FOG"]

_CONDITIONS = (None, "clear", "fog", "wet_ground")


def _raycast(mesh, origins, directions, t_max, backend):
    """(t, face) of the closest hits; a seam the tests can replace."""
    from place3d_kernels.ops import raycast

    hits = raycast(mesh, origins, directions, t_max, backend=backend)
    return hits.t, hits.face


def _face_normals(mesh) -> np.ndarray:
    n = getattr(mesh, "normals", None)
    if n is not None:
        return np.asarray(n, dtype=np.float64)
    v, f = mesh.vertices, mesh.faces
    c = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-300)


def lidar_returns(mesh, origins, directions, condition: str | None = None, model: str = "analytic", *,
                  t_max=np.inf, seed=0, backend=None, reflectivity=None, **params) -> Returns:
    """Per-ray returns of LiDAR beams in a mesh, clear or under fog / wet ground.

    Args:
        mesh: a ``place3d_kernels.Mesh`` (face labels pick the reflectivity).
        origins, directions: (N, 3) rays (origins may be one (3,) point).
        condition: None (clear), "fog" or "wet_ground".
        model: "analytic" (raycast + the point models) or "mitsuba" (Mitsuba 3; needs the extra).
        t_max: maximum range (scalar or (N,)).
        seed: seeds the condition's random draws.
        backend: backend for the raycast and the condition kernels (analytic model).
        reflectivity: per-class reflectivity table (default ``place3d_kernels.classes.REFLECTIVITY``).
        **params: the condition's parameters (fog: alpha, beta, noise, sensor; wet_ground: water_height_mm, ...).
    """
    if condition not in _CONDITIONS:
        raise ValueError(f"lidar_returns supports condition in {list(_CONDITIONS)}, got {condition!r}")
    if condition == "clear":
        condition = None
    if model == "mitsuba":
        from place3d_kernels.conditions.mitsuba_returns import mitsuba_lidar_returns

        if "water_height_mm" in params:         # mitsuba_returns still takes the unit-less name (also mm)
            params["water_height"] = params.pop("water_height_mm")

        return mitsuba_lidar_returns(mesh, origins, directions, condition, t_max=t_max, seed=seed,
                                     reflectivity=reflectivity, **params)
    if model != "analytic":
        raise ValueError(f"model must be 'analytic' or 'mitsuba', got {model!r}")
    from place3d_kernels.ops import check_rays

    o, d, tm = check_rays(origins, directions, t_max, "t_max")
    t, face = _raycast(mesh, o, d, tm, backend)
    t = np.asarray(t, dtype=np.float64)
    face = np.asarray(face, dtype=np.int64)
    n = len(o)
    hit = face >= 0
    refl = REFLECTIVITY if reflectivity is None else np.asarray(reflectivity, dtype=np.float64)
    label = np.where(hit, np.asarray(mesh.labels)[np.clip(face, 0, None)], -1).astype(np.int32)
    normals = _face_normals(mesh)[np.clip(face, 0, None)]
    cos = np.abs(np.einsum("ij,ij->i", normals, d))
    inten = np.where(hit, refl[np.clip(label, 0, len(refl) - 1)] * cos, 0.0)

    rng_ = np.full(n, np.inf)
    out_i = np.zeros(n)
    hard = np.zeros(n)
    fogp = np.zeros(n)
    kind = np.zeros(n, dtype=np.int8)
    hi = np.nonzero(hit)[0]
    cloud = PointCloud(o[hi] + d[hi] * t[hi, None], label[hi], inten[hi], o[hi])
    r0 = t[hi]
    i0 = cloud.intensity.astype(np.float64)

    if condition == "fog":
        from place3d_kernels.conditions.fog import FOG_ALPHAS, FogSensor, fog_arrays, fog_lookup

        sensor = params.pop("sensor", FogSensor())
        alpha = params.pop("alpha", None)
        if alpha is None:
            alpha = float(FOG_ALPHAS[int(rng(seed, 0).integers(len(FOG_ALPHAS)))])
        beta = float(params.pop("beta", 0.05))
        noise = float(params.pop("noise", 10.0))
        intensity_max = float(params.pop("intensity_max", 1.0))
        _reject(params)
        table = fog_lookup(alpha, sensor.tau_h, sensor.r1, sensor.r2)
        if len(hi):
            pts, new_i, is_fog, _ = fog_arrays(cloud, alpha, beta, seed, backend, noise, sensor, intensity_max)
            rng_[hi] = np.linalg.norm(pts - o[hi], axis=1)
            out_i[hi] = new_i
            kind[hi] = np.where(is_fog, FOG, SURFACE)
            hard[hi] = i0 * sensor.beta_0 * np.exp(-2.0 * alpha * r0) / (r0 * r0)
            fogp[hi] = i0 * beta * table.lookup(r0)[0]
        miss = ~hit
        fogp[miss] = beta * table.lookup(np.minimum(tm[miss], table.r0[-1]))[0]
    elif condition == "wet_ground":
        from place3d_kernels.conditions.fog import FogSensor
        from place3d_kernels.conditions.wet_ground import legacy_water_height, wet_arrays

        water_height = float(legacy_water_height(params.pop("water_height_mm", 1.0), params.pop("water_height", None)))
        kw = dict(ground=None, normal=normals[hi], p_out=None, noise_level=None, pavement_depth=1.2,
                  power_factor=15.0, noise_floor=0.7, n_air=1.0003, n_water=1.33)
        for key in list(params):
            if key in kw:
                kw[key] = params.pop(key)
        _reject(params)
        if len(hi):
            new_i, keep, _ = wet_arrays(cloud, water_height, seed, backend, kw["ground"], kw["normal"],
                                         kw["p_out"], kw["noise_level"], kw["pavement_depth"], kw["power_factor"],
                                         kw["noise_floor"], kw["n_air"], kw["n_water"])
            kept = hi[keep]
            rng_[kept] = r0[keep]
            out_i[kept] = new_i[keep]
            kind[kept] = SURFACE
            hard[kept] = new_i[keep] * FogSensor().beta_0 / (r0[keep] ** 2)
    else:
        _reject(params)
        from place3d_kernels.conditions.fog import FogSensor

        rng_[hi] = r0
        out_i[hi] = i0
        kind[hi] = SURFACE
        hard[hi] = i0 * FogSensor().beta_0 / (r0 * r0)
    return Returns(rng_, out_i, hard, fogp, kind, label)


def _reject(params: dict) -> None:
    if params:
        raise TypeError(f"unexpected condition parameters {sorted(params)} for lidar_returns")
