#!/usr/bin/env python3
"""Lane utilisation of the dense-rig score kernel (issue 17, goal 3): ray order and persistent threads.

Workload as in ``gpu_dense.py``: a population of ``--pop`` perturbed ``pyramid`` rigs of the dense LiDAR
(4 x 64 x 2048 rays each) over the default town's P-SOG on a ``--voxel`` grid, occlusion by the P-SOG's
stop mask. Times the shipped CUDA score kernel (``score_kernel_gpu``) and the variants of
``gpu_dense_variants_kernels.py`` side by side:

* ``tiled-CxA-rN``: one thread per ray, the 32 lanes of a warp on a C x A (channel x azimuth) tile
  (``tiled-1x32`` is the shipped order through the permutation: the permutation's own cost);
* ``select-CxA-rN``: the same with the branch-free step (``walk32_next_sel``: the axis to step chosen by
  selects, so lanes stepping along different axes do not serialise three branches). The lane model
  (``gpu_dense_lanes.py``) found ray lengths in the shipped order already keep some 97 % of lanes busy,
  so Nsight's 16 of 32 active lanes point at branches inside a step rather than at ray lengths;
* ``eager-1x32-rN``: that, and the brick's masks and bitset word loaded on every step (kept only on
  entering a new brick), so that only the flush on leaving a brick remains a branch;
* ``persist-stride-tCxA-wW-rN``: persistent threads (W times as many as the GPU holds at once at N
  registers and 128 threads per block), thread t walking rays t, t + T, ... in tile order;
* ``persist-atomic-tCxA-cK-wW-rN``: the same, a lane whose ray has ended taking K ray numbers at a time
  from a global atomic counter;
* ``...-bB-...``: a lane whose ray has ended waits until B lanes of its warp are done, and they set up
  their new rays together (a warp vote; Aila & Laine's dynamic fetch), instead of each stalling the warp
  for its own float64 set-up.

* third round (``gpu_dense_lean_kernels.py``; every one at a register cap ``-rN``): ``lean`` (the eager
  kernel with the brick word kept incrementally in int32, raw-address loads, an unsigned grid test, the
  flush on the raw address), ``lean32`` (the same with the word recomputed in int32 each step), ``skip``
  (the eager kernel jumping full bricks without stop bits), ``lean-skip`` / ``lean32-skip``, ``lean32-skipu``
  (jump and step in one branch-free body), ``lean32-keep`` / ``lean32-keep-skip`` (the brick's masks kept
  from its entry, so that their load is predicated on entry), ``lean-ahead``
  / ``lean32-ahead`` (the next voxel's loads issued right after the step), and ``walk-only``, a floor
  diagnostic (today's step and stop read only; wrong sums on purpose: it is left out of the equality
  checks and labelled in the JSON). ``--skip-stats`` adds counting builds' steps and jumps.

* fourth round (``gpu_dense_round4_kernels.py``, each at ``-r48``, ``-r56``, ``-r64``): ``lean32x`` (the shipped
  kernel on a walk state without the alive, exact and t1d fields), ``lean32xm`` (that, with the step test by
  minimum and median of the three crossings: fewer instructions, the same decisions) and ``lean32xr``
  (lean32x whose float64 step reloads the ray instead of keeping o and d live).

* seventh round (``gpu_dense_round7_kernels.py``, each at ``-r56`` and ``-r64``): the shipped kernel without the
  grid test at its loop's head (``head1``: one compare of i against DEAD; ``headless``: none, a dead walk caught
  after the float64 step; ``headless-guard``: that with the iteration bound kept), ``early`` (the next
  voxel's step taken while the current voxel's loads are in flight), ``prefetch`` / ``prefetch-l2`` (a
  prefetch hint for the brick ahead on entering a brick) and ``nosum`` / ``nosum-head1`` (no running sum in
  the loop).

* eighth round (``gpu_dense_near_kernels.py``): ``near-hN``, the near field: the voxels of a box of half-width N
  voxels around each LiDAR (free of stop bits) marked one thread per voxel, and every ray's walk started on its
  first voxel after the box (``dense_near_parts.py`` times its launches one by one).

* ninth and tenth rounds (``gpu_dense_round9_kernels.py``): the bitset's layout. ``b64-<B>-rN`` 64-voxel bricks in
  64-bit words (``-late``: the nonzero-weight word read at the flush); ``b32-<B>-<order>[-head1|-free][-nosum]
  [-b64|-b256]-rN`` 32-voxel bricks of shape B numbered in ``order`` (slowest axis first; ``4x4x2-xyz`` is the
  round-eight kernel), with the loop headed by ``i >= 0`` and the step bound (``head1``) or without the bound
  (``free``), without the running sum, at other block sizes; ``swz-<abc>-<order>-rN`` 4 x 4 x 2 bricks in
  super-blocks of 2^a x 2^b x 2^c bricks. The shipped kernel is ``b32-8x4x1-zxy-free-r56``, the harness's
  ``shipped`` launch runs it on its own inputs (``bricks.flat_brick_masks``).

Each kernel's register use and spills for sm_90 come from ``--registers`` (offline, ptxas; no GPU; with
``cuobjdump`` on PATH also the common step's instruction count, and with ``--listing`` its SASS).

Each variant's sums and counts (covered voxels, counted from the bitset with the shipped
``count_bits_kernel``, which is timed with every kernel; zeroing the outputs is not) must equal the shipped kernel's on every
repeat (diagnostics excepted); a mismatch stops the run. Timing: one warm-up launch each (compiles), then ``--repeat`` rounds,
each launching every variant once (interleaved, so clock and thermal drift fall on all alike); median and
range of the launch time per rig. Writes ``<--out>/gpu-dense-variants-<voxel>m.json``.

    python3 bench/gpu_dense_variants.py --out $OUT                                  # CUDA, the goal workload
    python3 bench/gpu_dense_variants.py --device cpu --voxel 0.4 --pop 2 --azimuths 256 --repeat 1  # smoke
    python3 bench/gpu_dense_variants.py --out $OUT --only eager-1x32-r72,lean32-r72,lean32-skip-r72 --skip-stats
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

import place3d_kernels as p3k
from place3d_kernels.backends.base import rotation_matrices, sensor_directions
from place3d_kernels.backends.bricks import brick_masks, brick_shape, flat_brick_masks, flat_shape
from place3d_app.kernel_bench import machine_info

# the kernels module beside this file (a script's own folder is on the path; an importing test's is not)
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parent))
import gpu_dense_near_kernels  # noqa: E402
import sass_hot_path  # noqa: E402
from gpu_dense_lean_kernels import make_eager_skip, make_lean, make_walk_only  # noqa: E402
from gpu_dense_round7_kernels import make_headless  # noqa: E402
import gpu_dense_round9_kernels as r9  # noqa: E402
from gpu_dense_round4_kernels import make_lean32x  # noqa: E402
from gpu_dense_variants_kernels import make_persistent, make_tiled  # noqa: E402

BLOCK_DIM = 128          # the shipped kernel's (SCORE_BLOCK_DIM); every variant launches with it
REGS_PER_SM = 65536      # H100 (and every CUDA GPU since Volta): 64 K 32-bit registers per SM
MAX_THREADS_PER_SM = 2048


def resident_threads(sm_count: int, maxreg: int | None, block_dim: int = BLOCK_DIM) -> int:
    """Threads the GPU runs at once for a kernel capped at ``maxreg`` registers (uncapped: taken as 128),
    from the register file alone (registers are allocated per warp in units of 256: 8 per thread)."""
    regs = -(-(maxreg or 128) // 8) * 8
    warps_per_block = block_dim // 32
    blocks = min(32, REGS_PER_SM // (regs * 32 * warps_per_block), MAX_THREADS_PER_SM // block_dim)
    return sm_count * max(blocks, 1) * block_dim


class Workload:
    """The score kernel's inputs for a population ``pop`` (P, L, 6) of ``lidar`` rigs over ``psog``, on a
    Warp ``device``, and the launches of the shipped kernel and of the variants on them."""

    def __init__(self, psog, lidar, pop, device: str):
        self.device = device
        self.backend = p3k.get_backend(f"warp:{device}")
        pop = np.asarray(pop, dtype=np.float64)
        self.P, self.L = pop.shape[:2]
        flat = pop.reshape(-1, 6)
        self.n_el, self.n_az = len(lidar.elevations), len(lidar.azimuths)
        spec = psog.grid.spec
        nx, ny, nz = spec.shape
        bx, by, bz = brick_shape(spec.shape)
        self.words = bx * by * bz
        masks = brick_masks(spec.shape, np.asarray(psog.weights).reshape(-1) != 0,
                            np.asarray(psog.stop_mask).reshape(-1) != 0)
        sd = sensor_directions(lidar.elevations, lidar.azimuths)
        self.n_rays = self.P * self.L * len(sd)
        # as WarpBackend.score_placements launches score_kernel_gpu (place3d_kernels/backends/warp/host.py)
        self.inputs = [
            wp.array(sd, dtype=wp.vec3d, device=device),
            wp.array(rotation_matrices(flat), dtype=wp.mat33d, device=device),
            wp.array(psog.grid.to_local(flat[:, :3]), dtype=wp.vec3d, device=device),
            int(self.L), float(lidar.max_range), float(spec.voxel_size), int(nx), int(ny), int(nz), int(by), int(bz),
            wp.array(masks.view(np.uint64), dtype=wp.uint64, device=device),
            wp.array(np.asarray(psog.weights).reshape(-1).astype(np.int64), dtype=wp.int64, device=device),
            int(self.words)]
        self.shape, self.bricks = spec.shape, (bx, by, bz)
        self.psog = psog
        # the shipped kernel's own inputs: flat 8 x 4 x 1 bricks (bricks.flat_brick_masks) and their bitset
        fx, fy, fz = flat_shape(spec.shape)
        self.flat_words = fx * fy * fz
        self.flat = (fx, fy, wp.array(flat_brick_masks(spec.shape, np.asarray(psog.weights).reshape(-1) != 0,
                                                       np.asarray(psog.stop_mask).reshape(-1) != 0),
                                      dtype=wp.uint64, device=device),
                     wp.zeros(self.P * self.flat_words, dtype=wp.uint32, device=device))
        self.b64 = {}            # ninth round: per brick layout (masks, bits, bny, bnz, words)
        self.b32 = {}            # ninth round: per (layout, order, swz) (masks, (n1, n2), words, bits)
        table = gpu_dense_near_kernels.lattice(lidar.elevations, lidar.azimuths)
        self.near_table = None if table is None else (wp.array(table[0], dtype=wp.float32, device=device),
                                                      wp.array(table[1], dtype=wp.int32, device=device), table[2])
        self.bits = wp.zeros(self.P * self.words, dtype=wp.uint32, device=device)
        self.sums = wp.zeros(self.P, dtype=wp.int64, device=device)
        self.counts = wp.zeros(self.P, dtype=wp.int64, device=device)
        self.counter = wp.zeros(1, dtype=wp.int32, device=device)
        self.stats = wp.zeros(4, dtype=wp.int64, device=device)      # the lean kernels' counters (count builds)

    def check_tile(self, tile_c: int) -> None:
        if 32 % tile_c or self.n_el % tile_c or self.n_az % (32 // tile_c):
            raise ValueError(f"tile {tile_c} x {32 // max(tile_c, 1)} (channel x azimuth) does not tile the "
                             f"{self.n_el} x {self.n_az} LiDAR; pick tile_c in 1, 2, 4, 8, 16, 32 dividing the "
                             f"channel count, with 32 / tile_c dividing the azimuth count")

    @staticmethod
    def shipped_kernel():
        """The shipped CUDA score kernel (``score_kernel_gpu``)."""
        return p3k.get_backend("warp:cpu").score_gpu.score_kernel_gpu

    def reset(self) -> None:
        """Zero the bitsets, sums, counts and the ray counter (outside the timed region)."""
        self.bits.zero_(), self.sums.zero_(), self.counts.zero_(), self.counter.zero_(), self.stats.zero_()
        self.flat[3].zero_()
        for b in self.b64.values():
            b[1].zero_()
        for b in self.b32.values():
            b[3].zero_()

    def bricks32(self, layout, order, swz) -> tuple:
        """The ninth round's inputs for 32-voxel bricks of 2^``layout`` voxels numbered in ``order`` in
        super-blocks of 2^``swz`` bricks: masks, (n1, n2), words per candidate, a zeroed bitset."""
        key = (tuple(layout), order, tuple(swz))
        if key not in self.b32:
            spec = self.psog.grid.spec
            masks = r9.brick_masks32(spec.shape, layout, order, np.asarray(self.psog.weights).reshape(-1) != 0,
                                     np.asarray(self.psog.stop_mask).reshape(-1) != 0, swz)
            self.b32[key] = (wp.array(masks, dtype=wp.uint64, device=self.device),
                             r9.order_counts(spec.shape, layout, order, swz), len(masks),
                             wp.zeros(self.P * len(masks), dtype=wp.uint32, device=self.device))
        return self.b32[key]

    def bricks64(self, layout) -> tuple:
        """The ninth round's inputs for 64-voxel bricks of 2^``layout`` voxels: masks (pairs per brick), a
        zeroed uint64 bitset per candidate, bricks along y and z, words per candidate."""
        layout = tuple(layout)
        if layout not in self.b64:
            spec = self.psog.grid.spec
            bx, by, bz = r9.brick_shape64(spec.shape, layout)
            masks = r9.brick_masks64(spec.shape, layout, np.asarray(self.psog.weights).reshape(-1) != 0,
                                     np.asarray(self.psog.stop_mask).reshape(-1) != 0)
            words = bx * by * bz
            self.b64[layout] = (wp.array(masks, dtype=wp.uint64, device=self.device),
                                wp.zeros(self.P * words, dtype=wp.uint64, device=self.device), by, bz, words)
        return self.b64[layout]

    def launch(self, v: dict) -> None:
        """Launch variant ``v`` (a dict from ``variants``) on zeroed outputs and count the covered voxels
        (the shipped ``count_bits_kernel``, part of every variant's time, as in gpu_score_variants.py)."""
        io = self.inputs + [self.bits, self.sums]
        bits, words = self.bits, self.words
        if v["kind"] == "b32":
            masks, (n1, n2), words, bits = self.bricks32(v["layout"], v["order"], v.get("swz", (0, 0, 0)))
            io = self.inputs[:9] + [n1, n2, masks, self.inputs[12], words, bits, self.sums, self.stats]
            wp.launch(v["kernel"], dim=self.n_rays, device=self.device, inputs=io,
                      block_dim=v.get("block_dim", BLOCK_DIM))
        elif v["kind"] == "b64":
            masks, bits64, by, bz, words64 = self.bricks64(v["layout"])
            io = self.inputs[:9] + [by, bz, masks, self.inputs[12], words64, bits64, self.sums, self.stats]
            wp.launch(v["kernel"], dim=self.n_rays, device=self.device, inputs=io, block_dim=BLOCK_DIM)
            # the same count kernel on the same bytes, as 32-bit words
            bits, words = wp.array(ptr=bits64.ptr, dtype=wp.uint32, shape=(2 * bits64.shape[0],),
                                   device=self.device), 2 * words64
        elif v["kind"] == "shipped":
            fx, fy, masks, bits = self.flat
            words = self.flat_words
            wp.launch(self.backend.score_gpu.score_kernel_gpu, dim=self.n_rays, device=self.device,
                      inputs=self.inputs[:9] + [fx, fy, masks, self.inputs[12], words, bits, self.sums],
                      block_dim=BLOCK_DIM)
        elif v["kind"] == "near":
            # the near field (gpu_dense_near_kernels.py) with boxes of half-width near_h / near_hz, then the
            # walks from them
            nf = gpu_dense_near_kernels
            near = nf.launch(self.device, self.near_table, self.inputs[0], self.inputs[1], self.inputs[2], self.L,
                             self.inputs[4], self.inputs[5], self.shape, self.bricks, self.inputs[11],
                             self.inputs[12], self.words, self.bits, self.sums, v["near_h"], v["near_hz"])
            wp.launch(nf.score_kernel_near, dim=self.n_rays, device=self.device,
                      inputs=io + [near, v["near_h"], v["near_hz"]], block_dim=BLOCK_DIM)
        elif v["kind"] == "lean":
            if self.words >= 2 ** 31:
                raise ValueError(f"{self.words} bitset words per candidate: the lean kernels keep a brick's word "
                                 f"in int32; use a coarser voxel (or fewer voxels) so that they fit")
            wp.launch(v["kernel"], dim=self.n_rays, device=self.device, inputs=io + [self.stats],
                      block_dim=BLOCK_DIM)
        elif v["kind"] == "tiled":
            wp.launch(v["kernel"], dim=self.n_rays, device=self.device, inputs=io + [self.n_az],
                      block_dim=BLOCK_DIM)
        else:
            wp.launch(v["kernel"], dim=v["threads"], device=self.device,
                      inputs=io + [self.n_az, self.n_rays, v["threads"], self.counter], block_dim=BLOCK_DIM)
        chunks = -(-words // self.backend.k.COUNT_WORDS)
        wp.launch(self.backend.k.count_bits_kernel, dim=self.P * chunks, device=self.device,
                  inputs=[bits, int(words), int(chunks), int(self.backend.k.COUNT_WORDS), self.counts])

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        return self.sums.numpy().copy(), self.counts.numpy().copy()


def variants(sm_count: int, cpu_threads: int | None = None) -> dict:
    """The study's variants by name (parameters only; ``build`` makes the kernels). ``cpu_threads``: the
    persistent launch size where there are no SMs (the CPU smoke test and tests)."""
    out = {"shipped": {"kind": "shipped"}}
    for tile_c in (1, 4, 8):
        out[f"tiled-{tile_c}x{32 // tile_c}-r80"] = {"kind": "tiled", "tile_c": tile_c, "maxreg": 80,
                                                     "select": False, "eager": False}
    for tile_c, maxreg in ((1, 72), (1, 80), (1, 96)):
        out[f"select-{tile_c}x{32 // tile_c}-r{maxreg}"] = {"kind": "tiled", "tile_c": tile_c, "maxreg": maxreg,
                                                            "select": True, "eager": False}
    for maxreg in (56, 64, 72, 80, 96):
        out[f"eager-1x32-r{maxreg}"] = {"kind": "tiled", "tile_c": 1, "maxreg": maxreg, "select": True,
                                        "eager": True}

    def persist(mode, tile_c, maxreg, chunk=1, waves=1, reload=False, batch=1, select=False):
        threads = cpu_threads or waves * resident_threads(sm_count, maxreg)
        name = (f"persist-{'stride' if mode == 0 else 'atomic'}-t{tile_c}x{32 // tile_c}"
                + (f"-c{chunk}" if mode else "") + ("-reload" if reload else "") + (f"-b{batch}" if batch > 1 else "")
                + ("-select" if select else "")
                + f"-w{waves}-r{maxreg or 'none'}")
        out[name] = {"kind": "persistent", "mode": mode, "tile_c": tile_c, "chunk": chunk, "reload": reload,
                     "batch": batch, "select": select, "waves": waves, "threads": int(threads), "maxreg": maxreg}

    persist(0, 1, 80)
    persist(1, 1, 80)
    persist(1, 4, 80)
    persist(1, 4, 80, chunk=4)
    persist(1, 4, 80, batch=8)
    persist(1, 4, 80, batch=16)
    persist(1, 1, 80, batch=16, select=True)
    # third round (gpu_dense_lean_kernels.py): lean address arithmetic (lean: the brick word kept
    # incrementally; lean32: recomputed in int32), full bricks skipped, loads one step ahead, and the
    # walk-only floor with today's step
    for body, skip, ahead, caps in (("lean", False, False, (64, 72, 80)), ("lean32", False, False, (48, 56, 64, 72, 80)),
                                    ("eager", True, False, (72, 80)), ("lean", True, False, (72, 80)),
                                    ("lean32", True, False, (72, 80)), ("lean", False, True, (72, 80)),
                                    ("lean32", False, True, (72, 80)), ("lean32", "unified", False, (72, 80)),
                                    ("lean32-keep", False, False, (56, 64, 72, 80)), ("lean32-keep", True, False, (72, 80))):
        for maxreg in caps:
            name = (body if body != "eager" else "") + ("-skipu" if skip == "unified" else "-skip" if skip else "") \
                + ("-ahead" if ahead else "")
            out[f"{name.lstrip('-')}-r{maxreg}"] = {"kind": "lean", "body": body, "skip": skip, "ahead": ahead,
                                                    "maxreg": maxreg}
    # fourth round (gpu_dense_round4_kernels.py): the shipped kernel on a smaller walk state (no alive,
    # exact or t1d fields); -reload: the float64 step reloads the ray instead of keeping o and d live
    for body in ("lean32x", "lean32xr", "lean32xm"):
        for maxreg in (48, 56, 64):
            out[f"{body}-r{maxreg}"] = {"kind": "lean", "body": body, "skip": False, "ahead": False, "maxreg": maxreg}
    # fifth round: the bitset snapshot loaded on a brick's entry and used only at its flush ("lazy"), so a
    # step never waits for it (the old filter, applied at the flush instead of each step: the same bits)
    for body in ("lean32-lazy", "lean32-lazy-keep", "lean32-pred"):
        for maxreg in (56, 64, 72):
            out[f"{body}-r{maxreg}"] = {"kind": "lean", "body": body, "skip": False, "ahead": False,
                                        "maxreg": maxreg}
    # seventh round (gpu_dense_round7_kernels.py): the shipped kernel without the grid test at its loop's head
    for mode in ("head1", "headless", "headless-guard", "early", "prefetch", "prefetch-l2", "nosum", "nosum-head1"):
        for maxreg in (56, 64):
            out[f"{mode}-r{maxreg}"] = {"kind": "lean", "body": mode, "skip": False, "ahead": False, "maxreg": maxreg}
    # eighth round (gpu_dense_near_kernels.py): voxels near each LiDAR marked per voxel, the walks starting
    # after each LiDAR's near box (half-widths in voxels, x and y / z)
    for h in (16, 32, 48, 64):
        out[f"near-h{h}"] = {"kind": "near", "near_h": h, "near_hz": 64}
    # ninth round (gpu_dense_round9_kernels.py): 64-voxel bricks in 64-bit words; -late: the nonzero-weight
    # word read at the flush only
    for layout in r9.LAYOUTS:
        for late in (False, True):
            for maxreg in (64, 72, 80):
                out[f"b64-{r9.layout_name(*layout)}{'-late' if late else ''}-r{maxreg}"] = {
                    "kind": "b64", "layout": layout, "late": late, "maxreg": maxreg}
    for layout, order in r9.LAYOUTS32:
        for maxreg in (56, 64):
            out[f"b32-{r9.layout_name(*layout)}-{order}-r{maxreg}"] = {"kind": "b32", "layout": layout,
                                                                       "order": order, "maxreg": maxreg}
    for layout, order in (((3, 2, 0), "zxy"), ((2, 3, 0), "zyx"), ((4, 1, 0), "zxy"), ((1, 4, 0), "zyx"),
                          ((3, 2, 0), "xzy"), ((5, 0, 0), "zxy"), ((2, 2, 1), "xyz")):
        for extra, opts in (("-head1", {"head1": True}), ("-free", {"head1": "free"}), ("-b64", {"block_dim": 64}),
                            ("-b256", {"block_dim": 256})):
            for maxreg in (56, 64):
                out[f"b32-{r9.layout_name(*layout)}-{order}{extra}-r{maxreg}"] = {
                    "kind": "b32", "layout": layout, "order": order, "maxreg": maxreg, **opts}
        for maxreg in (48, 52, 60):
            out[f"b32-{r9.layout_name(*layout)}-{order}-r{maxreg}"] = {"kind": "b32", "layout": layout, "order": order,
                                                                       "maxreg": maxreg}
    # the shipped form (flat 8 x 4 x 1 bricks, no loop bound) at other caps, without its running sum, other shapes
    for layout, order in (((3, 2, 0), "zxy"), ((4, 1, 0), "zxy"), ((2, 3, 0), "zyx")):
        for nosum in (False, True):
            for maxreg in (48, 52, 56):
                name = f"b32-{r9.layout_name(*layout)}-{order}-free{'-nosum' if nosum else ''}-r{maxreg}"
                out.setdefault(name, {"kind": "b32", "layout": layout, "order": order, "maxreg": maxreg,
                                      "head1": "free", "nosum": nosum})
    for swz, order in r9.SWIZZLES:
        for maxreg in (56, 64):
            out[f"swz-{''.join(map(str, swz))}-{order}-r{maxreg}"] = {"kind": "b32", "layout": (2, 2, 1),
                                                                      "order": order, "swz": swz, "maxreg": maxreg}
    out["walk-only"] = {"kind": "lean", "body": "walk", "skip": False, "ahead": False, "maxreg": 72,
                        "diagnostic": "floor: today's step (walk32_next_sel) and stop read only, no bitset, no "
                                      "weights; sums are step counts (wrong on purpose, not compared)"}
    out["walk-only-lean32"] = {"kind": "lean", "body": "walk-lean32", "skip": False, "ahead": False, "maxreg": 72,
                               "diagnostic": "floor of lean32: its step (unsigned grid test), int32 word and raw "
                                             "mask load only; sums are step counts (wrong on purpose)"}
    return out


PARAMS = ("tile_c", "mode", "chunk", "reload", "batch", "select", "eager", "maxreg", "body", "skip", "ahead",
          "layout", "late", "order", "swz", "head1", "block_dim", "nosum")


def build(vs: dict) -> None:
    """Attach each variant's kernel (one module per kernel and parameter set)."""
    made = {}
    for v in vs.values():
        if v["kind"] in ("shipped", "near"):
            continue
        key = (v["kind"],) + tuple(v.get(k) for k in PARAMS)
        if key not in made:
            if v["kind"] == "lean":
                made[key] = make_lean_kind(v)
            elif v["kind"] == "b32":
                made[key] = r9.make_b32(v["layout"], v["order"], v["maxreg"], v.get("swz", (0, 0, 0)),
                                        v.get("head1", False), v.get("block_dim", BLOCK_DIM), v.get("nosum", False))
            elif v["kind"] == "b64":
                made[key] = r9.make_b64(v["layout"], v["maxreg"], v["late"])
            elif v["kind"] == "tiled":
                made[key] = make_tiled(v["maxreg"], v["tile_c"], v["select"], v["eager"])
            else:
                made[key] = make_persistent(v["maxreg"], v["mode"], v["tile_c"], v["chunk"], v["reload"], v["batch"],
                                            v["select"])
        v["kernel"] = made[key]


def make_lean_kind(v: dict, count: bool = False):
    """The kernel of a variant of kind ``lean`` (``count``: the build that fills ``Workload.stats``)."""
    if v["body"] in ("walk", "walk-lean32"):
        return make_walk_only(v["maxreg"], count, lean=v["body"] == "walk-lean32")
    if v["body"] in ("lean32x", "lean32xr", "lean32xm"):
        return make_lean32x(v["maxreg"], reload=v["body"] == "lean32xr", med=v["body"] == "lean32xm")
    if v["body"] in ("head1", "headless", "headless-guard", "early", "prefetch", "prefetch-l2", "nosum", "nosum-head1"):
        return make_headless(v["maxreg"], v["body"])
    if v["body"] == "eager":
        return make_eager_skip(v["maxreg"], count)
    return make_lean(v["maxreg"], v["skip"], v["ahead"], count, inc=v["body"] == "lean",
                     keep=v["body"] in ("lean32-keep", "lean32-lazy-keep"), lazy=v["body"].startswith("lean32-lazy"),
                     pred=v["body"] == "lean32-pred")


def skip_stats(wl: Workload, ref: tuple) -> dict:
    """Counting builds of ``lean-r72``, ``skip-r72`` and ``lean-skip-r72`` (and ``walk-only``), one launch
    each on zeroed outputs: loop iterations, jumps, and the fraction of the lean kernel's steps the skip
    saves (on the CPU rays run in order; on the GPU the fraction depends on which rays run first). Sums
    and counts of the exact ones are checked against ``ref``."""
    vs = {k: v for k, v in variants(0, 1).items()
          if k in ("lean-r72", "skip-r72", "lean-skip-r72", "lean32-skip-r72", "lean32-skipu-r72", "walk-only")}
    out = {}
    for name, v in vs.items():
        wl.reset()
        wl.launch(dict(v, kernel=make_lean_kind(v, count=True)))
        got = wl.result()
        if "diagnostic" not in v and not (np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])):
            raise SystemExit(f"variant {name} (count build): sums/counts differ from the shipped kernel's")
        st = [int(x) for x in wl.stats.numpy()]
        out[name] = {"steps": st[0], "jumps": st[1], "jump_crossings": st[2], "full_brick_single_steps": st[3]}
    for name in ("skip-r72", "lean-skip-r72", "lean32-skip-r72", "lean32-skipu-r72"):
        out[name]["steps_saved_vs_lean"] = 1.0 - out[name]["steps"] / out["lean-r72"]["steps"]
    for name, r in out.items():
        print(f"{name:16s} {r}", flush=True)
    return out


def register_report(vs: dict, arch: int = 90, listing: bool = False) -> dict:
    """Registers and spills per variant, without a GPU: Warp compiles each kernel's module to PTX with
    NVRTC and ``ptxas -v`` (CUDA toolkit on PATH) assembles it for ``sm_<arch>``. Where this ptxas is older
    than the PTX NVRTC wrote, the ``.version`` line is lowered to what ptxas names and the assembly
    retried (the kernels use no newer instruction; ptxas would refuse one). Where ``cuobjdump`` is on
    PATH, also the instructions of the inner loop's common step (``sass_hot_path.py``; ``listing``: the
    instructions themselves too, in the JSON only)."""
    if shutil.which("ptxas") is None:
        raise SystemExit("--registers needs ptxas (the CUDA toolkit) on PATH")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, v in vs.items():
            kern = (Workload.shipped_kernel() if v["kind"] == "shipped"
                    else gpu_dense_near_kernels.score_kernel_near if v["kind"] == "near" else v["kernel"])
            [ptx] = wp.compile_aot_module(kern.module, device=None, arch=arch, module_dir=f"{tmp}/{name}",
                                          use_ptx=True)
            text = Path(ptx).read_bytes().replace(b"\0", b"").decode()
            src = Path(tmp, name, "k.ptx")
            for _ in range(2):
                src.write_text(text)
                r = subprocess.run(["ptxas", f"-arch=sm_{arch}", "-v", str(src), "-o", f"{tmp}/{name}/k.cubin"],
                                   capture_output=True, text=True)
                low = re.search(r"Unsupported \.version \S+; current version is '([\d.]+)'", r.stderr)
                if not low:
                    break
                text = re.sub(r"^\.version \S+", f".version {low.group(1)}", text, flags=re.M)
            regs = re.search(r"Used (\d+) registers", r.stderr)
            spill = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", r.stderr)
            if r.returncode or not regs:
                raise SystemExit(f"{name}: ptxas failed: {r.stderr[-400:]}")
            out[name] = {"registers": int(regs.group(1)), "spill_store_bytes": int(spill.group(1)) if spill else 0,
                         "spill_load_bytes": int(spill.group(2)) if spill else 0}
            if sass_hot_path.available():
                out[name].update(sass_hot_path.common_step(sass_hot_path.sass(f"{tmp}/{name}/k.cubin"), listing))
            print(f"{name:34s} {({k: x for k, x in out[name].items() if k != 'common_step_listing'})}", flush=True)
    return out


def dense_population(pop_size: int, seed: int = 0) -> np.ndarray:
    """``gpu_dense.py``'s population: ``pyramid`` with positions jittered by up to 0.3 m (0.1 m steps)."""
    rig = p3k.Placement.load("pyramid")
    rng = np.random.default_rng(seed)
    pop = np.repeat(rig.poses[None], pop_size, axis=0)
    pop[..., :3] += rng.uniform(-0.3, 0.3, pop[..., :3].shape).round(1)
    return pop


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--pop", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--azimuths", type=int, default=2048)
    ap.add_argument("--max-range", type=float, default=100.0, help="as gpu_dense.py (default 100 m)")
    ap.add_argument("--cpu-threads", type=int, default=509, help="persistent launch size on the CPU")
    ap.add_argument("--only", default="", help="comma-separated variant names (shipped always runs)")
    ap.add_argument("--skip-stats", action="store_true",
                    help="also run counting builds of lean/skip once and report steps, jumps and steps saved")
    ap.add_argument("--registers", action="store_true",
                    help="no timing: registers and spills per variant from ptxas for sm_90 (no GPU needed)")
    ap.add_argument("--listing", action="store_true",
                    help="with --registers: also each kernel's common-step SASS in the JSON")
    ap.add_argument("--out", default=os.environ.get("OUT", str(Path(__file__).resolve().parent / "results")))
    args = ap.parse_args()
    dev = args.device
    wp.init()
    sm = wp.get_device(dev).sm_count if dev.startswith("cuda") and not args.registers else 0
    vs = variants(sm, None if sm else args.cpu_threads)
    only = [x for x in args.only.split(",") if x]
    if only:
        unknown = set(only) - set(vs)
        if unknown:
            raise SystemExit(f"--only: unknown variants {sorted(unknown)}; known: {sorted(vs)}")
        vs = {k: v for k, v in vs.items() if k in only or k == "shipped"}
    if args.registers:
        build(vs)
        report = register_report(vs, listing=args.listing)
        res = Path(args.out)
        res.mkdir(parents=True, exist_ok=True)
        (res / "gpu-dense-variants-registers-sm90.json").write_text(json.dumps(
            {"info": machine_info(), "arch": "sm_90", "block_dim": BLOCK_DIM, "variants": report}, indent=2))
        return
    d0 = p3k.DEFAULT_GRID
    grid = p3k.Grid(d0.lower, d0.upper, args.voxel)
    t = time.perf_counter()
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend=f"warp:{dev}")
    psog_s = time.perf_counter() - t
    lidar = p3k.LidarModel.uniform(64, (-25, 15), args.azimuths, max_range=args.max_range, name="dense")
    wl = Workload(psog, lidar, dense_population(args.pop), dev)
    for v in vs.values():
        if "tile_c" in v:
            wl.check_tile(v["tile_c"])
    t = time.perf_counter()
    build(vs)
    ref = None
    for name, v in vs.items():          # warm-up: compiles each module once, checks exactness
        wl.reset()
        wl.launch(v)
        got = wl.result()
        ref = ref or got
        if "diagnostic" not in v and not (np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])):
            raise SystemExit(f"variant {name}: sums/counts differ from the shipped kernel's")
    compile_s = time.perf_counter() - t
    times = {k: [] for k in vs}
    for _ in range(args.repeat):
        for name, v in vs.items():
            wl.reset()
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            wl.launch(v)
            wp.synchronize_device(dev)
            times[name].append(time.perf_counter() - t0)
            got = wl.result()
            if "diagnostic" not in v and not (np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])):
                raise SystemExit(f"variant {name}: sums/counts differ from the shipped kernel's on a repeat")
    P = wl.P
    out = {"info": machine_info(), "device": dev, "device_name": str(wp.get_device(dev).name), "sm_count": sm,
           "grid": grid.to_dict(), "lidar": f"uniform(64, (-25, 15), {args.azimuths}, max_range={args.max_range})",
           "rays_per_rig": wl.n_rays // P, "population": P, "repeat": args.repeat, "psog_build_s": psog_s,
           "warmup_and_compile_s": compile_s, "sums": ref[0].tolist(), "covered_voxels": ref[1].tolist(),
           "all_identical_to_shipped": True,
           "diagnostics_not_compared": sorted(k for k, v in vs.items() if "diagnostic" in v), "variants": {}}
    base = statistics.median(times["shipped"])
    for name, v in vs.items():
        ts = times[name]
        out["variants"][name] = {
            **{k: v[k] for k in PARAMS + ("waves", "threads", "diagnostic") if k in v},
            "median_ms_per_rig": 1e3 * statistics.median(ts) / P, "min_ms_per_rig": 1e3 * min(ts) / P,
            "max_ms_per_rig": 1e3 * max(ts) / P, "speedup_vs_shipped": base / statistics.median(ts)}
        r = out["variants"][name]
        print(f"{name:34s} {r['median_ms_per_rig']:8.3f} ms/rig  [{r['min_ms_per_rig']:.3f}, "
              f"{r['max_ms_per_rig']:.3f}]  x{r['speedup_vs_shipped']:.3f}"
              + ("  (diagnostic)" if "diagnostic" in v else ""), flush=True)
    if args.skip_stats:
        out["skip_stats"] = skip_stats(wl, ref)
    res = Path(args.out)
    res.mkdir(parents=True, exist_ok=True)
    path = res / f"gpu-dense-variants-{args.voxel}m.json"
    path.write_text(json.dumps(out, indent=2))
    print("wrote", path)


if __name__ == "__main__":
    main()
