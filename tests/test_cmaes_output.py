"""The CMA-ES strategy prints nothing on stdout (issue 33, item 6: pycma's NOTE lines during optimize).

pycma prints its ``NOTE (module=cma, ...)`` lines when ``cma.utilities.utils.global_verbosity`` is 0 or
more; that is one module-wide value, reset by every ``CMAEvolutionStrategy`` built in the process. Before,
a strategy built after ours with pycma's default verbosity made our search print on stdout.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.lazy_imports import import_cma
from place3d_kernels.optimize.cmaes import make_strategy


def _strategy():
    return make_strategy("cma", x0=[0.0, 0.0, 0.0], kmin=np.array([-5.0] * 3), kmax=np.array([5.0] * 3),
                         sigma0=0.3, widths_idx=np.array([10.0] * 3), popsize=6, seed=3)


def test_no_pycma_notes_after_another_strategy_reset_its_verbosity(capsys, monkeypatch):
    cma = import_cma()
    s = _strategy()
    cma.CMAEvolutionStrategy([0.0, 0.0], 1.0, {"seed": 1})   # pycma's default verbosity (3), module-wide
    capsys.readouterr()
    tell = s.es.tell

    def tell_with_note(*a, **k):
        # what pycma's tell does when the covariance's condition in coordinates exceeds its limit
        cma.utilities.utils.print_message("condition in coordinate system exceeded", iteration=s.es.countiter)
        return tell(*a, **k)

    monkeypatch.setattr(s.es, "tell", tell_with_note)
    for _ in range(3):
        X = s.ask()
        s.tell(np.sum(X * X, axis=1))
    assert capsys.readouterr().out == ""
    assert cma.utilities.utils.global_verbosity == 3          # the other strategy's setting is put back


def test_strategy_built_twice_replays_identically(capsys):
    """Pinning the verbosity changes nothing of the search itself."""
    runs = []
    for _ in range(2):
        s = _strategy()
        xs = []
        for _ in range(4):
            X = s.ask()
            xs.append(X)
            s.tell(np.sum((X - 1.0) ** 2, axis=1))
        runs.append(np.concatenate(xs))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert capsys.readouterr().out == ""
