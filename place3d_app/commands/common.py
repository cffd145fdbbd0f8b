"""What the commands share: the scene and condition options, output checks, the P-SOG with progress."""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import Future
import time
from pathlib import Path

from place3d_kernels.profiling import section

from place3d_app.prefetch import backend_after_actors

__all__ = ["add_common", "add_roi_argument", "check_rigs_in_roi", "check_pool_roi", "check_output_file",
           "check_output_dir", "psog_for_spec"]


#: --roi's help, shared by every command that takes --voxel-size.
ROI_HELP = ("ROI box in metres, ego frame (x forward, y left, z up, z = 0 on the ground): 3 sizes LX LY LZ (x, y "
            "centred on the ego, z from 0.45 m below the ground) or 6 corners X0 Y0 Z0 X1 Y1 Z1; faces snap outward "
            "to -0.05 m + whole voxels (docs/assumptions.md, section 1). Default 80 80 5")


def add_roi_argument(p) -> None:
    """``--roi`` (3 sizes or 6 corners; ``grid.roi_bounds``), beside ``--voxel-size``."""
    p.add_argument("--roi", type=float, nargs="+", default=None, metavar="M", help=ROI_HELP)


def check_pool_roi(roi, voxel_size, rigs):
    """The grid of ``--roi`` / ``--voxel-size``, checked before any drive is built: it fits in memory and
    holds the collection LiDAR and every LiDAR of ``rigs`` (``{name: (..., L, 6) poses}``); ``ValueError``
    naming the option otherwise."""
    from place3d_kernels.grid import check_inside, check_roi
    from place3d_kernels.simulate import DEFAULT_MOUNT

    grid = check_roi(roi, voxel_size)
    check_inside(grid, DEFAULT_MOUNT[:3], "the collection LiDAR")
    check_rigs_in_roi(grid, rigs)
    return grid


def check_rigs_in_roi(grid, rigs) -> None:
    """``ValueError`` naming --roi when a LiDAR of ``rigs`` (``{name: (L, 6) poses}``) lies outside ``grid``."""
    import numpy as np

    from place3d_kernels.grid import check_inside

    for name, poses in rigs.items():
        check_inside(grid, np.asarray(poses, dtype=np.float64)[..., :3], f"a LiDAR of {name!r}")


class SceneList(argparse.Action):
    """``--scene`` given several times: ``args.scenes`` lists them all, ``args.scene`` stays the first
    (``commands/routes.py`` pools them)."""

    def __call__(self, parser, namespace, values, option_string=None):
        scenes = list(getattr(namespace, "scenes", None) or []) + [values]
        namespace.scenes = scenes
        namespace.scene = scenes[0]


def add_common(p: argparse.ArgumentParser, several_scenes: bool = False) -> None:
    """The scene and condition options; ``several_scenes``: ``--scene`` may repeat (pooled commands)."""
    p.add_argument("--backend", default=None,
                   help="reference | warp[:cpu|:cuda:N] | opencl[:platform] | auto (default: $PLACE3D_BACKEND or auto)")
    extra = {"action": SceneList} if several_scenes else {}
    p.add_argument("--scene", default="town", **extra,
                   help="scene: 'town' (the embedded procedural town), 'opendrive:PATH' (e.g. a CARLA .xodr map) or "
                        "'opendrive:Town06' (a shipped CARLA map by name), 'mesh:PATH' (a mesh file trimesh reads or "
                        "a Mitsuba XML; see --labels, --route) or 'semantickitti:DIR' (labelled frames + poses.txt: "
                        "the P-SOG is built from them)" + ("; repeat it to pool several scenes" if several_scenes else ""))
    p.add_argument("--labels", default=None,
                   help="mesh scenes: TOML label map (part name -> class) or one class for the whole file")
    p.add_argument("--route", default=None,
                   help="mesh scenes: ego poses, one per line: 'x y z roll pitch yaw' or 'x y yaw' (m, rad)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--frames", type=int, default=40, help="frames along the ego route (default 40, as the paper)")
    p.add_argument("--voxel-size", type=float, default=None, help="ROI voxel size in metres (default 0.1)")
    add_roi_argument(p)
    p.add_argument("--no-cache", action="store_true", help="rebuild the P-SOG even if a cached one exists")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--condition", default=None,
                   help="adverse condition on the simulated frames: fog, wet_ground, snow, motion_blur, crosstalk, "
                        "incomplete_echo (paper settings unless --severity/--param)")
    p.add_argument("--severity", default=None, choices=["light", "moderate", "heavy"], help="condition severity")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="condition parameter, e.g. --param alpha=0.03 (repeatable)")
    p.add_argument("--vehicle", default=None, metavar="car|suv|van|truck|none|PATH",
                   help="ego vehicle body blocking the rays of the collection LiDAR (P-SOG) and of the scored "
                        "rigs: a preset or a mesh file in the ego frame. Default none, the paper's setting (no "
                        "body), so the paper's numbers reproduce; optimize: giving it selects real-rig mode, "
                        "whose default is car")


def check_output_file(path, suffixes=(".json",), what="--output") -> None:
    """An output file path the writer can produce: the right extension, not an existing folder."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{what} {p} is a folder; give a file path ending in {' or '.join(suffixes)}")
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{what} {p}: only {' or '.join(suffixes)} is written; use e.g. {p.with_suffix(suffixes[0])}")


def check_output_dir(path, what="--output") -> None:
    if path is not None and Path(path).exists() and not Path(path).is_dir():
        raise ValueError(f"{what} {path} is an existing file; give a folder")


def psog_for_spec(spec, args, backend, with_scene: bool = True):
    """(scene, P-SOG) of ``spec`` built with ``backend`` (the local path), honouring --no-cache / --quiet.
    ``backend`` may be a ``concurrent.futures.Future`` of one, waited for only on a cache miss.

    Raises ``ValueError`` for a P-SOG without entropy (every voxel a single class: fewer than two subsets),
    on which every rig would score 0.
    """
    from place3d_kernels.pipeline import check_entropy
    from place3d_kernels.subset_records import records_aggregator

    t = time.perf_counter()
    # on a cache miss the P-SOG is pooled from per-subset records kept on disk, so the intervals find
    # them instead of simulating the same frames again
    aggregate = None if args.no_cache else records_aggregator(spec)
    with section("P-SOG (cache or build)"):
        psog = None
        if isinstance(backend, Future):
            # the backend is still being probed on a thread (optimize starts it early): a cached P-SOG
            # needs none, and a miss waits for it while the actors' meshes are built
            psog = spec.cached(cache=not args.no_cache)
            if psog is None:
                backend = backend_after_actors(spec, backend)
        if psog is None:
            # the new P-SOG's file is written on a thread while the command goes on (main waits for it at the
            # end), unless Ray workers will read it from the cache meanwhile
            local = getattr(args, "executor", "local") == "local" and not getattr(args, "ray_address", None)
            psog = spec.build(backend=backend, cache=not args.no_cache, progress=not args.quiet,
                              aggregate=aggregate, save_in_background=local)
    check_entropy(psog, spec.frames_per_subset)
    if not args.quiet:
        print(f"P-SOG ready in {time.perf_counter() - t:.1f} s: {psog}", file=sys.stderr)
    if not with_scene or spec.scene.kind == "semantickitti":
        return None, psog       # a cached P-SOG was found without building the scene (scene.keymemo)
    with section("scene build"):
        return spec.scene.build(), psog


# ---------------------------------------------------------------------------------------- commands


def flat_objective(psog, normalisation: str) -> str | None:
    """Why ``normalisation`` scores every rig alike on ``psog``, or None. With T = 2 subsets a voxel's class
    frequencies are 1 or 1/2 + 1/2, so every voxel with H > 0 has H = ln 2 and the uncertain M-SOG is -ln 2
    for any rig that covers one: the search has nothing to follow."""
    if normalisation == "uncertain" and psog.n_subsets == 2:
        return (f"--normalisation uncertain on a P-SOG of T = 2 subsets scores every rig -ln 2 = {-math.log(2):.6f} "
                f"(each voxel with entropy has H = ln 2): pool more routes (--routes), use more --frames (T >= 3), "
                f"or --normalisation paper")
    return None


def warn_flat_objective(psog, normalisation: str) -> None:
    """Print ``flat_objective``'s reason as a warning on stderr (the search still runs, as asked)."""
    import sys

    why = flat_objective(psog, normalisation)
    if why:
        print(f"place3d: warning: {why}", file=sys.stderr)
