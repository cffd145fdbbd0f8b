"""``lazy_imports.import_cma``: pycma without matplotlib or scipy.stats, which stay importable afterwards."""

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("cma")


def _run(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip()


def test_import_cma_leaves_the_hidden_modules_out_and_importable():
    out = _run("""
        import sys
        import numpy as np
        from place3d_kernels.lazy_imports import HIDDEN_FROM_CMA, import_cma
        cma = import_cma()
        print(sorted(n for n in HIDDEN_FROM_CMA if n in sys.modules))      # none imported, no None left
        es = cma.CMAEvolutionStrategy([0.0, 0.0], 0.5, {"verbose": -9, "seed": 1})
        for _ in range(3):
            xs = es.ask()
            es.tell(xs, [float(np.sum(np.square(x))) for x in xs])
        print(es.countevals)
        import matplotlib.pyplot, scipy.stats                              # importable after
        print(matplotlib.pyplot.__name__, scipy.stats.__name__)
        print(import_cma() is cma)
    """)
    assert out.splitlines() == ["[]", str(3 * 6), "matplotlib.pyplot scipy.stats", "True"]


def test_import_cma_keeps_a_matplotlib_imported_before():
    out = _run("""
        import sys
        import matplotlib
        from place3d_kernels.lazy_imports import import_cma
        import_cma()
        print(sys.modules["matplotlib"] is matplotlib, "scipy.stats" in sys.modules)
    """)
    assert out == "True False"


def test_optimize_scipy_imports_leave_scipy_to_the_helper():
    """place3d optimize's early SciPy imports (pycma is imported on its own, the one the search waits for):
    SciPy's pdist only where the certificate is computed in this process (no helper process), scipy.special
    where intervals over routes take t quantiles."""
    out = _run("""
        import sys
        from place3d_app.commands.optimize import _scipy_imports
        _scipy_imports(False, False)
        print("cma" in sys.modules, any(n.startswith("scipy") for n in sys.modules))
        _scipy_imports(False, True)
        print("scipy.special" in sys.modules, any(n.startswith("scipy.spatial") for n in sys.modules))
        _scipy_imports(True, False)
        print("scipy.spatial.distance" in sys.modules)
    """)
    assert out.splitlines() == ["False False", "True False", "True"]
