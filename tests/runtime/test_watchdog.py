"""A compiled call that stops making progress ends the command (dstereo/runtime/watchdog.py): one line, exit 1, no child
process left, nothing written. The hang is made by hand: the solver's compiled function is wrapped so that one
call of an already-seen shape never returns (as the two concurrent LAPACK calls of issue 28 never did)."""

import os
import sys
import time

import pytest

from test_signals import START_S, SUBSET_FLAGS, Run, alive, env_for, render_views

from dstereo.runtime import watchdog
from dstereo.errors import DstereoError
from dstereo.runtime.interrupts import children

# The third call of a shape sleeps for an hour; the earlier two of it finished, so its allowance is the
# test's 3 x their longest (at least 1 s), not the first call's.
HANG = """
import collections, sys, time
sys.argv[0] = 'dstereo'
import dstereo.calib.problem as problem
real, seen = problem.compiled_solver, collections.Counter()
def hanging(p, key):
    fn = real(p, key)
    def call(*args):
        shape = args[2].shape
        seen[shape] += 1
        if seen[shape] == 3:
            time.sleep(3600)
        return fn(*args)
    return call
problem.compiled_solver = hanging
from dstereo.cli import main
main(end_process=True)
"""


def test_the_allowance_is_the_first_calls_or_a_multiple_of_the_longest_finished_one():
    chosen = (2.0, 10.0, 50.0)
    key = ("test", object())
    assert watchdog.allowance(key, chosen) == 50.0  # nothing finished: the first call compiles or loads
    watchdog._longest[key] = 0.05
    assert watchdog.allowance(key, chosen) == 2.0  # never under the floor
    watchdog._longest[key] = 1.0
    assert watchdog.allowance(key, chosen) == 10.0
    assert watchdog.settings({"DSTEREO_WATCHDOG": "0"}) is None
    assert watchdog.settings({"DSTEREO_WATCHDOG": "5,4"}) == (5.0, 4.0, watchdog.FIRST_S)
    assert watchdog.settings({}) == (watchdog.FLOOR_S, watchdog.FACTOR, watchdog.FIRST_S)
    with pytest.raises(DstereoError, match="DSTEREO_WATCHDOG"):
        watchdog.settings({"DSTEREO_WATCHDOG": "soon"})


def test_a_finished_call_is_timed_and_a_watched_block_passes_its_result():
    key = ("timed", object())
    with watchdog.watched(key, "a test block"):
        time.sleep(0.05)
    assert 0.05 <= watchdog._longest[key] < 5.0 and not watchdog._running


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="children are listed from /proc")
def test_a_call_that_never_returns_ends_the_command_with_one_line(tmp_path):
    views = render_views(tmp_path / "images", 16)
    work = tmp_path / "work"
    work.mkdir()
    run = Run(["calibrate", "--images", views, *SUBSET_FLAGS, "--out", "results"], work,
              env_for(DSTEREO_SERVE="0", DSTEREO_WATCHDOG="1,3,60"), entry=HANG)
    try:
        run.wait_for(b"full-set solve: 1/1 done")
        kids = children(run.proc.pid)
        code = run.proc.wait(timeout=START_S)
        assert run.closed_within(5.0), "a process left behind holds the caller's pipes"
    finally:
        if run.proc.poll() is None:
            run.proc.kill()
    err = b"".join(run.err).decode()
    assert code == 1, err
    assert run.err[-1].startswith(b"dstereo: error: the compiled solver made no progress on a chunk of "), err
    assert b"nothing was written" in run.err[-1] and "Traceback" not in err
    assert [k for k in kids if alive(k)] == []
    assert os.listdir(work) == []  # no results folder, no staging folder
