"""CMA-ES's private generator (optimize.cmaes): np.random pointed at it for each pycma call, and restored."""


import numpy as np
import pytest

pytest.importorskip("cma")


def _strategy(seed=5):
    from place3d_kernels.optimize.cmaes import make_strategy

    return make_strategy("cma", x0=[0.0, 0.0, 0.0], kmin=np.array([-20, -20, -20]), kmax=np.array([20, 20, 20]),
                         sigma0=0.3, widths_idx=np.array([40.0, 40.0, 40.0]), popsize=8, seed=seed)


def _run(s, generations=6):
    out = []
    for g in range(generations):
        K = s.ask()
        out.append(K)
        s.tell(np.sum((K - 3.0) ** 2, axis=1) + 0.1 * g)
    return np.array(out)


def test_np_random_is_the_global_generator_again_after_each_call_even_one_that_raises():
    before = {n: getattr(np.random, n) for n in ("rand", "randn", "get_state", "set_state", "shuffle")}
    s = _strategy()
    _run(s, 2)
    with pytest.raises(RuntimeError, match="inside"):
        with s._rng():
            assert np.random.rand.__self__ is s._rs
            raise RuntimeError("inside")
    for n, f in before.items():
        assert getattr(np.random, n) == f and getattr(np.random, n).__self__ is f.__self__, n
