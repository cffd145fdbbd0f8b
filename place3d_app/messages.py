"""What a command prints besides its results: Python warnings and the library's log lines, one line each.

Without this, a warning came out as Python prints it: ``path/to/file.py:123: UserWarning: text`` and then
the source line that raised it, also under ``--quiet``; the library's log lines (``logging``) were lost
below WARNING and printed bare above it. While a command runs (``cli_output``):

* every warning that passes the warning filters (``-W``, ``PYTHONWARNINGS``) prints as
  ``place3d: warning: <message>`` on one line of stderr; one from another package says which
  (``(from numpy)``) and keeps its first line only (PyOpenCL's compiler warnings carry whole build logs);
* under ``--quiet`` only the warnings that matter print: those raised by place3d's own code, which name a
  cause in the user's inputs or results (a label rule that matched nothing, a cache rebuilt, a search that
  never left its start). Other packages' warnings and deprecation notices are dropped;
* the library's loggers (``place3d_kernels.*``) print INFO lines as ``place3d: <message>`` (e.g. that the
  OpenCL kernels are being compiled, or the size of a long simulation) and WARNING lines as
  ``place3d: warning: <message>``; under ``--quiet`` only WARNING and above.

Everything is put back when the command ends, so ``place3d serve`` and tests that call ``main`` in-process
keep their own handlers between commands.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import sys
import warnings
from pathlib import Path

__all__ = ["cli_output", "warning_line", "matters", "LIBRARY_LOGGERS"]

#: The loggers whose lines a command prints (the library logs under its module names).
LIBRARY_LOGGERS = ("place3d_kernels", "place3d_app")

#: Warnings about the code rather than the run: never shown under --quiet.
_CODE_CATEGORIES = (DeprecationWarning, PendingDeprecationWarning, FutureWarning, ImportWarning, ResourceWarning)


@functools.lru_cache(maxsize=1)
def _ours() -> tuple[str, ...]:
    import place3d_kernels

    return tuple(str(Path(m.__file__).resolve().parent) + "/" for m in (place3d_kernels, sys.modules[__package__]))


def _origin(filename: str) -> str | None:
    """None for place3d's own code, else the top-level package (or file stem) that raised the warning."""
    try:
        resolved = str(Path(filename).resolve())
    except (OSError, ValueError):
        resolved = str(filename)
    if resolved.startswith(_ours()):
        return None
    parts = Path(resolved).parts
    if "site-packages" in parts or "dist-packages" in parts:
        i = max(i for i, p in enumerate(parts) if p in ("site-packages", "dist-packages"))
        if i + 1 < len(parts):
            return Path(parts[i + 1]).stem
    return Path(resolved).stem


def matters(category: type[Warning], filename: str) -> bool:
    """Whether a warning prints under ``--quiet``: raised by place3d's own code and about the run, not the code."""
    return _origin(filename) is None and not issubclass(category, _CODE_CATEGORIES)


def warning_line(message, category: type[Warning], filename: str) -> str:
    """The one line a warning prints as."""
    text = str(message).strip()
    origin = _origin(filename)
    if origin is not None:
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        text = (lines[0] if lines else category.__name__) + (" (...)" if len(lines) > 1 else "")
        text += f" (from {origin})"
    return "place3d: warning: " + " ".join(text.split())


def _emit(line: str, file=None) -> None:
    """``line`` on its own line of ``file`` (stderr), above any progress bar being drawn there."""
    file = sys.stderr if file is None else file
    # tqdm's class, if it is imported: another thread may be importing it now (the module is in sys.modules
    # before its body has run), so it is looked up, never assumed (a logged line then printed plainly)
    bar = getattr(sys.modules.get("tqdm"), "tqdm", None)
    if bar is not None and getattr(bar, "_instances", None):
        bar.write(line, file=file)       # clears the bars, writes, draws them again
    else:
        print(line, file=file, flush=True)


class _LogFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        text = " ".join(record.getMessage().split())
        return f"place3d: {text}" if record.levelno < logging.WARNING else f"place3d: warning: {text}"


class _StderrHandler(logging.Handler):
    """Writes to the ``sys.stderr`` of the moment (the server swaps it per client; tests capture it)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            _emit(self.format(record))
        except Exception:  # noqa: BLE001 - logging must never break the command
            self.handleError(record)


@contextlib.contextmanager
def cli_output(quiet: bool = False):
    """Route warnings and the library's log lines to one-line messages on stderr for the block."""
    def show(message, category, filename, lineno, file=None, line=None):
        if quiet and not matters(category, filename):
            return
        _emit(warning_line(message, category, filename), file)

    handler = _StderrHandler(logging.WARNING if quiet else logging.INFO)
    handler.setFormatter(_LogFormatter())
    loggers = [logging.getLogger(name) for name in LIBRARY_LOGGERS]
    saved = [(lg, lg.level, lg.propagate) for lg in loggers]
    saved_show = warnings.showwarning
    warnings.showwarning = show
    for lg in loggers:
        lg.addHandler(handler)
        lg.setLevel(logging.INFO)
        lg.propagate = False            # printed here once, not again by a root handler
    try:
        yield
    finally:
        warnings.showwarning = saved_show
        for lg, level, propagate in saved:
            lg.removeHandler(handler)
            lg.setLevel(level)
            lg.propagate = propagate
