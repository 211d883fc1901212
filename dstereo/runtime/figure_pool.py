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
import threading
import types
from concurrent.futures import Future

_POOLS: list = []  # one single-worker ProcessPoolExecutor per started worker
_PENDING: list = []  # jobs handed to each and not finished
_LOCK = threading.Lock()


def _warm(parent: int = 0, death_signal: bool = False) -> None:
    """Worker initializer: tie the worker's life to its parent's (`_follow_parent`), then import matplotlib (Agg)
    and draw once, so the font cache is loaded before a job comes."""
    import io

    _follow_parent(parent, death_signal)

    import matplotlib

    matplotlib.use("Agg", force=True)  # as io.figures.pyplot: files only, forced (a worker starts fresh)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(1, 1))
    ax.set_title("x")
    fig.savefig(io.BytesIO(), format="png", dpi=20)
    plt.close(fig)
    # A worker's interpreter teardown (freeing matplotlib and numpy) cost ~0.1-0.2 s that the command's process
    # waited for when joining it, with nothing left to do: every job's result went back before the pool's stop
    # reached the worker. So a worker ends without it: atexit runs last-registered first, so this runs after
    # anything registered later and multiprocessing has already run its own exit handling by then.
    atexit.register(os._exit, 0)


def _follow_parent(parent: int, death_signal: bool) -> None:
    """A worker never outlives its parent (`kill -9` of a command or of the server must not leave it running,
    holding the caller's pipes): on Linux the kernel kills it when the parent thread that started it ends
    (PR_SET_PDEATHSIG; only asked when that thread is the parent's main thread, which lives as long as the
    process), and a thread checks every WATCH_S that the parent is still its parent, elsewhere or meanwhile.
    A terminal's Ctrl-C or hang-up reaches the whole process group: the parent handles it and ends the workers,
    so a worker ignores both (else each would print its own KeyboardInterrupt traceback on the caller's stderr)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    if death_signal and sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass
    if parent and os.getppid() != parent:  # the parent died before the death signal was set
        os._exit(1)
    if parent:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


WATCH_S = 0.5


def _watch_parent(parent: int) -> None:
    import time

    while os.getppid() == parent:
        time.sleep(WATCH_S)
    os._exit(1)


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


def start(now: int | None = None) -> None:
    """Start `now` of the workers (default: all, `workers_wanted`) now; `start_rest` starts the others. Idempotent;
    any failure leaves drawing in the calling process (or in the workers already started).

    A command starts one with itself and the others once JAX is imported (`start_rest`, before its solve): all
    started at once, they took a core from JAX's start-up while they imported matplotlib, and the single-threaded
    full-set solve then left a core idle (measured, new process on 2 cores: a plain calibration 1.50-1.55 ->
    1.33-1.37 s, rig640 C = 4845 3.42-3.68 -> 3.18-3.39 s). One single-worker pool per worker: a worker of its own
    can start at any time (a pool of two starts its second only when a job finds the first busy)."""
    wanted = workers_wanted() if now is None else min(now, workers_wanted())
    with _LOCK:
        while len(_POOLS) < wanted:
            pool = _new_worker()
            if pool is None:
                return
            _POOLS.append(pool)
            _PENDING.append(0)
            if len(_POOLS) == 1:
                atexit.register(stop)


def start_rest() -> None:
    """Start the workers `start(now=...)` left for later (none when figures are drawn in the calling process)."""
    if _POOLS:
        start()


def _new_worker():
    """A started single-worker pool, or None where processes cannot start here."""
    try:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # spawn starts the worker in this thread (the first submit below)
        main_thread = threading.current_thread() is threading.main_thread()
        pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_warm,
                                   initargs=(os.getpid(), main_thread))
        # spawn starts the worker at the first job, in this thread, and it would import the parent's main module
        # (the CLI: typer, pydantic, ~0.3-0.5 s): an empty stand-in for that moment, so it imports nothing.
        main = sys.modules["__main__"]
        sys.modules["__main__"] = types.ModuleType("__main__")
        try:
            pool.submit(_noop)
        finally:
            sys.modules["__main__"] = main
        return pool
    except Exception:  # noqa: BLE001 - no process support here: draw in the calling process
        return None


def started() -> int:
    """Workers started (0: figures are drawn in the calling process)."""
    return len(_POOLS)


def renew_broken() -> None:
    """A worker killed during a command leaves its pool broken (its figures were drawn in the caller instead):
    start new workers for the next command (the resident server) rather than draw in the caller from then on."""
    if any(getattr(pool, "_broken", False) for pool in _POOLS):
        count = len(_POOLS)
        stop()
        start(count)


def stop() -> None:
    with _LOCK:
        pools = list(_POOLS)
        _POOLS.clear()
        _PENDING.clear()
    for pool in pools:
        pool.shutdown(wait=True, cancel_futures=True)


def pids() -> list[int]:
    """The workers' process ids."""
    with _LOCK:
        pools = list(_POOLS)
    return [pid for pool in pools for pid in (getattr(pool, "_processes", None) or {})]


def kill() -> None:
    """End the workers now, their jobs unfinished (an interrupted command: nothing they draw is kept, and none may
    write into a folder after the command removed it). The server starts new ones for its next command."""
    with _LOCK:
        pools = list(_POOLS)
        _POOLS.clear()
        _PENDING.clear()
    for pool in pools:
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            try:
                process.kill()
            except (OSError, ValueError, AttributeError):
                pass
        try:
            pool.shutdown(wait=False, cancel_futures=True)
        except Exception:  # noqa: BLE001 - a broken pool: its processes are killed already
            pass


def _submit(fn, *args):
    """Hand a job to the worker with the fewest unfinished jobs; None when no worker takes it."""
    with _LOCK:
        if not _POOLS:
            return None
        i = min(range(len(_POOLS)), key=_PENDING.__getitem__)
        pool = _POOLS[i]
        _PENDING[i] += 1
    try:
        future = pool.submit(fn, *args)
    except Exception:  # noqa: BLE001 - the pool broke (a worker died)
        _done(pool)
        return None
    future.add_done_callback(lambda _f, p=pool: _done(p))
    return future


def _done(pool) -> None:
    with _LOCK:
        for i, p in enumerate(_POOLS):
            if p is pool:
                _PENDING[i] -= 1


class Figures:
    """Jobs of one results folder: `draw(fn, *args)` hands each to a worker (or runs it here), `wait()` returns
    once every file is written and raises the first job's error (the folder is then not kept)."""

    def __init__(self) -> None:
        self.jobs: list[tuple[Future | None, object, tuple]] = []

    def draw(self, fn, *args) -> None:
        future = _submit(_in_folder, os.getcwd(), fn, *args)
        if future is None:  # no worker, or its pool broke (a worker died): draw here
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
