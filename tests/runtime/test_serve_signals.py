"""The resident server and signals, its key and its status: a served command stopped by the client's SIGTERM ends
the client at once with the command's line and code while the server lives on without the command's processes;
a server of another dependency version refuses the client, which names the version and runs the command itself;
`--help` starts no server; `serve --status` shows memory, age and commands.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from dstereo.runtime import client as wire
from dstereo.runtime.interrupts import children

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from test_signals import END_S, SUBSET_FLAGS, Run, alive, render_views  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ENTRY = "import sys; sys.argv[0] = 'dstereo'; from dstereo.cli import main; main(end_process=True)"
STARTUP_S = 300  # not timed: JAX and the figure workers import on a loaded 2-core machine


def _env(run_dir: Path, **extra) -> dict:
    env = dict(os.environ, DSTEREO_SERVE_DIR=str(run_dir), **extra)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.pop("DSTEREO_SERVE", None)
    return env


def dstereo(env: dict, cwd: Path, *args) -> tuple[int, str, str]:
    done = subprocess.run([sys.executable, "-c", ENTRY, *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=STARTUP_S)
    return done.returncode, done.stdout, done.stderr


def _status(path: str) -> dict | None:
    from dstereo.commands.serve import ask

    return ask(path, "status")


@pytest.fixture(scope="module")
def views(tmp_path_factory) -> Path:
    """16 rendered board views, made once for the module's two served calibrations: read-only to them (both detect
    with --no-cache, and a corner cache lives outside the folder), so sharing changes nothing they see."""
    return render_views(tmp_path_factory.mktemp("views") / "images", 16)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="children are listed from /proc")
def test_a_served_command_stopped_by_sigterm_ends_the_client_and_its_processes_not_the_server(tmp_path, views):
    run_dir = tmp_path / "run"
    env = _env(run_dir)
    server = subprocess.Popen([sys.executable, "-c", ENTRY, "serve"], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    path = wire.socket_path(env)
    try:
        assert "ready" in server.stderr.readline()
        threading.Thread(target=server.stderr.read, daemon=True).start()
        # Once in full, so the interrupted run compiles nothing: a compile is native code that no signal stops,
        # which the server answers by ending itself (serve_server.STUCK_S); here it must survive.
        flags = [*SUBSET_FLAGS[:-1], "3000"]  # 3000 subsets (~2 s): the signal still lands in them
        warm = dstereo(env, tmp_path, "calibrate", "--images", views, *flags, "--out", "warm")
        assert warm[0] == 0 and _status(path)["served"] == 1, warm[2]
        own = set(children(server.pid))  # the server's figure workers and resource tracker
        work = tmp_path / "work"
        work.mkdir()
        run = Run(["calibrate", "--images", views, *flags, "--out", "results"], work, env)
        run.wait_for(b"full-set solve: 1/1 done")
        time.sleep(0.2)
        assert _status(path)["busy"]
        sent = time.monotonic()
        run.proc.send_signal(signal.SIGTERM)
        code = run.proc.wait(timeout=STARTUP_S)
        ended = time.monotonic() - sent
        assert ended < END_S and run.closed_within(END_S), f"ended {ended:.1f} s after SIGTERM"
        assert code == 143, b"".join(run.err).decode()
        assert run.err[-1] == b"dstereo: error: interrupted (SIGTERM)\n", b"".join(run.err).decode()
        assert os.listdir(work) == []  # no results, no staging folder
        state = _status(path)  # still serving: the command ended, the server did not
        assert state["pid"] == server.pid and state["history"][-1] == {**state["history"][-1], "code": 143}
        # no process of the interrupted command lives on: the server's children now are its tracker and the new
        # figure workers that replaced the killed ones
        killed = own - set(children(server.pid))
        assert killed and not any(alive(pid) for pid in killed)
        # The server stays busy while it replaces the killed figure workers (server._serve), and a command that
        # arrives meanwhile runs in its own process by design (measured under two test workers: `init` ran there,
        # served stayed 2). Once it is idle, it serves the next command.
        deadline = time.monotonic() + STARTUP_S
        while _status(path)["busy"] and time.monotonic() < deadline:
            time.sleep(0.1)
        assert dstereo(env, tmp_path, "init", "after")[0] == 0 and _status(path)["served"] == 3
    finally:
        dstereo(env, tmp_path, "serve", "--stop")
        if server.wait(timeout=STARTUP_S) is None:
            server.kill()


def _fake_versions(monkeypatch, **versions) -> None:
    real = wire.dependency_versions
    monkeypatch.setattr(wire, "dependency_versions", lambda package: {**real(package), **versions})


@pytest.mark.parametrize("auto", [False, True], ids=["started_by_hand", "auto_started"])
def test_a_server_of_another_dependency_version_refuses_the_client_which_says_so(monkeypatch, tmp_path, auto):
    """The server's key made with numpy 0.0.1 (faked through the key function, not by reinstalling); a real client
    (a subprocess with the installed numpy) is refused, runs the command itself and names numpy in its one note."""
    from dstereo.runtime.server import Server

    run_dir = tmp_path / "run"
    run_dir.mkdir(mode=0o700)
    env = _env(run_dir)
    with monkeypatch.context() as patch:
        _fake_versions(patch, numpy="0.0.1")
        server = Server(wire.socket_path(env), started_by=1 if auto else 0)
    assert server.key != wire.code_key(env) and server.parts["dist:numpy"] == "0.0.1"
    server.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.listener.bind(server.path)
    server.listener.listen(4)
    threading.Thread(target=server._listen, daemon=True).start()
    try:
        code, out, err = dstereo(env, tmp_path, "init", "project")
    finally:
        server.stopping = True
        server.listener.close()
    assert code == 0 and (tmp_path / "project" / "dstereo.toml").is_file() and server.served == 0
    assert len(err.splitlines()) == 1 and err.startswith("dstereo: note: "), err
    import numpy

    assert f"numpy {numpy.__version__} here, 0.0.1 in the server" in err
    assert ("a new server starts" in err) == auto and ("dstereo serve --stop" in err) == (not auto)


def test_the_key_holds_every_locked_dependency_version():
    lock = (ROOT / "requirements.lock").read_text().splitlines()
    locked = {wire._canonical(line.split("==")[0]) for line in lock if line[:1].isalnum() and "==" in line}
    parts = wire.key_parts()
    assert locked and {name.split(":", 1)[1] for name in parts if name.startswith("dist:")} == locked
    assert "absent" not in {parts[f"dist:{name}"] for name in locked}
    other = dict(wire.dependency_versions(str(ROOT / "dstereo")), scipy="0.1")
    assert wire.code_key(versions=other) != wire.code_key()
    assert wire.differences(wire.key_parts(versions=other), parts).startswith("scipy 0.1 here, ")


def test_help_starts_no_server(tmp_path):
    run_dir = tmp_path / "run"
    env = _env(run_dir)
    for name in ("PYTEST_CURRENT_TEST", "CI"):  # what keeps other tests' clients from starting servers
        env.pop(name, None)
    assert not wire.servable(["reconstruct", "--help"]) and wire.servable(["reconstruct", "--", "--help"])
    code, out, err = dstereo(env, tmp_path, "reconstruct", "--help")
    assert code == 0 and "--calib" in out and err == ""
    time.sleep(0.5)  # a server would have written its log by now (the client creates it before starting one)
    assert not run_dir.exists() or os.listdir(run_dir) == []


def test_status_shows_memory_age_commands_and_what_differs():
    from dstereo.commands.serve import describe

    parts = dict(wire.key_parts(), **{"env:XLA_FLAGS": "--xla_cpu_max_isa=SSE4_2"})
    state = {"pid": 7, "since": time.time() - 300, "busy": False, "served": 2, "key": "other", "parts": parts,
             "rss": 600 * 2**20, "children_rss": 200 * 2**20, "idle_timeout": 900.0,
             "history": [{"command": "calibrate", "code": 0, "seconds": 3.5, "at": time.time() - 60},
                         {"command": "reconstruct", "code": 143, "seconds": 1.2, "at": time.time() - 30}]}
    text = describe("/run/serve.sock", state)
    assert "pid 7, up 5 min" in text and "memory 800 MiB" in text and "stops after 15 min" in text
    assert "2 command(s) served" in text and "calibrate  exit 0  3.50 s" in text and "reconstruct  exit 143" in text
    assert "NOT the same" in text and "XLA_FLAGS unset here, --xla_cpu_max_isa=SSE4_2 in the server" in text
    assert json.dumps(state)  # what the server sends is JSON as it is


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="children are listed from /proc")
def test_a_served_command_stuck_in_a_compile_ends_the_client_and_the_server(tmp_path, views):
    """A signal while the served command compiles (native code: no Python handler runs until it returns): after
    serve_server.STUCK_S the server tells the client the command's line and code and ends itself. Found by
    experiments/signal_stages.py: the server's exit there went through the os._exit a served command runs with
    (a stand-in that raises), and the server lived on, deadlocked on the client's stream, holding its socket's
    lock. A cold cache (its own JAX cache folder, no executables) makes the first solve a compile. Which way it
    goes depends on the machine; the exit itself is tested deterministically in tests/runtime/test_signals.py."""
    env = _env(tmp_path / "run", DSTEREO_JAX_CACHE=str(tmp_path / "jax"), DSTEREO_AOT="0")
    server = subprocess.Popen([sys.executable, "-c", ENTRY, "serve"], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    try:
        assert "ready" in server.stderr.readline()
        threading.Thread(target=server.stderr.read, daemon=True).start()
        work = tmp_path / "work"
        work.mkdir()
        # the splined lens's solver compiles for seconds (cold), past STUCK_S (0.9 s) on a loaded machine; where
        # the command stops within it the server survives instead, as it should (both are checked below)
        flags = ["--pattern", "9x6", "--square", "20", "--model", "splined", "--no-cache"]
        run = Run(["calibrate", "--images", views, *flags, "--out", "results"], work, env)
        run.wait_for(b"detect: 16/16 done")  # the full-set solve's compile starts now
        time.sleep(0.3)
        run.proc.send_signal(signal.SIGTERM)
        code = run.proc.wait(timeout=STARTUP_S)
        assert code == 143, b"".join(run.err).decode()
        assert run.err[-1].startswith(b"dstereo: error: interrupted (SIGTERM)"), b"".join(run.err).decode()
        try:  # the server: ended (the compile outlasted STUCK_S) or still serving (the command stopped in time)
            server.wait(timeout=END_S + 5)
        except subprocess.TimeoutExpired:
            assert _status(wire.socket_path(env)) is not None, "the server neither ended nor answers"
        assert os.listdir(work) == []
    finally:
        if server.poll() is None:
            dstereo(env, tmp_path, "serve", "--stop")
            server.wait(timeout=STARTUP_S)
