"""The resident server behind `dstereo serve`: JAX, the commands and the figure workers loaded once, the
commands of `dstereo` clients (dstereo/serve_client.py) run one at a time on a Unix socket.

Threads: the main thread runs the commands (so a client's Ctrl-C can interrupt one as a signal would, and JAX
runs where a CLI runs it); a listener thread answers every connection at once: status, stop, `busy` while a
command runs (the client then runs it itself), `mismatch` when the client's code key differs (`retired` from an
auto-started server, which then stops); a watcher thread per command reads the client's interrupt or its
disconnection.

One server per user and installation: it holds serve-<id>.lock (flock) beside the socket for its life, so two
started at the same moment (two commands that both found none) cannot both load and bind. An auto-started server
(serve_autostart.py, `started_by` the client's pid) waits for that client to end before it loads, so the command
that started it keeps both cores; it stops after `idle_timeout` seconds without a command.
"""

from __future__ import annotations

import _thread
import json
import os
import queue
import socket
import sys
import threading
import time

from dstereo import serve_client as wire
from dstereo.commands.serve_request import INTERRUPT_SIGNAL, client_stream, install_interrupt, run_request
from dstereo.errors import DstereoError

GREETING_TIMEOUT_S = 5.0  # a connection that sends no request in this time is dropped
CLIENT_WAIT_S = 30.0  # an auto-started server loads once its client has ended, or after this long at most
LOCK_WAIT_S = 60.0  # an auto-started server waits this long for a retiring server's lock, then gives up
# What a calibration imports (test_startup lists the same modules): loaded at start-up, not at the first command;
# the second line: what a first served calibration still imported (typer's value coercion imports pydantic;
# OpenCV; scipy.linalg for LAPACK's kernels; the modules the pipeline and results folder import where used).
PRELOAD = ("jax", "jax.numpy", "dstereo.cli", "dstereo.calib.pipeline", "dstereo.calib.stereo_pipeline",
           "dstereo.calib.misfit", "dstereo.calib.mono", "dstereo.io.results",
           "pydantic", "cv2", "scipy.linalg", "jax.experimental.serialize_executable", "dstereo.calib.outliers",
           "dstereo.calib.model_choice", "dstereo.calib.view_checks", "dstereo.io.plots", "dstereo.io.sigma_maps",
           "dstereo.io.cameramodel", "dstereo.uncertainty.projection")


def prepare_folder(path: str) -> None:
    """The socket's folder, mode 0700 and ours; an old socket nobody answers on is removed, a live one refused."""
    folder = os.path.dirname(path)
    os.makedirs(folder, mode=0o700, exist_ok=True)
    if not wire.private(folder):
        if os.stat(folder).st_uid == os.getuid():
            os.chmod(folder, 0o700)
        else:
            raise DstereoError(f"{folder}: not this user's folder; set DSTEREO_SERVE_DIR to a private folder")
    if len(path.encode()) > 100:  # sun_path holds 108 bytes
        raise DstereoError(f"{path}: too long for a Unix socket; set DSTEREO_SERVE_DIR to a shorter folder")
    if os.path.exists(path):
        try:
            wire.connect(path).close()
        except OSError:
            os.unlink(path)  # stale: its server is gone
        else:
            raise DstereoError(f"a server already runs at {path}; stop it with dstereo serve --stop")


def take_lock(path: str, wait_s: float = 0.0) -> int | None:
    """The installation's lock (serve-<id>.lock beside the socket), held until the process ends: its file
    descriptor, or None when another server holds it (after trying for `wait_s` seconds)."""
    import fcntl

    fd = os.open(wire.sibling(path, ".lock"), os.O_RDWR | os.O_CREAT, 0o600)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except OSError:
            if time.monotonic() >= deadline:
                os.close(fd)
                return None
            time.sleep(0.2)


def wait_for_exit(pid: int, limit_s: float = CLIENT_WAIT_S) -> None:
    """Until the process `pid`, this one's parent, has ended (this process is then someone else's child)."""
    deadline = time.monotonic() + limit_s
    while os.getppid() == pid and time.monotonic() < deadline:
        time.sleep(0.05)


class Server:
    def __init__(self, path: str, idle_timeout: float = 0.0, started_by: int = 0):
        """`idle_timeout` > 0: stop after that many seconds without a command. `started_by` > 0: auto-started by
        that client process (serve_autostart.py): wait for its end before loading, and stop rather than answer
        `mismatch` when a client of other code or start-up settings comes."""
        self.path, self.key = path, wire.code_key()
        self.idle_timeout, self.started_by, self.auto = float(idle_timeout), int(started_by), started_by > 0
        self.requests: queue.Queue = queue.Queue()
        self.lock = threading.Lock()
        self.busy = self.stopping = False
        self.served, self.since = 0, time.time()
        self.last = time.monotonic()  # when the last command ended (or the server started)
        self.listener: socket.socket | None = None

    def run(self) -> None:
        os.makedirs(os.path.dirname(self.path), mode=0o700, exist_ok=True)
        if self.auto:
            if not wire.private(os.path.dirname(self.path)) or take_lock(self.path, LOCK_WAIT_S) is None:
                return  # another server runs or starts for this installation: nothing to do
            _truncate_log()
            wait_for_exit(self.started_by)
        elif take_lock(self.path) is None:
            raise DstereoError(f"a server already runs (or is starting) at {self.path}; stop it with "
                               "dstereo serve --stop")
        prepare_folder(self.path)
        _preload()
        self.last = time.monotonic()
        install_interrupt()
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(self.path)
        inode = os.stat(self.path).st_ino
        self.listener.listen(16)
        threading.Thread(target=self._listen, name="dstereo-serve-listener", daemon=True).start()
        print(f"dstereo serve: ready at {self.path} (pid {os.getpid()}); dstereo commands run here until "
              "dstereo serve --stop or Ctrl-C", file=sys.stderr, flush=True)
        try:
            self._loop()
        finally:
            self.stopping = True
            self.listener.close()
            try:
                if os.stat(self.path).st_ino == inode:  # still ours, not a newer server's
                    os.unlink(self.path)
            except OSError:
                pass
            from dstereo.io import figure_pool

            figure_pool.stop()

    def _loop(self) -> None:
        while True:
            try:
                item = self.requests.get(timeout=0.5)
                if item is None:
                    return
                self._serve(*item)
            except queue.Empty:
                if self.stopping or self._idle_expired():
                    return
            except KeyboardInterrupt:  # Ctrl-C in the server's own terminal (a client's is ClientInterrupt, caught)
                return
            except Exception:  # noqa: BLE001 - a request the server could not even start (a malformed one): its
                # client sees the connection end (one error line, exit 1); the server goes on
                import traceback

                traceback.print_exc()

    def _serve(self, conn: socket.socket, request: dict) -> None:
        done = threading.Event()
        try:
            threading.Thread(target=self._watch, args=(conn, done), daemon=True).start()
            lock = threading.Lock()
            out = client_stream(conn, b"o", request["stdout"], lock, line_buffering=bool(request["stdout"].get("tty")))
            err = client_stream(conn, b"e", request["stderr"], lock, line_buffering=True)
            code = run_request(request, out, err)
            done.set()
            try:
                send_code = json.dumps(code).encode()
                with lock:
                    wire.send(conn, b"x", send_code)
            except OSError:
                pass
        finally:
            done.set()
            try:
                conn.shutdown(socket.SHUT_RDWR)  # wakes the watcher's read (a close alone does not)
            except OSError:
                pass
            conn.close()
            _renew_broken_figure_pool()
            with self.lock:
                self.busy = False
                self.served += 1
                self.last = time.monotonic()

    def _idle_expired(self) -> bool:
        """The idle timeout has passed without a command: from now on every client runs its own (`busy`)."""
        with self.lock:
            if self.idle_timeout > 0 and not self.busy and time.monotonic() - self.last > self.idle_timeout:
                self.stopping = True
            return self.stopping

    def _watch(self, conn: socket.socket, done: threading.Event) -> None:
        """The client's Ctrl-C (an `i` frame) or its disconnection interrupts the running command."""
        try:
            frame = wire.receive(conn)
        except OSError:
            frame = None
        if not done.is_set() and (frame is None or frame[0] == b"i"):
            _thread.interrupt_main(INTERRUPT_SIGNAL)  # ignored unless the command is still running

    def _listen(self) -> None:
        while not self.stopping:
            try:
                conn, _ = self.listener.accept()
            except OSError:  # closed at stop, or out of file descriptors for a moment
                time.sleep(0.05)
                continue
            threading.Thread(target=self._greet, args=(conn,), daemon=True).start()

    def _greet(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(GREETING_TIMEOUT_S)
            frame = wire.receive(conn)
            if frame is None or frame[0] != b"q":
                conn.close()
                return
            request = json.loads(frame[1])
            if request.get("op") in ("status", "stop"):
                self._answer(conn, request)
                return
            if request.get("key") != self.key:
                if self.auto:  # made for other code or settings: make way for a server of the client's own
                    with self.lock:
                        self.stopping = True
                    self.requests.put(None)
                wire.send(conn, b"r" if self.auto else b"m")
                conn.close()
                return
            with self.lock:
                taken = self.busy or self.stopping or not request.get("argv") or \
                    request["argv"][0] in wire.NOT_SERVED
                self.busy = self.busy or not taken
            if taken:
                wire.send(conn, b"b")
                conn.close()
                return
            conn.settimeout(None)
            try:
                wire.send(conn, b"a")
            except OSError:
                with self.lock:
                    self.busy = False
                conn.close()
                return
            self.requests.put((conn, request))
        except (OSError, ValueError, KeyError):  # a broken or foreign connection: drop it, keep serving
            conn.close()

    def _answer(self, conn: socket.socket, request: dict) -> None:
        with self.lock:
            state = {"pid": os.getpid(), "since": self.since, "served": self.served, "busy": self.busy,
                     "key": self.key, "path": self.path}
            if request["op"] == "stop":
                self.stopping = True
        if request["op"] == "stop":
            self.requests.put(None)
        wire.send(conn, b"s", json.dumps(state).encode())
        conn.close()


def _truncate_log() -> None:
    """An auto-started server's stderr is serve-<id>.log (appended to by whoever starts one): begin it afresh."""
    try:
        os.ftruncate(sys.stderr.fileno(), 0)
    except (OSError, ValueError, AttributeError):
        pass


def _preload() -> None:
    import importlib

    from dstereo.io import figure_pool

    figure_pool.start()  # the workers import matplotlib meanwhile
    for name in PRELOAD:
        importlib.import_module(name)
    _warm_up()


def _warm_up() -> None:
    """What every calibration runs first whatever its shapes: LAPACK's kernels readied for loaded executables
    (imports scipy.linalg: ~0.1-0.2 s of a first served command, measured)."""
    from dstereo.jax_workarounds import prepare_loaded_executables

    prepare_loaded_executables()


def _renew_broken_figure_pool() -> None:
    """A worker killed during a command leaves the pool broken (its figures were drawn here instead); start new
    workers for the next command rather than draw in the server from then on."""
    from dstereo.io import figure_pool

    figure_pool.renew_broken()
