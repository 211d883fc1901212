"""Starting `dstereo serve` in the background from the `dstereo` entry point (runtime/client.py), standard library only.

A command that finds no server for its installation runs in its own process as before and, on its way, starts a
detached server: a new session (no terminal, no hang-up signal), stdin from /dev/null, stdout and stderr to
serve-<id>.log beside the socket (mode 0600 in the 0700 folder), working folder /. Nothing it does reaches the
command's output or exit code. The server (runtime/server.py) takes the installation's lock (one per user and
installation; a second one started at the same moment finds it taken and exits), waits until this process has
ended, loads, listens, and stops after DSTEREO_SERVE_IDLE seconds without a command (default IDLE_S).
"""

from __future__ import annotations

import os
import sys

IDLE_S = 900.0  # an auto-started server exits after this long without a command (DSTEREO_SERVE_IDLE)
# The server, started as `python -m dstereo.cli serve ...`: a `dstereo` command's process in every way the code
# asks (runtime/aot.py builds missing executables there, as in `dstereo serve` started by hand).
SERVER = ("-m", "dstereo.cli")


def wanted(servable: bool, env=None) -> bool:
    """Whether this command, run here for want of a server, starts one: a command a server may run (`servable`,
    client.servable), not DSTEREO_SERVE=0 or manual, not under pytest (PYTEST_CURRENT_TEST, which its
    subprocesses inherit) or in CI (`CI` set), not with a relative PYTHONPATH entry, and where Unix sockets exist."""
    env = os.environ if env is None else env
    # a relative PYTHONPATH entry would name another folder from the server's working folder (/)
    relative = any(p and not os.path.isabs(p) for p in env.get("PYTHONPATH", "").split(os.pathsep))
    return (servable and env.get("DSTEREO_SERVE", "") not in ("0", "manual")
            and "PYTEST_CURRENT_TEST" not in env and not env.get("CI") and not relative and os.name == "posix"
            and hasattr(os, "setsid"))


def idle_seconds(env=None) -> float:
    env = os.environ if env is None else env
    try:
        return max(0.0, float(env.get("DSTEREO_SERVE_IDLE", IDLE_S)))
    except ValueError:
        return IDLE_S


def lock_taken(lock: str) -> bool:
    """Whether a server (running or starting) holds the installation's lock."""
    import fcntl

    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError:
        return True  # cannot tell: do not start another
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # releases it
    return False


def start(path: str, replacing: bool = False) -> bool:
    """Start a detached server for the socket `path` (see the module); False where none was started: the folder
    cannot be made private, a server holds the lock (unless `replacing` a retiring one, which releases it), or the
    process could not be started. Never raises."""
    from dstereo.runtime.paths import private, sibling

    folder = os.path.dirname(path)
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        if not private(folder) or (not replacing and lock_taken(sibling(path, ".lock"))):
            return False
        import subprocess

        log = os.open(sibling(path, ".log"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            subprocess.Popen([sys.executable, *SERVER, "serve", "--idle-timeout", f"{idle_seconds():g}",
                              "--started-by", str(os.getpid())],
                             stdin=subprocess.DEVNULL, stdout=log, stderr=log, cwd="/", start_new_session=True,
                             close_fds=True)
        finally:
            os.close(log)
    except (OSError, ValueError):
        return False
    return True


def tell_once(path: str) -> None:
    """The first server started for this installation says so, once: a background process holding ~0.6-0.75 GB
    for IDLE_S must not come unannounced. A marker file beside the socket remembers that it was said."""
    from dstereo.runtime.paths import sibling

    marker = sibling(path, ".told")
    try:
        fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError:  # said before (or the folder refuses: then say nothing rather than say it every time)
        return
    os.close(fd)
    minutes = idle_seconds() / 60
    sys.stderr.write(f"dstereo: note: started a background server that keeps dstereo loaded so the next commands "
                     f"start faster; it stops after {minutes:g} min without a command; stop it now: dstereo "
                     "serve --stop; never start one: DSTEREO_SERVE=0 (this note is shown once)\n")
    sys.stderr.flush()
