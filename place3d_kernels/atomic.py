"""Atomic file writes for every file the package writes: caches, outputs, checkpoints, frames.

``atomic_write(path, data)`` writes to a temporary file beside ``path`` and renames it over ``path``
(``os.replace``), so a reader never sees half a file, a full disk never leaves an empty or truncated
output, and a killed writer leaves the previous version (or nothing). On any ``OSError`` the temporary
file is removed and a ``WriteError`` is raised: an ``OSError`` whose message is one line naming the path
and the cause (``place3d: error: cannot write out.json: no space left on device (errno 28)``), which the
command line prints without a traceback.

A writer killed between the creation of its temporary file and the rename (SIGKILL, power loss) leaves
that file behind. Temporary names say who wrote them (``<name>.p3tmp-<host>-<pid>-<thread>``), so the next
write into the same folder removes those of processes of this host that no longer run, and those of any
host older than a day (``remove_stale_temps``; once per folder and process). The temporary names of
earlier versions of the package (``*.tmp.npz``, ``checkpoint.pkl.tmp``, ...) are removed once they are an
hour old: no writer takes that long.
"""

from __future__ import annotations

import errno
import os
import re
import socket
import threading
import time
from pathlib import Path

__all__ = ["atomic_write", "atomic_write_text", "atomic_savefig", "WriteError", "remove_stale_temps", "temp_name", "TEMP_MARK",
           "file_identity"]

TEMP_MARK = ".p3tmp-"
#: temporary files of other hosts (a cache folder on a shared file system) are removed after this long
STALE_OTHER_HOST_S = 24 * 3600
#: temporary files named as earlier versions named them are removed after this long
STALE_LEGACY_S = 3600
_HOST = re.sub(r"[^A-Za-z0-9_.]", "_", socket.gethostname())[:40] or "host"
_OURS = re.compile(r"\.p3tmp-(?P<host>[A-Za-z0-9_.]+)-(?P<pid>\d+)-(?P<tid>\d+)$")
# the temporary names of earlier versions: sog.save, subset records, checkpoints, manifests, study cells,
# scene key memos, interval memos, frames
_LEGACY = re.compile(r"(\.\d+-\d+\.tmp\.npz|\.tmp\.npz|\.pkl\.tmp|\.json\.tmp\d+(-\d+)?|\.tmp\d+|\.\d+\.tmp"
                     r"|\.(bin|label)\.tmp)$")
_cleaned: set = set()
_cleaned_lock = threading.Lock()


class WriteError(OSError):
    """A file could not be written; ``str()`` is one line: the path and the cause."""

    def __init__(self, path, cause: OSError):
        code = cause.errno
        why = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
               errno.EROFS: "read-only file system", errno.EACCES: "permission denied"}.get(
            code, (cause.strerror or str(cause) or type(cause).__name__).lower())
        super().__init__(code, why, str(path))
        self.path = str(path)
        self.cause = why

    def __str__(self) -> str:
        tail = f" (errno {self.errno})" if self.errno else ""
        return f"cannot write {self.path}: {self.cause}{tail}"


def temp_name(path: Path) -> Path:
    """The temporary file of ``path`` for this process and thread."""
    return path.with_name(f"{path.name}{TEMP_MARK}{_HOST}-{os.getpid()}-{threading.get_ident()}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:             # exists, owned by someone else
        return True
    return True


def remove_stale_temps(folder, force: bool = False) -> list:
    """Remove the temporary files of killed writers in ``folder`` (see the module's docstring); returns
    the paths removed. Runs once per folder and process unless ``force``."""
    folder = Path(folder)
    key = str(folder.resolve()) if folder.exists() else str(folder)
    with _cleaned_lock:
        if key in _cleaned and not force:
            return []
        _cleaned.add(key)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for e in entries:
        name = e.name
        m = _OURS.search(name)
        stale = False
        try:
            if m is not None:
                if m["host"] == _HOST:
                    stale = int(m["pid"]) != os.getpid() and not _alive(int(m["pid"]))
                else:
                    stale = now - e.stat(follow_symlinks=False).st_mtime > STALE_OTHER_HOST_S
            elif _LEGACY.search(name):
                stale = now - e.stat(follow_symlinks=False).st_mtime > STALE_LEGACY_S
            if stale and e.is_file(follow_symlinks=False):
                os.unlink(e.path)
                removed.append(e.path)
        except OSError:
            pass            # gone meanwhile, or not ours to remove
    return removed


def atomic_write(path, data, *, fsync: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file beside it, then a rename.

    Args:
        path: the file to write (its folder is created).
        data: ``bytes``, ``str`` (UTF-8), or a callable ``data(fileobj)`` that writes into the open binary
            file (e.g. ``lambda f: fig.savefig(f, format="png")``).
        fsync: flush the file to the disk before the rename (checkpoints: a power loss then leaves the
            previous or the new file, never an empty one).

    Returns:
        ``path`` as a ``Path``.

    Raises:
        WriteError: any ``OSError`` on the way (full disk, quota, permissions); the temporary file is gone
            and ``path`` is as it was.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WriteError(path.parent, e) from None
    remove_stale_temps(path.parent)
    tmp = temp_name(path)
    try:
        with open(tmp, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise WriteError(path, e) from None
        raise
    return path


def atomic_write_text(path, text: str, *, fsync: bool = False) -> Path:
    """``atomic_write`` of ``text`` (UTF-8)."""
    return atomic_write(path, text.encode(), fsync=fsync)


def atomic_savefig(fig, path, **kw) -> Path:
    """``fig.savefig(path, **kw)`` through ``atomic_write`` (the format from the suffix unless given)."""
    fmt = kw.pop("format", None) or (Path(path).suffix[1:].lower() or "png")
    return atomic_write(path, lambda f: fig.savefig(f, format=fmt, **kw))


def file_identity(path) -> tuple | None:
    """(resolved path, device, inode, size, modification time in ns) of a file, or None if it is absent: the key
    under which a process keeps what it read from a cache file (``sog.keep_loaded``, the left-out grids of
    ``left_out_memo``, ``pool_memo``). ``atomic_write`` replaces a file (a new inode), so a rewritten file never
    has the identity of the one it replaced."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (os.path.realpath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
