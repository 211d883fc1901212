"""The resident server behind `dstereo serve`: JAX, the commands and the figure workers loaded once, the
commands of `dstereo` clients (dstereo/runtime/client.py) run one at a time on a Unix socket.

Threads: the main thread runs the commands (so a client's Ctrl-C can interrupt one as a signal would, and JAX
runs where a CLI runs it); a listener thread answers every connection at once: status, stop, `busy` while a
command runs (the client then runs it itself), `mismatch` when the client's code key differs (`retired` from an
auto-started server, which then stops); a watcher thread per command reads the client's interrupt or its
disconnection.

One server per user and installation: it holds serve-<id>.lock (flock) beside the socket for its life, so two
started at the same moment (two commands that both found none) cannot both load and bind. An auto-started server
(runtime/autostart.py, `started_by` the client's pid) waits for that client to end before it loads, so the command
that started it keeps both cores; it stops after `idle_timeout` seconds without a command.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import sys
import threading
import time

from dstereo.runtime import client as wire
from dstereo.runtime import interrupts, watchdog
from dstereo.runtime.request import client_stream, install_interrupt, interrupt_command, preload_modules, run_request
from dstereo.errors import DstereoError

GREETING_TIMEOUT_S = 5.0  # a connection that sends no request in this time is dropped
CLIENT_WAIT_S = 30.0  # an auto-started server loads once its client has ended, or after this long at most
# A command told to stop that has not returned after this long is stuck in native code (a JAX call that never
# completes): the server gives up on it, tells the client, and ends itself (the next command starts a new one),
# inside the client's INTERRUPT_GRACE_S and the 2 s a command has to end.
STUCK_S = 0.9
HISTORY = 20  # `serve --status` lists this many of the latest commands
LOCK_WAIT_S = 60.0  # an auto-started server waits this long for a retiring server's lock, then gives up
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
        that client process (runtime/autostart.py): wait for its end before loading, and stop rather than answer
        `mismatch` when a client of other code or start-up settings comes."""
        self.path = path
        self.parts = wire.key_parts()
        self.key = wire.code_key_of(self.parts)
        self.idle_timeout, self.started_by, self.auto = float(idle_timeout), int(started_by), started_by > 0
        self.requests: queue.Queue = queue.Queue()
        self.lock = threading.Lock()
        self.busy = self.stopping = False
        self.served, self.since = 0, time.time()
        self.last = time.monotonic()  # when the last command ended (or the server started)
        self.listener: socket.socket | None = None
        self.history: list[dict] = []  # the latest commands: argv[0], exit code, seconds, when
        self.workers = 0  # figure workers started at load; renewed after a command that killed them

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
        from dstereo.runtime import figure_pool

        self.workers = figure_pool.started()
        self.last = time.monotonic()
        install_interrupt()
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(self.path)
        inode = os.stat(self.path).st_ino
        interrupts.on_abandon(lambda: _unlink_if(self.path, inode))  # a watchdog's end leaves no stale socket
        self.listener.listen(16)
        threading.Thread(target=self._listen, name="dstereo-serve-listener", daemon=True).start()
        print(f"dstereo serve: ready at {self.path} (pid {os.getpid()}); dstereo commands run here until "
              "dstereo serve --stop or Ctrl-C", file=sys.stderr, flush=True)
        try:
            self._loop()
        finally:
            self.stopping = True
            self.listener.close()
            _unlink_if(self.path, inode)
            from dstereo.runtime import figure_pool

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
            except (KeyboardInterrupt, interrupts.Interrupted):  # the server's own SIGINT/SIGTERM/SIGHUP (a
                # client's is ClientInterrupt, caught in run_request)
                return
            except Exception:  # noqa: BLE001 - a request the server could not even start (a malformed one): its
                # client sees the connection end (one error line, exit 1); the server goes on
                import traceback

                traceback.print_exc()

    def _serve(self, conn: socket.socket, request: dict) -> None:
        done, code, t0 = threading.Event(), None, time.monotonic()
        before = interrupts.children()  # the server's own (its resource tracker); the command's are the others
        try:
            lock = threading.Lock()
            threading.Thread(target=self._watch, args=(conn, done, lock), daemon=True).start()
            out = client_stream(conn, b"o", request["stdout"], lock, line_buffering=bool(request["stdout"].get("tty")))
            err = client_stream(conn, b"e", request["stderr"], lock, line_buffering=True)
            watchdog.reporter = lambda line: _tell_client(conn, lock, line, 1)  # a stalled call ends the server
            try:
                code = run_request(request, out, err)
            finally:
                watchdog.reporter = None
            done.set()
            if code is not None and code > 128:  # stopped by the client's signal: end what the command started
                _end_command_children(before)
            self._count(request, code, t0)  # before the client hears the end: a status asked right after shows it
            try:
                send_code = json.dumps(code).encode()
                with lock:
                    wire.send(conn, b"x", send_code)
            except OSError:
                pass
        finally:
            done.set()
            self._count(request, code, t0)  # a request that raised: counted here (once: `_count` checks)
            try:
                conn.shutdown(socket.SHUT_RDWR)  # wakes the watcher's read (a close alone does not)
            except OSError:
                pass
            conn.close()
            _renew_figure_pool(self.workers)
            with self.lock:
                self.busy = False
                self.last = time.monotonic()

    def _count(self, request: dict, code, t0: float) -> None:
        """The command in `served` and `history`, once per request (the exit code's send and the end both call it:
        counted before the client hears the code, which once came after it and a status asked right then missed
        the command, seen under two test workers)."""
        with self.lock:
            if request.get("_counted"):
                return
            request["_counted"] = True
            self.served += 1
            self.history = [*self.history, {"command": (request.get("argv") or ["?"])[0], "code": code,
                                            "seconds": round(time.monotonic() - t0, 2), "at": time.time()}][-HISTORY:]

    def _idle_expired(self) -> bool:
        """The idle timeout has passed without a command: from now on every client runs its own (`busy`)."""
        with self.lock:
            if self.idle_timeout > 0 and not self.busy and time.monotonic() - self.last > self.idle_timeout:
                self.stopping = True
            return self.stopping

    def _watch(self, conn: socket.socket, done: threading.Event, lock: threading.Lock) -> None:
        """The client's signal (an `i` frame with its number) or its disconnection (SIGHUP, as a closed terminal
        would send) interrupts the running command; one that does not stop in STUCK_S ends the server."""
        try:
            frame = wire.receive(conn)
        except OSError:
            frame = None
        if done.is_set() or (frame is not None and frame[0] != b"i"):
            return
        try:
            signum = int(frame[1]) if frame is not None and frame[1] else int(signal.SIGHUP)
        except ValueError:
            signum = int(signal.SIGINT)
        interrupt_command(threading.main_thread().ident, signum)  # ignored unless the command is still running
        if not done.wait(STUCK_S):
            _abandon_stuck(conn, lock, signum)

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
                # its key's parts: the client names what differs (a dependency's version, a variable)
                wire.send(conn, b"r" if self.auto else b"m", json.dumps(self.parts).encode())
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
                     "key": self.key, "path": self.path, "parts": self.parts, "history": self.history,
                     "rss": _rss(os.getpid()), "children_rss": sum(_rss(p) for p in interrupts.children()),
                     "idle_timeout": self.idle_timeout, "auto": self.auto}
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

    from dstereo.runtime import figure_pool

    figure_pool.start()  # the workers import matplotlib meanwhile
    for name in preload_modules():  # named by the command line (`request.set_command`)
        importlib.import_module(name)
    _warm_up()


def _warm_up() -> None:
    """What every calibration runs first whatever its shapes: LAPACK's kernels readied for loaded executables
    (imports scipy.linalg: ~0.1-0.2 s of a first served command, measured)."""
    from dstereo.runtime.jax_workarounds import prepare_loaded_executables

    prepare_loaded_executables()


def _renew_figure_pool(workers: int) -> None:
    """A worker killed during a command leaves the pool broken (its figures were drawn here instead), and an
    interrupted command kills them all (`_end_command_children`): start new workers for the next command rather
    than draw in the server from then on."""
    from dstereo.runtime import figure_pool

    figure_pool.renew_broken()
    if figure_pool.started() < workers:
        figure_pool.start(workers)


def _end_command_children(before: list[int]) -> None:
    """After a command that a client's signal stopped: no process it started lives on (a local Dask cluster's
    workers, a figure still drawing into a folder the command removed). The figure workers go too; new ones come
    for the next command (`_renew_figure_pool`). multiprocessing's resource tracker, the server's since its
    first worker, stays: killed, it is relaunched with a warning and tracebacks for the semaphores it lost."""
    from dstereo.runtime import figure_pool

    workers = figure_pool.pids()
    figure_pool.kill()
    interrupts.kill_children(keep=set(before) - set(workers))


def _abandon_stuck(conn: socket.socket, lock: threading.Lock, signum: int) -> None:
    """The command did not stop (native code that never returns): tell the client its line and code, remove the
    command's staging folders, end every child, and end the server (interrupts.abandon: no stale socket)."""
    line = f"dstereo: error: {interrupts.Interrupted(signum)} (the command was stuck in a compiled call; the " \
           "background server stopped with it)\n"
    _tell_client(conn, lock, line, 128 + signum)
    interrupts.mark_said()
    interrupts.abandon()


def _tell_client(conn: socket.socket, lock: threading.Lock, line: str, code: int) -> None:
    """A command's last line and exit code, sent by a watchdog as the server ends (not the command's thread)."""
    if lock.acquire(timeout=0.2):  # the command's own output may hold it; the client says the line otherwise
        try:
            wire.send(conn, b"e", line.encode())
            wire.send(conn, b"x", json.dumps(code).encode())
        except OSError:
            pass


def _unlink_if(path: str, inode: int) -> None:
    try:
        if os.stat(path).st_ino == inode:  # still ours, not a newer server's
            os.unlink(path)
    except OSError:
        pass


def _rss(pid: int) -> int:
    """Resident memory of `pid` in bytes (Linux /proc; 0 elsewhere)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0
