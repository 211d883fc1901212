"""`dstereo serve` and the entry point's client: a served command gives the files, output and exit code of the
same command in its own process; every case the server cannot run exactly so runs in the client's process.

One server (a subprocess, its own runtime folder) serves the module. Each client is a new process through the
real entry point (dstereo.cli:main). Whether a command was served or ran in the client is read from the
server's own count of served commands, so a silent fallback cannot pass for a served run.
"""

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from dstereo.runtime import client as wire

ROOT = Path(__file__).resolve().parents[2]
ENTRY = "import sys; sys.argv[0] = 'dstereo'; from dstereo.cli import main; main(end_process=True)"
FLAGS = ["--pattern", "9x6", "--square", "20", "--model", "k1k2p1p2"]
STARTUP_S = 300  # generous: JAX and the figure workers import on a loaded 2-core machine; not a timed assertion
# Board poses (rvec, tvec mm) that keep the whole 9x6 board in a 640x480 view at 600-750 mm.
POSES = [(0.3, -0.2, 0.1, -110, -80, 650), (-0.25, 0.3, -0.1, -60, -50, 700), (0.1, 0.35, 0.2, -130, -20, 720),
         (-0.3, -0.25, 0.0, -40, -100, 680), (0.2, 0.1, -0.2, -90, -70, 600), (-0.1, -0.3, 0.15, -80, -40, 750)]


def _env(run_dir: Path, **extra) -> dict:
    env = dict(os.environ, DSTEREO_SERVE_DIR=str(run_dir), **extra)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.pop("DSTEREO_SERVE", None)
    return env


def dstereo(env: dict, cwd: Path, *args) -> tuple[int, str, str]:
    done = subprocess.run([sys.executable, "-c", ENTRY, *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=STARTUP_S)
    return done.returncode, done.stdout, done.stderr


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    import cv2

    from dstereo.models.camera import Camera
    from dstereo.synth import render_board
    from dstereo.synth.multiview import MULTIVIEW_BOARD, MULTIVIEW_OPTIONS

    folder = tmp_path_factory.mktemp("serve") / "images"
    folder.mkdir()
    cam = Camera.create(820.0, 820.0, 322.0, 238.0, (-0.1, 0.1), image_size=(640, 480))
    for i, pose in enumerate(POSES):
        image, _ = render_board(cam, np.array(pose, float), MULTIVIEW_BOARD, MULTIVIEW_OPTIONS, seed=i)
        cv2.imwrite(str(folder / f"view{i:02d}.png"), image)
    return folder


@pytest.fixture(scope="module")
def server(tmp_path_factory, images):
    """(env, socket path): a server started in the background, stopped (and checked to exit 0) at the end."""
    run_dir = tmp_path_factory.mktemp("run")
    env = _env(run_dir, DSTEREO_CACHE=str(images.parent / "cache"))
    proc = subprocess.Popen([sys.executable, "-c", ENTRY, "serve"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ready = proc.stderr.readline()  # "dstereo serve: ready at ..." once it listens
    if "ready" not in ready:
        proc.kill()
        pytest.fail(f"the server did not start: {ready}{proc.communicate()[1]}")
    threading.Thread(target=proc.stderr.read, daemon=True).start()  # keep its pipe from filling
    yield env, wire.socket_path(env)
    code, out, _ = dstereo(env, images.parent, "serve", "--stop")
    assert code == 0 and "stopped" in out
    assert proc.wait(timeout=STARTUP_S) == 0
    assert not os.path.exists(wire.socket_path(env))


def served(path: str) -> int:
    from dstereo.commands.serve import ask

    return ask(path, "status")["served"]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _without_timings(stdout: str) -> str:
    return "\n".join(line for line in stdout.splitlines() if not line.startswith("timings:"))


@pytest.mark.slow
def test_served_calibration_writes_the_files_of_a_run_in_its_own_process(server, images, tmp_path):
    """A calibration with subsets (`--per-set 5`: 6 subsets of the 6 views) in its own process, served by a cold
    server, and served again: the same output, code and files. One run covers the plain calibration too: a run
    with subsets writes every file of a run without them (the full-set solve, camera.yml, its plots, report and
    summary; measured: the plain run's 17 files are all among the subset run's 39) and adds the subsets',
    so the former `plain` case (a second set of three runs) checked nothing this one does not."""
    env, path = server
    extra = ["--per-set", "5"]
    runs = {}
    for name, run_env in (("here", {"DSTEREO_SERVE": "0"}), ("served", {}), ("served again", {})):
        cwd = tmp_path / name.replace(" ", "_")
        cwd.mkdir()
        before = served(path)
        # relative paths: the server must resolve them in the client's folder, its figure workers too
        runs[name] = dstereo({**env, **run_env}, cwd, "calibrate", "--images", os.path.relpath(images, cwd), *FLAGS,
                             *extra, "--out", "results")
        assert served(path) - before == (0 if name == "here" else 1), name
        assert runs[name][0] == 0, runs[name][2]
        runs[name] += (_files(cwd / "results"),)
    code, out, err, files = runs["here"]
    assert "camera.yml" in files and any(name.startswith("plots/") for name in files)
    assert "subsets.csv" in files and "plots/fx.png" in files  # the subsets did run (and their figures)
    for name in ("served", "served again"):
        s_code, s_out, s_err, s_files = runs[name]
        assert _without_timings(s_out) == _without_timings(out) and s_err == err, name
        assert sorted(s_files) == sorted(files), name
        # Every file byte for byte, but summary.json's stage timings (the only run-dependent field found).
        differ = [f for f in files if s_files[f] != files[f]]
        assert differ in ([], ["summary.json"]), (name, differ)
        a, b = json.loads(s_files["summary.json"]), json.loads(files["summary.json"])
        assert a.pop("timings").keys() == b.pop("timings").keys() and a == b, name


def test_bad_input_through_the_server_is_the_same_one_line_error(server, images, tmp_path):
    env, path = server
    args = ["calibrate", "--images", "absent", *FLAGS, "--out", "results"]
    before = served(path)
    got = dstereo(env, tmp_path, *args)
    assert served(path) == before + 1
    assert got == dstereo({**env, "DSTEREO_SERVE": "0"}, tmp_path, *args)
    code, out, err = got
    assert code == 1 and out == "" and len(err.splitlines()) == 1 and err.startswith("dstereo: error: ")
    assert "absent" in err and not (tmp_path / "results").exists()


def test_a_crash_in_a_command_ends_that_command_not_the_server(server, tmp_path):
    env = {**server[0], "DSTEREO_DEBUG": "1"}  # the CLI re-raises a file system error: an uncaught traceback
    (tmp_path / "a_file").write_text("")
    before = served(server[1])
    code, out, err = dstereo(env, tmp_path, "init", "a_file/project")
    here = dstereo({**env, "DSTEREO_SERVE": "0"}, tmp_path, "init", "a_file/project")
    assert served(server[1]) == before + 1
    assert code == here[0] == 1 and "Traceback" in err and err.splitlines()[-1] == here[2].splitlines()[-1]
    assert dstereo(server[0], tmp_path, "init", "project")[0] == 0 and served(server[1]) == before + 2
    assert (tmp_path / "project" / "dstereo.toml").is_file()


def test_a_malformed_request_ends_its_connection_not_the_server(server):
    env, path = server
    before = served(path)
    with wire.connect(path) as sock:  # the right key, but none of the request's streams, folder or environment
        wire.send(sock, b"q", json.dumps({"op": "run", "key": wire.code_key(env), "argv": ["init", "x"]}).encode())
        sock.settimeout(STARTUP_S)
        assert wire.receive(sock)[0] == b"a" and wire.receive(sock) is None
    assert served(path) == before + 1  # answered, counted, and still serving


def test_other_code_or_settings_run_in_the_client_with_a_note(server, tmp_path):
    env, path = server
    before = served(path)
    code, out, err = dstereo({**env, "DSTEREO_JAX_CACHE": str(tmp_path / "jax")}, tmp_path, "init", "project")
    assert code == 0 and (tmp_path / "project" / "dstereo.toml").is_file() and served(path) == before
    assert err.startswith("dstereo: note: ") and "other dstereo code" in err and len(err.splitlines()) == 1


def test_disabled_or_absent_server_runs_in_the_client_silently(server, tmp_path):
    env, path = server
    before = served(path)
    code, out, err = dstereo({**env, "DSTEREO_SERVE": "0"}, tmp_path, "init", "a")
    assert code == 0 and err == "" and (tmp_path / "a" / "dstereo.toml").is_file() and served(path) == before
    code, out, err = dstereo(_env(tmp_path / "no_server"), tmp_path, "init", "b")
    assert code == 0 and err == "" and (tmp_path / "b" / "dstereo.toml").is_file()


def test_a_stale_socket_runs_in_the_client_with_a_note(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir(mode=0o700)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(wire.socket_path(_env(run_dir)))
    stale.close()  # the file stays, nobody listens: a server killed without cleaning up
    code, out, err = dstereo(_env(run_dir), tmp_path, "init", "project")
    assert code == 0 and (tmp_path / "project" / "dstereo.toml").is_file()
    assert err.startswith("dstereo: note: ") and "stale" in err and len(err.splitlines()) == 1


def _fake_server(run_dir: Path, frames: list[tuple[bytes, bytes]]) -> threading.Thread:
    """A socket that answers one client with `frames`, then closes: a server busy, or one that dies mid-command."""
    run_dir.mkdir(mode=0o700)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(wire.socket_path(_env(run_dir)))
    listener.listen(1)

    def answer():
        conn, _ = listener.accept()
        with conn, listener:
            assert wire.receive(conn)[0] == b"q"
            for kind, payload in frames:
                wire.send(conn, kind, payload)

    worker = threading.Thread(target=answer, daemon=True)
    worker.start()
    return worker


def test_a_busy_server_leaves_the_command_to_the_client_silently(tmp_path):
    worker = _fake_server(tmp_path / "run", [(b"b", b"")])
    code, out, err = dstereo(_env(tmp_path / "run"), tmp_path, "init", "project")
    worker.join(timeout=STARTUP_S)
    assert code == 0 and err == "" and (tmp_path / "project" / "dstereo.toml").is_file()


def test_a_server_dying_mid_command_ends_the_client_with_one_error_line(tmp_path):
    worker = _fake_server(tmp_path / "run", [(b"a", b""), (b"o", b"half of it\n")])
    code, out, err = dstereo(_env(tmp_path / "run"), tmp_path, "init", "project")
    worker.join(timeout=STARTUP_S)
    assert code == 1 and out == "half of it\n" and not (tmp_path / "project").exists()
    assert err.startswith("dstereo: error: the background server ended during this command") and "its log: " in err \
        and len(err.splitlines()) == 1


def test_the_client_imports_nothing_heavy_when_served(server, tmp_path):
    env, path = server
    before = served(path)
    probe = ("import sys\nfrom dstereo.runtime.client import try_served\ncode = try_served(['init', 'project'])\n"
             "print(code, *[m for m in ('numpy', 'jax', 'typer', 'click', 'cv2') if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=STARTUP_S)
    assert done.stdout.splitlines()[-1].split() == ["0"], done.stdout + done.stderr  # served: exit 0, none loaded
    assert served(path) == before + 1 and (tmp_path / "project" / "dstereo.toml").is_file()


# --- the server's answers, without a process ----------------------------------------------------------------

def _greeted(server, request: dict) -> bytes:
    ours, theirs = socket.socketpair()
    with ours:
        worker = threading.Thread(target=server._greet, args=(theirs,))
        worker.start()
        wire.send(ours, b"q", json.dumps(request).encode())
        kind = wire.receive(ours)[0]
        worker.join()
    return kind


def test_the_server_answers_busy_mismatch_or_accepts(tmp_path):
    from dstereo.runtime.server import Server

    s = Server(str(tmp_path / "serve.sock"))
    request = {"op": "run", "key": s.key, "argv": ["init", "x"]}
    assert _greeted(s, {**request, "key": "other"}) == b"m"
    assert _greeted(s, {**request, "argv": ["demo"]}) == b"b"
    assert _greeted(s, request) == b"a" and s.busy and s.requests.qsize() == 1
    assert _greeted(s, request) == b"b" and s.requests.qsize() == 1  # one command at a time: the second runs itself


def test_the_code_key_follows_the_source_and_the_startup_settings(tmp_path):
    import shutil

    package = tmp_path / "dstereo"
    shutil.copytree(Path(wire.__file__).parents[1], package, ignore=shutil.ignore_patterns("__pycache__"))
    env = {"HOME": "/h", "DSTEREO_DEBUG": "1"}
    key = wire.code_key(env, str(package))
    assert wire.code_key({**env, "DSTEREO_DEBUG": "0"}, str(package)) == key  # read per command: sent, not keyed
    assert wire.code_key({**env, "XLA_FLAGS": "--xla_cpu_max_isa=SSE4_2"}, str(package)) != key
    (package / "errors.py").write_text((package / "errors.py").read_text() + "\n# changed\n")
    assert wire.code_key(env, str(package)) != key


def _run_in_server(monkeypatch, tmp_path, command) -> tuple[int, str, str]:
    """runtime.request.run_request with `command` standing in for dstereo.cli.main; (code, stdout, stderr)."""
    from dstereo.runtime import request as serve_request
    from dstereo.runtime.request import client_stream, run_request

    monkeypatch.setattr(serve_request, "_COMMAND", [command])
    ours, theirs = socket.socketpair()
    lock, traits = threading.Lock(), {"tty": False, "encoding": "utf-8"}
    request = {"cwd": str(tmp_path), "env": {"ONLY_THIS": "1"}, "argv0": "dstereo", "argv": ["init", "x"]}
    with ours, theirs:
        code = run_request(request, client_stream(theirs, b"o", traits, lock, False),
                           client_stream(theirs, b"e", traits, lock, True))
        theirs.shutdown(socket.SHUT_WR)
        streams = {b"o": b"", b"e": b""}
        while (frame := wire.receive(ours)) is not None:
            streams[frame[0]] += frame[1]
    return code, streams[b"o"].decode(), streams[b"e"].decode()


def test_a_request_runs_in_the_clients_folder_environment_and_argv_and_puts_them_back(monkeypatch, tmp_path):
    cwd, env, argv, exit_ = os.getcwd(), dict(os.environ), list(sys.argv), os._exit

    def command():
        print(os.getcwd(), sorted(os.environ), sys.argv)
        print("to stderr", file=sys.stderr)
        os._exit(3)  # a CLI that ends with os._exit: in the server it ends the command only

    code, out, err = _run_in_server(monkeypatch, tmp_path, command)
    assert (code, out, err) == (3, f"{tmp_path} ['ONLY_THIS'] ['dstereo', 'init', 'x']\n", "to stderr\n")
    assert (os.getcwd(), dict(os.environ), sys.argv, os._exit) == (cwd, env, argv, exit_)


def test_a_request_exits_as_the_interpreter_would(monkeypatch, tmp_path):
    def crash():
        raise RuntimeError("boom")

    code, out, err = _run_in_server(monkeypatch, tmp_path, crash)
    assert code == 1 and err.startswith("Traceback") and err.endswith("RuntimeError: boom\n")
    assert _run_in_server(monkeypatch, tmp_path, lambda: sys.exit("a message"))[::2] == (1, "a message\n")
    assert _run_in_server(monkeypatch, tmp_path, lambda: sys.exit(2))[0] == 2
    assert _run_in_server(monkeypatch, tmp_path, lambda: None)[0] == 0
