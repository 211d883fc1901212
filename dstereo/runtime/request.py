"""One command of a client, run inside `dstereo serve` as the `dstereo` process would run it.

The command sees what it would see in its own process: the client's argv, working folder and environment,
stdout/stderr that reach the client's terminal (and say whether it is one), an empty stdin, fresh warning
filters (a warning shown once per process is shown again), and `dstereo.cli.main`'s own error handling, exit
codes and tracebacks. The server runs one request at a time, so changing the folder and the environment of the
whole process for its duration is safe; both are put back afterwards.
"""

from __future__ import annotations

import io
import os
import signal
import sys
import threading
import traceback
import warnings

from dstereo.runtime.interrupts import Interrupted
from dstereo.runtime.client import send


class _FrameWriter(io.RawIOBase):
    """Bytes written here go to the client as frames of one kind (`o` stdout, `e` stderr); after the client has
    gone they are dropped, so the command runs on until the server interrupts it."""

    def __init__(self, conn, kind: bytes, tty: bool, lock: threading.Lock):
        super().__init__()
        self.conn, self.kind, self.tty, self.lock, self.gone = conn, kind, tty, lock, False

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return self.tty

    def write(self, data) -> int:
        if not self.gone:
            try:
                with self.lock:  # a progress bar's refresh thread writes too: frames must not interleave
                    send(self.conn, self.kind, bytes(data))
            except OSError:
                self.gone = True
        return len(data)


def client_stream(conn, kind: bytes, traits: dict, lock: threading.Lock, line_buffering: bool) -> io.TextIOWrapper:
    raw = _FrameWriter(conn, kind, bool(traits.get("tty")), lock)
    return io.TextIOWrapper(io.BufferedWriter(raw), encoding=traits.get("encoding") or "utf-8",
                            errors=traits.get("errors") or "strict", line_buffering=line_buffering)


# The client's signal reaches the command as this signal, sent to the main thread by the server's watcher
# (a real signal, not a simulated one: it also ends a blocked wait there). SIGINT, SIGTERM and SIGHUP stay the
# server's own (dstereo/runtime/interrupts.py: they stop the server). It interrupts the command only while the command
# runs, never the restoring around it.
INTERRUPT_SIGNAL = signal.SIGUSR1
_command_running = False
_client_signal = signal.SIGINT  # the signal the client got (sent with its interrupt), named in the command's line


class ClientInterrupt(Interrupted):
    """The client's signal (or its disconnection) inside the command: the command ends, the server goes on."""


def interrupt_command(main_thread: int, signum: int) -> None:
    """From the server's watcher: stop the running command as if `signum` had reached its own process."""
    global _client_signal
    _client_signal = signum
    signal.pthread_kill(main_thread, INTERRUPT_SIGNAL)


def _interrupt_command(signum, frame) -> None:
    if _command_running:
        raise ClientInterrupt(_client_signal)


def install_interrupt() -> None:
    """In the server's main thread, before serving."""
    signal.signal(INTERRUPT_SIGNAL, _interrupt_command)


class _ProcessExit(BaseException):
    """os._exit called by the command: in a server that ends the command, not the process."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def _exit_instead(code: int = 0) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    raise _ProcessExit(int(code))


_COMMAND = []  # the command line's `main` (dstereo.cli registers it: the runtime does not import the command line)
_PRELOAD: list[str] = []  # the modules a server loads at start-up for its first command (the command line names them)


def set_command(main, preload: tuple[str, ...] = ()) -> None:
    """Register the command line's entry (`dstereo.cli.main`) that `run_request` runs for a client, and the modules
    a server started from this process imports before its first request."""
    _COMMAND[:] = [main]
    _PRELOAD[:] = list(preload)


def preload_modules() -> tuple[str, ...]:
    return tuple(_PRELOAD)


def run_request(request: dict, stdout: io.TextIOWrapper, stderr: io.TextIOWrapper) -> int:
    """Run `dstereo ARGV` in the request's folder and environment with these streams; its exit code."""
    if not _COMMAND:
        raise RuntimeError("no command line registered (dstereo.cli.main registers itself before it dispatches)")
    main = _COMMAND[0]

    saved_streams = sys.argv, sys.stdout, sys.stderr, sys.stdin, sys.__stdout__, sys.__stderr__, sys.__stdin__
    saved_env, saved_cwd, saved_exit = dict(os.environ), os.getcwd(), os._exit
    try:
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        _forget_temp_folder()
        sys.argv = [request.get("argv0") or "dstereo", *request["argv"]]
        sys.stdout, sys.stderr, sys.stdin = stdout, stderr, io.StringIO()
        # shutil.get_terminal_size and rich ask these for the terminal's size: the server's own terminal is not
        # the client's (whose size, when it has one, came as COLUMNS/LINES)
        sys.__stdout__, sys.__stderr__, sys.__stdin__ = sys.stdout, sys.stderr, sys.stdin
        os._exit = _exit_instead
        with warnings.catch_warnings():  # entering resets the once-per-process registries, leaving the filters
            return _exit_code(main)  # in a server `cli.main` does not end the process (`cli._command_process`)
    finally:
        for stream in (stdout, stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit = saved_exit
        sys.argv, sys.stdout, sys.stderr, sys.stdin, sys.__stdout__, sys.__stderr__, sys.__stdin__ = saved_streams
        os.environ.clear()
        os.environ.update(saved_env)
        _forget_temp_folder()
        os.chdir(saved_cwd)


def _forget_temp_folder() -> None:
    """tempfile keeps the first TMPDIR it saw for the process; each command reads its own client's."""
    if "tempfile" in sys.modules:
        sys.modules["tempfile"].tempdir = None


def _exit_code(main) -> int:
    """What the interpreter would exit with after `main()`, printing what it would print (SystemExit's message,
    an uncaught exception's traceback)."""
    global _command_running
    try:
        try:
            _command_running = True
            main()
        finally:
            _command_running = False
        return 0
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(exc.code, file=sys.stderr)
        return 1
    except _ProcessExit as exc:
        return exc.code
    except ClientInterrupt as exc:  # its line was said (dstereo.cli); 128 + the signal, as a process would exit
        return exc.code
    except (Interrupted, KeyboardInterrupt):  # the server's own signal: it stops the server, not just this command
        raise
    except BaseException:  # noqa: BLE001 - a crash ends this command only, with the traceback Python would show
        traceback.print_exc()
        return 1
