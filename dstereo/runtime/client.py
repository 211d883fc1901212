"""The client of `dstereo serve`: the `dstereo` script (`dstereo.cli.main`) hands its command to a running server
if there is one (`run_served`), else runs it itself.

A new process pays ~0.5-1 s to import JAX and the commands before any work; a resident server (dstereo/runtime/
server.py) has paid it once. This module decides with the standard library alone (no numpy, JAX or typer before
the socket has been tried): it sends argv, cwd, the environment and the terminal's traits, streams back the
command's stdout and stderr, and exits with its code. Whenever the server cannot run the command exactly as this
process would, the command runs here as before: no server (silent), DSTEREO_SERVE=0 (silent), server busy with
another command (silent), a stale socket or a server started by hand from other dstereo code or start-up settings
(one `dstereo: note:` line on stderr, so a user knows why the fast path is not taken).

Auto-start (as Gradle's daemon or dmypy do): a command that runs here because no server runs for this
installation starts one, detached (dstereo/runtime/autostart.py): it waits until the command that started it has
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

from dstereo.runtime.paths import install_id, private, runtime_dir, sibling, socket_path  # noqa: F401

NOT_SERVED = ("serve", "demo")  # the server itself; demo writes a large folder and is run once, not often
CONNECT_TIMEOUT_S = 2.0
ANSWER_TIMEOUT_S = 10.0  # the server's listener answers at once; silence this long means it is wedged
# After a signal, how long the client waits for the served command to stop and report: within the 2 s a command
# has to end (the server's own watchdog gives up on a stuck command sooner, serve_server.STUCK_S).
INTERRUPT_GRACE_S = 1.1
# Environment read once at start-up (JAX, XLA, BLAS, matplotlib, Python, the JAX cache folder): a server
# started with other values would compute differently, so they are part of the key, not sent per request.
STARTUP_ENV_PREFIXES = ("JAX_", "XLA_", "TF_", "CUDA_", "OMP_", "OPENBLAS_", "MKL_", "MPL", "PYTHON", "LD_")
# DSTEREO_AOT is read per call, but a server keeps the programs the first command built with it.
STARTUP_ENV_NAMES = ("DSTEREO_JAX_CACHE", "DSTEREO_FIGURE_WORKERS", "DSTEREO_AOT", "XDG_CACHE_HOME")
_HEADER = struct.Struct("!cI")


def code_key(env=None, package: str | None = None, versions: dict | None = None) -> str:
    """What a server must share with this process to give the same results (`key_parts`), hashed."""
    return code_key_of(key_parts(env, package, versions))


def code_key_of(parts: dict) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def key_parts(env=None, package: str | None = None, versions: dict | None = None) -> dict[str, str]:
    """The code key's parts, by name (so `dstereo serve --status` and a mismatch note can say which differs):
    dstereo's version and source files' content, the interpreter and environment (venv), the start-up
    environment variables (`env:NAME`) and the installed version of every locked dependency (`dist:NAME`,
    `dependency_versions`; `versions` stands in for it in tests)."""
    from dstereo import __version__

    # the default `dstereo.cli` sets in a command's process (and so in a server's) counts as set on both sides
    env = {"OPENBLAS_NUM_THREADS": "1", **(os.environ if env is None else env)}
    package = package or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the dstereo package
    h = hashlib.sha256()
    for folder, dirs, files in os.walk(package):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, package).encode() + b"\0")
            with open(path, "rb") as fh:
                h.update(hashlib.sha256(fh.read()).digest())
    parts = {"dstereo": __version__, "source": h.hexdigest()[:16], "package": package, "prefix": sys.prefix,
             "python": f"{os.path.realpath(sys.executable)} {sys.version}"}
    for name in sorted(env):
        if name.startswith(STARTUP_ENV_PREFIXES) or name in STARTUP_ENV_NAMES:
            parts[f"env:{name}"] = env[name]
    versions = dependency_versions(package) if versions is None else versions
    parts.update({f"dist:{name}": version for name, version in versions.items()})
    return parts


def differences(ours: dict, theirs: dict, limit: int = 3) -> str:
    """`numpy 2.1.0 here, 2.0.2 in the server; XLA_FLAGS ...`: the key parts that differ, named for a person."""
    said = []
    for name in sorted(set(ours) | set(theirs)):
        if ours.get(name) != theirs.get(name):
            label = name.split(":", 1)[-1]
            here, there = ours.get(name, "unset"), theirs.get(name, "unset")
            if name in ("source", "package", "prefix", "python"):
                said.append({"source": "dstereo's source files", "package": "the package folder",
                             "prefix": "the Python environment", "python": "the interpreter"}[name])
            else:
                said.append(f"{label} {here} here, {there} in the server")
    more = f" and {len(said) - limit} more" if len(said) > limit else ""
    return "; ".join(said[:limit]) + more


def dependency_versions(package: str) -> dict[str, str]:
    """The installed version of every dependency in requirements.lock beside the package (an editable checkout),
    else of every installed distribution: a server started before an upgrade of OpenCV, JAX or SciPy in the same
    environment would go on serving the old libraries. Read from the `NAME-VERSION.dist-info` folder names on
    sys.path (~1 ms; importlib.metadata's lookups took ~100 ms for the 58 locked names, measured, and the client
    runs this for every command); a locked name found there under no such folder is asked of importlib.metadata."""
    installed: dict[str, str] = {}
    for entry in sys.path:
        try:
            names = os.listdir(entry or ".")
        except OSError:
            continue
        for name in names:
            if name.endswith(".dist-info") and "-" in name:
                dist, version = name[: -len(".dist-info")].rsplit("-", 1)
                installed.setdefault(_canonical(dist), version)
    lock = os.path.join(os.path.dirname(package), "requirements.lock")
    try:
        with open(lock, encoding="utf-8") as fh:
            locked = [line.split("==", 1)[0].strip() for line in fh if line[:1].isalnum() and "==" in line]
    except OSError:
        return installed
    versions = {}
    for name in locked:
        key = _canonical(name)
        if key not in installed:
            try:
                from importlib import metadata

                installed[key] = metadata.version(name)
            except Exception:  # noqa: BLE001 - not installed: that is a difference too
                installed[key] = "absent"
        versions[key] = installed[key]
    return versions


def _canonical(name: str) -> str:
    import re

    return re.sub(r"[-_.]+", "_", name).lower()


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
    """A command a server may run: not `serve` or `demo` (NOT_SERVED), not a bare option, not a help request
    (`dstereo reconstruct --help` must start nothing: it runs here in a moment)."""
    asks_help = any(a in ("--help", "-h") for a in argv[: argv.index("--") if "--" in argv else len(argv)])
    return bool(argv) and argv[0] not in NOT_SERVED and not argv[0].startswith("-") and not asks_help


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
            _note(f"the background server ran other dstereo code, settings or libraries ({_differ(answer[1])}); "
                  "running here, and a new server starts for the next command")
            return None, "retired"
        if answer[0] == b"m":
            _note(f"the server at {path} runs other dstereo code, start-up settings or libraries "
                  f"({_differ(answer[1])}); running here (restart it: dstereo serve --stop, then dstereo serve)")
            return None, "mismatch"
        if answer[0] != b"a":
            return None, "unanswered"
        return _stream(sock, path), "served"


def _differ(payload: bytes) -> str:
    """What differs between this process's key and the server's (its parts, sent with its answer)."""
    try:
        theirs = json.loads(payload)
    except ValueError:
        theirs = None
    if not isinstance(theirs, dict):  # an older server sends no parts
        return "an older server"
    return differences(key_parts(), theirs) or "the key"


def _stream(sock: socket.socket, path: str) -> int:
    """Copy the command's output here until its exit code comes. A signal here (Ctrl-C, SIGTERM, SIGHUP) is sent
    on to the server, which stops the command (its line `dstereo: error: interrupted (...)` and exit code come
    back as output); without an answer in INTERRUPT_GRACE_S this process says the line and exits itself."""
    from dstereo.runtime import interrupts

    out, err = sys.stdout.buffer, sys.stderr.buffer
    sock.settimeout(None)
    stopped: interrupts.Interrupted | None = None
    while True:
        try:
            frame = receive(sock)
        except interrupts.Interrupted as exc:
            stopped = exc
            _forward(sock, exc.signum)
            continue
        except OSError:  # the grace spent (a timeout), or the server gone
            frame = None
        if frame is None:
            if stopped is not None:
                interrupts.say(stopped)
                return stopped.code
            return _server_died(path)
        kind, payload = frame
        if kind in (b"o", b"e"):
            if stopped is not None and kind == b"e" and payload.startswith(b"dstereo: error: interrupted"):
                interrupts.mark_said()  # the server said it: this process must not say it again
            stream = out if kind == b"o" else err
            stream.write(payload)
            stream.flush()
        elif kind == b"x":
            return int(json.loads(payload))


def _forward(sock: socket.socket, signum: int) -> None:
    try:
        send(sock, b"i", str(signum).encode())
        sock.settimeout(INTERRUPT_GRACE_S)
    except OSError:
        pass


def _server_died(path: str) -> int:
    """The server ended mid-command (a crash in native code, say SIGFPE in OpenCV, or a kill): one line, and its
    socket removed if nobody answers there any more, so the next command runs in its own process and starts a new
    server rather than meet the dead one's socket."""
    try:
        connect(path, timeout=0.5).close()
    except OSError:
        try:
            os.unlink(path)
        except OSError:
            pass
    log = sibling(path, ".log")
    sys.stderr.write("dstereo: error: the background server ended during this command (it crashed or was "
                     f"killed; its log: {log}); nothing was written; the next command starts a new server "
                     "(DSTEREO_SERVE=0 runs commands in their own process)\n")
    sys.stderr.flush()
    return 1


def run_served(argv: list[str]) -> int | None:
    """The `dstereo` script's first step (`dstereo.cli.main`): the command's exit code once a server has run it,
    or None to run it here; starts a server for the next commands where none runs (module docstring)."""
    from dstereo.runtime import autostart

    auto = autostart.wanted(servable(argv))
    code, why = _try_served(argv, auto)
    if code is not None:
        return code
    if auto and why in ("absent", "stale", "retired") and \
            autostart.start(socket_path(), replacing=why == "retired"):
        autostart.tell_once(socket_path())
    return None
