"""``place3d simulate``: semantic LiDAR frames of a scene written as a SemanticKITTI sequence."""

from __future__ import annotations

__all__ = ["cmd_simulate"]


def cmd_simulate(args) -> int:
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.io import prepare_sequence_folder, sequence_spec, write_sequence_metadata
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.simulate import DEFAULT_MOUNT
    from place3d_kernels.spec import specs_from_args

    distributed = getattr(args, "executor", "local") == "ray" or getattr(args, "ray_address", None)
    # here every frame is held until the sequence is written; Ray workers write theirs chunk by chunk
    spec = specs_from_args(args, frames_lidar=None if distributed else args.lidar)
    meta = sequence_spec(spec.scene.to_dict(), LidarModel.load(args.lidar),
                         None if spec.condition is None else spec.condition.to_dict(), DEFAULT_MOUNT)
    body = spec.vehicle_body()
    if body is not None:
        # a sequence made with another body is another sequence (prepare_sequence_folder compares specs)
        meta["vehicle"] = {"name": body.name, "key": body.key}
    if distributed and body is not None:
        raise ValueError(f"--vehicle {spec.vehicle} is not supported with --executor ray yet; simulate locally "
                         f"(drop --executor/--ray-address) or drop --vehicle")
    prepare_sequence_folder(args.output, meta, overwrite=args.overwrite)
    if distributed:
        from place3d_app.executors import executor_from_args, simulate_to_folder

        ex = executor_from_args(args)
        try:
            r = simulate_to_folder(spec.scene, args.lidar, args.output, ex, chunk=args.chunk or 8,
                                   backend=args.backend, condition=spec.condition, overwrite=args.overwrite)
        finally:
            ex.shutdown()
        print(f"wrote {r['written']} frames ({r['skipped']} already there) to {r['out']} in {r['seconds']:.1f} s "
              f"on {ex.kind}")
        return 0
    from place3d_kernels.io import write_semantickitti_sequence
    from place3d_kernels.simulate import simulate

    b = get_backend(args.backend)
    frames = simulate(spec.scene.build(), args.lidar, backend=b, progress=not args.quiet, body=body)
    if spec.condition is not None:
        cond = spec.condition.condition(b)
        frames = [cond(f, i) for i, f in enumerate(frames)]
    out = write_semantickitti_sequence(frames, args.output)
    write_sequence_metadata(out, meta)
    print(f"wrote {len(frames)} frames to {out}")
    return 0
