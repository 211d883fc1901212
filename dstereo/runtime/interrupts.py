"""SIGINT, SIGTERM and SIGHUP end a `dstereo` command within ~2 s, whatever it is doing, standard library only.

Why not Python's default: a signal's Python handler runs only in the main thread, between two bytecodes. A main
thread waiting on worker threads that sit in a JAX call never gets there (its wait is not woken by a signal that
the kernel gave to another thread), and once it does, unwinding joins those threads (a thread pool's exit), which
may never return. And SIGTERM's default kills the process alone: the figure workers and multiprocessing's
resource tracker (which ignores SIGINT and SIGTERM) live on, holding the caller's stdout/stderr open.

So (`install`, at the entry point): the C-level handler writes the signal's number to a pipe
(`signal.set_wakeup_fd`); a daemon thread reads it, pokes the main thread awake (`POKE`, so a blocked wait returns
and the Python handler runs) and arms a watchdog. The Python handler raises `Interrupted` (a BaseException: click
turns a KeyboardInterrupt into "Aborted!", and no `except Exception` may swallow it); the command unwinds, its
`finally`/`except BaseException` blocks remove its staging folders, and `dstereo.cli` prints one line
`dstereo: error: interrupted (SIGTERM)`, ends every child process and exits 128 + the signal's number. If the main
thread has not got there within GRACE_S (stuck in native code, or joining a stuck thread), the watchdog does it
itself: removes the staging folders still registered (`staging`), kills the children, writes the line and
`os._exit`s. A second signal does that at once.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import threading

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
# The process's own exit, taken before anything can stand in for it: a served command runs with os._exit
# replaced (runtime/request.py: the command's end must not end the server), and a watchdog that ends the
# server from another thread during that command must really end it (measured: with os._exit it raised in the
# watchdog's thread instead, whose traceback then waited forever on the client's stream lock).
_hard_exit = getattr(__import__("posix"), "_exit", None) if os.name == "posix" else os._exit
POKE = signal.SIGUSR2  # sent to the main thread only to end a blocked system call; its handler does nothing
GRACE_S = 1.2  # the main thread's time to unwind cleanly; then the watchdog ends the process (within the 2 s)

_lock = threading.Lock()
_received: int | None = None  # the first signal's number
_count = 0  # signals read from the wakeup pipe (one byte each)
_raised = False
_installed = False
_said = False  # the one line was written (by the CLI or the watchdog)
_staging: set[str] = set()
_completed: list[str] = []  # results folders already in place (`completed`)
_cleanups: list = []  # callables run by the watchdog before it ends the process (the server: unlink its socket)


class Interrupted(BaseException):
    """A signal ends the command: `code` 128 + its number, the message names it (and what was kept, `detail`)."""

    def __init__(self, signum: int, detail: str = ""):
        super().__init__(signum, detail)
        self.signum, self.detail = int(signum), detail

    @property
    def code(self) -> int:
        return 128 + self.signum

    def __str__(self) -> str:
        return f"interrupted ({signal_name(self.signum)})" + (f"; {self.detail}" if self.detail else "")

    def with_detail(self, detail: str) -> "Interrupted":
        return type(self)(self.signum, detail)


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def received() -> int | None:
    return _received


def install() -> bool:
    """In the main thread of a process that runs commands (the entry point, `python -m dstereo.cli`). A signal the
    caller set to be ignored (nohup's SIGHUP, a background job's SIGINT) stays ignored. False where it cannot be
    installed (not the main thread: library use)."""
    global _installed
    if _installed:
        return True
    if threading.current_thread() is not threading.main_thread():
        return False
    _installed = True
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    try:
        signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
    except ValueError:
        return False
    for signum in SIGNALS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _raise)
    signal.signal(POKE, lambda *_: None)
    _default_unraisable = sys.unraisablehook

    def unraisable(info):
        # the handler's exception raised where Python ignores exceptions (a weakref callback, a __del__, an atexit
        # function) is reported as "Exception ignored in ..." with a traceback: say nothing; `check` and the
        # CLI's end (`finish`) still end the command as interrupted
        if not isinstance(info.exc_value, Interrupted):
            _default_unraisable(info)

    sys.unraisablehook = unraisable
    threading.Thread(target=_read_wakeups, args=(read_end,), name="dstereo-signals", daemon=True).start()
    return True


def _raise(signum, frame) -> None:
    global _raised
    _arm(signum, counted=False)  # the reader thread counts it (it may run before or after this)
    if not _raised:  # once: a second signal must not break the cleanup the first one started
        _raised = True
        raise Interrupted(signum)


def _read_wakeups(fd: int) -> None:
    main = threading.main_thread().ident
    while True:
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        for signum in data:
            if signum in SIGNALS and signal.getsignal(signum) is _raise:
                _arm(signum, counted=True)
                try:
                    signal.pthread_kill(main, POKE)
                except (OSError, ValueError):
                    pass


def _arm(signum: int, counted: bool) -> None:
    """The first signal starts the watchdog; a second (a user pressing Ctrl-C again) ends the process now."""
    global _received, _count
    with _lock:
        first = _received is None
        if first:
            _received = signum
        _count += counted
        again = _count > 1
    if first:
        timer = threading.Timer(GRACE_S, abandon)
        timer.daemon = True
        timer.start()
    if again:
        abandon()


def check() -> None:
    """Raise `Interrupted` if a signal came: its first raise can be lost (Python ignores an exception raised in a
    weakref callback, a __del__ or an atexit function, and the handler raises once). Called before a command
    makes its results visible and before it ends with success."""
    if _received is not None:
        raise Interrupted(_received)


def staging(path) -> None:
    """`path` is a folder the command writes and removes itself; the watchdog removes it if the command cannot."""
    with _lock:
        _staging.add(str(path))


def release(path) -> None:
    with _lock:
        _staging.discard(str(path))


def on_abandon(fn) -> None:
    _cleanups.append(fn)


def completed(path) -> None:
    """The command's results folder `path` is in place, whole: a signal from now on ends the process, but the
    line says that the results were written before it came (they are complete, not half-written)."""
    _completed.append(str(path))


def say(exc: Interrupted, stream=None) -> None:
    """The command's one line, once per process."""
    global _said
    if not _said:
        _said = True
        stream = sys.stderr if stream is None else stream
        if _completed and not exc.detail:
            exc = exc.with_detail(f"{_completed[-1]} had been written whole before it came")
        stream.write(f"dstereo: error: {exc}\n")
        stream.flush()


def mark_said() -> None:
    global _said
    _said = True


def abandon(line: str | None = None, code: int | None = None) -> None:
    """The watchdog: the main thread did not end the command in time (a signal's, or dstereo/runtime/watchdog.py's `line`
    and `code` for a compiled call that stopped making progress). Everything here avoids locks the main thread
    may hold (no print: sys.stderr's buffer lock; os.write to fd 2)."""
    global _said
    for path in list(_staging):
        shutil.rmtree(path, ignore_errors=True)
    for fn in list(_cleanups):
        try:
            fn()
        except Exception:  # noqa: BLE001 - the process ends either way
            pass
    kill_children()
    signum = _received or signal.SIGTERM
    if not _said:
        _said = True
        try:
            os.write(2, f"dstereo: error: {line or Interrupted(signum)}\n".encode())
        except OSError:
            pass
    _hard_exit(128 + signum if code is None else code)


def children(pid: int | None = None) -> list[int]:
    """Every live descendant of `pid` (default: this process), from /proc (Linux); [] where there is none."""
    pid = os.getpid() if pid is None else pid
    parents: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat[stat.rfind(b")") + 2:].split()  # after "(comm)", which may hold spaces
        if fields and fields[0] != b"Z":
            parents.setdefault(int(fields[1]), []).append(int(entry))
    found, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def kill_children(keep=()) -> None:
    """SIGKILL every descendant (figure workers, the resource tracker, Dask's worker processes) but `keep`, twice
    over: one may have started a child of its own meanwhile. Nothing they do is kept: the command is ending."""
    for _ in range(2):
        for pid in set(children()) - set(keep):
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
