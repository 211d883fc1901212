"""Staging folders beside a results folder OUT: `.OUT.tmp-<pid>@<host>-<random>` (the folder being written, renamed to
OUT at the end) and `.OUT.figures-<pid>@<host>-<random>` (figures drawn early).

The owner's pid and host are in the name so that a later run can tell a folder left by a process that no longer
exists (`kill -9`, a power cut: no cleanup ran) from one that a live run is writing: `clean_stale` removes the
former only, and only on the host that made it (on a shared file system another host's pid says nothing here).
Each folder is also registered with `dstereo.runtime.interrupts`, whose watchdog removes it if a signal's clean unwinding
does not get to it in time.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

from dstereo.runtime import interrupts

KINDS = ("tmp", "figures")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", socket.gethostname())[:40] or "host"


def make(parent: str | Path | None, name: str, kind: str) -> Path:
    """A new staging folder `.NAME.KIND-<pid>@<host>-<random>` in `parent` (None: the system's temporary folder),
    registered for the watchdog; `done` unregisters it."""
    folder = Path(tempfile.mkdtemp(prefix=f".{name}.{kind}-{os.getpid()}@{_host()}-", dir=parent))
    interrupts.staging(folder)
    return folder


def done(folder: str | Path) -> None:
    interrupts.release(folder)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def clean_stale(parent: str | Path, name: str) -> list[Path]:
    """Remove the staging folders of `name` in `parent` whose owner process is gone (this host only); the removed."""
    pattern = re.compile(rf"^\.{re.escape(name)}\.(?:{'|'.join(KINDS)})-(\d+)@([^-]+)-")
    removed = []
    try:
        entries = os.listdir(parent)
    except OSError:
        return removed
    host = _host()
    for entry in entries:
        match = pattern.match(entry)
        if match and match.group(2) == host and not _alive(int(match.group(1))):
            path = Path(parent) / entry
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed
