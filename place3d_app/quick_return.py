"""The console script's quick return: a kernel command's process ends before the kernel has freed it.

A process's end has a last part that no Python code sees: after ``os._exit`` the kernel unmaps its memory and
the CUDA driver tears its context down. On the H200 host that took 0.08-0.12 s of every command (the
time from the end of ``place3d_app.leave`` to the moment the shell's ``wait`` returned: 0.091-0.095 s for a
default ``optimize``, 0.079-0.120 s for ``evaluate``, 3 warm runs each; bench/results/ab-2026-12-01-s39/),
a wait with nothing left to compute. So the console script forks before it imports anything: the parent, the
process the shell waits for, only waits; the child runs the command and, once ``leave`` has done what
Python's exit does (threads joined, exit handlers run, streams flushed), sends its exit code to the parent and
lets go of the standard streams; the parent then leaves with that code while the child is still being torn
down. The mold linker ends the same way for the same reason.

Nothing a command promises changes: its outputs and cache files are written, and its streams flushed, before
the parent hears the code. A child that ends without sending one (killed, crashed, or ended through
``sys.exit``, as argparse does for a bad option) is waited for, and the parent ends with its status: the same
exit code, or the same signal. The parent passes SIGTERM, SIGHUP and SIGINT on to the child (not a Ctrl-C at
the terminal, which reaches the child itself: both are in the terminal's foreground process group; the child
stops the command and sends 130; a signal the caller ignores, as nohup does, stays ignored), and when the parent
itself is killed the kernel kills the child (``PR_SET_PDEATHSIG``). Linux only (the fork happens before any
thread or library exists); ``PLACE3D_FAST_EXIT=0`` turns it off with ``leave``'s own shortcut.

Standard library only: it runs before the package is imported.
"""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["can_fork", "start", "waiting_parent", "report"]

#: The write end of the pipe to the waiting parent, in the child; None elsewhere.
_report_fd: int | None = None
#: The waiting parent's pid, in the child; None elsewhere.
_parent: int | None = None


def can_fork() -> bool:
    """Whether this platform ends commands this way: Linux, with ``os.fork``."""
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def start() -> None:
    """Fork. The child returns, to run the command; the parent waits for the child's code and leaves with it
    (it never returns). Call it from the console script before anything starts a thread."""
    global _report_fd, _parent
    parent = os.getpid()
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read_end)
        _die_with(parent)
        _report_fd, _parent = write_end, parent
        return
    os.close(write_end)
    _wait(pid, read_end)


def waiting_parent() -> int | None:
    """The pid of the process the shell waits for, in a child started here (its start is the command's start:
    ``profiling.count_start_up_of``); None elsewhere."""
    return _parent


def report(code: int) -> None:
    """In the child, once the command has finished: send ``code`` to the parent and hand the standard streams
    back (``/dev/null`` in their place), so that neither the shell nor a reader of the output waits for this
    process's teardown. Does nothing in a process that did not fork here."""
    global _report_fd
    if _report_fd is None:
        return
    fd, _report_fd = _report_fd, None
    try:
        os.write(fd, f"{int(code)}\n".encode())
        os.close(fd)
        null = os.open(os.devnull, os.O_RDWR)
        for std in (0, 1, 2):
            os.dup2(null, std)
        os.close(null)
    except OSError:          # the parent is gone (killed): nothing to tell
        pass


def _die_with(parent: int) -> None:
    """Ask the kernel to kill this process when its parent ends (Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)``);
    leave at once if the parent ended before the request."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))   # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):   # no prctl here: a killed parent then leaves the command to finish alone
        pass
    if os.getppid() != parent:
        os._exit(1)


def _wait(pid: int, read_end: int) -> None:
    """The parent: the child's code from the pipe, else its exit status; leave with it."""
    def forward(signum, frame):
        if signum == signal.SIGINT and _foreground():
            return               # Ctrl-C: the terminal sent it to the child as well (one process group)
        try:
            os.kill(pid, signum)
        except ProcessLookupError:
            pass

    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(s) is not signal.SIG_IGN:    # one ignored here (nohup, a background job) stays so
            signal.signal(s, forward)
    data = b""
    # up to the newline: a process the child forked (not exec'd) may hold the pipe's write end for longer
    while not data.endswith(b"\n") and (chunk := os.read(read_end, 64)):   # EINTR: retried (PEP 475)
        data += chunk
    if data.endswith(b"\n"):
        os._exit(int(data))
    _, status = os.waitpid(pid, 0)
    code = os.waitstatus_to_exitcode(status)
    if code < 0:                                 # killed by a signal: end the same way, as the shell expects
        signal.signal(-code, signal.SIG_DFL)
        os.kill(os.getpid(), -code)
        code = 128 - code                        # a signal whose default action does not end a process
    os._exit(code)


def _foreground() -> bool:
    """Whether this process group is the foreground of the terminal on a standard stream: a Ctrl-C there is
    sent to every process of the group."""
    for fd in (0, 1, 2):
        try:
            return os.tcgetpgrp(fd) == os.getpgrp()
        except OSError:          # not a terminal
            continue
    return False
