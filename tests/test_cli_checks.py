"""Issue 15, "never a silently wrong answer": every case that used to give a wrong or stale result without a
word now gives an error (exit 2, one line, nothing written) or a loud warning; outputs carry provenance.

Each test fails on the code before this change (it reused stale cells, resumed any checkpoint, kept stale
frames, scored entropy-free P-SOGs, ...). Settings are tiny (8 frames, 0.8 m voxels) so each runs in
seconds.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from place3d_app.cli import main

TINY = ["--frames", "8", "--voxel-size", "0.8", "--quiet", "--routes", "1"]


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    # the one error line; warnings and notes ("place3d: warning: ...") may come beside it
    lines = [ln for ln in err if ln.startswith("place3d") and not ln.startswith(("place3d: warning:", "place3d: note:"))]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _study_toml(path: Path, voxel=0.8, occlusion="sog", placements=("center",)) -> Path:
    pl = ", ".join(f'"{p}"' for p in placements)
    path.write_text(f'[study]\nname = "t"\nocclusion = "{occlusion}"\nvoxel_size = {voxel}\nplacements = [{pl}]\n'
                    f'[[scenes]]\nname = "town"\nseed = 0\nframes = 8\n[[conditions]]\nname = "clean"\n')
    return path


# ------------------------------------------------------------------------------ 1. keys on everything
def test_study_rerun_with_other_settings_is_refused_then_recomputed_with_overwrite(tmp_path, capsys):
    cfg = _study_toml(tmp_path / "a.toml")
    assert main(["study", str(cfg), "--output", "st", "--quiet"]) == 0
    first = json.loads(Path("st/study.json").read_text())
    assert json.loads(Path("st/manifest.json").read_text())["spec"]["voxel_size"] == 0.8
    capsys.readouterr()
    cfg2 = _study_toml(tmp_path / "b.toml", voxel=1.6, occlusion="none")
    assert main(["study", str(cfg2), "--output", "st", "--quiet"]) == 2
    msg = _err(capsys)
    assert "occlusion" in msg and "--overwrite" in msg       # first differing field, sorted keys
    assert json.loads(Path("st/study.json").read_text()) == first   # nothing rewritten
    assert main(["study", str(cfg2), "--output", "st", "--quiet", "--overwrite"]) == 0
    second = json.loads(Path("st/study.json").read_text())
    assert second["executed"] > 0 and second["occlusion"] == "none" and second["settings"]["voxel_size"] == 1.6
    assert second["rows"][0]["msog_seg"] != first["rows"][0]["msog_seg"]
    assert len(list(Path("st/cells").iterdir())) == 1         # the old cell is gone


def test_optimize_resume_with_another_task_is_refused(capsys):
    args = ["optimize", *TINY, "--max-evals", "10", "--output", "o"]
    assert main(args) == 0
    assert Path("o/checkpoint.ckpt").exists()                 # checkpoints into the output folder by default
    before = Path("o/result.json").read_text()
    capsys.readouterr()
    assert main(args + ["--resume", "--task", "det"]) == 2
    msg = _err(capsys)
    assert "task" in msg and "'seg'" in msg and "'det'" in msg
    assert Path("o/result.json").read_text() == before
    assert main(args + ["--resume", "--max-evals", "20"]) == 0    # same setup, larger budget: resumes


def test_simulate_into_folder_of_other_settings(capsys):
    base = ["simulate", "--frames", "6", "--quiet", "--lidar", "place3d_16ch",
            "--output", "seq"]
    assert main(base) == 0
    capsys.readouterr()
    assert main(base[:2] + ["3"] + base[3:]) == 2             # 3 frames into a 6-frame folder
    assert "frames" in _err(capsys)
    assert main(base + ["--condition", "fog"]) == 2
    assert "condition" in _err(capsys)
    assert len(list(Path("seq/velodyne").glob("*.bin"))) == 6
    assert main(base[:2] + ["3"] + base[3:] + ["--overwrite"]) == 0
    assert len(list(Path("seq/velodyne").glob("*.bin"))) == 3
    assert len(Path("seq/poses.txt").read_text().splitlines()) == 3


def test_write_sequence_removes_frames_beyond_the_new_ones(tmp_path):
    from place3d_kernels import scene as scenes
    from place3d_kernels.io import write_semantickitti_sequence
    from place3d_kernels.simulate import simulate

    frames = simulate(scenes.town(seed=0, n_frames=4), "place3d_16ch")
    write_semantickitti_sequence(frames, tmp_path / "s")
    write_semantickitti_sequence(frames[:2], tmp_path / "s")
    assert len(list((tmp_path / "s/velodyne").glob("*.bin"))) == 2
    assert len(list((tmp_path / "s/labels").glob("*.label"))) == 2


def test_psog_cache_stores_and_checks_its_inputs(tmp_path, caplog):
    from place3d_kernels import scene as scenes
    from place3d_kernels.grid import DEFAULT_GRID, Grid
    from place3d_kernels.pipeline import scene_psog

    sc = scenes.town(seed=0, n_frames=8)
    grid = Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.8)
    a = scene_psog(sc, grid, "place3d_16ch", cache=tmp_path / "c")
    (man,) = (tmp_path / "c").glob("psog-*.json")
    stored = json.loads(man.read_text())
    assert stored["spec"]["k"] == 4 and stored["spec"]["grid"]["voxel_size"] == 0.8
    stored["spec"]["k"] = 5                                    # a cache whose inputs do not match ...
    man.write_text(json.dumps(stored))
    with pytest.warns(RuntimeWarning, match="rebuilt.*k:") as w:     # ... is rebuilt, loudly
        b = scene_psog(sc, grid, "place3d_16ch", cache=tmp_path / "c")
    assert str(man.with_suffix(".npz")) in str(w[0].message)
    np.testing.assert_array_equal(a.probs, b.probs)
    assert json.loads(man.read_text())["spec"]["k"] == 4


# ------------------------------------------------------------------------------ 2. provenance
def test_outputs_carry_provenance_and_sequences_read_back_without_hints(capsys):
    import place3d_kernels as p3k
    from place3d_kernels.io import psog_from_semantickitti, read_sequence

    assert main(["evaluate", *TINY, "center", "--condition", "crosstalk", "--param", "ratio=0.05",
                 "--output", "e.json"]) == 0
    e = json.loads(Path("e.json").read_text())
    assert e["provenance"]["version"] == p3k.__version__
    assert e["provenance"]["argv"][:2] == ["place3d", "evaluate"] and "--param" in e["provenance"]["argv"]
    assert e["provenance"]["time"].endswith("+00:00") and e["provenance"]["backend"] == e["backend"]
    assert e["condition"] == {"name": "crosstalk", "seed": 0, "severity": None, "params": {"ratio": 0.05}}
    assert e["grid"]["voxel_size"] == 0.8 and e["scene"]["frames"] == 8 and e["lidar"] == "place3d_16ch"

    assert main(["simulate", "--frames", "4", "--quiet", "--lidar", "place3d_16ch",
                 "--output", "seq"]) == 0
    meta = json.loads(Path("seq/sequence.json").read_text())
    assert meta["spec"]["labels"] == "place3d" and meta["spec"]["sensor"]["name"] == "place3d_16ch"
    assert meta["spec"]["mount"] == [0.0, 0.0, 2.5, 0.0, 0.0, 0.0] and meta["version"] == p3k.__version__
    back = read_sequence("seq")                               # no labels= hint: sequence.json says place3d
    from place3d_kernels import scene as scenes
    from place3d_kernels.simulate import simulate

    ref = simulate(scenes.town(seed=0, n_frames=4), "place3d_16ch")
    for f, r in zip(back, ref):
        np.testing.assert_array_equal(f.labels, r.labels)
        np.testing.assert_allclose(f.ego_pose, r.ego_pose, atol=1e-5)
    from place3d_kernels.grid import DEFAULT_GRID, Grid

    psog_from_semantickitti("seq", Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.8), 2)

    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and p3k.__version__ in capsys.readouterr().out


def test_result_json_records_sensor_grid_setup_and_provenance():
    assert main(["optimize", *TINY, "--max-evals", "10", "--output", "o"]) == 0
    r = json.loads(Path("o/result.json").read_text())
    assert r["grid"]["voxel_size"] == 0.8 and r["sensor"]["name"] == "place3d_16ch"
    assert r["setup"]["task"] == "seg" and r["provenance"]["version"] and "left_start" in r


# ------------------------------------------------------------------------------ 3. degenerate inputs
def test_psog_without_entropy_is_an_error(capsys):
    assert main(["evaluate", "--frames", "3", "--voxel-size", "0.8", "--quiet", "--routes", "1",
                 "center", "--output", "e.json"]) == 2
    msg = _err(capsys)
    assert "no entropy" in msg and "T = 1" in msg and "8 frames" in msg
    assert not Path("e.json").exists()


def test_optimiser_that_never_left_its_start_says_so():
    from place3d_kernels.optimize import SearchSpace, optimize

    space = SearchSpace(n_lidars=1)
    with pytest.warns(RuntimeWarning, match="never left its start"):
        res = optimize(lambda X: np.zeros(len(np.atleast_2d(X))), space, [], max_evals=12, seed=0,
                       x0=space.center(), progress=False)
    assert res.left_start is False and res.to_dict()["left_start"] is False
    res = optimize(lambda X: -np.sum((np.atleast_2d(X) - space.lower) ** 2, axis=1), space, [], max_evals=60,
                   seed=0, x0=space.center(), progress=False)
    assert res.left_start is True


def test_x0_outside_the_box_is_refused_before_work(tmp_path, capsys, monkeypatch):
    from place3d_kernels.spec import PSOGSpec

    monkeypatch.setattr(PSOGSpec, "build", lambda *a, **k: pytest.fail("P-SOG built before the check"))
    toml = Path("center.toml").write_text(Path(__file__).resolve().parents[1].joinpath(
        "place3d_kernels/configs/placements/center.toml").read_text().replace("z = 2.8", "z = 9.0"))
    assert toml
    assert main(["optimize", *TINY, "--x0", "center.toml", "--output", "o"]) == 2
    assert "outside the search box" in _err(capsys)
    assert not Path("o").exists()


def test_evaluate_output_must_be_json(capsys, monkeypatch):
    from place3d_kernels.spec import PSOGSpec

    monkeypatch.setattr(PSOGSpec, "build", lambda *a, **k: pytest.fail("P-SOG built before the check"))
    assert main(["evaluate", *TINY, "--output", "e.csv"]) == 2
    assert ".json" in _err(capsys)
    assert not Path("e.csv").exists()


def test_unmapped_mesh_parts_are_listed(tmp_path):
    import trimesh

    from place3d_kernels.scene import load_mesh

    sc = trimesh.Scene()
    sc.add_geometry(trimesh.creation.box((1, 1, 1)), node_name="road", geom_name="road")
    sc.add_geometry(trimesh.creation.box((1, 1, 1)).apply_translation((3, 0, 0)), node_name="blob7",
                    geom_name="blob7")
    path = tmp_path / "m.glb"
    sc.export(path)
    with pytest.warns(UserWarning, match="blob7"):
        m = load_mesh(path)
    assert (m.labels == 0).any()
    with pytest.raises(ValueError, match="blob7"):
        load_mesh(path, strict=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mesh(path, default="building")                  # an explicit default is the user's choice


# ------------------------------------------------------------------------------ 4. checks before work
@pytest.mark.parametrize("argv, words", [
    (["simulate", "--condition", "fog", "--param", "bogus=1", "--output", "out"], ["bogus", "alpha", "beta"]),
    (["simulate", "--condition", "fog", "--param", "alpha=abc", "--output", "out"], ["alpha=abc", "number"]),
    (["simulate", "--param", "alpha=0.1", "--output", "out"], ["--condition"]),
    (["simulate", "--severity", "heavy", "--output", "out"], ["--severity", "--condition"]),
    (["optimize", "--max-evals", "0", "--output", "out"], ["--max-evals"]),
    (["optimize", "--lidars", "9", "--output", "out"], ["--lidars"]),
    (["evaluate", "--voxel-size", "0", "--output", "out.json"], ["--voxel-size"]),
    (["evaluate", "--frames", "0", "--output", "out.json"], ["--frames"]),
    (["evaluate", "--scene", "nowhere", "--output", "out.json"], ["nowhere"]),
])
def test_bad_arguments_fail_before_work_and_leave_nothing(argv, words, capsys, monkeypatch):
    from place3d_kernels.spec import PSOGSpec, SceneSpec

    monkeypatch.setattr(PSOGSpec, "build", lambda *a, **k: pytest.fail("P-SOG built before the check"))
    monkeypatch.setattr(SceneSpec, "build", lambda *a, **k: pytest.fail("scene built before the check"))
    assert main(argv + ["--quiet"]) == 2
    msg = _err(capsys)
    assert all(w in msg for w in words), msg
    assert not Path("out").exists() and not Path("out.json").exists()


def test_output_paths_of_the_wrong_kind_are_refused_up_front(capsys, monkeypatch):
    from place3d_kernels.spec import PSOGSpec

    monkeypatch.setattr(PSOGSpec, "build", lambda *a, **k: pytest.fail("P-SOG built before the check"))
    Path("afile").write_text("x")
    Path("adir").mkdir()
    assert main(["optimize", *TINY, "--output", "afile"]) == 2
    assert "afile" in _err(capsys)
    assert main(["simulate", *TINY[:-2], "--output", "afile"]) == 2        # simulate takes no --routes
    assert "afile" in _err(capsys)
    assert main(["evaluate", *TINY, "--output", "adir"]) == 2
    assert "adir" in _err(capsys)


def test_study_with_unknown_placement_writes_nothing(tmp_path, capsys):
    cfg = _study_toml(tmp_path / "a.toml", placements=("center", "no_such_rig"))
    assert main(["study", str(cfg), "--output", "st", "--quiet"]) == 2
    assert "no_such_rig" in _err(capsys)
    assert not Path("st").exists()


def test_ctrl_c_is_one_line_and_exit_130(capsys, monkeypatch):
    import place3d_app.commands.common as common

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(common, "psog_for_spec", boom)      # the single-drive P-SOG (TINY has --routes 1)
    try:
        rc = main(["optimize", *TINY, "--output", "o"])
    except KeyboardInterrupt:
        pytest.fail("KeyboardInterrupt escaped main()")
    assert rc == 130
    msg = _err(capsys)
    assert "interrupted" in msg and "--resume" in msg


# ------------------------------------------------------------------------------ units
def test_wet_ground_water_height_carries_its_unit():
    import inspect

    from place3d_kernels import conditions as C
    from place3d_kernels.pointcloud import PointCloud

    assert "water_height_mm" in inspect.signature(C.wet_ground).parameters
    assert "water_height_mm" in inspect.signature(C.film_transmission).parameters
    assert C.SEVERITIES["wet_ground"]["moderate"] == {"water_height_mm": 1.0}
    assert C.load_condition("wet_ground")["params"]["water_height_mm"] == 1.0
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-20, 20, (200, 2)), np.zeros(200)]
    cloud = PointCloud(pts, np.full(200, 1, np.int32), rng.uniform(0.1, 1, 200).astype(np.float32),
                       np.array([0.0, 0.0, 2.0]))
    a = C.wet_ground(cloud, water_height_mm=0.5, seed=1)
    with pytest.warns(DeprecationWarning, match="water_height_mm"):
        b = C.wet_ground(cloud, water_height=0.5, seed=1)       # the old name still works, with a warning
    np.testing.assert_array_equal(a.intensity, b.intensity)


# ------------------------------------------------------------------------------ 5. the user's own data
def test_mesh_scene_with_route_and_label_map_from_the_cli(tmp_path, capsys):
    import trimesh

    sc = trimesh.Scene()
    sc.add_geometry(trimesh.creation.box((120, 30, 0.2)).apply_translation((0, 0, -0.1)), node_name="road",
                    geom_name="road")
    for i, x in enumerate(range(-50, 51, 10)):
        for side in (-1, 1):
            b = trimesh.creation.box((6, 6, 4 + (i % 3) * 3)).apply_translation((x, side * 12, 2 + (i % 3) * 1.5))
            sc.add_geometry(b, node_name=f"house{i}{side}", geom_name=f"house{i}{side}")
    # glTF is Y-up (the loader turns it Z-up; trimesh writes coordinates as they are): turn the Z-up street
    sc.apply_transform(np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=float))
    sc.export(tmp_path / "street.glb")
    (tmp_path / "labels.toml").write_text('"*" = "building"\nroad = "road"\n')
    (tmp_path / "route.txt").write_text("# x y yaw\n" + "".join(f"{x} 0 0\n" for x in np.linspace(-20, 20, 8)))
    argv = ["evaluate", "--scene", f"mesh:{tmp_path / 'street.glb'}", "--labels", str(tmp_path / "labels.toml"),
            "--route", str(tmp_path / "route.txt"), "--voxel-size", "0.8", "--quiet", "center", "line",
            "--output", "m.json"]
    assert main(argv) == 0
    rows = json.loads(Path("m.json").read_text())["rows"]
    assert all(r["msog_seg"] < 0 for r in rows)                # entropy was found (M-SOG is -H summed)
    capsys.readouterr()
    # without a route: one ego pose, T = 1, no entropy -> an error that says what to do
    assert main(argv[:5] + ["--voxel-size", "0.8", "--quiet", "center"]) == 2
    assert "--route" in _err(capsys)


def test_semantickitti_sequence_as_scene_equals_the_simulated_scene(capsys):
    assert main(["simulate", "--frames", "8", "--quiet", "--output", "seq"]) == 0
    assert main(["evaluate", "--scene", "semantickitti:seq", "--voxel-size", "0.8", "--quiet", "center",
                 "--output", "k.json"]) == 0
    assert main(["evaluate", *TINY, "--no-cache", "center", "--output", "t.json"]) == 0
    k = json.loads(Path("k.json").read_text())["rows"][0]
    t = json.loads(Path("t.json").read_text())["rows"][0]
    # the same frames (collection LiDAR, default mount), read back from float32 files
    assert k["msog_seg"] == pytest.approx(t["msog_seg"], rel=0.02)
    capsys.readouterr()
    assert main(["evaluate", "--scene", "semantickitti:nowhere", "--quiet"]) == 2
    assert "velodyne" in _err(capsys)


def test_mitsuba_xml_scene_from_the_cli(tmp_path, capsys):
    # a street of cubes on a road rectangle as a Mitsuba 3 XML scene, driven along a route
    shapes = ['<shape type="rectangle" id="road"><transform name="to_world"><scale x="60" y="15"/></transform></shape>']
    for i, x in enumerate(range(-50, 51, 10)):
        for side in (-1, 1):
            h = 2 + (i % 3)
            shapes.append(f'<shape type="cube" id="house{i}_{side + 1}"><transform name="to_world"><scale x="3" y="3" '
                          f'z="{h}"/><translate x="{x}" y="{side * 12}" z="{h}"/></transform></shape>')
    xml = tmp_path / "street.xml"
    xml.write_text('<?xml version="1.0"?>\n<scene version="3.0.0">\n' + "\n".join(shapes) + "\n</scene>\n")
    (tmp_path / "labels.toml").write_text('"*" = "building"\nroad = "road"\n')
    (tmp_path / "route.txt").write_text("".join(f"{x} 0 0\n" for x in np.linspace(-20, 20, 8)))
    out = tmp_path / "x.json"
    argv = ["evaluate", "--scene", f"mitsuba:{xml}", "--labels", str(tmp_path / "labels.toml"), "--route",
            str(tmp_path / "route.txt"), "--voxel-size", "0.8", "--quiet", "--interval", "none", "center",
            "--output", str(out)]
    assert main(argv) == 0
    assert json.loads(out.read_text())["rows"][0]["msog_seg"] < 0
    capsys.readouterr()
    # 'mitsuba:' takes XML only, refused before any work, nothing written
    bad = tmp_path / "b.json"
    assert main(["evaluate", "--scene", f"mitsuba:{tmp_path / 'labels.toml'}", "--quiet", "--output", str(bad)]) == 2
    assert "XML" in _err(capsys) and not bad.exists()
