"""The server of ``place3d serve``: its listening socket, the connections' checks, the job queue, signals.

``Server`` greets and checks each connection on a thread of its own (the peer's credentials, one
well-formed ``run`` request within ``HANDSHAKE_TIMEOUT_S``, the client's identity and start-up
variables) and queues what passes for the main thread, which runs one command at a time. SIGTERM stops
the loop; SIGINT interrupts the running command (a client's Ctrl-C, passed on by its watcher thread) or,
while idle, stops the loop. ``run_command`` and ``client_side`` run one command the way the in-process
``place3d`` would, in the client's streams, environment, working directory, umask and ``sys.argv``;
``settle_memory`` tidies up between commands. The entry point and its options are in
``place3d_app.serve``, the socket path and log checks in ``place3d_app.serve_socket``.
"""

from __future__ import annotations

import contextlib
import io
import os
import queue
import signal
import socket
import stat
import sys
import threading
import time
import traceback
from pathlib import Path

from place3d_app.serve_socket import claim_socket_path, client_wire
from place3d_kernels.profiling import count_start_up_of

__all__ = ["Server", "run_command", "client_side", "settle_memory", "DEFAULT_IDLE_TIMEOUT_S", "KEEP_PSOGS", "KEEP_POOLS",
           "HANDSHAKE_TIMEOUT_S", "MAX_HANDSHAKES"]

#: Seconds without a command after which the server exits.
DEFAULT_IDLE_TIMEOUT_S = 900.0
#: P-SOGs kept in memory between commands (``sog.keep_loaded``); one on the default 0.1 m grid keeps dense
#: fields of about 0.3 GB (``grid.DENSE_BYTES_PER_VOXEL``) and as much again in its prepared backend copy.
KEEP_PSOGS = 4
#: Pooled P-SOGs kept between commands (``pool_memo.keep_pools``) with their P-SOGs and prepared grids: a default
#: ``optimize`` pools its four searched drives and four held-out ones, ``evaluate`` the searched four. One
#: default pool keeps 1.3 GB of host memory with a CPU backend's grids (``pool_memo.keep_pools``), less on a GPU.
KEEP_POOLS = 2
#: Seconds a connected client has to send its request after the greeting; the client sends it at once
#: (computing its identity takes milliseconds), so only a stalled or hostile peer reaches this.
HANDSHAKE_TIMEOUT_S = 10.0
#: Connections greeted and checked at the same time; one more is turned away with an error reply.
MAX_HANDSHAKES = 32


class _Stop(BaseException):
    """SIGTERM: leave the serve loop (a BaseException, so no command's ``except Exception`` swallows it)."""


class _Job:
    """A checked request waiting for the main thread: the connection, the request, the client's descriptors."""

    def __init__(self, conn: socket.socket, hello: dict, fds: list, pid: int):
        self.conn, self.hello, self.fds, self.pid = conn, hello, fds, pid

    def close(self) -> None:
        for fd in self.fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.fds = []
        with contextlib.suppress(OSError):
            self.conn.shutdown(socket.SHUT_RDWR)        # ends the watcher's read
        self.conn.close()


class Server:
    """One listening socket; connections checked on threads, commands run one at a time on the main thread.

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
        self.handshake_timeout = HANDSHAKE_TIMEOUT_S
        self._lock = threading.Lock()
        self._busy = False
        self._client_interrupt = False
        self._run_id = 0                       # which command runs: a late watcher of an earlier one stays quiet
        self._jobs: queue.Queue = queue.Queue()
        self._sigterm = threading.Event()      # set by the SIGTERM handler (_on_sigterm)
        self._handshakes = threading.BoundedSemaphore(MAX_HANDSHAKES)
        self._closing = False
        self._bound = None                     # (st_dev, st_ino) of the socket this server made
        self._say_lock = threading.Lock()
        # the server's own messages go to its stderr as it was at start, never into a client's
        self.log = open(os.dup(2), "w", buffering=1, encoding="utf-8", errors="backslashreplace")

    def say(self, text: str) -> None:
        with self._say_lock:
            print(f"place3d serve: {text}", file=self.log)

    # ------------------------------------------------------------------ start-up
    def warm(self, backend: str | None, warm) -> None:
        """Import what commands use and start the backend, so the first command finds them loaded."""
        t = time.perf_counter()
        import numpy  # noqa: F401 - imported to have it loaded

        from place3d_kernels.backends.registry import get_backend
        from place3d_kernels.lazy_imports import import_cma
        from place3d_kernels.optimize.plots import keep_worker
        from place3d_kernels.pool_memo import keep_pools
        from place3d_kernels.sog import keep_loaded

        warm()                   # the CLI's parser: imports every subcommand's module
        import_cma()
        import tqdm  # noqa: F401
        self.backend = get_backend(backend).name      # imports Warp / PyOpenCL, starts CUDA or the OpenCL device
        keep_loaded(KEEP_PSOGS)
        keep_pools(KEEP_POOLS)
        # multiprocessing's resource tracker lives as long as this process once a command spawns a process
        # (optimize's plot worker on 4+ cores); started by a command it would inherit that client's stdout
        # and stderr and hold its pipe open after the command ends. Started now it holds the server's own.
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
        # so does the server the commands fork their workers from (a forkserver on Linux: reproduce's pool, the
        # drives a cold evaluate or optimize builds); started now, with this process's backend's imports
        from place3d_app import forkserver

        if forkserver.command_start_method() == "forkserver":
            forkserver.start(self.backend)
        keep_worker()            # optimize's plots: a pool with matplotlib imported, shared by the commands
        settle_memory()
        self.say(f"pid {os.getpid()}, backend {self.backend}, loaded in {time.perf_counter() - t:.2f} s")

    # ------------------------------------------------------------------ the loop
    def serve_forever(self) -> int:
        """Serve until idle for ``idle_timeout`` s, SIGTERM, Ctrl-C while idle, or a client with newer code."""
        listener = self._bind()
        old_int = signal.signal(signal.SIGINT, self._on_sigint)
        old_term = signal.signal(signal.SIGTERM, self._on_sigterm)
        threading.Thread(target=self._wake_on_sigterm, name="place3d-serve-term", daemon=True).start()
        threading.Thread(target=self._accept_loop, args=(listener,), name="place3d-serve-accept",
                         daemon=True).start()
        self.say(f"listening on {self.path}" + (f" (exits after {self.idle_timeout:g} s idle)"
                                                 if self.idle_timeout else ""))
        why = "stopped"
        try:
            while not self.stopping:
                try:
                    job = self._jobs.get(timeout=self.idle_timeout or None)
                except queue.Empty:
                    why = f"idle for {self.idle_timeout:g} s, exiting"
                    break
                if job is None:                 # a wake-up: see whether to stop
                    continue
                try:
                    self._serve_job(job)
                except KeyboardInterrupt:
                    if not self._client_interrupt:
                        raise
                    # a client's Ctrl-C that landed just after its command ended: nothing left to stop
                except OSError as e:
                    self.say(f"connection failed: {e}")
                except Exception as e:          # a fault of this code on one request: it fails, the server stays
                    self.say(f"the request of pid {job.pid} failed: {e!r}")
                    traceback.print_exc(file=self.log)
                    with contextlib.suppress(OSError):
                        self.wire.send(job.conn, {"type": "error", "message": f"the server failed: {e!r}"})
                finally:
                    job.close()
                settle_memory()                 # after the client has its exit code
            else:
                why = ("terminated, exiting" if self._sigterm.is_set()
                       else "a client runs newer code; exiting (start the server again to serve it)")
        except KeyboardInterrupt:
            why = "interrupted, exiting"
        except _Stop:
            why = "terminated, exiting"
        finally:
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)
            self._closing = True
            with contextlib.suppress(OSError):
                listener.shutdown(socket.SHUT_RDWR)     # wakes the accepting thread
            listener.close()
            while True:                                 # requests still queued: their clients run here
                try:
                    job = self._jobs.get_nowait()
                except queue.Empty:
                    break
                if job is not None:
                    job.close()
            self._unlink_own_socket()
        self.say(why)
        return 0

    def _bind(self) -> socket.socket:
        self.wire.private_folder(self.path.parent)
        claim_socket_path(self.path, remove=True)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)                   # the socket is born 0600: this user only
        try:
            listener.bind(str(self.path))
        except OSError as e:
            listener.close()
            raise ValueError(f"cannot listen on {self.path} ({e.strerror or e}); is another server starting "
                             f"there? Use another --socket") from None
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        st = os.lstat(self.path)
        self._bound = (st.st_dev, st.st_ino)
        listener.listen(16)
        return listener

    def _unlink_own_socket(self) -> None:
        """Remove the socket this server made, and nothing else that may have replaced it since."""
        try:
            st = os.lstat(self.path)
        except OSError:
            return
        if stat.S_ISSOCK(st.st_mode) and (st.st_dev, st.st_ino) == self._bound:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    def _on_sigint(self, signum, frame) -> None:
        if self._busy:
            raise KeyboardInterrupt            # stops the running command, as Ctrl-C does in-process
        if self._client_interrupt:
            return                             # late: the command it was meant for has ended
        raise KeyboardInterrupt                # Ctrl-C in the server's own terminal while idle: stop serving

    def _on_sigterm(self, signum, frame) -> None:
        # The flag and the waker end the loop even where this exception is lost: Python drops an exception
        # raised in a weakref callback or __del__, where a signal may land. The queue is put to by a thread,
        # not here: the main thread may hold the queue's lock at this very moment.
        self.stopping = True
        self._sigterm.set()
        raise _Stop()

    def _wake_on_sigterm(self) -> None:
        self._sigterm.wait()
        self._jobs.put(None)                    # wakes the main thread's wait for a job, which then stops

    # ------------------------------------------------------------------ connections (their own threads)
    def _accept_loop(self, listener: socket.socket) -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError as e:
                if self._closing:
                    return
                self.say(f"accept failed: {e}")
                time.sleep(0.1)                 # out of descriptors, say: do not spin
                continue
            if self._closing:
                conn.close()
                return
            if not self._handshakes.acquire(blocking=False):
                self._turn_away(conn, None, f"{MAX_HANDSHAKES} connections are being set up already; try again")
                continue
            try:
                threading.Thread(target=self._handshake_thread, args=(conn,), name="place3d-serve-handshake",
                                 daemon=True).start()
            except RuntimeError as e:           # no thread could start
                self._handshakes.release()
                self._turn_away(conn, None, f"cannot take the connection ({e})")

    def _handshake_thread(self, conn: socket.socket) -> None:
        try:
            job = self.handshake(conn)
        except Exception as e:                  # a fault of this code: this connection fails, the server goes on
            self.say(f"a connection failed: {e!r}")
            job = None
        finally:
            self._handshakes.release()
        if job is None:
            conn.close()
        elif self.stopping or self._closing:
            job.close()                         # the client runs the command itself and says why
        else:
            self._jobs.put(job)

    def _turn_away(self, conn: socket.socket, pid: int | None, message: str) -> None:
        """Answer ``conn`` with an error (best effort: a peer that does not read is not waited for) and close it."""
        self.say(f"turned away {'a connection' if pid is None else f'pid {pid}'}: {message}")
        with contextlib.suppress(OSError):
            conn.settimeout(1.0)
            self.wire.send(conn, {"type": "error", "message": message})
        conn.close()

    def handshake(self, conn: socket.socket) -> _Job | None:
        """Check one connection and read its request: the job to run, or None (answered and closed, or gone).

        Runs on the connection's own thread, so a client that stalls here holds up nobody else."""
        try:
            pid, uid, _gid = self.wire.peer_credentials(conn)
        except OSError as e:
            self._turn_away(conn, None, f"cannot tell which user connected ({e}); refused")
            return None
        if uid != os.getuid():
            self.say(f"refused a client of uid {uid} (pid {pid}): this server serves uid {os.getuid()} only")
            conn.close()
            return None
        conn.settimeout(self.handshake_timeout)
        try:
            self.wire.send(conn, {"type": "ready", "pid": os.getpid(), "backend": self.backend})
            hello, fds = self.wire.recv_with_fds(conn, timeout=self.handshake_timeout)
        except self.wire.FrameError as e:
            self._turn_away(conn, pid, f"bad request: {e}")
            return None
        except TimeoutError:
            self._turn_away(conn, pid, f"no request within {self.handshake_timeout:g} s")
            return None
        except OSError:
            conn.close()                        # a client that only checked the server is up, and left
            return None
        if hello is None:
            for fd in fds:
                os.close(fd)
            conn.close()
            return None
        try:
            problem, refusal = self.wire.run_problem(hello), None
            if hello.get("type") == "run" and hello.get("identity") != self.identity:
                problem, refusal = None, self._identity_refusal()
            elif problem is None:
                refusal = self._refusal(hello, fds)
        except BaseException:
            for fd in fds:
                os.close(fd)
            raise
        if problem or refusal:
            for fd in fds:
                os.close(fd)
            if problem:
                self._turn_away(conn, pid, f"bad request: {problem}")
            else:
                self.say(f"refused pid {pid}: {refusal}")
                with contextlib.suppress(OSError):
                    self.wire.send(conn, {"type": "refused", "message": refusal})
                conn.close()
            if self.stopping:
                self._jobs.put(None)            # wakes the main thread, which then stops
            return None
        conn.settimeout(None)
        return _Job(conn, hello, fds, pid)

    def _identity_refusal(self) -> str:
        self.stopping = True
        return (f"the server (pid {os.getpid()}) runs the package, interpreter or dependencies as they were "
                f"when it started, and they have changed since; it stops now. Start it again with "
                f"'place3d serve' to use the server")

    def _refusal(self, hello: dict, fds: list) -> str | None:
        """Why a well-formed request cannot run here (the server's state, not the request's form)."""
        env = self.wire.startup_env(hello["env"])
        if env != self.startup_env:
            names = sorted(k for k in set(env) | set(self.startup_env) if env.get(k) != self.startup_env.get(k))
            return (f"start-up variables differ from the server's ({', '.join(names)}), and a running process "
                    f"cannot take new ones; start a server with this environment (another --socket) to use one")
        if len(fds) != 3:
            return f"expected the client's 3 standard descriptors, got {len(fds)}"
        for i, fd in enumerate(fds):
            try:
                mode = os.fstat(fd).st_mode
            except OSError as e:
                return f"standard descriptor {i} cannot be used ({e.strerror or e})"
            if stat.S_ISDIR(mode):
                return f"standard descriptor {i} is a folder"
        if not os.path.isdir(hello["cwd"]):
            return f"the working directory {hello['cwd']!r} is not a folder here"
        return None

    # ------------------------------------------------------------------ one command (the main thread)
    def _serve_job(self, job: _Job) -> None:
        """Run one checked request and send its exit code."""
        if self.stopping:
            return                              # closed unanswered: the client runs it itself and says why
        if _gone(job.conn):
            self.say(f"pid {job.pid} left before its turn")
            return
        self._check_plot_worker()
        self.wire.send(job.conn, {"type": "started"})
        t = time.perf_counter()
        code = self._run(job.conn, job.hello, job.fds, job.pid)
        self.say(f"pid {job.pid} in {job.hello['cwd']}: {' '.join(job.hello['argv'][1:])} -> exit {code} in "
                 f"{time.perf_counter() - t:.2f} s")
        with contextlib.suppress(OSError):      # the client may have gone (Ctrl-C twice)
            self.wire.send(job.conn, {"type": "exit", "code": code})

    def _check_plot_worker(self) -> None:
        """Before a command, with the server's own streams: replace the plot pool if its process died."""
        from place3d_kernels.optimize.plots import keep_worker

        if keep_worker():
            self.say("the plot worker had stopped; started a new one")

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
        machine); ``run_id`` keeps it from interrupting that command. A malformed message counts as the
        client leaving."""
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


def _gone(conn: socket.socket) -> bool:
    """Whether the peer of ``conn`` has closed its end (a client that stopped waiting for its turn)."""
    try:
        return conn.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def settle_memory() -> None:
    """Collect the garbage of the last command (or of start-up), then freeze what is left (``gc.freeze``).

    A resident process holds some 10^5 objects that live as long as it does (modules, the parser, pycma,
    matplotlib's registries). Python's oldest-generation collection walks all of them, and one ran during
    each warm ``place3d optimize`` (a visible pause in the middle of the search). Frozen, they are skipped,
    so a command's collections see only what the command made. This runs between commands, when the client
    already has its answer: unfreezing first lets the next collection free what an earlier command left in
    reference cycles, so nothing frozen leaks."""
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
