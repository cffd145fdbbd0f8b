"""``Kept``: the last few objects a process keeps between commands, by key (``sog.keep_loaded``,
``pool_memo.keep_pools``). A resident process (``place3d serve``) sets how many; every other process keeps none."""

from __future__ import annotations

import threading
from collections import OrderedDict

__all__ = ["Kept"]


class Kept:
    """A thread-safe map of at most ``n`` entries, the least recently used dropped first; ``n`` = 0 (the start)
    keeps nothing. ``what`` names the entries in errors ("P-SOGs")."""

    def __init__(self, what: str):
        self.what = what
        self._items: OrderedDict = OrderedDict()
        self._n = 0
        self._lock = threading.Lock()

    def keep(self, n: int) -> None:
        """Keep at most ``n`` entries from now on (those beyond it are dropped now)."""
        if n < 0:
            raise ValueError(f"keeping {self.what} needs n >= 0, got {n}")
        with self._lock:
            self._n = int(n)
            self._trim()

    @property
    def keeps(self) -> bool:
        return self._n > 0

    def get(self, key):
        """The entry kept under ``key`` (now the most recent), or None."""
        if key is None:
            return None
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key, value) -> bool:
        """Keep ``value`` under ``key`` as the most recent entry; False (nothing kept) when nothing is."""
        with self._lock:
            if not self._n or key is None:
                return False
            self._items[key] = value
            self._items.move_to_end(key)
            self._trim()
            return True

    def _trim(self) -> None:
        while len(self._items) > self._n:
            self._items.popitem(last=False)
