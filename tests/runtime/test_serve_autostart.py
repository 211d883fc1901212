"""The `dstereo` entry point starts a server when none runs (dstereo/runtime/autostart.py): the first command runs in
its own process with the output and exit code it always had, a detached server comes up once that command has
ended, the next command is served, and a server made for other code makes way for one of the client's own. Never
under pytest, in CI, with DSTEREO_SERVE=0 or manual; an idle server stops.

The clients here drop PYTEST_CURRENT_TEST from their environment (pytest sets it, and its subprocesses inherit it,
which is what keeps every other test's clients from starting servers).
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dstereo.runtime import autostart
from dstereo.runtime import client as wire

ROOT = Path(__file__).resolve().parents[2]
ENTRY = "import sys; sys.argv[0] = 'dstereo'; from dstereo.cli import main; main(end_process=True)"
STARTUP_S = 300  # generous: JAX and the figure workers import on a loaded 2-core machine; not a timed assertion


def _env(run_dir: Path, **extra) -> dict:
    env = dict(os.environ, DSTEREO_SERVE_DIR=str(run_dir), **extra)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    for name in ("DSTEREO_SERVE", "PYTEST_CURRENT_TEST", "CI"):
        env.pop(name, None)
    return env


def dstereo(env: dict, cwd: Path, *args) -> tuple[int, str, str]:
    done = subprocess.run([sys.executable, "-c", ENTRY, *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=STARTUP_S)
    return done.returncode, done.stdout, done.stderr


def _status(path: str) -> dict | None:
    from dstereo.commands.serve import ask

    return ask(path, "status")


def _wait(condition, what: str) -> None:
    deadline = time.monotonic() + STARTUP_S
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"waited {STARTUP_S} s for {what}")
        time.sleep(0.1)


def _stop(env: dict, path: str) -> None:
    """Stop whatever server answers at `path`, and wait until its lock is free (the process has ended)."""
    dstereo({**env, "DSTEREO_SERVE": "manual"}, Path("/"), "serve", "--stop")
    _wait(lambda: not autostart.lock_taken(wire.sibling(path, ".lock")), "the server's end")


def test_wanted_only_from_a_served_command_outside_tests_and_ci():
    env = {"HOME": "/h"}
    wanted = lambda argv, e=env: autostart.wanted(wire.servable(argv), e)  # noqa: E731 - as main asks it
    assert wanted(["calibrate", "--images", "x"])
    assert not wanted(["serve"]) and not wanted(["demo"]) and not wanted(["--help"]) and not wanted([])
    for name, value in (("DSTEREO_SERVE", "0"), ("DSTEREO_SERVE", "manual"), ("PYTEST_CURRENT_TEST", "t"),
                        ("CI", "true"), ("PYTHONPATH", "relative/src")):
        assert not wanted(["init", "x"], {**env, name: value}), name
    assert wanted(["init", "x"], {**env, "DSTEREO_SERVE": "1", "PYTHONPATH": "/abs/src"})
    # the tests' own environment: pytest's variable keeps every test's clients from starting servers
    assert not autostart.wanted(wire.servable(["init", "x"]))


def test_no_server_is_started_under_pytest_or_when_off(tmp_path):
    run_dir = tmp_path / "run"
    path = wire.socket_path(_env(run_dir))
    for extra in ({"PYTEST_CURRENT_TEST": "t"}, {"DSTEREO_SERVE": "0"}, {"DSTEREO_SERVE": "manual"}, {"CI": "1"}):
        code, _, err = dstereo({**_env(run_dir), **extra}, tmp_path, "init", f"p{len(os.listdir(tmp_path))}")
        assert code == 0 and err == "", extra
        # the client writes the log's name before it starts a server: no log, no start
        assert not os.path.exists(wire.sibling(path, ".log")), extra


@pytest.mark.slow
def test_first_command_runs_here_and_starts_a_server_that_serves_the_next(tmp_path):
    run_dir = tmp_path / "run"
    env = _env(run_dir, DSTEREO_SERVE_IDLE="600")
    path = wire.socket_path(env)
    try:
        folders = {name: tmp_path / name for name in ("here", "first", "served")}
        for folder in folders.values():
            folder.mkdir()
        here = dstereo({**env, "DSTEREO_SERVE": "0"}, folders["here"], "init", "p")  # no server, none started
        first = dstereo(env, folders["first"], "init", "p")  # no server: runs here, starts one
        # same output and exit code; stderr: the one note that a background server was started (first time only)
        assert first[:2] == here[:2] and first[0] == 0 and len(first[2].splitlines()) == 1, first[2]
        assert "background server" in first[2] and "10 min" in first[2] and "dstereo serve --stop" in first[2]
        assert "DSTEREO_SERVE=0" in first[2] and os.path.exists(wire.sibling(path, ".told"))
        _wait(lambda: _status(path) is not None, "the auto-started server")
        assert oct(os.stat(run_dir).st_mode & 0o777) == "0o700"
        assert oct(os.stat(wire.sibling(path, ".log")).st_mode & 0o777) == "0o600"
        served = dstereo(env, folders["served"], "init", "p")
        assert served == here and _status(path)["served"] == 1  # the next command was served, same output
        files = [(f / "p" / "dstereo.toml").read_bytes() for f in folders.values()]
        assert files[0] == files[1] == files[2]
        # a command that fails exits with the same code and line through the server
        bad = ["calibrate", "--images", "absent", "--pattern", "9x6", "--out", "r"]
        assert dstereo(env, tmp_path, *bad) == dstereo({**env, "DSTEREO_SERVE": "0"}, tmp_path, *bad)
        assert _status(path)["served"] == 2
        # no second server: a command that finds one busy or running starts none (the lock is held)
        assert autostart.lock_taken(wire.sibling(path, ".lock"))
        assert not autostart.start(path)
        # A client of other start-up settings (another key): it runs here without a note, the server made for
        # the old settings stops, and one made for the client's comes up in its place.
        other = {**env, "MPLCONFIGDIR": str(tmp_path / "mpl")}
        old_pid = _status(path)["pid"]
        code, out, err = dstereo(other, tmp_path, "init", "d")
        # one note naming what differs; the replacing server's start is not announced again
        assert code == 0 and (tmp_path / "d" / "dstereo.toml").is_file() and len(err.splitlines()) == 1, err
        assert "MPLCONFIGDIR unset here" not in err and "MPLCONFIGDIR" in err and "a new server starts" in err
        _wait(lambda: (_status(path) or {}).get("pid", old_pid) != old_pid, "the replacing server")
        assert _status(path)["key"] == wire.code_key(other) != wire.code_key(env)
    finally:
        _stop(env, path)
    assert not os.path.exists(path)


def test_an_idle_server_stops_and_answers_busy_meanwhile(tmp_path):
    import socket as socket_module
    import threading

    from dstereo.runtime.server import Server

    s = Server(str(tmp_path / "serve.sock"), idle_timeout=30.0)
    assert not s._idle_expired()
    s.last -= 31.0
    s.busy = True
    assert not s._idle_expired()  # a command running is not idleness
    s.busy = False
    assert s._idle_expired() and s.stopping
    ours, theirs = socket_module.socketpair()
    with ours:
        worker = threading.Thread(target=s._greet, args=(theirs,))
        worker.start()
        wire.send(ours, b"q", b'{"op": "run", "key": "%s", "argv": ["init", "x"]}' % s.key.encode())
        assert wire.receive(ours)[0] == b"b"  # stopping: the client runs the command itself
        worker.join()
