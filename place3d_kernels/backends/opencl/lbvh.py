"""Linear BVH builder (Morton order, Karras 2012): the OpenCL backend's trees on every device.

A drive waits for its static mesh's tree more than for the walk: the binned SAH builder of ``bvh.py`` costs
about 3 us a triangle in NumPy on the host (one pass over every active triangle per tree level), a Town03
route's static mesh about 1 s on the dev VM. This builder sorts the triangles once by the Morton code of
their box centres and reads the whole binary radix tree off the sorted keys, every inner node at once
(Karras, "Maximizing Parallelism in the Construction of BVHs, Octrees, and k-d Trees", HPG 2012,
section 4): a few NumPy passes of O(n log n), 0.44 s for the same
mesh (1.30 s SAH; 3 builds each). The tree is looser than SAH's:
a Town03 drive's casts 10-27 % slower on the dev VM's PoCL, no slower on an H200's opencl:nvidia, which
the build more than repays where a drive's tree is built once and walked by 40 sweeps
(``OpenCLBackend.bvh_options`` has the figures; docs/performance.md).

The output is ``bvh.BVH`` in the builder's "levels" layout, so ``collapse_bvh4``, ``join_bvh`` and the
kernels read it unchanged, and every tree gives the same hits: the float64 triangle test decides each hit,
whatever tree found the candidates (tests/test_opencl_backend.py).

Details:

* Keys: group id (top bits), the 30-bit Morton code of the centre, then the triangle index, so every key is
  distinct and Karras' prefix lengths need no tie rule. The Morton grid is a cube (one scale, the largest
  centroid extent of the group), so a flat town's top splits fall across its long axes, as SAH's do; with
  a scale per axis, its height got as many bits as its width and the casts ran 19-37 % slower than SAH's.
* Leaves: a child whose key range holds at most ``leaf_size`` triangles is a leaf of that range (the sorted
  order is the leaf order), so leaves hold 1 .. ``leaf_size`` triangles.
* Groups (``groups``): keys of group g share their top bits, so the radix tree's node whose range is exactly
  the group exists (the longest common prefix of its first and last keys) and becomes root g; a group of one
  triangle gets a root whose two children are that triangle, as ``bvh.build_bvh`` makes.
* Depth: a radix tree is no deeper than its keys have bits; where the tree would be deeper than ``max_depth``
  or the keys do not fit in 64 bits (``morton_tree`` gives None), ``build_lbvh`` builds SAH's tree
  (``bvh.build_bvh``), whose depth bound is proven.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.opencl.bvh import DEFAULT_MAX_DEPTH, BVH, assemble_bvh, build_bvh, tree_input

__all__ = ["build_lbvh", "morton_tree"]

_MORTON_BITS = 10            # per axis: 30-bit codes


def _clz64(x: np.ndarray) -> np.ndarray:
    """Leading zero bits of each uint64 (64 for 0), from the exponents of its two 32-bit halves (exact in
    float64)."""
    hi = (x >> np.uint64(32)).astype(np.float64)
    lo = (x & np.uint64(0xFFFFFFFF)).astype(np.float64)
    return np.where(hi > 0, 32 - np.frexp(hi)[1], np.where(lo > 0, 64 - np.frexp(lo)[1], 64)).astype(np.int64)


def _spread(x: np.ndarray) -> np.ndarray:
    """The low 10 bits of each value spread to every third bit (bit i to bit 3i)."""
    x = x.astype(np.uint64) & np.uint64(0x3FF)
    for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def _radix_tree(key: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Karras' binary radix tree of ``n`` distinct sorted keys: per inner node i (0 .. n-2; node 0 the root)
    the first and last key of its range and its split gamma (the left child covers first .. gamma, the right
    gamma + 1 .. last; a child covering two or more keys is inner node gamma, resp. gamma + 1)."""
    n = len(key)

    def delta(i: np.ndarray, j: np.ndarray) -> np.ndarray:     # common prefix length, -1 outside the keys
        inside = (j >= 0) & (j < n)
        return np.where(inside, _clz64(key[i] ^ key[np.clip(j, 0, n - 1)]), -1)

    i_all = np.arange(n - 1, dtype=np.int64)
    d = np.where(delta(i_all, i_all + 1) >= delta(i_all, i_all - 1), 1, -1)      # direction of the range
    d_min = delta(i_all, i_all - d)
    l_max = np.full(n - 1, 2, dtype=np.int64)                 # an upper bound of the range's length
    a = i_all
    while len(a):
        grow = delta(a, a + l_max[a] * d[a]) > d_min[a]
        l_max[a[grow]] *= 2
        a = a[grow]
    length = np.zeros(n - 1, dtype=np.int64)                  # the range's length, bit by bit
    t = l_max // 2
    a = i_all
    while len(a):
        ok = delta(a, a + (length[a] + t[a]) * d[a]) > d_min[a]
        length[a[ok]] += t[a[ok]]
        t[a] //= 2
        a = a[t[a] >= 1]
    j = i_all + length * d
    d_node = delta(i_all, j)
    s = np.zeros(n - 1, dtype=np.int64)                       # the split: the last key sharing more than d_node
    a, div = i_all, 2
    while len(a):
        step = (length[a] + div - 1) // div
        ok = delta(a, a + (s[a] + step) * d[a]) > d_node[a]
        s[a[ok]] += step[ok]
        a = a[step > 1]
        div *= 2
    gamma = i_all + s * d + np.minimum(d, 0)
    return np.minimum(i_all, j), np.maximum(i_all, j), gamma


def build_lbvh(vertices, faces, leaf_size: int = 4, max_depth: int | None = DEFAULT_MAX_DEPTH, groups=None,
               **sah) -> BVH:
    """``bvh.BVH`` of a triangle mesh (one tree per group of faces with ``groups``) in Morton order
    (``morton_tree``), or where that tree would be deeper than ``max_depth``, ``bvh.build_bvh``'s binned SAH tree
    with the same arguments and ``sah`` (its ``bins``, ``full_sah_limit``). Either gives the same hits."""
    tree = morton_tree(vertices, faces, leaf_size, max_depth, groups)
    if tree is None:
        tree = build_bvh(vertices, faces, leaf_size=leaf_size, max_depth=max_depth, groups=groups, **sah)
    return tree


def morton_tree(vertices, faces, leaf_size: int = 4, max_depth: int | None = DEFAULT_MAX_DEPTH,
                groups=None) -> BVH | None:
    """The Morton-order tree of ``build_lbvh``, or None when it would be deeper than ``max_depth`` or its keys
    need more than 64 bits. Vertices go to float32 first, as in ``bvh.build_bvh``."""
    v, f, sizes, tlo, thi = tree_input(vertices, faces, groups)
    n = len(f)
    n_groups = len(sizes)
    index_bits = max(1, int(n - 1).bit_length())
    group_bits = int(n_groups - 1).bit_length()
    if group_bits + 3 * _MORTON_BITS + index_bits > 64:
        return None
    starts = np.zeros(n_groups, dtype=np.int64)
    np.cumsum(sizes[:-1], out=starts[1:])
    ends = starts + sizes - 1

    centre = 0.5 * (tlo.astype(np.float64) + thi)
    gid = np.repeat(np.arange(n_groups, dtype=np.int64), sizes)
    c_min = np.minimum.reduceat(centre, starts, axis=0)
    scale = (np.maximum.reduceat(centre, starts, axis=0) - c_min).max(axis=1, keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    cells = 1 << _MORTON_BITS
    q = np.clip(((centre - c_min[gid]) / scale[gid] * cells).astype(np.int64), 0, cells - 1)
    code = (_spread(q[:, 0]) << np.uint64(2)) | (_spread(q[:, 1]) << np.uint64(1)) | _spread(q[:, 2])
    key = ((gid.astype(np.uint64) << np.uint64(3 * _MORTON_BITS + index_bits)) | (code << np.uint64(index_bits))
           | np.arange(n, dtype=np.uint64))
    order = np.argsort(key)
    first, last, gamma = _radix_tree(key[order])
    m = n - 1

    # group roots: the radix node whose range is exactly the group (node start or node end)
    multi = np.flatnonzero(sizes > 1)
    s_, e_ = starts[multi], ends[multi]
    at_s = np.minimum(s_, max(m - 1, 0))
    roots = np.where((s_ < m) & (first[at_s] == s_) & (last[at_s] == e_), s_, e_) if len(multi) else multi
    # inner nodes level by level (ids 0 .. G-1 the roots, then breadth first): a child of more than leaf_size
    # triangles is inner, any other a leaf of its range
    levels = [(multi, roots)]                                  # (new ids, radix ids)
    n_nodes = n_groups
    frontier = roots
    while len(frontier):
        kids = np.stack([gamma[frontier], gamma[frontier] + 1], 1).reshape(-1)
        size = np.stack([gamma[frontier] - first[frontier] + 1, last[frontier] - gamma[frontier]], 1).reshape(-1)
        frontier = kids[size > leaf_size]
        if len(frontier):
            levels.append((np.arange(n_nodes, n_nodes + len(frontier)), frontier))
            n_nodes += len(frontier)
    depth = len(levels)
    if max_depth is not None and depth > max_depth:
        return None
    new_id = np.zeros(max(m, 1), dtype=np.int64)
    ids = np.concatenate([x[0] for x in levels])
    radix = np.concatenate([x[1] for x in levels])
    new_id[radix] = ids
    c_start = np.stack([first[radix], gamma[radix] + 1], 1)            # (inner, 2): each child's first key
    c_size = np.stack([gamma[radix] - first[radix] + 1, last[radix] - gamma[radix]], 1)
    leaf = c_size <= leaf_size
    c_ref = np.zeros((n_nodes, 2), np.int32)
    c_cnt = np.zeros((n_nodes, 2), np.int32)
    c_ref[ids] = np.where(leaf, c_start, new_id[np.minimum(np.stack([gamma[radix], gamma[radix] + 1], 1),
                                                           max(m - 1, 0))])
    c_cnt[ids] = np.where(leaf, c_size, 0)

    # leaf boxes: the leaves partition the sorted triangles, so one reduceat over them
    single = np.flatnonzero(sizes == 1)
    leaf_starts = np.unique(np.concatenate([c_start[leaf], starts[single]]))
    l_lo = np.minimum.reduceat(tlo[order], leaf_starts, axis=0)
    l_hi = np.maximum.reduceat(thi[order], leaf_starts, axis=0)
    which = np.searchsorted(leaf_starts, c_start)
    which = np.where(leaf, which, 0)
    # inner boxes from the deepest level up: a node's box is the union of its children's
    c_lo = np.zeros((n_nodes, 2, 3), np.float32)
    c_hi = np.zeros((n_nodes, 2, 3), np.float32)
    box_lo = np.zeros((n_nodes, 3), np.float32)
    box_hi = np.zeros((n_nodes, 3), np.float32)
    bounds = np.cumsum([0] + [len(x[0]) for x in levels])
    for lv in range(depth - 1, -1, -1):
        r = slice(bounds[lv], bounds[lv + 1])
        node, lf = ids[r], leaf[r][..., None]
        child = np.where(leaf[r], 0, c_ref[node])
        c_lo[node] = np.where(lf, l_lo[which[r]], box_lo[child])
        c_hi[node] = np.where(lf, l_hi[which[r]], box_hi[child])
        box_lo[node] = c_lo[node].min(axis=1)
        box_hi[node] = c_hi[node].max(axis=1)
    if len(single):                        # a group of one triangle: a root whose two children are that leaf
        k = np.searchsorted(leaf_starts, starts[single])
        c_ref[single], c_cnt[single] = starts[single][:, None], 1
        c_lo[single], c_hi[single] = l_lo[k][:, None], l_hi[k][:, None]
    n_leaves = int(leaf.sum()) + len(single)
    return assemble_bvh(v, f, order.astype(np.int64), c_lo, c_hi, c_ref, c_cnt, depth, n_leaves, max_depth,
                        tlo.min(axis=0), thi.max(axis=0), n_groups)
