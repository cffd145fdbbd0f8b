"""The spec layer: specs are plain data (pickle, dict round trip), the CLI builds them once, and the local
path and the executor path give the same bytes from the same specs."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from place3d_app.cli import build_parser, main
from place3d_kernels.grid import DEFAULT_GRID, Grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.spec import ConditionSpec, PSOGSpec, RoiSpec, SceneSpec, parse_params, specs_from_args

BACKEND = "warp:cpu"
TINY = LidarModel.uniform(8, fov_deg=(-25.0, 2.0), azimuth_steps=96, max_range=60.0, name="tiny8")


def _files(folder: Path) -> dict:
    """Every file's bytes; for ``sequence.json`` its spec (the provenance block holds a time and argv)."""
    import json

    return {str(p.relative_to(folder)): json.loads(p.read_text())["spec"] if p.name == "sequence.json"
            else p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_specs_are_plain_data():
    spec = PSOGSpec(SceneSpec("town", 3, 8), "warp:cpu", RoiSpec(0.4),
                    ConditionSpec("fog", 2, "heavy", (("alpha", 0.03),)), frames_per_subset=2,
                    mount=(0, 0, 2.5, 0, 0, 0))
    assert pickle.loads(pickle.dumps(spec)) == spec
    assert PSOGSpec.from_dict(spec.to_dict()) == spec
    assert hash(PSOGSpec.from_dict(spec.to_dict())) == hash(spec)      # usable as a memo key in workers
    for s in (spec.scene, spec.grid, spec.condition):
        assert type(s).from_dict(s.to_dict()) == s


def test_roi_spec_builds_the_grid_and_old_voxel_size_argument_still_works():
    assert RoiSpec().grid() is DEFAULT_GRID
    g = RoiSpec(0.4).grid()
    assert g == Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.4)      # the default ROI, whole 0.4 m voxels
    assert PSOGSpec(SceneSpec(), "reference", 0.4) == PSOGSpec(SceneSpec(), "reference", RoiSpec(0.4))
    assert PSOGSpec(SceneSpec(), "reference", None).grid == RoiSpec()


def test_condition_spec_from_study_table_and_clean():
    assert ConditionSpec.of({"name": "clean"}) is None
    c = ConditionSpec.of({"name": "fog", "severity": "light", "seed": 4, "alpha": 0.02})
    assert c == ConditionSpec("fog", 4, "light", (("alpha", 0.02),))
    assert c.label == "fog-light-alpha0.02-s4"
    fc = c.condition("reference")
    assert ConditionSpec.of(fc) == c                                 # FrameCondition -> spec -> same spec


def test_specs_from_args_once_for_every_command():
    args = build_parser().parse_args(["evaluate", "--scene", "town", "--seed", "5", "--frames", "12",
                                      "--voxel-size", "0.4", "--condition", "snow", "--severity", "light",
                                      "--param", "snowfall_rate=2", "--param", "terminal_velocity=1.2"])
    spec = specs_from_args(args)
    assert spec.scene == SceneSpec("town", 5, 12)
    assert spec.grid == RoiSpec(0.4)
    assert spec.condition == ConditionSpec("snow", 5, "light", (("snowfall_rate", 2.0), ("terminal_velocity", 1.2)))
    assert parse_params(["mode=x", "a=2"]) == {"mode": "x", "a": 2.0}      # text stays text, numbers float
    # a parameter the condition does not take is refused with the allowed set (issue 15)
    with pytest.raises(ValueError, match="no parameter 'mode'.*snowfall_rate"):
        specs_from_args(build_parser().parse_args(["evaluate", "--condition", "snow", "--param", "mode=x"]))
    assert specs_from_args(build_parser().parse_args(["evaluate"])).condition is None
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_params(["alpha"])
    # an unknown condition is refused while the specs are built, before any work starts
    with pytest.raises(ValueError, match="unknown condition 'hail'"):
        specs_from_args(build_parser().parse_args(["evaluate", "--condition", "hail"]))


def test_cli_local_simulate_equals_executor_path_from_the_same_specs(tmp_path):
    from place3d_app.executors import LocalExecutor, simulate_to_folder

    lidar = "place3d_16ch"
    argv = ["simulate", "--frames", "3", "--seed", "1", "--lidar", lidar, "--backend", BACKEND, "--quiet",
            "--condition", "fog", "--param", "alpha=0.03", "--output", str(tmp_path / "cli")]
    assert main(argv) == 0
    spec = specs_from_args(build_parser().parse_args(argv))
    simulate_to_folder(spec.scene, lidar, tmp_path / "ex", LocalExecutor(), chunk=2, backend=BACKEND,
                       condition=spec.condition)
    assert _files(tmp_path / "cli") == _files(tmp_path / "ex")
    assert len(_files(tmp_path / "cli")) == 8          # 3 frames x 2 files, poses.txt, sequence.json


def test_psog_spec_build_equals_scene_psog(tmp_path):
    from place3d_kernels.pipeline import FrameCondition, scene_psog

    spec = PSOGSpec(SceneSpec("town", 0, 4), BACKEND, RoiSpec(0.4), ConditionSpec("motion_blur", 2), TINY, 2)
    a = spec.build(cache=False)
    b = scene_psog(SceneSpec("town", 0, 4).build(), RoiSpec(0.4).grid(), TINY, 2, backend=BACKEND, cache=False,
                   condition=FrameCondition("motion_blur", seed=2, backend=BACKEND))
    np.testing.assert_array_equal(a.voxels, b.voxels)
    np.testing.assert_array_equal(a.probs, b.probs)
