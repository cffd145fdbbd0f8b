"""``place3d serve`` and its client against a hostile local user and a broken peer (issue 33, item 2).

One test (or case) per finding: the client trusted whoever listened on the socket, fell back to running
here without a word, and looked for its default socket under a possibly shared cache; the server died
on malformed requests, stalled behind a silent client, read any length field, appended its log through
a planted symbolic link and deleted whatever was at its socket path. The uid checks are tested by
replacing the credential read (``wire.peer_credentials``) in the process under test, and for real, as
root, with a peer that drops to uid 65534.

Servers here run on the reference backend: their start-up is what the tests wait for, not the command.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import stat
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from place3d_app import wire
from place3d_app import serve
from place3d_app.serve import is_listening

ROOT = Path(__file__).resolve().parents[1]
OTHER_UID = 65534                        # "nobody"; only its number matters
#: The server of these tests turns away a client that sends nothing after this many seconds.
HANDSHAKE_S = 2.0
IS_ROOT = os.geteuid() == 0


#: This process's environment when the module was imported: servers, clients and forged requests all start
#: from it, so a variable set here later (Ray's import sets PYTHONBREAKPOINT when an earlier test used it)
#: cannot make a server refuse a client for its start-up variables instead of what a test checks.
_BASE = dict(os.environ)


def _env(**extra) -> dict:
    path = os.pathsep.join([str(ROOT)] + ([_BASE["PYTHONPATH"]] if _BASE.get("PYTHONPATH") else []))
    env = dict(_BASE, PYTHONPATH=path)
    env.pop("PLACE3D_SERVER", None)
    env.update(extra)
    return env


ENV = _env()


def _place3d(*args, env=None, timeout=120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "place3d_app", *args], env=env or _env(),
                          capture_output=True, text=True, timeout=timeout, **kw)


def _folder(mode: int = 0o700) -> Path:
    folder = Path(tempfile.mkdtemp(prefix="p3x-", dir="/tmp"))     # short: sun_path holds 107 bytes
    folder.chmod(mode)
    return folder


def _rmtree(folder: Path) -> None:
    import shutil

    shutil.rmtree(folder, ignore_errors=True)


#: A server started with a short handshake timeout; ``argv[1]``: the socket; ``argv[2]``: Python run first
#: (a replaced credential read).
SERVER = ("import sys; exec(sys.argv[2]); from place3d_app import serve_loop; serve_loop.HANDSHAKE_TIMEOUT_S = "
          f"{HANDSHAKE_S}; from place3d_app import main; "
          "sys.exit(main(['serve', '--socket', sys.argv[1], '--backend', 'reference', '--idle-timeout', '0']))")


def _start_server(path: Path, prelude: str = "pass") -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", SERVER, str(path), prelude], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 120
    while not is_listening(path):
        assert proc.poll() is None, f"server exited: {proc.stdout.read()}"
        assert time.monotonic() < deadline, "server did not listen within 120 s"
        time.sleep(0.05)
    return proc


def _stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    return out


def _log_so_far(proc: subprocess.Popen) -> str:
    os.set_blocking(proc.stdout.fileno(), False)
    time.sleep(0.3)
    return proc.stdout.read() or ""


@pytest.fixture(scope="module")
def server():
    folder = _folder()
    path = folder / "s.sock"
    proc = _start_server(path)
    yield path, proc
    out = _stop(proc)
    _rmtree(folder)
    assert "terminated, exiting" in out, out


# ================================================================================= the client checks the server
#: A stand-in server: listens on the socket passed as descriptor argv[1] (after becoming uid argv[2] unless
#: it is -1), accepts one connection within argv[3] s, greets it as a real server does and counts the bytes
#: it then receives; prints {"connected": ..., "received": ...}.
FAKE = r"""
import json, os, socket, struct, sys
lst = socket.socket(fileno=int(sys.argv[1]))
uid = int(sys.argv[2])
if uid >= 0:
    os.setgid(uid)
    os.setuid(uid)
lst.listen(4)
lst.settimeout(float(sys.argv[3]))
got = {"connected": False, "received": 0}
try:
    conn, _ = lst.accept()
    got["connected"] = True
    conn.settimeout(5)
    greeting = json.dumps({"type": "ready", "pid": os.getpid(), "backend": "reference"}).encode()
    try:
        conn.sendall(struct.pack(">I", len(greeting)) + greeting)
        while True:
            chunk = conn.recv(1 << 16)
            if not chunk:
                break
            got["received"] += len(chunk)
    except OSError:
        pass
except OSError:
    pass
print(json.dumps(got))
"""


class _Fake:
    """A stand-in listening on ``path`` (bound here, by this process's user), run as ``uid`` (-1: ours)."""

    def __init__(self, path: Path, uid: int = -1, wait_s: float = 8.0):
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(str(path))
        self.proc = subprocess.Popen([sys.executable, "-c", FAKE, str(self.listener.fileno()), str(uid),
                                      str(wait_s)], pass_fds=[self.listener.fileno()], stdout=subprocess.PIPE,
                                     text=True)
        time.sleep(0.5)                          # listening (the client connects after its own start anyway)

    def result(self) -> dict:
        out, _ = self.proc.communicate(timeout=30)
        self.listener.close()
        return json.loads(out)


def _client_with_peer(path: Path, peer: tuple | None = None, *args, env=None) -> subprocess.CompletedProcess:
    """``place3d --server=PATH ARGS`` (default ``--version``), its credential read replaced by ``peer``."""
    patch = f"wire.peer_credentials = lambda sock: {peer!r}; " if peer else ""
    code = (f"import sys; from place3d_app import wire, main; {patch}"
            f"sys.exit(main(['--server={path}', *sys.argv[1:]]))")
    return subprocess.run([sys.executable, "-c", code, *(args or ["--version"])], env=env or _env(),
                          capture_output=True, text=True, timeout=120)


def _ran_here(r: subprocess.CompletedProcess, reason: str) -> None:
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("place3d-kernels "), r.stdout       # --version, run by the client itself
    lines = [x for x in r.stderr.splitlines() if "running here" in x]
    assert len(lines) == 1 and re.search(reason, lines[0]), r.stderr


def test_client_refuses_a_server_of_another_uid_and_sends_it_nothing():
    """The credential read says uid 65534 listens: refused, said once, nothing sent (the greeting was
    waiting for it), and the command runs here."""
    folder = _folder()
    try:
        fake = _Fake(folder / "s.sock")
        r = _client_with_peer(folder / "s.sock", (4242, OTHER_UID, OTHER_UID))
        got = fake.result()
        _ran_here(r, rf"runs as uid {OTHER_UID} .*not as this user")
        assert got == {"connected": True, "received": 0}, got
    finally:
        _rmtree(folder)


@pytest.mark.skipif(not IS_ROOT, reason="becoming another user needs root")
def test_client_refuses_a_server_that_really_runs_as_another_user():
    """No replaced read: the stand-in drops to uid 65534 before it listens, and the kernel says so."""
    folder = _folder()
    try:
        fake = _Fake(folder / "s.sock", uid=OTHER_UID)
        r = _client_with_peer(folder / "s.sock")
        got = fake.result()
        _ran_here(r, rf"runs as uid {OTHER_UID}")
        assert got == {"connected": True, "received": 0}, got
    finally:
        _rmtree(folder)


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o770, 0o702])
def test_client_refuses_a_socket_in_a_folder_others_may_write(mode):
    """Anyone who may write the folder may plant the socket: the client does not even connect."""
    folder = _folder(mode)
    try:
        fake = _Fake(folder / "s.sock", wait_s=4)
        r = _client_with_peer(folder / "s.sock")
        got = fake.result()
        _ran_here(r, r"may be written by other users")
        assert got == {"connected": False, "received": 0}, got
    finally:
        _rmtree(folder)


def test_client_refuses_a_socket_below_a_folder_others_may_write():
    """The socket's own folder is private, but the folder above it lets others rename it away."""
    top = _folder(0o777)
    try:
        inner = top / "d"
        inner.mkdir(mode=0o700)
        fake = _Fake(inner / "s.sock", wait_s=4)
        r = _client_with_peer(inner / "s.sock")
        got = fake.result()
        _ran_here(r, r"above it may be written by other users")
        assert got == {"connected": False, "received": 0}, got
    finally:
        _rmtree(top)


@pytest.mark.skipif(not IS_ROOT, reason="giving a file to another user needs root")
def test_client_refuses_a_socket_of_another_user():
    folder = _folder()
    try:
        fake = _Fake(folder / "s.sock", wait_s=4)
        os.chown(folder / "s.sock", OTHER_UID, OTHER_UID)
        r = _client_with_peer(folder / "s.sock")
        got = fake.result()
        _ran_here(r, rf"belongs to uid {OTHER_UID}")
        assert got == {"connected": False, "received": 0}, got
    finally:
        _rmtree(folder)


def test_client_refuses_a_symbolic_link_to_a_socket():
    folder = _folder()
    try:
        fake = _Fake(folder / "s.sock", wait_s=4)
        (folder / "link.sock").symlink_to(folder / "s.sock")
        r = _client_with_peer(folder / "link.sock")
        got = fake.result()
        _ran_here(r, r"symbolic link")
        assert got["received"] == 0, got
    finally:
        _rmtree(folder)


def test_a_dead_servers_socket_is_said_even_under_a_standing_setting():
    """PLACE3D_SERVER set, a socket left by a server that died (nobody answers): the command runs here and
    the client says why (it used to run here silently, hiding that the server had crashed)."""
    folder = _folder()
    try:
        left = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        left.bind(str(folder / "s.sock"))
        left.close()                                         # the file stays, nobody listens
        r = _place3d("--version", env=_env(PLACE3D_SERVER=str(folder / "s.sock")))
        _ran_here(r, r"is gone \(nothing answers")
    finally:
        _rmtree(folder)


def test_a_server_that_answers_with_an_error_is_said():
    """A greeting that is not 'ready' (here: the server turns the client away) is said, and run here."""
    folder = _folder()
    path = folder / "s.sock"
    proc = _start_server(path, prelude="from place3d_app import serve_loop; serve_loop.MAX_HANDSHAKES = 0")
    try:
        r = _client_with_peer(path)
        _ran_here(r, r"turned this client away: 0 connections are being set up")
    finally:
        _stop(proc)
        _rmtree(folder)


def test_default_socket_is_in_a_private_folder_never_the_shared_cache(tmp_path, monkeypatch):
    shared = tmp_path / "shared-cache"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    monkeypatch.setenv("PLACE3D_CACHE", str(shared))
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = wire.default_socket()
    assert shared not in path.parents
    assert path.parent == tmp_path / "cache" / "place3d-serve"
    # a runtime folder others may write is not used either
    runtime = tmp_path / "run"
    runtime.mkdir()
    runtime.chmod(0o777)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    assert runtime not in wire.default_socket().parents
    runtime.chmod(0o700)
    assert wire.default_socket().parent == runtime / "place3d"
    # the server creates its folder 0700 and checks it
    made = wire.private_folder(tmp_path / "cache" / "place3d-serve")
    assert stat.S_IMODE(made.stat().st_mode) == 0o700


def test_no_message_suggests_a_socket_in_tmp(tmp_path):
    with pytest.raises(ValueError) as e:
        serve._check_socket_path(tmp_path / ("x" * 120))
    assert "/tmp" not in str(e.value).split("Unix sockets allow")[1]


# ================================================================================= the server checks the client
def test_server_refuses_a_client_of_another_uid(tmp_path):
    """The server's credential read says the client is uid 65534: closed before the greeting, logged, and
    the client (which checks the server for real) runs here and says so."""
    folder = _folder()
    path = folder / "s.sock"
    proc = _start_server(path, prelude=f"from place3d_app import wire; "
                                       f"wire.peer_credentials = lambda sock: (4242, {OTHER_UID}, {OTHER_UID})")
    try:
        r = _client_with_peer(path)
        _ran_here(r, r"closed the connection before greeting")
        assert f"refused a client of uid {OTHER_UID}" in _log_so_far(proc)
        assert proc.poll() is None
    finally:
        _stop(proc)
        _rmtree(folder)


def _frame(body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + body


def _request(**change) -> bytes:
    msg = {"type": "run", "argv": ["place3d", "--version"], "cwd": "/", "env": ENV,
           "umask": 0o022, "identity": wire.identity(), "streams": {}}
    msg.update(change)
    for k in [k for k, v in change.items() if v is _DROP]:
        del msg[k]
    return _frame(json.dumps(msg).encode())


_DROP = object()

#: (name, frame bytes, whether the 3 standard descriptors go with it, what the error reply must say).
CASES = [
    ("non-JSON body", _frame(b"this is not JSON"), True, "not JSON"),
    ("JSON list", _frame(b"[1, 2, 3]"), True, "JSON list, not an object"),
    ("JSON string", _frame(b'"run"'), True, "JSON str, not an object"),
    ("invalid UTF-8", _frame(b'{"type": "run", "argv": ["\xff\xfe"]}'), True, "not UTF-8"),
    ("NaN in JSON", _frame(b'{"type": "run", "umask": NaN}'), True, "NaN"),
    ("nested 100,000 deep", _frame(b"[" * 100_000 + b"]" * 100_000), True, "nests too deep"),
    ("umask a string", _request(umask="abc"), True, "'umask'"),
    ("umask negative", _request(umask=-1), True, "'umask'"),
    ("umask above 0o777", _request(umask=0o1000), True, "'umask'"),
    ("umask true", _request(umask=True), True, "'umask'"),
    ("missing argv", _request(argv=_DROP), True, "'argv'"),
    ("empty argv", _request(argv=[]), True, "'argv'"),
    ("argv not strings", _request(argv=["place3d", 3]), True, "'argv'"),
    ("argv with NUL", _request(argv=["place3d", "a\0b"]), True, "'argv'"),
    ("env a list", _request(env=["PATH=/bin"]), True, "'env'"),
    ("env value not a string", _request(env={**_env(), "PATH": 1}), True, "'env'"),
    ("env value with NUL", _request(env={**_env(), "PATH": "/bin\0x"}), True, "'env'"),
    ("env name with '='", _request(env={**_env(), "A=B": "c"}), True, "'env'"),
    ("env with a lone surrogate", _request(env={**_env(), "X": "\ud800"}), True, "'env'"),
    ("missing cwd", _request(cwd=_DROP), True, "'cwd'"),
    ("cwd relative", _request(cwd="relative/path"), True, "'cwd'"),
    ("cwd not a folder", _request(cwd="/no/such/folder/here"), True, "is not a folder here"),
    ("unknown stream encoding", _request(streams={"stdout": {"encoding": "no-such-codec"}}), True, "encoding"),
    ("non-text stream encoding", _request(streams={"stdout": {"encoding": "rot13"}}), True, "encoding"),
    ("unknown error handler", _request(streams={"stderr": {"errors": "no-such-handler"}}), True, "error handler"),
    ("line_buffering not a bool", _request(streams={"stdout": {"line_buffering": "yes"}}), True, "true or false"),
    ("type not run", _request(type="shutdown"), True, "expected a 'run' request"),
    ("no descriptors", _request(), False, "3 standard descriptors, got 0"),
    ("length field 4 GiB", struct.pack(">I", 0xFFFFFFFF), True, "announces 4294967295 bytes"),
    ("length field just over the cap", struct.pack(">I", getattr(wire, "MAX_REQUEST_BYTES", 8 << 20) + 1), True, "at most"),
]


def _send_case(path: Path, frame: bytes, with_fds: bool) -> dict | None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(15)
    null = os.open(os.devnull, os.O_RDWR)
    try:
        s.connect(str(path))
        assert wire.recv(s)["type"] == "ready"
        try:
            rest = frame
            if with_fds:
                rest = frame[socket.send_fds(s, [frame[:4]], [null, null, null]):]
            if rest:
                s.sendall(rest)
        except (BrokenPipeError, ConnectionResetError):
            pass                 # refused on its header already: the reply is there to read
        reply = wire.recv(s)
        # held open until the server closes: a client that left at once could hide a crash (at 7fb2d94 its
        # leaving interrupted the command, and the interrupt replaced the error)
        assert wire.recv(s) is None
        return reply
    finally:
        os.close(null)
        s.close()


def _served(path: Path) -> None:
    """A real client is still served by the server at ``path``."""
    r = _place3d(f"--server={path}", "--version", timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("place3d-kernels ") and not r.stderr, r


@pytest.mark.parametrize("name,frame,with_fds,says", CASES, ids=[c[0] for c in CASES])
def test_a_malformed_request_gets_an_error_and_the_server_stays_up(server, name, frame, with_fds, says):
    path, proc = server
    reply = _send_case(path, frame, with_fds)
    assert reply is not None and reply["type"] in ("error", "refused") and says in reply["message"], reply
    assert proc.poll() is None, _stop(proc)
    _served(path)


def test_a_descriptor_that_is_a_folder_is_refused(server):
    path, proc = server
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(15)
    folder = os.open("/", os.O_RDONLY)
    try:
        s.connect(str(path))
        wire.recv(s)
        frame = _request()
        socket.send_fds(s, [frame], [folder, 1, 2])
        reply = wire.recv(s)
    finally:
        os.close(folder)
        s.close()
    assert reply["type"] == "refused" and "is a folder" in reply["message"], reply
    assert proc.poll() is None
    _served(path)


def _rss_kib(pid: int) -> int:
    return int(re.search(r"VmRSS:\s+(\d+)", Path(f"/proc/{pid}/status").read_text()).group(1))


def test_an_oversized_length_field_is_refused_before_reading(server):
    """A frame announcing 4 GiB, then 32 MiB of it sent: an error at once, without the server growing."""
    path, proc = server
    before = _rss_kib(proc.pid)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(15)
    s.connect(str(path))
    wire.recv(s)
    s.sendall(struct.pack(">I", 0xFFFFFFFF))
    try:
        for _ in range(32):
            s.sendall(b"x" * (1 << 20))
    except OSError:
        pass                                     # the server closed the connection: what it should do
    reply = wire.recv(s)
    s.close()
    assert reply["type"] == "error" and "at most" in reply["message"], reply
    assert _rss_kib(proc.pid) - before < 16 * 1024
    _served(path)


def test_a_silent_client_does_not_block_others_and_times_out(server):
    path, proc = server
    silent = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    silent.connect(str(path))                    # connects, then sends nothing and reads nothing
    try:
        t = time.monotonic()
        r = _place3d(f"--server={path}", "--version", timeout=60)
        assert r.returncode == 0 and r.stdout.startswith("place3d-kernels ") and not r.stderr, r
        assert time.monotonic() - t < 30
        silent.settimeout(HANDSHAKE_S + 20)
        assert wire.recv(silent)["type"] == "ready"
        reply = wire.recv(silent)               # the server gives up on it after its handshake timeout
        assert reply["type"] == "error" and "no request within" in reply["message"], reply
        assert wire.recv(silent) is None
    finally:
        silent.close()
    assert proc.poll() is None


def test_a_client_that_trickles_its_request_is_cut_off(server):
    """A byte every 0.3 s never lets a per-read timeout fire; the handshake has one deadline in all."""
    path, proc = server
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(HANDSHAKE_S + 20)
    s.connect(str(path))
    try:
        assert wire.recv(s)["type"] == "ready"
        t = time.monotonic()
        frame = _request()
        try:
            for i in range(len(frame)):
                s.sendall(frame[i:i + 1])
                time.sleep(0.3)
                if time.monotonic() - t > HANDSHAKE_S + 10:
                    break
        except OSError:
            pass                                 # closed by the server: what it should do
        reply = wire.recv(s)
        assert reply["type"] == "error" and "no request within" in reply["message"], reply
        assert time.monotonic() - t < HANDSHAKE_S + 5
    finally:
        s.close()
    assert proc.poll() is None


def test_a_client_that_leaves_mid_frame_is_forgotten(server):
    path, proc = server
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(path))
    wire.recv(s)
    s.sendall(_request()[:20])                   # a header and part of a body, then gone
    s.close()
    _served(path)
    assert proc.poll() is None


# ================================================================================= the socket path and the log
def _serve_cmd(path: Path, *extra, timeout=60) -> subprocess.CompletedProcess:
    return _place3d("serve", "--socket", str(path), "--backend", "reference", "--idle-timeout", "1", *extra,
                    timeout=timeout)


@pytest.mark.parametrize("kind", ["regular file", "symbolic link", "folder"])
def test_serve_never_removes_what_is_not_its_stale_socket(kind):
    folder = _folder()
    try:
        victim = folder / "victim.txt"
        victim.write_text("keep me\n")
        path = folder / "s.sock"
        if kind == "regular file":
            path.write_text("keep me too\n")
        elif kind == "symbolic link":
            path.symlink_to(victim)
        else:
            path.mkdir()
        r = _serve_cmd(path)
        assert r.returncode == 2, (r.returncode, r.stderr)
        assert "refusing to listen on" in r.stderr and "Nothing was removed" in r.stderr, r.stderr
        assert victim.read_text() == "keep me\n"
        if kind == "regular file":
            assert path.read_text() == "keep me too\n"
        elif kind == "symbolic link":
            assert path.is_symlink()
        else:
            assert path.is_dir()
    finally:
        _rmtree(folder)


def test_serve_replaces_a_stale_socket_of_its_own():
    folder = _folder()
    try:
        path = folder / "s.sock"
        left = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        left.bind(str(path))
        left.close()
        r = _serve_cmd(path)
        assert r.returncode == 0 and "idle for 1 s" in r.stderr, r.stderr
        assert not path.exists()
    finally:
        _rmtree(folder)


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o770])
def test_serve_refuses_a_folder_others_may_write(mode):
    folder = _folder(mode)
    try:
        r = _serve_cmd(folder / "s.sock")
        assert r.returncode == 2 and "may be written by other users" in r.stderr, (r.returncode, r.stderr)
        assert not (folder / "s.sock").exists()
    finally:
        _rmtree(folder)


def _stop_detached(out: str, path: Path) -> None:
    m = re.search(r"pid (\d+)", out)
    if m and is_listening(path):
        os.kill(int(m.group(1)), signal.SIGTERM)
        deadline = time.monotonic() + 30
        while is_listening(path) and time.monotonic() < deadline:
            time.sleep(0.1)


def test_detach_refuses_a_symlinked_log():
    folder = _folder()
    path = folder / "s.sock"
    r = None
    try:
        victim = folder / "victim.txt"
        victim.write_text("keep me\n")
        (folder / "s.log").symlink_to(victim)
        r = _serve_cmd(path, "--detach")
        assert r.returncode == 2 and "symbolic link" in r.stderr, (r.returncode, r.stdout, r.stderr)
        assert victim.read_text() == "keep me\n"
        assert not is_listening(path)
    finally:
        if r is not None:
            _stop_detached(r.stdout, path)
        _rmtree(folder)


def test_detach_writes_its_log_0600():
    folder = _folder()
    path = folder / "s.sock"
    r = None
    try:
        r = _serve_cmd(path, "--detach")
        assert r.returncode == 0 and "server started" in r.stdout, (r.stdout, r.stderr)
        log = folder / "s.log"
        assert stat.S_IMODE(log.lstat().st_mode) == 0o600
        deadline = time.monotonic() + 30
        while "listening on" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "listening on" in log.read_text()
    finally:
        if r is not None:
            _stop_detached(r.stdout, path)
        _rmtree(folder)


def test_open_log_refuses_a_fifo_and_a_hard_link(tmp_path):
    fifo = tmp_path / "fifo.log"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a plain file"):
        serve.open_log(fifo)
    (tmp_path / "a").write_text("x")
    os.link(tmp_path / "a", tmp_path / "b.log")
    with pytest.raises(ValueError, match="hard links"):
        serve.open_log(tmp_path / "b.log")
