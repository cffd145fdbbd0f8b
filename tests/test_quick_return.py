"""``place3d_app.quick_return``: the console script's process ends with the command's code once the command has
finished, without waiting for its child's teardown; a child that dies, is killed or is signalled through the
parent ends the parent the same way. Real processes throughout (fork, pipes, signals)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from place3d_app import quick_return

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the quick return forks on Linux only")

# argv: [pid file, behaviour, code]; the child writes its pid first, then does what it is told
PROGRAM = """
import os, signal, sys, time
import place3d_app
from place3d_app import quick_return
quick_return.start()
pid_file, what, code = sys.argv[1], sys.argv[2], int(sys.argv[3])
with open(pid_file, "w") as f:
    f.write(str(os.getpid()))
print("child output", flush=True)
assert quick_return.waiting_parent() == os.getppid() != os.getpid()
if what == "slow-end":                 # the command is done; its process then takes long to go
    sys.stdout.write("buffered, unflushed")
    sys.stdout.flush()
    quick_return.report(code)
    time.sleep(3)
    os._exit(code)
elif what == "leave":
    sys.stdout.write("buffered, unflushed")
    place3d_app.leave(code)
elif what == "sys-exit":
    sys.exit(code)
elif what == "signal":
    os.kill(os.getpid(), signal.SIGUSR1)
    time.sleep(10)
elif what == "wait-hup":               # a command with a SIGHUP handler of its own, then as "wait"
    signal.signal(signal.SIGHUP, lambda *_: print("child got SIGHUP", flush=True))
    time.sleep(30)
    os._exit(0)
elif what == "wait":                   # until a signal ends it (SIGINT: KeyboardInterrupt, as a command gets)
    try:
        time.sleep(30)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        place3d_app.leave(130)
    os._exit(0)
"""


def _start(tmp_path, what, code=0):
    pid_file = tmp_path / "child.pid"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PLACE3D_FAST_EXIT", None)
    p = subprocess.Popen([sys.executable, "-c", PROGRAM, str(pid_file), what, str(code)], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return p, pid_file


def _child_pid(pid_file, timeout=30.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pid_file.exists() and pid_file.read_text():
            return int(pid_file.read_text())
        time.sleep(0.01)
    raise AssertionError("the child never started")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0] != "Z"       # a zombie has ended
    except FileNotFoundError:
        return False


def _gone_within(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.02)
    return False


@pytest.mark.parametrize("code", [0, 3])
def test_the_parent_leaves_with_the_code_before_the_child_is_torn_down(tmp_path, code):
    p, pid_file = _start(tmp_path, "slow-end", code)
    t = time.monotonic()
    out, err = p.communicate(timeout=60)        # both pipes at their end: the child let go of them
    took = time.monotonic() - t
    child = _child_pid(pid_file)
    assert p.returncode == code, err
    assert out == "child output\nbuffered, unflushed"
    assert took < 2.5, took                     # the child sleeps 3 s after its report: not waited for
    assert _gone_within(child, 10)              # (its parent's end kills it: PR_SET_PDEATHSIG)


@pytest.mark.parametrize("code", [0, 5])
def test_leave_reports_the_code_after_flushing(tmp_path, code):
    p, _ = _start(tmp_path, "leave", code)
    out, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    assert out == "child output\nbuffered, unflushed"


def test_a_child_that_exits_without_reporting_gives_its_code(tmp_path):
    p, _ = _start(tmp_path, "sys-exit", 4)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 4, err
    assert out == "child output\n"


def test_a_child_killed_by_a_signal_ends_the_parent_by_it(tmp_path):
    p, _ = _start(tmp_path, "signal")
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGUSR1


def test_sigterm_to_the_parent_ends_the_child(tmp_path):
    p, pid_file = _start(tmp_path, "wait")
    child = _child_pid(pid_file)
    p.send_signal(signal.SIGTERM)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGTERM
    assert _gone_within(child, 10)


def test_sigint_to_the_parent_outside_a_terminal_interrupts_the_command(tmp_path):
    p, pid_file = _start(tmp_path, "wait")
    _child_pid(pid_file)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert out == "child output\ninterrupted\n"


def test_a_signal_the_caller_ignores_stays_ignored(tmp_path):
    # as nohup starts a command: SIGHUP ignored where the parent starts. The parent does not pass a SIGHUP sent to
    # it on to the child, even to a command that handles SIGHUP itself ("wait-hup"); both go on
    pid_file = tmp_path / "child.pid"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-c", PROGRAM, str(pid_file), "wait-hup", "0"], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    child = _child_pid(pid_file)
    time.sleep(0.3)                            # the child's own handler is installed after its pid file
    p.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert p.poll() is None and _alive(child)
    p.send_signal(signal.SIGTERM)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == -signal.SIGTERM and _gone_within(child, 10)
    assert "child got SIGHUP" not in out


def test_a_killed_parent_takes_the_child_with_it(tmp_path):
    p, pid_file = _start(tmp_path, "wait")
    child = _child_pid(pid_file)
    p.kill()
    p.wait(timeout=60)
    assert _gone_within(child, 10)              # PR_SET_PDEATHSIG
    p.stdout.close()
    p.stderr.close()


def test_which_commands_return_quickly():
    from place3d_app import returns_quickly

    assert returns_quickly(["optimize", "--max-evals", "10"], {}) and returns_quickly(["--profile", "evaluate"], {})
    assert not returns_quickly(["--server", "optimize"], {})          # a client of place3d serve holds no CUDA
    assert not returns_quickly(["optimize"], {"PLACE3D_SERVER": "1"})
    assert not returns_quickly(["serve"], {}) and not returns_quickly(["backends"], {}) and not returns_quickly([], {})
    assert not returns_quickly(["optimize"], {"PLACE3D_FAST_EXIT": "0"})
    assert quick_return.can_fork()


def test_report_outside_a_forked_child_does_nothing():
    assert quick_return._report_fd is None and quick_return.waiting_parent() is None
    before = [(os.fstat(fd).st_dev, os.fstat(fd).st_ino) for fd in (0, 1, 2)]
    quick_return.report(0)                      # no pipe written, no standard descriptor replaced by /dev/null
    assert [(os.fstat(fd).st_dev, os.fstat(fd).st_ino) for fd in (0, 1, 2)] == before


def test_a_kernel_command_through_the_console_module_keeps_its_exit_code():
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PLACE3D_SERVER": ""}
    p = subprocess.run([sys.executable, "-m", "place3d_app", "evaluate", "--no-such-option"], capture_output=True,
                       text=True, env=env, timeout=120)
    assert p.returncode == 2 and "unrecognized arguments: --no-such-option" in p.stderr
