"""``place3d serve``: a resident process that runs ``place3d`` commands with everything slow already loaded.

A warm ``place3d optimize --max-evals 2000`` spent about 2.4 s of its 6.5 s on the H100 host in start-up:
the interpreter and package imports, Warp, CUDA, pycma, the cached P-SOG. The kernels take milliseconds.
Like ``dmypy`` or the Gradle daemon, ``place3d serve`` pays that once and then runs each command sent by
``place3d --server ...`` (``place3d_app``) in its own process, where the imports are done, the backend
instances with their compiled kernels are kept by the registry, and the last P-SOGs read stay in memory
(``sog.keep_loaded``).

Per command the server takes on the client's side of the process: its standard input, output and error
(passed as descriptors, so the output is the bytes the in-process command writes, C-level output
included), working directory, environment, umask and ``sys.argv``; it restores its own afterwards. One
command runs at a time, on the main thread; a client that connects meanwhile waits its turn (and says so
after a second). Ctrl-C on the client (or the client going away) interrupts the command with
``KeyboardInterrupt``, as Ctrl-C does in-process; the server carries on.

The server refuses a client whose package, interpreter or dependencies differ from what it loaded
(``place3d_app.wire.identity``) and then stops, since its code is out of date; it also refuses a client
whose start-up variables (``CUDA_VISIBLE_DEVICES``, ``POCL_*``, ...) differ. Refused clients run the
command themselves, so old code never answers silently.
"""

from __future__ import annotations

import contextlib
import io
import os
import signal
import socket
import struct
import sys
import threading
import time
import traceback
from pathlib import Path

from place3d_kernels.profiling import count_start_up_of

__all__ = ["add_arguments", "serve", "Server", "client_wire", "is_listening", "DEFAULT_IDLE_TIMEOUT_S", "KEEP_PSOGS"]

#: Seconds without a command after which the server exits.
DEFAULT_IDLE_TIMEOUT_S = 900.0
#: P-SOGs kept in memory between commands (``sog.keep_loaded``); the dense 0.2 m town grid with its
#: prepared backend copy is a few hundred MB at most.
KEEP_PSOGS = 4
#: The most bytes of a Unix socket path (``sun_path`` holds 108 with its terminating NUL).
MAX_SOCKET_PATH = 107


def add_arguments(p) -> None:
    """The options of ``place3d serve``."""
    p.add_argument("--socket", default=None,
                   help="Unix socket to listen on (default: per user, interpreter and checkout, under "
                        "$XDG_RUNTIME_DIR/place3d or the P-SOG cache folder); clients name it with --server=PATH")
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
    path = Path(args.socket) if args.socket else wire.default_socket()
    if args.idle_timeout < 0:
        raise ValueError(f"--idle-timeout must be >= 0 seconds (0 = never), got {args.idle_timeout}")
    _check_socket_path(path)
    if args.detach:
        return _detach(args, path)
    server = Server(path, command, idle_timeout=args.idle_timeout)
    server.warm(args.backend, warm)
    return server.serve_forever()


def client_wire():
    """``place3d_app.wire`` (the socket, messages and identity the client shares), imported on use: the
    CLI imports this module for its parser, and a checkout installed before ``place3d_app`` existed
    must still run every other command.

    Raises:
        ValueError: ``place3d_app`` is not importable (reinstall the package: ``pip install -e .``).
    """
    try:
        from place3d_app import wire
    except ImportError as e:
        raise ValueError(f"place3d serve needs the place3d_app package beside place3d_kernels ({e}); "
                         f"reinstall the package (pip install -e . in the checkout)") from None
    return wire


def _check_socket_path(path: Path) -> None:
    n = len(os.fsencode(str(path)))
    if n > MAX_SOCKET_PATH:
        raise ValueError(f"socket path {path} is {n} bytes, Unix sockets allow {MAX_SOCKET_PATH}; give a shorter "
                         f"one with --socket (e.g. /tmp/place3d.sock)")


class _Stop(BaseException):
    """SIGTERM: leave the serve loop (a BaseException, so no command's ``except Exception`` swallows it)."""


class Server:
    """One listening socket, one command at a time on the main thread (see the module doc).

    Args:
        path: the socket path.
        command: ``command(None) -> int`` runs the ``place3d`` command line in ``sys.argv``.
        idle_timeout: seconds without a command before ``serve_forever`` returns (0 = never).
    """

    def __init__(self, path: Path, command, idle_timeout: float = DEFAULT_IDLE_TIMEOUT_S):
        self.path, self.command, self.idle_timeout = Path(path), command, float(idle_timeout)
        # a command may chdir (the server does, per client): an import path relative to the folder the server
        # started in ("" with python -c) must keep naming that folder
        sys.path[:] = [os.path.abspath(p) if not os.path.isabs(p) else p for p in sys.path]
        self.wire = wire = client_wire()
        self.identity = wire.identity()
        self.startup_env = wire.startup_env()
        self.backend = None
        self.stopping = False
        self._lock = threading.Lock()
        self._busy = False
        self._client_interrupt = False
        self._run_id = 0                       # which command runs: a late watcher of an earlier one stays quiet
        # the server's own messages go to its stderr as it was at start, never into a client's
        self.log = open(os.dup(2), "w", buffering=1, encoding="utf-8", errors="backslashreplace")

    def say(self, text: str) -> None:
        print(f"place3d serve: {text}", file=self.log)

    # ------------------------------------------------------------------ start-up
    def warm(self, backend: str | None, warm) -> None:
        """Import what commands use and start the backend, so the first command finds them loaded."""
        t = time.perf_counter()
        import numpy  # noqa: F401 - imported to have it loaded

        from place3d_kernels.backends.registry import get_backend
        from place3d_kernels.lazy_imports import import_cma
        from place3d_kernels.optimize.plots import keep_worker
        from place3d_kernels.sog import keep_loaded

        warm()                   # the CLI's parser: imports every subcommand's module
        import_cma()
        import tqdm  # noqa: F401
        self.backend = get_backend(backend).name      # imports Warp / PyOpenCL, starts CUDA or the OpenCL device
        keep_loaded(KEEP_PSOGS)
        # multiprocessing's resource tracker lives as long as this process once a command spawns a process
        # (optimize's plot worker on 4+ cores); started by a command it would inherit that client's stdout
        # and stderr and hold its pipe open after the command ends. Started now it holds the server's own.
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
        keep_worker()            # optimize's plots: a pool with matplotlib imported, shared by the commands
        settle_memory()
        self.say(f"pid {os.getpid()}, backend {self.backend}, loaded in {time.perf_counter() - t:.2f} s")

    # ------------------------------------------------------------------ the loop
    def serve_forever(self) -> int:
        """Serve until idle for ``idle_timeout`` s, SIGTERM, Ctrl-C while idle, or a client with newer code."""
        listener = self._bind()
        old_int = signal.signal(signal.SIGINT, self._on_sigint)
        old_term = signal.signal(signal.SIGTERM, self._on_sigterm)
        self.say(f"listening on {self.path}" + (f" (exits after {self.idle_timeout:g} s idle)"
                                                 if self.idle_timeout else ""))
        why = "stopped"
        try:
            while not self.stopping:
                listener.settimeout(self.idle_timeout or None)
                try:
                    conn, _ = listener.accept()
                except TimeoutError:
                    why = f"idle for {self.idle_timeout:g} s, exiting"
                    break
                try:
                    self.handle(conn)
                except KeyboardInterrupt:
                    if not self._client_interrupt:
                        raise
                    # a client's Ctrl-C that landed just after its command ended: nothing left to stop
                except OSError as e:
                    self.say(f"connection failed: {e}")
                finally:
                    conn.close()
            else:
                why = "a client runs newer code; exiting (start the server again to serve it)"
        except KeyboardInterrupt:
            why = "interrupted, exiting"
        except _Stop:
            why = "terminated, exiting"
        finally:
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)
            listener.close()
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        self.say(why)
        return 0

    def _bind(self) -> socket.socket:
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        if self.path.exists():
            if is_listening(self.path):
                raise ValueError(f"a server already listens on {self.path}; use it (place3d --server ...), stop it "
                                 f"(SIGTERM to its pid), or start this one with another --socket")
            self.path.unlink()                  # left by a server that did not exit cleanly
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)                   # the socket is born 0600: this user only
        try:
            listener.bind(str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        listener.listen(16)
        return listener

    def _on_sigint(self, signum, frame) -> None:
        if self._busy:
            raise KeyboardInterrupt            # stops the running command, as Ctrl-C does in-process
        if self._client_interrupt:
            return                             # late: the command it was meant for has ended
        raise KeyboardInterrupt                # Ctrl-C in the server's own terminal while idle: stop serving

    def _on_sigterm(self, signum, frame) -> None:
        raise _Stop()

    # ------------------------------------------------------------------ one client
    def handle(self, conn: socket.socket) -> None:
        """Greet one client, check it, run its command and send the exit code."""
        pid, uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                             struct.calcsize("3i")))
        if uid != os.getuid():
            self.say(f"refused a client of uid {uid} (pid {pid})")
            return
        try:
            self.wire.send(conn, {"type": "ready", "pid": os.getpid(), "backend": self.backend})
            hello, fds = self.wire.recv_with_fds(conn)
        except (BrokenPipeError, ConnectionResetError):
            return                              # a client that only checked the server is up, and left
        try:
            if hello is None or hello.get("type") != "run":
                return                          # a client that only checked the server is up
            refusal = self._refusal(hello, fds)
            if refusal:
                self.say(f"refused pid {pid}: {refusal}")
                self.wire.send(conn, {"type": "refused", "message": refusal})
                return
            self._check_plot_worker()
            self.wire.send(conn, {"type": "started"})
            t = time.perf_counter()
            code = self._run(conn, hello, fds, pid)
            self.say(f"pid {pid} in {hello['cwd']}: {' '.join(hello['argv'][1:])} -> exit {code} in "
                     f"{time.perf_counter() - t:.2f} s")
            with contextlib.suppress(OSError):          # the client may have gone (Ctrl-C twice)
                self.wire.send(conn, {"type": "exit", "code": code})
        finally:
            for fd in fds:
                os.close(fd)
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)         # ends the watcher's read
        settle_memory()                                 # after the client has its exit code

    def _check_plot_worker(self) -> None:
        """Before a command, with the server's own streams: replace the plot pool if its process died."""
        from place3d_kernels.optimize.plots import keep_worker

        if keep_worker():
            self.say("the plot worker had stopped; started a new one")

    def _refusal(self, hello: dict, fds: list) -> str | None:
        if hello.get("identity") != self.identity:
            self.stopping = True
            return (f"the server (pid {os.getpid()}) runs the package, interpreter or dependencies as they were "
                    f"when it started, and they have changed since; it stops now. Start it again with "
                    f"'place3d serve' to use the server")
        env = self.wire.startup_env(hello.get("env", {}))
        if env != self.startup_env:
            names = sorted(k for k in set(env) | set(self.startup_env) if env.get(k) != self.startup_env.get(k))
            return (f"start-up variables differ from the server's ({', '.join(names)}), and a running process "
                    f"cannot take new ones; start a server with this environment (another --socket) to use one")
        if len(fds) != 3:
            return f"expected the client's 3 standard descriptors, got {len(fds)}"
        if not os.path.isdir(hello.get("cwd", "")):
            return f"the working directory {hello.get('cwd')!r} is not a folder here"
        return None

    def _run(self, conn: socket.socket, hello: dict, fds: list, pid: int) -> int:
        with self._lock:
            self._run_id += 1
            self._busy, self._client_interrupt = True, False
            run_id = self._run_id
        watcher = threading.Thread(target=self._watch, args=(conn, run_id), name="place3d-serve-watch",
                                   daemon=True)
        watcher.start()
        try:
            with client_side(hello, fds):
                count_start_up_of(pid)          # --profile: the client's start-up, not the server's age
                try:
                    return run_command(self.command)
                finally:
                    count_start_up_of(None)
        finally:
            with self._lock:
                self._busy = False

    def _watch(self, conn: socket.socket, run_id: int) -> None:
        """Pass a client's interrupt (or its leaving) to the main thread as SIGINT, while its command runs.

        A watcher can see its client's connection close after the next command has started (a loaded
        machine); ``run_id`` keeps it from interrupting that command."""
        while True:
            try:
                msg = self.wire.recv(conn)
            except (OSError, ValueError):
                msg = None
            if msg is None or msg.get("type") == "interrupt":
                with self._lock:
                    if self._busy and self._run_id == run_id and not self._client_interrupt:
                        self._client_interrupt = True
                        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
            if msg is None:
                return


def settle_memory() -> None:
    """Collect the garbage of the last command (or of start-up), then freeze what is left (``gc.freeze``).

    A resident process holds some 10^5 objects that live as long as it does (modules, the parser, pycma,
    matplotlib's registries). Python's oldest-generation collection walks all of them, and one ran during
    each warm ``place3d optimize`` (0.11 s on the 2-core dev VM, in the middle of the search). Frozen,
    they are skipped, so a command's collections see only what the command made. This runs between
    commands, when the client already has its answer: unfreezing first lets the next collection free
    what an earlier command left in reference cycles, so nothing frozen leaks."""
    import gc

    gc.unfreeze()
    gc.collect()
    gc.freeze()


def run_command(command) -> int:
    """``command(None)`` as the in-process ``place3d`` would end: its exit code, errors printed on stderr."""
    import warnings

    import numpy as np

    try:
        warnings.onceregistry.clear()
        # catch_warnings also resets which warnings were shown already: each command warns as a fresh process
        with warnings.catch_warnings(), np.errstate(**np.geterr()), np.printoptions(**np.get_printoptions()):
            return int(command(None) or 0)
    except SystemExit as e:                     # argparse errors (2), --help and --version (0)
        if e.code is None or isinstance(e.code, int):
            return int(e.code or 0)
        print(e.code, file=sys.stderr)
        return 1
    except KeyboardInterrupt:                   # before the CLI's own handler was reached
        print("place3d: interrupted", file=sys.stderr)
        return 130
    except _Stop:
        raise
    except BaseException:                       # an uncaught error: the traceback and exit 1, as Python does
        traceback.print_exc()
        return 1


@contextlib.contextmanager
def client_side(hello: dict, fds: list):
    """Take on the client's standard streams, environment, working directory, umask and argv; restore after."""
    saved_streams = (sys.stdin, sys.stdout, sys.stderr)
    for s in saved_streams[1:]:
        s.flush()
    saved_fds = [os.dup(i) for i in range(3)]
    saved_env, saved_cwd, saved_argv = dict(os.environ), os.getcwd(), sys.argv
    saved_umask = os.umask(0o022)
    try:
        for i, fd in enumerate(fds):
            os.dup2(fd, i)
        streams = hello.get("streams", {})
        sys.stdin = _text_stream(0, streams.get("stdin", {}), write=False)
        sys.stdout = _text_stream(1, streams.get("stdout", {}), write=True)
        sys.stderr = _text_stream(2, streams.get("stderr", {"line_buffering": True}), write=True)
        os.environ.clear()
        os.environ.update(hello["env"])
        os.chdir(hello["cwd"])
        os.umask(int(hello["umask"]))
        sys.argv = list(hello["argv"])
        yield
    finally:
        for s in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                s.flush()
        sys.stdin, sys.stdout, sys.stderr = saved_streams
        for i, fd in enumerate(saved_fds):
            os.dup2(fd, i)
            os.close(fd)
        os.environ.clear()
        os.environ.update(saved_env)
        os.chdir(saved_cwd)
        os.umask(saved_umask)
        sys.argv = saved_argv


def _text_stream(fd: int, opts: dict, write: bool) -> io.TextIOWrapper:
    """A text stream on ``fd`` set up as the client's (encoding, errors, buffering); ``fd`` stays open."""
    raw = io.FileIO(fd, "w" if write else "r", closefd=False)
    buffered = io.BufferedWriter(raw) if write else io.BufferedReader(raw)
    return io.TextIOWrapper(buffered, encoding=opts.get("encoding", "utf-8"), errors=opts.get("errors", "strict"),
                            line_buffering=bool(opts.get("line_buffering", False)),
                            write_through=bool(opts.get("write_through", False)))


def is_listening(path: Path) -> bool:
    """Whether a server accepts connections on ``path`` (it greets, sees no command and carries on)."""
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
        return True
    except OSError:
        return False
    finally:
        probe.close()


def _detach(args, path: Path) -> int:
    """Start ``place3d serve`` in a session of its own and return once it listens."""
    import subprocess

    if is_listening(path):
        raise ValueError(f"a server already listens on {path}; use it (place3d --server ...), stop it (SIGTERM to "
                         f"its pid), or start this one with another --socket")
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    log = path.with_suffix(".log")
    cmd = [sys.executable, "-m", "place3d_app", "serve", "--socket", str(path),
           "--idle-timeout", str(args.idle_timeout)] + (["--backend", args.backend] if args.backend else [])
    with open(log, "ab") as f:
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
