"""What the ``place3d`` client and the ``place3d serve`` process share: the socket, the messages, the identity,
and the checks each side makes of the other.

Standard library only: the client imports this module before it knows whether the package (NumPy, the
backends) is needed at all.

Messages are JSON objects, each framed by a 4-byte big-endian length. The first client message also
carries the client's standard input, output and error as file descriptors (``SCM_RIGHTS``, Python's
``socket.send_fds``; the same design as Mercurial's ``chg``), so the server writes straight into the
client's terminal, pipe or file: output is the bytes the in-process command would write, C-level output
of the native libraries included, and nothing is copied through the socket.

That first message holds the client's whole environment and its live standard streams, so neither side
trusts the other before checking it (see ``docs/security.md``, "The server"):

- the socket must sit in a folder only this user can write (``unsafe_folder``), be a socket owned by this
  user (``socket_problem``), and the process on the other end must run as this user (``peer_credentials``);
- every frame is read with a size cap checked on the length field before anything is allocated, must be
  UTF-8 JSON holding an object (``recv``, ``FrameError``), and a request must carry its fields with the right
  types (``run_problem``).
"""

from __future__ import annotations

import codecs
import hashlib
import importlib.util
import io
import json
import os
import socket
import stat
import struct
import sys
import time
from pathlib import Path

__all__ = ["default_socket", "identity", "startup_env", "send", "recv", "send_with_fds", "recv_with_fds",
           "FrameError", "peer_credentials", "unsafe_folder", "socket_problem", "private_folder", "run_problem",
           "STARTUP_ENV_PREFIXES", "PACKAGES", "MAX_REQUEST_BYTES", "MAX_MESSAGE_BYTES"]

#: The packages whose source makes up the command: an edit to any of their ``SOURCE_SUFFIXES`` files is new code.
PACKAGES = ("place3d_kernels", "place3d_app")
#: Files a warm process holds in memory in some form: Python modules, OpenCL kernel sources (built once
#: per backend instance), TOML presets and configs.
SOURCE_SUFFIXES = (".py", ".cl", ".toml")

#: Third-party packages a command runs; an upgrade (a new ``__init__.py``) is new code as well.
DEPENDENCIES = ("numpy", "warp", "cma", "pyopencl", "scipy", "trimesh", "tqdm", "matplotlib")

#: Environment variables read when a library loads or a device starts (CUDA, OpenCL/PoCL, Warp, OpenMP and
#: BLAS thread pools, matplotlib's MPLBACKEND / MPLCONFIGDIR, the interpreter's own); a warm process cannot
#: apply a different value, so a client whose values differ is refused instead of being served with the
#: server's.
STARTUP_ENV_PREFIXES = ("CUDA_", "PYOPENCL_", "POCL_", "OCL_", "WARP_", "PLACE3D_WARP_", "OMP_", "MKL_",
                        "OPENBLAS_", "NVIDIA_", "LD_", "PYTHON", "MPL")

#: The largest request (the client's ``run`` message: argv and environment). Linux caps argv plus
#: environment at a quarter of the stack limit (2 MiB by default), and JSON escapes can double a byte.
MAX_REQUEST_BYTES = 8 << 20
#: The largest of every other message (greetings, refusals, interrupts, exit codes).
MAX_MESSAGE_BYTES = 64 << 10

_HEADER = struct.Struct(">I")
_MAX_FDS = 3


class FrameError(ValueError):
    """A frame that is not a message of this protocol (too long, not UTF-8, not JSON, not an object)."""


# ---------------------------------------------------------------------------------------------- identity
def _package_dir(name: str) -> Path | None:
    spec = importlib.util.find_spec(name)       # finds, never imports (a top-level name has no parent to run)
    if spec is None:
        return None
    if spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations))).resolve()
    return Path(spec.origin).resolve().parent if spec.origin else None


def identity() -> str:
    """A digest of the code a command would run: interpreter, package sources, dependency versions.

    Covers the path, size and modification time (ns) of every source file of ``PACKAGES`` and the
    ``__init__.py`` of each of ``DEPENDENCIES``, plus the interpreter's path and version. Stat calls only
    (about 200 files: a few milliseconds), so the client can afford it on every command.
    """
    h = hashlib.sha256(f"{os.path.realpath(sys.executable)} {sys.version}".encode())
    for name in PACKAGES:
        root = _package_dir(name)
        h.update(f"|{name}={root}".encode())
        if root is None:
            continue
        for line in sorted(_source_stamps(str(root))):
            h.update(line.encode())
    for name in DEPENDENCIES:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        origin = getattr(spec, "origin", None)
        if origin and os.path.exists(origin):
            st = os.stat(origin)
            h.update(f"|{name} {origin} {st.st_size} {st.st_mtime_ns}".encode())
        else:
            h.update(f"|{name} absent".encode())
    return h.hexdigest()[:32]


def _source_stamps(root: str) -> list[str]:
    """'relative path, size, mtime (ns)' of every source file under ``root`` (``os.scandir``: one stat each)."""
    out, todo = [], [root]
    while todo:
        folder = todo.pop()
        with os.scandir(folder) as entries:
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    if e.name != "__pycache__":
                        todo.append(e.path)
                elif e.name.endswith(SOURCE_SUFFIXES):
                    st = e.stat()
                    out.append(f"|{os.path.relpath(e.path, root)} {st.st_size} {st.st_mtime_ns}")
    return out


def startup_env(env=None) -> dict:
    """The variables of ``env`` (default ``os.environ``) that only take effect at start-up (see
    ``STARTUP_ENV_PREFIXES``)."""
    env = os.environ if env is None else env
    return {k: v for k, v in env.items() if k.startswith(STARTUP_ENV_PREFIXES)}


# ---------------------------------------------------------------------------------------------- where
def default_socket() -> Path:
    """The socket of this user's server for this interpreter and package checkout.

    In ``$XDG_RUNTIME_DIR/place3d`` when that variable names a folder of this user that nobody else may
    write (the login manager creates it with mode 0700), else in ``$XDG_CACHE_HOME/place3d-serve`` (default
    ``~/.cache/place3d-serve``), a folder the server creates with mode 0700. Never under ``$PLACE3D_CACHE``:
    a P-SOG cache may be shared with other users, and whoever can write the socket's folder can plant a
    server there. The name carries a hash of the interpreter and package paths, so two checkouts or
    virtual environments never share a server.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isabs(runtime) and os.path.isdir(runtime) and unsafe_folder(runtime) is None:
        folder = Path(runtime) / "place3d"
    else:
        cache = os.environ.get("XDG_CACHE_HOME")
        base = Path(cache) if cache and os.path.isabs(cache) else Path.home() / ".cache"
        folder = base / "place3d-serve"
    where = f"{os.path.realpath(sys.executable)} {_package_dir('place3d_kernels')}"
    return folder / f"serve-{os.getuid()}-{hashlib.sha256(where.encode()).hexdigest()[:12]}.sock"


def unsafe_folder(folder, uid: int | None = None) -> str | None:
    """Why a socket in ``folder`` could be planted or replaced by another user; None when it cannot.

    The folder itself (symbolic links resolved) must belong to ``uid`` (default: this process's) and have
    no group or other write permission. Every folder above it must belong to ``uid`` or root and be
    writable by nobody else, unless it has the sticky bit (``/tmp``): there nobody else may rename or
    remove the entry of ours below it. The same rule as OpenSSH's ``StrictModes``, plus that sticky case.
    """
    uid = os.getuid() if uid is None else uid
    real = os.path.realpath(folder)
    try:
        st = os.stat(real)
    except OSError as e:
        return f"its folder {real} cannot be read ({e.strerror or e})"
    if not stat.S_ISDIR(st.st_mode):
        return f"{real} is not a folder"
    if st.st_uid != uid:
        return f"its folder {real} belongs to uid {st.st_uid}, not to this user (uid {uid})"
    if st.st_mode & 0o022:
        return (f"its folder {real} may be written by other users (mode {stat.S_IMODE(st.st_mode):04o}); "
                f"use a folder only you can write (mode 0700)")
    above = os.path.dirname(real)
    while True:
        st = os.stat(above)
        if st.st_uid not in (uid, 0):
            return f"the folder {above} above it belongs to uid {st.st_uid}, neither this user nor root"
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            return (f"the folder {above} above it may be written by other users (mode "
                    f"{stat.S_IMODE(st.st_mode):04o}), who could replace the folder of the socket")
        if above == os.path.dirname(above):
            return None
        above = os.path.dirname(above)


def socket_problem(path, uid: int | None = None) -> str | None:
    """Why the existing entry ``path`` is not a socket of ``uid`` (default: this process's); None when it is.

    Raises:
        FileNotFoundError: nothing is at ``path``.
    """
    uid = os.getuid() if uid is None else uid
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        return f"{path} is a symbolic link, not a socket; name the socket itself"
    if not stat.S_ISSOCK(st.st_mode):
        return f"{path} is not a socket"
    if st.st_uid != uid:
        return f"the socket {path} belongs to uid {st.st_uid}, not to this user (uid {uid})"
    return None


def private_folder(folder) -> Path:
    """Create ``folder`` (and missing parents) with mode 0700 if it does not exist, then check it.

    Raises:
        ValueError: the folder, or one above it, may be written by another user (``unsafe_folder``).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    problem = unsafe_folder(folder)
    if problem:
        raise ValueError(f"refusing the socket folder {folder}: {problem}")
    return folder


def peer_credentials(sock: socket.socket) -> tuple[int, int, int]:
    """(pid, uid, gid) of the process at the other end of the Unix socket ``sock``, from the kernel.

    Linux's ``SO_PEERCRED``: for a connected client these are the server's when it called ``listen``, for
    an accepted connection the client's when it called ``connect``; neither side can forge them.

    Raises:
        OSError: the platform does not tell (no ``SO_PEERCRED``); callers then refuse the peer.
    """
    opt = getattr(socket, "SO_PEERCRED", None)
    if opt is None:
        raise OSError(f"this platform ({sys.platform}) does not report the peer of a Unix socket (SO_PEERCRED)")
    size = struct.calcsize("3i")
    return struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, opt, size))


# ---------------------------------------------------------------------------------------------- frames
def send(sock: socket.socket, msg: dict) -> None:
    """Send one message."""
    data = json.dumps(msg).encode()
    sock.sendall(_HEADER.pack(len(data)) + data)


def send_with_fds(sock: socket.socket, msg: dict, fds: list[int]) -> None:
    """Send one message with file descriptors attached to its first bytes."""
    data = json.dumps(msg).encode()
    frame = _HEADER.pack(len(data)) + data
    sent = socket.send_fds(sock, [frame], fds)
    if sent < len(frame):
        sock.sendall(frame[sent:])


def _read_exact(sock: socket.socket, n: int, first: bytes = b"", deadline: float | None = None) -> bytes | None:
    """``n`` bytes (None if the peer closes first), read 1 MiB at most at a time, so memory grows with what
    arrives and not with what a length field announces; by ``deadline`` (``time.monotonic``) if given."""
    buf = bytearray(first)
    while len(buf) < n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("timed out")
            sock.settimeout(left)
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def _refuse_constant(name: str):
    raise FrameError(f"the message holds {name}, which JSON does not have")


def decode(body: bytes) -> dict:
    """One message from a frame's body.

    Raises:
        FrameError: not UTF-8, not JSON (NaN and Infinity included), nested deeper than the interpreter's
            recursion limit, or not a JSON object.
    """
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as e:
        raise FrameError(f"the message is not UTF-8 ({e.reason} at byte {e.start})") from None
    try:
        msg = json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as e:
        raise FrameError(f"the message is not JSON ({e.msg} at character {e.pos})") from None
    except RecursionError:                  # the C decoder's own depth check: a clean error, no crash
        raise FrameError("the message nests too deep") from None
    if not isinstance(msg, dict):
        raise FrameError(f"the message is a JSON {type(msg).__name__}, not an object")
    return msg


def _length(head: bytes, limit: int) -> int:
    n = _HEADER.unpack(head)[0]
    if n > limit:
        raise FrameError(f"the message announces {n} bytes; at most {limit} are accepted")
    return n


def recv(sock: socket.socket, limit: int = MAX_MESSAGE_BYTES) -> dict | None:
    """Receive one message of at most ``limit`` bytes; None when the peer closed the connection.

    Raises:
        FrameError: the length field asks for more than ``limit`` (refused before reading the body), or the
            body is not a message (``decode``).
    """
    head = _read_exact(sock, _HEADER.size)
    if head is None:
        return None
    body = _read_exact(sock, _length(head, limit))
    return None if body is None else decode(body)


def recv_with_fds(sock: socket.socket, limit: int = MAX_REQUEST_BYTES,
                  timeout: float | None = None) -> tuple[dict | None, list[int]]:
    """Receive one message sent by ``send_with_fds``: (message or None on a closed connection, descriptors).

    Reads the header alone first (the descriptors travel with it), so a message the client sends right
    after (an interrupt) stays in the socket for ``recv``. The descriptors received are closed here when
    the frame is refused. ``timeout``: seconds for the whole message (a peer that trickles bytes gets no
    more time than a silent one).

    Raises:
        FrameError: as ``recv``; ``OSError`` (``TimeoutError`` included) as the socket's reads.
    """
    deadline = None if timeout is None else time.monotonic() + timeout
    if timeout is not None:
        sock.settimeout(timeout)
    data, fds, _flags, _addr = socket.recv_fds(sock, _HEADER.size, _MAX_FDS)
    try:
        head = _read_exact(sock, _HEADER.size, data, deadline) if data else None
        body = None if head is None else _read_exact(sock, _length(head, limit), deadline=deadline)
        return (None if body is None else decode(body)), fds
    except BaseException:
        for fd in fds:
            os.close(fd)
        raise


# ---------------------------------------------------------------------------------------------- requests
def _os_string(s) -> bool:
    """Whether ``s`` is a str the OS can take (no NUL; encodable as the file system encoding would)."""
    if not isinstance(s, str) or "\0" in s:
        return False
    try:
        os.fsencode(s)
    except UnicodeError:
        return False
    return True


def run_problem(msg: dict) -> str | None:
    """What is wrong with a ``run`` request (the fields the server uses, with their types); None if nothing.

    ``argv``: a non-empty list of strings; ``cwd``: an absolute path; ``env``: an object of strings to
    strings, names without ``=``; ``umask``: an integer 0..0o777; ``identity``: a string; ``streams``
    (optional): for ``stdin``/``stdout``/``stderr``, an ``encoding`` and ``errors`` this Python knows and
    booleans ``line_buffering`` / ``write_through``. No string may hold a NUL or fail to encode as a path.
    """
    if msg.get("type") != "run":
        return f"expected a 'run' request, got type {msg.get('type')!r}"
    argv = msg.get("argv")
    if not isinstance(argv, list) or not argv or not all(_os_string(a) for a in argv):
        return "'argv' must be a non-empty list of strings without NUL"
    cwd = msg.get("cwd")
    if not _os_string(cwd) or not os.path.isabs(cwd):
        return "'cwd' must be an absolute path (a string without NUL)"
    env = msg.get("env")
    if not isinstance(env, dict) or not all(_os_string(k) and k and "=" not in k and _os_string(v)
                                            for k, v in env.items()):
        return "'env' must be an object of names (without '=') to strings, without NUL"
    umask = msg.get("umask")
    if type(umask) is not int or not 0 <= umask <= 0o777:
        return f"'umask' must be an integer from 0 to 0o777, got {umask!r}"
    if not isinstance(msg.get("identity"), str):
        return "'identity' must be a string"
    streams = msg.get("streams", {})
    if not isinstance(streams, dict) or set(streams) - {"stdin", "stdout", "stderr"}:
        return "'streams' must be an object with stdin, stdout or stderr"
    for name, opts in streams.items():
        if not isinstance(opts, dict):
            return f"'streams.{name}' must be an object"
        for key in ("line_buffering", "write_through"):
            if key in opts and not isinstance(opts[key], bool):
                return f"'streams.{name}.{key}' must be true or false"
        if not all(isinstance(opts.get(key, ""), str) for key in ("encoding", "errors")):
            return f"'streams.{name}.encoding' and '.errors' must be strings"
        try:
            # TextIOWrapper refuses what is no text encoding (rot13, base64) as the server's stream would
            io.TextIOWrapper(io.BytesIO(), encoding=opts.get("encoding", "utf-8"))
            codecs.lookup_error(opts.get("errors", "strict"))
        except (LookupError, TypeError, ValueError):
            return f"'streams.{name}' names an encoding or error handler this Python does not know"
    return None
