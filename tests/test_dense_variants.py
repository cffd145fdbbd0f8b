"""The dense-rig study's kernel variants (bench/gpu_dense_variants*.py, bench/gpu_dense_lean_kernels.py,
bench/gpu_dense_near_kernels.py) are exact: tiled ray order, persistent threads, lean address arithmetic,
full-brick skips, loads one step ahead and the near field return the shipped score kernel's int64 sums and
covered-voxel counts, bit for bit.

Runs on Warp's CPU device (small and fast) and, where there is one, on CUDA, so the GPU run checks the
same variants before timing them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import place3d_kernels as p3k

wp = pytest.importorskip("warp")
sys.path.append(str(Path(__file__).resolve().parents[1] / "bench"))     # appended: shadows nothing
import gpu_dense_near_kernels  # noqa: E402
from gpu_dense_lean_kernels import walk32_next_lean, walk32_skip_brick, walk32_step_or_jump  # noqa: E402
from gpu_dense_round4_kernels import inside, walk32x_from, walk32x_next, walk32x_next_med  # noqa: E402
from gpu_dense_variants import Workload, build, make_lean_kind, variants  # noqa: E402
from gpu_dense_variants_kernels import tiled_ray, walk32_next_sel  # noqa: E402
from gpu_score_variants_kernels import walk32_begin, walk32_next  # noqa: E402

from place3d_kernels.backends.warp import kernels as shipped_k  # noqa: E402   (Walk32x converts its Walk32)
from place3d_kernels.backends.warp import score_gpu  # noqa: E402
from place3d_kernels.backends.bricks import brick_bits, brick_shape, flat_brick_masks  # noqa: E402

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
CPU_THREADS = 97     # persistent launch size on the CPU: not a multiple of 32, far fewer than the rays


@wp.kernel
def _hit_kernel(n: wp.int32, n_az: wp.int32, tile_c: wp.int32, hits: wp.array(dtype=wp.int32)):
    rig, sd = tiled_ray(wp.tid(), n, n_az, tile_c)
    wp.atomic_add(hits, rig * n + sd, 1)


@wp.kernel
def _lockstep_kernel(o: wp.array(dtype=wp.vec3d), d: wp.array(dtype=wp.vec3d), s: wp.float64, n: wp.int32,
                     lean: wp.int32, steps: wp.array(dtype=wp.int32), bad: wp.array(dtype=wp.int32)):
    # both steps from the same start, compared field by field after every step
    tid = wp.tid()
    sf = wp.float32(s)
    a = walk32_begin(o[tid], d[tid], wp.float64(1.0e3), s, sf, n, n, n)
    b = a
    c = wp.int32(0)
    for _ in range(3 * n + 3):
        if a.alive == 0 and b.alive == 0:
            break
        if (a.i != b.i or a.j != b.j or a.k != b.k or a.alive != b.alive or a.tx != b.tx or a.ty != b.ty
                or a.tz != b.tz or a.ki != b.ki or a.kj != b.kj or a.kk != b.kk):
            bad[tid] = 1
        if lean == 2:
            b = walk32_step_or_jump(b, False, o[tid], d[tid], s, sf, n, n, n)
        elif lean == 1:
            b = walk32_next_lean(b, o[tid], d[tid], s, sf, n, n, n)
        else:
            b = walk32_next_sel(b, o[tid], d[tid], s, sf, n, n, n)
        a = walk32_next(a, o[tid], d[tid], s, sf, n, n, n)
        c += 1
    steps[tid] = c


def tie_rays(m: int, s: float, n, seed: int = 7):
    """``m`` rays full of ties in a grid of ``n`` voxels of size ``s`` per axis: origins on voxel planes,
    edges and corners; directions along axes, face and space diagonals, and random."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(0.0, 1.0, (m, 3)) * np.asarray(n) * s
    snap = rng.integers(0, 4, m)                       # 0: random, 1-3: that many coordinates on a plane
    for k in range(3):
        on = snap > k
        o[on, k] = np.round(o[on, k] / s) * s
    dirs = np.array([[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [0, 1, 1], [1, 1, 1], [-1, 1, -1],
                     [2, 1, 0], [1, 2, 2], [1e-31, 1, 0.5], [4, 4, 2], [-4, 4, 2], [2, -2, -1],
                     # near-ties: diagonals off by about a float32 rounding, where float32 may misorder crossings
                     [1, 1 + 2 ** -22, 0.5], [1, 1 - 2 ** -23, 1 + 2 ** -22], [-2 - 2 ** -21, 2, 1],
                     [1 + 3e-7, -1, 1 - 3e-7]], dtype=np.float64)
    d = np.where((rng.random(m) < 0.6)[:, None], dirs[rng.integers(0, len(dirs), m)], rng.normal(size=(m, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def near_tie_rays(m: int, s: float, seed: int = 5):
    """``m`` rays whose crossings of different axes nearly coincide, closer than float32 can order them:
    origins on a voxel-lattice diagonal (the same fraction of a voxel on every axis, plus ~1e-7 voxels of
    noise) and directions a diagonal off by 1e-8.5 to 1e-6 relative."""
    rng = np.random.default_rng(seed)
    o = (rng.integers(0, 20, (m, 3)) + rng.uniform(0, 1, (m, 1)) + rng.normal(size=(m, 3)) * 1e-7) * s
    base = np.array([[1, 1, 1], [1, 1, 0.5], [2, 1, 1], [1, -1, 1], [1, 1, 0], [4, 4, 2]], dtype=np.float64)
    d = base[rng.integers(0, len(base), m)] * rng.choice([-1, 1], (m, 3))
    d = d + rng.normal(size=(m, 3)) * 10 ** rng.uniform(-8.5, -6, (m, 1))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("rays", ["ties", "near-ties"])
@pytest.mark.parametrize("lean", [0, 1, 2])
def test_branch_free_step_takes_the_shipped_steps(lean, rays):
    """walk32_next_sel (lean=0), walk32_next_lean (1: unsigned grid test) and walk32_step_or_jump outside a
    full brick (2) against walk32_next on rays full of ties (``tie_rays``) and near-ties."""
    s, n, m = 0.25, 24, 6000
    o, d = tie_rays(m, s, n) if rays == "ties" else near_tie_rays(m, s)
    steps = wp.zeros(m, dtype=wp.int32, device="cpu")
    bad = wp.zeros(m, dtype=wp.int32, device="cpu")
    wp.launch(_lockstep_kernel, dim=m, device="cpu",
              inputs=[wp.array(o, dtype=wp.vec3d, device="cpu"), wp.array(d, dtype=wp.vec3d, device="cpu"), s, n, lean,
                      steps, bad])
    assert steps.numpy().sum() > 10 * m, "the rays must walk"
    assert bad.numpy().sum() == 0, f"{int(bad.numpy().sum())} rays stepped differently"


@wp.kernel
def _lockstep_x_kernel(o: wp.array(dtype=wp.vec3d), d: wp.array(dtype=wp.vec3d), t_end: wp.array(dtype=wp.float64),
                       s: wp.float64, nx: wp.int32,
                       ny: wp.int32, nz: wp.int32, med: wp.int32, steps: wp.array(dtype=wp.int32),
                       exact: wp.array(dtype=wp.int32), bad: wp.array(dtype=wp.int32)):
    # walk32x_next (round four's smaller state) against walk32_next from the same start, after every step:
    # on while the shipped walk is alive, the same voxel, planes and (float32 walks) crossing times
    tid = wp.tid()
    sf = wp.float32(s)
    a = shipped_k.walk32_begin(o[tid], d[tid], t_end[tid], s, sf, nx, ny, nz)
    b = walk32x_from(a)
    exact[tid] = a.exact
    c = wp.int32(0)
    for _ in range(nx + ny + nz + 3):
        on = inside(b, nx, ny, nz)
        if on != (a.alive != 0):
            bad[tid] = 1
        if a.alive == 0 or not on:
            break
        if a.i != b.i or a.j != b.j or a.k != b.k or a.ki != b.ki or a.kj != b.kj or a.kk != b.kk:
            bad[tid] = 1
        if a.exact == 0 and (a.tx != b.tx or a.ty != b.ty or a.tz != b.tz or a.t1 != b.t1 or a.tol != b.tol):
            bad[tid] = 1
        if a.exact != 0 and b.t1 >= wp.float32(0.0):
            bad[tid] = 1
        if med != 0:
            b = walk32x_next_med(b, o[tid], d[tid], a.t1d, s, sf, nx, ny, nz)
        else:
            b = walk32x_next(b, o[tid], d[tid], a.t1d, s, sf, nx, ny, nz)
        a = shipped_k.walk32_next(a, o[tid], d[tid], s, sf, nx, ny, nz)
        c += 1
    steps[tid] = c


@wp.kernel
def _lockstep_gpu_kernel(o: wp.array(dtype=wp.vec3d), d: wp.array(dtype=wp.vec3d), t_end: wp.array(dtype=wp.float64),
                         s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32, steps: wp.array(dtype=wp.int32),
                         exact: wp.array(dtype=wp.int32), bad: wp.array(dtype=wp.int32)):
    # the shipped CUDA score kernel's walk (score_gpu.WalkGPU, next_step) against walk32_next, as above
    tid = wp.tid()
    sf = wp.float32(s)
    a = shipped_k.walk32_begin(o[tid], d[tid], t_end[tid], s, sf, nx, ny, nz)
    b = score_gpu.walk_from(a)
    exact[tid] = a.exact
    c = wp.int32(0)
    for _ in range(nx + ny + nz + 3):
        on = score_gpu.inside(b, nx, ny, nz)
        if on != (a.alive != 0):
            bad[tid] = 1
        if a.alive == 0 or not on:
            break
        if a.i != b.i or a.j != b.j or a.k != b.k or a.ki != b.ki or a.kj != b.kj or a.kk != b.kk:
            bad[tid] = 1
        if a.exact == 0 and (a.tx != b.tx or a.ty != b.ty or a.tz != b.tz or a.t1 != b.t1 or a.tol != b.tol):
            bad[tid] = 1
        if a.exact != 0 and b.t1 >= wp.float32(0.0):
            bad[tid] = 1
        b = score_gpu.next_step(b, o[tid], d[tid], a.t1d, s, sf)
        a = shipped_k.walk32_next(a, o[tid], d[tid], s, sf, nx, ny, nz)
        c += 1
    steps[tid] = c


def _tie_segments(rays: str, s: float, m: int, n: tuple):
    """Rays full of ties (or near-ties) in a grid whose edges cut bricks, with segment ends: a third end
    inside the grid (some on a voxel plane, where the float32 step must defer to the float64 one), the
    others leave it."""
    o, d = tie_rays(m, s, n, seed=13) if rays == "ties" else near_tie_rays(m, s, seed=17)
    rng = np.random.default_rng(19)
    t_end = np.where(rng.random(m) < 0.33, rng.uniform(0.0, 4.0, m), 1.0e3)
    plane = rng.random(m) < 0.1        # segments ending on an x plane of the grid: ties with the end
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = ((np.floor(o[:, 0] / s) + np.sign(d[:, 0]) * rng.integers(1, 6, m)) * s - o[:, 0]) / d[:, 0]
    t_end = np.where(plane & np.isfinite(t_plane) & (t_plane > 0), t_plane, t_end)
    return (wp.array(o, dtype=wp.vec3d, device="cpu"), wp.array(d, dtype=wp.vec3d, device="cpu"),
            wp.array(t_end, dtype=wp.float64, device="cpu"))


@pytest.mark.parametrize("med", [0, 1, "shipped"])
@pytest.mark.parametrize("rays", ["ties", "near-ties"])
def test_small_walk_state_takes_the_shipped_steps(rays, med):
    """Round four's Walk32x (no alive, exact or t1d fields; gpu_dense_round4_kernels.py) steps as walk32_next
    on rays full of ties and near-ties, float64-only rays among them, and ends where it ends (``_tie_segments``).
    med=1: the step test by minimum and median (walk32x_next_med); "shipped": that form as the CUDA score
    kernel runs it (place3d_kernels/backends/warp/score_gpu.py)."""
    s, m, n = 0.25, 6000, (23, 22, 21)
    o, d, t_end = _tie_segments(rays, s, m, n)
    steps, exact, bad = (wp.zeros(m, dtype=wp.int32, device="cpu") for _ in range(3))
    if med == "shipped":
        wp.launch(_lockstep_gpu_kernel, dim=m, device="cpu", inputs=[o, d, t_end, s, *n, steps, exact, bad])
    else:
        wp.launch(_lockstep_x_kernel, dim=m, device="cpu", inputs=[o, d, t_end, s, *n, med, steps, exact, bad])
    assert steps.numpy().sum() > 10 * m, "the rays must walk"
    if rays == "ties":
        assert exact.numpy().sum() > 0, "some rays must be float64-only (a direction component below DIR_SMALL)"
    assert bad.numpy().sum() == 0, f"{int(bad.numpy().sum())} rays stepped differently"


@wp.kernel
def _jump_kernel(o: wp.array(dtype=wp.vec3d), d: wp.array(dtype=wp.vec3d), s: wp.float64, nx: wp.int32,
                 ny: wp.int32, nz: wp.int32, unified: wp.int32, jumps: wp.array(dtype=wp.int32),
                 bad: wp.array(dtype=wp.int32)):
    # from every voxel of a walk: walk32_skip_brick is either one ordinary step, or the state that stepping
    # voxel by voxel reaches on leaving the brick (4 x 4 x 2), field by field (or both walks end)
    tid = wp.tid()
    sf = wp.float32(s)
    a = walk32_begin(o[tid], d[tid], wp.float64(1.0e3), s, sf, nx, ny, nz)
    for _ in range(nx + ny + nz + 3):
        if a.alive == 0:
            break
        jmp = walk32_skip_brick(a, o[tid], d[tid], s, sf, nx, ny, nz)
        if unified != 0:
            jmp = walk32_step_or_jump(a, True, o[tid], d[tid], s, sf, nx, ny, nz)
        one = walk32_next(a, o[tid], d[tid], s, sf, nx, ny, nz)
        if (jmp.i != one.i or jmp.j != one.j or jmp.k != one.k or jmp.alive != one.alive or jmp.tx != one.tx
                or jmp.ty != one.ty or jmp.tz != one.tz or jmp.ki != one.ki or jmp.kj != one.kj or jmp.kk != one.kk):
            b = one
            for _ in range(12):
                if b.alive == 0 or b.i >> 2 != a.i >> 2 or b.j >> 2 != a.j >> 2 or b.k >> 1 != a.k >> 1:
                    break
                b = walk32_next(b, o[tid], d[tid], s, sf, nx, ny, nz)
            if b.alive == 0 and jmp.alive == 0:
                jumps[tid] += 1
            elif (jmp.i != b.i or jmp.j != b.j or jmp.k != b.k or jmp.alive != b.alive or jmp.tx != b.tx
                    or jmp.ty != b.ty or jmp.tz != b.tz or jmp.ki != b.ki or jmp.kj != b.kj or jmp.kk != b.kk):
                bad[tid] += 1
            else:
                jumps[tid] += 1
        a = one


@pytest.mark.parametrize("unified", [0, 1])
@pytest.mark.parametrize("rays", ["ties", "near-ties"])
def test_brick_jump_lands_where_steps_do(rays, unified):
    """walk32_skip_brick from every voxel of rays full of ties (``tie_rays``) or of near-ties that float32
    cannot order (``near_tie_rays``; without the certainty margin ``tol`` some jumps land elsewhere), in a
    grid whose edges cut bricks (23 x 22 x 21 voxels): where it jumps, it lands on the state stepping
    reaches, bit for bit. unified=1: walk32_step_or_jump in a full brick."""
    s, m = 0.25, 6000 if rays == "ties" else 20000
    o, d = tie_rays(m, s, (23, 22, 21), seed=11) if rays == "ties" else near_tie_rays(m, s)
    jumps = wp.zeros(m, dtype=wp.int32, device="cpu")
    bad = wp.zeros(m, dtype=wp.int32, device="cpu")
    wp.launch(_jump_kernel, dim=m, device="cpu",
              inputs=[wp.array(o, dtype=wp.vec3d, device="cpu"), wp.array(d, dtype=wp.vec3d, device="cpu"), s, 23, 22,
                      21, unified, jumps, bad])
    assert jumps.numpy().sum() > 3 * m, "the jump must run"
    assert bad.numpy().sum() == 0, f"{int(bad.numpy().sum())} jumps landed elsewhere than the steps"


@pytest.fixture(scope="module")
def small():
    """A 0.4 m P-SOG of the default town, a 32 x 64 LiDAR and 3 rigs: the ``pyramid`` rig, the same
    moved by 0.3 m, and one with a LiDAR 6 m outside the grid (its rays enter from outside)."""
    d0 = p3k.DEFAULT_GRID
    grid = p3k.Grid(d0.lower, d0.upper, 0.4)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend="warp:cpu")   # the brute-force reference
    # would take many minutes to simulate on a cold cache; P-SOGs are identical across backends
    assert np.asarray(psog.stop_mask).any(), "the stop mask must be on (occupied voxels) for the test to bite"
    lidar = p3k.LidarModel.uniform(32, (-25, 15), 64, max_range=100.0)
    rig = p3k.Placement.load("pyramid").poses
    pop = np.stack([rig, rig, rig])
    pop[1, :, :2] += 0.3
    pop[2, 0, 0] = d0.lower[0] - 6.0
    return psog, lidar, pop


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("tile_c", [1, 2, 4, 8, 16, 32])
def test_tile_order_is_a_permutation(device, tile_c):
    n_az, n_el, rigs = 64, 32, 3
    n = n_az * n_el
    hits = wp.zeros(rigs * n, dtype=wp.int32, device=device)
    wp.launch(_hit_kernel, dim=rigs * n, device=device, inputs=[n, n_az, tile_c, hits])
    assert (hits.numpy() == 1).all(), f"tile_c={tile_c}: some rays walked twice or never"


@pytest.mark.parametrize("device", DEVICES)
def test_variants_match_the_shipped_kernel(small, device):
    psog, lidar, pop = small
    ref = p3k.get_backend("reference")
    local = pop.copy()
    local[..., :3] = psog.grid.to_local(pop[..., :3])
    want = ref.score_placements(psog.handle(ref, "sog"), lidar.elevations, lidar.azimuths, lidar.max_range, local)

    wl = Workload(psog, lidar, pop, device)
    sm = wp.get_device(device).sm_count if device.startswith("cuda") else 0
    vs = variants(sm, None if sm else CPU_THREADS)
    # every tile shape, a chunked counter, uncapped registers on top of the study's own list
    threads = CPU_THREADS if not sm else vs["persist-stride-t1x32-w1-r80"]["threads"]
    vs["persist-stride-t32x1"] = {"kind": "persistent", "mode": 0, "tile_c": 32, "chunk": 1, "reload": True,
                                  "batch": 1, "select": False, "maxreg": None, "threads": threads}
    vs["persist-atomic-t2x16-c3"] = dict(vs["persist-stride-t32x1"], mode=1, tile_c=2, chunk=3, reload=False)
    vs["persist-atomic-t16x2-c1-reload-b4"] = dict(vs["persist-stride-t32x1"], mode=1, tile_c=16, batch=4)
    vs["persist-stride-t8x4-select"] = dict(vs["persist-stride-t32x1"], tile_c=8, reload=False, select=True)
    vs["tiled-16x2"] = {"kind": "tiled", "tile_c": 16, "maxreg": 80, "select": False, "eager": False}
    vs["select-32x1"] = {"kind": "tiled", "tile_c": 32, "maxreg": None, "select": True, "eager": False}
    vs["eager-4x8"] = {"kind": "tiled", "tile_c": 4, "maxreg": None, "select": True, "eager": True}
    build(vs)

    wl.reset()
    wl.launch(vs["shipped"])
    shipped = wl.result()
    # the harness's launch of the shipped kernel is the product's: the reference backend's sums and counts
    np.testing.assert_array_equal(shipped[0], want[0])
    np.testing.assert_array_equal(shipped[1], want[1])
    assert (shipped[1] > 0).all() and (shipped[0] != 0).all(), "every rig must cover voxels with entropy"
    assert shipped[1][2] != shipped[1][0], "the rig with a LiDAR outside the grid must see something else"
    for name, v in vs.items():
        wl.check_tile(v.get("tile_c", 1))
        wl.reset()
        wl.launch(v)
        sums, counts = wl.result()
        if "diagnostic" in v:
            # walk-only: wrong sums on purpose (each candidate's voxel visits), no bitset
            assert (sums > 0).all() and (counts == 0).all(), name
            continue
        np.testing.assert_array_equal(sums, shipped[0], err_msg=name)
        np.testing.assert_array_equal(counts, shipped[1], err_msg=name)


def _launch(wl, v, pre=None, count=False):
    wl.reset()
    if pre is not None:
        wl.bits.assign(pre)
    if count:
        v = dict(v, kernel=make_lean_kind(v, count=True))
    wl.launch(v)
    return wl.result() + (wl.stats.numpy().copy(),)


@pytest.mark.parametrize("device", DEVICES)
def test_skip_on_full_bricks_matches_the_shipped_kernel(small, device):
    """Bitsets with full bricks before the launch (a random third of the words all ones, a fifth random
    bits), and a second launch on the bitset the reference left: the skip and lean variants (and their
    counting builds) return the sums and counts of ``lean32xm-r64`` (the form that shipped until the flat
    bricks, on the same 4 x 4 x 2 bitset), the shipped kernel those of the same bits in its flat bricks, and
    the skip variants do jump."""
    psog, lidar, pop = small
    wl = Workload(psog, lidar, pop, device)
    sm = wp.get_device(device).sm_count if device.startswith("cuda") else 0
    vs = variants(sm, None if sm else CPU_THREADS)
    names = ["skip-r72", "lean-skip-r72", "lean32-skip-r72", "lean32-skipu-r72", "lean32-keep-skip-r72",
             "lean32-keep-r72", "lean-r72", "lean32-r72", "lean-ahead-r72",
             "lean32-ahead-r72", "lean32x-r56", "lean32xr-r56", "lean32xm-r56", "lean32-lazy-r64",
             "lean32-lazy-keep-r64", "lean32-pred-r64"]
    vs = {k: vs[k] for k in ["shipped", "lean32xm-r64"] + names}
    build(vs)
    old = vs["lean32xm-r64"]
    rng = np.random.default_rng(3)
    pre = np.zeros(wl.P * wl.words, dtype=np.uint32)
    r = rng.random(pre.size)
    pre[r < 0.33] = 0xFFFFFFFF
    part = (r >= 0.33) & (r < 0.53)
    pre[part] = rng.integers(0, 2 ** 32, int(part.sum()), dtype=np.uint64).astype(np.uint32)
    pre &= np.tile(brick_bits(np.ones(psog.grid.n_voxels, bool), psog.grid.shape), wl.P)   # no bits past the grid
    want = _launch(wl, old, pre)
    assert (want[0] > 0).all(), "the rays must still find new voxels with entropy"
    first = _launch(wl, old)
    filled = wl.bits.numpy().copy()
    again = _launch(wl, old, filled)
    # nothing new the second time: no weights, the same covered voxels
    assert (again[0] == 0).all() and (again[1] == first[1]).all()
    for bits, ref in ((pre, want), (filled, again)):       # the shipped kernel on the same bits, flat bricks
        wl.reset()
        wl.flat[3].assign(_to_flat(bits, wl.P, psog.grid.shape))
        wl.launch(vs["shipped"])
        got = wl.result()
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
    visits = None
    for name in names:
        for count in (False, True):
            for bits, ref in ((pre, want), (filled, again)):
                sums, counts, st = _launch(wl, vs[name], bits, count)
                tag = f"{name} count={count} {'prefilled' if bits is pre else 'second launch'}"
                np.testing.assert_array_equal(sums, ref[0], err_msg=tag)
                np.testing.assert_array_equal(counts, ref[1], err_msg=tag)
                if count and "skip" in name:
                    assert st[1] > 0 and st[2] > 2 * st[1], f"{tag}: no brick was jumped ({st})"
                if count and name == "lean-r72" and bits is pre:
                    assert st[1] == st[2] == st[3] == 0 and st[0] > 0, st
                    visits = st[0]
    # the floor diagnostic walks the same voxels as the exact kernels: its sums are each rig's visits
    for name in ("walk-only", "walk-only-lean32"):
        diag = dict(variants(sm, None if sm else CPU_THREADS)[name])
        sums, counts, st = _launch(wl, dict(diag, kernel=make_lean_kind(diag)))
        assert sums.sum() == visits and (counts == 0).all(), name


def _to_flat(words, P, shape):
    """P candidates' 4 x 4 x 2 bitsets (bricks.py) as the same voxels' bits in flat 8 x 4 x 1 bricks."""
    nx, ny, nz = shape
    bx, by, bz = brick_shape(shape)
    out = []
    for c in np.asarray(words, dtype=np.uint32).reshape(P, -1):
        b = np.unpackbits(c.view(np.uint8), bitorder="little").reshape(bx, by, bz, 2, 4, 4)   # (.., kk, jj, ii)
        vox = b.transpose(0, 5, 1, 4, 2, 3).reshape(4 * bx, 4 * by, 2 * bz)[:nx, :ny, :nz]
        out.append(flat_brick_masks(shape, vox.reshape(-1), None) >> np.uint64(32))
    return np.concatenate(out).astype(np.uint32)


def test_a_tile_that_does_not_fit_is_refused(small):
    psog, _, pop = small
    wl = Workload(psog, p3k.LidarModel.uniform(6, (-25, 15), 64, max_range=100.0), pop[:1], "cpu")
    with pytest.raises(ValueError, match="does not tile the 6 x 64 LiDAR"):
        wl.check_tile(4)


def test_near_field_marks_the_walks_bits():
    """The near field (bench/gpu_dense_near_kernels.py: voxels near each LiDAR marked per voxel, the walks
    starting after the box) sets exactly the shipped kernel's bits, sums and counts: on a 0.1 m grid, with
    LiDAR origins on voxel planes (a start that depends on the ray's sign), axis-aligned rays (yaw and roll
    0: direction components exactly 0, and ties between axes) and a rolled rig."""
    d0 = p3k.DEFAULT_GRID
    grid = p3k.Grid(d0.lower, d0.upper, 0.1)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend="warp:cpu")
    lidar = p3k.LidarModel.uniform(41, (-25, 15), 128, max_range=100.0)       # a channel at exactly 0 degrees
    rig = p3k.Placement.load("pyramid").poses
    pop = np.stack([rig, rig])
    pop[1, :, :3] += 0.05          # onto voxel planes
    pop[1, :, 3:] = 0.0
    wl = Workload(psog, lidar, pop, "cpu")
    v = {"kind": "near", "near_h": 16, "near_hz": 16}
    old = {"x": dict(variants(0, CPU_THREADS)["lean32xm-r64"])}    # the 4 x 4 x 2 form the near field extends
    build(old)
    wl.reset()
    wl.launch(old["x"])
    want_bits, want = wl.bits.numpy().copy(), wl.result()
    wl.reset()
    wl.launch({"kind": "shipped"})
    shipped = wl.result()
    np.testing.assert_array_equal(shipped[0], want[0])
    np.testing.assert_array_equal(shipped[1], want[1])
    wl.reset()
    near = gpu_dense_near_kernels.launch("cpu", wl.near_table, wl.inputs[0], wl.inputs[1], wl.inputs[2], wl.L,
                                         wl.inputs[4], wl.inputs[5], wl.shape, wl.bricks, wl.inputs[11],
                                         wl.inputs[12], wl.words, wl.bits, wl.sums, 16, 16)
    n = near.numpy()
    rigs = wl.P * wl.L
    assert (n[rigs:] < 16 - 1).all() and (n[:rigs] < wl.shape[2]).all(), "every LiDAR must get a box"
    assert wl.bits.numpy().any(), "the cover kernel must mark voxels"
    wl.reset()
    wl.launch(v)
    np.testing.assert_array_equal(wl.bits.numpy(), want_bits)
    got = wl.result()
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@wp.kernel
def _near_box_kernel(o: wp.array(dtype=wp.vec3d), d: wp.array(dtype=wp.vec3d), s: wp.float64, n: wp.int32,
                     r: wp.int32, bad: wp.array(dtype=wp.int32)):
    # walk ray tid through the box of +-r voxels around its origin's voxel: every voxel of the box is
    # visited exactly when visits() says so, and leave_box lands on the walk's state after the box
    tid = wp.tid()
    sf = wp.float32(s)
    t_max = wp.float64(1.0e3)
    w0 = shipped_k.walk32_begin(o[tid], d[tid], t_max, s, sf, n, n, n)
    c = gpu_dense_near_kernels.near_origin(o[tid], s, n, n, n)
    b = gpu_dense_near_kernels.NearBox()
    b.x0 = c[0] - r
    b.x1 = c[0] + r
    b.y0 = c[1] - r
    b.y1 = c[1] + r
    b.z0 = c[2] - r
    b.z1 = c[2] + r
    w = score_gpu.walk_from(w0)
    jumped = gpu_dense_near_kernels.leave_box(w, b, o[tid], d[tid], w0.t1d, s, sf)
    seen = wp.int32(0)
    for _ in range(3 * n + 3):
        if not score_gpu.inside(w, n, n, n):
            break
        if w.i < b.x0 or w.i > b.x1 or w.j < b.y0 or w.j > b.y1 or w.k < b.z0 or w.k > b.z1:
            break
        seen += 1
        if not gpu_dense_near_kernels.visits(w.i, w.j, w.k, o[tid], d[tid], s, n, n, n):
            bad[tid] = 1
        w = score_gpu.next_step(w, o[tid], d[tid], w0.t1d, s, sf)
    # the walk's first voxel after the box (or its end) is where leave_box put it
    if jumped.i != w.i or (w.i != score_gpu.DEAD and (jumped.j != w.j or jumped.k != w.k or jumped.ki != w.ki
                                                      or jumped.kj != w.kj or jumped.kk != w.kk or jumped.tx != w.tx
                                                      or jumped.ty != w.ty or jumped.tz != w.tz)):
        bad[tid] = 2
    # and visits() claims no other voxel of the box
    count = wp.int32(0)
    for q in range((2 * r + 1) * (2 * r + 1) * (2 * r + 1)):
        i = b.x0 + q / ((2 * r + 1) * (2 * r + 1))
        j = b.y0 + (q / (2 * r + 1)) % (2 * r + 1)
        k = b.z0 + q % (2 * r + 1)
        if gpu_dense_near_kernels.visits(i, j, k, o[tid], d[tid], s, n, n, n):
            count += 1
    if count != seen:
        bad[tid] = 3


def test_near_box_voxels_and_exit_are_the_walks():
    """visits() and leave_box() against the walk itself, on rays made of ties: origins on voxel corners,
    edges and faces, directions with equal components (a ray through voxel edges and corners, whose axes
    step together), components exactly 0, both signs; and random rays."""
    rng = np.random.default_rng(5)
    s, n = 0.1, 64
    a = 1.0 / np.sqrt(2.0)
    b3 = 1.0 / np.sqrt(3.0)
    dirs = [(1, 0, 0), (0, -1, 0), (0, 0, 1), (a, a, 0), (-a, a, 0), (a, 0, -a), (0, -a, -a), (b3, b3, b3),
            (-b3, b3, -b3), (b3, -b3, b3), (0.6, 0.8, 0.0), (0.48, 0.6, 0.64)]
    dirs = np.array([d for d in dirs] + [tuple(-np.array(d)) for d in dirs], dtype=np.float64)
    starts = np.array([(3.2, 3.2, 3.2), (3.2, 3.25, 3.2), (3.25, 3.25, 3.2), (3.21, 3.2, 3.27), (3.25, 3.25, 3.25)])
    o = np.repeat(starts, len(dirs), axis=0)
    d = np.tile(dirs, (len(starts), 1))
    rd = rng.normal(size=(400, 3))
    o = np.vstack([o, 3.2 + rng.uniform(-0.1, 0.1, (400, 3)) * rng.integers(0, 2, (400, 3))])
    d = np.vstack([d, rd / np.linalg.norm(rd, axis=1)[:, None]])
    assert (d[:, 0] == d[:, 1]).sum() >= 4, "the rays must hold exact ties"
    for r in (1, 3):
        bad = wp.zeros(len(o), dtype=wp.int32)
        wp.launch(_near_box_kernel, dim=len(o), inputs=[wp.array(o, dtype=wp.vec3d), wp.array(d, dtype=wp.vec3d),
                                                         s, n, r, bad])
        got = bad.numpy()
        assert not got.any(), f"r={r}: rays {np.nonzero(got)[0][:8]} codes {got[np.nonzero(got)[0][:8]]}"
