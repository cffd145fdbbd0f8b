"""OpenCL backend: BVH builder and its depth bound, stack-overflow fallback, program/device caching, error
messages, and agreement with the float64 reference on seeded random and adversarial inputs.

Every device test runs once per OpenCL platform found (ids like ``[opencl:pocl]``) and, where the device
has doubles, once more on the pure float32 path (``[opencl:pocl-fp32]``, what a device without
cl_khr_fp64 runs); ray-mesh tests also run the other BVH width (``[opencl:pocl-bvh2]``: CPUs default to
the 4-wide tree, GPUs to the binary one). Without PyOpenCL or without a device the tests skip with the
reason.
"""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.backends.base import BackendUnavailable, GridSpec
from place3d_kernels.backends.geometry import brute_force_raycast
from place3d_kernels.backends.opencl.bvh import DEFAULT_MAX_DEPTH, build_bvh, need_levels, validate_bvh
from place3d_kernels.backends.opencl.lbvh import build_lbvh, morton_tree
from place3d_kernels.backends.reference import ReferenceBackend

try:
    from place3d_kernels.backends.opencl import OpenCLBackend, opencl_devices

    _DEVICES = opencl_devices()
    _WHY = "no OpenCL platform with a device (install PoCL: pip install 'place3d-kernels[opencl]')"
except ImportError as e:  # pragma: no cover - environment without PyOpenCL
    _DEVICES, _WHY = [], f"PyOpenCL not importable: {e}"

REF = ReferenceBackend()
BUILDERS = {"sah": build_bvh, "lbvh": build_lbvh}     # the two tree builders, for the host-only BVH tests
EPS = 1e-4  # 0.1 mm (docs/architecture.md, Kernel contract)

_instances: dict[str, "OpenCLBackend"] = {}


def _backend(variant: str) -> "OpenCLBackend":
    """``<platform>``: defaults; ``-fp32``: the pure float32 path; ``-bvh2``: the binary-tree ray caster."""
    if variant not in _instances:
        plat, _, mode = variant.partition("-")
        _instances[variant] = OpenCLBackend(plat, fp64=False if mode == "fp32" else None,
                                            bvh_width=2 if mode == "bvh2" else None)
    return _instances[variant]


def _variants() -> list:
    out = []
    for d in list(_DEVICES):
        try:
            b = _backend(d)
        except BackendUnavailable:  # pragma: no cover - a listed platform that cannot open a context
            _DEVICES.remove(d)
            continue
        out.append(pytest.param(d, id=f"opencl:{d}"))
        if b.fp64:
            out.append(pytest.param(f"{d}-fp32", id=f"opencl:{d}-fp32"))
    return out or [pytest.param(None, marks=pytest.mark.skip(reason=_WHY), id="opencl")]


VARIANTS = _variants()
PLATFORMS = [p for p in VARIANTS if not str(p.id).endswith("-fp32")]
#: ray-mesh tests also run the other tree width than the device's default
RAY_VARIANTS = VARIANTS + [pytest.param(f"{d}-bvh2", id=f"opencl:{d}-bvh2") for d in _DEVICES
                           if _backend(d).bvh_width == 4]


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


# ============================================================================ exact geometry for judging
def _clip(o, d, t0, t1, lo, hi):
    """Parameter range of the segment o + t d, t in [t0, t1], inside the closed box [lo, hi]."""
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                return None
            continue
        ta, tb = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return (t0, t1) if t1 >= t0 else None


def _segment_box_distance(o, d, t0, t1, lo, hi) -> float:
    """Euclidean distance between the segment [t0, t1] and the box: minimise the convex function
    f(t) = |p(t) - clamp(p(t), lo, hi)| by ternary search (converges to ~1e-15 of the range)."""
    def f(t):
        p = o + t * d
        return float(np.linalg.norm(p - np.clip(p, lo, hi)))
    a, b = t0, t1
    for _ in range(200):
        m1, m2 = a + (b - a) / 3, b - (b - a) / 3
        if f(m1) <= f(m2):
            b = m2
        else:
            a = m1
    return min(f(a), f(t0), f(t1))


def assert_visits_within_tolerance(spec: GridSpec, o, d, t_end, got, want, eps=EPS):
    """``got`` equals ``want`` except for voxels the ray passes within ``eps`` of (docs/architecture.md,
    Kernel contract):

    * an extra voxel must lie within Euclidean distance ``eps`` of the segment (clipped to the grid);
    * a missing voxel may be entered by at most ``eps``: the segment must not reach the voxel shrunk by
      ``eps`` on every side.
    Both lists must be free of duplicates, and their common voxels must keep the same order.
    """
    got, want = np.asarray(got), np.asarray(want)
    assert len(np.unique(got)) == len(got), f"duplicate voxels in {got}"
    s = spec.voxel_size
    n = np.asarray(spec.shape)
    seg = _clip(o, d, 0.0, float(t_end), np.zeros(3), n * s)
    for v in np.setdiff1d(got, want):
        lo = np.array(np.unravel_index(v, spec.shape)) * s
        assert seg is not None, f"voxel {v} visited by a ray that misses the grid"
        dist = _segment_box_distance(o, d, seg[0], seg[1], lo, lo + s)
        assert dist <= eps, f"extra voxel {v} is {dist:.3g} m from the ray (> {eps})"
    for v in np.setdiff1d(want, got):
        lo = np.array(np.unravel_index(v, spec.shape)) * s
        inner = None if seg is None else _clip(o, d, seg[0], seg[1], lo + eps, lo + s - eps)
        assert inner is None or inner[1] - inner[0] <= 0, \
            f"voxel {v} skipped although the ray passes more than {eps} m inside it"
    common = np.intersect1d(got, want)
    np.testing.assert_array_equal(got[np.isin(got, common)], want[np.isin(want, common)])


# ============================================================================ adversarial inputs
def adversarial_rays(spec: GridSpec, rng, n=300):
    s = spec.voxel_size
    shape = np.asarray(spec.shape)
    ijk = rng.integers(0, shape + 1, (n, 3)).astype(float)
    jitter = rng.uniform(0, 1, (n, 3)) * (rng.uniform(size=(n, 3)) < 0.4)
    o = (ijk + jitter) * s                                   # faces, edges, corners of voxels
    d = rng.normal(size=(n, 3))
    zero = rng.uniform(size=(n, 3)) < 0.3
    d[zero] = np.where(rng.uniform(size=zero.sum()) < 0.5, 0.0, -0.0)   # axis-parallel, planar, -0.0
    d[np.all(d == 0, axis=1)] = [0.0, -1.0, 0.0]
    diag = rng.uniform(size=n) < 0.2
    d[diag] = rng.choice([-1.0, 1.0], (diag.sum(), 3))       # through edges and corners
    outside = rng.uniform(size=n) < 0.25
    o[outside] = -3 * s + rng.uniform(0, 1, (outside.sum(), 3)) * (shape + 6) * s
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # near-ties: rays aimed within 1e-7 m of a voxel edge (the float32 walk must defer to float64)
    k = n // 5
    tgt = (rng.integers(1, shape, (k, 3)) * s).astype(float)
    tgt[:, 2] += rng.uniform(0.2, 0.8, k) * s                 # on an x-y edge line, inside in z
    tgt[:, :2] += rng.uniform(-1e-7, 1e-7, (k, 2))
    src = rng.uniform(0, 1, (k, 3)) * shape * s
    dd = tgt - src
    dd /= np.linalg.norm(dd, axis=1, keepdims=True)
    o = np.concatenate([o, src])
    d = np.concatenate([d, dd])
    t_end = rng.choice([0.0, 0.3, 2.0, 50.0, 1e3], len(o))
    return o, d, t_end


def random_rays(spec: GridSpec, rng, n=1500, t=30.0):
    size = np.asarray(spec.shape) * spec.voxel_size
    o = rng.uniform(-0.1 * size, 1.1 * size, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d, np.full(n, t)


def _csr_rows(offsets, voxels):
    return [voxels[offsets[i]:offsets[i + 1]] for i in range(len(offsets) - 1)]


# ============================================================================ BVH (host only)
def _random_soup(rng, n):
    c = rng.uniform(-10, 10, (n, 1, 3))
    v = (c + rng.normal(scale=0.5, size=(n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n).reshape(n, 3)


def deep_scene(n=120, r=1.35, first=0):
    """Tiny triangles at x = r**i: binned SAH peels a few off per level, a chain instead of a tree."""
    x = float(r) ** (np.arange(n) + first)
    w = 1e-3 * x
    v0 = np.stack([x, np.zeros(n), np.zeros(n)], 1)
    v1 = np.stack([x, w, np.zeros(n)], 1)
    v2 = np.stack([x, np.zeros(n), w], 1)
    return np.stack([v0, v1, v2], 1).reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


@pytest.mark.parametrize("builder", ["sah", "lbvh"])
@pytest.mark.parametrize("n", [1, 2, 3, 5, 17, 1000])
def test_bvh_structure(n, builder, rng):
    v, f = _random_soup(rng, n)
    bvh = BUILDERS[builder](v, f)
    validate_bvh(bvh, v, f)
    assert sorted(bvh.order.tolist()) == list(range(n))
    assert bvh.depth <= DEFAULT_MAX_DEPTH


@pytest.mark.parametrize("builder", ["sah", "lbvh"])
def test_bvh_identical_triangles_split_by_median(builder):
    """One centre for every triangle: SAH splits at the object median, Morton order by the triangle index
    (the keys' low bits); either way a balanced tree."""
    v = np.tile(np.eye(3), (100, 1))
    f = np.arange(300).reshape(100, 3)
    bvh = BUILDERS[builder](v, f, leaf_size=4)
    validate_bvh(bvh, v, f)
    assert bvh.depth <= int(need_levels(100, 4)) + 1


def test_bvh4_collapse_keeps_every_triangle_once(rng):
    from place3d_kernels.backends.opencl.bvh import collapse_bvh4

    v, f = _random_soup(rng, 3000)
    bvh = build_bvh(v, f)
    b4 = collapse_bvh4(bvh)
    ints = b4.nodes[:, 24:32].view(np.int32)
    ref, cnt = ints[:, :4], ints[:, 4:]
    seen = np.zeros(len(f), int)
    for r_, c_ in zip(ref[cnt > 0], cnt[cnt > 0]):
        seen[bvh.order[r_:r_ + c_]] += 1
    assert np.all(seen == 1)
    inner = ref[cnt == 0]
    assert sorted(inner.tolist()) == list(range(1, b4.n_nodes))   # every node but the root is a child once
    assert b4.depth <= bvh.depth and b4.n_nodes < bvh.n_nodes


def _subtree_faces(bvh, root):
    """Original face ids in the leaves under binary node ``root``."""
    refs = bvh.child_refs()
    out, stack = set(), [root]
    while stack:
        node = stack.pop()
        for c in range(2):
            ref, cnt = int(refs[node, 2 * c]), int(refs[node, 2 * c + 1])
            if cnt == 0:
                stack.append(ref)
            else:
                out.update(bvh.order[ref:ref + cnt].tolist())
    return out


@pytest.mark.parametrize("builder", ["sah", "lbvh"])
@pytest.mark.parametrize("sizes", [[1], [2], [1, 1, 1], [5, 1, 300, 2, 1, 40], [1000, 17]])
def test_grouped_bvh_gives_each_group_a_tree_of_its_own(sizes, builder, rng):
    """build_bvh's groups: node g is group g's root and its subtree holds exactly that group's faces (every
    face in one leaf, boxes nested, depth within the cap); the 4-wide collapse keeps the roots as nodes
    0 .. G-1, each over its group's faces; one group is the plain build, byte for byte."""
    from place3d_kernels.backends.opencl.bvh import collapse_bvh4

    v, f = _random_soup(rng, sum(sizes))
    bvh = BUILDERS[builder](v, f, groups=sizes)
    validate_bvh(bvh, v, f)
    assert bvh.roots == len(sizes) and bvh.depth <= DEFAULT_MAX_DEPTH
    starts = np.concatenate([[0], np.cumsum(sizes)])
    for g in range(len(sizes)):
        assert _subtree_faces(bvh, g) == set(range(starts[g], starts[g + 1]))
    b4 = collapse_bvh4(bvh)
    ints = b4.nodes[:, 24:32].view(np.int32)
    for g in range(len(sizes)):
        faces, stack = set(), [g]
        while stack:
            node = stack.pop()
            for r_, c_ in zip(ints[node, :4], ints[node, 4:]):
                if c_ == 0:
                    stack.append(int(r_))
                elif c_ > 0:
                    faces.update(bvh.order[r_:r_ + c_].tolist())
        assert faces == set(range(starts[g], starts[g + 1]))
    if len(sizes) == 1:
        plain = BUILDERS[builder](v, f)
        assert plain.nodes.tobytes() == bvh.nodes.tobytes() and plain.tris.tobytes() == bvh.tris.tobytes()


def test_grouped_bvh_refuses_groups_that_do_not_cover_the_faces(rng):
    v, f = _random_soup(rng, 10)
    for bad in ([], [4, 5], [4, 7], [10, 0], [11, -1]):
        with pytest.raises(ValueError, match="groups must be face counts"):
            build_bvh(v, f, groups=bad)
    with pytest.raises(ValueError, match="layout='levels' only"):
        build_bvh(v, f, groups=[10], layout="dfs")


def test_dfs_layout_is_the_same_tree_with_left_children_next(rng):
    """bvh.dfs_layout renumbers inner nodes in depth-first preorder: a valid tree over the same leaves
    (the same triangle order, depth and leaf count), each inner left child in the row after its parent,
    and the ray caster's hits unchanged on every OpenCL device here, for both tree widths."""
    from place3d_kernels.backends.opencl.bvh import dfs_layout

    v, f = _random_soup(rng, 3000)
    bvh = build_bvh(v, f)
    dfs = dfs_layout(bvh)
    assert build_bvh(v, f, layout="dfs").nodes.tobytes() == dfs.nodes.tobytes()
    validate_bvh(dfs, v, f)
    assert (dfs.order == bvh.order).all() and dfs.depth == bvh.depth and dfs.n_leaves == bvh.n_leaves
    ints = dfs.nodes[:, 12:16].view(np.int32)
    left = np.flatnonzero(ints[:, 1] == 0)
    assert len(left) > 100 and (ints[left, 0] == left + 1).all()
    assert sorted(np.concatenate([ints[ints[:, 1] == 0, 0], ints[ints[:, 3] == 0, 2]]).tolist()) == \
        list(range(1, len(ints)))                          # every inner node but the root a child once
    with pytest.raises(ValueError, match="layout"):
        build_bvh(v, f, layout="bfs")
    _same_hits_with_options(v, f, rng, {}, {"layout": "dfs"})


def _same_hits_with_options(v, f, rng, before: dict, after: dict) -> None:
    """2000 random rays cast into (v, f) built with ``bvh_options`` ``before`` and ``after``: the same hits on
    every OpenCL device here, for both tree widths."""
    o = rng.uniform(-1.0, 2.0, (2000, 3))
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for dev in _DEVICES:
        for width in (2, 4):
            b = OpenCLBackend(dev, bvh_width=width)
            b.bvh_options = before
            want = b.raycast(b.upload_mesh(v, f), o, d, 5.0)
            b.bvh_options = after
            got = b.raycast(b.upload_mesh(v, f), o, d, 5.0)
            assert np.isfinite(want[0]).sum() > 200
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def test_widest_axis_trees_are_valid_and_give_the_same_hits(rng):
    """``full_sah_limit=0`` (the CPU devices' builds: each node split on its widest centroid axis) gives another
    valid tree (every face in one leaf, boxes nested, the depth cap kept), and the same hits as the three-axis
    tree on every OpenCL device here, for both tree widths and a grouped build."""
    v, f = _random_soup(rng, 3000)
    three, widest = build_bvh(v, f), build_bvh(v, f, full_sah_limit=0)
    validate_bvh(widest, v, f)
    assert widest.nodes.tobytes() != three.nodes.tobytes()      # another tree, or the test proves nothing
    validate_bvh(build_bvh(v, f, full_sah_limit=0, groups=[1000, 1, 1999]), v, f)
    _same_hits_with_options(v, f, rng, {"full_sah_limit": 65536}, {"full_sah_limit": 0})


def test_morton_trees_are_valid_and_give_the_same_hits(rng):
    """``lbvh.build_lbvh`` (every OpenCL device's builds) gives another valid tree (every face in one leaf, boxes
    nested, within the depth cap, leaves of at most ``leaf_size``), and the same hits as the SAH tree on every
    OpenCL device here, for both tree widths; a tree built with the town's part joined under a route's
    (``join_bvh``) too."""
    from place3d_kernels.backends.opencl.bvh import join_bvh

    v, f = _random_soup(rng, 3000)
    sah, morton = build_bvh(v, f), build_lbvh(v, f)
    validate_bvh(morton, v, f)
    assert morton.nodes.tobytes() != sah.nodes.tobytes()        # another tree, or the test proves nothing
    assert morton.order.tolist() != sah.order.tolist()
    counts = morton.child_refs()[:, [1, 3]]
    assert counts.max() <= 4 and (counts > 0).any()
    joined = join_bvh(build_lbvh(v, f[:1000], max_depth=DEFAULT_MAX_DEPTH - 1),
                      build_lbvh(v, f[1000:], max_depth=DEFAULT_MAX_DEPTH - 1), np.zeros(3))
    validate_bvh(joined, v, f)
    for dev in _DEVICES:
        b = OpenCLBackend(dev)
        assert b.bvh_options == ({"builder": "lbvh", "full_sah_limit": 0} if b.is_cpu else {"builder": "lbvh"})
    _same_hits_with_options(v, f, rng, {}, {"builder": "lbvh"})
    if _DEVICES:
        b = OpenCLBackend(_DEVICES[0])
        b.bvh_options = {"builder": "octree"}
        with pytest.raises(ValueError, match="builder must be"):
            b.upload_mesh(v, f)


def test_morton_tree_deeper_than_the_cap_falls_back_to_sah():
    """``morton_tree`` gives None where its tree would exceed ``max_depth``; ``build_lbvh`` then builds SAH's tree
    with its arguments, byte for byte, within the cap."""
    v, f = deep_scene(210, 2.0, -105)        # tiny triangles at 2**i: a chain in Morton order too
    cap = int(need_levels(len(f), 4)) + 2
    assert morton_tree(v, f, max_depth=None).depth > cap, "the scene must be deeper than the cap in Morton order"
    assert morton_tree(v, f, max_depth=cap) is None
    got, want = build_lbvh(v, f, max_depth=cap, full_sah_limit=0), build_bvh(v, f, max_depth=cap, full_sah_limit=0)
    validate_bvh(got, v, f)
    assert got.depth <= cap and got.nodes.tobytes() == want.nodes.tobytes()


def test_need_levels():
    assert need_levels(np.array([1, 4, 5, 8, 9, 16, 17, 2**20]), 4).tolist() == [0, 0, 1, 1, 2, 2, 3, 18]


def test_bvh_depth_cap_holds_on_a_scene_built_to_exceed_it():
    v, f = deep_scene(210, 2.0, -105)        # within float32 range: 2**-105 ... 2**104
    free = build_bvh(v, f, max_depth=None)
    assert free.depth > DEFAULT_MAX_DEPTH, "the scene must defeat plain SAH (else the test proves nothing)"
    capped = build_bvh(v, f)
    validate_bvh(capped, v, f)
    assert capped.depth <= DEFAULT_MAX_DEPTH
    tight = build_bvh(v, f, max_depth=int(need_levels(len(f), 4)))
    validate_bvh(tight, v, f)
    assert tight.depth <= int(need_levels(len(f), 4))


def test_bvh_builds_large_meshes_fast(rng):
    import time

    v, f = _random_soup(rng, 200_000)
    t = time.process_time()
    bvh = build_bvh(v, f)
    assert time.process_time() - t < 5.0
    assert bvh.depth <= DEFAULT_MAX_DEPTH


# ============================================================================ backend basics and errors
def test_unknown_platform_names_what_exists():
    if not _DEVICES:
        pytest.skip(_WHY)
    with pytest.raises(BackendUnavailable) as e:
        OpenCLBackend("no-such-vendor")
    msg = str(e.value)
    assert "no-such-vendor" in msg and _DEVICES[0] in msg and "pip install" in msg


def test_no_platform_message(monkeypatch):
    if not _DEVICES:
        pytest.skip(_WHY)
    from place3d_kernels.backends.opencl import _runtime

    monkeypatch.setattr(_runtime, "platform_table", lambda vendor=None: {})
    with pytest.raises(BackendUnavailable, match=r"no CL platforms.*pip install 'place3d-kernels\[opencl\]'"):
        OpenCLBackend("pocl")


def test_a_named_platform_alone_is_probed_and_its_probe_context_used_once():
    """OpenCLBackend("pocl") in a fresh process probes PoCL's platform only (another vendor's driver is not
    started: on the H200 host NVIDIA's beside PoCL), and takes the probe's context instead of making a second;
    a second backend on that device makes a context of its own; listing every platform keeps no probe context."""
    import subprocess
    import sys

    if "pocl" not in _DEVICES:
        pytest.skip("needs PoCL")
    code = ("from place3d_kernels.backends.opencl import _runtime as rt\n"
            "from place3d_kernels.backends.opencl.host import OpenCLBackend\n"
            "a = OpenCLBackend('pocl')\n"
            "print('PROBES', len(rt._probed))\n"
            "print('LEFT', len(rt._probe_contexts))\n"
            "b = OpenCLBackend('pocl')\n"
            "print('DISTINCT', a.ctx.int_ptr != b.ctx.int_ptr)\n"
            "print('ALL', sorted(rt.platform_table()))\n"
            "print('KEPT', len(rt._probe_contexts))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = dict(ln.split(" ", 1) for ln in out.stdout.splitlines())
    assert lines["PROBES"] == "1"                   # PoCL's platform only, whatever else is installed
    assert lines["LEFT"] == "0" and lines["DISTINCT"] == "True"
    assert "pocl" in lines["ALL"] and lines["KEPT"] == "0"   # a listing of every platform keeps no context


def _add_one(ctx, dev):
    import pyopencl as cl

    q = cl.CommandQueue(ctx)
    prg = cl.Program(ctx, "__kernel void add1(__global int *a) { a[get_global_id(0)] += 1; }").build()
    a = np.arange(64, dtype=np.int32)
    buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
    prg.add1(q, a.shape, None, buf)
    out = np.empty_like(a)
    cl.enqueue_copy(q, out, buf)
    return out


@pytest.mark.parametrize("platform", _DEVICES or [pytest.param(None, marks=pytest.mark.skip(reason=_WHY))])
def test_a_context_made_through_the_loader_is_pyopencls_and_owns_one_reference(platform, monkeypatch):
    """new_context makes the context through ctypes (PyOpenCL holds the GIL in clCreateContext), never through
    PyOpenCL's constructor where the loader is found, and hands PyOpenCL a context it owns alone: one
    reference, freed with it; a kernel runs there."""
    import sys

    import pyopencl as cl

    from place3d_kernels.backends.opencl import _runtime as rt

    dev = rt.platform_table()[platform][1][0]
    if sys.platform.startswith("linux"):
        assert rt._icd_loader() is not None          # PyOpenCL's own libOpenCL, found in this process's maps
    made = cl.Context

    class NoConstructor:                              # PyOpenCL's clCreateContext refused; from_int_ptr kept
        from_int_ptr = staticmethod(made.from_int_ptr)

        def __new__(cls, *a, **k):
            raise AssertionError("new_context called PyOpenCL's Context()")

    if rt._icd_loader() is not None:
        monkeypatch.setattr(rt.cl, "Context", NoConstructor)
    ctx = rt.new_context(dev)
    monkeypatch.undo()
    assert isinstance(ctx, made) and ctx.devices == [dev]
    assert ctx.get_info(cl.context_info.REFERENCE_COUNT) == 1
    np.testing.assert_array_equal(_add_one(ctx, dev), np.arange(1, 65, dtype=np.int32))


def test_without_the_loader_a_context_is_made_by_pyopencl(monkeypatch):
    if not _DEVICES:
        pytest.skip(_WHY)
    import pyopencl as cl

    from place3d_kernels.backends.opencl import _runtime as rt

    dev = rt.platform_table()[_DEVICES[0]][1][0]
    made, calls = cl.Context, []
    monkeypatch.setattr(rt, "_icd_loader", lambda: None)
    monkeypatch.setattr(rt.cl, "Context", lambda devices: calls.append(devices) or made(devices))
    ctx = rt.new_context(dev)
    monkeypatch.undo()
    assert calls == [[dev]]                           # PyOpenCL's own constructor, on that device alone
    assert isinstance(ctx, cl.Context) and ctx.get_info(cl.context_info.REFERENCE_COUNT) == 1
    np.testing.assert_array_equal(_add_one(ctx, dev), np.arange(1, 65, dtype=np.int32))


def test_missing_pyopencl_is_an_import_error_and_the_backend_is_listed_as_missing():
    import subprocess
    import sys

    code = ("import sys; sys.modules['pyopencl'] = None\n"
            "try:\n    import place3d_kernels.backends.opencl\nexcept ImportError as e:\n    print('IMPORT', e)\n"
            "import place3d_kernels as p3k\n"
            "print('NAMES', [b for b in p3k.available_backends() if b.startswith('opencl')])\n"
            "print('REPORT', [r for r in p3k.backend_report() if r[0] == 'opencl'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120).stdout
    assert "IMPORT PyOpenCL is not installed" in out
    assert "NAMES []" in out
    assert "place3d-kernels[opencl]" in out


def test_bad_device_index():
    if not _DEVICES:
        pytest.skip(_WHY)
    with pytest.raises(BackendUnavailable, match="device index"):
        OpenCLBackend(f"{_DEVICES[0]}:99")


def test_opencl_devices_are_short_unique_names():
    from place3d_kernels.backends.opencl._runtime import short_name

    assert short_name("Portable Computing Language") == "pocl"
    assert short_name("NVIDIA CUDA") == "nvidia"
    assert short_name("AMD Accelerated Parallel Processing") == "amd"
    assert short_name("Intel(R) OpenCL HD Graphics") == "intel"
    assert short_name("Some Vendor 9") == "some"
    assert len(set(_DEVICES)) == len(_DEVICES)
    assert all(d == d.lower() and " " not in d for d in _DEVICES)


@pytest.mark.parametrize("variant", PLATFORMS)
def test_programs_compiled_once_per_context(variant, rng):
    from place3d_kernels.backends.opencl import _runtime

    b = _backend(variant)
    spec = GridSpec(0.5, (4, 4, 4))
    o, d, t = random_rays(spec, rng, 10)
    b.coverage(spec, o, d, t)
    v, f = _random_soup(rng, 20)
    h = b.upload_mesh(v, f)
    b.raycast(h, o, d, t)
    n_programs = len(_runtime._programs)
    k = b._kernel("dda_coverage")
    for _ in range(3):
        b.coverage(spec, o, d, t)
        b.raycast(h, o, d, t)
    assert len(_runtime._programs) == n_programs
    assert b._kernel("dda_coverage") is k


@pytest.mark.parametrize("variant", PLATFORMS)
def test_mesh_and_grid_handles_keep_device_buffers(variant, rng):
    b = _backend(variant)
    v, f = _random_soup(rng, 50)
    h = b.upload_mesh(v, f)
    tree = h.bvh4 if h.width == 4 else h.bvh
    assert h.nodes.size == tree.nodes.nbytes and h.tris.size == h.bvh.tris.nbytes
    spec = GridSpec(0.5, (4, 5, 6))
    g = b.prepare_grid(spec, np.arange(spec.n_voxels), None)
    assert g.weights.size == spec.n_voxels * 8 and not g.use_stop
    with pytest.raises(ValueError, match="one int64 per voxel"):
        b.prepare_grid(spec, np.arange(7), None)
    # handles hold copies: editing the inputs afterwards changes nothing
    w = rng.integers(0, 100, spec.n_voxels)
    stop = (rng.uniform(size=spec.n_voxels) < 0.05).astype(np.uint8)
    g = b.prepare_grid(spec, w, stop)
    el, az = np.array([-0.1, 0.0, 0.1]), np.linspace(0, 6, 40)
    poses = np.array([[[1.1, 1.2, 1.3, 0, 0, 0]]])
    before = b.score_placements(g, el, az, 5.0, poses)
    w[:] = 0
    stop[:] = 1
    after = b.score_placements(g, el, az, 5.0, poses)
    assert before[0][0] == after[0][0] and before[1][0] == after[1][0] > 0
    with pytest.raises(TypeError, match="upload_mesh"):
        b.raycast(object(), v[:1], v[:1], [1.0])


@pytest.mark.parametrize("variant", PLATFORMS)
def test_empty_inputs(variant):
    b = _backend(variant)
    spec = GridSpec(0.5, (4, 4, 4))
    e3 = np.empty((0, 3))
    off, vox = b.traverse(spec, e3, e3, np.empty(0))
    assert off.tolist() == [0] and vox.size == 0
    assert not b.coverage(spec, e3, e3, np.empty(0)).any()
    assert b.voxel_keys(spec, e3).size == 0
    vv, ll = b.vote(np.empty(0, np.int64), np.empty(0, np.int32), 22)
    assert vv.size == 0 and ll.size == 0
    vv, ll = b.vote(np.array([3, 4, -1]), np.array([0, 0, 5]), 22)   # nobody votes
    assert vv.size == 0 and ll.size == 0


# ============================================================================ traversal vs reference
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("voxel", [0.2, 1.0, 0.05])
def test_traverse_adversarial_vs_reference(variant, voxel, rng):
    b = _backend(variant)
    spec = GridSpec(voxel, tuple(int(round(x / voxel)) for x in (6.4, 3.2, 1.6)))
    o, d, t_end = adversarial_rays(spec, rng)
    got = _csr_rows(*b.traverse(spec, o, d, t_end))
    want = _csr_rows(*REF.traverse(spec, o, d, t_end))
    for i in range(len(o)):
        assert_visits_within_tolerance(spec, o[i], d[i], t_end[i], got[i], want[i])
    if b.fp64:
        # Away from degenerate starts (origin on a voxel plane: the ray may run exactly along edges, where
        # the reference itself decides at 1e-17 m), the fp64 path settles every near-tie in float64 as the
        # reference does: identical lists, including the rays aimed within 1e-7 m of an edge.
        frac = o / spec.voxel_size
        clean = np.all(np.abs(frac - np.round(frac)) > 1e-4, axis=1)
        assert clean[-(len(o) // 6):].all() and clean.sum() > 60
        for i in np.flatnonzero(clean):
            np.testing.assert_array_equal(got[i], want[i], err_msg=f"ray {i}: {o[i]} {d[i]} {t_end[i]}")


@pytest.mark.parametrize("variant", VARIANTS)
def test_traverse_random_vs_reference(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.2, (100, 100, 20))
    o, d, t = random_rays(spec, rng, 1500)
    off, vox = b.traverse(spec, o, d, t)
    roff, rvox = REF.traverse(spec, o, d, t)
    assert np.all((vox >= 0) & (vox < spec.n_voxels))
    if b.fp64:
        np.testing.assert_array_equal(off, roff)
        np.testing.assert_array_equal(vox, rvox)
    else:
        got, want = _csr_rows(off, vox), _csr_rows(roff, rvox)
        for i in range(len(o)):
            assert_visits_within_tolerance(spec, o[i], d[i], t[i], got[i], want[i])


@pytest.mark.parametrize("variant", VARIANTS)
def test_tiny_voxels_on_long_rays(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.01, (20000, 50, 50))                    # 200 m x 0.5 m x 0.5 m
    n = 6
    o = np.column_stack([np.full(n, 0.003), rng.uniform(0.1, 0.4, n), rng.uniform(0.1, 0.4, n)])
    d = np.column_stack([np.ones(n), rng.uniform(-1e-3, 1e-3, n), rng.uniform(-1e-3, 1e-3, n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = _csr_rows(*b.traverse(spec, o, d, np.full(n, 200.0)))
    want = _csr_rows(*REF.traverse(spec, o, d, np.full(n, 200.0)))
    for i in range(n):
        assert len(want[i]) > 10_000
        assert_visits_within_tolerance(spec, o[i], d[i], 200.0, got[i], want[i])
        if b.fp64:
            np.testing.assert_array_equal(got[i], want[i])


@pytest.mark.parametrize("variant", VARIANTS)
def test_coverage_and_stop_mask_vs_reference(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.25, (40, 32, 12))
    o, d, t = random_rays(spec, rng, 800, t=12.0)
    stop = (rng.uniform(size=spec.n_voxels) < 0.01).astype(np.uint8)
    for s in (None, stop):
        got = b.coverage(spec, o, d, t, s)
        want = REF.coverage(spec, o, d, t, s)
        if b.fp64:
            np.testing.assert_array_equal(got, want)
        else:
            assert (got != want).sum() <= 2
        off, vox = b.traverse(spec, o, d, t, s)
        m = np.zeros(spec.n_voxels, bool)
        m[vox] = True
        np.testing.assert_array_equal(m, got)                 # coverage is the union of traversal
        if s is not None:                                     # each list ends at its first stop voxel
            for row in _csr_rows(off, vox):
                hit = np.flatnonzero(s[row])
                assert len(hit) == 0 or hit[0] == len(row) - 1


# ============================================================================ batched scores
@pytest.mark.parametrize("variant", VARIANTS)
def test_score_placements_identical_to_reference(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.2, (60, 50, 15))
    el = np.deg2rad(np.linspace(-25, 3, 6))
    az = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    lo, hi = [1, 1, 0.5, -0.1, -0.1, -np.pi], [11, 9, 2.5, 0.1, 0.1, np.pi]
    poses = rng.uniform(lo, hi, (4, 3, 6))
    poses[1, :, 3:] = 0.0                                    # axis-aligned beams (exact zeros)
    poses[2, 0, :3] = [2.0, 3.0, 1.0]                        # a sensor on a voxel corner
    w = rng.integers(0, 2**40, spec.n_voxels)
    stop = (rng.uniform(size=spec.n_voxels) < 0.003).astype(np.uint8)
    for s in (None, stop):
        got = b.score_placements(b.prepare_grid(spec, w, s), el, az, 25.0, poses)
        want = REF.score_placements(REF.prepare_grid(spec, w, s), el, az, 25.0, poses)
        if b.fp64:
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
        else:
            assert np.all(np.abs(got[1] - want[1]) <= 2)
    # one candidate alone scores the same as in a batch, and repeated calls are deterministic
    h = b.prepare_grid(spec, w, stop)
    s_all, c_all = b.score_placements(h, el, az, 25.0, poses)
    s_one, c_one = b.score_placements(h, el, az, 25.0, poses[2:3])
    assert s_one[0] == s_all[2] and c_one[0] == c_all[2]
    np.testing.assert_array_equal(b.score_placements(h, el, az, 25.0, poses)[0], s_all)


def test_prepared_grid_rejects_a_bad_stop_mask_on_both_strategies():
    """Each strategy keeps only the mask form it reads (bytes or bricked bits); both still check the size."""
    if not _DEVICES:
        pytest.skip(_WHY)
    spec = GridSpec(0.25, (8, 8, 4))
    for strategy in ("private", "atomic"):
        b = OpenCLBackend(_DEVICES[0], score_strategy=strategy)
        with pytest.raises(ValueError, match="one uint8 per voxel"):
            b.prepare_grid(spec, np.zeros(spec.n_voxels, np.int64), np.zeros(5, np.uint8))
        h = b.prepare_grid(spec, np.zeros(spec.n_voxels, np.int64), None)
        assert (h.stop is None) == (strategy == "atomic") and (h.masks is None) == (strategy == "private")


@pytest.mark.parametrize("shape", [(41, 38, 11), (8, 4, 1), (3, 9, 2)])
def test_flat_masks_on_the_device_match_their_layout(shape, rng):
    """The atomic strategy's score kernel reads flat 8 x 4 x 1 brick masks, made on the device from the grid's
    4 x 4 x 2 pairs (grid.cl flat_masks): the words of bricks.flat_brick_masks, partial bricks included."""
    if not _DEVICES:
        pytest.skip(_WHY)
    import pyopencl as cl

    from place3d_kernels.backends.bricks import flat_brick_masks

    spec = GridSpec(0.25, shape)
    w = np.where(rng.uniform(size=spec.n_voxels) < 0.4, rng.integers(1, 2**40, spec.n_voxels), 0)
    stop = (rng.uniform(size=spec.n_voxels) < 0.2).astype(np.uint8)
    b = OpenCLBackend(_DEVICES[0], score_strategy="atomic")
    h = b.prepare_grid(spec, w, stop)
    want = flat_brick_masks(shape, w != 0, stop != 0)
    got = np.empty_like(want)
    cl.enqueue_copy(b.queue, got, b._flat_masks(h))
    np.testing.assert_array_equal(got, want)
    assert b._flat_masks(h) is h.flat, "made once per grid"


@pytest.mark.parametrize("kernel", ["flat", "gpu"])
def test_gpu_score_on_ties_matches_the_reference(kernel, rng):
    """The atomic strategy's kernels (score_rays_flat: grid.cl's walk, flat bricks, a flush per brick; score_rays_gpu:
    the same with the min/median certainty test and no grid test in the loop) on rays built of ties: LiDARs on
    voxel corners and edges, azimuths on the axes and diagonals (equal direction components, components exactly
    0), elevations 0 and 45 degrees; sums and counts equal the reference's."""
    if not _DEVICES:
        pytest.skip(_WHY)
    spec = GridSpec(0.25, (19, 14, 7))
    w = np.where(rng.uniform(size=spec.n_voxels) < 0.5, rng.integers(1, 2**40, spec.n_voxels), 0)
    stop = (rng.uniform(size=spec.n_voxels) < 0.02).astype(np.uint8)
    el = np.deg2rad([-45.0, -10.0, 0.0, 45.0])
    az = np.deg2rad(np.arange(0.0, 360.0, 45.0))
    poses = np.array([[[1.0, 1.0, 0.75, 0, 0, 0], [2.5, 1.25, 1.0, 0, 0, 0]],
                      [[2.125, 2.0, 0.5, 0, 0, 0], [0.0, 3.5, 1.25, 0, 0, 0]],
                      [[4.75, 3.25, 1.5, 0, 0, 0], [3.0, 0.25, 0.25, 0, 0, 0]]])
    ref = ReferenceBackend()
    want = ref.score_placements(ref.prepare_grid(spec, w, stop), el, az, 20.0, poses)
    b = OpenCLBackend(_DEVICES[0], score_strategy="atomic", score_kernel=kernel)
    got = b.score_placements(b.prepare_grid(spec, w, stop), el, az, 20.0, poses)
    assert (want[1] > 0).all()
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_score_strategies_agree(rng):
    """Private bitsets + OR-reduction (CPU default) and the shared atomic bitset (GPU default), with either
    atomic kernel, any number of rays per work-item and any population size, give the same exact sums."""
    if not _DEVICES:
        pytest.skip(_WHY)
    spec = GridSpec(0.25, (41, 38, 11))      # partial 4 x 4 x 2 and 8 x 4 x 1 bricks at the far faces
    el = np.deg2rad(np.linspace(-20, 2, 5))
    az = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    poses = rng.uniform([1, 1, 0.5, 0, 0, -3], [9, 9, 2, 0, 0, 3], (9, 2, 6))
    w = rng.integers(0, 2**40, spec.n_voxels)
    w[rng.uniform(size=spec.n_voxels) < 0.7] = 0   # free space: the atomic path skips reading zero weights
    stop = (rng.uniform(size=spec.n_voxels) < 0.01).astype(np.uint8)
    res = []
    for strategy, per, kernel in (("private", 1, None), ("atomic", 1, "flat"), ("atomic", 7, "flat"),
                                  ("atomic", 64, "flat"), ("atomic", 1, "gpu")):
        b = OpenCLBackend(_DEVICES[0], rays_per_item=per, score_strategy=strategy, score_kernel=kernel)
        res.append(b.score_placements(b.prepare_grid(spec, w, stop), el, az, 15.0, poses))
        one = b.score_placements(b.prepare_grid(spec, w, stop), el, az, 15.0, poses[4:5])
        assert one[0][0] == res[-1][0][4] and one[1][0] == res[-1][1][4]
    for r in res[1:]:
        np.testing.assert_array_equal(r[0], res[0][0])
        np.testing.assert_array_equal(r[1], res[0][1])



@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("n_az", [1, 3, 50])
def test_lane_walk_equals_one_ray_walk_and_reference(variant, n_az, rng):
    """The CPU walk in vector lanes (walk_lanes.cl) against score_walk (one ray per work-item), and with
    doubles against the reference: rays from voxel corners along 45-degree and 1:2 diagonals (exact ties, so lanes take the
    slow step), rays leaving the grid or ending inside it, stop voxels, and fewer rays than lanes (n_az = 1: 5 rays per LiDAR,
    idle lanes from the start)."""
    b = _backend(variant)
    if not b.is_cpu:
        pytest.skip("the lane walk is the CPU strategy's")
    spec = GridSpec(0.25, (32, 28, 12))                 # exact binary planes: ties are exact
    el = np.radians([-45.0, -np.degrees(np.arctan(0.5)), -10.0, 0.0, 30.0])
    az = np.radians(np.concatenate([[45.0, 0.0, 90.0], np.degrees(np.arctan2([1, 2, -1], [2, 1, 2]))]))[:n_az]
    if n_az == 50:
        az = rng.uniform(-np.pi, np.pi, 50)
    poses = np.zeros((6, 2, 6))
    poses[..., :3] = rng.integers(2, 24, (6, 2, 3)) * 0.25 * np.array([1, 1, 0.5])
    poses[..., 5] = np.radians(rng.choice([0.0, 45.0, 90.0, -135.0], (6, 2)))
    poses[4:, :, 3:] = rng.uniform(-0.5, 0.5, (2, 2, 3))  # two rigs off the lattice
    w = rng.integers(0, 2**40, spec.n_voxels)
    w[rng.uniform(size=spec.n_voxels) < 0.6] = 0
    stop = (rng.uniform(size=spec.n_voxels) < 0.02).astype(np.uint8)
    for s, t_max in ((stop, 12.0), (None, 12.0), (None, 2.3)):     # 2.3 m: segments ending inside the grid
        ref = REF.score_placements(REF.prepare_grid(spec, w, s), el, az, t_max, poses)
        got = {}
        for lanes in (True, False):
            b.walk_lanes = lanes
            try:
                got[lanes] = b.score_placements(b.prepare_grid(spec, w, s), el, az, t_max, poses)
            finally:
                b.walk_lanes = b.is_cpu
        np.testing.assert_array_equal(got[True][0], got[False][0])
        np.testing.assert_array_equal(got[True][1], got[False][1])
        if b.fp64:      # without doubles, near-ties are settled in float32: within the contract, not the bits
            np.testing.assert_array_equal(got[True][0], ref[0])
            np.testing.assert_array_equal(got[True][1], ref[1])

# ============================================================================ rays, keys, vote
@pytest.mark.parametrize("variant", VARIANTS)
def test_lidar_rays_vs_reference(variant, rng):
    b = _backend(variant)
    el = np.deg2rad(np.linspace(-30, 10, 7))
    az = np.linspace(-np.pi, np.pi, 33)
    poses = rng.uniform(-3, 3, (3, 6))
    o, d = b.lidar_rays(el, az, poses)
    ro, rd = REF.lidar_rays(el, az, poses)
    tol = 1e-12 if b.fp64 else 1e-6
    np.testing.assert_allclose(o, ro, atol=tol * 10)
    np.testing.assert_allclose(d, rd, atol=tol)
    for a in (o, d):         # on CPU devices the kernel writes the returned arrays: each call its own
        assert a.dtype == np.float64 and a.shape == (3 * 7 * 33, 3) and a.flags.c_contiguous
    kept = o.copy(), d.copy()
    b.lidar_rays(el, az, poses + 1.0)
    assert np.array_equal(o, kept[0]) and np.array_equal(d, kept[1])
    e = b.lidar_rays(el, az, np.zeros((0, 6)))
    assert e[0].shape == (0, 3) and e[1].shape == (0, 3)


@pytest.mark.parametrize("variant", VARIANTS)
def test_voxel_keys_vs_reference(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.2, (30, 20, 10))
    p = rng.uniform(-1, 7, (5000, 3))
    p[:500] = rng.integers(-2, 32, (500, 3)) * 0.2           # on voxel faces, edges, corners, borders
    got, want = b.voxel_keys(spec, p), REF.voxel_keys(spec, p)
    if b.fp64:
        np.testing.assert_array_equal(got, want)
    else:
        assert (got != want).mean() < 0.15                   # float32 rounds points on faces either way


@pytest.mark.parametrize("on_host", [False, True])
@pytest.mark.parametrize("variant", VARIANTS)
def test_vote_identical_to_reference(variant, on_host, rng, monkeypatch):
    # the kernels and the host's sort (what a CPU device votes with, ``vote_on_host``) on every device
    b = _backend(variant)
    monkeypatch.setattr(b, "vote_on_host", on_host)
    n = 50_000
    keys = rng.integers(-3, 4000, n)
    labels = rng.integers(0, 6, n)                            # few classes: many ties
    got = b.vote(keys, labels, 22)
    want = REF.vote(keys, labels, 22)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert got[0].dtype == np.int64 and got[1].dtype == np.int32
    # explicit tie: two labels with two points each -> the lower label wins; label 0 never votes
    k = np.array([7, 7, 7, 7, 7, 7, 9, 9])
    lab = np.array([5, 3, 5, 3, 0, 0, 0, 0])
    v, l = b.vote(k, lab, 22)
    assert v.tolist() == [7] and l.tolist() == [3]
    with pytest.raises(ValueError, match="labels must lie"):
        b.vote(np.array([1]), np.array([22]), 22)


@pytest.mark.parametrize("variant", PLATFORMS)
@pytest.mark.parametrize("path", ["dense", "hash", "dense-keys-hash-counts"])
def test_vote_paths_identical_to_reference(variant, path, rng, monkeypatch):
    """Dense flags + prefix-sum ranks (keys of one grid), hash tables (sparse huge keys), and the mixed
    case (dense ranks, too many (voxel, class) pairs for a dense count table) agree with the reference."""
    import place3d_kernels.backends.opencl.host as be

    b = _backend(variant)
    monkeypatch.setattr(b, "vote_on_host", False)       # the kernels' paths, also on a CPU device
    n = 30_000
    hi = 2**30 if path == "hash" else 5000
    keys = rng.integers(-2, hi, n)
    keys[: n // 3] = rng.integers(0, 40, n // 3)               # crowded voxels: long vote lists, ties
    labels = rng.integers(0, 5, n)
    if path == "dense-keys-hash-counts":
        monkeypatch.setattr(be, "_DENSE_VOTE_BYTES", 0)
    got, want = b.vote(keys, labels, 22), REF.vote(keys, labels, 22)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


# ============================================================================ ray-mesh
def _closed_meshes():
    trimesh = pytest.importorskip("trimesh")
    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.5)
    box = trimesh.creation.box(extents=(2.0, 1.0, 3.0)).subdivide().subdivide()
    return {"icosphere": (ico.vertices, ico.faces, ico.edges_unique),
            "cube": (box.vertices, box.faces, box.edges_unique)}


@pytest.mark.parametrize("variant", RAY_VARIANTS)
@pytest.mark.parametrize("name", ["icosphere", "cube"])
def test_no_leaks_at_shared_vertices_and_edges(variant, name, rng):
    b = _backend(variant)
    v, f, edges = _closed_meshes()[name]
    v = v + [3.0, -2.0, 1.0]
    w = rng.uniform(0.05, 0.95, (len(edges), 1))
    tgt = np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]]),
                          w * v[edges[:, 0]] + (1 - w) * v[edges[:, 1]]])
    centre = v.mean(axis=0)
    out = tgt - centre
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out += 0.1 * rng.normal(size=out.shape)
    origins = tgt + 10.0 * out
    d = tgt - origins
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    h = b.upload_mesh(v, f)
    t, face = b.raycast(h, origins, d, np.full(len(d), 100.0))
    assert np.all(face >= 0), f"{int((face < 0).sum())} of {len(d)} rays slipped through the mesh"
    assert np.all(t <= dist * (1 + 1e-6) + 1e-6), "a ray passed its target: it leaked into the body"
    # axis-aligned rays through every vertex (exact zero direction components)
    for axis in range(3):
        dd = np.zeros((len(v), 3))
        dd[:, axis] = 1.0
        oo = v.copy()
        oo[:, axis] = v[:, axis].min() - 5.0
        t, face = b.raycast(h, oo, dd, np.full(len(v), 100.0))
        # each ray passes exactly through a vertex of the convex body: it enters it or touches it there
        assert np.all(face >= 0), f"axis {axis}: {int((face < 0).sum())} rays through vertices missed"


@pytest.mark.parametrize("variant", RAY_VARIANTS)
def test_raycast_vs_reference(variant, rng):
    trimesh = pytest.importorskip("trimesh")
    b = _backend(variant)
    tm = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    v, f = tm.vertices + [40.0, -25.0, 3.0], tm.faces       # away from the origin, like a city part
    o = rng.normal(size=(1500, 3)) * 5.0 + [40.0, -25.0, 3.0]
    d = rng.normal(size=(1500, 3)) * 1.5 - (o - [40.0, -25.0, 3.0])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_max = rng.choice([3.0, 8.0, 30.0], len(o))
    h = b.upload_mesh(v, f)
    got_t, got_f = b.raycast(h, o, d, t_max)
    want_t, want_f = REF.raycast(REF.upload_mesh(v, f), o, d, t_max)
    hit = want_f >= 0
    np.testing.assert_array_equal(got_f >= 0, hit)
    assert hit.sum() > 300
    np.testing.assert_allclose(got_t[hit], want_t[hit], rtol=1e-5)
    assert np.all(np.isinf(got_t[~hit])) and np.all(got_f[~hit] == -1)
    same = got_f[hit] == want_f[hit]
    assert same.mean() > 0.995
    # a different face id only where the two faces are hit at the same distance (shared edge/vertex)
    for i in np.flatnonzero(hit)[~same]:
        tt, _ = brute_force_raycast(v, f[got_f[i]][None], o[i:i + 1], d[i:i + 1], t_max[i:i + 1])
        np.testing.assert_allclose(tt, want_t[i:i + 1], rtol=1e-6)


@pytest.mark.parametrize("variant", RAY_VARIANTS)
def test_closest_hit_ties_go_to_the_lowest_face(variant):
    b = _backend(variant)
    # the same square twice (faces 0-1 and 2-3): every hit ties; the lower id must win
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3]])
    o = np.array([[0.3, -0.5, 2.0], [-0.5, 0.3, 2.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0]])
    t, face = b.raycast(b.upload_mesh(v, f), o, d, np.array([10.0, 10.0]))
    np.testing.assert_allclose(t, [2.0, 2.0])
    assert face.tolist() == [0, 1]


@pytest.mark.parametrize("variant", RAY_VARIANTS)
def test_t_max_bounds_the_hit(variant):
    b = _backend(variant)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2]])
    o = np.array([[0.2, 0.2, 1.0]] * 4)
    d = np.array([[0, 0, -1.0]] * 4)
    t, face = b.raycast(b.upload_mesh(v, f), o, d, np.array([1.0, 1.0 - 1e-9, 0.5, 10.0]))
    assert face.tolist() == [0, -1, -1, 0]
    assert t[0] == 1.0 and np.isinf(t[1]) and np.isinf(t[2]) and t[3] == 1.0


def test_stack_overflow_rays_are_retraced_on_the_host(rng):
    """A deliberately tiny stack overflows on the deep scene; flagged rays must come back exact."""
    if not _DEVICES:
        pytest.skip(_WHY)
    v, f = deep_scene(120)
    b = OpenCLBackend(_DEVICES[0], stack_size=2, bvh_width=2)
    h = b.upload_mesh(v, f)
    assert h.bvh.depth > 2
    x = 1.35 ** np.arange(120)
    # rays along -x through the tiny triangles' corner region, and random ones near the deep end of the
    # chain (far out, at 1e15 m, even float64 cannot resolve 1 mm triangles)
    # (float32 Woop products overflow beyond ~1e12 m, so stay below that)
    o = np.column_stack([x[:90:3] * 1.5 + 1.0, np.full(30, 1e-7), np.full(30, 1e-7)])
    o = np.concatenate([o, rng.uniform([0, -0.5, -0.5], [300, 0.5, 0.5], (200, 3))])
    d = np.tile([-1.0, 0.0, 0.0], (len(o), 1))
    d[30:] = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tm = np.full(len(o), 1e30)
    t, face = b.raycast(h, o, d, tm)
    assert b.stats["retraced_rays"] > 0
    bt, bf = brute_force_raycast(v, f, o, d, tm)
    np.testing.assert_array_equal(face, bf)
    np.testing.assert_allclose(t[bf >= 0], bt[bf >= 0], rtol=1e-9)
    # the 4-wide tree with a tiny stack overflows too (up to 3 entries per level)
    b4 = OpenCLBackend(_DEVICES[0], stack_size=1, bvh_width=4)
    t4, face4 = b4.raycast(b4.upload_mesh(v, f), o, d, tm)
    assert b4.stats["retraced_rays"] > 0
    np.testing.assert_array_equal(face4, bf)
    # with the proven stack size nothing is handed back, and the answers are the same
    for width in (2, 4):
        b64 = OpenCLBackend(_DEVICES[0], bvh_width=width)
        t2, face2 = b64.raycast(b64.upload_mesh(v, f), o, d, tm)
        assert b64.stats["retraced_rays"] == 0
        np.testing.assert_array_equal(face2, bf)


# ============================================================================ benchmark hooks
@pytest.mark.parametrize("variant", RAY_VARIANTS)
def test_resident_raycast_matches_raycast(variant, rng):
    """The kernel-only timer (rays kept on the device) runs repeatedly and leaves what ``raycast`` returns."""
    trimesh = pytest.importorskip("trimesh")
    b = _backend(variant)
    tm = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    v, f = tm.vertices, tm.faces
    o = rng.normal(size=(400, 3)) * 4.0
    d = rng.normal(size=(400, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_max = rng.choice([3.0, 30.0], len(o))
    h = b.upload_mesh(v, f)
    run = b.resident_raycast(h, o, d, t_max)
    run()
    run()
    got_t, got_f = run.read()
    want_t, want_f = b.raycast(h, o, d, t_max)
    assert (want_f >= 0).sum() > 50 and (want_f < 0).sum() > 10
    np.testing.assert_array_equal(got_f, want_f)
    np.testing.assert_array_equal(got_t, want_t)
    empty = b.resident_raycast(h, np.empty((0, 3)), np.empty((0, 3)), 1.0)
    empty()
    assert empty.read()[1].shape == (0,)


@pytest.mark.parametrize("variant", VARIANTS)
def test_resident_traverse_matches_traverse(variant, rng):
    b = _backend(variant)
    spec = GridSpec(0.5, (12, 9, 7))
    o, d, t_end = random_rays(spec, rng, n=500, t=6.0)
    stop = (rng.random(spec.n_voxels) < 0.05).astype(np.uint8)
    for s in (None, stop):
        run = b.resident_traverse(spec, o, d, t_end, stop=s)
        run()
        run()
        offsets, _ = b.traverse(spec, o, d, t_end, stop=s)
        counts = run.read()
        assert counts.sum() > 1000
        np.testing.assert_array_equal(counts, np.diff(offsets))
