"""Full disks and killed writers (issue 33, item 3): every writer goes through ``atomic.atomic_write``.

A write that fails (ENOSPC is simulated by an ``open`` whose file raises ``OSError(errno.ENOSPC)`` after
writing some bytes) leaves no temporary file, no empty or truncated output (the previous version stays),
and raises ``WriteError``: an ``OSError`` whose message is one line naming the path, which ``place3d``
prints without a traceback. Temporary files of killed writers are removed by the next write into their
folder.
"""

from __future__ import annotations

import builtins
import errno
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from place3d_kernels import atomic
from place3d_kernels.atomic import WriteError, atomic_write, atomic_write_text, remove_stale_temps, temp_name

ROOT = Path(__file__).resolve().parents[1]


class _FullFile:
    """A real file whose writes stop with ENOSPC after ``room`` bytes."""

    def __init__(self, f, room):
        self._f, self._room = f, room

    def write(self, b):
        if len(b) > self._room:
            self._f.write(b[:self._room])
            self._room = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._room -= len(b)
        return self._f.write(b)

    def __getattr__(self, k):
        return getattr(self._f, k)

    def __enter__(self):
        return self

    def __exit__(self, *a):
        self._f.close()


@pytest.fixture
def full_disk(monkeypatch):
    """Every file ``atomic_write`` opens has 100 bytes of room."""
    real = builtins.open
    monkeypatch.setattr(atomic, "open", lambda p, mode="r", *a, **k: _FullFile(real(p, mode, *a, **k), 100),
                        raising=False)


def _temps(folder: Path) -> list:
    return [p for p in folder.rglob("*") if atomic.TEMP_MARK in p.name or ".tmp" in p.name]


def test_enospc_leaves_no_temp_and_the_previous_file(tmp_path, full_disk):
    out = tmp_path / "o" / "result.json"
    with pytest.raises(WriteError) as e:
        atomic_write_text(out, "x" * 1000)
    msg = str(e.value)
    assert "\n" not in msg and str(out) in msg and "no space left on device" in msg and e.value.errno == errno.ENOSPC
    assert isinstance(e.value, OSError)
    assert not out.exists() and not _temps(tmp_path)                  # no empty output, no temp file


def test_enospc_keeps_the_previous_version(tmp_path, monkeypatch):
    out = tmp_path / "r.json"
    atomic_write_text(out, "old")
    real = builtins.open
    monkeypatch.setattr(atomic, "open", lambda p, mode="r", *a, **k: _FullFile(real(p, mode, *a, **k), 1),
                        raising=False)
    with pytest.raises(WriteError):
        atomic_write_text(out, "new content")
    assert out.read_text() == "old" and not _temps(tmp_path)


def test_a_writer_callback_that_fails_leaves_nothing(tmp_path):
    def boom(f):
        f.write(b"half")
        raise OSError(errno.EDQUOT, "quota")

    with pytest.raises(WriteError, match="quota"):
        atomic_write(tmp_path / "fig.png", boom)
    assert not list(tmp_path.iterdir())


def test_optimize_checkpoint_on_a_full_disk(tmp_path, full_disk):
    """``optimize`` left ``checkpoint.pkl.tmp`` behind on a full disk; now nothing, and a one-line error."""
    from place3d_kernels.optimize import SearchSpace, optimize

    def f(X):
        return -np.sum(X ** 2, axis=1)

    with pytest.raises(WriteError, match="run.ckpt: no space left"):
        optimize(f, SearchSpace(n_lidars=2), checkpoint=tmp_path / "run.ckpt", max_evals=40, progress=False)
    assert not list(tmp_path.iterdir())


def test_psog_and_subset_record_caches_on_a_full_disk_warn_in_one_line(tmp_path, full_disk, caplog):
    from place3d_kernels.grid import Grid
    from place3d_kernels.sog import PSOG
    from place3d_kernels.subset_records import _write_records
    from place3d_kernels.pooled import DriveRecord

    g = Grid([0, 0, 0], [4, 4, 4], 1.0)
    p = PSOG.from_probabilities(g, np.full(g.shape + (18,), 1 / 18))
    with pytest.raises(WriteError):
        p.save(tmp_path / "p.npz")
    rec = DriveRecord("a", 1, np.arange(500, dtype=np.int64), np.ones(500, np.int16), np.ones(500, np.int32))
    with caplog.at_level("WARNING"):
        _write_records(tmp_path / "subsets-x.npz", {"k": 1}, [rec])          # a cache: warns, goes on
    (line,) = [r.getMessage() for r in caplog.records]
    assert "\n" not in line and "subsets-x.npz" in line and "no space left" in line
    assert not list(tmp_path.iterdir())


def test_cli_output_on_a_full_disk_is_one_line_and_no_file(tmp_path, monkeypatch, capsys, full_disk):
    """``place3d evaluate --output`` on a full disk: exit 2, one ``place3d: error`` line naming the file, no
    traceback, no 0-byte JSON (it used to leave one), no temporary file."""
    from place3d_app.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    code = main(["evaluate", "--routes", "1", "--frames", "8", "--voxel-size", "0.8", "--quiet", "center",
                 "--resamples", "0", "--backend", "warp:cpu", "--lidar", "place3d_16ch", "--output", "out/eval.json"])
    err = capsys.readouterr().err
    # the cache that could not be written is a one-line warning each (the command goes on); the output
    # that could not be written is the one error
    lines = [ln for ln in err.splitlines() if ln.startswith("place3d: error")]
    warned = [ln for ln in err.splitlines() if ln.startswith("place3d: warning")]
    assert code == 2 and len(lines) == 1, err
    assert all("not written" in w and "no space left on device" in w for w in warned if "cache" in w), err
    assert "out/eval.json" in lines[0] and "no space left on device" in lines[0] and "Traceback" not in err
    assert not (tmp_path / "out/eval.json").exists() and not _temps(tmp_path)


def test_temps_of_killed_writers_are_removed_by_the_next_write(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()                                              # a pid that no longer runs
    dead = tmp_path / f"psog-x.npz{atomic.TEMP_MARK}{atomic._HOST}-{child.pid}-1"
    alive = tmp_path / f"psog-y.npz{atomic.TEMP_MARK}{atomic._HOST}-{os.getppid()}-1"
    mine = temp_name(tmp_path / "psog-z.npz")
    other_host_old = tmp_path / f"a.npz{atomic.TEMP_MARK}elsewhere-1-1"
    legacy_old = tmp_path / "checkpoint.pkl.tmp"
    legacy_new = tmp_path / "psog-q.npz.123-456.tmp.npz"
    for p in (dead, alive, mine, other_host_old, legacy_old, legacy_new):
        p.write_bytes(b"partial")
    old = time.time() - 2 * 24 * 3600
    os.utime(other_host_old, (old, old))
    os.utime(legacy_old, (old, old))
    atomic_write(tmp_path / "next.json", b"{}")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert sorted([alive.name, mine.name, legacy_new.name, "next.json"]) == left
    assert remove_stale_temps(tmp_path) == []                # once per folder and process


def test_a_writer_killed_mid_write_leaves_a_temp_the_next_run_removes(tmp_path):
    code = ("import sys, time; sys.path.insert(0, %r)\n"
            "from place3d_kernels.atomic import atomic_write\n"
            "def slow(f):\n    f.write(b'half'); f.flush(); print('writing', flush=True); time.sleep(60)\n"
            "atomic_write(%r, slow)\n") % (str(ROOT), str(tmp_path / "cache.npz"))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"writing"
    proc.kill()
    proc.wait()
    assert len(_temps(tmp_path)) == 1 and not (tmp_path / "cache.npz").exists()
    remove_stale_temps(tmp_path, force=True)
    assert not list(tmp_path.iterdir())
