"""Host BVH builder for the OpenCL ray caster: binned SAH, vectorised in NumPy, with a proven depth bound.

Layout (what ``raycast.cl`` reads):

* ``nodes``: (n_nodes, 16) float32. Row ``i`` holds the boxes of both children of inner node ``i``
  (``lo0 xyz, hi0 xyz, lo1 xyz, hi1 xyz``) followed by four int32 stored bit-for-bit:
  ``ref0, cnt0, ref1, cnt1``. ``cnt == 0``: the child is inner node ``ref``; ``cnt > 0``: the child is a
  leaf holding triangles ``ref .. ref + cnt - 1`` of the reordered triangle array. Node 0 is the root (a
  grouped build, ``build_bvh(groups=...)``: nodes 0 .. G-1 are the groups' roots, one tree per group).
* ``tris``: (F, 12) float32 in leaf order: ``v0 xyz, face id (int32 bits), v1 xyz, 0, v2 xyz, 0`` with
  the ORIGINAL face id, so hits report faces in the caller's order.

Build: top-down, one level of the tree per NumPy pass (every node of a level is split at once), binned SAH
over up to ``bins`` centroid bins (Wald 2007; fewer bins once nodes are small), on all three axes while a
level has few nodes and on the widest centroid axis after that (``full_sah_limit``; 0, the widest axis
everywhere, on CPU devices, where a drive waits for the build more than for the walk). Triangles whose
node becomes a leaf leave the working set, so each pass costs O(active triangles) (build times:
bench/run_bench.py). Child boxes are padded outward by ~2**-21 of their coordinates (see ``_pad``).

The OpenCL backend builds its trees with ``lbvh.build_lbvh`` instead (Morton order, a few NumPy passes in all, a
looser tree that its drives' sweeps walk about as fast), which falls back to this builder where its tree would be
too deep (``OpenCLBackend.bvh_options``).

Devices traverse the 4-wide collapse of this tree by default (``collapse_bvh4``: one float4 slab test per
node; somewhat faster than the binary tree on an NVIDIA GPU, bench/README.md, "What the studies found",
ray-mesh, OpenCL on NVIDIA).

Depth bound (why a fixed traversal stack is safe). Let ``L = leaf_size`` and, for a node of ``n``
triangles, ``need(n) = ceil(log2(ceil(n / L)))`` = the number of inner levels an object-median split
needs below (and including) it. Invariant for every node at inner depth ``d`` (root: d = 1)::

    d - 1 + need(n) <= max_depth

It holds at the root when ``need(F) <= max_depth`` (F <= L * 2**max_depth). An SAH split is accepted only
if both children keep it (``d + need(n_child) <= max_depth``); otherwise the node is split at the object
median, which keeps it because ``need(ceil(n / 2)) = need(n) - 1``. Nodes with ``n <= L`` at depth
``max_depth`` become leaves. Hence no inner node is deeper than ``max_depth``. Traversal pushes at most
one entry per inner level of the current path (push far child, descend near child), so a stack of
``max_depth`` entries never overflows; the kernel still checks and flags a ray if it would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BVH", "BVH4", "build_bvh", "join_bvh", "dfs_layout", "collapse_bvh4", "need_levels", "validate_bvh",
           "tree_input", "assemble_bvh", "DEFAULT_MAX_DEPTH"]

#: Inner-node depth cap; the binary traversal stack of ``raycast.cl`` has this many entries (the 4-wide
#: one three times as many).
DEFAULT_MAX_DEPTH = 64

_C_TRAV = 1.0  # SAH cost of visiting one inner node, relative to one triangle test
_FULL_SAH_LIMIT = 65536  # bins x nodes of a level up to which all three axes are tried


@dataclass
class BVH:
    nodes: np.ndarray         # (n_nodes, 16) float32 (ints bit-cast in columns 12..15)
    tris: np.ndarray          # (F, 12) float32, leaf order
    order: np.ndarray         # (F,) int32: original face id of each reordered triangle
    depth: int                # deepest inner node (root = 1)
    max_depth: int            # the cap the builder guaranteed
    n_leaves: int
    lo: np.ndarray            # scene bounds (3,) float32
    hi: np.ndarray
    roots: int = 1            # nodes 0 .. roots - 1 are the roots, one per group (build_bvh's ``groups``)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    def child_refs(self) -> np.ndarray:
        """(n_nodes, 4) int32 view: ref0, cnt0, ref1, cnt1."""
        return self.nodes[:, 12:16].view(np.int32)


def need_levels(n, leaf_size: int) -> np.ndarray:
    """Inner levels an object-median build needs for ``n`` triangles (0 when ``n <= leaf_size``)."""
    m = (np.asarray(n, dtype=np.int64) + leaf_size - 1) // leaf_size
    m = np.maximum(m, 1)
    # bit_length(m - 1) == ceil(log2(m)) for m >= 1, exact for m < 2**52
    out = np.zeros(m.shape, dtype=np.int64)
    big = m > 1
    out[big] = np.floor(np.log2((m[big] - 1).astype(np.float64))).astype(np.int64) + 1
    return out


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def build_bvh(vertices: np.ndarray, faces: np.ndarray, leaf_size: int = 4, bins: int = 16,
              max_depth: int | None = DEFAULT_MAX_DEPTH, layout: str = "levels", groups=None,
              full_sah_limit: int | None = None) -> BVH:
    """Build the flattened BVH of a triangle mesh, or one tree per group of its faces.

    Args:
        vertices: (V, 3) float; converted to float32 first, so boxes bound the triangles the kernel tests.
        faces: (F, 3) int vertex indices.
        leaf_size: largest leaf the depth argument relies on (SAH may stop earlier).
        bins: SAH bins per axis.
        max_depth: inner-depth cap (see the module docstring); ``None`` disables it (tests only: shows
            how deep plain SAH goes on adversarial input).
        layout: ``"levels"`` (inner nodes numbered level by level, as built) or ``"dfs"`` (``dfs_layout``).
        groups: optional (G,) face counts, each >= 1, summing to F: faces ``0 .. groups[0] - 1`` are group 0,
            and so on. Each group gets a tree of its own, rooted at node ``g`` (``BVH.roots`` = G), built level
            by level together with the others, so G small meshes cost about one build of their union
            (``MeshGroups``). Only with ``layout="levels"``.
        full_sah_limit: a level of the build tries all three axes while its nodes times bins are at most this
            (None: ``_FULL_SAH_LIMIT``), else each node's widest centroid axis; 0 = the widest axis everywhere
            (the OpenCL backend's choice on CPU devices, where the build, not the walk, is what a drive waits
            for). Any value gives a valid tree and the same hits (the float64 test decides); only speed differs.
    """
    if layout not in ("levels", "dfs"):
        raise ValueError(f"layout must be 'levels' or 'dfs', got {layout!r}")
    if groups is not None and layout != "levels":
        raise ValueError("grouped trees are built with layout='levels' only")
    bvh = _build(vertices, faces, leaf_size, bins, max_depth, groups,
                 _FULL_SAH_LIMIT if full_sah_limit is None else int(full_sah_limit))
    return dfs_layout(bvh) if layout == "dfs" else bvh


def _group_sizes(groups, n_tri: int) -> np.ndarray:
    """(G,) int64 face counts of ``build_bvh``'s ``groups`` (one group of every face for None), checked."""
    sizes = np.array([n_tri] if groups is None else groups, dtype=np.int64).reshape(-1)
    if len(sizes) == 0 or sizes.min() < 1 or sizes.sum() != n_tri:
        raise ValueError(f"groups must be face counts >= 1 summing to the {n_tri} faces, got {len(sizes)} "
                         f"counts summing to {int(sizes.sum())}")
    return sizes


def tree_input(vertices, faces, groups=None) -> tuple[np.ndarray, ...]:
    """What a tree builder starts from, checked: (vertices (V, 3) float32, faces (F, 3) int64, the groups' face
    counts (checked), each triangle's box lo and hi (F, 3) float32).

    Raises:
        ValueError: vertices not finite in float32, no faces, or groups that do not cover the faces."""
    with np.errstate(over="ignore"):
        v = np.ascontiguousarray(vertices, dtype=np.float32)
    if not np.all(np.isfinite(v)):
        raise ValueError("mesh vertices are not finite in float32 (|x| > 3.4e38?); shift the mesh near the origin")
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if len(f) == 0:
        raise ValueError("cannot build a BVH of an empty mesh")
    sizes = _group_sizes(groups, len(f))
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return v, f, sizes, np.minimum(np.minimum(p0, p1), p2), np.maximum(np.maximum(p0, p1), p2)


def _build(vertices, faces, leaf_size, bins, max_depth, groups=None, full_sah_limit=_FULL_SAH_LIMIT) -> BVH:
    v, f, sizes, tlo, thi = tree_input(vertices, faces, groups)
    n_tri = len(f)
    G = len(sizes)
    if max_depth is not None and int(need_levels(sizes.max(), leaf_size)) > max_depth:
        what = f"{n_tri} triangles need" if groups is None else f"a group of {int(sizes.max())} triangles needs"
        raise ValueError(f"{what} more than max_depth={max_depth} levels with leaf_size={leaf_size}")
    cap = np.iinfo(np.int64).max if max_depth is None else int(max_depth)
    starts = np.zeros(G, dtype=np.int64)
    np.cumsum(sizes[:-1], out=starts[1:])

    perm = np.empty(n_tri, dtype=np.int64)
    # node storage (grown as needed); nodes 0 .. G-1 are the groups' roots
    cap_nodes = max(16, n_tri // 2 + G + 16)
    c_lo = np.empty((cap_nodes, 2, 3), dtype=np.float32)
    c_hi = np.empty((cap_nodes, 2, 3), dtype=np.float32)
    c_ref = np.zeros((cap_nodes, 2), dtype=np.int32)
    c_cnt = np.zeros((cap_nodes, 2), dtype=np.int32)
    n_nodes = G
    # a root must be an inner node: a group of one triangle gets both children = its one-triangle leaf
    one = np.flatnonzero(sizes == 1)
    perm[starts[one]] = starts[one]
    c_lo[one] = tlo[starts[one]][:, None]
    c_hi[one] = thi[starts[one]][:, None]
    c_ref[one] = starts[one][:, None]
    c_cnt[one] = 1
    n_leaves = len(one)
    max_seen = 1

    # working set: triangles of the active nodes, concatenated in node order, as rows
    # (lo x y z, hi x y z) so that one np.take moves them all
    many = np.flatnonzero(sizes > 1)
    w_id = np.arange(n_tri, dtype=np.int64)
    if len(one):
        w_id = w_id[np.repeat(sizes > 1, sizes)]
    geo = np.empty((6, len(w_id)), dtype=np.float32)
    geo[0:3] = tlo[w_id].T
    geo[3:6] = thi[w_id].T
    # active nodes
    a_start = starts[many]                       # position of the node's first triangle in ``perm``
    a_cnt = sizes[many]
    a_parent = -1 - many                         # parent inner node (a root: -1 - its group)
    a_slot = np.zeros(len(many), dtype=np.int64)
    a_depth = np.ones(len(many), dtype=np.int64)  # inner depth this node would have
    root_lo = tlo.min(axis=0)
    root_hi = thi.max(axis=0)
    big = np.iinfo(np.int64).max // 4

    while len(a_cnt):
        k = len(a_cnt)
        m = len(w_id)
        # fewer bins once nodes are small: a node of n triangles fills at most n bins
        B = int(np.clip(m // k, 4, bins))
        seg_off = np.zeros(k, dtype=np.int64)
        np.cumsum(a_cnt[:-1], out=seg_off[1:])
        seg = np.repeat(np.arange(k, dtype=np.int64), a_cnt)
        seg32 = seg.astype(np.int32)
        cen = 0.5 * (geo[0:3] + geo[3:6])                       # (3, m) float32
        n_lo = np.stack([np.minimum.reduceat(geo[c], seg_off) for c in range(3)], 1)
        n_hi = np.stack([np.maximum.reduceat(geo[3 + c], seg_off) for c in range(3)], 1)
        cmin = np.stack([np.minimum.reduceat(cen[c], seg_off) for c in range(3)], 1)
        cmax = np.stack([np.maximum.reduceat(cen[c], seg_off) for c in range(3)], 1)
        has_parent = a_parent >= 0
        c_lo[a_parent[has_parent], a_slot[has_parent]] = n_lo[has_parent]
        c_hi[a_parent[has_parent], a_slot[has_parent]] = n_hi[has_parent]
        is_root = ~has_parent

        # ---- binned SAH: all three axes while the level is small, else the widest centroid axis
        ext = (cmax - cmin).astype(np.float32)
        area = _half_area(n_lo.astype(np.float64), n_hi.astype(np.float64))
        area = np.where(area > 0, area, 1.0)
        # largest child keeping the depth invariant: need(n) <= cap - d  <=>  n <= L * 2**(cap - d)
        room = cap - a_depth
        lim = np.where(room >= 40, big, leaf_size * np.left_shift(1, np.clip(room, 0, 40)))
        limited = bool(np.any(lim < a_cnt))
        a_cnt32 = a_cnt.astype(np.int32)
        if k * B <= full_sah_limit:
            cand_axes = [np.full(k, ax, dtype=np.int64) for ax in range(3)]
        else:
            cand_axes = [np.argmax(ext, axis=1)]
        best_cost = np.full(k, np.inf)
        best_axis = np.zeros(k, dtype=np.int64)
        best_bin = np.zeros(k, dtype=np.int64)
        best_nl = np.zeros(k, dtype=np.int64)
        best_bins = None
        ar = np.arange(k)
        for axn in cand_axes:
            e_n = ext[ar, axn]
            scale = np.where(e_n > 0, np.float32(B * (1 - 1e-6)) / np.where(e_n > 0, e_n, 1), 0).astype(np.float32)
            ax_t = axn[seg]
            c_t = np.choose(ax_t, cen) if len(cand_axes) == 1 else cen[int(axn[0])]
            bin_t = ((c_t - cmin[ar, axn][seg]) * scale[seg]).astype(np.int32)
            np.clip(bin_t, 0, B - 1, out=bin_t)
            key = seg32 * np.int32(B) + bin_t
            cnt = np.bincount(key, minlength=k * B).reshape(k, B).T  # (B, k) view
            ext_l, ext_r = [], []
            for c in range(3):
                lo = np.full(k * B, np.inf, dtype=np.float32)
                np.minimum.at(lo, key, geo[c])
                hi = np.full(k * B, -np.inf, dtype=np.float32)
                np.maximum.at(hi, key, geo[3 + c])
                lo = np.ascontiguousarray(lo.reshape(k, B).T)     # (B, k)
                hi = np.ascontiguousarray(hi.reshape(k, B).T)
                llo, lhi, rlo, rhi = lo.copy(), hi.copy(), lo, hi
                for j in range(1, B):  # running min/max over bins, row by row (fast in NumPy)
                    np.minimum(llo[j - 1], llo[j], out=llo[j])
                    np.maximum(lhi[j - 1], lhi[j], out=lhi[j])
                    np.minimum(rlo[B - j], rlo[B - j - 1], out=rlo[B - j - 1])
                    np.maximum(rhi[B - j], rhi[B - j - 1], out=rhi[B - j - 1])
                ext_l.append(np.maximum(lhi[:-1] - llo[:-1], 0))
                ext_r.append(np.maximum(rhi[1:] - rlo[1:], 0))
            ha = [e[0] * e[1] + e[1] * e[2] + e[2] * e[0] for e in ([x.astype(np.float64) for x in ext_l],
                                                             [x.astype(np.float64) for x in ext_r])]
            nl = np.cumsum(cnt, axis=0, dtype=np.int32)[:-1]         # (B-1, k)
            nr = a_cnt32[None, :] - nl
            cost = ha[0] * nl + ha[1] * nr
            bad = (nl == 0) | (nr == 0)
            if limited:
                bad |= (nl > lim[None, :]) | (nr > lim[None, :])
            cost[bad] = np.inf
            # argmin over bins, row by row (NumPy's argmin along axis 0 is slow)
            cmin_row = cost[0].copy()
            j = np.zeros(k, dtype=np.int64)
            for r in range(1, B - 1):
                lt = cost[r] < cmin_row
                np.copyto(cmin_row, cost[r], where=lt)
                j[lt] = r
            cj = cmin_row.astype(np.float64) / area + _C_TRAV
            cj[~(e_n > 0)] = np.inf
            better = cj < best_cost
            best_cost = np.where(better, cj, best_cost)
            best_axis = np.where(better, axn, best_axis)
            best_bin = np.where(better, j, best_bin)
            best_nl = np.where(better, nl[j, ar], best_nl)
            if best_bins is None:
                best_bins = bin_t
            else:
                best_bins = np.where(better[seg], bin_t, best_bins)

        sah_ok = np.isfinite(best_cost)
        make_leaf = (a_cnt <= leaf_size) & (~sah_ok | (a_cnt <= best_cost) | (a_depth >= cap))
        make_leaf |= a_cnt <= 1
        make_leaf &= ~is_root  # a root is always an inner node (its group has >= 2 triangles here)
        if np.any(make_leaf & (a_cnt > leaf_size)):  # pragma: no cover - excluded by the invariant
            raise AssertionError("BVH depth invariant violated")
        median = ~make_leaf & ~sah_ok
        in_leaf = make_leaf[seg]
        rank = np.arange(m, dtype=np.int64) - seg_off[seg]

        # ---- leaves: their triangles reach their final place
        leaf_nodes = np.flatnonzero(make_leaf)
        if len(leaf_nodes):
            perm[(a_start[seg] + rank)[in_leaf]] = w_id[in_leaf]
            par, slot = a_parent[leaf_nodes], a_slot[leaf_nodes]
            c_ref[par, slot] = a_start[leaf_nodes]
            c_cnt[par, slot] = a_cnt[leaf_nodes]
            n_leaves += len(leaf_nodes)

        # ---- inner nodes: ids and parent links
        inner = np.flatnonzero(~make_leaf)
        if len(inner) == 0:
            break
        ids = np.where(is_root, -1 - a_parent, 0)
        nonroot = inner[~is_root[inner]]
        n_new = len(nonroot)
        if n_nodes + n_new > len(c_ref):
            grow = max(len(c_ref), n_new) + 16
            c_lo = np.concatenate([c_lo, np.empty((grow, 2, 3), np.float32)])
            c_hi = np.concatenate([c_hi, np.empty((grow, 2, 3), np.float32)])
            c_ref = np.concatenate([c_ref, np.zeros((grow, 2), np.int32)])
            c_cnt = np.concatenate([c_cnt, np.zeros((grow, 2), np.int32)])
        ids[nonroot] = np.arange(n_nodes, n_nodes + n_new)
        n_nodes += n_new
        c_ref[a_parent[nonroot], a_slot[nonroot]] = ids[nonroot]
        c_cnt[a_parent[nonroot], a_slot[nonroot]] = 0
        max_seen = max(max_seen, int(a_depth[inner].max()))

        # ---- stable partition of each inner node: lefts first, then rights
        go_left = best_bins <= best_bin[seg]
        n_left = best_nl.copy()
        med_nodes = np.flatnonzero(median)
        if len(med_nodes):
            # object median along the widest centroid extent (index order when all centroids coincide)
            idx = np.flatnonzero(median[seg])
            axis = np.argmax(ext, axis=1)
            coord = cen[axis[seg[idx]], idx]
            order = np.lexsort((idx, coord, seg[idx]))
            r = np.empty(len(idx), dtype=np.int64)
            srt = seg[idx[order]]
            r[order] = np.arange(len(idx)) - np.searchsorted(srt, srt, side="left")
            half = a_cnt // 2
            go_left[idx] = r < half[seg[idx]]
            n_left[med_nodes] = half[med_nodes]
        gl = go_left.astype(np.int64)
        cl = np.cumsum(gl) - gl
        cr = rank - cl + cl[seg_off][seg]                          # rights before me in my node
        local = np.where(go_left, cl - cl[seg_off][seg], n_left[seg] + cr)
        kept = np.where(make_leaf, 0, a_cnt)
        new_off = np.zeros(k, dtype=np.int64)
        np.cumsum(kept[:-1], out=new_off[1:])
        keep = ~in_leaf
        src = np.empty(int(kept.sum()), dtype=np.int64)
        src[(new_off[seg] + local)[keep]] = np.flatnonzero(keep)
        geo = np.take(geo, src, axis=1)
        w_id = w_id[src]

        # children of every inner node, in node order (left, right)
        nl_k = n_left[inner]
        nr_k = a_cnt[inner] - nl_k
        a_start = np.stack([a_start[inner], a_start[inner] + nl_k], 1).reshape(-1)
        a_cnt = np.stack([nl_k, nr_k], 1).reshape(-1)
        a_parent = np.repeat(ids[inner], 2)
        a_slot = np.tile(np.array([0, 1], dtype=np.int64), len(inner))
        a_depth = np.repeat(a_depth[inner] + 1, 2)

    return assemble_bvh(v, f, perm, c_lo[:n_nodes], c_hi[:n_nodes], c_ref[:n_nodes], c_cnt[:n_nodes],
                        max_seen, n_leaves, max_depth, root_lo, root_hi, G)


def _pad(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grow float32 boxes outward by about 2**-21 of their coordinates (plus a denormal floor).

    The kernel's slab test is conservative for rays whose direction components are all non-zero
    (Ize 2013); a component that is exactly 0 is replaced by 1e-20 there, which would reject a ray lying
    exactly in a box face (e.g. an axis-aligned ray through a silhouette vertex). The padding keeps such
    rays inside, at a negligible cost in extra box hits.
    """
    lo64, hi64 = lo.astype(np.float64), hi.astype(np.float64)
    mag = np.maximum(np.abs(lo64), np.abs(hi64))
    pad = mag * 2.0**-21 + 1e-30
    with np.errstate(over="ignore"):
        plo = np.nextafter((lo64 - pad).astype(np.float32), np.float32(-np.inf))
        phi = np.nextafter((hi64 + pad).astype(np.float32), np.float32(np.inf))
    return plo, phi


def assemble_bvh(v, f, perm, c_lo, c_hi, c_ref, c_cnt, depth, n_leaves, max_depth, lo, hi, roots=1) -> BVH:
    """The ``BVH`` of a built binary tree (this module's and ``lbvh``'s builders): per inner node its two children's
    boxes (padded outward here, ``_pad``), refs and counts, and ``perm``, the original face of each leaf slot."""
    n = len(c_ref)
    nodes = np.empty((n, 16), dtype=np.float32)
    c_lo, c_hi = _pad(np.asarray(c_lo), np.asarray(c_hi))
    nodes[:, 0:3] = c_lo[:, 0]
    nodes[:, 3:6] = c_hi[:, 0]
    nodes[:, 6:9] = c_lo[:, 1]
    nodes[:, 9:12] = c_hi[:, 1]
    ints = nodes[:, 12:16].view(np.int32)
    ints[:, 0] = c_ref[:, 0]
    ints[:, 1] = c_cnt[:, 0]
    ints[:, 2] = c_ref[:, 1]
    ints[:, 3] = c_cnt[:, 1]
    ff = f[perm]
    tris = np.zeros((len(perm), 12), dtype=np.float32)
    tris[:, 0:3] = v[ff[:, 0]]
    tris[:, 4:7] = v[ff[:, 1]]
    tris[:, 8:11] = v[ff[:, 2]]
    tris[:, 3].view(np.int32)[:] = perm.astype(np.int32)
    return BVH(nodes=nodes, tris=tris, order=perm.astype(np.int32), depth=int(depth),
               max_depth=-1 if max_depth is None else int(max_depth), n_leaves=int(n_leaves),
               lo=np.asarray(lo, np.float32), hi=np.asarray(hi, np.float32), roots=int(roots))


def join_bvh(first: BVH, second: BVH, offset) -> BVH:
    """One tree over two: a new root whose children are ``first`` (its coordinates moved by ``offset``) and
    ``second``, for a mesh whose faces are ``first``'s followed by ``second``'s (face ids of ``second`` follow on
    from ``first``'s). What a mesh extending another reuses (``Mesh.extended``: a town's roads, built once,
    under each route's roadside); the hits are those of a tree built over the whole mesh (with doubles the
    float64 test decides whatever the tree; tests/test_mesh_extended.py).

    ``offset``: (3,) float64 added to ``first``'s coordinates (the difference of the two meshes' shifts, whole
    metres). Its boxes are moved in float64 and rounded outward to float32, so each still holds its triangles;
    the float32 triangles are moved and rounded to nearest (read only by devices without doubles). Each tree
    must have one root and a depth below its cap: the joined depth is one more than the deeper of the two."""
    if first.roots != 1 or second.roots != 1:
        raise ValueError("join_bvh joins single-root trees")
    off = np.asarray(offset, dtype=np.float64).reshape(3)
    n1, f1 = len(first.nodes), len(first.tris)
    a = first.nodes.copy()
    boxes = a[:, :12].astype(np.float64).reshape(-1, 4, 3) + off           # lo0, hi0, lo1, hi1
    moved = boxes.astype(np.float32)
    lo, hi = moved[:, 0::2], moved[:, 1::2]
    moved[:, 0::2] = np.where(lo > boxes[:, 0::2], np.nextafter(lo, np.float32(-np.inf)), lo)
    moved[:, 1::2] = np.where(hi < boxes[:, 1::2], np.nextafter(hi, np.float32(np.inf)), hi)
    a[:, :12] = moved.reshape(-1, 12)
    b = second.nodes.copy()
    for nodes, inner_shift, leaf_shift in ((a, 1, 0), (b, 1 + n1, f1)):
        ints = nodes[:, 12:16].view(np.int32)
        for c in (0, 2):
            inner = ints[:, c + 1] == 0
            ints[:, c] += np.where(inner, inner_shift, leaf_shift).astype(np.int32)
    root = np.zeros((1, 16), dtype=np.float32)
    for c, n in ((0, a), (1, b)):           # each child's box: the union of its root's two child boxes
        root[0, 6 * c:6 * c + 3] = np.minimum(n[0, 0:3], n[0, 6:9])
        root[0, 6 * c + 3:6 * c + 6] = np.maximum(n[0, 3:6], n[0, 9:12])
    root[0, 12:16].view(np.int32)[:] = (1, 0, 1 + n1, 0)
    t1 = first.tris.copy()
    for k in (0, 4, 8):
        t1[:, k:k + 3] = (t1[:, k:k + 3].astype(np.float64) + off).astype(np.float32)
    t2 = second.tris.copy()
    t2[:, 3].view(np.int32)[:] += f1
    caps = [t.max_depth for t in (first, second)]
    return BVH(nodes=np.concatenate([root, a, b]), tris=np.concatenate([t1, t2]),
               order=np.concatenate([first.order, second.order + f1]).astype(np.int32),
               depth=max(first.depth, second.depth) + 1, max_depth=-1 if min(caps) < 0 else max(caps) + 1,
               n_leaves=first.n_leaves + second.n_leaves, lo=np.minimum(root[0, 0:3], root[0, 6:9]),
               hi=np.maximum(root[0, 3:6], root[0, 9:12]))


def dfs_layout(bvh: BVH) -> BVH:
    """The same tree with its inner nodes renumbered in depth-first preorder (left child first), so a
    node's left child is the next row: the builder numbers them level by level, which puts a parent and
    its children far apart in memory. Leaves, triangles, depth and results are unchanged; only where a
    node's row lives moves (``bench/raymesh_bvh.py --opencl`` times it on GPUs)."""
    ints = bvh.nodes[:, 12:16].view(np.int32)
    n = len(ints)
    inner = np.stack([ints[:, 1] == 0, ints[:, 3] == 0], axis=1)          # (n, 2): child is an inner node
    child = np.stack([ints[:, 0], ints[:, 2]], axis=1).astype(np.int64)
    levels, frontier = [], np.array([0], dtype=np.int64)
    while len(frontier):                                                   # inner nodes, level by level
        levels.append(frontier)
        frontier = child[frontier][inner[frontier]]
    size = np.ones(n, dtype=np.int64)                                      # inner nodes in each subtree
    for lev in reversed(levels[:-1]):
        size[lev] += np.where(inner[lev], size[np.where(inner[lev], child[lev], 0)], 0).sum(axis=1)
    pre = np.zeros(n, dtype=np.int64)
    for lev in levels:
        left = np.where(inner[lev, 0], size[np.where(inner[lev, 0], child[lev, 0], 0)], 0)
        pre[child[lev, 0][inner[lev, 0]]] = (pre[lev] + 1)[inner[lev, 0]]
        pre[child[lev, 1][inner[lev, 1]]] = (pre[lev] + 1 + left)[inner[lev, 1]]
    nodes = np.empty_like(bvh.nodes)
    nodes[pre] = bvh.nodes
    out = nodes[:, 12:16].view(np.int32)
    for c in (0, 1):
        is_inner = out[:, 2 * c + 1] == 0
        out[is_inner, 2 * c] = pre[out[is_inner, 2 * c]]
    return BVH(nodes=nodes, tris=bvh.tris, order=bvh.order, depth=bvh.depth, max_depth=bvh.max_depth,
               n_leaves=bvh.n_leaves, lo=bvh.lo, hi=bvh.hi)


def validate_bvh(bvh: BVH, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Check structure: every triangle in exactly one leaf, child boxes contain their triangles. Tests."""
    refs = bvh.child_refs()
    n_tri = len(faces)
    seen = np.zeros(n_tri, dtype=np.int64)
    v = np.asarray(vertices, np.float32)
    stack = [(g, 1) for g in range(bvh.roots)]
    max_d = 0
    while stack:
        node, depth = stack.pop()
        max_d = max(max_d, depth)
        for c in range(2):
            ref, cnt = int(refs[node, 2 * c]), int(refs[node, 2 * c + 1])
            lo = bvh.nodes[node, 6 * c:6 * c + 3]
            hi = bvh.nodes[node, 6 * c + 3:6 * c + 6]
            if cnt == 0:
                stack.append((ref, depth + 1))
                # the child's children lie inside this box
                for cc in range(2):
                    assert np.all(bvh.nodes[ref, 6 * cc:6 * cc + 3] >= lo)
                    assert np.all(bvh.nodes[ref, 6 * cc + 3:6 * cc + 6] <= hi)
            else:
                ids = bvh.order[ref:ref + cnt]
                # a root of one triangle has that leaf as both children: count it once
                if c == 0 or node >= bvh.roots or refs[node, 1] != 1 or refs[node, 0] != ref:
                    seen[ids] += 1
                pts = v[np.asarray(faces)[ids]].reshape(-1, 3)
                assert np.all(pts >= lo) and np.all(pts <= hi)
    assert np.all(seen == 1), "every triangle must sit in exactly one leaf"
    assert max_d == bvh.depth


# ------------------------------------------------------------------------------ 4-wide collapse
@dataclass
class BVH4:
    """The BVH collapsed to 4 children per node (for CPUs: one SIMD box test covers a whole node).

    ``nodes``: (n_nodes, 32) float32, per node ``lo_x[4] hi_x[4] lo_y[4] hi_y[4] lo_z[4] hi_z[4]`` then int32
    bits ``ref[4] cnt[4]``; ``cnt == 0``: inner node ``ref``; ``cnt > 0``: leaf of triangles
    ``ref .. ref + cnt - 1`` (the same ``tris`` array as the binary tree); ``cnt == -1``: empty slot.
    Each level of the 4-wide tree consumes at least one level of the binary one, so its depth is at most
    the binary depth, and traversal (push up to 3 children per node) needs at most ``3 * depth`` entries.
    """

    nodes: np.ndarray
    depth: int

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)


def collapse_bvh4(bvh: BVH) -> BVH4:
    """Collapse the binary tree: each 4-wide node takes a binary node's children and twice replaces the inner
    child of largest surface area by its two children. Vectorised over one level at a time. A grouped tree's
    roots stay nodes 0 .. roots - 1."""
    b_lo = np.stack([bvh.nodes[:, 0:3], bvh.nodes[:, 6:9]], 1)      # (n, 2, 3)
    b_hi = np.stack([bvh.nodes[:, 3:6], bvh.nodes[:, 9:12]], 1)
    refs = bvh.child_refs()
    b_ref = np.stack([refs[:, 0], refs[:, 2]], 1).astype(np.int64)  # (n, 2)
    b_cnt = np.stack([refs[:, 1], refs[:, 3]], 1).astype(np.int64)
    out: list[np.ndarray] = []
    # binary inner nodes becoming 4-wide nodes, in id order: the roots first, so they keep their ids
    frontier = np.arange(bvh.roots, dtype=np.int64)
    next_id = bvh.roots
    depth = 0
    while len(frontier):
        depth += 1
        k = len(frontier)
        lo = np.zeros((k, 4, 3), np.float32)
        hi = np.zeros((k, 4, 3), np.float32)
        ref = np.zeros((k, 4), np.int64)
        cnt = np.full((k, 4), -1, np.int64)
        lo[:, :2], hi[:, :2] = b_lo[frontier], b_hi[frontier]
        ref[:, :2], cnt[:, :2] = b_ref[frontier], b_cnt[frontier]
        used = np.full(k, 2)
        ar = np.arange(k)
        for _ in range(2):
            e = np.maximum(hi.astype(np.float64) - lo, 0)
            area = e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]
            area = np.where(cnt == 0, area, -1.0)
            j = np.argmax(area, axis=1)
            ok = area[ar, j] >= 0
            rows, js = ar[ok], j[ok]
            child = ref[rows, js]
            slot2 = used[rows]
            lo[rows, slot2], hi[rows, slot2] = b_lo[child, 1], b_hi[child, 1]
            ref[rows, slot2], cnt[rows, slot2] = b_ref[child, 1], b_cnt[child, 1]
            lo[rows, js], hi[rows, js] = b_lo[child, 0], b_hi[child, 0]
            ref[rows, js], cnt[rows, js] = b_ref[child, 0], b_cnt[child, 0]
            used[rows] += 1
        inner = cnt == 0
        n_inner = int(inner.sum())
        new_ids = np.arange(next_id, next_id + n_inner)
        frontier = ref[inner]                       # binary ids, row-major order = the new ids' order
        ref[inner] = new_ids
        next_id += n_inner
        node = np.zeros((k, 32), np.float32)
        for c in range(3):
            node[:, 8 * c:8 * c + 4] = lo[:, :, c]
            node[:, 8 * c + 4:8 * c + 8] = hi[:, :, c]
        node[:, 24:28].view(np.int32)[:] = ref.astype(np.int32)
        node[:, 28:32].view(np.int32)[:] = cnt.astype(np.int32)
        out.append(node)
    nodes = np.concatenate(out)
    assert len(nodes) == next_id
    return BVH4(nodes=nodes, depth=depth)
