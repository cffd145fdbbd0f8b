"""``optimize``: CMA-ES placement search on the delta grid, with cache, penalties, checkpoints, certificate.

The objective sees batches: ``objective(X) -> scores`` with X a (P, D) float64 array of snapped parameter
vectors of the user's ``SearchSpace`` (``space.to_poses(X)`` gives the (P, L, 6) poses) and scores a
(P,) array, higher is better (e.g. M-SOG). Each generation calls it once, with only the candidates whose
grid point has not been scored before (repeated grid points are answered from a cache), so a GPU
backend sees whole populations. The optimiser itself never imports a backend.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable as _Fn, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from place3d_kernels.optimize.certificate import certify
from place3d_kernels.optimize.checkpoint import (FRESH_RUN_HINT, load_checkpoint, replay, save_checkpoint, snapshot,
                                                 write_snapshot)
from place3d_kernels.optimize.cmaes import METHODS, make_strategy
from place3d_kernels.optimize.constraints import Constraint, prepare, total_penalty
from place3d_kernels.optimize.space import DEFAULT_DELTA, SearchSpace
from place3d_kernels.placement import Placement
from place3d_kernels.profiling import section

__all__ = ["optimize", "OptimizeResult", "DEFAULT_PENALTY_WEIGHT"]

#: lambda in G = -F + lambda * P. Penalties are in metres (or the user's units); 1000 makes a 1 mm
#: violation cost 1, far more than the spread of M-SOG scores. Scale it to your objective if needed.
DEFAULT_PENALTY_WEIGHT = 1000.0
#: Seconds between two checkpoints of a run at most (a killed run replays at most this much work).
CHECKPOINT_SECONDS = 1.0


def _json(v):
    """JSON-safe copy: numpy -> Python, non-finite floats -> None."""
    if isinstance(v, Mapping):
        return {str(k): _json(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    if v is None or isinstance(v, str):
        return v
    return str(v)


def _num(v):
    return None if v is None or not math.isfinite(v) else float(v)


@dataclass
class OptimizeResult:
    """Outcome of ``optimize``.

    Attributes:
        best_vector: (D,) best parameter vector in the user's space (feasible if any feasible was seen).
        best_placement: the same as a ``Placement`` (name ``"optimized"``).
        best_score: objective F at the best vector (higher is better).
        best_G: ``-F + penalty_weight * P`` there; ``best_penalty`` is P.
        feasible: whether the best vector satisfies every constraint (P == 0).
        history: one dict per generation: generation, evaluations (cumulative), new (rows sent to the
            objective), cache_hits, best / mean (F over the generation), best_G, best_so_far (F of the
            incumbent), n_feasible, n_nonfinite, sigma (pycma's step size, relative to bound widths;
            None for non-CMA methods). Missing values are None.
        evaluations: rows scored by the objective (distinct grid points).
        certificate: Theorem 1 estimate over all evaluated samples (keys k_G, C_M, bound,
            bound_corollary, ...), with ``certificate["feasible"]`` the same over feasible samples only.
        cache: hits, misses, size, hit_rate, nonfinite.
        stop_reason: why the run ended (``max_evals``, ``stalled``, ``callback``, ``cma:tolfun``, ...).
        method: the strategy that ran (``cma``, ``random``, ``grid``).
        space / search_space: the user's space and the one actually searched (after FixedHeight).
        diagnostics: filled by callers that know the P-SOG (``place3d optimize``): variables on a bound,
            entropy shares of the winner and the baselines (``optimize.diagnostics.diagnose``); None otherwise.
        holdout: re-scoring on held-out P-SOGs, the winner's rank there (``optimize.diagnostics.holdout``),
            or None.
        transfer: the verdict on them (``optimize.diagnostics.transfer``: first on every one), or None.
        intervals: the best rig's and the baselines' intervals over the drive's subsets
            (``uncertainty.rig_vs_baselines_intervals``, filled by ``place3d optimize``), or None.
    """

    best_vector: np.ndarray
    best_placement: Placement
    best_score: float
    best_G: float
    best_penalty: float
    feasible: bool
    history: list
    evaluations: int
    generations: int
    seconds: float
    certificate: dict
    seed: int
    cache: dict
    stop_reason: str
    method: str
    popsize: int
    space: SearchSpace
    search_space: SearchSpace
    delta: object = DEFAULT_DELTA
    penalty_weight: float = DEFAULT_PENALTY_WEIGHT
    resumed: bool = False
    checkpoint: str | None = None
    left_start: bool = True
    extra: dict = field(default_factory=dict)
    diagnostics: dict | None = None
    holdout: list | None = None
    transfer: dict | None = None
    intervals: dict | None = None

    def to_dict(self) -> dict:
        """JSON-safe summary (non-finite numbers become null)."""
        return _json({
            "best_vector": self.best_vector, "best_placement": {"name": self.best_placement.name,
                                                                "poses": self.best_placement.poses},
            "best_score": self.best_score, "best_G": self.best_G, "best_penalty": self.best_penalty,
            "feasible": self.feasible, "evaluations": self.evaluations, "generations": self.generations,
            "seconds": self.seconds, "seed": self.seed, "method": self.method, "popsize": self.popsize,
            "stop_reason": self.stop_reason, "delta": self.delta, "penalty_weight": self.penalty_weight,
            "resumed": self.resumed, "checkpoint": self.checkpoint, "left_start": self.left_start,
            "cache": self.cache,
            "certificate": self.certificate, "space": self.space.to_dict(),
            "search_space": self.search_space.to_dict(), "names": list(self.space.names),
            "history": self.history, "diagnostics": self.diagnostics, "holdout": self.holdout, "transfer": self.transfer,
            **self.extra})

    def __repr__(self) -> str:
        return (f"OptimizeResult(best_score={self.best_score:.6g}, feasible={self.feasible}, "
                f"evaluations={self.evaluations}, generations={self.generations}, method={self.method!r}, "
                f"stop_reason={self.stop_reason!r}, seconds={self.seconds:.2f})")


def _setup(space, constraints, method, sigma0, popsize, delta, seed, penalty_weight, x0, cma_options,
           max_stall) -> dict:
    return _json({"space": space.to_dict(), "constraints": [c.describe() for c in constraints],
                  "method": method, "sigma0": sigma0, "popsize": popsize,
                  "delta": dict(delta) if isinstance(delta, Mapping) else float(delta), "seed": seed,
                  "penalty_weight": penalty_weight, "x0": None if x0 is None else np.asarray(x0).tolist(),
                  "cma_options": repr(sorted((cma_options or {}).items())),
                  "max_stall_generations": max_stall})


def _check_int(name, v, lo):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")
    return int(v)


def optimize(objective: _Fn, space: SearchSpace, constraints: Sequence[Constraint] | Constraint = (), *,
             method: str = "cma", sigma0: float = 0.3, popsize: int | None = None, max_evals: int = 2000,
             delta=DEFAULT_DELTA, seed: int = 0, penalty_weight: float = DEFAULT_PENALTY_WEIGHT,
             checkpoint=None, resume: bool = False, progress: bool = True, callback: _Fn | None = None,
             x0=None, max_stall_generations: int = 30, cma_options: dict | None = None,
             restarts: int = 0, on_search_end: _Fn | None = None, certificate_executor=None) -> OptimizeResult:
    """Maximise ``objective`` over placements on the delta grid of ``space`` (paper, Algorithm 1).

    Minimises ``G = -F + penalty_weight * P`` with CMA-ES (pycma ask/tell), F the objective and P the
    summed constraint penalties. Candidates are snapped to the grid (anchored at 0, inside the bounds);
    a cache maps each grid point to its score so repeats cost nothing.

    Args:
        objective: ``f(X (P, D) float64) -> (P,) float64``, higher is better. Called once per generation
            with the not-yet-scored rows only. NaN / inf scores are treated as failed candidates: they
            rank below every finite one (G = worst finite G seen + max(1, |worst|) + lambda P), are never
            chosen as best, are left out of the certificate, and raise a RuntimeWarning; if the whole
            first generation fails, ValueError.
        space: the ``SearchSpace``.
        constraints: ``MinDistance``, ``FixedHeight``, ``Bounds``, ``FunctionConstraint`` (or your own
            ``Constraint``). ``FixedHeight`` removes z from the searched variables (see
            ``result.search_space``); the objective still receives vectors of ``space``.
        method: ``"cma"`` (default), ``"random"`` (uniform grid points) or ``"grid"`` (exhaustive). With
            fewer than two free dimensions ``"cma"`` enumerates the grid.
        sigma0: initial CMA-ES step size relative to the bound widths: coordinate i starts with standard
            deviation ``sigma0 * (upper_i - lower_i)``.
        popsize: candidates per generation (default: pycma's, ``4 + 3 ln n`` raised for integer search).
        max_evals: budget of objective rows (distinct grid points); the last generation is cut to fit.
        delta: grid step, metres for positions and radians for angles (paper: 0.1), or
            ``{variable: step}``.
        seed: seeds the search; same seed and objective give the identical result.
        penalty_weight: lambda (default 1000).
        checkpoint: path of a checkpoint, written atomically after a generation that evaluated
            something, at most once per ``CHECKPOINT_SECONDS`` (1 s; generations answered wholly from the
            cache cost nothing to replay, so they are saved only every 10th time), and at the end.
            ``resume=True`` continues from it (same setup required; ``max_evals`` may grow); a missing file
            starts a fresh run; ``resume=False`` overwrites it. A run killed at any moment (even SIGKILL)
            and resumed ends with the same result, bit for bit, as one that was not; a kill loses at most
            the generations of the last second, a run that raises none that completed (one interrupted
            inside the strategy's own ask or tell, as Ctrl-C may, at most the last second). The objective
            is not stored: resume with the same objective.
        progress: tqdm progress bar on stderr.
        callback: ``callback(info: dict)`` after each generation (the history entry plus ``best_vector``);
            return True to stop.
        x0: initial mean, a ``Placement`` or a vector of ``space`` (default: centre of the box). With
            ``method="cma"`` it is also injected into the first generation, so it is always scored.
        max_stall_generations: stop after this many generations in a row without a new grid point.
        cma_options: extra pycma options (e.g. ``{"tolfun": 0}``).
        restarts: independent further runs with seeds ``seed + 1, ..., seed + restarts``, each with the
            full ``max_evals`` budget (multi-start, for objectives with strong local optima). The result
            is the best run's, with ``evaluations``, ``generations``
            and ``seconds`` summed, the histories concatenated (each entry has ``run``), and
            ``extra["runs"]`` one summary per run. A callback returning True stops all runs. Not
            combinable with ``checkpoint``.
        on_search_end: ``on_search_end(history, best_placement)`` once the search has ended and before
            the certificate is estimated, with what the result will hold (``history``, and
            ``best_placement`` named ``"optimized"``), so that work on them (the command's figures) can
            start meanwhile. With ``restarts``, once at the end.
        certificate_executor: where the certificate (every pair of evaluated points) is computed: an
            executor (``submit(fn, *args, **kw)`` returning a ``concurrent.futures.Future``), to which it is
            handed before ``on_search_end`` and waited for after it. ``place3d optimize`` passes a helper
            process started with the command, so that its own process never imports SciPy (the pair scan's
            ``pdist``, a visible part of a cold command's import time, which had held the interpreter lock
            during the simulation). Default (None), or a process pool found broken: computed here, after
            ``on_search_end``. The result is the same either way (the same function on the same arrays).

    Returns:
        OptimizeResult.

    Raises:
        ValueError: bad arguments, infeasible constraints, a misbehaving objective.
    """
    _check_basics(objective, space, method)
    max_evals = _check_int("max_evals (the evaluation budget)", max_evals, 1)
    restarts = _check_int("restarts", restarts, 0)
    if on_search_end is not None and not callable(on_search_end):
        raise ValueError(f"on_search_end must be callable, got {on_search_end!r}")
    if restarts:
        if checkpoint is not None:
            raise ValueError("restarts cannot be combined with checkpoint; checkpoint each run on its own")
        res = _multistart(objective, space, constraints, restarts, callback,
                          dict(method=method, sigma0=sigma0, popsize=popsize, max_evals=max_evals, delta=delta,
                               seed=seed, penalty_weight=penalty_weight, progress=progress, x0=x0,
                               max_stall_generations=max_stall_generations, cma_options=cma_options,
                               certificate_executor=certificate_executor))
        if on_search_end is not None:   # copies, as for a single run: the hook may rename or keep them
            on_search_end([dict(h) for h in res.history], space.to_placement(res.best_vector, name="optimized"))
        return res
    seed, popsize, max_stall_generations, sigma0, penalty_weight = _check_run(
        seed, popsize, max_stall_generations, sigma0, penalty_weight, resume, checkpoint, callback)

    grid, x0_vec, k0 = _searched_grid(space, constraints, delta, x0, penalty_weight)
    setup = _setup(space, grid.cons, method, sigma0, popsize, delta, seed, penalty_weight, x0_vec, cma_options,
                   max_stall_generations)
    state, resumed = _initial_state(grid, setup, checkpoint, resume, method, k0, x0_vec, sigma0, popsize, seed,
                                    cma_options)
    _run_generations(grid, state, objective, max_evals, max_stall_generations, checkpoint, progress, callback)
    if checkpoint is not None:
        save_checkpoint(checkpoint, state)
    pending = None
    if certificate_executor is not None and state["best"] is not None:
        pending = _submit_certificate(certificate_executor, state, grid.search, grid.steps, penalty_weight, delta)
    if on_search_end is not None and state["best"] is not None:
        # what _result will hold, before its certificate (all pairs of evaluated points) is estimated
        on_search_end([dict(h) for h in state["history"]], space.to_placement(state["best"]["X"], name="optimized"))
    res = _result(state, space, grid.search, grid.cons, state["strategy"], delta, grid.steps, penalty_weight, seed,
                  resumed, checkpoint, pending)
    res.left_start = _left_start(grid, res.best_vector, k0)
    if not res.left_start:
        warnings.warn(f"the search never left its start: after {res.evaluations} evaluations the best placement "
                      f"is the starting one (score {res.best_score:.6g}); nothing better was found", RuntimeWarning,
                      stacklevel=2)
    return res


def _left_start(grid, best_vector, k0) -> bool:
    """Whether the best vector lies on another grid point than the start (k0, free grid indices)."""
    kb = grid.search.snap_indices(grid.search.from_poses(grid.space.to_poses(best_vector)), grid.delta)[grid.free]
    return bool(np.any(np.abs(kb - np.asarray(k0)) > 0.5))


# ------------------------------------------------------------------------------ setup
def _check_basics(objective, space, method) -> None:
    if not callable(objective):
        raise ValueError(f"objective must be callable X (P, D) -> scores (P,), got {objective!r}")
    if not isinstance(space, SearchSpace):
        raise ValueError(f"space must be a SearchSpace, got {type(space).__name__}")
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; available: {list(METHODS)}")


def _check_run(seed, popsize, max_stall_generations, sigma0, penalty_weight, resume, checkpoint, callback):
    """The single-run arguments, checked and normalised: (seed, popsize, max_stall, sigma0, penalty_weight)."""
    seed = _check_int("seed", seed, 0)
    if seed >= 2 ** 32:
        raise ValueError(f"seed must be below 2**32, got {seed}")
    if popsize is not None:
        popsize = _check_int("popsize", popsize, 2)
    max_stall_generations = _check_int("max_stall_generations", max_stall_generations, 1)
    try:
        sigma0 = float(sigma0)
        penalty_weight = float(penalty_weight)
    except (TypeError, ValueError):
        raise ValueError(f"sigma0 and penalty_weight must be numbers, got {sigma0!r}, {penalty_weight!r}") from None
    if not (math.isfinite(sigma0) and sigma0 > 0):
        raise ValueError(f"sigma0 must be > 0 (a fraction of the bound widths, e.g. 0.3), got {sigma0}")
    if not (math.isfinite(penalty_weight) and penalty_weight >= 0):
        raise ValueError(f"penalty_weight must be finite and >= 0, got {penalty_weight}")
    if resume and checkpoint is None:
        raise ValueError("resume=True needs a checkpoint path (place3d optimize: --resume needs --checkpoint "
                         "FILE or --output DIR)")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable, got {callback!r}")
    return seed, popsize, max_stall_generations, sigma0, penalty_weight


@dataclass
class _Grid:
    """The searched grid: what a generation needs to turn strategy samples into scored candidates."""

    space: SearchSpace           # the user's space (the objective's vectors)
    search: SearchSpace          # the space actually searched (after FixedHeight)
    cons: list
    delta: object
    steps: np.ndarray
    kmin: np.ndarray             # grid-index bounds of the searched coordinates
    kmax: np.ndarray
    free: np.ndarray             # coordinates with more than one grid point
    penalty_weight: float


def _searched_grid(space, constraints, delta, x0, penalty_weight):
    """(the ``_Grid``, x0 as a vector of ``space`` or None, the start in free grid indices)."""
    search, cons = prepare(space, constraints, delta)
    steps = search.grid_steps(delta)
    kmin, kmax = search.grid_index_bounds(delta)
    free = kmax > kmin
    x0_vec = None
    if x0 is not None:
        x0_vec = space.from_placement(x0) if isinstance(x0, Placement) else np.asarray(x0, dtype=np.float64)
        if x0_vec.shape != (space.dim,) or not np.all(np.isfinite(x0_vec)):
            raise ValueError(f"x0 must be a Placement or a finite vector of length {space.dim}, got {x0!r}")
        if not np.all(space.contains(x0_vec, tol=1e-9)):
            bad = [f"{n}={v:.3g} not in [{lo:.3g}, {hi:.3g}]" for n, v, lo, hi
                   in zip(space.names, x0_vec, space.lower, space.upper) if not lo - 1e-9 <= v <= hi + 1e-9]
            raise ValueError(f"x0 lies outside the search box: {', '.join(bad)}; move it inside or widen the bounds")
        k0 = search.snap_indices(search.from_poses(space.to_poses(x0_vec)), delta)[free].astype(float)
    else:
        k0 = (kmin[free] + kmax[free]) / 2.0
    return _Grid(space, search, cons, delta, steps, kmin, kmax, free, penalty_weight), x0_vec, k0


def _initial_state(grid: _Grid, setup, checkpoint, resume, method, k0, x0_vec, sigma0, popsize, seed, cma_options):
    """(state, resumed): the checkpoint's state when resuming one of the same setup, else a fresh one."""
    free = grid.free

    def fresh_strategy():
        s = make_strategy(method, x0=k0, kmin=grid.kmin[free], kmax=grid.kmax[free], sigma0=sigma0,
                          widths_idx=grid.search.widths[free] / grid.steps[free], popsize=popsize, seed=seed,
                          options=cma_options)
        if x0_vec is not None and hasattr(s, "es"):
            # the first generation scores x0 itself, so a warm start never ends below its starting rig
            s.es.inject([k0], force=True)
        return s

    if resume and Path(checkpoint).exists():
        state = load_checkpoint(checkpoint)
        if state.get("setup") != setup:
            old = state.get("setup", {})
            diff = sorted(k for k in set(old) | set(setup) if old.get(k) != setup.get(k))
            raise ValueError(f"Checkpoint {checkpoint} was written by a run with a different setup "
                             f"(differs in {diff}); resume with the same settings, or {FRESH_RUN_HINT}")
        # the strategy is rebuilt, not unpickled: a fresh one replays the run's asks and tells (checkpoint.py)
        state["strategy"] = fresh_strategy()
        with section("checkpoint replay"):
            replay(state["strategy"], state["log"], state["asked"], checkpoint)
        return state, True
    state = {"setup": setup, "strategy": fresh_strategy(), "cache": {}, "U": np.zeros((0, grid.search.dim)),
             "F": [], "P": [], "history": [], "evaluations": 0, "generation": 0, "hits": 0, "stall": 0,
             "nonfinite": 0, "worst_G": None, "best": None, "seconds": 0.0, "stop_reason": None, "asked": None,
             "strategy_calls": 0, "log": []}
    return state, False


# ------------------------------------------------------------------------------ the generation loop
def _stop_reason(state, strategy, max_evals, max_stall_generations) -> str | None:
    if state["evaluations"] >= max_evals:
        return "max_evals"
    if strategy.stop():
        return ",".join(f"{strategy.name}:{k}" if strategy.name == "cma" else str(k) for k in strategy.stop())
    if state["stall"] >= max_stall_generations:
        return "stalled"
    return None


def _run_generations(grid: _Grid, state, objective, max_evals, max_stall_generations, checkpoint, progress,
                     callback) -> None:
    """Generations until a stop condition; updates ``state`` (incl. seconds and stop_reason) in place."""
    strategy = state["strategy"]
    t0 = time.perf_counter()
    seconds_before = state["seconds"]
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=max_evals, initial=min(state["evaluations"], max_evals), unit="eval",
                   desc=f"optimize[{strategy.name}]", leave=False, dynamic_ncols=True)
    warned = [False]                  # the non-finite warning is given once per run
    stop_reason = None
    unsaved = 0
    last_save = t0                    # the first checkpoint after CHECKPOINT_SECONDS, as every later one
    snap, written = None, True        # the state after the last completed generation; whether on disk
    try:
        while True:
            stop_reason = _stop_reason(state, strategy, max_evals, max_stall_generations)
            if stop_reason:
                break
            entry, new, partial = _generation(grid, state, objective, max_evals, warned)
            state["seconds"] = seconds_before + time.perf_counter() - t0
            # At most one checkpoint per CHECKPOINT_SECONDS: encoding the growing state and an fsync per
            # generation was a visible part of a 2,000-evaluation run, more on slower disks. A generation
            # answered wholly from the cache is not worth an fsync either: replaying it after a crash costs no
            # evaluation and, with the same cache and random state, gives the same result. Between writes the
            # latest state is kept as a snapshot (lengths and references, no copy: serialising the state each
            # generation added up over a run), written when the run raises, so only a kill (SIGKILL, power) can
            # lose up to the last second.
            unsaved += 1
            if checkpoint is not None:
                with section("checkpoint"):
                    snap, written = snapshot(state), False
                    now = time.perf_counter()
                    if (new or unsaved >= 10) and now - last_save >= CHECKPOINT_SECONDS:
                        write_snapshot(checkpoint, snap, state)
                        written, last_save, unsaved = True, now, 0
            if bar is not None:
                bar.update(len(new))
                if state["best"]:
                    bar.set_postfix(best=f"{state['best']['F']:.6g}", refresh=False)
            if partial:
                stop_reason = "max_evals"
                break
            if callback is not None:
                info = dict(entry, best_vector=None if not state["best"] else state["best"]["X"].copy())
                if callback(info):
                    stop_reason = "callback"
                    break
    except BaseException:
        # the last completed generation, not the one that raised, with the strategy as it is now when that
        # matches: unchanged since, or a completed ask whose batch the resumed run then scores first. An
        # interruption inside the strategy's ask or tell (Ctrl-C) leaves the last written checkpoint.
        if snap is not None and not written:
            calls = state["strategy_calls"] - snap["values"]["strategy_calls"]
            if calls == 0 or (calls == 1 and state["asked"] is not None):
                write_snapshot(checkpoint, snap, state, asked=state["asked"], strategy_calls=state["strategy_calls"])
        raise
    finally:
        if bar is not None:
            bar.close()
    state["seconds"] = seconds_before + time.perf_counter() - t0
    state["stop_reason"] = stop_reason


def _evaluate(objective, X, new, keys, P, state) -> None:
    """Score the rows ``new`` of X (not yet cached) in one objective call; record them in ``state``."""
    Xn = np.ascontiguousarray(X[new])
    with section("scoring (objective)"):
        Fn = objective(Xn)
    try:
        Fn = np.asarray(Fn, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"objective returned {type(Fn).__name__}, not numbers; it must return "
                         f"one float per row, shape ({len(new)},)") from None
    if Fn.shape != (len(new),):
        raise ValueError(f"objective returned shape {Fn.shape} for a batch of {len(new)} candidates "
                         f"(X shape {Xn.shape}); it must return one score per row, shape "
                         f"({len(new)},)")
    for i, f in zip(new, Fn):
        state["cache"][keys[i]] = float(f)
        state["F"].append(float(f))
        state["P"].append(float(P[i]))
    state["evaluations"] += len(new)


def _generation(grid: _Grid, state, objective, max_evals, warned) -> tuple[dict, list, bool]:
    """Ask, snap, score the new grid points, rank (penalties, failed scores), tell; returns (history entry,
    rows scored, whether the budget cut the generation short)."""
    strategy, cache, free, lam = state["strategy"], state["cache"], grid.free, grid.penalty_weight
    if state.get("asked") is None:
        sigma = strategy.sigma
        state["strategy_calls"] = state.get("strategy_calls", 0) + 1   # counted before: a call may not return
        state["asked"] = {"K": strategy.ask(), "sigma": sigma}
        state["log"].append(("a", state["asked"]["K"]))     # what a resumed run replays (checkpoint.py)
    # else a resumed run: the batch the interrupted run had asked for (checkpoint.py)
    Kf, sigma = state["asked"]["K"], state["asked"]["sigma"]
    n = len(Kf)
    K = np.repeat(grid.kmin[None], n, axis=0)
    K[:, free] = np.clip(np.rint(Kf), grid.kmin[free], grid.kmax[free]).astype(np.int64)
    U = grid.search.grid_values(K, grid.delta)    # searched coordinates
    poses = grid.search.to_poses(U)               # (n, L, 6)
    X = grid.space.from_poses(poses)              # the user's vectors
    P = total_penalty(grid.cons, poses)
    keys = [row.tobytes() for row in X]
    new, seen = [], set()
    for i, k in enumerate(keys):
        if k not in cache and k not in seen:
            seen.add(k)
            new.append(i)
    left = max_evals - state["evaluations"]
    partial = len(new) > left
    if partial:
        new = new[:left]
    hits = n - len(seen)
    if new:
        _evaluate(objective, X, new, keys, P, state)
        state["U"] = np.concatenate([state["U"], U[new]])
    state["hits"] += hits

    # values of this generation (rows cut by the budget stay unknown)
    F = np.array([cache.get(k, np.nan) for k in keys])
    known = np.array([k in cache for k in keys])
    fin = np.isfinite(F)
    G = -F + lam * P
    if fin.any():
        gmax = float(G[fin].max())
        state["worst_G"] = gmax if state["worst_G"] is None else max(state["worst_G"], gmax)
    bad = known & ~fin
    if bad.any():
        _rank_failed(state, G, F, P, X, bad, new, lam, warned)

    # incumbent: feasible first, then lowest G; ties keep the earlier one
    for i in np.flatnonzero(known & fin):
        rank = (0 if P[i] == 0 else 1, float(G[i]))
        b = state["best"]
        if b is None or rank < b["rank"]:
            state["best"] = {"rank": rank, "X": X[i].copy(), "U": U[i].copy(), "F": float(F[i]),
                             "G": float(G[i]), "P": float(P[i])}

    state["asked"] = None             # told (or, cut by the budget, dropped: a resume asks anew, as before)
    if not partial:
        state["strategy_calls"] += 1
        strategy.tell(G)
        state["log"].append(("t", G.copy()))
    kf = known & fin
    entry = {"generation": state["generation"], "evaluations": state["evaluations"], "new": len(new),
             "cache_hits": hits,
             "best": _num(float(F[kf].max())) if kf.any() else None,
             "mean": _num(float(F[kf].mean())) if kf.any() else None,
             "best_G": _num(float(G[kf].min())) if kf.any() else None,
             "best_so_far": state["best"]["F"] if state["best"] else None,
             "n_feasible": int(np.sum(kf & (P == 0))), "n_nonfinite": int(bad.sum()),
             "sigma": sigma}
    state["history"].append(entry)
    state["generation"] += 1
    state["stall"] = 0 if new else state["stall"] + 1
    return entry, new, partial


def _rank_failed(state, G, F, P, X, bad, new, lam, warned) -> None:
    """Give non-finite scores a G below every finite one seen (in place), and warn once per run."""
    state["nonfinite"] += int(np.sum(bad[new])) if new else 0
    if state["worst_G"] is None:
        if state["generation"] == 0:
            raise ValueError(f"objective returned no finite score for any of the {int(bad.sum())} "
                             f"candidates of the first generation (e.g. {F[bad][:3].tolist()}); "
                             f"check the objective on X such as {X[bad][0].tolist()}")
        worst = 0.0
    else:
        worst = state["worst_G"]
    G[bad] = worst + max(1.0, abs(worst)) + lam * P[bad]
    if not warned[0]:
        # stacklevel: _rank_failed <- _generation <- _run_generations <- optimize <- the caller
        warnings.warn(f"objective returned non-finite scores for {int(bad.sum())} candidates in "
                      f"generation {state['generation']}; they are ranked below all finite ones "
                      f"and never chosen as best", RuntimeWarning, stacklevel=5)
        warned[0] = True


# ------------------------------------------------------------------------------ result
def _certificate_inputs(state, search, steps, lam, delta) -> tuple:
    """(U, G, feasible, keywords) of ``certify`` for the evaluated points, G = -F + lambda P."""
    P = np.asarray(state["P"])
    G = -np.asarray(state["F"]) + lam * P
    kw = dict(delta=float(np.max(steps)), side_lengths=search.widths, delta_l2=search.covering_radius(delta))
    return state["U"], G, P == 0, kw


def _submit_certificate(executor, state, search, steps, lam, delta):
    """The certificate handed to ``executor`` (a Future), or None where it cannot take it (a broken pool)."""
    U, G, feas, kw = _certificate_inputs(state, search, steps, lam, delta)
    try:
        return executor.submit(certify, U, G, feas, **kw)
    except RuntimeError:        # a broken pool (BrokenProcessPool) or one shut down: computed here instead
        return None


def _collect_certificate(pending) -> dict | None:
    """The certificate a Future computed, or None where its process died (computed here instead)."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return pending.result()
    except BrokenProcessPool:
        return None


def _result(state, space, search, cons, strategy, delta, steps, lam, seed, resumed, checkpoint,
            pending=None) -> OptimizeResult:
    b = state["best"]
    if b is None:
        raise ValueError(f"objective returned no finite score in {state['evaluations']} evaluations")
    if b["P"] > 0:
        warnings.warn(f"no feasible placement was found in {state['evaluations']} evaluations; the best "
                      f"infeasible one (penalty {b['P']:.3g}) is returned. Raise penalty_weight or max_evals, "
                      f"or relax the constraints", RuntimeWarning, stacklevel=3)
    with section("certificate"):
        cert = None if pending is None else _collect_certificate(pending)
        if cert is None:
            U, G, feas, kw = _certificate_inputs(state, search, steps, lam, delta)
            cert = certify(U, G, feas, **kw)
    cert["penalty_weight"] = lam
    n = state["evaluations"]
    hits = state["hits"]
    cache = {"hits": hits, "misses": n, "size": len(state["cache"]),
             "hit_rate": hits / (hits + n) if hits + n else 0.0, "nonfinite": state["nonfinite"]}
    return OptimizeResult(
        best_vector=b["X"].copy(), best_placement=space.to_placement(b["X"], name="optimized"),
        best_score=b["F"], best_G=b["G"], best_penalty=b["P"], feasible=b["P"] == 0,
        history=[dict(h) for h in state["history"]], evaluations=n, generations=state["generation"],
        seconds=state["seconds"], certificate=cert, seed=seed, cache=cache, stop_reason=state["stop_reason"],
        method=strategy.name, popsize=strategy.popsize, space=space, search_space=search,
        delta=dict(delta) if isinstance(delta, Mapping) else float(delta), penalty_weight=lam,
        resumed=resumed, checkpoint=None if checkpoint is None else str(checkpoint))


def _multistart(objective, space, constraints, restarts: int, callback, kw: dict) -> OptimizeResult:
    """``restarts + 1`` independent runs (seeds ``seed + r``); the best one, with totals (see ``optimize``)."""
    from dataclasses import replace

    seed = _check_int("seed", kw.pop("seed"), 0)
    stopped = [False]

    def cb(info):
        if callback is not None and callback(info):
            stopped[0] = True
            return True
        return False

    runs: list[OptimizeResult] = []
    for r in range(restarts + 1):
        runs.append(optimize(objective, space, constraints, seed=seed + r, callback=cb, **kw))
        if stopped[0]:
            break
    # the penalised objective G = -F + lambda P decides, as inside a run
    i_best = min(range(len(runs)), key=lambda i: (runs[i].best_G, -runs[i].best_score))
    best = runs[i_best]
    history = [dict(h, run=r) for r, res in enumerate(runs) for h in res.history]
    summary = [{"seed": res.seed, "best_score": res.best_score, "feasible": res.feasible,
                "evaluations": res.evaluations, "stop_reason": res.stop_reason} for res in runs]
    return replace(best, history=history, evaluations=sum(res.evaluations for res in runs),
                   generations=sum(res.generations for res in runs), seconds=sum(res.seconds for res in runs),
                   seed=seed, stop_reason="callback" if stopped[0] else f"restarts: {best.stop_reason}",
                   extra={**best.extra, "runs": summary, "best_run": i_best})
