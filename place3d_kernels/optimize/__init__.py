"""Placement optimisation (paper Sec. 3.3): search space, constraints, CMA-ES on the delta grid, certificate.

Backend-agnostic: the objective is any function from a batch of parameter vectors to scores.

    >>> from place3d_kernels.optimize import SearchSpace, MinDistance, optimize
    >>> space = SearchSpace(n_lidars=4)                       # x, y, z, roll per LiDAR, the paper's box
    >>> res = optimize(lambda X: score(space.to_poses(X)), space, [MinDistance(0.2)], max_evals=500)
    >>> res.best_placement.save("optimized.toml")

``plot_convergence`` and ``plot_rig`` (matplotlib) are imported on first use.
"""

from place3d_kernels.optimize.certificate import certificate
from place3d_kernels.optimize.checkpoint import load_checkpoint, save_checkpoint
from place3d_kernels.optimize.cmaes import METHODS
from place3d_kernels.optimize.constraints import (Bounds, Constraint, FixedHeight, FunctionConstraint, MinDistance,
                                                  total_penalty)
from place3d_kernels.optimize.objective import MSOGObjective
from place3d_kernels.optimize.optimizer import DEFAULT_PENALTY_WEIGHT, OptimizeResult, optimize
from place3d_kernels.optimize.space import DEFAULT_BOUNDS, DEFAULT_DELTA, POSE_KEYS, SearchSpace

__all__ = ["SearchSpace", "optimize", "MSOGObjective", "OptimizeResult", "Constraint", "MinDistance", "FixedHeight", "Bounds",
           "FunctionConstraint", "total_penalty", "certificate", "load_checkpoint", "save_checkpoint", "METHODS",
           "DEFAULT_BOUNDS", "DEFAULT_DELTA", "DEFAULT_PENALTY_WEIGHT", "POSE_KEYS",
           "plot_convergence", "plot_rig"]


def __getattr__(name):
    if name in ("plot_convergence", "plot_rig"):
        from place3d_kernels.optimize import plots

        return getattr(plots, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
