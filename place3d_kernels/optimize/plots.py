"""Figures of an optimisation: convergence curve and rig layout. Agg only; pyplot's state is untouched.

Both functions build a ``matplotlib.figure.Figure`` directly (no ``pyplot``), so they work headless and
never change the backend of an interactive session.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from place3d_kernels.placement import Placement

__all__ = ["plot_convergence", "plot_rig", "draw_coverage", "draw_outputs", "PlotWorker", "keep_worker"]

#: The pool a resident process keeps for every command's ``PlotWorker`` (``keep_worker``), or None.
_kept = None


def _figure(w, h):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=120)
    FigureCanvasAgg(fig)
    return fig


#: PNG writer settings: zlib level 1 (matplotlib's Pillow writer uses 6, whose compressing was a visible
#: part of a figure's time); the files grow only a little
PNG = {"compress_level": 1}


def _save(fig, path, margins: Mapping[str, float]) -> Path:
    """Place the axes at fixed ``margins`` (``Figure.subplots_adjust`` fractions, sized for each figure's
    labels) and write the figure. Measuring the labels instead (``tight_layout``) lays out every text
    once more before drawing: it took a large part of each figure's time (bench/README.md, "What the
    studies found", warm command and place3d serve), and ``bbox_inches="tight"`` drew every figure twice."""
    from place3d_kernels.atomic import atomic_savefig

    path = Path(path)
    fig.subplots_adjust(**margins)
    atomic_savefig(fig, path, pil_kwargs=PNG)      # never an empty or half PNG, even on a full disk
    return path


#: axes placement of each figure (fractions of the figure), in place of a measured layout
CONVERGENCE_MARGINS = {"left": 0.14, "right": 0.87, "bottom": 0.12, "top": 0.92}
RIG_MARGINS = {"left": 0.05, "right": 0.99, "bottom": 0.12, "top": 0.86, "wspace": 0.28}
COVERAGE_MARGINS = {"left": 0.07, "right": 0.99, "bottom": 0.1, "top": 0.93, "wspace": 0.08}


def _col(history, key):
    return np.array([np.nan if h.get(key) is None else float(h[key]) for h in history])


def plot_convergence(history: Sequence[Mapping], path, title: str = "CMA-ES placement search") -> Path:
    """Objective against evaluations: best so far, generation best and mean; step size on a second axis.

    Args:
        history: ``OptimizeResult.history`` (or its JSON form).
        path: output image (PNG, SVG, PDF by suffix).
    """
    if not history:
        raise ValueError("plot_convergence needs a non-empty history")
    ev = _col(history, "evaluations")
    fig = _figure(7, 4)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(ev, _col(history, "mean"), color="0.6", lw=1, label="generation mean")
    ax.plot(ev, _col(history, "best"), ".", color="tab:blue", ms=3, label="generation best")
    ax.plot(ev, _col(history, "best_so_far"), color="tab:red", lw=2, drawstyle="steps-post",
            label="best so far (feasible first)")
    ax.set_xlabel("objective evaluations (distinct grid points)")
    ax.set_ylabel("score F (higher is better)")
    ax.grid(alpha=0.3)
    sig = _col(history, "sigma")
    handles, labels = ax.get_legend_handles_labels()
    if np.isfinite(sig).any():
        ax2 = ax.twinx()
        ax2.semilogy(ev, sig, color="tab:green", lw=1, ls="--", label="sigma (relative)")
        ax2.set_ylabel("CMA-ES step size sigma")
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.legend(handles, labels, loc="lower right", fontsize=8)
    ax.set_title(title)
    return _save(fig, path, CONVERGENCE_MARGINS)


def _as_placements(baselines) -> list[Placement]:
    if baselines is None:
        return []
    if isinstance(baselines, Placement):
        return [baselines]
    if isinstance(baselines, Mapping):
        return [p if isinstance(p, Placement) else Placement(p, name=str(k)) for k, p in baselines.items()]
    out = []
    for b in baselines:
        out.append(b if isinstance(b, Placement) else Placement.load(b))
    return out


def _box(bounds, key, fallback):
    if bounds is None:
        return None
    b = bounds.bounds if hasattr(bounds, "bounds") else bounds
    if key in b:
        return tuple(float(t) for t in b[key])
    return fallback


def plot_rig(placement: Placement, path, baselines=None, bounds=None, title: str | None = None) -> Path:
    """Top view (x-y), side view (x-z) and front view (y-z, seen from ahead; roll drawn as each sensor's tilt).

    Args:
        placement: the rig to draw (highlighted, LiDARs numbered).
        path: output image.
        baselines: optional placements drawn faintly for comparison: Placements, shipped names
            (``"pyramid"``), or ``{name: Placement}``.
        bounds: optional search box (``SearchSpace`` or ``{name: (lower, upper)}``) drawn dashed.
    """
    if not isinstance(placement, Placement):
        placement = Placement(placement)
    others = _as_placements(baselines)
    fig = _figure(13, 4.4)
    views = [("top view", 0, 1, "x forward [m]", "y left [m]"),
             ("side view", 0, 2, "x forward [m]", "z up [m]"),
             ("front view (roll)", 1, 2, "y left [m]", "z up [m]")]
    keys = "xyz"
    colors = [f"C{i}" for i in range(1, 10)]
    for j, (name, a, b, xl, yl) in enumerate(views):
        ax = fig.add_subplot(1, 3, j + 1)
        ba, bb = _box(bounds, keys[a], None), _box(bounds, keys[b], None)
        if ba and bb:
            ax.add_patch(_rect(ba, bb))
        for k, o in enumerate(others):
            ax.scatter(o.poses[:, a], o.poses[:, b], s=18, marker="x", color=colors[k % len(colors)],
                       alpha=0.6, label=o.name or f"baseline {k}")
        p = placement.poses
        ax.scatter(p[:, a], p[:, b], s=60, color="tab:red", zorder=3, label=placement.name or "placement")
        for i, row in enumerate(p):
            ax.annotate(str(i + 1), (row[a], row[b]), textcoords="offset points", xytext=(5, 5), fontsize=8)
            if name.startswith("front"):
                # the sensor's horizontal plane tilted by roll (rotation about x; y left, z up)
                r, half = row[3], 0.12
                dy, dz = half * np.cos(r), half * np.sin(r)
                ax.plot([row[1] - dy, row[1] + dy], [row[2] - dz, row[2] + dz], color="tab:red", lw=2)
                if abs(r) > 1e-12:
                    ax.annotate(f"{r:+.2f} rad", (row[1], row[2]), textcoords="offset points", xytext=(5, -11),
                                fontsize=7, color="tab:red")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.set_aspect("equal", adjustable="datalim")
        if j == 0:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle(title or f"LiDAR rig: {placement.name or 'placement'}")
    return _save(fig, path, RIG_MARGINS)


def _rect(ra, rb):
    from matplotlib.patches import Rectangle

    return Rectangle((ra[0], rb[0]), ra[1] - ra[0], rb[1] - rb[0], fill=False, ls="--", color="0.5",
                     label="search box")


def draw_coverage(entropy2d, covered2d, n_covered: int, extent, name: str, path, reuse: bool = True) -> Path:
    """Top view of the voxels a rig covers (``covered2d``: columns with a covered voxel) over the P-SOG's
    column entropy (``entropy2d``), as coverage.png of ``place3d optimize``.

    The left panel (the entropy map and its colour bar) depends on the P-SOG only: with ``reuse`` its
    pixels are drawn once per P-SOG and process (``PANELS_KEPT`` kept) and later figures build and draw
    only the right panel over them (its place is the same whether the left one is built or not), which
    writes the same bytes as drawing the whole figure (``reuse=False``).
    """
    key = _panel_key(entropy2d, extent) if reuse and _plain_savefig() else None
    fig = _figure(11, 5)
    if key not in _PANELS:               # (drawn from the kept pixels otherwise: only its layout matters)
        _coverage_left(fig, entropy2d, extent)
    right = fig.add_subplot(1, 2, 2)
    right.imshow(np.where(covered2d, entropy2d, np.nan), origin="lower", extent=extent, cmap="magma",
                 interpolation="nearest")
    right.set_title(f"covered by {name}: {int(n_covered):,} voxels")
    right.set_xlabel("y (m, left)")
    if key is None:
        return _save(fig, path, COVERAGE_MARGINS)
    return _save_over_panel(fig, right, key, path)


def _coverage_left(fig, entropy2d, extent) -> None:
    ax = fig.add_subplot(1, 2, 1)
    # nearest: one grid column is about one pixel here, and the smoothing resampler ("antialiased")
    # cost a visible part of the figure's time and made the file several times larger
    im = ax.imshow(entropy2d, origin="lower", extent=extent, cmap="magma", interpolation="nearest")
    ax.set_title("P-SOG entropy, summed over z (nats)")
    ax.set_xlabel("y (m, left)")
    ax.set_ylabel("x (m, forward)")
    fig.colorbar(im, ax=ax, shrink=0.8)


def keep_coverage_panel(entropy2d, extent) -> bool:
    """Draw coverage.png's left panel for this P-SOG now and keep its pixels, as ``draw_coverage`` does on
    its first figure of a P-SOG, so that the figure drawn at the search's end builds only its right panel.
    ``place3d optimize`` sends it to the coverage process once the P-SOG is built. Returns whether it drew
    (not when the panel is kept already, nor when savefig settings forbid reuse)."""
    if not _plain_savefig():
        return False
    key = _panel_key(entropy2d, extent)
    if key in _PANELS:
        return False
    fig = _figure(11, 5)
    _coverage_left(fig, entropy2d, extent)
    right = fig.add_subplot(1, 2, 2)         # in place, so the layout is the figure's; never drawn here
    fig.subplots_adjust(**COVERAGE_MARGINS)
    _kept_panel(fig, right, key)
    return True


#: left panels of coverage.png kept per process (``_PANELS``): a resident server's recent P-SOGs
PANELS_KEPT = 4
_PANELS: dict = {}


def _panel_key(entropy2d, extent) -> tuple:
    """What the left panel is drawn from: the entropy map's shape, type and bytes (a digest), the extent."""
    import hashlib

    a = np.ascontiguousarray(entropy2d)
    return (a.shape, a.dtype.str, tuple(float(v) for v in extent),
            hashlib.blake2b(a.view(np.uint8).reshape(-1), digest_size=16).hexdigest())


def _plain_savefig() -> bool:
    """Whether ``savefig`` would write the canvas as drawn (matplotlib's default savefig settings), the
    condition for ``_save_over_panel`` to write the same file."""
    import matplotlib as mpl

    rc = mpl.rcParams
    return (rc["savefig.dpi"] == "figure" and rc["savefig.facecolor"] == "auto" and rc["savefig.edgecolor"] == "auto"
            and not rc["savefig.transparent"] and rc["savefig.bbox"] is None)


def _save_over_panel(fig, top, key, path) -> Path:
    """Write ``fig`` as ``_save`` does, drawing only the axes ``top`` over the kept pixels of the rest.

    The figure draws its axes in the order they were added and ``top`` was added last, so the rest drawn
    alone and then ``top`` drawn over it are the same operations on the same pixels as one full draw.
    The file is written as matplotlib's Agg ``print_png`` writes a drawn canvas.
    """
    import matplotlib.image as mimage

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.subplots_adjust(**COVERAGE_MARGINS)
    canvas = fig.canvas
    _kept_panel(fig, top, key)
    top.draw(canvas.get_renderer())
    mimage.imsave(path, canvas.buffer_rgba(), format="png", origin="upper", dpi=fig.dpi, pil_kwargs=PNG)
    return path


def _kept_panel(fig, top, key) -> None:
    """Put on ``fig``'s canvas its pixels without the axes ``top``: the ones kept for ``key``, else drawn
    now and kept (the most recently used last, ``PANELS_KEPT`` at most)."""
    canvas = fig.canvas
    panel = _PANELS.pop(key, None)
    if panel is None:
        top.set_visible(False)
        canvas.draw()
        top.set_visible(True)
        panel = canvas.copy_from_bbox(fig.bbox)
    else:
        canvas.restore_region(panel)
    _PANELS[key] = panel
    while len(_PANELS) > PANELS_KEPT:
        _PANELS.pop(next(iter(_PANELS)))


def draw_outputs(history, best: Placement, bounds, coverage: tuple, out) -> list[str]:
    """convergence.png, rig.png and coverage.png of ``place3d optimize`` in ``out`` (``coverage``: the
    arguments of ``draw_coverage`` before the path)."""
    from place3d_kernels.profiling import section

    out = Path(out)
    with section("plotting (worker)"):          # recorded when drawn on a thread of a profiled command
        paths = [plot_convergence(history, out / "convergence.png"),
                 plot_rig(best, out / "rig.png", baselines=None, bounds=bounds),
                 draw_coverage(*coverage, out / "coverage.png")]
    return [str(p) for p in paths]


def _worker_started() -> None:
    """Initializer of each plot worker process: its exit skips the interpreter's teardown.

    A worker leaves when its pool shuts down, by returning from multiprocessing's bootstrap into
    ``sys.exit``; the teardown that follows (every module of NumPy, matplotlib and Pillow, the loaded C
    libraries) was a visible part of each command, and ``PlotWorker.close`` waits for it (bench/README.md,
    "What the studies found", cold command: imports, tail and exit). Each figure is written and closed
    before its result goes back, and the bootstrap has already run multiprocessing's own exit steps and
    flushed the streams when the ``atexit`` handler registered here runs (before any registered earlier, as
    ``atexit`` goes last first), so it flushes the streams again and leaves with ``os._exit``. The exit
    status is 0 even for a worker that failed; a pool tells a dead worker by its process sentinel, not by
    the status.
    """
    from place3d_kernels.threads import leave_at_exit

    leave_at_exit()


def _warm_up() -> None:
    """Import matplotlib and draw one small figure to memory, so that the first real figure of a worker
    process finds fonts, the Agg renderer and the PNG writer loaded."""
    import io

    fig = _figure(1, 1)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [0, 1], label="x")
    ax.set_title("warm-up")
    ax.legend()
    fig.savefig(io.BytesIO(), format="png")


def _warm_up_helper() -> None:
    """Import what the helper process runs (the certificate's pair scan: SciPy's ``pdist``), ahead of it."""
    import scipy.spatial.distance  # noqa: F401 - imported to have it loaded

    import place3d_kernels.optimize.certificate  # noqa: F401


def _all_of(parts):
    """A Future of the results of ``parts`` in order; it raises the first part's error, if any."""
    import threading
    from concurrent.futures import Future

    done, lock = Future(), threading.Lock()

    def check(_):
        with lock:
            if done.done() or not all(p.done() for p in parts):
                return
            errors = [p.exception() for p in parts if p.exception() is not None]
            if errors:
                done.set_exception(errors[0])
            else:
                done.set_result([str(p.result()) for p in parts])

    for p in parts:
        p.add_done_callback(check)
    return done


#: worker processes where there are cores to spare: one per figure, drawn at the same time
PLOT_PROCESSES = 3
#: besides them, one helper process for the command's other work that needs a library its own process
#: would otherwise import (the optimiser's certificate: SciPy), started and warmed up with them
HELPER_PROCESSES = 1


def _spawn_can_start() -> bool:
    """Whether a spawned process can start here: it re-runs the main module from its file, which a
    program read from standard input or a string (``python -``, ``python -c``) does not have."""
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    return path is None or Path(path).is_file()


def _default_processes() -> bool:
    return (os.cpu_count() or 1) >= 4 and _spawn_can_start()


class _Pools:
    """The executors that draw the figures: on processes, ``PLOT_PROCESSES - 1`` for convergence.png and
    rig.png and one of its own for coverage.png, so that every figure of a resident process's commands
    finds the coverage panels that one process keeps (``draw_coverage``); else one thread for all. With
    processes there is also ``helper`` (``HELPER_PROCESSES``; None with a thread), which runs the
    optimiser's certificate (``optimize(certificate_executor=...)``) so that the command's own process never
    imports SciPy.

    ``submit`` and ``shutdown`` act as an executor's (``submit`` on the first executor, ``submit_coverage``
    on the second); ``_processes`` maps the pids of all, as ``ProcessPoolExecutor._processes`` does.
    """

    def __init__(self, processes: bool):
        from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

        if not processes:
            self.figures = self.coverage = ThreadPoolExecutor(1, thread_name_prefix="place3d-plots")
            self.helper = None
            return
        import multiprocessing

        spawn = multiprocessing.get_context("spawn")
        self.figures = ProcessPoolExecutor(PLOT_PROCESSES - 1, mp_context=spawn, initializer=_worker_started)
        self.coverage = ProcessPoolExecutor(1, mp_context=spawn, initializer=_worker_started)
        self.helper = ProcessPoolExecutor(HELPER_PROCESSES, mp_context=spawn, initializer=_worker_started)
        for _ in range(PLOT_PROCESSES - 1):    # each submit finds no idle worker: one process each
            self.figures.submit(_warm_up)
        self.coverage.submit(_warm_up)
        self.helper.submit(_warm_up_helper)

    def _executors(self):
        if self.coverage is self.figures:
            return [self.figures]
        return [self.figures, self.coverage] + ([self.helper] if self.helper is not None else [])

    def submit(self, fn, *args):
        return self.figures.submit(fn, *args)

    def submit_coverage(self, fn, *args):
        return self.coverage.submit(fn, *args)

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        for e in self._executors():
            e.shutdown(wait=wait, cancel_futures=cancel_futures)

    def check(self, timeout: float) -> None:
        """A no-op round trip through each executor (at the same time): raises if a process died."""
        for f in [e.submit(int) for e in self._executors()]:
            f.result(timeout=timeout)

    @property
    def _processes(self) -> dict:
        return {pid: p for e in self._executors() for pid, p in (getattr(e, "_processes", None) or {}).items()}


def _new_pool(processes: bool) -> _Pools:
    return _Pools(processes)


def keep_worker() -> bool:
    """Start the plot pool every later ``PlotWorker()`` of this process shares (``place3d serve``).

    A resident process calls it at start and after each command: the pool (processes on 4 or more cores,
    else a thread, as for one command) then has matplotlib imported before a command needs it, instead of
    each command spawning processes that import NumPy, the package and matplotlib again (a large part of a
    warm command). Call it between commands only (``place3d serve`` calls it before each): a process spawned
    during one would inherit that command's standard streams. A pool found broken (a process died) is
    replaced.

    Returns:
        True when a new pool was started (the first call, or after a broken one).
    """
    global _kept
    if _kept is not None:
        try:
            _kept.check(timeout=60)                       # a no-op round trip: raises if a process died
            return False
        except Exception:  # noqa: BLE001 - BrokenProcessPool or a hung worker: start a fresh one
            _kept.shutdown(wait=False, cancel_futures=True)
    processes = _default_processes()
    _kept = _new_pool(processes)
    if not processes:
        _kept.submit(_warm_up)
    return True


class PlotWorker:
    """Draws the outputs of ``place3d optimize`` beside the main thread.

    Where the machine has cores to spare (4 or more) these are ``PLOT_PROCESSES`` processes of their own,
    started with the command so that importing matplotlib and a first drawing (a visible part of a command)
    overlap the search, and each figure is drawn in its own process (coverage.png always in the same one,
    which keeps the P-SOG's panel: ``_Pools``), neither waiting for the main thread's Python (the GIL) nor
    slowing it; elsewhere (a 2-core machine, where PoCL's scoring uses both cores) one thread draws them in
    turn. In a process that called ``keep_worker`` it uses that pool, and ``close`` waits for this worker's
    drawings only. A pool whose process died (or could not start) is replaced by a thread. ``submit``
    returns a Future whose ``result()`` is the list of paths, or re-raises a plotting error.
    """

    def __init__(self, processes: bool | None = None):
        if processes is None:
            processes = _default_processes()
        self.shared = _kept is not None and processes == _default_processes()
        self.pool = _kept if self.shared else _new_pool(processes)
        self.processes = bool(processes)
        self._futures = []

    @property
    def helper(self):
        """The helper process's executor (``_Pools``), or None where the figures are drawn on a thread."""
        return self.pool.helper if self.processes else None

    def keep_panel(self, entropy2d, extent) -> None:
        """Have the coverage process draw and keep coverage.png's left panel now (``keep_coverage_panel``),
        while the search runs; with a thread instead of processes, nothing (it would take the search's
        interpreter lock). A failure there is left to the figure, which then draws the panel itself."""
        if self.processes:
            from concurrent.futures.process import BrokenProcessPool

            try:
                self.pool.submit_coverage(keep_coverage_panel, entropy2d, extent)
            except BrokenProcessPool:
                pass                         # submit finds the broken pool and falls back to a thread

    def submit(self, history, best, bounds, coverage, out):
        """Draw the three figures; ``coverage`` is ``draw_coverage``'s arguments before the path, or a
        function returning them, called after the other two figures are handed to their processes."""
        # absolute: a kept pool's process (keep_worker) has the working directory of the server, not the command's
        out = Path(os.path.abspath(out))
        if not self.processes:
            coverage = coverage() if callable(coverage) else coverage
            f = self.pool.submit(draw_outputs, list(history), best, bounds, coverage, str(out))
        else:
            from concurrent.futures.process import BrokenProcessPool

            out.mkdir(parents=True, exist_ok=True)
            parts = []
            try:
                # convergence.png and rig.png first, while the coverage view is computed
                parts.append(self.pool.submit(plot_convergence, list(history), out / "convergence.png"))
                parts.append(self.pool.submit(plot_rig, best, out / "rig.png", None, bounds))
                coverage = coverage() if callable(coverage) else coverage
                # coverage.png in its own process, which keeps the P-SOG's panel between commands
                parts.append(self.pool.submit_coverage(draw_coverage, *coverage, out / "coverage.png"))
            except BrokenProcessPool:
                # a worker process died (killed, or it could not start): the figures are drawn on a thread,
                # once what was submitted is cancelled or done (two writers of one file could tear it)
                from concurrent.futures import wait

                for part in parts:
                    part.cancel()
                wait(parts)
                if not self.shared:
                    self.pool.shutdown(wait=False, cancel_futures=True)
                self.pool = _Pools(False)
                self.processes = self.shared = False
                return self.submit(history, best, bounds, coverage, out)
            f = _all_of(parts)                  # the paths in the order draw_outputs gives them
        self._futures.append(f)
        return f

    def close(self, cancel: bool = False) -> None:
        """Wait for the drawing (``cancel``: drop what has not started, as when the command failed)."""
        if not self.shared:
            self.pool.shutdown(wait=True, cancel_futures=cancel)
            return
        from concurrent.futures import wait

        if cancel:
            for f in self._futures:
                f.cancel()
        wait(self._futures)
