"""The ROI box as a choice (issue 34, item 2): ``--roi`` parses and is checked, the box lands on the default
grid's face lattice, the default (0.1 m) and the old 0.2 m default stay bit for bit what they were, a P-SOG
of one ROI is never read for another, and the ROI study's summary is read from reproduce.json."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from place3d_app.cli import build_parser, main
from place3d_kernels.grid import DEFAULT_GRID, FACE_OFFSET, Grid, check_roi, roi_bounds, roi_grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.manifest import StaleCacheWarning
from place3d_kernels.pooled import PoolSettings
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec, specs_from_args

BACKEND = "warp:cpu"
TINY = LidarModel.uniform(8, fov_deg=(-25.0, 2.0), azimuth_steps=96, max_range=60.0, name="tiny8")
NUSCENES = (-54.0, -54.0, -3.2, 54.0, 54.0, 4.8)
DEFAULT_DICT = {"lower": [-40.05, -40.05, -0.45], "upper": [39.95, 39.95, 4.55], "voxel_size": 0.1,
                "shape": [800, 800, 50]}
#: The default before 0.1 m (issue 34, item 2): --voxel-size 0.2 must still find the caches made with it
OLD_DEFAULT_DICT = {"lower": [-40.05, -40.05, -0.45], "upper": [39.95, 39.95, 4.55], "voxel_size": 0.2,
                    "shape": [400, 400, 25]}


def _err(capsys) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("place3d: error:")]
    assert len(lines) == 1, lines
    return lines[0]


# ------------------------------------------------------------------------------ the default
def test_the_default_grid_is_bit_for_bit_what_it_was():
    assert RoiSpec().grid() is DEFAULT_GRID and PoolSettings().grid is DEFAULT_GRID
    assert DEFAULT_GRID.to_dict() == DEFAULT_DICT              # the dict every P-SOG cache key is made of
    # the old 0.2 m default, to the bit, under --voxel-size 0.2 (json: floats as the cache key writes them)
    for old in (RoiSpec(0.2).grid(), PoolSettings(0.2).grid, roi_grid(None, 0.2)):
        assert json.dumps(old.to_dict()) == json.dumps(OLD_DEFAULT_DICT)
    # and --voxel-size 0.1 is the new default to the bit: P-SOGs cached with it before are the default's now
    assert json.dumps(RoiSpec(0.1).grid().to_dict()) == json.dumps(DEFAULT_GRID.to_dict())
    assert RoiSpec().to_dict() == {"voxel_size": None}         # no "roi" key: old manifests still match
    # --roi 80 80 5 is the default box, to the bit, at every voxel size that divides it
    for v in (0.2, 0.1, 0.05, 0.4):
        g = roi_grid((80, 80, 5), v)
        assert g == Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, v)
        assert json.dumps(g.to_dict()) == json.dumps(Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, v).to_dict())
    assert RoiSpec(None, (80, 80, 5)).grid() == DEFAULT_GRID
    assert PoolSettings(roi=(80, 80, 5)).grid.to_dict() == DEFAULT_DICT


# ------------------------------------------------------------------------------ the box
@pytest.mark.parametrize("v", [0.2, 0.1, 0.4])
@pytest.mark.parametrize("roi", [(40, 40, 5), (108, 108, 8), (80, 80, 10), (33.3, 12.1, 4.9), NUSCENES,
                                 (0, -20, -1, 70.4, 20, 3)])
def test_a_chosen_roi_holds_the_box_asked_for_on_the_face_lattice(roi, v):
    g = roi_grid(roi, v)
    lo, hi = np.array(g.lower), np.array(g.upper)
    faces = np.concatenate([lo, hi])
    n = (faces - FACE_OFFSET) / v
    np.testing.assert_allclose(n, np.round(n), atol=1e-6)     # every face at -0.05 m + whole voxels
    if len(roi) == 6:
        want_lo, want_hi = np.array(roi[:3]), np.array(roi[3:])
    else:
        want_lo = np.array([-roi[0] / 2 + FACE_OFFSET, -roi[1] / 2 + FACE_OFFSET, -0.45])
        want_hi = want_lo + np.array(roi)
    assert np.all(lo <= want_lo + 1e-9) and np.all(hi >= want_hi - 1e-9)     # the box asked for, at least
    assert np.all(want_lo - lo < v + 1e-9) and np.all(hi - want_hi < v + 1e-9)   # and less than a voxel more
    # LiDARs on the paper's 0.1 m grid (and the ground, z = 0) never sit on a face
    k = np.arange(-600, 601) * 0.1
    for axis in range(3):
        d = (k - lo[axis]) / v
        assert np.all(np.abs(d - np.round(d)) > 1e-3)


def test_sizes_centre_x_y_on_the_ego_and_start_z_below_the_ground():
    assert roi_bounds((40, 40, 5), 0.2) == ((-20.05, -20.05, -0.45), (19.95, 19.95, 4.55))
    assert roi_bounds(None, 0.1) == (DEFAULT_GRID.lower, DEFAULT_GRID.upper)
    g = roi_grid(NUSCENES, 0.2)
    assert g.lower == (-54.05, -54.05, -3.25) and g.shape == (541, 541, 41)


def test_a_psog_of_a_smaller_roi_is_the_default_psog_cut_to_its_box(tmp_path):
    """The same frames voted on the default box and on 40 x 40 x 5 m (both at 0.4 m, one face lattice):
    every voxel of the small P-SOG is the default P-SOG's voxel at the same place, same probabilities."""
    from place3d_kernels import scene as scenes
    from place3d_kernels.simulate import simulate
    from place3d_kernels.sog import PSOG

    frames = simulate(scenes.town(seed=0, n_frames=8), TINY, backend=BACKEND)
    big_grid, small_grid = roi_grid(None, 0.4), roi_grid((40, 40, 5), 0.4)
    big, small = (PSOG.from_frames(frames, g, 2, backend=BACKEND) for g in (big_grid, small_grid))
    assert small.grid == small_grid and small.grid.shape == (100, 100, 13)
    inside = small_grid.contains(big_grid.centers(big.voxels))
    assert 0 < inside.sum() < len(big.voxels)
    np.testing.assert_array_equal(small_grid.flat(small_grid.index(big_grid.centers(big.voxels[inside]))),
                                  small.voxels)
    np.testing.assert_array_equal(big.probs[inside], small.probs)


# ------------------------------------------------------------------------------ caches
def test_a_psog_built_for_one_roi_is_never_read_for_another(tmp_path):
    from place3d_kernels import scene as scenes
    from place3d_kernels.pipeline import cache_file, cached_psog, scene_psog

    scene = scenes.town(seed=0, n_frames=8)
    a, b = roi_grid((40, 40, 5), 0.8), roi_grid((40, 40, 10), 0.8)
    grids = (a, b, roi_grid(None, 0.8), roi_grid(NUSCENES, 0.8))
    files = {cache_file(scene, g, TINY, 4, cache=tmp_path) for g in grids}
    assert len(files) == 4                                     # one cache key per box
    assert cache_file(scene, roi_grid((80, 80, 5)), TINY, 4, cache=tmp_path) == \
        cache_file(scene, DEFAULT_GRID, TINY, 4, cache=tmp_path)        # --roi 80 80 5 shares the default's
    built = scene_psog(scene, a, TINY, 4, backend=BACKEND, cache=tmp_path)
    assert cached_psog(scene, a, TINY, 4, cache=tmp_path) is not None
    assert cached_psog(scene, b, TINY, 4, cache=tmp_path) is None
    # even A's file under B's name (a stale or hand-copied cache) is refused: its manifest names grid A
    fa, fb = cache_file(scene, a, TINY, 4, cache=tmp_path), cache_file(scene, b, TINY, 4, cache=tmp_path)
    shutil.copy(fa, fb)
    shutil.copy(fa.with_suffix(".json"), fb.with_suffix(".json"))
    with pytest.warns(StaleCacheWarning):
        assert cached_psog(scene, b, TINY, 4, cache=tmp_path) is None
    assert built.grid == a


def test_spec_and_pool_settings_carry_the_roi_into_their_keys():
    s1 = PSOGSpec(SceneSpec("town", 0, 8), BACKEND, RoiSpec(0.4, (40, 40, 5)))
    s2 = PSOGSpec(SceneSpec("town", 0, 8), BACKEND, RoiSpec(0.4))
    assert s1 != s2 and hash(s1) != hash(s2)                   # memo keys of workers (spec._load_psog)
    assert PSOGSpec.from_dict(s1.to_dict()) == s1
    assert s1.to_dict()["grid"] == {"voxel_size": 0.4, "roi": [40.0, 40.0, 5.0]}
    assert PoolSettings(0.4, roi=[40, 40, 5]).to_dict()["roi"] == [40.0, 40.0, 5.0]
    assert PoolSettings(0.4, roi=[40, 40, 5]).grid == roi_grid((40, 40, 5), 0.4)


# ------------------------------------------------------------------------------ the option
@pytest.mark.parametrize("command", ["evaluate", "optimize", "simulate"])
def test_roi_parses_as_sizes_or_corners_on_every_command_with_voxel_size(command):
    extra = ["--output", "x"] if command == "simulate" else []
    args = build_parser().parse_args([command, "--roi", "40", "40", "5", "--voxel-size", "0.4", *extra])
    assert specs_from_args(args, frames_lidar=None).grid == RoiSpec(0.4, (40, 40, 5))
    args = build_parser().parse_args([command, "--roi", *map(str, NUSCENES), *extra])     # negative corners
    assert specs_from_args(args, frames_lidar=None).grid.grid() == roi_grid(NUSCENES)
    for other in (["reproduce"], ["study", "x.toml"]):
        assert build_parser().parse_args([*other, "--roi", "40", "40", "5"]).roi == [40, 40, 5]


@pytest.mark.parametrize("roi, voxel, words", [
    (["80", "80"], None, "3 sizes LX LY LZ or 6 corners"),
    (["0", "80", "5"], None, "must be > 0"),
    (["-1", "-1", "-1", "1", "1", "-2"], None, "Z1 > Z0"),
    (["80", "80", "5"], "0.005", "--voxel-size of at least"),      # 2.6e9 voxels: refused with a hint
    (["80", "80", "1"], None, "the collection LiDAR at (0, 0, 2.5)"),
    (["1", "1", "5"], None, "a LiDAR of 'line'"),
])
def test_bad_rois_are_refused_naming_the_option(roi, voxel, words, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["evaluate", "--frames", "8", "--routes", "1", "--quiet", "--roi", *roi]
    assert main(argv + (["--voxel-size", voxel] if voxel else [])) == 2
    msg = _err(capsys)
    assert "--roi" in msg and words in msg
    assert not list(tmp_path.iterdir())                       # nothing written, nothing built


def test_the_memory_guard_names_the_size_and_a_voxel_size_that_fits():
    with pytest.raises(ValueError, match=r"1e\+11 voxels \(about 838 GiB .* --voxel-size of at least (0\.\d+) m") as e:
        check_roi((1000, 1000, 100), 0.1)
    hint = float(e.value.args[0].rsplit("at least ", 1)[1].split()[0])
    assert check_roi((1000, 1000, 100), hint).n_voxels <= 400_000_000          # the hint fits
    with pytest.raises(ValueError):
        check_roi((1000, 1000, 100), round(hint - 0.01, 2))                      # and is the smallest that does
    assert check_roi((108, 108, 8), 0.1).n_voxels == 1080 * 1080 * 80


def test_reproduce_optimize_and_study_check_their_rigs_against_the_roi(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["reproduce", "--towns", "town", "--routes", "2", "--frames", "8", "--roi", "1", "1", "5",
                 "--executor", "local", "--output", "r", "--quiet"]) == 2
    assert "--roi" in (msg := _err(capsys)) and "placements" in msg
    assert main(["optimize", "--frames", "8", "--routes", "1", "--roi", "-0.6", "-0.6", "2", "0.55", "0.6", "3",
                 "--quiet", "--no-holdout"]) == 2
    assert "a corner of the search box" in _err(capsys)
    cfg = tmp_path / "s.toml"
    cfg.write_text('[study]\nname = "t"\nvoxel_size = 0.2\nroi = [1, 1, 5]\nplacements = ["line"]\n'
                   '[[scenes]]\nname = "town"\nframes = 8\n')
    assert main(["study", str(cfg), "--output", "st", "--quiet"]) == 2
    assert "a LiDAR of 'line'" in _err(capsys) and not Path("st").exists()
    from place3d_app.commands.study import study_settings

    assert "roi" not in study_settings({"voxel_size": 0.8})   # the cells of earlier studies keep their names
    # the default's size, not None: cells made when the default was 0.2 m are not read as 0.1 m ones
    assert study_settings({})["voxel_size"] == DEFAULT_GRID.voxel_size == 0.1
    assert study_settings({"roi": [40, 40, 5]})["roi"] == [40.0, 40.0, 5.0]


# ------------------------------------------------------------------------------ the study's summary
def _roi_study():
    path = Path(__file__).resolve().parents[1] / "bench" / "roi_study.py"
    spec = importlib.util.spec_from_file_location("roi_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _fake_reproduce(scale: float) -> dict:
    names = ["center", "line", "pyramid", "square", "trapezoid", "line-roll", "pyramid-roll", "ours", "mine"]
    msog = [-1.0, -2.0, -1.5, -1.2, -1.8, -1.9, -1.1, -1.05, -0.5]     # "mine" (a user rig) is best of all
    task = {"placements": names, "msog": [m * scale for m in msog], "rank": list(range(1, 10)),
            "tau_paper": 0.5, "tau_paper_loo_range": [0.4, 0.6], "tau_downstream": 0.7,
            "tau_downstream_loo_range": [0.6, 0.8], "within_noise": []}
    grid = roi_grid((40, 40, 5), 0.2).to_dict()
    return {"settings": {"grid": grid, "voxel_size": 0.2, "roi": [40.0, 40.0, 5.0], "n_subsets_total": 40},
            "machine": {"cpu": "test"}, "seconds": {"total": 3.0}, "drives": ["a", "b"],
            "tasks": {"seg": task, "det": dict(task, tau_paper=-0.2)}}


def test_the_study_summary_reads_reproduce_json_fields():
    mod = _roi_study()
    assert mod.parse_roi("nuscenes-det") == ("nuscenes-det", NUSCENES)
    assert mod.parse_roi("60x60x6") == ("60x60x6", (60.0, 60.0, 6.0))
    s = mod.summarise([("40x40x5-0.2m", (40, 40, 5), _fake_reproduce(0.01), 12.5)], {"backend": "x"})
    row = s["rows"][0]
    assert row["n_voxels"] == 200 * 200 * 25 and row["box_m"] == [40.0, 40.0, 5.0] and row["wall_s"] == 12.5
    seg = row["seg"]
    # the paper's eight only: "mine" is left out of the range and the spread
    assert (seg["best"], seg["worst"]) == ("center", "line")
    assert math.isclose(seg["msog_best"], -0.01) and math.isclose(seg["worst_best_ratio"], 2.0)
    assert math.isclose(seg["paper_worst_best_ratio"], 3.13 / 1.29)
    assert seg["tau_paper"] == 0.5 and seg["tau_downstream_loo_range"] == [0.6, 0.8]    # copied, not recomputed
    assert row["det"]["tau_paper"] == -0.2
    assert json.loads(json.dumps(s)) == s


def test_an_optimize_checkpoint_records_the_default_voxel_size():
    from place3d_app.commands.optimize import run_setup

    # the default's size, not None: a checkpoint made when the default was 0.2 m does not resume at 0.1 m
    args = build_parser().parse_args(["optimize"])
    assert run_setup(args, specs_from_args(args, frames_lidar=None))["psog"]["grid"] == {"voxel_size": 0.1}
    args = build_parser().parse_args(["optimize", "--voxel-size", "0.2", "--roi", "40", "40", "5"])
    assert run_setup(args, specs_from_args(args, frames_lidar=None))["psog"]["grid"] == \
        {"voxel_size": 0.2, "roi": [40.0, 40.0, 5.0]}
