"""Building the other shape buckets' programs ahead of need, in the background (issue 33).

A command records the programs it ran whose shapes follow the view count (`buckets.note`: the solver for its lens
models and cameras, the per-view refits, the projection map). When it has finished, `start` hands those not yet
built to a detached builder (`python -m dstereo.jobs.prebuild`): it compiles each of them for every view bucket of
5-60 views (`VIEWS`) into the executables folder (`runtime/aot.py`), so that a later data set of another size
loads its programs instead of compiling them. The builder runs at the lowest priority on one core, in a session of
its own (no terminal: Ctrl-C in the shell does not reach it, and it never holds a command up), one at a time per
cache folder (a lock; a second one leaves its list for the running one), and ends after `LIMIT_S` at most.

Off with DSTEREO_PREBUILD=0, without an executables folder, under pytest and in CI (as `autostart`). What was built
is marked per program and code version (`marker`), so each is built once per machine and version.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import sys
import uuid
from pathlib import Path

VIEWS = (5, 60)  # the view counts built ahead: every bucket between
LIMIT_S = 3600.0  # a builder ends after this long, built or not (the rest is built by the next one)
FOLDER = "prebuild"  # in the executables folder: the lists waiting, the markers of what is built, the lock, the log


def folder() -> Path | None:
    from dstereo.runtime import aot

    base = aot.cache_folder()
    return None if base is None else base / FOLDER


def marker(kind: str, spec) -> str:
    """The name of a program's done marker: its kind, spec and the environment (versions, code: `aot.environment`)."""
    from dstereo.runtime import aot

    h = hashlib.sha256(aot.environment().encode() + b"\0" + kind.encode() + b"\0")
    h.update(pickle.dumps(spec, protocol=4))
    return h.hexdigest()[:32] + ".done"


def wanted(env=None) -> bool:
    """Whether this process starts builders: not DSTEREO_PREBUILD=0 nor shape buckets off, not under pytest or in
    CI, with an executables folder."""
    env = os.environ if env is None else env
    return (env.get("DSTEREO_PREBUILD", "") != "0" and env.get("DSTEREO_SHAPE_BUCKETS", "") != "0"
            and "PYTEST_CURRENT_TEST" not in env and not env.get("CI") and os.name == "posix" and folder() is not None)


def pending(records) -> list:
    """The (kind, spec) of `records` not marked as built."""
    where = folder()
    if where is None:
        return []
    return [(kind, spec) for kind, spec in records if not (where / marker(kind, spec)).exists()]


def start(records, sizes=()) -> bool:
    """Write the records not built yet as a list for the builder and start one (detached, see the module); False
    where nothing was started (nothing to build, not wanted, or it could not be). `sizes`: the view buckets the
    command ran at (the builder builds the nearest first). Never raises."""
    try:
        if not wanted():
            return False
        todo = pending(records)
        if not todo:
            return False
        where = folder()
        where.mkdir(parents=True, exist_ok=True)
        name = where / f"todo-{uuid.uuid4().hex}.pkl"
        tmp = name.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps({"records": todo, "sizes": tuple(sizes)}, protocol=4))
        os.replace(tmp, name)
        import subprocess

        log = os.open(where / "prebuild.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            env = dict(os.environ, DSTEREO_AOT="1")  # it builds (runtime/aot.builds_here)
            env.pop("DSTEREO_SERVE", None)
            # this very package (its code is in the executables' key), wherever the builder's working folder is
            root = str(Path(__file__).resolve().parents[2])
            env["PYTHONPATH"] = os.pathsep.join([root, *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
            subprocess.Popen([sys.executable, "-m", "dstereo.jobs.prebuild", str(where)], stdin=subprocess.DEVNULL,
                             stdout=log, stderr=log, cwd="/", start_new_session=True, close_fds=True, env=env)
        finally:
            os.close(log)
        return True
    except (OSError, ValueError, pickle.PicklingError):
        return False
