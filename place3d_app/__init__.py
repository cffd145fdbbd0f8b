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
"""

from __future__ import annotations

import os
import sys

__all__ = ["main", "run", "leave", "server_request", "forward"]

#: The option that asks for the server; ``--server=PATH`` names its socket.
FLAG = "--server"
#: ``PLACE3D_SERVER``: unset, empty or ``0`` = run here; ``1`` = the default socket; anything else = a socket path.
ENV = "PLACE3D_SERVER"
#: ``PLACE3D_FAST_EXIT``: ``0`` = the console script exits through the interpreter's full teardown (see ``leave``).
FAST_EXIT_ENV = "PLACE3D_FAST_EXIT"
#: Seconds without the server's greeting after which the client says it waits for a busy server.
BUSY_NOTE_AFTER_S = 1.0


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
    from place3d_app.cli import main as run_here

    return run_here(None if from_sys else rest)


def run() -> None:
    """The ``place3d`` console script: ``main``, then ``leave`` with its exit code."""
    leave(main())


def leave(code) -> None:
    """End the process with exit code ``code`` as ``sys.exit`` would, less the interpreter's last teardown.

    Python's own exit does three things once the program returns: it tells thread pools to stop and joins
    the threads that are not daemons, it runs the ``atexit`` handlers, and then it tears the interpreter
    down (module namespaces, every object still alive, the loaded C libraries' destructors: Warp's LLVM,
    the CUDA driver, PoCL). A finished command needs the first two (a P-SOG file written on a thread,
    Ray's shutdown, temporary directories' finalizers) and none of the third, which took 0.2-0.25 s of a
    ``place3d optimize`` on the dev VM (README, "What a user waits for, ninth session"). So this runs the
    first two as the interpreter would, flushes the standard streams and leaves with ``os._exit``. Where
    the interpreter lacks the hooks it uses (``threading._shutdown``, ``atexit._run_exitfuncs``: CPython
    has both), or with ``PLACE3D_FAST_EXIT=0``, it calls ``sys.exit`` instead.
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


def forward(path: str, argv: list[str], explicit: bool) -> int | None:
    """Run ``place3d ARGV`` on the server at ``path`` ("" = the default socket).

    Returns:
        The command's exit code, or None when no server took it (none listening, or it refused): the
        caller then runs the command here. The reason is said on stderr when the user asked for the
        server with ``--server`` or when the server refused.
    """
    import signal
    import socket

    from place3d_app import wire

    where = path or str(wire.default_socket())
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(where)
    except OSError as e:
        sock.close()
        if explicit:
            print(f"place3d: no server at {where} ({e.strerror or e}); running here. Start one with "
                  f"'place3d serve --detach'", file=sys.stderr)
        return None
    opened: list[int] = []
    try:
        sock.settimeout(BUSY_NOTE_AFTER_S)
        try:
            greeting = wire.recv(sock)
        except TimeoutError:
            print(f"place3d: the server at {where} is busy with another command; waiting for it (Ctrl-C to "
                  f"stop waiting)", file=sys.stderr)
            sock.settimeout(None)
            greeting = wire.recv(sock)
        sock.settimeout(None)
        if greeting is None:
            if explicit:
                print(f"place3d: the server at {where} closed the connection; running here", file=sys.stderr)
            return None
        umask = os.umask(0)
        os.umask(umask)
        fds, opened = _std_fds()
        wire.send_with_fds(sock, {"type": "run", "argv": list(sys.argv[:1]) + list(argv), "cwd": os.getcwd(),
                                  "env": dict(os.environ), "umask": umask, "identity": wire.identity(),
                                  "streams": _streams()}, fds)
        reply = wire.recv(sock)
        if reply is None or reply.get("type") == "refused":
            why = "it closed the connection" if reply is None else reply.get("message", "")
            print(f"place3d: the server at {where} did not run the command: {why}; running here",
                  file=sys.stderr)
            return None
        return _wait(sock, where, signal)
    except KeyboardInterrupt:
        # Ctrl-C before the server started the command: nothing ran
        print("place3d: interrupted", file=sys.stderr)
        return 130
    finally:
        for fd in opened:
            os.close(fd)
        sock.close()


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
    finally:
        signal.signal(signal.SIGINT, old)
    if msg is None:
        print(f"place3d: the server at {where} stopped before the command finished", file=sys.stderr)
        return 1
    return int(msg.get("code", 1))
