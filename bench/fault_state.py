"""Fault table of docs/security.md ("Stored state and how it is verified"): kills, damaged files and full disks against stored state.

    PYTHONPATH=. python3 bench/fault_state.py [--kills 5] [--full DIR]

--full DIR: an (empty, small) file system to fill, e.g. ``mount -t tmpfs -o size=256k tmpfs DIR`` (root);
without it the full-disk rows are skipped. Prints one line per row. Backend warp:cpu, 4-frame town at 0.8 m.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PSOG_CHILD = textwrap.dedent("""
    import sys; sys.path.insert(0, {root!r})
    from place3d_kernels import scene as scenes
    from place3d_kernels.grid import DEFAULT_GRID, Grid
    from place3d_kernels.pipeline import scene_psog
    from place3d_kernels.sog import PSOG
    real = PSOG.save
    def save(self, path):
        print("saving", flush=True)
        return real(self, path)
    PSOG.save = save
    scene_psog(scenes.town(seed=0, n_frames=4), Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.8), "place3d_16ch",
               frames_per_subset=2, backend="warp:cpu", cache=sys.argv[1])
    print("done", flush=True)
""")

OPT_CHILD = textwrap.dedent("""
    import json, sys; sys.path.insert(0, {root!r})
    import numpy as np
    from place3d_kernels.optimize import MinDistance, SearchSpace, optimize
    def wavy(X):
        return -np.sum(np.sin(3 * X) ** 2 + 0.1 * X ** 2 + 0.3 * np.cos(7 * X[:, ::-1]), axis=1)
    sys.modules["place3d_kernels.optimize.optimizer"].CHECKPOINT_SECONDS = float(sys.argv[3])
    r = optimize(wavy, SearchSpace(n_lidars=4), [MinDistance(0.2)], checkpoint=sys.argv[1] or None,
                 resume=sys.argv[2] == "resume", max_evals=2430, seed=0, progress=False, delta=0.05)
    print(json.dumps({{"best": r.best_score, "evals": r.evaluations, "history": r.history}}))
""")


def _temps(folder) -> list:
    return [p for p in Path(folder).rglob("*") if ".p3tmp-" in p.name or ".tmp" in p.name]


def _psog(folder):
    from place3d_kernels import scene as scenes
    from place3d_kernels.grid import DEFAULT_GRID, Grid
    from place3d_kernels.pipeline import scene_psog

    return scene_psog(scenes.town(seed=0, n_frames=4), Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.8),
                      "place3d_16ch", frames_per_subset=2, backend="warp:cpu", cache=folder)


def kills_psog(n, tmp) -> str:
    ref = _psog(tmp / "ref")
    script = tmp / "psog_child.py"
    script.write_text(PSOG_CHILD.format(root=str(ROOT)))
    ok, landed = 0, 0
    for i in range(n):
        folder = tmp / f"k{i}"
        p = subprocess.Popen([sys.executable, str(script), str(folder)], stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL)
        assert p.stdout.readline().strip() == b"saving"
        time.sleep(random.uniform(0, 0.01))          # the save of this file takes some 10-30 ms here
        p.send_signal(signal.SIGKILL)
        p.wait()
        landed += not list(folder.glob("psog-*.json"))      # killed before the manifest was written
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            got = _psog(folder)
        same = got.voxels.tobytes() == ref.voxels.tobytes() and got.counts.tobytes() == ref.counts.tobytes()
        ok += same and not _temps(folder)
    return f"P-SOG cache write killed (SIGKILL 0-10 ms into the save): {ok} of {n} next runs identical with no temp " \
           f"file left ({landed} kills before the manifest was on disk)"


def kills_optimize(n, tmp) -> str:
    script = tmp / "opt_child.py"
    script.write_text(OPT_CHILD.format(root=str(ROOT)))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    ref = json.loads(subprocess.run([sys.executable, str(script), "", "fresh", "1"], capture_output=True,
                                    env=env, check=True).stdout.decode().splitlines()[-1])
    ok, at, killed = 0, [], 0
    for i in range(n):
        ck = tmp / f"run{i}.ckpt"
        p = subprocess.Popen([sys.executable, str(script), str(ck), "fresh", "0.2"],
                             env={**env, "PYTHONHASHSEED": str(100 + i)}, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL)
        from place3d_kernels.optimize.checkpoint import load_checkpoint

        target = random.randint(200, 2200)       # killed after the first checkpoint past a random count
        while p.poll() is None:
            try:
                if load_checkpoint(ck)["evaluations"] >= target:
                    break
            except (OSError, ValueError):
                pass
            time.sleep(0.002)
        p.send_signal(signal.SIGKILL)
        p.wait()
        killed += p.returncode == -signal.SIGKILL

        at.append(load_checkpoint(ck)["evaluations"])
        r = subprocess.run([sys.executable, str(script), str(ck), "resume", "0.2"], capture_output=True,
                           env={**env, "PYTHONHASHSEED": str(200 + i)})
        got = json.loads(r.stdout.decode().splitlines()[-1])
        ok += got == ref
    return (f"optimize (2,430 evaluations) SIGKILLed after a random evaluation count and resumed in a process of another hash "
            f"seed: {ok} of {n} identical to the uninterrupted run ({killed} killed before the end; checkpoints at "
            f"{sorted(at)} evaluations)")


def damaged(tmp, n_ckpt=200, n_psog=20) -> list:
    from place3d_kernels.optimize import MinDistance, SearchSpace, optimize
    from place3d_kernels.optimize.checkpoint import CheckpointError, decode

    ck = tmp / "d.ckpt"
    optimize(lambda X: -np.sum(X ** 2, axis=1), SearchSpace(n_lidars=2), [MinDistance(0.3)], checkpoint=ck,
             max_evals=200, seed=1, progress=False)
    data = ck.read_bytes()
    rng = random.Random(0)
    found = 0
    for _ in range(n_ckpt):
        b = bytearray(data)
        b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        try:
            decode(bytes(b))
        except CheckpointError:
            found += 1
    rows = [f"checkpoint, one random bit flipped: {found} of {n_ckpt} refused with a one-line CheckpointError"]
    folder = tmp / "dp"
    ref = _psog(folder)
    (npz,) = folder.glob("psog-*.npz")
    good = npz.read_bytes()
    caught = 0
    for _ in range(n_psog):
        b = bytearray(good)
        b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        npz.write_bytes(bytes(b))
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            got = _psog(folder)
        warned = any("rebuilt" in str(x.message) for x in w)
        caught += warned and got.counts.tobytes() == ref.counts.tobytes()
    rows.append(f"P-SOG cache .npz, one random bit flipped: {caught} of {n_psog} rebuilt with one warning, "
                f"result identical")
    return rows


def full_disk(full: Path) -> list:
    """Real ENOSPC: ``full`` filled up to its last bytes, then each writer tried."""
    from place3d_kernels.atomic import WriteError, atomic_write_text
    from place3d_kernels.optimize import SearchSpace, optimize

    filler = full / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        while True:
            os.write(fd, b"\0" * 4096)
    except OSError:
        pass
    try:
        while True:
            os.write(fd, b"\0")
    except OSError:
        os.close(fd)
    rows = []

    def clean(tag, ok):
        rows.append(f"full disk, {tag}: {'one-line error, no temp, no empty output' if ok else 'FAILED'}")

    try:
        atomic_write_text(full / "out.json", "x" * 100_000)
        clean("atomic_write_text", False)
    except WriteError as e:
        clean("atomic_write_text", "\n" not in str(e) and "no space" in str(e) and not _temps(full)
              and not (full / "out.json").exists())
    try:
        optimize(lambda X: -np.sum(X ** 2, axis=1), SearchSpace(n_lidars=4), checkpoint=full / "c.ckpt",
                 max_evals=400, progress=False)
        clean("optimize checkpoint", False)
    except WriteError as e:
        clean("optimize checkpoint", "\n" not in str(e) and not _temps(full) and not (full / "c.ckpt").exists())
    r = subprocess.run([sys.executable, "-m", "place3d_kernels.cli", "evaluate", "--frames", "8", "--voxel-size",
                        "0.8", "--quiet", "center", "--resamples", "0", "--backend", "warp:cpu", "--lidar",
                        "place3d_16ch", "--output", str(full / "eval.json")],
                       capture_output=True, env=dict(os.environ, PYTHONPATH=str(ROOT),
                                                     PLACE3D_CACHE=str(full / "cache")))
    err = r.stderr.decode()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    clean(f"place3d evaluate --output and its P-SOG cache (exit {r.returncode}, {len(lines)} stderr lines)",
          r.returncode == 2 and "Traceback" not in err and not _temps(full) and not (full / "eval.json").exists()
          and "eval.json: no space left" in lines[-1] and len(lines) <= 3)
    filler.unlink()
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=5)
    ap.add_argument("--full", default=None)
    a = ap.parse_args()
    random.seed(1)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        os.environ["PLACE3D_CACHE"] = str(tmp / "cache")
        print(kills_psog(a.kills, tmp), flush=True)
        print(kills_optimize(a.kills, tmp), flush=True)
        for row in damaged(tmp):
            print(row, flush=True)
    if a.full:
        for row in full_disk(Path(a.full)):
            print(row, flush=True)


if __name__ == "__main__":
    main()
