"""Bricked bitsets: ``brick_bits``' two packings (dense and scatter) against the layout's definition."""

import numpy as np
import pytest

from place3d_kernels.backends import bricks
from place3d_kernels.backends.bricks import brick_bits, brick_shape


def _by_definition(mask, shape):
    # one voxel at a time: brick ((i >> 2) * by + (j >> 2)) * bz + (k >> 1), bit (i & 3) | (j & 3) << 2 | (k & 1) << 4
    _, by, bz = brick_shape(shape)
    words = np.zeros(int(np.prod(brick_shape(shape))), dtype=np.uint32)
    for i, j, k in zip(*np.unravel_index(np.flatnonzero(mask), shape)):
        words[((i >> 2) * by + (j >> 2)) * bz + (k >> 1)] |= np.uint32(1 << int((i & 3) | (j & 3) << 2 | (k & 1) << 4))
    return words


@pytest.mark.parametrize("shape", [(8, 8, 4), (9, 7, 5), (1, 1, 1), (13, 4, 2), (4, 13, 3)])
@pytest.mark.parametrize("share", [0.0, 0.03, 0.5, 1.0])
def test_dense_and_sparse_packings_match_the_layout(shape, share):
    rng = np.random.default_rng(abs(hash((shape, share))) % 2**32)
    mask = rng.random(int(np.prod(shape))) < share
    want = _by_definition(mask, shape)
    for pack in (bricks._brick_bits_dense, bricks._brick_bits_sparse):
        got = pack(mask, shape)
        assert got.dtype == np.uint32 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)


def test_brick_bits_takes_either_path_with_the_same_words(monkeypatch):
    # a grid above DENSE_MIN_VOXELS: 1 % set takes the scatter, 10 % the dense packing; both are checked
    # against the definition (and uint8 masks, as the backends pass stop masks, give the same words)
    shape = (40, 36, 6)
    rng = np.random.default_rng(7)
    n = int(np.prod(shape))
    assert n >= bricks.DENSE_MIN_VOXELS
    taken = []
    for kind in ("dense", "sparse"):
        pack = getattr(bricks, f"_brick_bits_{kind}")
        monkeypatch.setattr(bricks, f"_brick_bits_{kind}", lambda m, s, pack=pack, kind=kind: taken.append(kind) or pack(m, s))
    for share, path in ((0.01, "sparse"), (0.1, "dense")):
        mask = rng.random(n) < share
        for m in (mask, mask.astype(np.uint8)):
            taken.clear()
            np.testing.assert_array_equal(brick_bits(m, shape), _by_definition(mask, shape))
            assert taken == [path]


def _flat_by_definition(nonzero, stop, shape):
    # one voxel at a time: flat brick (k * nbx + (i >> 3)) * nby + (j >> 2), bit (i & 7) | (j & 3) << 3, the
    # occlusion bits in the low word and the nonzero-weight bits in the high one
    nbx, nby, nz = bricks.flat_shape(shape)
    words = np.zeros(nbx * nby * nz, dtype=np.uint64)
    for mask, at in ((stop, 0), (nonzero, 32)):
        for i, j, k in zip(*np.unravel_index(np.flatnonzero(mask), shape)):
            words[(k * nbx + (i >> 3)) * nby + (j >> 2)] |= np.uint64(1 << int(at + ((i & 7) | (j & 3) << 3)))
    return words


@pytest.mark.parametrize("shape", [(8, 8, 4), (9, 7, 5), (1, 1, 1), (13, 4, 2), (4, 13, 3), (20, 6, 1)])
def test_flat_bricks_match_their_layout_on_the_host_and_from_the_device_kernel(shape):
    """The CUDA score kernel's masks: ``flat_brick_masks`` (host) by definition, and ``flat_masks_kernel``
    (run here on Warp's CPU device) from the 4 x 4 x 2 pairs gives the same words, partial bricks included."""
    wp = pytest.importorskip("warp")
    from place3d_kernels.backends.warp import score_gpu
    from place3d_kernels.backends.warp.host import WarpCore

    WarpCore("cpu")                          # Warp initialised as the package does
    rng = np.random.default_rng(sum(shape))
    n = int(np.prod(shape))
    nonzero, stop = rng.random(n) < 0.4, rng.random(n) < 0.2
    want = _flat_by_definition(nonzero, stop, shape)
    np.testing.assert_array_equal(bricks.flat_brick_masks(shape, nonzero, stop), want)
    no_stop = _flat_by_definition(nonzero, np.zeros(n, bool), shape)
    np.testing.assert_array_equal(bricks.flat_brick_masks(shape, nonzero, None), no_stop)
    pairs = wp.array(bricks.brick_masks(shape, nonzero, stop).view(np.uint64), dtype=wp.uint64, device="cpu")
    bx, by, bz = brick_shape(shape)
    fx, fy, fz = bricks.flat_shape(shape)
    flat = wp.zeros(fx * fy * fz, dtype=wp.uint64, device="cpu")
    wp.launch(score_gpu.flat_masks_kernel, dim=fx * fy * fz, device="cpu", inputs=[pairs, bx, by, bz, fx, fy, flat])
    np.testing.assert_array_equal(flat.numpy(), want)
