"""One lock around every temporary change of the warning filters in the package.

``warnings.catch_warnings`` copies the process-wide filter list on entry and puts the copy back on exit,
so two threads inside it at once undo each other's filters (the Python docs call it not thread-safe):
``place3d optimize`` printed pycma's "Could not import matplotlib.pyplot" warning now and then, when the
OpenCL backend probe built a program on its thread (ignoring PyOpenCL's compiler warnings) while the main
thread imported pycma (ignoring that warning). Every such block in the package goes through ``ignoring``,
which holds one lock for its span, so the blocks nest instead of interleaving.
"""

from __future__ import annotations

import contextlib
import threading
import warnings

__all__ = ["ignoring", "LOCK"]

#: Held while a block of ``ignoring`` runs (re-entrant: such blocks may nest on one thread).
LOCK = threading.RLock()


@contextlib.contextmanager
def ignoring(category: type[Warning] = Warning):
    """Ignore warnings of ``category`` (default: all) for the block, without racing other threads' blocks."""
    with LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore", category)
        yield
