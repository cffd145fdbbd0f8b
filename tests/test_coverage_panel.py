"""coverage.png drawn over a kept left panel (``optimize.plots.draw_coverage``) is the file a full draw writes."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")


def _view(seed, n=60):
    rng = np.random.default_rng(seed)
    entropy = rng.random((n, n)).astype(np.float32) * 3
    covered = rng.random((n, n)) < 0.4
    return entropy, covered, int(covered.sum() * 7), (-6.05, 5.95, -6.05, 5.95)


def test_a_figure_over_the_kept_panel_has_the_bytes_of_a_full_draw(tmp_path, monkeypatch):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from place3d_kernels.optimize import plots

    monkeypatch.setattr(plots, "_PANELS", {})
    draws = []
    full_draw = FigureCanvasAgg.draw
    monkeypatch.setattr(FigureCanvasAgg, "draw", lambda self: (draws.append(1), full_draw(self))[1])
    a, b = _view(1), _view(2)
    # one P-SOG, two rigs (the second over the kept panel); another P-SOG; the first one's panel again
    cases = [(a, "rig one", 1), (a, "rig two", 0), (b, "rig one", 1), (a, "rig three", 0)]
    for k, ((entropy, covered, n, extent), name, full_draws) in enumerate(cases):
        covered = np.roll(covered, k, axis=0)                     # each rig covers other columns
        draws.clear()
        kept = plots.draw_coverage(entropy, covered, n + k, extent, name, tmp_path / f"kept{k}.png")
        assert len(draws) == full_draws, k                        # the panel was drawn only when not kept
        draws.clear()
        full = plots.draw_coverage(entropy, covered, n + k, extent, name, tmp_path / f"full{k}.png", reuse=False)
        assert len(draws) == 1
        assert kept.read_bytes() == full.read_bytes(), k
    assert len(plots._PANELS) == 2


def test_kept_panels_are_few_and_keyed_by_what_they_show(tmp_path, monkeypatch):
    from place3d_kernels.optimize import plots

    monkeypatch.setattr(plots, "_PANELS", {})
    entropy, covered, n, extent = _view(3, n=20)
    for i in range(plots.PANELS_KEPT + 2):
        plots.draw_coverage(entropy + i, covered, n, extent, "rig", tmp_path / "c.png")
    assert len(plots._PANELS) == plots.PANELS_KEPT
    # the same values as another type, or another extent, are another panel
    assert plots._panel_key(entropy, extent) != plots._panel_key(entropy.astype(np.float64), extent)
    assert plots._panel_key(entropy, extent) != plots._panel_key(entropy, (-6.0, 5.95, -6.05, 5.95))
    assert plots._panel_key(entropy, extent) == plots._panel_key(entropy.copy(), tuple(np.float64(v) for v in extent))


def test_coverage_has_a_process_of_its_own_that_keeps_the_panel(tmp_path):
    """With plot processes, every coverage.png of a worker goes to the same process, so a later command
    of a resident server finds the panel an earlier one drew: two P-SOGs' figures leave two panels there."""
    from place3d_kernels.optimize import SearchSpace, plots
    from place3d_kernels.placement import Placement

    history = [{"evaluations": 10 * (i + 1), "best": -0.05 + 0.001 * i, "sigma": 0.3} for i in range(4)]
    entropy, covered, n, extent = _view(4, n=30)
    worker = plots.PlotWorker(processes=True)
    try:
        for k, run in enumerate("ab"):
            worker.submit(history, Placement.load("pyramid"), SearchSpace(n_lidars=4),
                          (entropy + k, covered, n, extent, run), tmp_path / run).result(timeout=120)
        assert len(worker.pool._processes) == plots.PLOT_PROCESSES + plots.HELPER_PROCESSES
        kept = worker.pool.submit_coverage(eval, "len(__import__('place3d_kernels.optimize.plots', "
                                                 "fromlist=['plots'])._PANELS)").result(timeout=60)
        assert kept == 2
    finally:
        worker.close()


def test_a_plot_worker_leaves_without_the_teardown():
    """The plot processes' initializer (_worker_started) makes their exit skip the interpreter's teardown:
    an exit handler registered before it never runs, what was printed still comes out, the status is 0."""
    import subprocess
    import sys

    code = ("import atexit; atexit.register(print, 'teardown ran'); "
            "from place3d_kernels.optimize import plots; plots._worker_started(); print('drawn', end='')")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout == "drawn"


def test_plot_processes_exit_once_closed(tmp_path):
    """A pool of plot processes started with that initializer draws its figures and, once closed, has no
    process left running, each ended with status 0."""
    from place3d_kernels.optimize import SearchSpace, plots
    from place3d_kernels.placement import Placement

    history = [{"evaluations": 10 * (i + 1), "best": -0.05 + 0.001 * i, "sigma": 0.3} for i in range(4)]
    entropy, covered, n, extent = _view(5, n=30)
    worker = plots.PlotWorker(processes=True)
    paths = worker.submit(history, Placement.load("pyramid"), SearchSpace(n_lidars=4),
                          (entropy, covered, n, extent, "rig"), tmp_path).result(timeout=120)
    procs = list(worker.pool._processes.values())
    worker.close()
    assert sorted(p.rsplit("/", 1)[1] for p in paths) == ["convergence.png", "coverage.png", "rig.png"]
    assert all((tmp_path / name).stat().st_size > 0 for name in ("convergence.png", "coverage.png", "rig.png"))
    assert len(procs) == plots.PLOT_PROCESSES + plots.HELPER_PROCESSES
    assert [p.exitcode for p in procs] == [0] * len(procs)


def test_a_panel_kept_ahead_gives_the_bytes_of_a_full_draw(tmp_path, monkeypatch):
    """keep_coverage_panel (what optimize sends to the coverage process once the P-SOG is built) keeps the
    left panel; the figure drawn later over it draws nothing whole and writes the full draw's bytes. A
    second call for the same P-SOG draws nothing."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from place3d_kernels.optimize import plots

    monkeypatch.setattr(plots, "_PANELS", {})
    entropy, covered, n, extent = _view(6)
    assert plots.keep_coverage_panel(entropy, extent) is True
    assert plots.keep_coverage_panel(entropy.copy(), extent) is False
    draws = []
    full_draw = FigureCanvasAgg.draw
    monkeypatch.setattr(FigureCanvasAgg, "draw", lambda self: (draws.append(1), full_draw(self))[1])
    kept = plots.draw_coverage(entropy, covered, n, extent, "rig", tmp_path / "kept.png")
    assert draws == []
    full = plots.draw_coverage(entropy, covered, n, extent, "rig", tmp_path / "full.png", reuse=False)
    assert kept.read_bytes() == full.read_bytes()


def test_the_worker_keeps_the_panel_in_its_coverage_process(tmp_path):
    """PlotWorker.keep_panel sends the panel to the coverage process; the figures drawn afterwards (the
    coverage view given as a function, called once the other two figures are submitted) are complete."""
    from place3d_kernels.optimize import SearchSpace, plots
    from place3d_kernels.placement import Placement

    history = [{"evaluations": 10 * (i + 1), "best": -0.05 + 0.001 * i, "sigma": 0.3} for i in range(4)]
    entropy, covered, n, extent = _view(7, n=30)
    worker = plots.PlotWorker(processes=True)
    try:
        worker.keep_panel(entropy, extent)
        kept = worker.pool.submit_coverage(eval, "len(__import__('place3d_kernels.optimize.plots', "
                                                 "fromlist=['plots'])._PANELS)").result(timeout=120)
        assert kept == 1
        paths = worker.submit(history, Placement.load("pyramid"), SearchSpace(n_lidars=4),
                              lambda: (entropy, covered, n, extent, "rig"), tmp_path).result(timeout=120)
        assert [p.rsplit("/", 1)[1] for p in paths] == ["convergence.png", "rig.png", "coverage.png"]
    finally:
        worker.close()
    full = plots.draw_coverage(entropy, covered, n, extent, "rig", tmp_path / "full.png", reuse=False)
    assert (tmp_path / "coverage.png").read_bytes() == full.read_bytes()
