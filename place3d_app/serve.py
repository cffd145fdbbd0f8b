"""``place3d serve``: a resident process that runs ``place3d`` commands with everything slow already loaded.

A warm ``place3d optimize --max-evals 2000`` spent a large part of its time in start-up: the interpreter and
package imports, Warp, CUDA, pycma, the cached P-SOG, while the kernels take milliseconds (bench/README.md,
"What the studies found", warm command and ``place3d serve``). Like ``dmypy`` or the Gradle daemon,
``place3d serve`` pays that once and then runs each command sent by ``place3d --server ...``
(``place3d_app``) in its own process, where the imports are done, the backend instances with their compiled
kernels are kept by the registry, and the last P-SOGs read stay in memory (``sog.keep_loaded``), as do the
last pooled P-SOGs with their prepared grids (``pool_memo.keep_pools``).

Per command the server takes on the client's side of the process: its standard input, output and error
(passed as descriptors, so the output is the bytes the in-process command writes, C-level output
included), working directory, environment, umask and ``sys.argv``; it restores its own afterwards.

Each connection is greeted and checked on a thread of its own: the peer must run as this user (kernel
credentials, ``SO_PEERCRED``), and its request must arrive within ``HANDSHAKE_TIMEOUT_S`` as one frame
of at most ``wire.MAX_REQUEST_BYTES`` holding a well-formed ``run`` request (``wire.run_problem``). A bad
frame gets an error reply and the server goes on; a silent client holds only its own thread. Accepted
requests queue for the main thread, which runs one command at a time (a client whose command waits says
so after a second). Ctrl-C on the client (or the client going away) interrupts the command with
``KeyboardInterrupt``, as Ctrl-C does in-process; the server carries on.

The server refuses a client whose package, interpreter or dependencies differ from what it loaded
(``place3d_app.wire.identity``) and then stops, since its code is out of date; it also refuses a client
whose start-up variables (``CUDA_VISIBLE_DEVICES``, ``POCL_*``, ...) differ. Refused clients run the
command themselves and say why, so old code never answers silently.

It listens only in a folder no other user may write (created with mode 0700), never removes anything at
its socket path but a stale socket of its own, and ``--detach`` opens its log without following a
symbolic link. ``docs/security.md`` ("The server") lists what it trusts and what it refuses.

The code is in three files, each importing only the ones after it: this one (the options of ``place3d
serve``, its start and ``--detach``), ``place3d_app.serve_loop`` (the ``Server``: connections, job queue,
signals, running one command on the client's side) and ``place3d_app.serve_socket`` (the socket path and
the log, checked before use). The names of the other two that callers use are importable from here too.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

# Server, settle_memory, run_command, client_side and the settings are imported here so that they stay
# importable from place3d_app.serve; the server reads its settings (HANDSHAKE_TIMEOUT_S, MAX_HANDSHAKES,
# KEEP_PSOGS, KEEP_POOLS) from place3d_app.serve_loop, so change them there.
from place3d_app.serve_loop import (  # noqa: F401
    DEFAULT_IDLE_TIMEOUT_S, HANDSHAKE_TIMEOUT_S, KEEP_POOLS, KEEP_PSOGS, MAX_HANDSHAKES, Server, client_side,
    run_command, settle_memory)
from place3d_app.serve_socket import claim_socket_path, client_wire, is_listening, open_log

__all__ = ["add_arguments", "serve", "Server", "client_wire", "is_listening", "claim_socket_path", "open_log",
           "DEFAULT_IDLE_TIMEOUT_S", "KEEP_PSOGS", "KEEP_POOLS", "HANDSHAKE_TIMEOUT_S", "MAX_HANDSHAKES"]

#: The most bytes of a Unix socket path (``sun_path`` holds 108 with its terminating NUL).
MAX_SOCKET_PATH = 107


def add_arguments(p) -> None:
    """The options of ``place3d serve``."""
    p.add_argument("--socket", default=None,
                   help="Unix socket to listen on, in a folder only you may write (default: per user, interpreter "
                        "and checkout, under $XDG_RUNTIME_DIR/place3d or ~/.cache/place3d-serve, created with mode "
                        "0700); clients name it with --server=PATH")
    p.add_argument("--idle-timeout", type=float, default=DEFAULT_IDLE_TIMEOUT_S,
                   help=f"exit after this many seconds without a command (default {DEFAULT_IDLE_TIMEOUT_S:.0f}; "
                        f"0 = never)")
    p.add_argument("--backend", default=None,
                   help="backend to load and probe at start (default: $PLACE3D_BACKEND or auto); commands may "
                        "still name others, loaded on first use")
    p.add_argument("--detach", action="store_true",
                   help="start the server in the background, wait until it listens, print its pid and return")


def serve(args, command, warm) -> int:
    """Run ``place3d serve`` (``command``: the CLI's ``main``; ``warm``: a call that imports its subcommands)."""
    wire = client_wire()
    path = Path(os.path.abspath(args.socket)) if args.socket else wire.default_socket()
    if args.idle_timeout < 0:
        raise ValueError(f"--idle-timeout must be >= 0 seconds (0 = never), got {args.idle_timeout}")
    _check_socket_path(path)
    # refused before the slow start: a folder others may write, or something at the path that is not a
    # stale socket of ours
    wire.private_folder(path.parent)
    claim_socket_path(path, remove=False)
    if args.detach:
        return _detach(args, path)
    server = Server(path, command, idle_timeout=args.idle_timeout)
    server.warm(args.backend, warm)
    return server.serve_forever()


def _check_socket_path(path: Path) -> None:
    n = len(os.fsencode(str(path)))
    if n > MAX_SOCKET_PATH:
        raise ValueError(f"socket path {path} is {n} bytes, Unix sockets allow {MAX_SOCKET_PATH}; give a shorter "
                         f"one with --socket, in a folder only you may write (mode 0700)")


def _detach(args, path: Path) -> int:
    """Start ``place3d serve`` in a session of its own and return once it listens."""
    import subprocess

    if is_listening(path):
        raise ValueError(f"a server already listens on {path}; use it (place3d --server ...), stop it (SIGTERM to "
                         f"its pid), or start this one with another --socket")
    log = path.with_suffix(".log") if path.suffix != ".log" else path.with_name(path.name + ".log")
    cmd = [sys.executable, "-m", "place3d_app", "serve", "--socket", str(path),
           "--idle-timeout", str(args.idle_timeout)] + (["--backend", args.backend] if args.backend else [])
    with os.fdopen(open_log(log), "ab") as f:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        code = proc.poll()
        if code is not None:
            raise ValueError(f"the server exited with code {code} before listening; its log: {log}")
        if not is_listening(path):
            time.sleep(0.05)
            continue
        print(f"server started: pid {proc.pid}, listening on {path} (log {log}); use it with "
              f"place3d --server{'' if args.socket is None else '=' + str(path)} COMMAND")
        return 0
    raise ValueError(f"the server (pid {proc.pid}) did not listen on {path} within 300 s; its log: {log}")
