"""Imports that cost more than what a command uses from them.

``import cma`` (pycma 4.x) spends most of its time in two optional extras that CMA-ES ask/tell never
touches: ``cma.s`` imports ``matplotlib.pyplot`` for pycma's plotting shortcuts, and ``cma.fitness_models``
imports ``scipy.stats`` only for ``kendalltau``, used by the surrogate models of ``fmin_lq_surr``.
:func:`import_cma` imports pycma with both hidden from pycma's import only: a ``None`` entry in
``sys.modules`` makes an import of that name raise ImportError (Python docs, "The import system", 5.3.1 The
module cache), and pycma handles both ImportErrors itself. ``matplotlib`` itself is hidden too: ``cma.s``
writes ``from matplotlib import pyplot``, which imports the ``matplotlib`` package before it finds
``pyplot`` hidden, and in ``place3d optimize`` nothing else in the main process imports it (the figures are
drawn in processes of their own; with a thread instead, after the search). With it hidden too,
``import_cma`` after NumPy is several times faster (bench/README.md, "What the studies found", cold
command: imports, tail and exit).

* ``cma.fitness_models`` takes its documented fallback ``_kendall_tau`` ("implemented only to potentially
  remove dependency on scipy.stats"): the same coefficient, used only by ``fmin_lq_surr``.
* ``cma.s`` sets its plotting shortcuts to "not available" (``cma.s.figsave``; ``cma.plot`` still imports
  pyplot itself when called). This package never plots through pycma.

The entries are removed right after, so ``scipy.stats`` and matplotlib import normally for everyone else.
While they are in place, another thread's import of those names fails too: ``place3d optimize`` calls
this on the thread that has just imported the backend, before any thread draws, and ``place3d serve``
before it starts its plot pool. (A lazy module, ``importlib.util.LazyLoader``, does not help here: ``cma.s`` runs
``from matplotlib.pyplot import savefig`` at import, which loads the module at once.)

Neither step runs when the module is already imported (then it costs nothing to import anyway).
"""

from __future__ import annotations

import sys

from place3d_kernels.backends.warnfilters import ignoring

__all__ = ["import_cma", "HIDDEN_FROM_CMA"]

#: Optional pycma dependencies hidden while pycma is imported (see the module doc).
HIDDEN_FROM_CMA = ("scipy.stats", "matplotlib", "matplotlib.pyplot")


def import_cma():
    """``import cma`` without importing ``matplotlib.pyplot`` or ``scipy.stats`` (see the module doc).

    Returns:
        The ``cma`` package, as ``import cma`` gives it.

    Raises:
        ImportError: pycma is not installed (install with ``pip install cma``).
    """
    if "cma" in sys.modules:
        return sys.modules["cma"]
    hidden = [name for name in HIDDEN_FROM_CMA if name not in sys.modules]
    for name in hidden:
        sys.modules[name] = None
    try:
        # cma.s warns that its plotting shortcuts are unavailable; ``ignoring`` holds the package's lock on
        # the warning filters, which the OpenCL probe on another thread may be changing at the same time
        with ignoring():
            import cma
    finally:
        for name in hidden:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]
    return cma
