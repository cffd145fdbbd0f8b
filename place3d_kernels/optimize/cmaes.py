"""Search strategies over the integer grid indices: pycma's CMA-ES, uniform random search, exhaustive grid.

All strategies work on integer grid indices ``k`` (grid value = ``k * delta``) of the free dimensions,
propose batches with ``ask()`` and learn from ``tell(values)`` (lower is better: values of G). Each is
deterministic given its constructor's arguments and the sequence of asks and tells, which is what makes
checkpoints resume bit for bit: a resumed run builds a fresh strategy and replays that sequence
(``optimize/checkpoint.py``); no strategy is ever pickled to disk.

CMA-ES runs pycma in index coordinates with ``integer_variables`` set for every dimension, so pycma
samples lattice points itself (its LB+IC integer handling keeps a minimum step size, so the search does
not stall below the grid spacing), with bounds ``[kmin, kmax]`` and per-coordinate initial standard
deviations ``sigma0 * (upper - lower) / delta`` (``CMA_stds``): ``sigma0`` is relative to the bound widths.
pycma draws its random numbers from NumPy's global generator (its samples and its integer centering)
through ``np.random``'s functions, looked up at each call. Around every pycma call the adapter points
those functions at a private ``RandomState`` of the strategy, so user code that touches ``np.random``
neither disturbs nor is disturbed by the search.
"""

from __future__ import annotations

import contextlib
import math
import sys
import warnings

import numpy as np

from place3d_kernels.profiling import section

__all__ = ["METHODS", "make_strategy", "default_popsize"]

METHODS = ("cma", "random", "grid")
_GRID_LIMIT = 10_000_000
#: pycma's ``verbose`` for every search: no output at all (its display, logs and notes are ours to print)
_VERBOSE = -9


def default_popsize(n: int) -> int:
    """pycma's default population size ``4 + floor(3 ln n)``."""
    return 4 + int(3 * math.log(max(n, 1)))


#: the names in ``np.random`` that draw from (or set) NumPy's legacy global generator: its bound methods
#: (``rand``, ``randn``, ``get_state``, ``seed``, ...). Pointing them at another ``RandomState`` for a pycma
#: call gives pycma that generator's numbers, as copying its state into the global generator and back did;
#: that copy (``get_state`` / ``set_state``, four per call) was a visible part of a warm optimise's host time
#: (bench/README.md, "What the studies found", warm command and place3d serve)
_GLOBAL_NAMES = tuple(n for n in dir(np.random) if getattr(getattr(np.random, n), "__self__", None)
                      is np.random.rand.__self__)


@contextlib.contextmanager
def quiet_pycma():
    """pycma prints nothing on stdout for the block.

    pycma's ``NOTE (module=cma, ...)`` lines (e.g. "condition in coordinate system exceeded", in ``tell``)
    are printed unless ``cma.utilities.utils.global_verbosity`` is below 0. That is one module-wide value,
    set by the ``verbose`` option of whichever ``CMAEvolutionStrategy`` was built last, so a strategy built
    elsewhere in the process (another search, the user's own code) with pycma's default verbosity made
    this search chat on stdout. It is pinned for every pycma call and put back after."""
    utils = sys.modules.get("cma.utilities.utils")
    if utils is None:
        yield
        return
    outer = utils.global_verbosity
    utils.global_verbosity = _VERBOSE
    try:
        yield
    finally:
        utils.global_verbosity = outer


def _global_randn(*shape):
    # pycma calls opts['randn'](lam, N). This function looks np.random.randn up at each call, so it draws
    # from the generator the strategy points np.random at (``_rng``); np.random.randn itself would be the
    # global RandomState's method, bound once.
    return np.random.randn(*shape)


class CMAStrategy:
    """pycma ask/tell on integer grid indices with an isolated random state."""

    name = "cma"

    def __init__(self, x0, kmin, kmax, sigma0: float, widths_idx, popsize: int | None, seed: int,
                 options: dict | None = None):
        from place3d_kernels.lazy_imports import import_cma

        with section("import cma"):
            cma = import_cma()  # the only import of pycma: only this strategy needs it

        self._rs = np.random.RandomState(seed)
        n = len(kmin)
        opts = {
            "bounds": [np.asarray(kmin, float).tolist(), np.asarray(kmax, float).tolist()],
            "integer_variables": list(range(n)),
            "CMA_stds": np.asarray(widths_idx, float).tolist(),
            "seed": np.nan,  # seeding happens through the private state above
            "randn": _global_randn,
            "verbose": _VERBOSE, "verb_log": 0, "verb_disp": 0,
        }
        if popsize is not None:
            opts["popsize"] = int(popsize)
        opts.update(options or {})
        with self._rng(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pycma chats about option choices; our options are deliberate
            self.es = cma.CMAEvolutionStrategy(np.asarray(x0, float).tolist(), float(sigma0), opts)
        self.popsize = int(self.es.popsize)
        self._asked = None

    @contextlib.contextmanager
    def _rng(self):
        module = vars(np.random)
        outer = {n: module[n] for n in _GLOBAL_NAMES}
        module.update({n: getattr(self._rs, n) for n in _GLOBAL_NAMES})
        try:
            with quiet_pycma():
                yield
        finally:
            module.update(outer)

    def ask(self) -> np.ndarray:
        with section("CMA-ES ask/tell"), self._rng():
            self._asked = self.es.ask()
        return np.array(self._asked, dtype=np.float64)

    def tell(self, values) -> None:
        with section("CMA-ES ask/tell"), self._rng():
            self.es.tell(self._asked, [float(v) for v in values])
        self._asked = None

    def stop(self) -> dict:
        return dict(self.es.stop())

    @property
    def sigma(self) -> float | None:
        return float(self.es.sigma)

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.es.mean, dtype=np.float64)


class RandomStrategy:
    """Uniform random grid points (a baseline for CMA-ES)."""

    name = "random"

    def __init__(self, kmin, kmax, popsize: int, seed: int):
        self.kmin, self.kmax = np.asarray(kmin), np.asarray(kmax)
        self.popsize = int(popsize)
        self.rng = np.random.default_rng(seed)

    def ask(self) -> np.ndarray:
        return self.rng.integers(self.kmin, self.kmax + 1, size=(self.popsize, len(self.kmin))).astype(np.float64)

    def tell(self, values) -> None:
        pass

    def stop(self) -> dict:
        return {}

    sigma = None


class GridStrategy:
    """Every grid point once, in lexicographic order, ``popsize`` at a time."""

    name = "grid"

    def __init__(self, kmin, kmax, popsize: int):
        self.kmin, self.kmax = np.asarray(kmin, np.int64), np.asarray(kmax, np.int64)
        self.shape = tuple(int(n) for n in self.kmax - self.kmin + 1)
        self.total = math.prod(self.shape)
        if self.total > _GRID_LIMIT:
            raise ValueError(f"method='grid' would enumerate {self.total:.3g} grid points (limit {_GRID_LIMIT:.0e}); "
                             f"use method='cma', fewer variables or a coarser delta")
        self.popsize = int(popsize)
        self.next = 0

    def ask(self) -> np.ndarray:
        idx = np.arange(self.next, min(self.next + self.popsize, self.total))
        self.next = int(idx[-1]) + 1 if len(idx) else self.next
        if not self.shape:
            return np.zeros((len(idx), 0))
        K = np.stack(np.unravel_index(idx, self.shape), axis=1) + self.kmin
        return K.astype(np.float64)

    def tell(self, values) -> None:
        pass

    def stop(self) -> dict:
        return {"grid_exhausted": self.total} if self.next >= self.total else {}

    sigma = None


def make_strategy(method: str, *, x0, kmin, kmax, sigma0, widths_idx, popsize, seed, options=None):
    """A strategy over the free dimensions (``kmin < kmax``).

    ``method='cma'`` on fewer than two free dimensions enumerates the grid instead (pycma does not
    support one-dimensional integer search); the returned strategy's ``name`` says which ran.
    """
    if method not in METHODS:
        raise ValueError(f"Unknown method {method!r}; available: {list(METHODS)}")
    n = len(kmin)
    pop = popsize if popsize is not None else default_popsize(max(n, 2))
    if method == "grid" or (method == "cma" and n < 2):
        return GridStrategy(kmin, kmax, pop)
    if method == "random":
        return RandomStrategy(kmin, kmax, pop, seed)
    return CMAStrategy(x0, kmin, kmax, sigma0, widths_idx, popsize, seed, options)
