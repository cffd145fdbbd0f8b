"""What the ``place3d`` client and the ``place3d serve`` process share: the socket, the messages, the identity.

Standard library only: the client imports this module before it knows whether the package (NumPy, the
backends) is needed at all.

Messages are JSON objects, each framed by a 4-byte big-endian length. The first client message also
carries the client's standard input, output and error as file descriptors (``SCM_RIGHTS``, Python's
``socket.send_fds``; the same design as Mercurial's ``chg``), so the server writes straight into the
client's terminal, pipe or file: output is the bytes the in-process command would write, C-level output
of the native libraries included, and nothing is copied through the socket.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import socket
import struct
import sys
from pathlib import Path

__all__ = ["default_socket", "identity", "startup_env", "send", "recv", "send_with_fds", "recv_with_fds",
           "STARTUP_ENV_PREFIXES", "PACKAGES"]

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

_HEADER = struct.Struct(">I")
_MAX_FDS = 3


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


def default_socket() -> Path:
    """The socket of this user's server for this interpreter and package checkout.

    ``$XDG_RUNTIME_DIR/place3d`` (a per-user folder the login manager creates with mode 0700), else the
    P-SOG cache folder (``$PLACE3D_CACHE`` or ~/.cache/place3d). The name carries a hash of the
    interpreter and package paths, so two checkouts or virtual environments never share a server.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isdir(runtime):
        folder = Path(runtime) / "place3d"
    else:
        folder = Path(os.environ.get("PLACE3D_CACHE", Path.home() / ".cache" / "place3d"))
    where = f"{os.path.realpath(sys.executable)} {_package_dir('place3d_kernels')}"
    return folder / f"serve-{os.getuid()}-{hashlib.sha256(where.encode()).hexdigest()[:12]}.sock"


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


def _read_exact(sock: socket.socket, n: int, first: bytes = b"") -> bytes | None:
    buf = bytearray(first)
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def recv(sock: socket.socket) -> dict | None:
    """Receive one message; None when the peer closed the connection."""
    head = _read_exact(sock, _HEADER.size)
    if head is None:
        return None
    body = _read_exact(sock, _HEADER.unpack(head)[0])
    return None if body is None else json.loads(body)


def recv_with_fds(sock: socket.socket) -> tuple[dict | None, list[int]]:
    """Receive one message sent by ``send_with_fds``: (message or None on a closed connection, descriptors).

    Reads the header alone first (the descriptors travel with it), so a message the client sends right
    after (an interrupt) stays in the socket for ``recv``.
    """
    data, fds, _flags, _addr = socket.recv_fds(sock, _HEADER.size, _MAX_FDS)
    head = _read_exact(sock, _HEADER.size, data) if data else None
    body = None if head is None else _read_exact(sock, _HEADER.unpack(head)[0])
    return (None if body is None else json.loads(body)), fds
