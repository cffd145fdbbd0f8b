"""On the default scene, CMA-ES finds a placement that beats all seven heuristic baselines (seg and det).

As ``place3d optimize`` does by default, the search starts from the best baseline with sigma0 0.15: for
det, "center" is a strong local optimum that runs from the box centre (sigma0 0.3) beat in none of seeds
0-3 on this scene, while runs from center beat it in each of seeds 0-3 (after 1,165-1,506 evaluations;
2026-11-22). One restart (seed 1) is allowed as a margin; the run stops once every baseline is beaten."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k


@pytest.fixture(scope="module")
def town_psog():
    # the 0.2 m box, the default when these outcomes were set; the 0.1 m default costs 8x the memory
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.2)
    return p3k.scene_psog(p3k.scene.town(seed=0), grid, backend="warp:cpu", cache=False)


@pytest.mark.parametrize("task", ["seg", "det"])
def test_optimised_rig_beats_the_heuristic_baselines(town_psog, task):
    lidar = p3k.LidarModel.load("place3d_16ch")
    space = p3k.SearchSpace(n_lidars=4)
    base = {n: p3k.msog(town_psog, lidar, p3k.Placement.load(n), task=task, backend="warp:cpu")
            for n in p3k.BASELINES}
    target = max(base.values())

    def objective(X):
        return p3k.msog_batch(town_psog, lidar, space.to_poses(X), task=task, backend="warp:cpu")

    # the CLI budget (2,000 evaluations) per run; stops as soon as the best beats every baseline
    start = p3k.Placement.load(max(base, key=base.get))
    res = p3k.optimize(objective, space, [p3k.MinDistance(0.2)], max_evals=2000, seed=0, progress=False,
                       x0=start, sigma0=0.15, restarts=1, callback=lambda info: info["best_so_far"] > target)
    assert res.feasible
    assert res.best_score > target, (res.best_score, base)
    # the reported score is the rig's real M-SOG, and the rig respects the constraints
    assert p3k.msog(town_psog, lidar, res.best_placement, task=task, backend="warp:cpu") == res.best_score
    assert res.best_placement.min_distance() >= 0.2 - 1e-9
    assert np.all(res.best_placement.poses[:, 2] >= 2.2 - 1e-9) and np.all(res.best_placement.poses[:, 2] <= 2.8 + 1e-9)
