"""The pooled P-SOGs a process keeps between commands (``keep_pools``), by their drives' cache files.

A resident process (``place3d serve``) pools the same drives command after command: the default
``optimize`` and ``evaluate`` pool the same four searched drives, ``optimize`` four held-out ones too.
Kept, a pool comes back with what was derived from it during the last command: its summed counts, its
P-SOG (``PooledPSOG.kept_psog``) and what that P-SOG keeps (entropy, weights, stop mask, each backend's
prepared grids), and the jackknife's rows (``PooledPSOG.derived``). A warm served optimize on the H200 spent
0.27 s reading and summing its drives and about 0.4 s more on threads making the held-out pool and its
grids, every command (bench/results/ab-2026-11-30-s29, section 8).

The key names every drive's cache file by its identity (``atomic.file_identity``: resolved path,
device, inode, size and modification time in ns) and its label, and the grid. A cache file is written
by ``os.replace`` (a new inode), so a rebuilt or rewritten drive gives another key and its pool is pooled
again. ``pool_specs`` keeps a pool only when every drive was read from its file and every identity was the
same before and after the reads. A kept pool is shared: ``PooledPSOG.add`` refuses it.
"""

from __future__ import annotations

from place3d_kernels.kept import Kept

__all__ = ["keep_pools", "kept_pool", "keep_pool", "pool_files_key"]

_POOLS = Kept("pools")


def keep_pools(n: int) -> None:
    """Keep the last ``n`` pools ``pool_specs`` made from cached drives (0, the default, keeps none and
    forgets those kept). One default pool (four drives, 0.1 m grid) keeps its counts and rank rows, its P-SOG's
    dense fields and each backend's prepared grids: 1.30-1.31 GB of host memory with opencl:pocl's grids (host
    memory on a CPU device; dev VM, 3 runs, 2026-11-30), less on a GPU, whose grids are on the device."""
    _POOLS.keep(n)


def pool_files_key(specs, cache=True) -> tuple | None:
    """The key of a pool of ``specs`` (``spec.PSOGSpec``s): the grid and, per drive, its label and its cache
    file's identity; None when nothing is kept (``keep_pools(0)``, no cache) or a drive's file is not known
    without building its scene or does not exist."""
    if not _POOLS.keeps or not cache:
        return None
    from place3d_kernels.atomic import file_identity

    out = []
    for s in specs:
        f = s.cache_file(cache)
        ident = None if f is None else file_identity(f)
        if ident is None:
            return None
        out.append((s.scene.label, ident))
    return repr(specs[0].grid.grid().to_dict()), tuple(out)


def kept_pool(key):
    """The pool kept under ``key`` (``pool_files_key``), or None."""
    return _POOLS.get(key)


def keep_pool(key, pooled) -> None:
    """Keep ``pooled`` under ``key`` (nothing when ``key`` is None or no pool is kept); it is shared from now
    on (``PooledPSOG.add`` refuses it)."""
    if key is not None and _POOLS.keeps:
        pooled.shared = True              # before it is visible to another caller
        _POOLS.put(key, pooled)
