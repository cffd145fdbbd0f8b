"""Checkpoint overhead of a run: a 2,000-evaluation CMA-ES run as `place3d optimize` runs it (4 LiDARs,
MinDistance 0.2, x0 center, sigma0 0.15) on a synthetic rugged objective that sleeps 1.6 ms per call (about
the H100's scoring), with a checkpoint; prints the profile's checkpoint, ask/tell and certificate rows, the
run's wall time and a digest of the result (equal digests: the same search).

    PYTHONPATH=. python3 bench/checkpoint_overhead.py LABEL
"""
import hashlib, sys, time, tempfile, os
import numpy as np
from place3d_kernels.optimize import SearchSpace, MinDistance, optimize
from place3d_kernels.placement import Placement
from place3d_kernels.profiling import profile
space = SearchSpace(n_lidars=4)
T = space.from_placement(Placement.load("pyramid"))
def obj(X):
    time.sleep(0.0016)
    h = np.array([int.from_bytes(hashlib.blake2b(r.tobytes(), digest_size=4).digest(), "little") for r in X]) / 2**32
    return -np.sum((X - T) ** 2, axis=1) * 0.01 + 0.002 * h
d = tempfile.mkdtemp()
with profile(print_table=False) as p:
    t = time.perf_counter()
    r = optimize(obj, space, [MinDistance(0.2)], max_evals=2000, sigma0=0.15, x0=Placement.load("center"), seed=0,
                 progress=False, checkpoint=os.path.join(d, "c.pkl"))
    wall = time.perf_counter() - t
row = {k[-1]: v for k, v in p.totals.items()}
dig = hashlib.sha1(repr((r.best_vector.tolist(), r.best_score, r.history, r.certificate)).encode()).hexdigest()[:12]
print(f"{sys.argv[1]} wall {wall:.3f} checkpoint {row['checkpoint'][0]*1e3:.1f} ms/{row['checkpoint'][1]} "
      f"ask/tell {row['CMA-ES ask/tell'][0]*1e3:.1f} ms certificate {row['certificate'][0]*1e3:.1f} ms gens {r.generations} digest {dig}")
