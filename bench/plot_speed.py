"""Warm-process drawing time of the three `place3d optimize` figures, with the shipped fixed margins and
with the measured layout used before (``tight_layout``), each drawing coverage.png whole, and with the
fixed margins and coverage.png over its kept P-SOG panel ("kept", as every command of a server after its
first on that P-SOG); 5 alternating rounds, then a profile of two; and a pure-Python loop as a yardstick
of the host's single-thread speed:

    python3 bench/plot_speed.py > bench/results/plot-speed-<machine>-<date>.txt
"""
import cProfile, io, pstats, time, sys
import numpy as np
from pathlib import Path
from place3d_kernels.optimize import plots
from place3d_kernels.placement import Placement
t = time.perf_counter(); s = 0
for i in range(3_000_000): s += i * i
print(f"python loop 3M: {time.perf_counter() - t:.3f} s")
t = time.perf_counter(); plots._warm_up(); print(f"warm-up: {time.perf_counter() - t:.3f} s")
rng = np.random.default_rng(0)
hist = [{"generation": g, "evaluations": 22 * (g + 1), "new": 22, "cache_hits": 0, "best": -0.03 - rng.random() * 0.003,
         "mean": -0.034 + g * 1e-5, "best_G": 0.03, "best_so_far": -0.0315, "sigma": 0.1 * 0.99 ** g} for g in range(92)]
best = Placement.load("pyramid")
ent = rng.random((400, 400)); cov = rng.random((400, 400)) < 0.3
out = Path("/tmp/plt"); out.mkdir(exist_ok=True)
fixed_save = plots._save


def measured_save(fig, path, margins):
    # the layout before 2026-11-25: every label measured (tight_layout) before the figure is drawn
    fig.tight_layout()
    return fixed_save(fig, path, margins)


# fixed margins (shipped) and a measured layout alternate, so drift on a shared machine hits both alike
times = {"fixed": [], "measured": [], "kept": []}
for rep in range(5):
    for mode, save in (("fixed", fixed_save), ("measured", measured_save), ("kept", fixed_save)):
        plots._save = save
        a = time.perf_counter(); plots.plot_convergence(hist, out / "c.png"); b = time.perf_counter()
        plots.plot_rig(best, out / "r.png", None, None); c = time.perf_counter()
        plots.draw_coverage(ent, cov, 123456, (-40, 40, -40, 40), "x", out / "v.png", reuse=mode == "kept")
        d = time.perf_counter()
        times[mode].append((b - a, c - b, d - c))
        print(f"{mode:8s} convergence {b - a:.3f} rig {c - b:.3f} coverage {d - c:.3f}")
plots._save = fixed_save
for mode, rows in times.items():
    med = [sorted(col)[len(col) // 2] for col in zip(*rows)]
    print(f"median of 5, {mode:8s}: convergence {med[0]:.3f} rig {med[1]:.3f} coverage {med[2]:.3f} "
          f"all three {sum(med):.3f} s")
pr = cProfile.Profile(); pr.enable()
plots.plot_rig(best, out / "r.png", None, None)
plots.draw_coverage(ent, cov, 123456, (-40, 40, -40, 40), "x", out / "v.png", reuse=False)
pr.disable(); st = io.StringIO(); pstats.Stats(pr, stream=st).sort_stats("tottime").print_stats(8); print(st.getvalue()[-2500:])
