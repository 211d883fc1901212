"""The `dstereo` entry point: hand the command to a running `dstereo serve` if there is one, else run it here.

A new process pays ~0.5-1 s to import JAX and the commands before any work; a resident server (dstereo/commands/
serve.py) has paid it once. This module decides with the standard library alone (no numpy, JAX or typer before
the socket has been tried): it sends argv, cwd, the environment and the terminal's traits, streams back the
command's stdout and stderr, and exits with its code. Whenever the server cannot run the command exactly as this
process would, the command runs here as before: no server (silent), DSTEREO_SERVE=0 (silent), server busy with
another command (silent), a stale socket or a server started by hand from other dstereo code or start-up settings
(one `dstereo: note:` line on stderr, so a user knows why the fast path is not taken).

Auto-start (as Gradle's daemon or dmypy do): a command that runs here because no server runs for this
installation starts one, detached (dstereo/serve_autostart.py): it waits until the command that started it has
ended (so the two never share the cores), loads, serves the commands that follow, and exits after
DSTEREO_SERVE_IDLE seconds (default 900) without one. An auto-started server that meets a client of other code or
start-up settings (an edit, an upgrade) answers `retired` and stops: the client runs the command here silently and
starts a server of its own code. Never under pytest, in CI (`CI` set) or in library use (only this entry point
starts one); DSTEREO_SERVE=0 neither uses nor starts a server, DSTEREO_SERVE=manual uses one started by hand only.

Wire format: frames of one kind byte, a 4-byte big-endian length and the payload. Client -> server: `q` the
request (JSON), `i` interrupt (Ctrl-C). Server -> client: `a` accepted, `b` busy (run it yourself), `m` key
mismatch, `r` key mismatch and the (auto-started) server stops, `o`/`e` stdout/stderr bytes, `x` the exit code
(JSON), `s` a status or stop reply (JSON).

One server per user and installation: the socket's name carries a hash of the package's folder and the Python
environment (`install_id`), so two checkouts or virtual environments of one user each get their own.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import struct
import sys

from dstereo.serve_paths import install_id, private, runtime_dir, sibling, socket_path  # noqa: F401

NOT_SERVED = ("serve", "demo")  # the server itself; demo writes a large folder and is run once, not often
CONNECT_TIMEOUT_S = 2.0
ANSWER_TIMEOUT_S = 10.0  # the server's listener answers at once; silence this long means it is wedged
INTERRUPT_GRACE_S = 5.0  # after Ctrl-C, how long the client waits for the command to stop and report
# Environment read once at start-up (JAX, XLA, BLAS, matplotlib, Python, the JAX cache folder): a server
# started with other values would compute differently, so they are part of the key, not sent per request.
STARTUP_ENV_PREFIXES = ("JAX_", "XLA_", "TF_", "CUDA_", "OMP_", "OPENBLAS_", "MKL_", "MPL", "PYTHON", "LD_")
# DSTEREO_AOT is read per call, but a server keeps the programs the first command built with it.
STARTUP_ENV_NAMES = ("DSTEREO_JAX_CACHE", "DSTEREO_FIGURE_WORKERS", "DSTEREO_AOT", "XDG_CACHE_HOME")
_HEADER = struct.Struct("!cI")


def code_key(env=None, package: str | None = None) -> str:
    """What a server must share with this process to give the same results: dstereo's version and every source
    file's content, the interpreter and environment (venv), and the start-up environment variables."""
    from dstereo import __version__

    # the default `dstereo.cli` sets in a command's process (and so in a server's) counts as set on both sides
    env = {"OPENBLAS_NUM_THREADS": "1", **(os.environ if env is None else env)}
    package = package or os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for part in (__version__, package, sys.prefix, os.path.realpath(sys.executable), sys.version):
        h.update(part.encode() + b"\0")
    for folder, dirs, files in os.walk(package):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, package).encode() + b"\0")
            with open(path, "rb") as fh:
                h.update(hashlib.sha256(fh.read()).digest())
    for name in sorted(env):
        if name.startswith(STARTUP_ENV_PREFIXES) or name in STARTUP_ENV_NAMES:
            h.update(f"{name}={env[name]}".encode() + b"\0")
    return h.hexdigest()


def send(sock: socket.socket, kind: bytes, payload: bytes = b"") -> None:
    sock.sendall(_HEADER.pack(kind, len(payload)) + payload)


def receive(sock: socket.socket) -> tuple[bytes, bytes] | None:
    """One frame (kind, payload), or None at end of stream."""
    header = _exactly(sock, _HEADER.size)
    if header is None:
        return None
    kind, size = _HEADER.unpack(header)
    payload = _exactly(sock, size)
    if payload is None:
        return None
    return kind, payload


def _exactly(sock: socket.socket, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = sock.recv(min(left, 1 << 16))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def connect(path: str, timeout: float = CONNECT_TIMEOUT_S) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout)
    try:
        sock.connect(path)
    except BaseException:
        sock.close()
        raise
    return sock


def _note(text: str) -> None:
    sys.stderr.write(f"dstereo: note: {text}\n")
    sys.stderr.flush()


def _terminal(stream) -> dict:
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return {"tty": tty, "encoding": getattr(stream, "encoding", None) or "utf-8",
            "errors": getattr(stream, "errors", None) or "strict"}


def request(argv: list[str]) -> dict:
    env = dict(os.environ)
    if "COLUMNS" not in env or "LINES" not in env:  # the server's own terminal is not the client's
        for stream in (sys.stdout, sys.stderr):
            try:
                if stream.isatty():
                    size = os.get_terminal_size(stream.fileno())
                    env.setdefault("COLUMNS", str(size.columns))
                    env.setdefault("LINES", str(size.lines))
                    break
            except (AttributeError, ValueError, OSError):
                continue
    return {"op": "run", "key": code_key(), "argv0": sys.argv[0] if sys.argv else "dstereo", "argv": argv,
            "cwd": os.getcwd(), "env": env, "stdout": _terminal(sys.stdout), "stderr": _terminal(sys.stderr)}


def servable(argv: list[str]) -> bool:
    """A command a server may run: not `serve` or `demo` (NOT_SERVED), not a bare option (--help)."""
    return bool(argv) and argv[0] not in NOT_SERVED and not argv[0].startswith("-")


def try_served(argv: list[str]) -> int | None:
    """The command's exit code once a server has run it; None when it must run in this process."""
    return _try_served(argv, auto_start=False)[0]


def _try_served(argv: list[str], auto_start: bool) -> tuple[int | None, str]:
    """(exit code or None, why not served: "served", "off", "absent", "stale", "busy", "mismatch", "retired",
    "unanswered", "foreign"). With `auto_start` (this process will start a server when there is none), a stale
    socket is replaced without a note."""
    if os.environ.get("DSTEREO_SERVE") == "0" or not servable(argv):
        return None, "off"
    path = socket_path()
    if not os.path.exists(path):
        return None, "absent"
    if not private(os.path.dirname(path)):
        _note(f"{os.path.dirname(path)} is not a private folder of this user; not using the server there")
        return None, "foreign"
    try:
        sock = connect(path)
    except OSError:
        if not auto_start:
            _note(f"no server answers at {path} (a stale socket: `dstereo serve` replaces it); running here")
        return None, "stale"
    with sock:
        try:
            message = request(argv)
        except OSError:  # the cwd was deleted, say: let the in-process run report it as it would
            return None, "unanswered"
        try:
            send(sock, b"q", json.dumps(message).encode())
            sock.settimeout(ANSWER_TIMEOUT_S)
            answer = receive(sock)
        except OSError:
            answer = None
        if answer is None:
            _note(f"the server at {path} did not answer; running here")
            return None, "unanswered"
        if answer[0] == b"b":
            return None, "busy"
        if answer[0] == b"r":  # an auto-started server of other code: it stops; a new one takes its place
            return None, "retired"
        if answer[0] == b"m":
            _note(f"the server at {path} runs other dstereo code or start-up settings; running here (restart it: "
                  "dstereo serve --stop, then dstereo serve)")
            return None, "mismatch"
        if answer[0] != b"a":
            return None, "unanswered"
        return _stream(sock, path), "served"


def _stream(sock: socket.socket, path: str) -> int:
    """Copy the command's output here until its exit code comes; Ctrl-C asks the server to interrupt it."""
    out, err = sys.stdout.buffer, sys.stderr.buffer
    sock.settimeout(None)
    while True:
        try:
            frame = receive(sock)
        except KeyboardInterrupt:
            return _interrupt(sock)
        except OSError:
            frame = None
        if frame is None:
            sys.stderr.write(f"dstereo: error: the server at {path} stopped before the command finished; run it "
                             "again (DSTEREO_SERVE=0 runs it in this process)\n")
            return 1
        kind, payload = frame
        if kind in (b"o", b"e"):
            stream = out if kind == b"o" else err
            stream.write(payload)
            stream.flush()
        elif kind == b"x":
            return int(json.loads(payload))


def _interrupt(sock: socket.socket) -> int:
    """Ctrl-C: the server interrupts the command (between two Python steps of it, so a long compiled call ends
    first); wait a little for it to finish, unread (a frame may have been cut), and exit as Python does, 130."""
    try:
        send(sock, b"i")
        sock.settimeout(INTERRUPT_GRACE_S)
        while sock.recv(1 << 16):
            pass
    except (OSError, KeyboardInterrupt):  # a second Ctrl-C, the grace spent, or the server gone: leave now
        pass
    return 130


def main() -> None:
    from dstereo import serve_autostart

    argv = sys.argv[1:]
    auto = serve_autostart.wanted(servable(argv))
    code, why = _try_served(argv, auto)
    if code is not None:
        sys.exit(code)
    if auto and why in ("absent", "stale", "retired"):
        serve_autostart.start(socket_path(), replacing=why == "retired")
    from dstereo.cli import main as run_here

    run_here()


if __name__ == "__main__":
    main()
