"""Issue 13 item 4: the optimiser must not game M-SOG by rolling beams into empty air.

A synthetic P-SOG carries entropy only in its ground layer; everything above it was never occupied
(H = 0). LiDARs whose beams all point down see only ground and the air on the way to it; rolling them to
the bound tilts half their beams upwards, through empty voxels up to the grid's top. Under the paper's
normalisation (divide by N_L) those free voxels raise the score, so the roll bound wins; the diagnostics
must show its bound variables and its low entropy share, and the "evidence" / "uncertain" normalisations
must not reward it. Whether a winner holds is decided on held-out P-SOGs (``holdout`` / ``transfer``,
issue 34 item 4).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.classes import CLASS_ID
from place3d_kernels.metrics import coverage_counts, covered_voxels, msog_batch, msog_from_voxels
from place3d_kernels.optimize import SearchSpace, optimize
from place3d_kernels.optimize.diagnostics import bound_variables, diagnose, format_holdout, holdout, transfer

ROAD = CLASS_ID["road"]
GRID = p3k.Grid(lower=(-8, -8, 0), upper=(8, 8, 4), voxel_size=0.5)
# all beams point down (-0.5 ... -0.2 rad): at roll 0 every ray ends on the ground
LIDAR = p3k.LidarModel(elevations=[-0.5, -0.35, -0.2], azimuths=np.linspace(0, 2 * np.pi, 72, endpoint=False),
                       max_range=40.0)
# two LiDARs at fixed positions; only their rolls vary, in the paper's box [-0.3, 0.3] rad
SPACE = SearchSpace(2, variables=("roll",), fixed={"x": [-0.5, 0.5], "y": 0.0, "z": 2.0})
LEVEL = SPACE.to_poses(np.array([0.0, 0.0]))


@pytest.fixture(scope="module")
def psog():
    probs = np.zeros(GRID.shape + (22,))
    probs[..., 0] = 1.0
    # ground layer: seen occupied in half the subsets -> H = ln 2, occupancy 0.5 stops "sog" rays
    probs[:, :, 0, 0] = 0.5
    probs[:, :, 0, ROAD] = 0.5
    return p3k.PSOG.from_probabilities(GRID, probs)


def _score(normalisation, psog, backend="reference"):
    return lambda X: msog_batch(psog, LIDAR, SPACE.to_poses(X), backend=backend, normalisation=normalisation)


def test_bound_hugging_rig_wins_under_paper_and_shows_in_the_diagnostics(psog):
    res = optimize(_score("paper", psog), SPACE, method="grid", max_evals=100, progress=False)
    rolls = res.best_vector
    assert np.allclose(np.abs(rolls), 0.3), f"expected both rolls on the bound, got {rolls}"
    level = msog_batch(psog, LIDAR, LEVEL[None])[0]
    assert res.best_score > level
    d = diagnose(psog, LIDAR, res.search_space, res.best_placement.poses, {"level": LEVEL}, delta=0.1)
    assert d["n_on_bounds"] == 2 and d["summary"].startswith("2 of 2 variables on a bound") and all("bound" in s for s in d["on_bounds"])
    assert d["on_bounds"][0].startswith("lidar0.roll = ")
    assert d["best"]["entropy_share"] < 0.8 * d["baselines"]["level"]["entropy_share"]


@pytest.mark.parametrize("normalisation", ["evidence", "uncertain"])
def test_alternative_normalisation_does_not_reward_air(psog, normalisation):
    X = SPACE.grid_values(np.array([[k, j] for k in range(-3, 4) for j in range(-3, 4)]), 0.1)
    s = _score(normalisation, psog)(X)
    level = s[np.flatnonzero(np.all(X == 0, axis=1))[0]]
    rolled = s[np.flatnonzero(np.all(np.abs(X) > 0.29, axis=1))]
    # every ground voxel has the same entropy: the mean over evidence is ln 2 whatever the roll
    assert np.all(rolled <= level + 1e-12), (rolled, level)
    assert level == pytest.approx(-np.log(2), abs=1e-9)
    paper = _score("paper", psog)(X)
    assert paper[np.flatnonzero(np.all(np.abs(X) > 0.29, axis=1))].max() > paper[np.all(X == 0, axis=1)][0]


def test_a_level_rig_has_nothing_on_a_bound(psog):
    d = diagnose(psog, LIDAR, SPACE, LEVEL, {"level": LEVEL}, delta=0.1)
    assert d["on_bounds"] == [] and d["summary"].startswith("0 of 2 variables on a bound")


def test_bound_variables_names_and_grid_edges():
    s = SearchSpace(1, bounds={"roll": (-0.35, 0.3)})
    # -0.35 is no multiple of 0.1: the outermost grid value -0.3 counts as the lower bound
    x = s.from_poses(np.array([[[0.6, 0.0, 2.5, -0.3, 0, 0]]]))[0]
    got = bound_variables(s, x, delta=0.1)
    assert got == ["lidar0.x = +0.6 (upper bound)", "lidar0.roll = -0.3 (lower bound)"]
    assert bound_variables(s, x) == ["lidar0.x = +0.6 (upper bound)"]


def test_counts_exact_across_backends(psog, backend):
    poses = SPACE.to_poses(np.array([[0.0, 0.0], [0.3, -0.3], [-0.1, 0.2]]))
    ref = coverage_counts(psog, LIDAR, poses, backend="reference")
    got = coverage_counts(psog, LIDAR, poses, backend=backend)
    for k in ref:
        assert np.array_equal(ref[k], got[k]), k
    for n in ("paper", "evidence", "uncertain"):
        a = msog_batch(psog, LIDAR, poses, backend="reference", normalisation=n)
        b = msog_batch(psog, LIDAR, poses, backend=backend, normalisation=n)
        assert np.array_equal(a, b), n


def test_default_msog_is_the_paper_definition_bit_for_bit(psog, backend):
    poses = SPACE.to_poses(np.array([[0.0, 0.0], [0.3, -0.3]]))
    default = msog_batch(psog, LIDAR, poses, backend=backend)
    assert np.array_equal(default, msog_batch(psog, LIDAR, poses, backend=backend, normalisation="paper"))
    for i in range(len(poses)):
        vox = covered_voxels(psog, LIDAR, poses[i], backend=backend)
        assert default[i] == msog_from_voxels(psog, vox)     # exact: same integer sum, same N_L
        w = psog.weights
        assert default[i] == -(float(w[vox].sum(dtype=np.int64)) / p3k.backends.base.ENTROPY_SCALE) / len(vox)


# sensors msog_batch scores by explicit rays (issue 34 item 4: optimize's default must take every sensor)
OFFSET = p3k.LidarModel(elevations=[-0.5, -0.35, -0.2], azimuths=np.linspace(0, 2 * np.pi, 36, endpoint=False),
                        max_range=40.0, azimuth_offsets=[0.0, 0.03, -0.02], min_range=0.6, name="offset")
NEAR = p3k.LidarModel(elevations=[-0.5, -0.35, -0.2], azimuths=np.linspace(0, 2 * np.pi, 36, endpoint=False),
                      max_range=40.0, min_range=0.6, name="near")


@pytest.fixture(scope="module")
def mixed():
    """The ground of ``psog`` with a strip that is road in every subset (stored, H = 0): there the three
    denominators differ (N_L > evidence > uncertain)."""
    probs = np.zeros(GRID.shape + (22,))
    probs[..., 0] = 1.0
    probs[:, :, 0, 0] = 0.5
    probs[:, :, 0, ROAD] = 0.5
    probs[:, 20:, 0, 0] = 0.0
    probs[:, 20:, 0, ROAD] = 1.0
    return p3k.PSOG.from_probabilities(GRID, probs)


@pytest.mark.parametrize("normalisation", ["paper", "evidence", "uncertain"])
def test_ray_sensors_take_every_normalisation(mixed, backend, normalisation):
    from place3d_kernels.metrics import coverage_counts, indicator_weights, score_from_counts
    from place3d_kernels.ops import coverage
    from place3d_kernels.rig_metrics import rigs_rays
    from place3d_kernels.vehicle import VehicleBody

    # a box under the rig: some downward rays end on it instead of the ground
    box = VehicleBody.from_boxes([[[-1.0, -1.0, 0.0], [1.0, 1.0, 1.5]]], "box")
    poses = SPACE.to_poses(np.array([[0.0, 0.0], [0.3, -0.2]]))
    w = mixed.weights
    den = np.ones_like(w) if normalisation == "paper" else indicator_weights(mixed, normalisation)
    scores = {}
    for lidar, body in ((OFFSET, None), (NEAR, None), (NEAR, box)):
        got = msog_batch(mixed, lidar, poses, backend=backend, normalisation=normalisation, body=body)
        # by hand: the covered voxels of the rays msog_batch builds (min range, offsets, body), summed in NumPy
        o, d, te, off, _ = rigs_rays([([lidar] * 2, rig) for rig in poses], body, "reference")
        want = []
        for i in range(len(poses)):
            s = slice(off[i], off[i + 1])
            m = coverage(GRID, o[s], d[s], te[s], backend="reference", stop=mixed.stop_mask).reshape(-1)
            want.append(-(float(w[m].sum(dtype=np.int64)) / p3k.backends.base.ENTROPY_SCALE)
                        / int(den[m].sum(dtype=np.int64)))
        assert got.tolist() == want, (lidar.name, body)
        # the diagnostics and the held-out ranks count the same rays (optimize.diagnostics)
        c = coverage_counts(mixed, lidar, poses, backend=backend, body=body)
        assert np.array_equal(score_from_counts(c, normalisation), got)
        scores[lidar.name, body is None] = c["n_covered"]
    assert np.all(scores["near", False] < scores["near", True])        # the box ends rays early
    # the three denominators differ on this P-SOG: the test tells them apart
    others = {n: msog_batch(mixed, OFFSET, poses, normalisation=n) for n in ("paper", "evidence", "uncertain")}
    assert len({tuple(v) for v in others.values()}) == 3


def test_unknown_normalisation_is_refused(psog):
    with pytest.raises(ValueError, match="normalisation must be one of"):
        msog_batch(psog, LIDAR, LEVEL[None], normalisation="per-ray")


def test_holdout_rows_rank_the_winner(psog):
    rolled = SPACE.to_poses(np.array([0.3, -0.3]))
    half = SPACE.to_poses(np.array([0.1, -0.1]))
    base = {"level": LEVEL, "half": half}
    rows = holdout([("synthetic", [1, 2], psog)], LIDAR, rolled, base)
    (r,) = rows
    assert r["scene"] == "synthetic" and r["seeds"] == [1, 2] and r["n_rigs"] == 3
    # paper: the rolled rig's air voxels win; uncertain: every rig sees the same ground entropy (ln 2), a
    # tie: it shares rank 1 (ranks count strictly better rigs) but beats nothing
    assert r["rank"] == 1 and r["beats_all_baselines"] and r["ranks"]["paper"] == 1
    (t,) = holdout([("synthetic", [1, 2], psog)], LIDAR, rolled, base, normalisation="uncertain")
    assert t["rank"] == 1 and not t["beats_all_baselines"] and transfer([t])["transfers"] is False
    paper = [r["best"], *r["baselines"].values()]
    assert r["rank"] == 1 + sum(v > r["best"] for v in paper[1:])
    rows_u = holdout([("synthetic", [1], psog)], LIDAR, LEVEL, {"rolled": rolled, "half": half})
    # the level rig is last under the paper's normalisation: the others add free air voxels
    assert rows_u[0]["ranks"]["paper"] == 3 and rows_u[0]["rank"] == 3 and not rows_u[0]["beats_all_baselines"]


def test_transfer_verdict_needs_first_place_on_every_held_out_psog():
    def row(scene, rank, seeds=(100, 101, 102)):
        return {"scene": scene, "seeds": list(seeds), "rank": rank, "n_rigs": 9, "best": -0.04,
                "baselines": {"center": -0.041 if rank == 1 else -0.039}, "beats_all_baselines": rank == 1}
    ok = transfer([row("Town01", 1), row("Town03", 1)])
    assert ok["transfers"] is True and ok["worst_rank"] == 1 and "first of 9" in ok["reason"]
    bad = transfer([row("Town01", 1), row("opendrive:/maps/Town06.xodr", 12, (100,))])
    assert bad["transfers"] is False and bad["worst_rank"] == 12 and bad["ranks"] == [1, 12]
    assert "Town06 route 100 12 of 9" in bad["reason"] and "Town01 routes 100-102 1 of 9" in bad["reason"]
    assert transfer([])["transfers"] is None
    lines = format_holdout([row("Town06", 12, (100,))])
    assert lines[0].startswith("held out Town06 route 100: optimised") and lines[-1].startswith("DOES NOT TRANSFER")


def test_cli_writes_diagnostics_and_holdout(tmp_path, capsys):
    from place3d_kernels.backends.registry import backend_report
    from place3d_app.cli import main

    # the fastest CPU backend present builds the two tiny P-SOGs (the backends agree bit for bit)
    have = {name for name, ok, _ in backend_report() if ok}
    b = "opencl:pocl" if "opencl:pocl" in have else "reference"
    out = tmp_path / "run"
    assert main(["optimize", "--frames", "8", "--voxel-size", "0.8", "--max-evals", "24", "--quiet", "--routes", "1", "--backend", b,
                 "--holdout-seeds", "1", "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "diagnostics: N_L" in printed and "held out town route 1: optimised" in printed
    assert "TRANSFERS: first of" in printed or "DOES NOT TRANSFER: not above every baseline" in printed
    r = json.loads((out / "result.json").read_text())
    assert r["normalisation"] == "uncertain"                # optimize's default since issue 34, item 4
    assert set(r["diagnostics"]) >= {"on_bounds", "summary", "best", "baselines"}
    assert r["diagnostics"]["best"]["n_covered"] > 0
    (h,) = r["holdout"]
    assert h["scene"] == "town" and h["seeds"] == [1] and 1 <= h["rank"] <= h["n_rigs"] == 1 + len(r["baseline_scores"])
    assert set(h["baselines"]) == set(r["baseline_scores"])
    assert r["details"]["holdout"] == r["holdout"]
    # transfers: strictly above every baseline (a tie shares rank 1 and beats nothing)
    assert r["transfer"]["ranks"] == [h["rank"]] and r["transfer"]["transfers"] == h["beats_all_baselines"]
    assert h["beats_all_baselines"] == all(v < h["best"] for v in h["baselines"].values())


def test_default_holdout_pools_unseen_routes_and_can_be_skipped():
    import argparse

    from place3d_app.commands.optimize import HOLDOUT_SEED, holdout_specs
    from place3d_kernels.spec import PSOGSpec, SceneSpec

    spec = PSOGSpec(SceneSpec("town", 0, 8))
    drives = [PSOGSpec(SceneSpec("town", s, 8)) for s in (0, 1, 2)]
    args = argparse.Namespace(holdout_seeds=None, holdout_scenes=None, no_holdout=False, drives=drives)
    ((name, seeds, specs),) = holdout_specs(args, spec)
    assert name == "town" and seeds == [HOLDOUT_SEED, HOLDOUT_SEED + 1, HOLDOUT_SEED + 2]
    assert [s.scene.seed for s in specs] == seeds
    args.no_holdout = True
    assert holdout_specs(args, spec) == []
    args.holdout_seeds = "100"
    with pytest.raises(ValueError, match="--no-holdout with --holdout-seeds"):
        holdout_specs(args, spec)
    args.no_holdout, args.holdout_seeds = False, "1-3"
    with pytest.raises(ValueError, match="seed 1 is one the search pooled"):
        holdout_specs(args, spec)
