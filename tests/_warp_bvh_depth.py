"""A Warp mesh's BVH depth and Warp's stack cap, read from Warp's native structures (tests only; imported
where Warp is installed)."""

from __future__ import annotations

import warp as wp


@wp.func_native("return wp::mesh_get(mesh).bvh.max_depth;")
def _depth(mesh: wp.uint64) -> int: ...


@wp.func_native("return BVH_QUERY_STACK_SIZE;")
def _cap() -> int: ...


@wp.kernel(enable_backward=False)
def _depth_kernel(mesh: wp.uint64, out: wp.array(dtype=int)):
    out[0] = _depth(mesh)
    out[1] = _cap()


def depth_and_cap(mesh_id: int, device: str = "cpu") -> tuple[int, int]:
    """(the tree's max_depth, BVH_QUERY_STACK_SIZE) of the Warp mesh ``mesh_id`` on ``device``."""
    out = wp.zeros(2, dtype=int, device=device)
    wp.launch(_depth_kernel, dim=1, inputs=[mesh_id, out], device=device)
    depth, cap = out.numpy()
    return int(depth), int(cap)
