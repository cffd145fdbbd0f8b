"""Placement optimiser: search space, grid, constraints, CMA-ES runs, cache, checkpoints, certificate."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place3d_kernels.optimize import (Bounds, FixedHeight, FunctionConstraint, MinDistance, SearchSpace, certificate,
                                      load_checkpoint, optimize, total_penalty)
from place3d_kernels.placement import Placement

TARGET2 = np.array([0.3, -0.2, 2.5, 0.1, -0.4, 0.5, 2.3, -0.2])  # on the 0.1 grid, inside the paper box


def sphere(target):
    def f(X):
        return -np.sum((X - target) ** 2, axis=1)
    return f


class Recorder:
    """Objective wrapper that records every batch it is called with."""

    def __init__(self, fn):
        self.fn, self.batches = fn, []

    def __call__(self, X):
        self.batches.append(np.array(X, copy=True))
        return self.fn(X)

    @property
    def rows(self):
        return np.concatenate(self.batches) if self.batches else np.zeros((0, 0))


def on_grid(X, delta=0.1):
    k = X / delta
    return np.allclose(k, np.round(k), atol=1e-9)


# ----------------------------------------------------------------------------------------- search space
def test_space_layout_and_roundtrip():
    s = SearchSpace(4)
    assert s.dim == 16
    assert s.names[:5] == ("x[0]", "y[0]", "z[0]", "roll[0]", "x[1]")
    p = Placement.load("pyramid-roll")
    v = s.from_placement(p)
    assert v.shape == (16,)
    np.testing.assert_array_equal(v[:4], p.poses[0, :4])
    np.testing.assert_array_equal(s.to_placement(v, "r").poses, p.poses)
    X = np.stack([v, v + 0.01])
    poses = s.to_poses(X)
    assert poses.shape == (2, 4, 6)
    np.testing.assert_array_equal(s.from_poses(poses), X)
    np.testing.assert_array_equal(poses[:, :, 4:], 0.0)  # pitch, yaw fixed at 0
    assert s.to_poses(v).shape == (4, 6)
    assert SearchSpace.from_dict(s.to_dict()) == s


def test_space_shared_and_fixed():
    s = SearchSpace(3, variables=("x", "y", "z"), shared=("z",), fixed={"yaw": [0.0, 0.1, 0.2]})
    assert s.dim == 7 and s.names[-1] == "z"
    poses = s.to_poses(np.array([0, 0, 0.1, 0.1, 0.2, 0.2, 2.5]))
    np.testing.assert_array_equal(poses[:, 2], 2.5)
    np.testing.assert_array_equal(poses[:, 5], [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(poses[:, 3], 0.0)  # roll defaults to 0


@pytest.mark.parametrize("kwargs, match", [
    (dict(n_lidars=0), "n_lidars"),
    (dict(n_lidars=9), "n_lidars"),
    (dict(n_lidars=2.0), "n_lidars"),
    (dict(variables=("x", "height")), "Unknown variable 'height'"),
    (dict(bounds={"x": (0.5, -0.5)}), "inverted"),
    (dict(bounds={"x": (0.2, 0.2)}), "empty"),
    (dict(bounds={"q": (0, 1)}), "Unknown bounds key"),
    (dict(variables=("x", "y")), "'z' is neither a variable nor fixed"),
    (dict(fixed={"x": 0.0}), "both variables and fixed"),
    (dict(variables=("x", "y", "z", "yaw")), "needs bounds"),
    (dict(fixed={"yaw": [0, 1]}), "one per LiDAR"),
    (dict(variables=()), "at least one variable"),
])
def test_space_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SearchSpace(**kwargs)


def test_space_bad_vectors_and_grid():
    s = SearchSpace(2)
    with pytest.raises(ValueError, match="length 8"):
        s.to_poses(np.zeros((3, 7)))
    with pytest.raises(ValueError, match="no multiple of delta"):
        SearchSpace(1, bounds={"x": (0.01, 0.05)}).snap(np.zeros(4))
    with pytest.raises(ValueError, match="positive"):
        s.snap(np.zeros(8), delta=0)


def test_snap_grid_anchored_at_zero_inside_bounds():
    s = SearchSpace(1, bounds={"x": (-0.55, 0.55), "y": (-0.6, 0.6), "z": (2.2, 2.8), "roll": (-0.3, 0.3)})
    X = np.array([[0.58, -0.04, 2.26, 0.29], [-9.0, 9.0, 0.0, -0.31], [0.3, 0.1, 2.5, -0.15]])
    S = s.snap(X)
    np.testing.assert_array_equal(S[0], [0.5, -0.0, 2.3, 0.3])
    np.testing.assert_array_equal(S[1], [-0.5, 0.6, 2.2, -0.3])  # clipped to the inside multiples
    assert S[2, 0] == 0.3 and S[2, 2] == 2.5  # clean decimals, not 0.30000000000000004
    assert on_grid(S)
    assert np.all(s.contains(S))
    assert np.signbit(S).sum() == np.sum(S < 0)  # no -0.0 (stable cache keys)
    np.testing.assert_array_equal(s.snap(S), S)  # idempotent


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 5, allow_nan=False), min_size=8, max_size=8),
       st.sampled_from([0.1, 0.05, 0.2]))
def test_snap_property(x, delta):
    s = SearchSpace(2)
    v = s.snap(np.array(x), delta)
    assert np.all(s.contains(v))
    assert on_grid(v, delta)
    inner = (np.array(x) >= s.lower) & (np.array(x) <= s.upper)
    assert np.all(np.abs(v - np.array(x))[inner] <= delta / 2 + 1e-9)


def test_covering_radius():
    s = SearchSpace(1, variables=("x", "y"), fixed={"z": 2.5})
    assert s.covering_radius(0.1) == pytest.approx(math.sqrt(2) * 0.05)
    s2 = SearchSpace(1, variables=("x",), bounds={"x": (-0.55, 0.55)}, fixed={"y": 0, "z": 2.5})
    assert s2.covering_radius(0.1) == pytest.approx(0.05)


# ------------------------------------------------------------------------------------------ constraints
def test_penalties_by_hand():
    poses = np.zeros((2, 3, 6))
    poses[0, :, :3] = [[0, 0, 2.2], [0.1, 0, 2.2], [0, 0.5, 2.2]]  # pair (0,1) 0.1 apart
    poses[1, :, :3] = [[0, 0, 2.2], [0.5, 0, 2.3], [0, 0.5, 2.4]]
    np.testing.assert_allclose(MinDistance(0.4).penalty(poses), [0.3, 0.0])
    np.testing.assert_allclose(FixedHeight(2.2).penalty(poses), [0.0, 0.3])
    np.testing.assert_allclose(FixedHeight().penalty(poses), [0.0, 0.2])
    np.testing.assert_allclose(Bounds({"z": (2.2, 2.35)}).penalty(poses), [0.0, 0.05])
    c = FunctionConstraint(lambda p: p[:, :, 0].sum(axis=1), name="sum_x")
    np.testing.assert_allclose(total_penalty([c, MinDistance(0.4)], poses), [0.4, 0.5])
    with pytest.raises(ValueError, match="finite penalties >= 0"):
        FunctionConstraint(lambda p: -np.ones(len(p))).penalty(poses)
    with pytest.raises(ValueError, match="shape"):
        FunctionConstraint(lambda p: np.ones(7)).penalty(poses)
    with pytest.raises(ValueError, match="positive"):
        MinDistance(0)


@pytest.mark.parametrize("space, cons", [
    (SearchSpace(4), [MinDistance(2.0)]),                                    # beyond the box diagonal
    (SearchSpace(4, variables=("y",), fixed={"x": 0, "z": 2.2}), [MinDistance(0.5)]),  # 4 on a 1.2 m line
    (SearchSpace(8), [MinDistance(1.0)]),                                    # pigeonhole bound
    (SearchSpace(2, variables=("roll",), fixed={"x": 0, "y": 0, "z": 2.2}), [MinDistance(0.1)]),
    (SearchSpace(4, variables=("x", "roll"), fixed={"y": 0, "z": 2.2}), [FixedHeight(), MinDistance(0.5)]),
])
def test_obviously_infeasible_setups_raise(space, cons):
    with pytest.raises(ValueError, match="MinDistance"):
        optimize(lambda X: np.zeros(len(X)), space, cons, max_evals=10, progress=False)


def test_conflicting_fixed_height_raises():
    s = SearchSpace(2, variables=("x", "y"), fixed={"z": [2.2, 2.4]})
    with pytest.raises(ValueError, match="conflicts"):
        optimize(lambda X: np.zeros(len(X)), s, [FixedHeight(2.2)], max_evals=10, progress=False)


# ---------------------------------------------------------------------------------------- optimisation
def test_finds_grid_optimum_with_population_batches():
    space = SearchSpace(2)
    obj = Recorder(sphere(TARGET2))
    res = optimize(obj, space, max_evals=1500, seed=0, progress=False)
    np.testing.assert_array_equal(res.best_vector, TARGET2)
    assert res.best_score == 0.0 and res.feasible
    assert res.best_placement.poses.shape == (2, 6)
    # whole populations in one call, float64 (P, D), snapped, inside bounds, never the same row twice
    assert obj.batches[0].shape == (res.popsize, space.dim)
    assert all(b.ndim == 2 and b.shape[1] == space.dim and b.dtype == np.float64 for b in obj.batches)
    assert len(obj.batches) <= res.generations
    rows = obj.rows
    assert len(rows) == res.evaluations <= 1500
    assert len(np.unique(rows, axis=0)) == len(rows)
    assert on_grid(rows) and np.all(space.contains(rows))
    # cache accounting: every candidate is either a miss (evaluated) or a hit
    assert res.cache["misses"] == res.evaluations
    assert res.cache["hits"] + res.cache["misses"] == sum(h["new"] + h["cache_hits"] for h in res.history)
    assert res.cache["hits"] > 0
    best = [h["best_so_far"] for h in res.history]
    assert best == sorted(best)  # unconstrained: the incumbent never gets worse


def test_optimum_on_the_boundary_stays_in_bounds():
    space = SearchSpace(1, variables=("x", "y", "z"))
    obj = Recorder(sphere(np.array([5.0, -5.0, 0.0])))
    res = optimize(obj, space, max_evals=400, progress=False)
    np.testing.assert_array_equal(res.best_vector, [0.6, -0.6, 2.2])
    assert np.all(space.contains(obj.rows))


def test_min_distance_holds_for_best_and_is_penalised():
    space = SearchSpace(3, variables=("x", "y"), fixed={"z": 2.4})
    obj = Recorder(lambda X: -np.sum(X ** 2, axis=1))  # wants every LiDAR at the origin
    res = optimize(obj, space, [MinDistance(0.4)], max_evals=800, progress=False)
    assert res.feasible and res.best_penalty == 0
    assert res.best_placement.min_distance() >= 0.4 - 1e-9
    P = MinDistance(0.4).penalty(space.to_poses(obj.rows))
    assert np.any(P > 0)  # infeasible candidates were proposed ...
    F = -np.sum(obj.rows ** 2, axis=1)
    assert res.best_score < F.max()  # ... and the best unconstrained score was infeasible, so not chosen
    assert res.best_score == F[P == 0].max()


def test_fixed_height_keeps_every_z_equal():
    space = SearchSpace(4)
    target = np.tile([0.2, 0.1, 2.7, 0.0], 4)
    obj = Recorder(sphere(target))
    res = optimize(obj, space, [FixedHeight(2.3)], max_evals=300, progress=False)
    z = space.to_poses(obj.rows)[:, :, 2]
    assert np.all(z == 2.3)
    assert np.all(res.best_placement.poses[:, 2] == 2.3)
    assert "z" not in res.search_space.variables and res.search_space.dim == 12
    # free common height: z shared, equal within every candidate, varying between candidates
    obj = Recorder(sphere(target))
    res = optimize(obj, space, [FixedHeight()], max_evals=300, progress=False)
    z = space.to_poses(obj.rows)[:, :, 2]
    assert np.all(z == z[:, :1]) and len(np.unique(z)) > 1
    assert res.search_space.shared == ("z",)
    assert np.all(res.best_placement.poses[:, 2] == res.best_placement.poses[0, 2])


def test_determinism_and_rng_isolation():
    space = SearchSpace(2)
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    a = optimize(sphere(TARGET2), space, max_evals=250, seed=7, progress=False)
    assert np.array_equal(np.random.get_state()[1], before)  # global RNG untouched

    def noisy_user_code(X):  # consumes the global RNG: must not change the search
        np.random.rand(5)
        return sphere(TARGET2)(X)

    b = optimize(noisy_user_code, space, max_evals=250, seed=7, progress=False)
    c = optimize(sphere(TARGET2), space, max_evals=250, seed=8, progress=False)
    np.testing.assert_array_equal(a.best_vector, b.best_vector)
    assert a.history == b.history and a.certificate == b.certificate and a.cache == b.cache
    assert a.history != c.history


def test_budget_is_exact_and_validated():
    obj = Recorder(lambda X: -np.abs(X).sum(axis=1))
    res = optimize(obj, SearchSpace(4), max_evals=50, progress=False)
    assert res.evaluations == 50 == len(obj.rows) and res.stop_reason == "max_evals"
    for bad in (0, -1, 2.5):
        with pytest.raises(ValueError, match="max_evals"):
            optimize(obj, SearchSpace(4), max_evals=bad, progress=False)


@pytest.mark.parametrize("kwargs, match", [
    (dict(method="nelder-mead"), "Unknown method"),
    (dict(sigma0=0), "sigma0"),
    (dict(popsize=1), "popsize"),
    (dict(penalty_weight=-1), "penalty_weight"),
    (dict(resume=True), "checkpoint"),
    (dict(seed=-1), "seed"),
    (dict(x0=np.zeros(3)), "x0"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        optimize(lambda X: np.zeros(len(X)), SearchSpace(2), max_evals=10, progress=False, **kwargs)


def test_bad_objective_output():
    with pytest.raises(ValueError, match="one score per row"):
        optimize(lambda X: np.zeros((len(X), 2)), SearchSpace(2), max_evals=10, progress=False)
    with pytest.raises(ValueError, match="callable"):
        optimize("msog", SearchSpace(2), max_evals=10, progress=False)
    with pytest.raises(ValueError, match="Constraint objects"):
        optimize(lambda X: np.zeros(len(X)), SearchSpace(2), [lambda p: 0], max_evals=10, progress=False)


def test_nonfinite_scores():
    space = SearchSpace(2)

    def half_nan(X):
        f = sphere(TARGET2)(X)
        f[X[:, 0] > 0.0] = np.nan  # the true optimum (x0 = 0.3) is in the failing region
        f[X[:, 1] < -0.5] = np.inf
        return f

    with pytest.warns(RuntimeWarning, match="non-finite"):
        res = optimize(half_nan, space, max_evals=400, progress=False)
    assert math.isfinite(res.best_score) and res.best_vector[0] <= 0.0
    assert res.cache["nonfinite"] > 0
    assert res.certificate["n_samples"] == res.evaluations - res.cache["nonfinite"]
    with pytest.raises(ValueError, match="no finite score"):
        optimize(lambda X: np.full(len(X), np.nan), space, max_evals=100, progress=False)


def test_grid_and_random_methods_and_one_dimension():
    space = SearchSpace(1, variables=("x", "y"), fixed={"z": 2.4})
    obj = Recorder(sphere(np.array([0.2, -0.3])))
    res = optimize(obj, space, method="grid", max_evals=10_000, progress=False)
    assert res.evaluations == 13 * 13 and res.stop_reason == "grid_exhausted"
    np.testing.assert_array_equal(res.best_vector, [0.2, -0.3])
    res = optimize(sphere(np.array([0.2, -0.3])), space, method="random", max_evals=60, progress=False)
    assert res.evaluations == 60 and res.method == "random"
    one = SearchSpace(1, variables=("z",), fixed={"x": 0, "y": 0})  # pycma has no 1-D integer search
    res = optimize(sphere(np.array([2.6])), one, max_evals=100, progress=False)
    assert res.method == "grid" and res.best_vector[0] == 2.6 and res.evaluations == 7


def test_callback_can_stop():
    seen = []
    res = optimize(sphere(TARGET2), SearchSpace(2), max_evals=1000, progress=False,
                   callback=lambda info: seen.append(info["generation"]) or info["generation"] >= 2)
    assert seen == [0, 1, 2] and res.generations == 3 and res.stop_reason == "callback"


def test_restarts_run_independent_seeds_and_keep_the_best(tmp_path):
    space = SearchSpace(2)
    runs = [optimize(sphere(TARGET2), space, max_evals=120, seed=s, progress=False) for s in (5, 6, 7)]
    res = optimize(sphere(TARGET2), space, max_evals=120, seed=5, progress=False, restarts=2)
    # the same three runs as done one by one; the best of them wins
    assert [r["seed"] for r in res.extra["runs"]] == [5, 6, 7]
    assert [r["best_score"] for r in res.extra["runs"]] == [r.best_score for r in runs]
    assert res.best_score == max(r.best_score for r in runs)
    np.testing.assert_array_equal(res.best_vector, runs[res.extra["best_run"]].best_vector)
    assert res.evaluations == sum(r.evaluations for r in runs)
    assert res.generations == sum(r.generations for r in runs) == len(res.history)
    assert [h["run"] for h in res.history] == [i for i, r in enumerate(runs) for _ in r.history]
    # a callback that stops ends every run; checkpoints and restarts do not mix
    one = optimize(sphere(TARGET2), space, max_evals=120, seed=5, progress=False, restarts=2,
                   callback=lambda info: True)
    assert len(one.extra["runs"]) == 1 and one.stop_reason == "callback"
    with pytest.raises(ValueError, match="restarts"):
        optimize(sphere(TARGET2), space, max_evals=120, progress=False, restarts=1, checkpoint=tmp_path / "c")
    with pytest.raises(ValueError, match="restarts"):
        optimize(sphere(TARGET2), space, max_evals=120, progress=False, restarts=-1)


# ------------------------------------------------------------------------------------------ checkpoints
_CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from place3d_kernels.optimize import SearchSpace, MinDistance, optimize
    TARGET = np.array({target})
    def objective(X):
        time.sleep(0.1)
        return -np.sum((X - TARGET) ** 2, axis=1)
    optimize(objective, SearchSpace(2), [MinDistance(0.3)], max_evals=220, popsize=8, seed=3,
             checkpoint=sys.argv[1], progress=False)
    print("finished")
""")


def _run_kw(**kw):
    return dict(space=SearchSpace(2), constraints=[MinDistance(0.3)], max_evals=220, popsize=8, seed=3,
                progress=False, **kw)


def _same(a, b):
    np.testing.assert_array_equal(a.best_vector, b.best_vector)
    assert a.best_score == b.best_score and a.best_G == b.best_G
    assert a.history == b.history
    assert a.evaluations == b.evaluations and a.generations == b.generations
    assert a.cache == b.cache and a.certificate == b.certificate and a.stop_reason == b.stop_reason


def test_resume_after_sigkill_is_bit_identical(tmp_path):
    ckpt = tmp_path / "run.ckpt"
    script = tmp_path / "child.py"
    script.write_text(_CHILD.format(target=TARGET2.tolist()))
    proc = subprocess.Popen([sys.executable, str(script), str(ckpt)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 40
        gen = 0
        while time.time() < deadline and proc.poll() is None:
            if ckpt.exists():
                gen = load_checkpoint(ckpt)["generation"]
                if gen >= 3:
                    break
            time.sleep(0.01)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGKILL)  # most likely inside the objective's sleep: mid-generation
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    state = load_checkpoint(ckpt)
    assert 3 <= state["generation"] and state["stop_reason"] is None and state["evaluations"] < 220

    obj = Recorder(sphere(TARGET2))
    resumed = optimize(obj, checkpoint=ckpt, resume=True, **_run_kw())
    fresh = optimize(sphere(TARGET2), **_run_kw())
    assert resumed.resumed and not fresh.resumed
    assert len(obj.rows) == fresh.evaluations - state["evaluations"]  # only the rest was evaluated
    _same(resumed, fresh)
    # resuming a finished run returns the same result without evaluating anything
    again = optimize(Recorder(sphere(TARGET2)), checkpoint=ckpt, resume=True, **_run_kw())
    _same(again, fresh)


def test_resume_after_crash_in_objective(tmp_path):
    ckpt = tmp_path / "run.ckpt"
    calls = {"n": 0}

    def crashing(X):
        calls["n"] += 1
        if calls["n"] == 5:
            raise RuntimeError("GPU fell off the bus")
        return sphere(TARGET2)(X)

    with pytest.raises(RuntimeError, match="bus"):
        optimize(crashing, checkpoint=ckpt, **_run_kw())
    assert load_checkpoint(ckpt)["generation"] >= 4
    resumed = optimize(sphere(TARGET2), checkpoint=ckpt, resume=True, **_run_kw())
    _same(resumed, optimize(sphere(TARGET2), **_run_kw()))
    with pytest.raises(ValueError, match="different setup"):
        optimize(sphere(TARGET2), checkpoint=ckpt, resume=True, **{**_run_kw(), "seed": 4})
    # resume=False starts over (and overwrites), resume=True on a missing file starts fresh
    fresh = optimize(sphere(TARGET2), checkpoint=tmp_path / "new.ckpt", resume=True, **_run_kw())
    assert not fresh.resumed and (tmp_path / "new.ckpt").exists()


def test_a_crash_after_ask_resumes_with_the_asked_batch(tmp_path):
    """A run whose objective raises writes the last completed generation with the batch its strategy had
    just proposed (checkpoint.py, format 2); the resumed run scores that batch first and ends as a run
    that never stopped. Checked for CMA-ES and random search, which both advance their random state on
    ask (the grid strategy its position; its grid here is too large to enumerate)."""
    for method in ("cma", "random"):
        ckpt = tmp_path / f"{method}.ckpt"
        calls = {"n": 0}

        def crashing(X):
            calls["n"] += 1
            if calls["n"] == 4:
                raise RuntimeError("device lost")
            return sphere(TARGET2)(X)

        kw = {**_run_kw(), "method": method, "max_evals": 120}
        with pytest.raises(RuntimeError, match="device lost"):
            optimize(crashing, checkpoint=ckpt, **kw)
        state = load_checkpoint(ckpt)
        assert state["generation"] == 3 and state["asked"] is not None and len(state["asked"]["K"]) == 8
        obj = Recorder(sphere(TARGET2))
        resumed = optimize(obj, checkpoint=ckpt, resume=True, **kw)
        fresh = optimize(sphere(TARGET2), **kw)
        _same(resumed, fresh)
        assert len(obj.rows) == fresh.evaluations - state["evaluations"]


# ------------------------------------------------------------------------------------------ certificate
def test_certificate_by_hand():
    # G at (0,0), (1,0), (0,2): slopes 3/1, 1/2, 2/sqrt(5) -> k_G = 3; C_M = 3
    c = certificate([[0, 0], [1, 0], [0, 2]], [0.0, 3.0, 1.0], delta=0.1, side_lengths=[1.0, 2.0])
    assert c["k_G"] == pytest.approx(3.0) and c["C_M"] == pytest.approx(3.0)
    assert c["bound"] == pytest.approx(3.0 + 3.0 * 0.1)
    assert c["bound_corollary"] == pytest.approx(3.0 * 3.0 + 3.0 * 0.1)
    assert c["n_pairs"] == 3
    # duplicates and non-finite values are ignored; no samples -> None
    c2 = certificate([[0, 0], [0, 0], [1, 0], [5, 5]], [0.0, 0.0, 3.0, np.nan], delta=0.1, side_lengths=[1, 2])
    assert c2["k_G"] == pytest.approx(3.0) and c2["n_samples"] == 3
    assert certificate(np.zeros((0, 2)), [], 0.1, [1, 1])["k_G"] is None



def _all_pairs_slope(U, G):
    """k_G by its definition: every pair i < j of distinct points, the slope in float64 (the sum of
    squares over the contiguous last axis, as certificate's exact recheck takes it)."""
    U, G = np.asarray(U, float), np.asarray(G, float)
    i, j = np.triu_indices(len(U), 1)
    d = np.sqrt(((U[i] - U[j]) ** 2).sum(-1))
    keep = d > 0
    return (float((np.abs(G[i] - G[j])[keep] / d[keep]).max()) if keep.any() else 0.0), int(keep.sum())


def test_certificate_slope_is_the_all_pairs_maximum_bit_for_bit():
    """k_G is screened with SciPy's pdist (another summation order) and then recomputed exactly near
    the maximum: the value must be the all-pairs definition's to the bit, with lattice points (many equal
    slopes), duplicates and up to 29 variables."""
    rng = np.random.default_rng(5)
    for t in range(150):
        n, D = int(rng.integers(2, 160)), int(rng.integers(1, 30))
        U = rng.integers(-5, 5, (n, D)) * rng.choice([0.05, 0.1, 1 / 3])
        if t % 3 == 0:
            U[: n // 2] = U[n // 2: 2 * (n // 2)]           # duplicated points: no slope
        G = rng.normal(size=n) if t % 2 else rng.integers(0, 3, n) * 0.1
        c = certificate(U, G, 0.1, np.ones(D))
        k, pairs = _all_pairs_slope(U, G)
        assert c["k_G"] == k and c["n_pairs"] == pairs, (t, n, D)

def test_result_certificate_matches_samples_and_json(tmp_path):
    space = SearchSpace(1, variables=("x", "y"), fixed={"z": 2.4})
    f = sphere(np.array([0.2, -0.3]))
    res = optimize(f, space, method="grid", max_evals=10_000, progress=False)
    g = np.arange(-6, 7) / 10
    X = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    G = -f(X)
    assert res.certificate["C_M"] == pytest.approx(G.max() - G.min())
    # the steepest grid slope of this quadratic: between corner (-0.6, 0.6) and a neighbour
    assert res.certificate["k_G"] == pytest.approx(certificate(X, G, 0.1, [1.2, 1.2])["k_G"])
    assert res.certificate["bound_corollary"] == pytest.approx(res.certificate["k_G"] * (2.4 + 0.1))
    text = json.dumps(res.to_dict(), allow_nan=False)
    d = json.loads(text)
    assert d["best_vector"] == [0.2, -0.3] and d["certificate"]["feasible"]["n_samples"] == 169



def test_on_search_end_gets_what_the_result_holds_once():
    """The hook runs once, before the certificate, with the result's history and best placement (the
    command starts its figures there); with restarts once at the end; a non-callable is refused."""
    space = SearchSpace(1, variables=("x", "y"), fixed={"z": 2.4})
    f = sphere(np.array([0.2, -0.3]))
    for restarts in (0, 2):
        calls = []
        res = optimize(f, space, max_evals=200, progress=False, restarts=restarts,
                       on_search_end=lambda h, p: calls.append((h, p)))
        assert len(calls) == 1
        history, placement = calls[0]
        assert history == res.history and placement.name == res.best_placement.name == "optimized"
        np.testing.assert_array_equal(placement.poses, res.best_placement.poses)
    with pytest.raises(ValueError, match="on_search_end must be callable"):
        optimize(f, space, max_evals=10, progress=False, on_search_end="plots")

def test_plots(tmp_path):
    from place3d_kernels.optimize import plot_convergence, plot_rig

    space = SearchSpace(4)
    res = optimize(sphere(np.tile([0.2, 0.1, 2.5, 0.1], 4)), space, [MinDistance(0.3)], max_evals=120,
                   progress=False)
    a = plot_convergence(res.history, tmp_path / "conv.png")
    b = plot_rig(res.best_placement, tmp_path / "rig.png", baselines=["pyramid", "square"], bounds=space)
    for p in (a, b):
        assert p.exists() and p.stat().st_size > 5000


# ---------------------------------------------------------------------------- M-SOG objective (lead)
def test_msog_objective_cache_is_bit_identical_to_msog_batch(backend):
    import place3d_kernels as p3k
    from place3d_kernels.classes import CLASS_ID
    from place3d_kernels.optimize import MSOGObjective, SearchSpace

    grid = p3k.Grid(lower=(-6.05, -6.05, -0.45), upper=(5.95, 5.95, 3.55), voxel_size=0.2)
    rng = np.random.default_rng(3)
    probs = np.zeros(grid.shape + (22,))
    probs[..., 0] = 1.0
    occ = rng.uniform(size=grid.shape) < 0.03
    probs[occ, 0] = 0.4
    probs[occ, CLASS_ID["road"]] = 0.6
    probs[:, :, 2] = 0
    probs[:, :, 2, CLASS_ID["road"]] = 1.0         # the ground layer stops downward rays
    psog = p3k.PSOG.from_probabilities(grid, probs)
    lidar = p3k.LidarModel.uniform(4, (-20, 2), 40, max_range=30.0)
    space = SearchSpace(n_lidars=2)
    X = space.snap(rng.uniform(space.lower, space.upper, (6, space.dim)))
    X[3] = X[0]                                      # a repeated rig: both its poses come from the cache
    obj = MSOGObjective(psog, lidar, space, task="seg", backend=backend)
    got = obj(X)
    want = p3k.msog_batch(psog, lidar, space.to_poses(X), backend=backend)
    np.testing.assert_array_equal(got, want)
    assert obj.pose_misses <= 10 and obj.pose_hits >= 2
    misses = obj.pose_misses
    np.testing.assert_array_equal(obj(X[:2]), want[:2])
    assert obj.pose_misses == misses               # nothing traversed again


def _certificate_executor_runs(executor, **kw):
    """(result with ``executor``, result without) of one constrained run (some infeasible samples)."""
    space = SearchSpace(2, variables=("x", "y"), fixed={"z": 2.4})
    f = sphere(np.array([0.2, -0.3, 0.1, 0.3]))
    runs = [optimize(f, space, [MinDistance(0.5)], max_evals=300, progress=False, certificate_executor=ex, **kw)
            for ex in (executor, None)]
    return runs


def test_certificate_computed_by_an_executor_is_the_same():
    """optimize(certificate_executor=...) hands the certificate to that executor (a spawned process, as
    place3d optimize's helper) before on_search_end: the same dict as computed here, feasible part included."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    calls = []

    class Counting(ProcessPoolExecutor):
        def submit(self, fn, *args, **kw):
            calls.append(fn.__name__)
            return super().submit(fn, *args, **kw)

    with Counting(1, mp_context=multiprocessing.get_context("spawn")) as ex:
        there, here = _certificate_executor_runs(ex)
        assert calls == ["certify"]
        assert there.certificate == here.certificate
        assert there.certificate["feasible"]["n_samples"] < there.certificate["n_samples"]   # infeasible ones left out
        assert there.best_score == here.best_score and there.history == here.history
        calls.clear()
        there, here = _certificate_executor_runs(ex, restarts=1)    # each run's certificate there
        assert calls == ["certify"] * 2 and there.certificate == here.certificate


def test_certificate_falls_back_here_when_the_executor_is_gone():
    """A process pool found broken (its process killed) or already shut down: the certificate is computed
    here, the same as without an executor."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    ex = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    try:
        ex.submit(int).result(timeout=120)                    # the process is up
        for pid in list(ex._processes):
            os.kill(pid, signal.SIGKILL)
        time.sleep(1.0)
        broken, here = _certificate_executor_runs(ex)
        assert broken.certificate == here.certificate
    finally:
        ex.shutdown(wait=True)
    closed, here = _certificate_executor_runs(ex)           # shut down: submit raises RuntimeError
    assert closed.certificate == here.certificate


def test_certificate_falls_back_here_when_its_process_dies_while_computing():
    """A Future whose pool broke after taking the certificate (BrokenProcessPool from result()): computed
    here, the same dict; any other error of the certificate itself is raised, not hidden."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    class Failing:
        def __init__(self, error):
            self.error = error

        def submit(self, fn, *args, **kw):
            f = Future()
            f.set_exception(self.error)
            return f

    died, here = _certificate_executor_runs(Failing(BrokenProcessPool("killed")))
    assert died.certificate == here.certificate
    with pytest.raises(ValueError, match="bad input"):
        _certificate_executor_runs(Failing(ValueError("bad input")))
