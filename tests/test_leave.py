"""``place3d_app.leave``: the console script's exit keeps what Python's exit does for a program (thread
pools stopped, non-daemon threads joined, atexit handlers, flushed streams, the exit code) and skips the
interpreter's teardown."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

PROGRAM = """
import atexit, concurrent.futures, os, sys, threading, time
import place3d_app
atexit.register(lambda: print("atexit ran", flush=True))
def late():
    time.sleep(0.3)
    with open(sys.argv[1], "w") as f:
        f.write("written by a thread")
threading.Thread(target=late).start()
pool = concurrent.futures.ThreadPoolExecutor(1)
pool.submit(time.sleep, 0.2)                          # a pool never shut down: Python's exit stops it
sys.stdout.write("no newline, still buffered")         # a pipe: block-buffered, not yet written
class Noisy:
    def __del__(self):
        print("teardown ran", flush=True)
keep = Noisy()                                         # alive until the interpreter's teardown
place3d_app.leave(int(sys.argv[2]))
"""


def _run(tmp_path, code, env=None):
    out = tmp_path / "thread.txt"
    e = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    p = subprocess.run([sys.executable, "-c", PROGRAM, str(out), str(code)], capture_output=True, text=True,
                       env=e, timeout=60)
    return p, out


@pytest.mark.parametrize("code", [0, 3])
def test_leave_runs_threads_atexit_and_flushes(tmp_path, code):
    p, out = _run(tmp_path, code)
    assert p.returncode == code, p.stderr
    assert out.read_text() == "written by a thread"    # the non-daemon thread was joined
    assert "no newline, still buffered" in p.stdout     # the buffer was flushed
    assert "atexit ran" in p.stdout
    assert "teardown ran" not in p.stdout               # the teardown was skipped: that is the point


def test_leave_can_be_turned_off(tmp_path):
    p, out = _run(tmp_path, 5, {"PLACE3D_FAST_EXIT": "0"})
    assert p.returncode == 5, p.stderr
    assert out.read_text() == "written by a thread"
    assert "atexit ran" in p.stdout and "no newline, still buffered" in p.stdout
    # sys.exit's teardown: the object's __del__ runs (or the interpreter drops it silently); either way the
    # program's outputs are the same as above


def test_console_script_module_exits_with_the_command_code():
    # python -m place3d_app is the place3d command: a bad subcommand is argparse's exit code 2
    p = subprocess.run([sys.executable, "-m", "place3d_app", "no-such-command"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "PLACE3D_SERVER": ""}, timeout=120)
    assert p.returncode == 2 and "invalid choice" in p.stderr
    p = subprocess.run([sys.executable, "-m", "place3d_app", "--version"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "PLACE3D_SERVER": ""}, timeout=120)
    assert p.returncode == 0 and p.stdout.strip()
