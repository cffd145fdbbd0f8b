"""Cold load of the Warp CUDA modules: compiled on the host (NVRTC) against the shipped AOT binaries.

    for mode in jit ptx75 ptx90 cubin90; do
      d=$(mktemp -d); WARP_CACHE_PATH=$d/warp CUDA_CACHE_PATH=$d/cuda python3 bench/bench_aot_load.py $mode
    done

Run each mode in a fresh process with empty Warp kernel and CUDA driver caches (as above), which is what
a cold host has. ``jit`` lets Warp compile ``kernels.py`` and the score kernel's module; ``ptx75`` /
``ptx90`` load the shipped PTX (``backends/warp/aot.py``; ptx90 must be built first with
``wp.compile_aot_module(..., arch=90, use_ptx=True)`` into the same folder, it is not shipped), which the
driver compiles for the device; ``cubin90`` loads the shipped sm_90 CUBIN. Prints one line: the import
time, the load time of both modules, the first use (one ``score_placements`` and one ``raycast``), and a
digest of those results, which must be the same in every mode. Needs a CUDA device.
"""

from __future__ import annotations

import hashlib
import sys
import time


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    mode = argv[0] if argv else "cubin90"
    if mode not in ("jit", "ptx75", "ptx90", "cubin90"):
        raise SystemExit(f"mode must be jit, ptx75, ptx90 or cubin90, got {mode!r}")
    t0 = time.perf_counter()
    import numpy as np
    import warp as wp

    wp.init()
    from place3d_kernels.backends.warp import aot

    t1 = time.perf_counter()
    for m in aot.modules():
        if mode == "jit":
            wp.load_module(m, device="cuda:0")
        else:
            arch = 75 if mode == "ptx75" else 90
            wp.load_aot_module(m, device="cuda:0", arch=arch, module_dir=str(aot.folder()),
                               use_ptx=mode.startswith("ptx"))
    t2 = time.perf_counter()
    import os

    os.environ["PLACE3D_WARP_AOT"] = "0"          # the modules are loaded: the backend must not load again
    import place3d_kernels as p3k
    from place3d_kernels.backends.base import GridSpec

    b = p3k.get_backend("warp:cuda:0")
    rng = np.random.default_rng(3)
    spec = GridSpec(0.25, (41, 38, 11))
    el, az = np.deg2rad(np.linspace(-20, 2, 5)), np.linspace(0, 2 * np.pi, 50, endpoint=False)
    poses = rng.uniform([1, 1, 0.5, 0, 0, -3], [9, 9, 2, 0, 0, 3], (9, 2, 6))
    w = rng.integers(0, 2**40, spec.n_voxels)
    w[rng.uniform(size=spec.n_voxels) < 0.7] = 0
    stop = (rng.uniform(size=spec.n_voxels) < 0.01).astype(np.uint8)
    s, c = b.score_placements(b.prepare_grid(spec, w, stop), el, az, 15.0, poses)
    v, f = rng.uniform(-5, 5, (3000, 3)), rng.integers(0, 3000, (1000, 3))
    o, d = rng.uniform(-1, 1, (5000, 3)), rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = p3k.raycast(p3k.Mesh(v, f, np.zeros(1000, np.int32)), o, d, 20.0, backend=b)
    t3 = time.perf_counter()
    dig = hashlib.sha1(s.tobytes() + c.tobytes() + np.asarray(h.t).tobytes() + np.asarray(h.face).tobytes())
    print(f"RESULT mode={mode} import={t1 - t0:.2f} load={t2 - t1:.2f} first_use={t3 - t2:.2f} "
          f"digest={dig.hexdigest()[:12]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
