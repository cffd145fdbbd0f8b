"""Page-locked host blocks for large device-to-host copies, recycled once the arrays handed out die.

A copy from a GPU into pageable NumPy memory goes through the driver's staging buffer; into page-locked
(pinned) memory it is one DMA. The ray-mesh API returns 20 bytes per ray (float64 distance, int64 face,
int32 label), five times what a plain float32 caster returns, so on a GPU host that copy was most of the
API's distance to a plain Warp kernel (issue 17, goal 2). Allocating pinned memory per call would cost
more than it saves (every page is locked), so blocks are pooled: a block goes back to the pool when the
last NumPy view of it is garbage-collected (the view's base is the block's owner, whose ``__del__``
returns it), never while the caller can still read it.

The pool is backend-neutral: a backend passes ``alloc(capacity) -> (block, address)``, where ``block``
keeps the memory alive (a pinned ``wp.array`` for Warp, a mapped ``ALLOC_HOST_PTR`` buffer for OpenCL)
and ``address`` is where its bytes start on the host.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

import numpy as np

__all__ = ["HostBlockPool", "warp_pinned_alloc"]


class _Owner:
    """Exposes a pooled block as a NumPy buffer; returns the block to its pool when no view is left."""

    def __init__(self, pool: "HostBlockPool", entry: tuple, nbytes: int):
        self._pool, self._entry = pool, entry
        self.__array_interface__ = {"data": (int(entry[2]), False), "shape": (int(nbytes),),
                                    "typestr": "|u1", "version": 3}

    def __del__(self):
        try:
            self._pool._give_back(self._entry)
        except Exception:  # noqa: BLE001 - at interpreter exit the pool may be gone; the block is freed
            pass


class HostBlockPool:
    """Host blocks by capacity (powers of two from 1 MiB), handed out as NumPy views that own them.

    Args:
        alloc: ``alloc(capacity)`` -> ``(block, address)``: a new block of ``capacity`` bytes.
        max_free: blocks kept for reuse (the rest are freed when returned).
    """

    def __init__(self, alloc: Callable[[int], tuple[Any, int]], max_free: int = 4):
        self._alloc, self._max_free = alloc, int(max_free)
        self._free: list[tuple] = []      # (capacity, block, address)
        self._lock = threading.Lock()
        self.allocated = 0                # blocks allocated over the pool's life (tests: reuse happens)

    def take(self, nbytes: int):
        """(block, host): a block of at least ``nbytes`` bytes and an (nbytes,) uint8 NumPy view of it that
        owns the block: copy into ``block`` (or into ``host``), read ``host`` and its views."""
        nbytes = int(nbytes)
        with self._lock:
            fits = [e for e in self._free if e[0] >= nbytes]
            entry = min(fits, key=lambda e: e[0]) if fits else None
            if entry is not None:
                self._free.remove(entry)
        if entry is None:
            cap = 1 << max(20, (max(nbytes, 1) - 1).bit_length())
            block, address = self._alloc(cap)
            entry = (cap, block, int(address))
            self.allocated += 1
        return entry[1], np.asarray(_Owner(self, entry, nbytes))

    def _give_back(self, entry: tuple) -> None:
        with self._lock:
            if len(self._free) < self._max_free:
                self._free.append(entry)

    @property
    def free_blocks(self) -> int:
        return len(self._free)


def warp_pinned_alloc(wp, pinned: bool = True) -> Callable[[int], tuple[Any, int]]:
    """``alloc`` for Warp: a uint8 ``wp.array`` on the CPU device, page-locked unless ``pinned`` is False
    (tests on machines without CUDA)."""

    def alloc(cap: int):
        block = wp.empty(cap, dtype=wp.uint8, device="cpu", pinned=bool(pinned))
        return block, block.ptr

    return alloc
