"""What the command prints besides its results (issue 33, item 6, "Noise"): warnings and log lines as one
line each, only those that matter under --quiet; errors that name the command's options; no output
written before a bad --plot path is refused.

Before, a warning printed as Python prints it (``file.py:12: UserWarning: ...`` and the source line),
also under --quiet; ``evaluate --plot x.xyz`` wrote the JSON and then failed with exit 2.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import pytest

import place3d_kernels
from place3d_app import cli
from place3d_app.cli import main

OURS = str(Path(place3d_kernels.__file__).parent / "scene" / "loaders.py")
THEIRS = "/usr/lib/python3/site-packages/numpy/core/fromnumeric.py"


@pytest.fixture
def noisy_evaluate(monkeypatch):
    """``place3d evaluate`` replaced by a command that only warns and logs."""
    def fake(args):
        warnings.warn_explicit("3 of 5 shapes match no label rule and are class 0\n(pass --labels)",
                               UserWarning, OURS, 174)
        warnings.warn_explicit("invalid value encountered in divide", RuntimeWarning, THEIRS, 88)
        warnings.warn_explicit("old API", DeprecationWarning, OURS, 175)
        logging.getLogger("place3d_kernels.backends.opencl").info("compiling OpenCL kernels")
        logging.getLogger("place3d_kernels.pipeline").warning("P-SOG cache x not written: disk full")
        return 0

    monkeypatch.setattr(cli, "cmd_evaluate", fake)


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


def test_warnings_print_as_one_line_each(noisy_evaluate, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["evaluate"]) == 0
    err = _lines(capsys.readouterr().err)
    assert err == ["place3d: warning: 3 of 5 shapes match no label rule and are class 0 (pass --labels)",
                   "place3d: warning: invalid value encountered in divide (from numpy)",
                   "place3d: warning: old API",
                   "place3d: compiling OpenCL kernels",
                   "place3d: warning: P-SOG cache x not written: disk full"]


def test_quiet_keeps_only_the_warnings_that_matter(noisy_evaluate, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["evaluate", "--quiet"]) == 0
    err = _lines(capsys.readouterr().err)
    assert err == ["place3d: warning: 3 of 5 shapes match no label rule and are class 0 (pass --labels)",
                   "place3d: warning: P-SOG cache x not written: disk full"]


def test_handlers_are_put_back_after_the_command(noisy_evaluate):
    before = warnings.showwarning
    handlers = list(logging.getLogger("place3d_kernels").handlers)
    assert main(["evaluate", "--quiet"]) == 0
    assert warnings.showwarning is before
    assert logging.getLogger("place3d_kernels").handlers == handlers


def test_a_plot_path_of_another_format_is_refused_before_any_output(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = ["evaluate", "--frames", "12", "--voxel-size", "0.8", "--routes", "1", "--quiet", "--backend", "warp:cpu",
            "center", "line", "--output", "r.json", "--plot", "x.xyz"]
    assert main(argv) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--plot x.xyz" in err[0] and ".png" in err[0], err
    assert not (tmp_path / "r.json").exists()
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("psog-*.npz"))


def test_a_plot_without_intervals_is_refused_before_any_output(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "--quiet", "--interval", "none", "--plot", "p.png", "center"]) == 2
    assert "--interval none" in capsys.readouterr().err


def test_a_line_logged_while_another_thread_imports_tqdm_is_printed(monkeypatch, capsys):
    # a P-SOG save thread logged its full-disk warning while the command's thread was importing tqdm: the
    # module was in sys.modules without its class yet, and the line became a "--- Logging error ---" traceback
    import sys
    import types

    from place3d_app.messages import _emit

    monkeypatch.setitem(sys.modules, "tqdm", types.ModuleType("tqdm"))        # partially initialised
    _emit("place3d: warning: a line")
    assert capsys.readouterr().err == "place3d: warning: a line\n"
