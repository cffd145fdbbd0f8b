"""Page-locked host blocks for large device-to-host copies, recycled once the arrays handed out die.

A copy from a CUDA device into pageable NumPy memory goes through the driver's staging buffer; into
page-locked (pinned) memory it is one DMA. The ray-mesh API returns 20 bytes per ray (float64 distance,
int64 face, int32 label), five times what a plain float32 caster returns, so on an H100 host that copy
was most of the API's distance to a plain Warp kernel (issue 17, goal 2). Allocating pinned memory
per call would cost more than it saves (``cudaHostAlloc`` locks every page), so blocks are pooled: a
block goes back to the pool when the last NumPy view of it is garbage-collected (the view's base is the
block's owner, whose ``__del__`` returns it), never while the caller can still read it.
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["PinnedPool"]


class _Owner:
    """Exposes a pooled block as a NumPy buffer; returns the block to its pool when no view is left."""

    def __init__(self, pool: "PinnedPool", block, nbytes: int):
        self._pool, self.block = pool, block
        self.__array_interface__ = {"data": (int(block.ptr), False), "shape": (int(nbytes),),
                                    "typestr": "|u1", "version": 3}

    def __del__(self):
        try:
            self._pool._give_back(self.block)
        except Exception:  # noqa: BLE001 - at interpreter exit the pool may be gone; the block is freed
            pass


class PinnedPool:
    """Pinned ``wp.array`` blocks (uint8) on the CPU device, by capacity.

    Args:
        wp: the ``warp`` module.
        max_free: blocks kept for reuse (the rest are freed when returned).
        pinned: False only in tests on machines without CUDA (then the blocks are ordinary memory).
    """

    def __init__(self, wp, max_free: int = 4, pinned: bool = True):
        self._wp, self._max_free, self._pinned = wp, int(max_free), bool(pinned)
        self._free: list = []
        self._lock = threading.Lock()
        self.allocated = 0            # blocks allocated over the pool's life (tests: reuse happens)

    def take(self, nbytes: int):
        """(block, host): a ``wp.array`` of at least ``nbytes`` bytes and an (nbytes,) uint8 NumPy view of it
        that owns the block: copy into ``block``, read ``host`` and its views."""
        nbytes = int(nbytes)
        with self._lock:
            fits = [b for b in self._free if b.shape[0] >= nbytes]
            block = min(fits, key=lambda b: b.shape[0]) if fits else None
            if block is not None:
                self._free.remove(block)
        if block is None:
            cap = 1 << max(20, (max(nbytes, 1) - 1).bit_length())      # powers of two from 1 MiB
            block = self._wp.empty(cap, dtype=self._wp.uint8, device="cpu", pinned=self._pinned)
            self.allocated += 1
        return block, np.asarray(_Owner(self, block, nbytes))

    def _give_back(self, block) -> None:
        with self._lock:
            if len(self._free) < self._max_free:
                self._free.append(block)

    @property
    def free_blocks(self) -> int:
        return len(self._free)
