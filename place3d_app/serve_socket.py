"""What the server claims on disk, each checked before use: its socket path and its log.

``place3d serve`` (``place3d_app.serve``) claims the socket path before its slow start, the loop
(``place3d_app.serve_loop``) claims it again when it binds, and ``--detach`` opens the log beside the socket.
Nothing is removed at the socket path but a stale socket of this user's, and the log is opened without
following a symbolic link. ``client_wire`` gives the
socket, message and identity helpers the client shares (``place3d_app.wire``). ``docs/security.md`` ("The
server") lists what the server trusts and what it refuses.
"""

from __future__ import annotations

import errno
import os
import socket
import stat
from pathlib import Path

__all__ = ["client_wire", "is_listening", "claim_socket_path", "open_log"]


def client_wire():
    """``place3d_app.wire`` (the socket, messages and identity the client shares), imported on use: the
    CLI imports ``place3d_app.serve`` (and so this module) for its parser, and a checkout installed before
    ``place3d_app`` existed must still run every other command.

    Raises:
        ValueError: ``place3d_app`` is not importable (reinstall the package: ``pip install -e .``).
    """
    try:
        from place3d_app import wire
    except ImportError as e:
        raise ValueError(f"place3d serve needs the place3d_app package beside place3d_kernels ({e}); "
                         f"reinstall the package (pip install -e . in the checkout)") from None
    return wire


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


def claim_socket_path(path: Path, remove: bool) -> None:
    """Make sure ``path`` is free for this user's server: nothing there, or a stale socket of ours.

    Stale means: a socket (not a link, file or folder), owned by this user, on which a connect is refused
    (``ECONNREFUSED``: nobody listens; a server that did not exit cleanly left it). Only such a socket is
    removed (with ``remove``); anything else is refused, and left as it is.

    Raises:
        ValueError: something else is at ``path``, or a server answers on it.
    """
    wire = client_wire()
    try:
        problem = wire.socket_problem(path)
    except FileNotFoundError:
        return
    if problem:
        raise ValueError(f"refusing to listen on {path}: {problem}. Nothing was removed; move it away yourself "
                         f"or start the server with another --socket")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except ConnectionRefusedError:
        if remove:
            path.unlink()                       # ours, and nobody answers: left by a server that did not exit
        return
    except OSError as e:
        raise ValueError(f"refusing to listen on {path}: cannot tell whether the socket there is in use "
                         f"({e.strerror or e}); nothing was removed") from None
    finally:
        probe.close()
    raise ValueError(f"a server already listens on {path}; use it (place3d --server ...), stop it (SIGTERM to "
                     f"its pid), or start this one with another --socket")


def open_log(path: Path) -> int:
    """Open the server log ``path`` for appending, created 0600: a descriptor.

    ``O_NOFOLLOW``: a symbolic link at ``path`` (one another user could plant to make the server append to
    a file of theirs choosing) is refused, not followed; so is anything that is not a plain file of ours
    with one name (a FIFO, a device, a hard link).

    Raises:
        ValueError: the log cannot be opened safely.
    """
    flags = (os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NOCTTY
             | os.O_NONBLOCK)               # a planted FIFO must not block the open; refused below
    try:
        fd = os.open(path, flags, 0o600)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ValueError(f"refusing the log {path}: it is a symbolic link, which the server does not follow; "
                             f"remove it, or start the server with another --socket") from None
        if e.errno == errno.ENXIO:          # a FIFO nobody reads, or a socket
            raise ValueError(f"refusing the log {path}: it is not a plain file; remove it, or start the server "
                             f"with another --socket") from None
        raise ValueError(f"cannot open the log {path} ({e.strerror or e})") from None
    st = os.fstat(fd)
    problem = (None if stat.S_ISREG(st.st_mode) else "it is not a plain file") or \
              (None if st.st_uid == os.getuid() else f"it belongs to uid {st.st_uid}") or \
              (None if st.st_nlink == 1 else f"it has {st.st_nlink} names (hard links)")
    if problem:
        os.close(fd)
        raise ValueError(f"refusing the log {path}: {problem}; remove it, or start the server with another --socket")
    os.set_blocking(fd, True)
    return fd
