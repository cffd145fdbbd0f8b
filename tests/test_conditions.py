"""Adverse conditions: the models' definitions, checked on seeded clouds, on every backend.

Each condition is checked against what its model says (thresholds derived from the model, Fresnel
values worked out independently here, statistics of large seeded clouds), for determinism and purity,
and for agreement of every device backend with the reference.
"""

from __future__ import annotations

import importlib
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels import conditions as C
from place3d_kernels._toml import read_toml
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.conditions_base import ConditionKernels
from place3d_kernels.classes import REFLECTIVITY, VEHICLE
from place3d_kernels.conditions.fog import FogSensor

S = importlib.import_module("place3d_kernels.conditions.snow")  # the package attribute `snow` is the function

ORIGIN = np.array([0.0, 0.0, 2.0])


@pytest.fixture(autouse=True)
def _condition_kernels_only(request):
    """Backends without condition kernels would only rerun the reference (with a warning): skip them."""
    params = getattr(getattr(request.node, "callspec", None), "params", {})
    for key in ("backend", "device_backend"):
        name = params.get(key)
        if name is not None and not isinstance(get_backend(name), ConditionKernels):
            pytest.skip(f"backend {name!r} has no condition kernels (it falls back to the reference)")
CONFIGS = Path(__file__).resolve().parents[1] / "place3d_kernels" / "configs" / "conditions"


def _sphere_cloud(n, r_lo, r_hi, seed=0, labels=None, origin=ORIGIN):
    g = np.random.default_rng(seed)
    d = g.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = g.uniform(r_lo, r_hi, n)
    lab = g.integers(1, 22, n) if labels is None else np.broadcast_to(labels, (n,))
    return p3k.PointCloud(origin + d * r[:, None], lab, g.uniform(0.05, 1.0, n), origin)


def _street(n_ground=20_000, n_other=5_000, seed=0, labels=True):
    """Flat road (z = 0) around a sensor at 2 m, plus building points; Lambertian intensities."""
    g = np.random.default_rng(seed)
    xy = g.uniform(-60, 60, (n_ground, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > 3.0]
    ground = np.column_stack([xy, np.zeros(len(xy))])
    cls = g.choice([7, 6, 8, 13, 21], len(ground), p=[0.6, 0.05, 0.2, 0.1, 0.05])
    cos = np.abs(ORIGIN[2]) / np.linalg.norm(ground - ORIGIN, axis=1)
    i_ground = REFLECTIVITY[cls] * cos * g.uniform(0.8, 1.2, len(ground))
    walls = np.column_stack([g.uniform(-50, 50, n_other), g.choice([-15.0, 15.0], n_other),
                             g.uniform(0.5, 10, n_other)])
    pts = np.vstack([ground, walls])
    lab = np.concatenate([cls, np.full(n_other, 1)]) if labels else np.zeros(len(pts), dtype=int)
    inten = np.concatenate([i_ground, g.uniform(0.1, 0.5, n_other)])
    return p3k.PointCloud(pts, lab, inten, ORIGIN), len(ground)


def _snapshot(cloud):
    return [None if a is None else np.array(a, copy=True)
            for a in (cloud.points, cloud.labels, cloud.intensity, cloud.origins, cloud.scattered)]


def _assert_unchanged(cloud, snap):
    for a, b in zip((cloud.points, cloud.labels, cloud.intensity, cloud.origins, cloud.scattered), snap):
        if b is None:
            assert a is None
        else:
            np.testing.assert_array_equal(a, b)


def _assert_same(a, b):
    _assert_unchanged(a, _snapshot(b))


# ================================================================================================ fog
def test_mor_helpers():
    assert C.mor(0.06) == pytest.approx(math.log(20) / 0.06)
    assert C.alpha_from_mor(C.mor(0.013)) == pytest.approx(0.013)
    assert C.mor(0.0) == math.inf


def _soft_peak_brute(alpha, r0, tau_h=20e-9, r1=0.9, r2=1.0):
    """max over R of the normalised P_soft(R), by direct quadrature on a 1 mm grid (independent of fog_lookup)."""
    c = 299_792_458.0
    t = np.linspace(0.0, 2 * tau_h, 4001)
    best, best_r = 0.0, 0.0
    for R in np.arange(r1, r0 + c * tau_h + 1e-9, 1e-3):
        r = R - c * t / 2
        xi = np.clip((r - r1) / (r2 - r1), 0, 1)
        f = np.sin(np.pi * t / (2 * tau_h)) ** 2 * np.exp(-2 * alpha * r) * xi * (r <= r0)
        f = np.where(r > 0, f / np.where(r > 0, r * r, 1), 0.0)
        val = np.trapezoid(f, t)
        if val > best:
            best, best_r = val, R
    return best, best_r


@pytest.mark.parametrize("alpha, r0", [(0.03, 2.5), (0.06, 30.0)])
def test_fog_lookup_matches_direct_quadrature(alpha, r0):
    table = C.fog_lookup(alpha)
    i, d = table.lookup(r0)
    want_i, want_r = _soft_peak_brute(alpha, r0)
    assert i == pytest.approx(want_i, rel=2e-4)
    shift = 299_792_458.0 * 20e-9 / 2
    assert d == pytest.approx(want_r - shift, abs=2e-3)
    raw = C.fog_lookup(alpha, shift=False)
    assert raw.lookup(r0)[1] == pytest.approx(want_r, abs=2e-3)


def test_fog_lookup_shape_and_cache():
    t = C.fog_lookup(0.02)
    assert t is C.fog_lookup(0.02)                       # computed once, cached
    assert t.step == 0.1 and t.r0[-1] == pytest.approx(200.0) and len(t.i) == 2001
    assert np.all(t.i[t.r0 <= 0.9] == 0)                 # no overlap before R1
    assert np.all(np.diff(t.i) >= -1e-20)                # i grows with R0 ...
    assert np.all(t.i[t.r0 >= 5.0] == t.i[-1])           # ... and is constant past about 5 m
    with pytest.raises(ValueError, match="alpha"):
        C.fog_lookup(-0.1)


def _fog_threshold(alpha, beta):
    """R0 where I_soft = I_hard, from the cached i(R0): bisection on i R0^2 beta/beta_0 - exp(-2 alpha R0)."""
    table = C.fog_lookup(alpha)
    ratio = beta / FogSensor().beta_0

    def g(r):
        return table.lookup(r)[0] * r * r * ratio - math.exp(-2 * alpha * r)

    lo, hi = 5.0, 200.0
    assert g(lo) < 0 < g(hi)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("alpha", [0.005, 0.01, 0.02, 0.03, 0.06])
def test_fog_threshold(backend, alpha):
    beta = 0.05
    cloud = _sphere_cloud(20_000, 0.5, 150.0, seed=1)
    snap = _snapshot(cloud)
    out = C.fog(cloud, alpha, beta, seed=3, backend=backend)
    _assert_unchanged(cloud, snap)
    r_t = _fog_threshold(alpha, beta)
    r0 = cloud.ranges
    far = np.abs(r0 - r_t) > 1e-3
    np.testing.assert_array_equal(out.scattered[far], (r0 > r_t)[far])
    assert out.scattered.sum() > 1000 and (~out.scattered).sum() > 1000
    # no point deleted, labels and origins kept
    assert len(out) == len(cloud)
    np.testing.assert_array_equal(out.labels, cloud.labels)
    np.testing.assert_array_equal(out.origins, cloud.origins)
    # hard targets stay put, dimmed by exp(-2 alpha R0)
    hard = ~out.scattered
    np.testing.assert_array_equal(out.points[hard], cloud.points[hard])
    np.testing.assert_allclose(out.intensity[hard], cloud.intensity[hard] * np.exp(-2 * alpha * r0[hard]),
                               rtol=2e-5)
    # fog returns: on their own ray, at d_fog R0 / u with u in [R0 - 10, R0 + 10], intensity min(I_soft, 1)
    f = out.scattered
    u0 = (cloud.points[f] - ORIGIN) / r0[f, None]
    v = out.points[f] - ORIGIN
    r_new = np.linalg.norm(v, axis=1)
    assert np.all(np.einsum("ij,ij->i", u0, v) > 0)
    assert np.max(np.linalg.norm(np.cross(u0, v / r_new[:, None]), axis=1)) < 1e-6
    i_tab, d_tab = C.fog_lookup(alpha).lookup(r0[f])
    assert np.all(r_new >= d_tab * r0[f] / (r0[f] + 10) * (1 - 1e-5))
    assert np.all(r_new <= d_tab * r0[f] / np.maximum(r0[f] - 10, r0[f] / 2) * (1 + 1e-5))
    i_soft = i_tab * cloud.intensity[f] * r0[f] ** 2 * beta / FogSensor().beta_0
    np.testing.assert_allclose(out.intensity[f], np.minimum(i_soft, 1.0), rtol=2e-5)
    # the noise is uniform: its draws fill the interval
    spread = (d_tab * r0[f] / r_new - r0[f])
    assert spread.min() < -9 and spread.max() > 9


def test_fog_off_changes_nothing(backend):
    cloud = _sphere_cloud(5_000, 0.5, 150.0, seed=2)
    _assert_same(C.fog(cloud, 0.0, 0.0, seed=1, backend=backend), cloud)
    # the kernel itself is the identity for alpha = beta = 0
    k = get_backend(backend)
    r0 = cloud.ranges
    t = C.fog_lookup(0.0)
    r, i, s = k.fog_points(r0, cloud.intensity.astype(float), t.i, t.d, t.step, 0.0, 0.0,
                           np.full(len(r0), 0.5), 10.0, 1.0)
    assert not s.any()
    np.testing.assert_allclose(r, r0, rtol=1e-7)
    np.testing.assert_allclose(i, cloud.intensity, rtol=1e-7)


def test_fog_draws_alpha_from_the_paper_set():
    cloud = _sphere_cloud(2_000, 1.0, 150.0, seed=4)
    by_alpha = {a: C.fog(cloud, a, seed=0, backend="reference") for a in C.FOG_ALPHAS}
    seen = set()
    for seed in range(40):
        out = C.fog(cloud, None, seed=seed, backend="reference")
        match = [a for a, ref in by_alpha.items() if np.array_equal(ref.intensity, out.intensity)]
        assert len(match) == 1
        seen.add(match[0])
    assert seen == set(C.FOG_ALPHAS)


# ================================================================================================ wet ground
def _fresnel_by_hand(theta, n1, n2):
    """Power coefficients from Snell's law and the amplitude Fresnel equations, written out."""
    st = n1 / n2 * math.sin(theta)
    tt = math.asin(st)
    ci, ct = math.cos(theta), math.cos(tt)
    r_s = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
    r_p = (n2 * ci - n1 * ct) / (n2 * ci + n1 * ct)
    t_s = 2 * n1 * ci / (n1 * ci + n2 * ct)
    t_p = 2 * n1 * ci / (n2 * ci + n1 * ct)
    k = n2 * ct / (n1 * ci)
    R_s, R_p, T_s, T_p = r_s ** 2, r_p ** 2, k * t_s ** 2, k * t_p ** 2
    assert R_s + T_s == pytest.approx(1.0) and R_p + T_p == pytest.approx(1.0)   # energy conserved
    return R_s, R_p, T_s, T_p, tt


@pytest.mark.parametrize("theta_deg, rho, h_w", [(60.0, 0.1, 1.0), (80.0, 0.5, 0.6), (85.0, 0.05, 1.2),
                                                  (30.0, 0.9, 2.0)])
def test_film_transmission_by_hand(theta_deg, rho, h_w):
    th = math.radians(theta_deg)
    _, _, Ts_aw, Tp_aw, tw = _fresnel_by_hand(th, 1.0003, 1.33)
    Rs_wa, Rp_wa, Ts_wa, Tp_wa, _ = _fresnel_by_hand(tw, 1.33, 1.0003)
    t = max(Ts_aw * rho * Ts_wa / (1 - rho * Rs_wa), Tp_aw * rho * Tp_wa / (1 - rho * Rp_wa))
    f = min(h_w / 1.2, 1.0)
    want = ((1 - f) * rho + f * t / th) / rho
    assert C.film_transmission(th, rho, h_w) == pytest.approx(want, rel=1e-12)
    assert C.film_transmission(th, rho, 0.0) == pytest.approx(1.0, rel=1e-15)


def test_film_transmission_worked_example():
    # theta = 60 deg, rho = 0.1, h = 1.2 mm (f = 1). Air -> water: sin t = 1.0003/1.33 sin 60 = 0.65135,
    # t = 40.64 deg; R_s = 0.0588, R_p = 0.0042 (T = 1 - R). Water -> air at 40.64 deg has the same
    # R_s, R_p (reciprocity). s: 0.9412^2 * 0.1 / (1 - 0.1 * 0.0588) = 0.08911; p: 0.9958^2 * 0.1 /
    # (1 - 0.1 * 0.0042) = 0.09920; t = 0.09920; I'/I = t / (theta rho) = 0.09920 / (1.0472 * 0.1) = 0.9473.
    assert C.film_transmission(math.radians(60), 0.1, 1.2) == pytest.approx(0.9473, abs=5e-4)
    vec = C.film_transmission(np.radians([60.0, 70.0, 80.0]), np.array([0.1, 0.2, 0.3]), 1.0)
    assert vec.shape == (3,)


def test_wet_ground_zero_water_is_identity(backend):
    cloud, _ = _street(seed=1)
    _assert_same(C.wet_ground(cloud, 0.0, backend=backend), cloud)


def _index_of(sub_points, points):
    """Row of each sub point in points (points unique)."""
    key = {tuple(p): i for i, p in enumerate(points)}
    return np.array([key[tuple(p)] for p in sub_points])


def test_wet_ground_dims_or_drops_ground_only(backend):
    cloud, n_ground = _street(seed=2)
    snap = _snapshot(cloud)
    out = C.wet_ground(cloud, 1.0, backend=backend)
    _assert_unchanged(cloud, snap)
    idx = _index_of(out.points, cloud.points)             # points never move
    ground = np.zeros(len(cloud), dtype=bool)
    ground[:n_ground] = True
    kept = np.zeros(len(cloud), dtype=bool)
    kept[idx] = True
    assert kept[~ground].all()                            # non-ground never dropped ...
    other = ~ground[idx]
    np.testing.assert_array_equal(out.intensity[other], cloud.intensity[idx][other])   # ... nor dimmed
    g = ground[idx]
    assert np.all(out.intensity[g] <= cloud.intensity[idx][g])                         # ground only dimmed
    assert np.mean(out.intensity[g] < cloud.intensity[idx][g] * 0.999) > 0.5
    assert (~kept[ground]).sum() > 0                      # and some dropped at grazing incidence
    np.testing.assert_array_equal(out.labels, cloud.labels[idx])


def test_wet_ground_follows_the_film_model(backend):
    cloud, n_ground = _street(seed=3)
    p_out, noise = 1.5, 0.02                              # rho = I / (cos p_out) stays inside [0.05, 1]
    out = C.wet_ground(cloud, 0.8, backend=backend, p_out=p_out, noise_level=noise)
    idx = _index_of(out.points, cloud.points)
    gi = np.arange(n_ground)
    v = cloud.points[gi] - ORIGIN
    cos = np.abs(v[:, 2]) / np.linalg.norm(v, axis=1)
    inten = cloud.intensity[gi].astype(float)
    rho = inten / (cos * p_out)
    assert rho.min() > 0.05 and rho.max() < 1.0
    want = np.minimum(inten * C.film_transmission(np.arccos(cos), rho, 0.8), inten)
    drop = want < noise * cos
    decided = np.abs(want - noise * cos) > 1e-5 * noise
    kept = np.isin(gi, idx)
    np.testing.assert_array_equal(kept[decided], ~drop[decided])
    pos = np.searchsorted(idx, gi[kept])
    np.testing.assert_allclose(out.intensity[pos], want[kept], rtol=1e-4)


def test_wet_ground_without_labels_fits_the_plane(backend):
    cloud, n_ground = _street(seed=4, labels=False)
    out = C.wet_ground(cloud, 1.0, seed=0, backend=backend)
    idx = _index_of(out.points, cloud.points)
    other = idx >= n_ground
    np.testing.assert_array_equal(out.intensity[other], cloud.intensity[idx][other])
    assert np.sum(idx >= n_ground) == len(cloud) - n_ground
    mask, normal = C.ground_points(cloud, seed=0)
    assert mask[:n_ground].all() and not mask[n_ground:].any()
    assert normal == pytest.approx([0, 0, 1], abs=1e-6)
    assert np.any(out.intensity[~other] < cloud.intensity[idx][~other])


def test_laser_parameter_fits():
    g = np.random.default_rng(30)
    d = g.uniform(5, 80, 5000)
    cos = g.uniform(0.05, 0.5, 5000)
    refl = g.choice([0.12, 0.25], 5000)
    inten = refl * cos * (1.0 - 0.002 * d)                 # a linear fall-off of the normalised intensity
    (a, b), (c, e) = C.laser_parameters(d, cos, inten)
    slope, icpt = np.polyfit(d, inten / cos, 1)
    assert a == pytest.approx(15 * slope) and b == pytest.approx(15 * icpt)
    # the noise floor passes under the darkest dry return of every 10-70 m bin, at 0.7 of its level
    inside = (d >= 10) & (d <= 70)
    floor = (c * d + e)[inside]
    assert np.all(floor <= 0.7 * (inten / cos)[inside] + 1e-12)
    assert np.max(floor / (0.7 * 0.12 * (1 - 0.002 * d[inside]))) > 0.97


def test_conditions_import_no_optional_packages():
    import subprocess
    import sys

    code = ("import sys, place3d_kernels.conditions as c; "
            "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules, sorted(sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True)


# ================================================================================================ snow
def test_snowflake_sampling_statistics():
    r0 = np.full(200_000, 20.0)
    fl = C.snowflakes(r0, 2.5, 1.6, seed=5)
    density, mu, mean_a = S.flake_density(2.5, 1.6)
    part_a, part_b = 3e-3 * 20.0 ** 2 / 2, 2 * mean_a * 20.0
    lam = density * (part_a + part_b)
    counts = fl.counts
    assert counts.mean() == pytest.approx(lam, rel=0.01)
    assert counts.var() == pytest.approx(lam, rel=0.03)                    # Poisson
    assert np.mean(counts == 0) == pytest.approx(math.exp(-lam), abs=0.005)
    # ranges: mixture of r ~ R0 sqrt(U) (weight A) and r ~ U(0, R0) (weight B)
    want_mean = (part_a * 2 / 3 * 20 + part_b * 10) / (part_a + part_b)
    assert fl.range.mean() == pytest.approx(want_mean, rel=0.01)
    assert fl.range.min() >= 0 and fl.range.max() <= 20.0
    assert fl.radius.max() <= 0.01 and fl.radius.min() >= 0
    assert np.all(np.abs(fl.offset) <= 1.5e-3 * fl.range + fl.radius + 1e-12)
    ray = np.repeat(np.arange(len(r0)), counts)
    assert np.all((np.diff(fl.range) >= 0) | (np.diff(ray) > 0))           # sorted inside each beam
    # occupancy and Gunn-Marshall constants (Hahner et al.'s sampling of S = 2.5, v = 1.6 and S = 0.5, v = 2)
    assert S.snow_occupancy(2.5, 1.6) == pytest.approx(4.340277777e-06)
    assert S.equivalent_rainfall_rate(0.5, 2.0) == pytest.approx(2.2383844962893775)
    assert S.gunn_marshall_rate(1.0) == 25.5


def test_snow_model(backend):
    cloud = _sphere_cloud(30_000, 2.0, 40.0, seed=6)
    snap = _snapshot(cloud)
    kw = dict(snowfall_rate=2.5, terminal_velocity=1.6, threshold=0.02)
    out = C.snow(cloud, seed=7, backend=backend, **kw)
    _assert_unchanged(cloud, snap)
    # the same draws, to know which beams met flakes
    fl = C.snowflakes(cloud.ranges, 2.5, 1.6, seed=7)
    ks, ni, sc, keep = get_backend(backend).snow_points(
        cloud.ranges, cloud.intensity.astype(float), fl.offsets, fl.range, fl.radius, fl.offset,
        np.full(len(cloud), 0.02), 3e-3, 299_792_458.0 * 10e-9, 0.1, 0.9, 0.9, 1.0, 1.0)
    assert len(out) == keep.sum()
    met = fl.counts > 0
    assert 0.1 < met.mean() < 0.99
    assert np.all(keep[~met]) and not sc[~met].any()
    np.testing.assert_array_equal(ni[~met], cloud.intensity[~met])
    assert sc.sum() > 20 and (~keep).sum() > 0                 # flakes scatter some beams and kill others
    # flake returns lie on their ray, in front of the target
    o = cloud.points[keep] - ORIGIN
    moved = sc[keep]
    v = out.points[moved] - ORIGIN
    u0 = o[moved] / np.linalg.norm(o[moved], axis=1, keepdims=True)
    assert np.max(np.linalg.norm(np.cross(u0, v / np.linalg.norm(v, axis=1, keepdims=True)), axis=1)) < 1e-6
    assert np.all(np.linalg.norm(v, axis=1) < cloud.ranges[keep][moved])
    np.testing.assert_array_equal(out.scattered, sc[keep])
    # beams whose flakes are all far from the target only lose light
    ray = np.repeat(np.arange(len(cloud)), fl.counts)
    near = np.zeros(len(cloud), dtype=bool)
    near[ray[cloud.ranges[ray] - fl.range < 3.0]] = True
    quiet = met & ~near & ~sc
    assert np.all(ni[quiet] <= cloud.intensity[quiet] * (1 + 1e-6))
    # no snow, no change
    _assert_same(C.snow(cloud, 0.0, seed=7, backend=backend), cloud)


# ================================================================================================ Robo3D
def test_motion_blur_statistics(backend):
    sigma = 0.30
    cloud = _sphere_cloud(100_000, 1.0, 80.0, seed=8)
    snap = _snapshot(cloud)
    out = C.motion_blur(cloud, sigma, seed=9, backend=backend)
    _assert_unchanged(cloud, snap)
    d = out.points - cloud.points
    jit = d - np.median(d, axis=0)
    np.testing.assert_allclose(jit.std(axis=0), [0.1 * sigma, 0.1 * sigma, 0.05 * sigma], rtol=0.03)
    assert np.all(np.abs(jit) < 3 * sigma)
    np.testing.assert_array_equal(out.labels, cloud.labels)
    np.testing.assert_array_equal(out.intensity, cloud.intensity)
    np.testing.assert_array_equal(out.origins, cloud.origins)
    small = _sphere_cloud(50, 1.0, 10.0, seed=10)
    offsets = np.array([np.median(C.motion_blur(small, sigma, seed=s, backend=backend).points - small.points, axis=0)
                        for s in range(300)])
    np.testing.assert_allclose(offsets.std(axis=0), sigma, rtol=0.15)
    assert np.all(np.abs(offsets.mean(axis=0)) < 0.1)


def test_crosstalk_statistics(backend):
    cloud = _sphere_cloud(100_000, 1.0, 80.0, seed=11)
    snap = _snapshot(cloud)
    out = C.crosstalk(cloud, 0.07, seed=12, backend=backend)
    _assert_unchanged(cloud, snap)
    moved = np.any(out.points != cloud.points, axis=1)
    assert moved.sum() == int(0.07 * len(cloud))
    np.testing.assert_array_equal(out.scattered, moved)
    d = out.points[moved] - cloud.points[moved]
    np.testing.assert_allclose(d.std(axis=0), 3.0, rtol=0.04)
    assert np.all(np.abs(d.mean(axis=0)) < 0.15)
    np.testing.assert_array_equal(out.labels, cloud.labels)
    np.testing.assert_array_equal(out.intensity, cloud.intensity)


def _cars(sizes, seed=0, spacing=8.0):
    """Vehicle boxes of the given point counts on a line, 8 m apart, plus ground points."""
    g = np.random.default_rng(seed)
    pts, inst = [], []
    for k, n in enumerate(sizes):
        pts.append(np.array([10.0 + spacing * k, 5.0, 0.2]) + g.uniform([0, 0, 0], [4.5, 1.8, 1.5], (n, 3)))
        inst.append(np.full(n, k))
    car_pts = np.vstack(pts)
    ground = np.column_stack([g.uniform(-40, 40, (3000, 2)), np.zeros(3000)])
    points = np.vstack([car_pts, ground])
    labels = np.concatenate([np.full(len(car_pts), VEHICLE), np.full(3000, 7)])
    instances = np.concatenate([np.concatenate(inst), np.full(3000, -1)])
    return p3k.PointCloud(points, labels, g.uniform(0.1, 0.9, len(points)), np.zeros(3)), instances


SIZES = [5, 10, 11, 40, 100, 1000, 2500]


@pytest.mark.parametrize("given", [True, False], ids=["instances", "clustered"])
def test_incomplete_echo_drops_per_object(backend, given):
    cloud, inst = _cars(SIZES, seed=13)
    snap = _snapshot(cloud)
    out = C.incomplete_echo(cloud, 0.85, seed=14, backend=backend, instances=inst if given else None)
    _assert_unchanged(cloud, snap)
    idx = _index_of(out.points, cloud.points)
    kept_inst = inst[idx]
    for k, n in enumerate(SIZES):
        want = n if n <= 10 else n - int(n * 0.85)
        assert np.sum(kept_inst == k) == want
    assert np.sum(kept_inst < 0) == 3000                       # non-vehicle points untouched
    np.testing.assert_array_equal(out.intensity, cloud.intensity[idx])


def test_cluster_points():
    g = np.random.default_rng(15)
    a = g.uniform(0, 3, (300, 3))
    b = g.uniform(0, 3, (300, 3)) + [10.0, 0, 0]
    ids = C.cluster_points(np.vstack([a, b]), 1.0)
    assert len(np.unique(ids[:300])) == 1 and len(np.unique(ids[300:])) == 1 and ids[0] != ids[300]
    chain = np.column_stack([np.arange(0, 50, 0.9), np.zeros(56), np.zeros(56)])
    assert len(np.unique(C.cluster_points(chain, 1.0))) == 1
    assert C.cluster_points(np.zeros((0, 3))).shape == (0,)


# ================================================================================================ all conditions
ALL = [("fog", dict(alpha=0.03)), ("wet_ground", {}), ("snow", dict(snowfall_rate=2.5)), ("motion_blur", {}),
       ("crosstalk", {}), ("incomplete_echo", {})]


def _mixed_cloud():
    street, _ = _street(8_000, 2_000, seed=16)
    cars, _ = _cars([30, 200, 800], seed=17)
    cars = p3k.PointCloud(cars.points + [0, 0, 0], cars.labels, cars.intensity, ORIGIN)
    return p3k.PointCloud(np.vstack([street.points, cars.points]), np.concatenate([street.labels, cars.labels]),
                          np.concatenate([street.intensity, cars.intensity]), ORIGIN)


@pytest.mark.parametrize("name, params", ALL, ids=[a for a, _ in ALL])
def test_condition_is_deterministic_and_pure(backend, name, params):
    cloud = _mixed_cloud()
    snap = _snapshot(cloud)
    a = C.apply(cloud, name, seed=21, backend=backend, **params)
    b = C.apply(cloud, name, seed=21, backend=backend, **params)
    _assert_unchanged(cloud, snap)
    _assert_same(a, b)
    if name != "wet_ground":                                     # wet ground draws nothing for labelled clouds
        c = C.apply(cloud, name, seed=22, backend=backend, **params)
        assert len(c) != len(a) or not np.array_equal(c.points, a.points)


@pytest.mark.parametrize("name, params", ALL, ids=[a for a, _ in ALL])
def test_device_backend_matches_reference(device_backend, name, params):
    cloud = _mixed_cloud()
    ref = C.apply(cloud, name, seed=23, backend="reference", **params)
    dev = C.apply(cloud, name, seed=23, backend=device_backend, **params)
    assert len(dev) == len(ref)
    np.testing.assert_array_equal(dev.labels, ref.labels)
    np.testing.assert_allclose(dev.points, ref.points, atol=2e-4)
    np.testing.assert_allclose(dev.intensity, ref.intensity, rtol=1e-4, atol=1e-6)
    if ref.scattered is not None:
        np.testing.assert_array_equal(dev.scattered, ref.scattered)


def test_backend_without_condition_kernels_falls_back_once(monkeypatch):
    from place3d_kernels.conditions import _common

    class Bare:
        name = "bare-test"

    monkeypatch.setattr(_common, "_warned", set())
    cloud = _sphere_cloud(1000, 1.0, 50.0, seed=24)
    with pytest.warns(RuntimeWarning, match="no condition kernels"):
        out = C.crosstalk(cloud, 0.1, seed=1, backend=Bare())
    _assert_same(out, C.crosstalk(cloud, 0.1, seed=1, backend="reference"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        C.motion_blur(cloud, 0.2, seed=1, backend=Bare())          # warned once per backend


# ================================================================================================ registry, configs
def test_apply_severity_and_errors():
    cloud = _sphere_cloud(2000, 1.0, 50.0, seed=25)
    _assert_same(C.apply(cloud, "motion_blur", seed=3, severity="heavy"),
                 C.motion_blur(cloud, 0.40, seed=3))
    _assert_same(C.apply(cloud, "crosstalk", seed=3, severity="light", ratio=0.2),
                 C.crosstalk(cloud, 0.2, seed=3))                    # explicit params win
    with pytest.raises(ValueError, match="Unknown condition 'rain'"):
        C.apply(cloud, "rain")
    with pytest.raises(ValueError, match="Unknown severity"):
        C.apply(cloud, "fog", severity="extreme")
    with pytest.raises(ValueError, match="ratio"):
        C.crosstalk(cloud, 1.5)
    with pytest.raises(TypeError, match="PointCloud"):
        C.fog(np.zeros((3, 3)), 0.01)


def test_configs_match_the_code():
    assert sorted(p.stem for p in CONFIGS.glob("*.toml")) == sorted(C.CONDITIONS)
    import inspect

    for name, fn in C.CONDITIONS.items():
        cfg = C.load_condition(name)
        assert cfg["condition"] == name
        sig = inspect.signature(fn)
        for key, value in cfg["params"].items():
            default = sig.parameters[key].default
            assert default == (tuple(value) if isinstance(value, list) else value), (name, key)
        assert cfg["severities"] == C.SEVERITIES[name], name
        assert cfg["severities"]["moderate"].items() <= {**cfg["params"], **cfg["severities"]["moderate"]}.items()
    raw = read_toml(CONFIGS / "fog.toml")
    assert raw["params"]["beta"] == 0.05 and raw["params"]["alphas"] == [0.0, 0.005, 0.01, 0.02, 0.03, 0.06]
    cloud = _sphere_cloud(500, 1.0, 50.0, seed=26)
    _assert_same(C.apply(cloud, str(CONFIGS / "crosstalk.toml"), seed=4), C.crosstalk(cloud, 0.07, seed=4))


# ================================================================================================ lidar_returns
def _wall_and_road(dist):
    """A wall (class wall 11) facing the sensor at x = dist, and a road (7) plane z = 0."""
    v = np.array([[dist, -50, -5], [dist, 50, -5], [dist, 50, 30], [dist, -50, 30],
                  [-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return p3k.Mesh(v, f, labels=[11, 11, 7, 7])


def test_lidar_returns_analytic(backend):
    o = np.array([[0.0, 0.0, 2.0]] * 4)
    d = np.array([[1.0, 0, 0], [1.0, 0.2, 0.05], [1.0, 0, -0.25], [0.0, 0, 1.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for dist, want_fog in [(10.0, False), (40.0, True)]:
        mesh = _wall_and_road(dist)
        clear = C.lidar_returns(mesh, o, d, backend=backend)
        np.testing.assert_array_equal(clear.kind, [1, 1, 1, 0])
        assert clear.range[0] == pytest.approx(dist, rel=1e-6) and clear.range[3] == np.inf
        assert clear.intensity[0] == pytest.approx(REFLECTIVITY[11], rel=1e-6)
        np.testing.assert_array_equal(clear.label, [11, 11, 7, -1])
        foggy = C.lidar_returns(mesh, o, d, "fog", backend=backend, alpha=0.06, beta=0.05, seed=1)
        assert (foggy.kind[0] == 2) == want_fog
        beta0 = FogSensor().beta_0
        r0 = clear.range[:3]
        i_tab = C.fog_lookup(0.06).lookup(r0)[0]
        np.testing.assert_allclose(foggy.hard_power[:3], clear.intensity[:3] * beta0 * np.exp(-0.12 * r0) / r0 ** 2,
                                   rtol=1e-6)
        np.testing.assert_allclose(foggy.fog_power[:3], clear.intensity[:3] * 0.05 * i_tab, rtol=1e-6)
        np.testing.assert_array_equal(foggy.kind[:3] == 2, foggy.fog_power[:3] > foggy.hard_power[:3])
        if not want_fog:
            assert foggy.range[0] == pytest.approx(dist, rel=1e-6)
            assert foggy.intensity[0] == pytest.approx(clear.intensity[0] * math.exp(-0.12 * dist), rel=1e-5)
        else:
            assert foggy.range[0] < 3.0
        assert foggy.kind[3] == 0 and foggy.fog_power[3] > 0
    wet = C.lidar_returns(_wall_and_road(30.0), o, d, "wet_ground", backend=backend, water_height_mm=1.0,
                          p_out=1.0, noise_level=0.0)
    clear = C.lidar_returns(_wall_and_road(30.0), o, d, backend=backend)
    assert wet.intensity[0] == clear.intensity[0]                       # the wall is not ground
    assert 0 < wet.intensity[2] < clear.intensity[2]
    with pytest.raises(ValueError, match="condition"):
        C.lidar_returns(_wall_and_road(30.0), o, d, "rain")


def test_lidar_returns_mitsuba_needs_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mitsuba", None)          # as if the extra were not installed
    o, d = np.zeros((1, 3)), np.array([[1.0, 0, 0]])
    with pytest.raises(ImportError, match=r"pip install 'place3d-kernels\[mitsuba\]'"):
        C.lidar_returns(_wall_and_road(10.0), o, d, "fog", model="mitsuba", alpha=0.01)
