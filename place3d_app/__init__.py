"""The ``place3d`` command's entry point: run the command here, or hand it to a warm ``place3d serve``.

``place3d --server CMD ...`` (or ``PLACE3D_SERVER`` set) sends the command to a resident server started
with ``place3d serve``, which has the package, NumPy, pycma and the backend (Warp, CUDA, OpenCL) loaded
already. Deciding that needs the standard library only, so this module imports neither NumPy nor the
package until it runs the command itself: when no server is asked for, when none is running, when the
server refuses (its code is older than the package on disk, or a start-up variable such as
``CUDA_VISIBLE_DEVICES`` differs), and for ``place3d serve`` itself.

The server writes into this process's own standard output and error (the descriptors are passed over
the socket), runs in this process's working directory with its environment, and returns the exit code;
Ctrl-C here interrupts the command there. See ``docs/commands.md``, section ``serve``.

Since the first message carries the whole environment and the live standard streams, the client sends
nothing before it knows the server is this user's: the socket's folder may be written by nobody else,
the socket is this user's, and the kernel reports the listening process as running under this user's
uid (``_checked_socket``). Whenever the client runs a command here that it was asked to send, it says
why in one line on stderr; the one quiet case is a standing ``PLACE3D_SERVER`` with no socket at all
(no server started). See ``docs/security.md``, "The server".
"""

from __future__ import annotations

import os
import sys

__all__ = ["main", "run", "leave", "returns_quickly", "server_request", "forward", "one_work_queue"]

#: The option that asks for the server; ``--server=PATH`` names its socket.
FLAG = "--server"
#: ``PLACE3D_SERVER``: unset, empty or ``0`` = run here; ``1`` = the default socket; anything else = a socket path.
ENV = "PLACE3D_SERVER"
#: ``PLACE3D_FAST_EXIT``: ``0`` = the console script exits through the interpreter's full teardown (see ``leave``).
FAST_EXIT_ENV = "PLACE3D_FAST_EXIT"
#: The commands that run here with one hardware work queue per CUDA context (``CUDA_DEVICE_MAX_CONNECTIONS=1``,
#: unless the user set it; ``one_work_queue``). Each runs the package's kernels on one Warp stream or one OpenCL
#: queue, in order, so one queue takes nothing from them, and the driver makes such a context faster: on an H200,
#: with the command's drive workers already on one queue, cold default ``optimize`` 4.77 [4.20-4.89] -> 4.49
#: [4.45-4.59] s, warm 2.67 -> 2.54 s, ``evaluate`` cold 3.58 -> 3.28 s, warm 1.37 -> 1.32 s (3 runs each,
#: alternated; bench/results/ab-2026-11-30-s34/README.md). Not ``downstream`` (PyTorch's training may overlap
#: copies with kernels on several streams) nor ``serve``, whose clients must start with its ``CUDA_*`` settings.
ONE_QUEUE_COMMANDS = frozenset({"evaluate", "optimize", "reproduce", "study", "simulate", "blindspot"})
ONE_QUEUE_ENV = "CUDA_DEVICE_MAX_CONNECTIONS"
#: Seconds without an answer from the server after which the client says that it waits, and for what.
BUSY_NOTE_AFTER_S = 1.0
#: Seconds the server has to greet a client (it does so from a thread of its own at once, busy or not);
#: past this the client runs the command itself.
GREETING_TIMEOUT_S = 10.0


def server_request(argv: list[str], environ=None) -> tuple[str | None, bool, list[str]]:
    """Whether ``argv`` (without the program name) asks for the server.

    Returns:
        (socket path, "" for the default one, or None for no server; whether ``--server`` was given on the
        command line; ``argv`` without the flag). The flag counts among the options before the subcommand
        only, so a subcommand's own arguments are never taken for it.
    """
    environ = os.environ if environ is None else environ
    rest, path, explicit = [], None, False
    leading = True
    for a in argv:
        if leading and (a == FLAG or a.startswith(FLAG + "=")):
            path, explicit = a.partition("=")[2], True
            continue
        if not a.startswith("-"):
            leading = False
        rest.append(a)
    if path is None:
        env = environ.get(ENV, "")
        if env not in ("", "0"):
            path = "" if env == "1" else env
    return path, explicit, rest


def _subcommand(argv: list[str]) -> str | None:
    return next((a for a in argv if not a.startswith("-")), None)


def one_work_queue(argv: list[str], environ=None) -> bool:
    """Set ``CUDA_DEVICE_MAX_CONNECTIONS=1`` in ``environ`` (default ``os.environ``) for a command of
    ``ONE_QUEUE_COMMANDS`` run in this process, before anything starts CUDA, unless the user set it; returns
    whether it was set here. Its worker processes have it anyway (``forkserver.WORKER_ENV``)."""
    environ = os.environ if environ is None else environ
    if _subcommand(argv) not in ONE_QUEUE_COMMANDS or ONE_QUEUE_ENV in environ:
        return False
    environ[ONE_QUEUE_ENV] = "1"
    return True


def main(argv: list[str] | None = None) -> int:
    """Run ``place3d`` (``argv`` without the program name; default ``sys.argv[1:]``); returns the exit code."""
    from_sys = argv is None
    path, explicit, rest = server_request(sys.argv[1:] if from_sys else list(argv))
    if from_sys:
        sys.argv[1:] = rest          # outputs record the command line without --server, as the server does
    if path is not None and _subcommand(rest) != "serve":
        code = forward(path, rest, explicit)
        if code is not None:
            return code
    if from_sys:
        # the console script only: a caller of main() in its own process keeps its environment
        one_work_queue(rest)
    # the workers' server imports beside this process's own imports, for the commands that will use it
    # (start_early decides; place3d_app.forkserver, standard library only)
    from place3d_app.forkserver import start_early

    start_early(rest)
    from place3d_app.cli import main as run_here

    return run_here(None if from_sys else rest)


def run() -> None:
    """The ``place3d`` console script: ``main``, then ``leave`` with its exit code; a kernel command run here
    runs in a child process whose teardown the shell does not wait for (``place3d_app.quick_return``)."""
    from place3d_app import quick_return

    if returns_quickly(sys.argv[1:]) and quick_return.can_fork():
        quick_return.start()
    leave(main())


def returns_quickly(argv: list[str], environ=None) -> bool:
    """Whether the console script runs ``argv`` (without the program name) in a child whose teardown it does not
    wait for (``place3d_app.quick_return``): a kernel command (``ONE_QUEUE_COMMANDS``: CUDA contexts and large
    arrays, the slow ends) run here (no server asked for: a client of ``place3d serve`` holds neither), with
    the fast exit on (``PLACE3D_FAST_EXIT`` not 0)."""
    environ = os.environ if environ is None else environ
    server, _, rest = server_request(argv, environ)
    return (_subcommand(rest) in ONE_QUEUE_COMMANDS and server is None
            and environ.get(FAST_EXIT_ENV, "1").strip() != "0")


def leave(code) -> None:
    """End the process with exit code ``code`` as ``sys.exit`` would, less the interpreter's last teardown.

    Python's own exit does three things once the program returns: it tells thread pools to stop and joins
    the threads that are not daemons, it runs the ``atexit`` handlers, and then it tears the interpreter
    down (module namespaces, every object still alive, the loaded C libraries' destructors: Warp's LLVM, the
    CUDA driver, PoCL). A finished command needs the first two (a P-SOG file written on a thread, Ray's
    shutdown, temporary directories' finalizers) and none of the third, which was a visible part of a
    ``place3d optimize`` (bench/README.md, "What the studies found", cold command: imports, tail and exit).
    So this runs the first two as the interpreter would, flushes the standard streams and leaves with
    ``os._exit``. Where the interpreter lacks the hooks it uses (``threading._shutdown``,
    ``atexit._run_exitfuncs``: CPython has both), or with ``PLACE3D_FAST_EXIT=0``, it calls ``sys.exit``
    instead.
    """
    import atexit
    import threading

    if isinstance(code, bool) or not isinstance(code, int):
        code = 0 if code is None else 1          # as sys.exit: None is success, other objects failure
    shutdown = getattr(threading, "_shutdown", None)
    exit_funcs = getattr(atexit, "_run_exitfuncs", None)
    if (os.environ.get(FAST_EXIT_ENV, "1").strip() == "0" or shutdown is None or exit_funcs is None
            or threading.current_thread() is not threading.main_thread()):
        sys.exit(code)
    shutdown()                                   # thread pools told to stop; non-daemon threads joined
    exit_funcs()                                 # atexit handlers, last registered first
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):            # a closed pipe (place3d ... | head), a closed stream
            code = code or 120                   # the code Python's exit gives when its flush fails
    quick = sys.modules.get("place3d_app.quick_return")
    if quick is not None:
        quick.report(code)                       # the console script's waiting parent leaves now (run)
    os._exit(code)


def _std_fds() -> tuple[list[int], list[int]]:
    """Descriptors 0, 1, 2 to pass (``/dev/null`` for a closed one) and the ones opened here to close."""
    fds, opened = [], []
    for fd, mode in ((0, os.O_RDONLY), (1, os.O_WRONLY), (2, os.O_WRONLY)):
        try:
            os.fstat(fd)
            fds.append(fd)
        except OSError:
            fds.append(os.open(os.devnull, mode))
            opened.append(fds[-1])
    return fds, opened


def _streams() -> dict:
    """How this process's text streams are set up, so the server's stand-ins write the same bytes."""
    out = {}
    for name in ("stdout", "stderr"):
        s = getattr(sys, name)
        out[name] = {"encoding": getattr(s, "encoding", None) or "utf-8", "errors": getattr(s, "errors", None)
                     or "strict", "line_buffering": bool(getattr(s, "line_buffering", name == "stderr")),
                     "write_through": bool(getattr(s, "write_through", False))}
    return out


def _one_line(text) -> str:
    """``text`` on one line, control characters shown escaped (a server's message is printed as data)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in " ".join(str(text).split()))


#: What the client adds when no server runs at the socket.
START_HINT = ". Start one with 'place3d serve --detach'"


def _fallback(why: str, hint: str = "") -> None:
    """Say on stderr, in one line, why the command runs here instead of on the server; None (run here)."""
    print(f"place3d: {_one_line(why)}; running here{hint}", file=sys.stderr)
    return None


def _checked_socket(where: str, explicit: bool):
    """Connect to the server socket ``where`` once it is shown to be this user's: (socket, None), or (None,
    why) with why None or a reason for ``_fallback`` with its hint.

    Nothing is sent before these checks pass: the socket's folder (symbolic links resolved) and every folder
    above it may be written by nobody but this user (``wire.unsafe_folder``), the socket belongs to this
    user (``wire.socket_problem``), and the process listening on it runs as this user (``SO_PEERCRED``,
    ``wire.peer_credentials``: the check no one can plant around). ``why`` is None when nothing is at
    ``where`` and no one asked for this socket explicitly: a standing ``PLACE3D_SERVER`` with no server
    started runs the command here without a word.
    """
    import errno
    import socket

    from place3d_app import wire

    folder = os.path.realpath(os.path.dirname(os.path.abspath(where)))
    real = os.path.join(folder, os.path.basename(where))
    missing = (f"no server at {where} (No such file or directory)", START_HINT)
    try:
        entry = wire.socket_problem(real)
    except FileNotFoundError:
        return None, (missing if explicit else None)
    except OSError as e:
        return None, (f"cannot use the server socket {where} ({e.strerror or e})", "")
    problem = wire.unsafe_folder(folder) or entry
    if problem:
        return None, (f"refusing the server socket {where}: {problem}", "")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(real)
        pid, uid, _gid = wire.peer_credentials(sock)
    except OSError as e:
        sock.close()
        if e.errno == errno.ENOENT:
            return None, (missing if explicit else None)
        if e.errno == errno.ECONNREFUSED:       # a socket left behind: its server died
            return None, (f"the server at {where} is gone (nothing answers on its socket)", START_HINT)
        return None, (f"cannot reach the server at {where} ({e.strerror or e})", "")
    if uid != os.getuid():
        sock.close()
        return None, (f"refusing the server at {where}: it runs as uid {uid} (pid {pid}), not as this user "
                      f"(uid {os.getuid()}); nothing was sent to it", "")
    return sock, None


def forward(path: str, argv: list[str], explicit: bool) -> int | None:
    """Run ``place3d ARGV`` on the server at ``path`` ("" = the default socket).

    Returns:
        The command's exit code, or None when no server took it: the caller then runs the command here.
        Why is said in one line on stderr every time, except in one case: nothing at all at the socket path
        (no server started) when the server was asked for by ``PLACE3D_SERVER``, a standing setting, rather
        than by ``--server``.
    """
    import signal

    from place3d_app import wire

    where = path or str(wire.default_socket())
    sock, why = _checked_socket(where, explicit)
    if sock is None:
        return None if why is None else _fallback(*why)
    opened: list[int] = []
    try:
        greeting = _recv_waiting(sock, wire, GREETING_TIMEOUT_S,
                                 f"place3d: waiting for the server at {where} to answer (at most "
                                 f"{GREETING_TIMEOUT_S:g} s)")
        if greeting is None:
            return _fallback(f"the server at {where} closed the connection before greeting")
        if greeting.get("type") != "ready":
            return _fallback(f"the server at {where} turned this client away: "
                             f"{greeting.get('message', greeting.get('type'))}")
        umask = os.umask(0)
        os.umask(umask)
        fds, opened = _std_fds()
        wire.send_with_fds(sock, {"type": "run", "argv": list(sys.argv[:1]) + list(argv), "cwd": os.getcwd(),
                                  "env": dict(os.environ), "umask": umask, "identity": wire.identity(),
                                  "streams": _streams()}, fds)
        reply = _recv_waiting(sock, wire, None, f"place3d: the server at {where} is busy with another command; "
                                                f"waiting for it (Ctrl-C to stop waiting)")
        if reply is None:
            return _fallback(f"the server at {where} did not run the command: it closed the connection")
        if reply.get("type") != "started":
            return _fallback(f"the server at {where} did not run the command: "
                             f"{reply.get('message', reply.get('type'))}")
        return _wait(sock, where, signal)
    except KeyboardInterrupt:
        # Ctrl-C before the server started the command: nothing ran
        print("place3d: interrupted", file=sys.stderr)
        return 130
    except TimeoutError:
        return _fallback(f"the server at {where} did not answer within {GREETING_TIMEOUT_S:g} s")
    except wire.FrameError as e:
        return _fallback(f"the server at {where} sent a malformed message ({e})")
    except OSError as e:
        return _fallback(f"the connection to the server at {where} failed ({e.strerror or e})")
    finally:
        for fd in opened:
            os.close(fd)
        sock.close()


def _recv_waiting(sock, wire, limit_s: float | None, note: str):
    """One message from the server; after ``BUSY_NOTE_AFTER_S`` without one, ``note`` on stderr (once), then
    wait up to ``limit_s`` s in all (None: as long as it takes).

    Raises:
        TimeoutError: nothing within ``limit_s``.
    """
    sock.settimeout(BUSY_NOTE_AFTER_S)
    try:
        return wire.recv(sock)
    except TimeoutError:
        print(note, file=sys.stderr)
        sock.settimeout(None if limit_s is None else max(limit_s - BUSY_NOTE_AFTER_S, 0.1))
        return wire.recv(sock)
    finally:
        sock.settimeout(None)


def _wait(sock, where: str, signal) -> int:
    """Wait for the command's exit code; the first Ctrl-C is passed on to the server, a second one leaves."""
    from place3d_app import wire

    interrupts = []

    def on_sigint(signum, frame):
        if interrupts:
            raise KeyboardInterrupt
        interrupts.append(signum)
        try:
            wire.send(sock, {"type": "interrupt"})
        except OSError:
            raise KeyboardInterrupt from None

    old = signal.signal(signal.SIGINT, on_sigint)
    try:
        msg = wire.recv(sock)
    except KeyboardInterrupt:
        print("place3d: interrupted (the server stops the command as this client leaves)", file=sys.stderr)
        return 130
    except (OSError, wire.FrameError) as e:
        print(f"place3d: the connection to the server at {where} failed while the command ran "
              f"({_one_line(e)})", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, old)
    if msg is None:
        print(f"place3d: the server at {where} stopped before the command finished", file=sys.stderr)
        return 1
    code = msg.get("code")
    if msg.get("type") != "exit" or type(code) is not int or not 0 <= code <= 255:
        print(f"place3d: the server at {where} ended the command without an exit code: "
              f"{_one_line(msg.get('message', msg))}", file=sys.stderr)
        return 1
    return code
