"""raycast on backends that check rays on the device (raycast_checks_rays): the same Hits, bit for bit,
and the same errors as the host path, for float32 and float64 rays."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import place3d_kernels as p3k

SHIFT = np.array([12345.678, -9876.5, 321.25])


def _mesh():
    tm = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    v = np.concatenate([tm.vertices, [[0.0, 0.0, 0.0]]]) + SHIFT
    # one degenerate face (not uploaded), so uploaded and caller face ids differ after it
    f = np.concatenate([[[len(v) - 1, len(v) - 1, 0]], tm.faces])
    return p3k.Mesh(v, f, labels=(np.arange(len(f)) * 7) % 23)


def _rays(rng, n=1500):
    o = SHIFT + rng.normal(size=(n, 3)) * 4.0
    d = (SHIFT + rng.normal(size=(n, 3))) - o          # not unit; most aim at the sphere
    return o, d


def _same(got, want):
    for k in ("t", "face", "label"):
        a, b = getattr(got, k), getattr(want, k)
        assert a.dtype == b.dtype, (k, a.dtype, b.dtype)
        assert a.tobytes() == b.tobytes(), f"{k}: {int((a != b).sum())} rays differ"


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_same_hits_as_reference(device_backend, rng, dtype):
    mesh = _mesh()
    o, d = _rays(rng)
    o, d = o.astype(dtype), d.astype(dtype)
    t_rays = rng.uniform(0.0, 12.0, len(o))
    for t_max in (20.0, np.inf, t_rays):
        want = p3k.raycast(mesh, o.astype(np.float64), d.astype(np.float64), t_max, backend="reference")
        got = p3k.raycast(mesh, o, d, t_max, backend=device_backend)
        assert want.hit.sum() > 100
        _same(got, want)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_one_shared_origin(device_backend, rng, dtype):
    mesh = _mesh()
    _, d = _rays(rng, 800)
    o = (SHIFT + [0.3, -4.0, 0.2]).astype(dtype)
    d = d.astype(dtype)
    want = p3k.raycast(mesh, o.astype(np.float64), d.astype(np.float64), 30.0, backend="reference")
    for origin in (o, o[None], np.broadcast_to(o, d.shape)):
        _same(p3k.raycast(mesh, origin, d, 30.0, backend=device_backend), want)
    assert want.hit.sum() > 50


def test_device_path_runs_for_valid_rays(device_backend, rng):
    # valid rays must not fall back to the host checks: raycast_checked answers itself
    b = p3k.get_backend(device_backend)
    if not b.raycast_checks_rays:
        pytest.skip(f"{b.name} checks rays on the host")
    mesh = _mesh()
    o, d = _rays(rng)
    for dt in (np.float64, np.float32):
        out = b.raycast_checked(mesh.handle(b), o.astype(dt), d.astype(dt), 20.0, shift=mesh.shift)
        assert out is not None
        _same(p3k.Hits(*out), p3k.raycast(mesh, o.astype(dt).astype(np.float64), d.astype(dt).astype(np.float64),
                                          20.0, backend="reference"))


def test_unit_decision_at_the_bound(device_backend, rng):
    # directions scaled to norms around 1 +- 1e-12: those within the bound are used as given, the others
    # normalised; the device must decide and divide exactly as the host does
    mesh = _mesh()
    o, d = _rays(rng, 1200)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= 1.0 + np.linspace(-3e-12, 3e-12, len(d))[:, None]
    d[::7] = np.nextafter(d[::7], np.inf)
    want = p3k.raycast(mesh, o, d, 20.0, backend="reference")
    _same(p3k.raycast(mesh, o, d, 20.0, backend=device_backend), want)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("what, value, match", [
    ("origin", np.nan, "ray 2 has a non-finite origin"),
    ("origin", np.inf, "ray 2 has a non-finite origin"),
    ("direction", np.nan, "ray 2 has a non-finite direction"),
    ("direction", -np.inf, "ray 2 has a non-finite direction"),
    ("direction", 0.0, "ray 2 has a zero-length direction"),
    ("t_max", -1.0, "t_max of ray 2 is -1.0"),
    ("t_max", np.nan, "t_max of ray 2 is nan"),
])
def test_bad_rays_give_the_host_errors(backend, dtype, what, value, match):
    mesh = _mesh()
    o = np.tile(SHIFT + [0.0, 0.0, 5.0], (4, 1)).astype(dtype)
    d = np.tile([0.0, 0.0, -1.0], (4, 1)).astype(dtype)
    t = np.full(4, 10.0)
    if what == "origin":
        o[2, 1] = value
    elif what == "direction":
        d[2] = value if value == 0.0 else [0.0, value, -1.0]
    else:
        t[2] = value
    o0, d0 = o.copy(), d.copy()
    with pytest.raises(ValueError, match=match):
        p3k.raycast(mesh, o, d, t, backend=backend)
    assert o.tobytes() == o0.tobytes() and d.tobytes() == d0.tobytes()
    if what == "t_max":   # a scalar bound: named as ray 0
        with pytest.raises(ValueError, match=match.replace("ray 2", "ray 0")):
            p3k.raycast(mesh, o, d, value, backend=backend)


def test_overflowing_norm_is_normalised_as_on_the_host(device_backend):
    # a component of 1e200 squares to inf: the host rule divides by the inf norm (a zero direction);
    # the device flags it and the host path gives exactly that result
    mesh = _mesh()
    o = np.tile(SHIFT + [0.13, 0.07, 5.0], (3, 1))   # off the sphere's vertices (no face ties)
    d = np.array([[0.0, 0.0, -1.0], [0.0, 1e200, -1.0], [0.0, 0.0, -2.0]])
    want = p3k.raycast(mesh, o, d, 10.0, backend="reference")
    assert want.hit[0] and want.hit[2]
    _same(p3k.raycast(mesh, o, d, 10.0, backend=device_backend), want)


def test_other_inputs_take_the_host_path(device_backend, rng):
    # lists, mixed dtypes and strided arrays are converted on the host: the same hits
    mesh = _mesh()
    o, d = _rays(rng, 300)
    want = p3k.raycast(mesh, o, d, 20.0, backend="reference")
    for oo, dd in ((o.tolist(), d.tolist()), (o, d.astype(np.float32).astype(np.float64)),
                   (np.asfortranarray(o), d)):
        _same(p3k.raycast(mesh, oo, dd, 20.0, backend=device_backend),
              p3k.raycast(mesh, np.asarray(oo), np.asarray(dd), 20.0, backend="reference"))
    _same(p3k.raycast(mesh, o, d.astype(np.float32), 20.0, backend=device_backend),
          p3k.raycast(mesh, o, d.astype(np.float32).astype(np.float64), 20.0, backend="reference"))
    assert want.hit.sum() > 50


def test_opencl_stack_overflow_goes_to_the_host_path(rng):
    # a tiny traversal stack overflows: raycast_checked hands the call back and the host path retraces
    # those rays, so the hits stay the reference's
    try:
        from place3d_kernels.backends.opencl import OpenCLBackend
        b = OpenCLBackend("pocl", stack_size=1, bvh_width=4)
    except Exception as e:  # noqa: BLE001 - no PyOpenCL or no PoCL here
        pytest.skip(f"no opencl:pocl ({e})")
    mesh = _mesh()
    o, d = _rays(rng, 600)
    assert b.raycast_checked(mesh.handle(b), o, d, 20.0, shift=mesh.shift) is None
    _same(p3k.raycast(mesh, o, d, 20.0, backend=b), p3k.raycast(mesh, o, d, 20.0, backend="reference"))
    assert b.stats["retraced_rays"] > 0


def test_shape_errors_are_the_host_path_s(device_backend):
    mesh = _mesh()
    o = np.broadcast_to(SHIFT, (3, 3))
    d = np.tile([0.0, 0.0, -1.0], (2, 1))
    with pytest.raises(ValueError, match=r"origins \(3, 3\) and directions \(2, 3\) must have the same shape"):
        p3k.raycast(mesh, o, d, 10.0, backend=device_backend)
    with pytest.raises(ValueError, match="one value per ray"):
        p3k.raycast(mesh, o[:2], d, [1.0, 2.0, 3.0], backend=device_backend)
    with pytest.raises(ValueError, match=r"must be \(N, 3\) arrays"):
        p3k.raycast(mesh, o[:, :2], d[:, :2], 10.0, backend=device_backend)


def test_earlier_hits_survive_later_calls(device_backend, rng):
    """Results come back in recycled host blocks on CUDA (backends/pinned.py): a block is reused
    only after every array of an earlier result is gone, so holding one result across later calls
    keeps it intact."""
    import gc

    mesh = _mesh()
    held = []
    for seed in range(4):
        o, d = _rays(np.random.default_rng(seed), 3000 + 500 * seed)
        got = p3k.raycast(mesh, o, d, 20.0, backend=device_backend)
        held.append((got, (got.t.copy(), got.face.copy(), got.label.copy())))
        if seed % 2:
            gc.collect()
    for got, (t, f, lab) in held:
        assert got.t.tobytes() == t.tobytes() and got.face.tobytes() == f.tobytes()
        assert got.label.tobytes() == lab.tobytes()
    # a face array kept alone (its Hits and the other arrays dropped) keeps its block
    o, d = _rays(rng, 2000)
    face = p3k.raycast(mesh, o, d, 20.0, backend=device_backend).face
    want = face.copy()
    gc.collect()
    for seed in range(3):
        o2, d2 = _rays(np.random.default_rng(100 + seed), 2000)
        p3k.raycast(mesh, o2, d2, 20.0, backend=device_backend)
    assert face.tobytes() == want.tobytes()


def _pocl(**kw):
    try:
        from place3d_kernels.backends.opencl import OpenCLBackend
        return OpenCLBackend("pocl", **kw)
    except Exception as e:  # noqa: BLE001 - no PyOpenCL or no PoCL here
        pytest.skip(f"no opencl:pocl ({e})")


@pytest.mark.parametrize("width", [2, 4])
def test_opencl_gpu_output_path_on_pocl(rng, width):
    """The OpenCL GPU path of raycast_checked (one device buffer of t | int64 face | label | flags, copied
    into a pooled mapped host block) run on PoCL by treating its device as a GPU: the reference's hits bit
    for bit, results held across later calls intact, blocks reused once their arrays are gone, and the
    stack-overflow flag still hands the call back."""
    import gc

    b = _pocl(bvh_width=width)
    b.is_cpu = False                        # the GPU branches: explicit copies, pinned pool, no work-group size
    mesh = _mesh()
    held = []
    for seed in range(4):
        o, d = _rays(np.random.default_rng(seed), 1000 + 300 * seed)
        got = p3k.raycast(mesh, o, d, 20.0, backend=b)
        want = p3k.raycast(mesh, o, d, 20.0, backend="reference")
        _same(got, want)
        assert got.face.base is not None    # a view of a pooled block, not a fresh array
        held.append((got, want))
    gc.collect()
    for got, want in held:                  # nothing written over while the arrays live
        _same(got, want)
    assert b._pinned.allocated == 4 and b._pinned.free_blocks == 0
    del held, got, want
    gc.collect()
    assert b._pinned.free_blocks == 4       # (max_free) every block returned
    o, d = _rays(rng, 900)
    _same(p3k.raycast(mesh, o, d, 20.0, backend=b), p3k.raycast(mesh, o, d, 20.0, backend="reference"))
    assert b._pinned.allocated == 4         # served from the pool

    small = _pocl(stack_size=1, bvh_width=width)
    small.is_cpu = False
    assert small.raycast_checked(mesh.handle(small), o, d, 20.0, shift=mesh.shift) is None
    # a bad ray raises the host path's error, and the pooled buffers it used serve the next call intact
    bad = o.copy()
    bad[5, 2] = np.nan
    with pytest.raises(ValueError, match="ray 5 has a non-finite origin"):
        p3k.raycast(mesh, bad, d, 20.0, backend=b)
    assert b._scratch                       # device buffers were handed back to the pool
    _same(p3k.raycast(mesh, o, d, 20.0, backend=b), p3k.raycast(mesh, o, d, 20.0, backend="reference"))


def test_opencl_ray_group_size_on_pocl(rng):
    """A set work-group size for the GPU ray casters rounds the launch up to whole groups; the kernels
    return for the padding ids, so a ragged ray count gives the reference's hits."""
    b = _pocl()
    b.is_cpu = False
    b.ray_group_size = 64
    mesh = _mesh()
    o, d = _rays(rng, 1001)
    _same(p3k.raycast(mesh, o, d, 20.0, backend=b), p3k.raycast(mesh, o, d, 20.0, backend="reference"))
