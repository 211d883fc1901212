"""Figures drawn in worker processes while the caller writes the rest of the results folder.

matplotlib draws one figure in ~0.1-0.2 s of pure Python (text layout, Agg, PNG); a results folder has 10-20 of
them. The workers are started at the beginning of a command (`start`), so their imports (numpy, matplotlib, its
font cache) overlap JAX's start-up and the solve, and at writing time they draw side by side with the parent
(CSV, statistics, images). They are spawned, not forked: a fork of a process that runs JAX's thread pools can
deadlock. A job is a function of `dstereo.io` plus small picklable data (numpy arrays, no JAX objects), so a
worker never imports JAX. Without started workers (library use, tests, DSTEREO_FIGURE_WORKERS=0) or when the
workers cannot start or die, the same functions run in the calling process: the files are the same either way.
"""

from __future__ import annotations

import atexit
import os
import sys
import types
from concurrent.futures import Future

_POOL = None  # the started ProcessPoolExecutor, or None


def _warm() -> None:
    """Worker initializer: import matplotlib (Agg) and draw once, so the font cache is loaded before a job comes."""
    import io

    from dstereo.io.figures import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(1, 1))
    ax.set_title("x")
    fig.savefig(io.BytesIO(), format="png", dpi=20)
    plt.close(fig)
    # A worker's interpreter teardown (freeing matplotlib and numpy) cost ~0.1-0.2 s that the command's process
    # waited for when joining it, with nothing left to do: every job's result went back before the pool's stop
    # reached the worker. So a worker ends without it: atexit runs last-registered first, so this runs after
    # anything registered later and multiprocessing has already run its own exit handling by then.
    atexit.register(os._exit, 0)


def _noop() -> None:
    return None


def _in_folder(cwd: str, fn, *args) -> None:
    """Run a job in the caller's working folder: its paths may be relative, and a worker outlives a command (the
    resident `dstereo serve` runs each command in its client's folder; its workers started in the server's)."""
    if os.getcwd() != cwd:
        os.chdir(cwd)
    fn(*args)


def workers_wanted() -> int:
    """DSTEREO_FIGURE_WORKERS (0: draw in the calling process), else 2 (at most one per core). Measured on 2 shared
    cores, new process, warm compile cache: at load ~3 the plain run 2.9-3.0 s with two workers vs 3.4-3.5 s
    without (writing 0.6-0.7 vs 1.1 s) and C=4845 6.6-6.7 vs 7.3-9.8 s (writing 1.2-1.4 vs 2.2-2.5 s); at load
    8-10, no core free, the plain run was slower with them (a worker's start costs ~0.3-0.5 s of CPU)."""
    setting = os.environ.get("DSTEREO_FIGURE_WORKERS", "")
    try:
        return max(0, int(setting)) if setting else min(2, os.cpu_count() or 1)
    except ValueError:
        return 0


def start() -> None:
    """Start the workers now (idempotent); any failure leaves drawing in the calling process."""
    global _POOL
    if _POOL is not None or workers_wanted() == 0:
        return
    try:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(workers_wanted(), mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_warm)
        # spawn launches a process per job submitted while none is idle (up to the pool's size), in this thread;
        # each would import the parent's main module (the CLI: typer, pydantic, ~0.3-0.5 s): an empty stand-in
        # for that moment, so it imports nothing. One job per worker, so that all start now, under the stand-in
        # (one job started one worker; the second started at the first figure, importing the CLI).
        main = sys.modules["__main__"]
        sys.modules["__main__"] = types.ModuleType("__main__")
        try:
            for _ in range(workers_wanted()):
                pool.submit(_noop)
        finally:
            sys.modules["__main__"] = main
    except Exception:  # noqa: BLE001 - no process support here: draw in the calling process
        return
    _POOL = pool
    atexit.register(stop)


def stop() -> None:
    global _POOL
    pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


class Figures:
    """Jobs of one results folder: `draw(fn, *args)` hands each to a worker (or runs it here), `wait()` returns
    once every file is written and raises the first job's error (the folder is then not kept)."""

    def __init__(self) -> None:
        self.jobs: list[tuple[Future | None, object, tuple]] = []

    def draw(self, fn, *args) -> None:
        future = None
        if _POOL is not None:
            try:
                future = _POOL.submit(_in_folder, os.getcwd(), fn, *args)
            except Exception:  # noqa: BLE001 - the pool broke (a worker died): draw here
                future = None
        if future is None:
            fn(*args)
        self.jobs.append((future, fn, args))

    def wait(self) -> None:
        from concurrent.futures.process import BrokenProcessPool

        jobs, self.jobs = self.jobs, []
        for future, fn, args in jobs:
            if future is None:
                continue
            try:
                future.result()
            except BrokenProcessPool:  # a worker was killed (memory?): the figure is drawn here instead
                fn(*args)
