"""Where a `dstereo serve` server lives, standard library only (the entry point imports this before anything else):
its folder, the installation's id, the socket, lock and log beside it, and whether the folder is private."""

from __future__ import annotations

import hashlib
import os
import sys


def runtime_dir(env=None) -> str:
    """DSTEREO_SERVE_DIR, else $XDG_RUNTIME_DIR/dstereo, else ~/.cache/dstereo/serve (made mode 0700 by the server)."""
    env = os.environ if env is None else env
    if env.get("DSTEREO_SERVE_DIR"):
        return env["DSTEREO_SERVE_DIR"]
    if env.get("XDG_RUNTIME_DIR"):
        return os.path.join(env["XDG_RUNTIME_DIR"], "dstereo")
    cache = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(cache, "dstereo", "serve")


def install_id() -> str:
    """12 hex digits naming this installation: the package's folder, the Python environment and interpreter."""
    h = hashlib.sha256()
    for part in (os.path.dirname(os.path.dirname(os.path.abspath(__file__))), sys.prefix, os.path.realpath(sys.executable)):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:12]


def socket_path(env=None) -> str:
    """The server's socket for this installation in `runtime_dir`; its lock and log sit beside it (`sibling`)."""
    return os.path.join(runtime_dir(env), f"serve-{install_id()}.sock")


def sibling(path: str, suffix: str) -> str:
    """serve-<id>.lock / .log beside the socket serve-<id>.sock."""
    return path[: -len(".sock")] + suffix


def private(folder: str) -> bool:
    """The folder is ours and closed to others: the socket carries our environment and runs as us."""
    try:
        st = os.stat(folder)
    except OSError:
        return False
    return st.st_uid == os.getuid() and not st.st_mode & 0o077
