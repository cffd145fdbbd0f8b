"""LiDAR returns rendered with Mitsuba 3: ``lidar_returns(..., model="mitsuba")``.

Imported only when that model is asked for; needs ``pip install 'place3d-kernels[mitsuba]'`` and, for the
default ``llvm_ad_rgb`` variant, a system libLLVM >= 16 (Dr.Jit's LLVM backend; e.g. Debian 12:
``apt-get install libllvm19``). Older LLVM builds abort the process inside Dr.Jit, so this module picks a
recent one through ``DRJIT_LIBLLVM_PATH`` before Dr.Jit starts, or refuses with that instruction.

The model, per ray (one Mitsuba wavefront over all rays):

* geometry: ``scene.ray_intersect`` on the mesh (Embree on the LLVM variant), two-sided BSDFs;
* surface return: ``pi * bsdf.eval(wi, wo = wi)``, the monostatic BSDF value times cos; a diffuse surface
  of the class reflectivity rho gives ``rho |cos theta|`` as the analytic model;
* wet ground: ground classes get ``blendbsdf`` by film fraction ``f = clip(h_w / 1.2 mm, 0, 1)`` of the dry
  diffuse base and a rough dielectric (water, n = 1.33 in air 1.0003, Beckmann roughness) over that base
  (Mitsuba's ``roughplastic`` in its default colour-preserving mode, ``nonlinear=False``). Its monostatic
  film term is ``rho T(theta)^2 / (n^2 (1 - F_int))`` (unpolarised Fresnel in and out, hemispherical
  internal reflectance F_int ~ 0.47); the physical layered surface (Lekner & Dorf 1988) would have
  ``1 - rho F_int`` and is about 36 % darker than Hahner's formula. The analytic ``film_transmission``
  uses the larger polarisation, the internal reflection at the refracted angle, no 1/n^2 and an empirical
  1 / theta, so the two wet/dry ratios agree only to ~5.5 % at 60-85 deg (see
  ``tests/test_conditions_mitsuba.py`` for the alternatives measured). No factor is fitted to close that gap;
* fog: a homogeneous medium with ``sigma_t = alpha``; the hard return's two-way transmittance is the
  survival fraction of ``spp`` stratified free-flight samples (``medium.sample_interaction``) over 2 R0.
  The fog backscatter peak is Hahner et al.'s soft-target integral (``fog_lookup``), which a radiance
  renderer does not resolve in time; the return is the stronger of the two, as in the analytic model,
  with the same range noise for a fog return.

Powers follow the analytic model's convention (``returns.py``).
"""

from __future__ import annotations

import glob
import os
import re

import numpy as np

from place3d_kernels.classes import GROUND_CLASSES, REFLECTIVITY
from place3d_kernels.conditions._common import rng
from place3d_kernels.conditions.return_types import FOG, NONE, SURFACE, Returns

__all__ = ["mitsuba_lidar_returns", "import_mitsuba"]

INSTALL = "pip install 'place3d-kernels[mitsuba]'"
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib", "/usr/local/lib",
             "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")


def _llvm_candidates() -> list[tuple[int, str]]:
    found = []
    for d in _LIB_DIRS:
        for p in glob.glob(os.path.join(d, "libLLVM*")) + glob.glob(os.path.join(d, "llvm-*", "lib", "libLLVM*")):
            m = re.search(r"libLLVM(?:-|\.so\.|\.)(\d+)", os.path.basename(p))
            if m and (p.endswith(".so") or ".so." in p or p.endswith(".dylib")):
                found.append((int(m.group(1)), p))
    return sorted(found, reverse=True)


def import_mitsuba(variant: str = "llvm_ad_rgb"):
    """Import Mitsuba 3 with a JIT variant; raise ImportError naming the install command otherwise."""
    import importlib.util

    for mod in ("mitsuba", "drjit"):
        try:
            missing = importlib.util.find_spec(mod) is None
        except (ImportError, ValueError):   # a module set to None in sys.modules
            missing = True
        if missing:
            raise ImportError(f"model='mitsuba' needs Mitsuba 3 and Dr.Jit ({mod} is not installed); install them "
                              f"with: {INSTALL}")
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        cands = _llvm_candidates()
        if cands and cands[0][0] >= 16:
            os.environ["DRJIT_LIBLLVM_PATH"] = cands[0][1]
        elif cands:
            raise ImportError(f"Mitsuba's {variant} variant needs libLLVM >= 16; found only LLVM {cands[0][0]} "
                              f"({cands[0][1]}). Install a newer one (Debian 12: apt-get install libllvm19) or set "
                              f"DRJIT_LIBLLVM_PATH.")
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:
        raise ImportError(f"model='mitsuba' needs Mitsuba 3 and Dr.Jit ({e}); install them with: {INSTALL}") from None
    current = mi.variant()
    if current is None or current != variant:
        if variant not in mi.variants():
            raise ImportError(f"Mitsuba variant {variant!r} is not available; this build has {mi.variants()}")
        mi.set_variant(variant)
    return mi, dr


def _shape(mi, dr, name, verts, faces, bsdf):
    props = mi.Properties()
    props["bsdf"] = bsdf
    m = mi.Mesh(name, len(verts), len(faces), props=props, has_vertex_normals=False, has_vertex_texcoords=False)
    p = mi.traverse(m)
    v = np.ascontiguousarray(verts, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    p["vertex_positions"] = dr.ravel(mi.Point3f(v[:, 0], v[:, 1], v[:, 2]))
    p["faces"] = dr.ravel(mi.Vector3u(f[:, 0], f[:, 1], f[:, 2]))
    p.update()
    return m


def _bsdf(mi, rho, wet_fraction, roughness, n_air, n_water):
    base = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(rho)] * 3}}
    if wet_fraction > 0:
        film = {"type": "roughplastic", "distribution": "beckmann", "alpha": float(roughness),
                "int_ior": float(n_water), "ext_ior": float(n_air),
                "diffuse_reflectance": {"type": "rgb", "value": [float(rho)] * 3}}
        base = {"type": "blendbsdf", "weight": float(wet_fraction), "dry": base, "wet": film}
    return mi.load_dict({"type": "twosided", "material": base})


def mitsuba_lidar_returns(mesh, origins, directions, condition=None, *, t_max=np.inf, seed=0, reflectivity=None,
                          variant: str = "llvm_ad_rgb", spp: int = 1024, alpha=None, beta: float = 0.05,
                          sensor=None, noise: float = 10.0, intensity_max: float = 1.0, water_height: float = 1.0,
                          pavement_depth: float = 1.2, roughness: float = 0.01, ground_classes=GROUND_CLASSES,
                          n_air: float = 1.0003, n_water: float = 1.33) -> Returns:
    """Per-ray returns rendered with Mitsuba 3 (module docstring). Same outputs as ``lidar_returns``."""
    from place3d_kernels.conditions.fog import FOG_ALPHAS, FogSensor, fog_lookup
    from place3d_kernels.ops import check_rays

    if condition not in (None, "fog", "wet_ground"):
        raise ValueError(f"the mitsuba model supports condition None, 'fog' or 'wet_ground', got {condition!r}")
    mi, dr = import_mitsuba(variant)
    o, d, tm = check_rays(origins, directions, t_max, "t_max")
    n = len(o)
    refl = REFLECTIVITY if reflectivity is None else np.asarray(reflectivity, dtype=np.float64)
    f_wet = float(np.clip(water_height / pavement_depth, 0.0, 1.0)) if condition == "wet_ground" else 0.0
    shift = mesh.shift                                 # float64 shift before float32, as the raycast does
    shapes = {}
    for lab in np.unique(mesh.labels):
        sel = mesh.faces[mesh.labels == lab]
        used, inv = np.unique(sel, return_inverse=True)
        wet = f_wet if int(lab) in tuple(ground_classes) else 0.0
        bsdf = _bsdf(mi, refl[min(int(lab), len(refl) - 1)], wet, roughness, n_air, n_water)
        shapes[f"label_{int(lab)}"] = _shape(mi, dr, f"label_{int(lab)}", mesh.vertices[used] - shift,
                                             inv.reshape(-1, 3), bsdf)
    label_of = {f"label_{int(lab)}": int(lab) for lab in np.unique(mesh.labels)}
    scene = mi.load_dict({"type": "scene", **shapes})
    oo = (o - shift).astype(np.float32)
    dd = d.astype(np.float32)
    ray = dr.zeros(mi.Ray3f, n)
    ray.o = mi.Point3f(oo[:, 0], oo[:, 1], oo[:, 2])
    ray.d = mi.Vector3f(dd[:, 0], dd[:, 1], dd[:, 2])
    ray.maxt = mi.Float(np.minimum(tm, 1e7).astype(np.float32))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    val = si.bsdf(ray).eval(mi.BSDFContext(), si, si.wi, valid)
    hit = np.array(valid, dtype=bool)
    t = np.where(hit, np.array(si.t, dtype=np.float64), np.inf)
    inten = np.where(hit, np.pi * np.array(val[0], dtype=np.float64), 0.0)
    label = np.full(n, -1, dtype=np.int32)
    if hit.any():
        # identify the shape hit through a per-shape ray cast: cheap, shapes are few (one per label)
        for name, shp in shapes.items():
            sub = mi.load_dict({"type": "scene", name: shp})
            si_s = sub.ray_intersect(ray)
            t_s = np.where(hit, np.array(si_s.t, dtype=np.float64), 0.0)
            same = np.array(si_s.is_valid(), dtype=bool) & hit & \
                (np.abs(t_s - np.where(hit, t, 0.0)) <= 1e-6 * np.maximum(np.where(hit, t, 0.0), 1.0))
            label[same & (label < 0)] = label_of[name]

    rng_ = np.where(hit, t, np.inf)
    out_i = inten.copy()
    kind = np.where(hit & (inten > 0), SURFACE, NONE).astype(np.int8)
    rng_[kind == NONE] = np.inf
    out_i[kind == NONE] = 0.0
    sensor = FogSensor() if sensor is None else sensor
    hard = np.where(kind == SURFACE, inten * sensor.beta_0 / np.where(hit, t * t, 1.0), 0.0)
    fogp = np.zeros(n)
    if condition == "fog":
        if alpha is None:
            alpha = float(FOG_ALPHAS[int(rng(seed, 0).integers(len(FOG_ALPHAS)))])
        medium = mi.load_dict({"type": "homogeneous", "sigma_t": float(alpha), "albedo": 0.0})
        table = fog_lookup(alpha, sensor.tau_h, sensor.r1, sensor.r2)
        hi = np.nonzero(kind == SURFACE)[0]
        tr2 = np.ones(n)
        if len(hi) and alpha > 0:
            g = rng(seed, 3)
            u = (np.arange(spp)[None, :] + g.random((len(hi), 1))) / spp            # stratified per ray
            mray = dr.zeros(mi.Ray3f, len(hi) * spp)
            mray.o = mi.Point3f(0.0, 0.0, 0.0)
            mray.d = mi.Vector3f(1.0, 0.0, 0.0)
            mray.maxt = mi.Float(np.inf)
            mei = medium.sample_interaction(mray, mi.Float(u.reshape(-1).astype(np.float32)), mi.UInt32(0), True)
            free = np.array(mei.t, dtype=np.float64).reshape(len(hi), spp)
            tr2[hi] = np.mean(free > 2.0 * t[hi, None], axis=1)                   # two-way: survive 2 R0
        r0 = t[hi]
        hard[hi] = inten[hi] * tr2[hi] * sensor.beta_0 / (r0 * r0)
        fogp[hi] = inten[hi] * beta * table.lookup(r0)[0]
        fogp[~hit] = beta * table.lookup(np.minimum(tm[~hit], table.r0[-1]))[0]
        is_fog = fogp[hi] > hard[hi]
        uni = rng(seed, 1).random(n)[hi]
        uu = np.maximum(r0 + noise * (2.0 * uni - 1.0), 0.5 * r0)
        d_fog = table.lookup(r0)[1] * r0 / uu
        rng_[hi] = np.where(is_fog, d_fog, r0)
        out_i[hi] = np.where(is_fog, np.minimum(inten[hi] * beta * table.lookup(r0)[0] * r0 * r0 / sensor.beta_0,
                                                intensity_max), inten[hi] * tr2[hi])
        kind[hi] = np.where(is_fog, FOG, SURFACE)
    return Returns(rng_, out_i, hard, fogp, kind, label)
