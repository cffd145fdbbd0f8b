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
