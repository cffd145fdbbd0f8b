"""The Mitsuba 3 return model (``lidar_returns(..., model="mitsuba")``) against the analytic models.

Skipped when Mitsuba 3 (``pip install 'place3d-kernels[mitsuba]'``) or a libLLVM >= 16 for its
``llvm_ad_rgb`` variant is missing.
"""

from __future__ import annotations


import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels import conditions as C
from place3d_kernels.classes import REFLECTIVITY

try:
    from place3d_kernels.conditions.mitsuba_returns import import_mitsuba

    import_mitsuba("llvm_ad_rgb")
except ImportError as e:  # pragma: no cover - depends on the machine
    pytest.skip(f"Mitsuba 3 is not usable here: {e}", allow_module_level=True)

SENSOR = np.array([0.0, 0.0, 2.0])


def _wall(dist):
    """A wall (class 11) facing the sensor at x = dist."""
    v = np.array([[dist, -60, -30], [dist, 60, -30], [dist, 60, 40], [dist, -60, 40]], dtype=float)
    return p3k.Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), labels=[11, 11])


def _road():
    v = np.array([[-300, -300, 0], [300, -300, 0], [300, 300, 0], [-300, 300, 0]], dtype=float)
    return p3k.Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), labels=[7, 7])


@pytest.mark.parametrize("alpha", [0.02, 0.06])
def test_two_way_fog_transmittance(alpha):
    mor = C.mor(alpha)
    o = np.array([SENSOR] * 3)
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.3, 0.1], [1.0, -0.2, -0.05]])
    for dist in [5.0, mor / 8, mor / 4, mor / 2]:
        mesh = _wall(dist)
        clear = C.lidar_returns(mesh, o, d, model="mitsuba")
        foggy = C.lidar_returns(mesh, o, d, "fog", model="mitsuba", alpha=alpha, beta=0.0, seed=2)
        assert np.all(clear.kind == 1) and np.all(foggy.kind == 1)
        np.testing.assert_allclose(foggy.range, clear.range, rtol=1e-6)
        two_way = foggy.hard_power / clear.hard_power
        np.testing.assert_allclose(two_way, np.exp(-2 * alpha * clear.range), rtol=0.03)
        np.testing.assert_allclose(foggy.intensity / clear.intensity, two_way, rtol=1e-6)


def test_mitsuba_matches_the_analytic_surface_model():
    mesh = _wall(25.0)
    g = np.random.default_rng(0)
    d = np.column_stack([np.ones(200), g.uniform(-1, 1, 200), g.uniform(-0.5, 0.5, 200)])
    o = np.broadcast_to(SENSOR, d.shape)
    ana = C.lidar_returns(mesh, o, d, backend="reference")
    mit = C.lidar_returns(mesh, o, d, model="mitsuba")
    np.testing.assert_array_equal(mit.kind, ana.kind)
    np.testing.assert_array_equal(mit.label, ana.label)
    np.testing.assert_allclose(mit.range, ana.range, rtol=1e-5)
    np.testing.assert_allclose(mit.intensity, ana.intensity, rtol=1e-4)
    # in thick fog the far wall turns into fog returns in both models
    a = C.lidar_returns(mesh, o, d, "fog", backend="reference", alpha=0.06, seed=5)
    m = C.lidar_returns(mesh, o, d, "fog", model="mitsuba", alpha=0.06, seed=5)
    np.testing.assert_array_equal(m.kind, a.kind)
    assert np.all(a.kind == 2)


def _fresnel_unpolarised(cos_i, n1, n2):
    """Unpolarised power reflectance (R_s + R_p) / 2 of an n1 -> n2 interface (1 beyond the critical angle)."""
    sin_t = np.sqrt(np.clip(1.0 - cos_i * cos_i, 0.0, 1.0)) * n1 / n2
    cos_t = np.sqrt(np.clip(1.0 - sin_t * sin_t, 0.0, 1.0))
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return np.where(sin_t < 1.0, 0.5 * (rs * rs + rp * rp), 1.0)


def test_wet_road_ratio_follows_film_transmission():
    """Wet/dry road returns at 60-85 deg incidence against the analytic film model: within 6 %, not 5 %.

    Mitsuba renders the wet road as ``blendbsdf`` of weight f = h_w / 1.2 mm between the dry diffuse base
    and ``roughplastic`` (a smooth-ish water interface, n = 1.33, over a diffuse base of the same rho) in
    Mitsuba's default colour-preserving mode (``nonlinear=False``). Its monostatic film term is
    ``rho T(theta)^2 / (n^2 (1 - F_int))``: unpolarised Fresnel transmission in and out, the 1/n^2 of
    light leaving the denser water, and the cosine-weighted hemispherical internal reflectance F_int of the
    water/air interface, but ``1 - F_int`` where the physical layered surface (Lekner & Dorf 1988, Appl.
    Opt. 27(7)) has ``1 - rho F_int``; checked below at three reflectivities. The analytic film term is
    ``max_{s,p}[T_aw rho T_wa / (1 - rho R_wa(theta_w))] / theta``: the larger polarisation, internal
    reflection at the refracted angle only, no 1/n^2, and a division by the incidence angle in radians.
    The wet/dry ratios differ by up to 5.5 % (72.5-75 deg, road reflectivity 0.12), hence the 6 % bound.

    Measured alternatives (2026-11-22): Beckmann/GGX roughness 0.001-0.5 (5.35 % at best, far worse above
    0.05), smooth ``plastic`` 6.7 %, ``pplastic`` unpolarised -5.4 % (Mitsuba calls it ad hoc), a
    p-polarised laser (no change: the diffuse coating depolarises), and the physical layered surface
    (``nonlinear=True``) about -36 %. Meeting 5 % would mean writing the formula's 1/theta into the
    rendered radiance, which would make the comparison circular; that is not done.
    """
    mesh = _road()
    theta = np.radians(np.arange(60.0, 85.1, 2.5))
    d = np.column_stack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)])
    o = np.broadcast_to(SENSOR, d.shape)
    dry = C.lidar_returns(mesh, o, d, model="mitsuba")
    wet = C.lidar_returns(mesh, o, d, "wet_ground", model="mitsuba", water_height=1.0)
    assert np.all(dry.kind == 1) and np.all(wet.kind == 1)
    ratio = wet.intensity / dry.intensity
    want = C.film_transmission(theta, 0.12, 1.0)
    np.testing.assert_allclose(ratio, want, rtol=0.06)
    assert np.all(ratio < 1.0) and np.all(np.diff(ratio) < 0)      # darker, and more so at grazing incidence
    # the rendered film term, independently of the formula under test and at any reflectivity: Mitsuba
    # evaluates F_int with a fitted approximation, 1.4 % off the integral below, hence rtol 2 %
    f, n_air, n_water = 1.0 / 1.2, 1.0003, 1.33
    mu = (np.arange(20000) + 0.5) / 20000                                   # midpoint rule over cos
    f_int = np.mean(2.0 * mu * _fresnel_unpolarised(mu, n_water, n_air))
    film = (1.0 - _fresnel_unpolarised(np.cos(theta), n_air, n_water)) ** 2 / ((n_water / n_air) ** 2 * (1 - f_int))
    for rho in (0.05, 0.12, 0.5):
        refl = np.array(REFLECTIVITY, dtype=float)
        refl[7] = rho
        dry = C.lidar_returns(mesh, o, d, model="mitsuba", reflectivity=refl)
        wet = C.lidar_returns(mesh, o, d, "wet_ground", model="mitsuba", water_height=1.0, reflectivity=refl)
        np.testing.assert_allclose((wet.intensity / dry.intensity - (1.0 - f)) / f, film, rtol=0.02)
