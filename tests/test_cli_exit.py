"""The `dstereo` command ends its own process once its work is done (cli.finish: os._exit, no interpreter
teardown), with its output flushed and its exit code; library use and pytest get SystemExit as before."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dstereo import cli

ROOT = Path(__file__).resolve().parents[1]
# The command as `python -m dstereo.cli` runs it, plus an atexit handler: it prints only if the interpreter's
# normal teardown runs.
AS_COMMAND = ("import atexit, runpy, sys\natexit.register(lambda: print('TEARDOWN', flush=True))\n"
              "sys.argv = ['dstereo', *sys.argv[1:]]\n"
              "runpy.run_module('dstereo.cli', run_name='__main__', alter_sys=True)")


def _run(code: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=120)


def test_library_use_gets_system_exit(monkeypatch):
    def refused(code):
        raise AssertionError(f"os._exit({code}) called in library use")

    monkeypatch.setattr(os, "_exit", refused)
    monkeypatch.setattr(sys, "argv", ["dstereo", "calibrate", "--help"])
    assert not cli._command_process()  # under pytest
    with pytest.raises(SystemExit) as exc:
        cli.main()
    assert exc.value.code == 0


def test_the_command_process_ends_itself_with_its_output_and_code():
    done = _run(AS_COMMAND, "calibrate", "--help")
    assert done.returncode == 0, done.stderr
    assert "--per-set" in done.stdout  # the help text came out (flushed before the process ended)
    assert "TEARDOWN" not in done.stdout  # ended by finish: no interpreter teardown
    bad = _run(AS_COMMAND, "calibrate", "--images", str(ROOT / "no-such-folder"), "--pattern", "9x6")
    assert bad.returncode == 1 and "TEARDOWN" not in bad.stdout
    # bad input: still its one line (written before the process ended)
    assert bad.stderr.startswith("dstereo: error: images:") and bad.stderr.count("\n") == 1, bad.stderr


def test_a_plain_python_caller_keeps_its_teardown():
    """`python -c` that calls main itself is library use: SystemExit, its own atexit handlers run."""
    code = ("import atexit, sys\natexit.register(lambda: print('TEARDOWN', flush=True))\nfrom dstereo.cli import main\n"
            "sys.argv = ['dstereo', 'calibrate', '--help']\nmain()")
    done = _run(code)
    assert done.returncode == 0 and "TEARDOWN" in done.stdout, done.stderr
