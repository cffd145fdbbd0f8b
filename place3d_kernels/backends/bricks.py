"""Bricked voxel bitsets of the score kernels (Warp ``score_kernel`` on the CPU, OpenCL ``score_rays_csr``;
the masks from which the GPU kernels' flat bricks are made).

One 32-bit word holds a brick of 4 x 4 x 2 voxels (x, y, z), so the next voxel of a ray's walk is
usually in the word just read. Bricks are numbered ``((i >> 2) * by + (j >> 2)) * bz + (k >> 1)``
and a voxel's bit is ``(i & 3) | (j & 3) << 2 | (k & 1) << 4``, with (bx, by, bz) = ``brick_shape``.

The GPU score kernels (Warp's ``warp/score_gpu.py`` on CUDA, OpenCL's ``score_gpu.cl`` and ``score_rays_flat``) keep their
bitsets in flat bricks of 8 x 4 x 1 voxels numbered ``(k * nbx + (i >> 3)) * nby + (j >> 2)`` (z slowest,
y fastest), bit ``(i & 7) | (j & 3) << 3``, with (nbx, nby, nz) = ``flat_shape``: the voxel bit needs no z
term, and the 8 words of a 32-byte memory sector cover 8 x 32 voxels of one layer, along which the LiDAR's
near-horizontal rays run, where a sector of 4 x 4 x 2 bricks covers a column 4 x 4 x 16 (figures:
bench/README.md, "What the studies found", dense-rig score kernel). ``flat_brick_masks`` is the host's copy of what
``score_gpu.flat_masks_kernel`` and OpenCL's ``flat_masks`` make on the device.
"""

from __future__ import annotations

import numpy as np

__all__ = ["brick_shape", "brick_bits", "brick_word_bits", "brick_masks", "flat_shape", "flat_brick_masks"]


def brick_shape(shape) -> tuple[int, int, int]:
    """Bricks along x, y, z of a grid of ``shape`` voxels."""
    nx, ny, nz = (int(v) for v in shape)
    return (nx + 3) // 4, (ny + 3) // 4, (nz + 1) // 2


def brick_bits(mask: np.ndarray, shape) -> np.ndarray:
    """Pack a flat per-voxel boolean mask (C order over ``shape``) into one uint32 word per brick."""
    mask = np.asarray(mask)
    if mask.size >= DENSE_MIN_VOXELS and np.count_nonzero(mask) * DENSE_SHARE >= mask.size:
        return _brick_bits_dense(mask, shape)
    return _brick_bits_sparse(mask, shape)


#: ``brick_bits`` packs the whole grid at once (``_brick_bits_dense``) when at least one voxel in
#: ``DENSE_SHARE`` is set, else it scatters the set voxels one by one: packing the whole grid costs the
#: same whatever the share set, scattering grows with it, and the two crossed near 2 % set on random masks
#: (the study, ``brick_pack.py``, is at tag lab-2026-11-27).
DENSE_SHARE = 50
DENSE_MIN_VOXELS = 4096


def brick_word_bits(voxels: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """(brick word (N,) int64, the voxel's bit in it (N,) uint32) of flat voxel indices (C order over ``shape``)."""
    i, j, k = np.unravel_index(np.asarray(voxels, dtype=np.int64), tuple(int(v) for v in shape))
    _, by, bz = brick_shape(shape)
    word = ((i >> 2) * by + (j >> 2)) * bz + (k >> 1)
    bit = np.left_shift(np.uint32(1), ((i & 3) | ((j & 3) << 2) | ((k & 1) << 4)).astype(np.uint32))
    return word, bit


def _brick_bits_sparse(mask: np.ndarray, shape) -> np.ndarray:
    bx, by, bz = brick_shape(shape)
    words = np.zeros(bx * by * bz, dtype=np.uint32)
    word, bit = brick_word_bits(np.flatnonzero(mask), shape)
    if word.size:
        order = np.argsort(word, kind="stable")
        word, bit = word[order], bit[order]
        first = np.flatnonzero(np.r_[True, word[1:] != word[:-1]])
        words[word[first]] = np.bitwise_or.reduceat(bit, first)
    return words


def _brick_bits_dense(mask: np.ndarray, shape) -> np.ndarray:
    # the grid padded to whole bricks, viewed as (bx, ii, by, jj, bz, kk) and reordered to
    # (bx, by, bz, kk, jj, ii): the 32 voxels of a brick then lie in the order of their bit numbers
    # (ii | jj << 2 | kk << 4), and packbits with little bit order makes each brick's 4 bytes its
    # little-endian word
    nx, ny, nz = (int(v) for v in shape)
    bx, by, bz = brick_shape(shape)
    m = mask.reshape(nx, ny, nz).astype(bool, copy=False)
    if (nx, ny, nz) != (4 * bx, 4 * by, 2 * bz):
        padded = np.zeros((4 * bx, 4 * by, 2 * bz), dtype=bool)
        padded[:nx, :ny, :nz] = m
        m = padded
    bricks = m.reshape(bx, 4, by, 4, bz, 2).transpose(0, 2, 4, 5, 3, 1).reshape(bx * by * bz, 32)
    return np.packbits(bricks, axis=1, bitorder="little").view("<u4").reshape(-1).astype(np.uint32, copy=False)


def brick_masks(shape, nonzero: np.ndarray, stop: np.ndarray | None) -> np.ndarray:
    """Interleaved per-brick pairs: word ``2b`` the occlusion bits of brick b (zero without a stop mask:
    a ray never stops), word ``2b + 1`` the bits of voxels with a nonzero weight."""
    nz_bits = brick_bits(nonzero, shape)
    out = np.zeros(2 * len(nz_bits), dtype=np.uint32)
    out[1::2] = nz_bits
    if stop is not None:
        out[0::2] = brick_bits(stop, shape)
    return out


def flat_shape(shape) -> tuple[int, int, int]:
    """Flat bricks (8 x 4 x 1 voxels) along x, y, z of a grid of ``shape`` voxels."""
    nx, ny, nz = (int(v) for v in shape)
    return (nx + 7) // 8, (ny + 3) // 4, nz


def flat_brick_masks(shape, nonzero: np.ndarray, stop: np.ndarray | None) -> np.ndarray:
    """One uint64 per flat brick, in the CUDA score kernel's numbering: the occlusion bits low (zero without
    a stop mask), the bits of voxels with a nonzero weight high."""
    nx, ny, nz = (int(v) for v in shape)
    bx, by, _ = flat_shape(shape)
    out = np.zeros(bx * by * nz, dtype=np.uint64)
    for half, mask in ((1, nonzero), (0, stop)):
        if mask is None:
            continue
        m = np.zeros((8 * bx, 4 * by, nz), dtype=bool)
        m[:nx, :ny] = np.asarray(mask).reshape(nx, ny, nz)
        # (bx, ii, by, jj, k) -> (k, bx, by, jj, ii): a brick's 32 voxels in the order of their bit numbers
        b = m.reshape(bx, 8, by, 4, nz).transpose(4, 0, 2, 3, 1).reshape(-1, 32)
        words = np.packbits(b, axis=1, bitorder="little").view("<u4").reshape(-1).astype(np.uint64)
        out |= words << np.uint64(32 * half)
    return out
