"""The CUDA binaries shipped with the package (backends/warp/aot.py): present and current for the code,
picked by architecture, loaded on a CUDA device instead of compiling."""

from __future__ import annotations

import pytest

wp = pytest.importorskip("warp")

from place3d_kernels.backends.warp import aot  # noqa: E402
from place3d_kernels.backends.warp.host import WarpCore  # noqa: E402

REBUILD = "rebuild them with: python -m place3d_kernels.backends.warp.aot (no GPU needed)"


def test_shipped_binaries_are_those_of_the_current_kernels():
    """Every shipped module's identifier (name + content hash) is the current code's, with a CUBIN per
    architecture in CUBIN_ARCHS and the PTX; no file of older code is left beside them."""
    WarpCore("cpu")                                  # Warp initialised (quietly), as the package does
    where = aot.folder()
    shipped = sorted(p.name for p in where.parent.glob("warp-*"))
    if not where.is_dir():
        pytest.skip(f"binaries shipped for {shipped}, Warp {wp.config.version} installed: it compiles instead")
    expected = set()
    for m in aot.modules():
        ident = m.get_module_identifier()
        expected.add(f"{ident}.meta")
        expected.update(f"{ident}.sm{a}.cubin" for a in aot.CUBIN_ARCHS)
        expected.add(f"{ident}.sm{aot.PTX_ARCH}.ptx")
    have = {p.name for p in where.iterdir()}
    assert not expected - have, f"missing for the current kernels: {sorted(expected - have)}; {REBUILD}"
    assert not have - expected, f"files of other code: {sorted(have - expected)}; {REBUILD}"


def test_binary_for_picks_the_exact_cubin_else_the_ptx(tmp_path):
    ident = "wp_mod_abc1234"
    (tmp_path / f"{ident}.meta").write_text("{}")
    (tmp_path / f"{ident}.sm90.cubin").write_bytes(b"x")
    (tmp_path / f"{ident}.sm{aot.PTX_ARCH}.ptx").write_text("x")
    assert aot.binary_for(ident, 90, tmp_path) == (90, False)
    assert aot.binary_for(ident, 87, tmp_path) == (aot.PTX_ARCH, True)    # no CUBIN: the driver compiles the PTX
    assert aot.binary_for(ident, 70, tmp_path) is None                   # older than the PTX
    assert aot.binary_for("wp_mod_0000000", 90, tmp_path) is None         # other code: not found
    (tmp_path / f"{ident}.meta").unlink()
    assert aot.binary_for(ident, 90, tmp_path) is None                    # no metadata: not loadable


def test_a_cuda_backend_loads_the_shipped_binaries():
    try:
        b = WarpCore("cuda:0")
    except Exception as e:  # noqa: BLE001 - BackendUnavailable on hosts without a GPU
        pytest.skip(f"no CUDA device: {e}")
    if not aot.folder().is_dir():
        pytest.skip(f"no binaries shipped for Warp {wp.config.version}")
    assert b.aot.startswith(("cubin", "ptx")), b.aot
    assert WarpCore("cpu").aot is None


def test_the_score_module_is_loaded_once_per_cuda_device():
    """Every launch of a kernel in score_gpu.py uses the module's block size: Warp keys a loaded module by
    (device, block size), and another size compiles the whole module again (a second's wait on a cold
    host, which a launch at Warp's default did cost once). Prepared and patched grids, a score and a count."""
    try:
        b = WarpCore("cuda:0")
    except Exception as e:  # noqa: BLE001 - BackendUnavailable on hosts without a GPU
        pytest.skip(f"no CUDA device: {e}")
    import numpy as np

    from place3d_kernels.backends.base import GridSpec
    from place3d_kernels.backends.warp import score_gpu

    rng = np.random.default_rng(0)
    spec = GridSpec(voxel_size=0.5, shape=(20, 18, 6))
    n = 20 * 18 * 6
    w = np.where(rng.random(n) < 0.3, rng.integers(1, 10**6, n), 0).astype(np.int64)
    stop = rng.random(n) < 0.05
    h = b.prepare_grid(spec, w, stop)
    b.patched_grid(b.grid_base(spec, w, stop), np.array([3], dtype=np.int64), np.array([5]), np.array([False]))
    poses = np.zeros((2, 1, 6))
    poses[:, 0, :3] = (5.0, 4.5, 1.5)
    b.score_placements(h, np.radians([-10.0, 0.0, 5.0]), np.linspace(0, 2 * np.pi, 64, endpoint=False), 50.0, poses)
    ctx = b.device.context
    sizes = {bd for (c, bd) in score_gpu.score_kernel_gpu.module.execs if c == ctx}
    assert sizes == {score_gpu.SCORE_BLOCK_DIM}, f"score_gpu.py loaded for block sizes {sorted(sizes)}"
