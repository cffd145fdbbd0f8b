"""The pinned host-block pool (backends/pinned.py), with Warp's allocator: a block is reused only after
every NumPy view of it has died, the smallest free block that fits is taken, and the free list is bounded.
On machines without CUDA the pool runs with ordinary memory (pinned=False); the CUDA path is covered by
tests/test_raycast_checked.py on a GPU."""

from __future__ import annotations

import gc

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from place3d_kernels.backends.pinned import HostBlockPool, warp_pinned_alloc  # noqa: E402


def test_block_returns_only_when_every_view_is_gone():
    pool = HostBlockPool(warp_pinned_alloc(wp, pinned=False))
    block, host = pool.take(4096)
    assert host.shape == (4096,) and host.dtype == np.uint8 and block.shape[0] >= 4096
    block.numpy()[:8] = np.arange(8, dtype=np.uint8)             # what a copy into the block writes
    assert host[:8].tolist() == list(range(8))                   # the host view reads the block's memory
    view = host[:16].view(np.float64)
    del host
    gc.collect()
    assert pool.free_blocks == 0                                 # a view still reads the block
    del view
    gc.collect()
    assert pool.free_blocks == 1
    again, host2 = pool.take(1000)                               # fits: the same block, no new allocation
    assert again is block and pool.allocated == 1 and host2.shape == (1000,)


def test_smallest_fitting_block_and_bounded_free_list():
    pool = HostBlockPool(warp_pinned_alloc(wp, pinned=False), max_free=2)
    taken = [pool.take(n) for n in (1 << 20, 1 << 22, 1 << 21)]
    caps = sorted(b.shape[0] for b, _ in taken)
    assert caps == [1 << 20, 1 << 21, 1 << 22] and pool.allocated == 3
    del taken
    gc.collect()
    assert pool.free_blocks == 2                                 # the third was freed, not kept
    block, _ = pool.take(3 << 19)                                # 1.5 MiB: the smallest free block that fits
    assert block.shape[0] >= 3 << 19
    big, _ = pool.take(1 << 23)                                  # larger than any free block: a new one
    assert big.shape[0] == 1 << 23 and pool.allocated == 4
