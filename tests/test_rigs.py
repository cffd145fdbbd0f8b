"""Real rigs (issue 16): M-SOG of non-grid models, min range and a body; mounting surfaces; heterogeneous
rig batches; the rig search (enumerated and integer); prices and Pareto fronts; the CLI's outputs and its
refusals of bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels import rig_metrics as rm
from place3d_kernels.lidar import LidarModel
from place3d_kernels.mounting import SURFACE_NAMES, surfaces_for
from place3d_kernels.optimize.rig_search import RigProblem, search_rigs
from place3d_kernels.pricing import check_prices, load_prices, pareto_front
from place3d_kernels.scan_patterns import RosettePattern
from place3d_kernels.vehicle import PRESETS, VehicleBody

REF = p3k.get_backend("reference")
GRID = p3k.Grid(lower=(-10, -10, -1), upper=(10, 10, 5), voxel_size=0.25)
AZ = np.linspace(0, 2 * np.pi, 60, endpoint=False) + 0.01
GRID_M = LidarModel(np.radians(np.linspace(-31.0, 9.0, 7)), AZ, max_range=12.0, name="grid")
OFFSET_M = LidarModel(np.radians([-25.0, -12.0, -3.0, 4.0]), AZ[::2], max_range=9.0, name="offset",
                      azimuth_offsets=np.radians([0.0, 1.5, -2.0, 0.7]), min_range=0.4)
ROSETTE_M = LidarModel.rosette(RosettePattern(38.4, 4000.0, 0.1, (17.0, 11.0)), max_range=11.0, name="rose",
                               min_range=0.3)
CAR = VehicleBody.preset("car")


@pytest.fixture(scope="module")
def psog():
    rng = np.random.default_rng(3)
    n = GRID.n_voxels
    vox = np.sort(rng.choice(n, n // 5, replace=False))
    return p3k.PSOG(GRID, vox, rng.dirichlet(np.r_[6.0, np.full(21, 0.2)], len(vox)))


def _box_distance(body, p):
    lo, hi = body.boxes[:, 0], body.boxes[:, 1]
    gap = np.maximum(np.maximum(lo[None] - p[:, None], p[:, None] - hi[None]), 0.0)
    return np.sqrt((gap ** 2).sum(axis=2)).min(axis=1)


# ------------------------------------------------------------------------------------------ surfaces
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_surface_corners_lie_just_outside_the_body(preset):
    body = VehicleBody.preset(preset)
    names = [n for n in SURFACE_NAMES if n != "roof-box"]
    for name, s in surfaces_for(body, names).items():
        c = s.corners()
        assert not body.contains(c).any(), name
        dist = _box_distance(body, c)
        # w = 0 corners sit at the standoff, w = 1 corners at standoff + lift (to rounding)
        w0 = np.array([k % 2 == 0 for k in range(8)])
        np.testing.assert_allclose(dist[w0], s.standoff, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(dist[~w0], s.standoff + s.lift, atol=1e-9, err_msg=name)
        for key, (lo, hi) in s.orientation.items():
            assert lo <= s.nominal[key] <= hi and s.angle(key, 0.0) == lo and s.angle(key, 1.0) == hi
    sf = surfaces_for(body, ["front-bumper", "rear-bumper", "left-fender", "right-fender"])
    assert sf["front-bumper"].nominal["yaw"] == 0.0 and sf["rear-bumper"].nominal["yaw"] == pytest.approx(np.pi)
    assert sf["left-fender"].nominal["yaw"] == pytest.approx(np.pi / 2)


def test_roof_box_keeps_the_paper_bounds_and_bad_lists_are_refused():
    rb = surfaces_for(None, ["roof-box"])["roof-box"]
    c = rb.corners()
    np.testing.assert_allclose(c.min(0), [-0.6, -0.6, 2.2])
    np.testing.assert_allclose(c.max(0), [0.6, 0.6, 2.8])
    with pytest.raises(ValueError, match="empty"):
        surfaces_for(CAR, [])
    with pytest.raises(ValueError, match="'hood'"):
        surfaces_for(CAR, ["roof", "hood"])
    with pytest.raises(ValueError, match="need a vehicle body"):
        surfaces_for(None, ["roof"])


# ------------------------------------------------------------------------------------------ metric
def test_msog_accepts_offset_and_rosette_models_with_min_range(backend, psog):
    poses = np.array([[0.1, 0.05, 2.0, 0.0, 0.0, 0.3], [-0.4, 0.2, 2.2, 0.0, 0.1, 2.0]])
    for m in (OFFSET_M, ROSETTE_M):
        got = p3k.msog(psog, m, poses, backend=backend)
        # the same rays built by hand: origins moved min_range along each ray, lengths shortened by it
        o, d = rm.rig_rays(m.directions(), poses)
        s, n = rm.rig_sums(psog, o + m.min_range * d, d, np.full(len(o), m.max_range - m.min_range),
                           np.array([0, len(o)]), backend="reference")
        assert got == rm.msog_from_sums(s, n)[0]
        assert got == p3k.msog(psog, m, poses, backend="reference")
        # covered_voxels (coverage plots, the pose cache) walks the same rays
        assert p3k.metrics.msog_from_voxels(psog, p3k.covered_voxels(psog, m, poses, backend=backend)) == got
    from place3d_kernels.optimize import MSOGObjective, SearchSpace

    with pytest.raises(ValueError, match="minimum range"):          # its cache would ignore min_range
        MSOGObjective(psog, OFFSET_M, SearchSpace(n_lidars=2))
    # a grid model with no min range and no body keeps the fused kernel, and the ray path agrees with it
    fused = p3k.msog_batch(psog, GRID_M, poses[None], backend=backend)
    rays = rm.msog_rigs(psog, [([GRID_M] * 2, poses)], backend=backend).msog
    np.testing.assert_array_equal(fused, rays)


def test_min_range_drops_rays_the_body_blocks_before_it(psog):
    # a LiDAR 0.3 m above a plate with min range 0.5: every downward ray is blocked before it starts
    plate = VehicleBody.from_boxes([[[-3, -3, 1.5], [3, 3, 1.7]]], "plate")
    m = LidarModel(np.radians([-70.0, -40.0, 10.0]), AZ, max_range=8.0, min_range=0.5)
    pose = np.array([[0.0, 0.0, 2.0, 0, 0, 0]])
    o, d, te, off, reasons = rm.rigs_rays([([m], pose)], plate, "reference")
    assert reasons == [""] and off.tolist() == [0, len(AZ)]         # only the upward channel is left
    assert np.all(d[:, 2] > 0) and np.allclose(te, 7.5)
    got = p3k.msog(psog, m, pose, body=plate, backend="reference")
    up = LidarModel(np.radians([10.0]), AZ, max_range=8.0, min_range=0.5)
    assert got == p3k.msog(psog, up, pose, backend="reference")
    with pytest.raises(ValueError, match="inside"):
        p3k.msog(psog, m, np.array([[0.0, 0.0, 1.6, 0, 0, 0]]), body=plate)


def test_heterogeneous_batch_equals_each_rig_alone(backend, psog):
    rng = np.random.default_rng(5)
    models = [GRID_M, OFFSET_M, ROSETTE_M]
    rigs = []
    for size in (1, 3, 2, 4):
        idx = rng.integers(0, 3, size)
        poses = np.c_[rng.uniform(-0.5, 0.5, (size, 2)), rng.uniform(1.6, 2.3, size), rng.uniform(-0.2, 0.2, (size, 3))]
        rigs.append(([models[i] for i in idx], poses))
    rigs.append(([GRID_M], np.array([[0.5, 0.0, 1.2, 0, 0, 0]])))          # inside the car: infeasible
    batch = rm.msog_rigs(psog, rigs, CAR, backend=backend)
    assert batch.feasible.tolist() == [True] * 4 + [False] and np.isnan(batch.msog[-1])
    for k, rig in enumerate(rigs[:-1]):
        alone = rm.msog_rigs(psog, [rig], CAR, backend="reference")
        assert batch.sums[k] == alone.sums[0] and batch.counts[k] == alone.counts[0]
        assert batch.msog[k] == alone.msog[0]
    # one model per rig: the same number as msog with a body
    same = ([OFFSET_M] * 2, rigs[2][1])
    assert rm.msog_rigs(psog, [same], CAR, backend=backend).msog[0] == p3k.msog(psog, OFFSET_M, same[1], body=CAR,
                                                                                 backend="reference")


# ------------------------------------------------------------------------------------------ search
def test_search_enumerates_small_and_uses_integer_genes_for_large(psog):
    surf = surfaces_for(CAR, ["roof", "front-bumper"])
    small = RigProblem(psog, {"grid": GRID_M, "offset": OFFSET_M}, surf, 2, ("x", "y", "yaw"), CAR, backend="reference")
    r = search_rigs(small, max_evals=12, seed=1)
    assert r.mode == "enumerate" and len(r.per_combination) == 3 and r.launches >= 1
    assert r.evaluations >= 12
    for c in r.per_combination:
        assert sorted(c.sensors) in (["grid", "grid"], ["grid", "offset"], ["offset", "offset"])
        assert set(c.surfaces) <= {"roof", "front-bumper"}
        again = rm.msog_rigs(psog, [([small.sensors[s] for s in c.sensors], c.poses)], CAR, backend="reference")
        assert again.msog[0] == c.msog
    assert r.best.msog == max(c.msog for c in r.per_combination)
    many = {f"m{i}": GRID_M.subsample(1, i + 1) for i in range(5)}       # C(9, 5) = 126 multisets > 64
    big = RigProblem(psog, many, surf, 5, ("x", "yaw"), CAR, backend="reference")
    r = search_rigs(big, max_evals=16, seed=0)
    assert r.mode == "integer" and np.isfinite(r.best.msog) and len(r.best.sensors) == 5
    assert set(r.best.sensors) <= set(many)


@pytest.mark.parametrize("normalisation", ["evidence", "uncertain"])
def test_search_scores_with_its_normalisation(psog, normalisation):
    """optimize's default normalisation (uncertain) reaches the real-rig search: every rig it reports
    carries the score of that denominator, not the paper's (issue 34, item 4)."""
    surf = surfaces_for(CAR, ["roof", "front-bumper"])
    prob = RigProblem(psog, {"grid": GRID_M, "offset": OFFSET_M}, surf, 2, ("x", "y", "yaw"), CAR,
                      backend="reference", normalisation=normalisation)
    r = search_rigs(prob, max_evals=12, seed=1)
    for c in r.per_combination:
        rig = [([prob.sensors[s] for s in c.sensors], c.poses)]
        assert rm.msog_rigs(psog, rig, CAR, backend="reference", normalisation=normalisation).msog[0] == c.msog
        assert rm.msog_rigs(psog, rig, CAR, backend="reference").msog[0] != c.msog
    # a one-model rig: the number msog_batch gives with the body
    same = ([OFFSET_M] * 2, r.per_combination[-1].poses)
    assert rm.msog_rigs(psog, [same], CAR, backend="reference", normalisation=normalisation).msog[0] == \
        p3k.msog(psog, OFFSET_M, same[1], body=CAR, backend="reference", normalisation=normalisation)
    with pytest.raises(ValueError, match="normalisation must be one of"):
        RigProblem(psog, {"grid": GRID_M}, surf, 1, ("x",), CAR, normalisation="per-ray")


def test_blind_spot_constraint_penalises_exactly_the_rigs_that_break_it(psog):
    from place3d_kernels.blindspot import max_blind_extent

    # 0.5 deg azimuth steps, so that every 1 deg sector of the blind-spot map can get a ground hit
    dense = LidarModel(np.radians(np.linspace(-31.0, 9.0, 5)), np.linspace(0, 2 * np.pi, 720, endpoint=False),
                       max_range=12.0, name="dense")
    surf = surfaces_for(CAR, ["front-bumper", "rear-bumper", "left-fender", "right-fender"])
    args = (psog, {"dense": dense}, surf, 4, ("x", "z", "pitch", "yaw"), CAR)
    free, tied = RigProblem(*args, backend="reference"), RigProblem(*args, backend="reference", max_blind_extent=3.0)
    around = tied.decode(tied.x0(False), ("dense",) * 4)[2]             # one unit on each side of the car
    front = around.copy()
    front[1] = around[0] + [0, 0.4, 0, 0, 0, 0]                         # two on the front bumper: rear is blind
    assert max_blind_extent(CAR, [dense] * 4, around) <= 3.0 < max_blind_extent(CAR, [dense] * 4, front)
    rigs = [(["dense"] * 4, around), (["dense"] * 4, front)]
    ms_free, f_free, _ = free.score(rigs)
    ms, f, reasons = tied.score(rigs)
    assert f[0] == f_free[0] and ms[0] == ms_free[0] and reasons[0] == ""
    assert np.isfinite(ms_free[1]) and np.isnan(ms[1]) and f[1] > 10.0 and "blind spot at z = 0 m" in reasons[1]


def test_pareto_front_is_non_dominated():
    rng = np.random.default_rng(9)
    s, c = rng.normal(size=60).round(1), rng.integers(1, 12, 60).astype(float)
    s[3] = np.nan
    f = pareto_front(s, c)
    assert 3 not in f and np.all(np.diff(c[f]) > 0) and np.all(np.diff(s[f]) > 0)
    for i in f:
        dominated = (s >= s[i]) & (c <= c[i]) & ((s > s[i]) | (c < c[i]))
        assert not dominated.any()
    for j in set(range(60)) - set(f.tolist()) - {3}:
        assert any((s[i] >= s[j]) and (c[i] <= c[j]) for i in f)


def test_price_table_names_missing_sensors(tmp_path):
    prices = load_prices()
    check_prices(prices, ["vlp16", "os1-64", "mid40"])
    bad = tmp_path / "p.toml"
    bad.write_text('[sensors.vlp16]\nprice_usd = 100\n')
    with pytest.raises(ValueError, match=r"\['os1-64'\]"):
        check_prices(load_prices(bad), ["vlp16", "os1-64"], bad)


# ------------------------------------------------------------------------------------------ CLI
# 12 frames: T = 3 subsets, where optimize's default (uncertain) is not the same for every rig
TINY = ["--frames", "12", "--voxel-size", "0.8", "--max-evals", "24", "--quiet", "--routes", "1",
        "--azimuth-step", "4"]
RIG = ["--n-lidars", "3", "--sensors", "vlp16,os1-64", "--surfaces", "roof,front-bumper", "--dofs",
       "x,y,z,pitch,yaw", "--vehicle", "car"]


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    from place3d_app.cli import main

    root = tmp_path_factory.mktemp("rigs")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PLACE3D_CACHE", str(root / "cache"))
        rc1 = main(["optimize", *RIG, *TINY, "--output", str(root / "best")])
        rc2 = main(["optimize", *RIG, *TINY, "--objective", "pareto", "--output", str(root / "pareto")])
    return root, rc1, rc2


def test_cli_writes_rig_outputs(cli_runs, monkeypatch):
    root, rc1, rc2 = cli_runs
    assert rc1 == 0 and rc2 == 0
    for d, extra in (("best", []), ("pareto", ["pareto.json", "pareto.png"])):
        names = sorted(p.name for p in (root / d).iterdir())
        assert names == sorted(["result.json", "rig.toml", "rig.png", "blindspot.png", *extra])
    res = json.loads((root / "best" / "result.json").read_text())
    assert res["normalisation"] == "uncertain"          # optimize's default (issue 34, item 4)
    # the winner's score is its uncertain M-SOG on the searched P-SOG (poses rounded to 1e-6 m in result.json)
    from place3d_app.cli import build_parser
    from place3d_app.commands.rig import check_rig_args
    from place3d_kernels.spec import specs_from_args

    monkeypatch.setenv("PLACE3D_CACHE", str(root / "cache"))
    args = build_parser().parse_args(["optimize", *RIG, *TINY])
    sensors = check_rig_args(args)["sensors"]
    rig = [([sensors[s] for s in res["best"]["sensors"]], np.array(res["best"]["poses"]))]
    psog = specs_from_args(args).load()
    score = {n: rm.msog_rigs(psog, rig, CAR, normalisation=n).msog[0] for n in ("paper", "uncertain")}
    assert res["best_msog"] == pytest.approx(score["uncertain"], rel=1e-4)
    assert res["best_msog"] != pytest.approx(score["paper"], rel=1e-2)
    assert len(res["best"]["sensors"]) == 3 and set(res["best"]["sensors"]) <= {"vlp16", "os1-64"}
    assert set(res["best"]["surfaces"]) <= {"roof", "front-bumper"} and res["vehicle"]["name"] == "car"
    assert res["best_msog"] == max(c["msog"] for c in res["per_combination"] if c["msog"] is not None)
    assert res["blind_spot"]["area_m2"] > 0 and res["best_cost_usd"] > 0
    pl = p3k.Placement.load(root / "best" / "rig.toml")
    np.testing.assert_allclose(pl.poses, res["best"]["poses"], atol=1e-6)
    assert not CAR.contains(pl.poses[:, :3]).any()
    front = json.loads((root / "pareto" / "pareto.json").read_text())
    pts = [(r["msog"], r["cost_usd"]) for r in front["all"] if r["msog"] is not None]
    assert {len(r["sensors"]) for r in front["all"]} == {1, 2, 3}
    for r in front["vs_cost"]:
        assert not any(s >= r["msog"] and c <= r["cost_usd"] and (s > r["msog"] or c < r["cost_usd"]) for s, c in pts)


@pytest.mark.parametrize("bad, message", [
    (["--sensors", "vlp16,vlp99"], "vlp99"),
    (["--surfaces", "roof-box", "--vehicle", "van"], "inside the vehicle body"),
    (["--surfaces", ""], "empty"),
    (["--n-lidars", "0"], "1-8"),
    (["--objective", "pareto", "--prices", "PRICES"], "os1-64"),
    (["--restarts", "1"], "--restarts not supported"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, bad, message):
    from place3d_app.cli import main

    prices = tmp_path / "prices.toml"
    prices.write_text('[sensors.vlp16]\nprice_usd = 3999\n')
    out = tmp_path / "out"
    args = ["optimize", *RIG, *TINY, "--output", str(out)]
    bad = [str(prices) if b == "PRICES" else b for b in bad]
    for k in range(0, len(bad), 2):              # later options override RIG's
        args += bad[k:k + 2]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()
