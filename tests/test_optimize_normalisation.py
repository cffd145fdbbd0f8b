"""``place3d optimize`` searches with the uncertain normalisation by default (issue 34, item 4), on every path.

Each path must score with the normalisation asked for: the winner's recorded score, the baselines' and the
held-out scores equal ``msog_batch(..., normalisation=...)`` of the same rigs on the same P-SOGs. Results and
checkpoints of a run that searched with another normalisation (a paper run from before the switch among
them) are refused, naming the option. The Ray paths are in tests/test_distributed.py and tests/test_actors.py.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil

import numpy as np
import pytest

from place3d_kernels.backends.registry import available_backends
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import msog_batch
from place3d_kernels.placement import PAPER_PLACEMENTS, Placement

# the fastest CPU backend present (the backends agree bit for bit)
B = "opencl:pocl" if "opencl:pocl" in available_backends() else "reference"
TINY = ["--frames", "8", "--voxel-size", "0.8", "--max-evals", "24", "--quiet", "--backend", B]
RUNS = {
    # pooled over two routes, held out on a third; in-process fused scoring
    "default": ["--routes", "2", "--holdout-seeds", "5"],
    # the pose cache (MSOGObjective) on one drive of 12 frames (T = 3: uncertain is flat on T = 2, see below)
    "pose_cache": ["--routes", "1", "--frames", "12", "--pose-cache", "--no-holdout", "--interval", "none"],
    # the paper's definition, asked for: a run as every run without --normalisation was before the switch
    "paper": ["--routes", "1", "--normalisation", "paper", "--no-holdout", "--interval", "none"],
}


def _args(extra):
    from place3d_app.cli import build_parser

    return build_parser().parse_args(["optimize", *TINY, *extra])


def _psog(extra):
    """The P-SOG the run of ``extra`` searched (pooled over its drives), read from the run's cache."""
    from place3d_app.commands.routes import drive_specs
    from place3d_kernels.pooled import pool_specs
    from place3d_kernels.spec import specs_from_args

    args = _args(extra)
    spec = specs_from_args(args)
    drives = drive_specs(args, spec)
    return drives[0].load() if len(drives) == 1 else pool_specs(drives, backend=B).psog()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from place3d_app.cli import main

    root = tmp_path_factory.mktemp("optnorm")
    printed = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PLACE3D_CACHE", str(root / "cache"))
        for name, extra in RUNS.items():
            buf = io.StringIO()
            with contextlib.redirect_stdout(buf):
                assert main(["optimize", *TINY, *extra, "--output", str(root / name)]) == 0, name
            printed[name] = buf.getvalue()
    return root, printed


def test_optimize_defaults_to_uncertain_and_evaluate_keeps_paper():
    from place3d_app.cli import build_parser
    from place3d_app.commands.optimize import DEFAULT_NORMALISATION

    assert DEFAULT_NORMALISATION == "uncertain"
    p = build_parser()
    assert p.parse_args(["optimize"]).normalisation == "uncertain"
    assert p.parse_args(["evaluate"]).normalisation == "paper"
    # reproduce scores the paper's study with the paper's definition: it has no such option
    assert not hasattr(p.parse_args(["reproduce"]), "normalisation")


@pytest.mark.parametrize("name, normalisation", [("default", "uncertain"), ("pose_cache", "uncertain"),
                                                 ("paper", "paper")])
def test_each_path_scores_with_its_normalisation(runs, monkeypatch, name, normalisation):
    root, printed = runs
    monkeypatch.setenv("PLACE3D_CACHE", str(root / "cache"))
    r = json.loads((root / name / "result.json").read_text())
    assert r["normalisation"] == normalisation and r["diagnostics"]["normalisation"] == normalisation
    assert f"best M-SOG (seg, {normalisation} normalisation)" in printed[name]
    assert f"--normalisation {normalisation}" in (root / name / "optimized-seg.toml").read_text()
    psog = _psog(RUNS[name])
    lidar = LidarModel.load("place3d_16ch")
    best = np.array(r["best_placement"])

    def score(poses, n=normalisation, p=psog):
        return float(msog_batch(p, lidar, poses[None], backend=B, normalisation=n)[0])

    assert r["best_score"] == score(best)
    other = "paper" if normalisation != "paper" else "uncertain"
    assert r["best_score"] != score(best, other)          # the test tells the normalisations apart
    assert r["baseline_scores"] and all(v == score(Placement.load(k).poses) for k, v in r["baseline_scores"].items())
    assert len(set(r["baseline_scores"].values())) > 1       # the objective tells rigs apart (not flat)
    if name == "default":
        # held-out re-scoring under the run's normalisation
        from place3d_app.commands.optimize import holdout_specs
        from place3d_app.commands.routes import drive_specs
        from place3d_kernels.spec import specs_from_args

        args = _args(RUNS[name])
        spec = specs_from_args(args)
        args.drives = drive_specs(args, spec)
        ((_, seeds, (held,)),) = holdout_specs(args, spec)
        (h,) = r["holdout"]
        assert seeds == [5] and h["seeds"] == [5]
        assert h["best"] == score(best, p=held.load())
        assert h["baselines"]["center"] == score(Placement.load("center").poses, p=held.load())
        assert r["intervals"]["best"]["score"] == r["best_score"]


def test_a_paper_checkpoint_is_not_resumed_as_uncertain(runs, tmp_path, capsys):
    """A checkpoint written by a paper run (its manifest, like every one from before the switch, records no
    normalisation) is refused by a run of the default normalisation, and resumes with --normalisation paper."""
    from place3d_app.cli import main

    root, _ = runs
    out = tmp_path / "paper"
    shutil.copytree(root / "paper", out)
    manifest = json.loads((out / "checkpoint.ckpt.manifest.json").read_text())
    assert "normalisation" not in manifest["spec"]          # as a checkpoint of an earlier version
    base = ["optimize", *TINY, "--routes", "1", "--no-holdout", "--interval", "none", "--output", str(out)]
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PLACE3D_CACHE", str(root / "cache"))
        capsys.readouterr()
        assert main(base + ["--resume"]) == 2
        err = capsys.readouterr().err
        assert "searched with --normalisation paper" in err and "this one searches with uncertain" in err
        assert "add --normalisation paper to resume it" in err and len(err.strip().splitlines()) == 1
        assert main(base) == 2                               # a fresh run into its folder: refused too
        assert "add --normalisation paper to continue that run" in capsys.readouterr().err
        before = json.loads((out / "result.json").read_text())
        assert main(base + ["--normalisation", "paper", "--resume"]) == 0
        after = json.loads((out / "result.json").read_text())
        assert after["best_score"] == before["best_score"] and after["evaluations"] == before["evaluations"]
        assert after["details"]["resumed"] is True
        # --overwrite discards it and starts afresh with the default
        assert main(base + ["--overwrite"]) == 0
        assert json.loads((out / "result.json").read_text())["normalisation"] == "uncertain"
        assert json.loads((out / "checkpoint.ckpt.manifest.json").read_text())["spec"]["normalisation"] == \
            "uncertain"


def test_process_executor_scores_with_the_normalisation():
    """``DistributedObjective``'s tasks carry the normalisation to worker processes (the Ray tasks run the
    same ``_score_task``)."""
    from place3d_app.executors import DistributedObjective, ProcessExecutor
    from place3d_kernels.optimize import SearchSpace
    from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec

    spec = PSOGSpec(SceneSpec("town", 0, 4), B, RoiSpec(0.8), frames_per_subset=2).resolved()
    psog = spec.load()                                   # the workers read the cache this fills
    space = SearchSpace(n_lidars=2)
    X = np.random.default_rng(1).uniform(space.lower, space.upper, (6, space.dim))
    lidar = LidarModel.load("place3d_16ch")
    ex = ProcessExecutor(1, backend=B)
    try:
        for n in ("uncertain", "paper"):
            obj = DistributedObjective(spec, "place3d_16ch", space, ex, backend=B, normalisation=n, n_chunks=2)
            np.testing.assert_array_equal(obj(X), msog_batch(psog, lidar, space.to_poses(X), backend=B,
                                                             normalisation=n))
    finally:
        ex.shutdown()
    with pytest.raises(ValueError, match="normalisation must be one of"):
        DistributedObjective(spec, "place3d_16ch", space, ex, normalisation="per-ray")


def test_uncertain_on_two_subsets_is_flat_and_the_command_says_so(capsys):
    """With T = 2 subsets every voxel with entropy has H = ln 2: uncertain scores every rig alike, so the
    search has nothing to follow; the command warns (the tiny drives of the tests above are such P-SOGs)."""
    from place3d_app.commands.common import flat_objective, warn_flat_objective
    from place3d_kernels.optimize import SearchSpace
    from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec

    two = PSOGSpec(SceneSpec("town", 0, 8), B, RoiSpec(0.8)).resolved().load()
    assert two.n_subsets == 2
    space = SearchSpace(n_lidars=2)
    X = np.random.default_rng(2).uniform(space.lower, space.upper, (5, space.dim))
    poses = space.to_poses(X)
    lidar = LidarModel.load("place3d_16ch")
    flat = msog_batch(two, lidar, poses, backend=B, normalisation="uncertain")
    assert np.all(flat == flat[0]) and flat[0] == pytest.approx(-np.log(2), abs=1e-9)
    assert len(set(msog_batch(two, lidar, poses, backend=B).tolist())) > 1        # paper still ranks them
    assert "T = 2 subsets" in flat_objective(two, "uncertain")
    assert flat_objective(two, "paper") is None and flat_objective(two, "evidence") is None
    three = PSOGSpec(SceneSpec("town", 0, 12), B, RoiSpec(0.8)).resolved().load()
    assert three.n_subsets == 3 and flat_objective(three, "uncertain") is None
    capsys.readouterr()
    warn_flat_objective(two, "uncertain")
    err = capsys.readouterr().err
    assert err.startswith("place3d: warning: --normalisation uncertain on a P-SOG of T = 2 subsets")
    assert "--normalisation paper" in err and len(err.strip().splitlines()) == 1


def test_held_out_pool_made_during_the_search_scores_as_after_it(tmp_path, monkeypatch):
    """The held-out P-SOG pooled from two drives is made on a thread while the search runs (``held_out_ahead``,
    hosts of 4+ cores or PLACE3D_JACKKNIFE_PREFETCH=1), with its grids or without them (made in the held-out
    check, as on a GPU: ``grids_beside_search``), or after the search (=0): the same held-out scores every way,
    each ``msog_batch`` of the rig on that pool under the run's normalisation."""
    import place3d_app.commands.optimize as opt
    from place3d_app.cli import main
    from place3d_app.commands.optimize import holdout_specs
    from place3d_app.commands.routes import drive_specs
    from place3d_kernels.pooled import pool_specs
    from place3d_kernels.spec import specs_from_args

    extra = ["--routes", "2", "--holdout-seeds", "5,6", "--interval", "none"]
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    asked = []
    real = opt.held_out_psogs

    def held_out_psogs(*a, **k):
        asked.append(k.get("grids", False))
        yield from real(*a, **k)

    monkeypatch.setattr(opt, "held_out_psogs", held_out_psogs)
    got = {}
    for ahead, grids in (("1", True), ("1", False), ("0", None)):
        monkeypatch.setenv("PLACE3D_JACKKNIFE_PREFETCH", ahead)
        monkeypatch.setattr(opt, "grids_beside_search", lambda b, grids=grids: grids)
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["optimize", *TINY, *extra, "--output", str(tmp_path / f"{ahead}{grids}")]) == 0
        got[ahead, grids] = json.loads((tmp_path / f"{ahead}{grids}" / "result.json").read_text())
    assert asked == [True, False, False]        # the thread's with and without grids, then the check's own
    assert got["1", True]["holdout"] == got["1", False]["holdout"] == got["0", None]["holdout"]
    assert got["1", True]["best_placement"] == got["1", False]["best_placement"] == got["0", None]["best_placement"]
    args = _args(extra)
    spec = specs_from_args(args)
    args.drives = drive_specs(args, spec)
    ((_, seeds, drives),) = holdout_specs(args, spec)
    held = pool_specs(drives, backend=B).psog()
    (h,) = got["1", True]["holdout"]
    lidar = LidarModel.load("place3d_16ch")
    assert seeds == [5, 6] and h["seeds"] == [5, 6]
    for name, poses in [("best", np.array(got["1", True]["best_placement"])),
                        *((n, Placement.load(n).poses) for n in ("center", "line"))]:
        want = float(msog_batch(held, lidar, poses[None], backend=B, normalisation="uncertain")[0])
        assert (h["best"] if name == "best" else h["baselines"][name]) == want, name


def test_jackknife_tables_made_during_the_search_give_the_same_intervals(tmp_path, monkeypatch):
    """The jackknife's index tables of the pooled routes (``LeftOutRows.batch``) are made on a thread while the
    search runs (``left_out_rows_ahead``, hosts of 4+ cores or PLACE3D_JACKKNIFE_PREFETCH=1), once, and the
    jackknife takes them; with =0 the jackknife makes them itself. The intervals are the same either way."""
    import threading

    from place3d_app.cli import main
    from place3d_kernels.left_out import LeftOutRows

    made = []
    real = LeftOutRows.batch

    def batch(self):
        if self._batch is None:
            made.append(threading.current_thread().name)
        return real(self)

    monkeypatch.setattr(LeftOutRows, "batch", batch)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    got = {}
    for ahead in ("1", "0"):
        monkeypatch.setenv("PLACE3D_JACKKNIFE_PREFETCH", ahead)
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["optimize", *TINY, "--routes", "3", "--no-holdout", "--interval", "jackknife",
                         "--output", str(tmp_path / ahead)]) == 0
        got[ahead] = json.loads((tmp_path / ahead / "result.json").read_text())
    from place3d_kernels.backends.registry import get_backend
    from place3d_kernels.left_out import index_tables_used

    if index_tables_used(LidarModel.load("place3d_16ch"), "sog", "uncertain", get_backend(B)):
        assert made == ["place3d-left-out-rows", "MainThread"]  # once a run: on the thread, then in the jackknife
    else:
        assert made == []                   # a jackknife that reads no tables: none made, on no thread
    assert got["1"]["intervals"] == got["0"]["intervals"] and got["1"]["intervals"] is not None
    assert got["1"]["best_placement"] == got["0"]["best_placement"]


def test_held_out_thread_starts_after_the_baselines(tmp_path, monkeypatch):
    """The held-out P-SOGs' thread (``held_out_ahead``) starts once the baselines are scored (the first
    ``msog_batch`` of the command), not beside that call; the search's first score comes after both."""
    import place3d_app.commands.optimize as opt
    import place3d_kernels.metrics as metrics
    from place3d_app.cli import main

    order = []
    real_ahead, real_batch = opt.held_out_ahead, metrics.msog_batch

    def held_out_ahead(*a, **k):
        order.append("held-out thread")
        return real_ahead(*a, **k)

    def msog_batch(psog, lidar, poses, *a, **k):
        order.append(f"score {len(poses)}")
        return real_batch(psog, lidar, poses, *a, **k)

    monkeypatch.setattr(opt, "held_out_ahead", held_out_ahead)
    monkeypatch.setattr(metrics, "msog_batch", msog_batch)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PLACE3D_JACKKNIFE_PREFETCH", "1")
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["optimize", *TINY, "--routes", "2", "--holdout-seeds", "5,6", "--interval", "none",
                     "--output", str(tmp_path / "out")]) == 0
    baselines = f"score {len(PAPER_PLACEMENTS)}"
    assert order[:2] == [baselines, "held-out thread"], order[:3]
    assert order[2].startswith("score ")                # the search's first generation


def test_held_out_grids_beside_the_search_off_the_gpu_only():
    """The held-out grids are made beside the search where the backend makes grids on this process's threads
    (the reference, Warp's CPU, an OpenCL CPU device), not where it makes them on a GPU's queue."""
    from place3d_app.commands.optimize import grids_beside_search
    from place3d_kernels.backends.registry import get_backend

    names = [n for n in available_backends() if n in ("reference", "warp:cpu", "opencl:pocl")
             or n.startswith("warp:cuda")]
    assert "reference" in names
    for n in names:
        b = get_backend(n)
        assert grids_beside_search(b) is (not n.startswith("warp:cuda")), n


@pytest.mark.parametrize("ahead", ["1", "0"])
def test_a_held_out_failure_is_the_commands_error_either_way(tmp_path, monkeypatch, capsys, ahead):
    """An error making the held-out P-SOGs, on the search's thread (``held_out_ahead``) or after the search,
    ends the command as the same one-line error (exit 2), after the search's report."""
    import place3d_app.commands.optimize as opt
    from place3d_app.cli import main

    def broken(*a, **k):
        raise ValueError("held-out drive unreadable")
        yield                                             # a generator, as held_out_psogs

    monkeypatch.setattr(opt, "held_out_psogs", broken)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PLACE3D_JACKKNIFE_PREFETCH", ahead)
    code = main(["optimize", *TINY, "--routes", "2", "--holdout-seeds", "5,6", "--interval", "none",
                 "--output", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    assert code == 2 and "held-out drive unreadable" in err and "best M-SOG" in out
