"""Independent per-frame tasks run in this process, on a local Dask cluster or on an existing one.

One code path: `FrameRunner(workers=1)` calls the task frame after frame here (Dask is not even imported);
`workers=N` starts a `distributed.LocalCluster` of N processes with one thread each; `scheduler=ADDRESS` uses a
running cluster. Results come back as they finish (`as_completed`) and are handed to `on_done` in this process,
which stores them (a cluster's workers need not share a disk with the client for that).

A worker process that dies (killed, out of memory) has its task rerun elsewhere up to `retries` times (the
scheduler's `allowed-failures`; on an external cluster its own setting holds); then the task is reported as
failed with the reason, never dropped.
"""

from __future__ import annotations

import os
import re
import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable

# Default (`workers=None`): the first task runs here and is timed; a local cluster is started for the rest only
# when they would take longer serially than PAYOFF_S. Measured (experiments/bench_frames.py, since removed; 2 cores):
# starting the cluster plus each worker's first frame costs about 10 s, 2 workers then run 1.57x the serial rate,
# so parallel wins once the serial remainder exceeds 10 / (1 - 1 / 1.57) = 27.5 s; rounded up. Re-measured after
# the per-frame work was cut to ~0.37 s CPU (load 9-11): the start still ~10 s, the steady
# rate 1.04-1.26x by wall time on that load and 1.73x from the CPU times (2 cores to themselves).
CLUSTER_START_S = 10.0
PAYOFF_S = 30.0

NOTE_EVERY_S = 30.0  # a line with the per-frame time and the rate at most this often (and after the first frame)

# Each worker runs one frame at a time on one core: XLA's and OpenCV's own thread pools would otherwise fight
# over the cores the other workers use (N workers x N threads on N cores).
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                     "DSTEREO_WORKER_THREADS": "1"}
XLA_SINGLE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


# A local cluster of far more worker processes than cores runs no faster and can exhaust the machine: 100000 asked
# for made no progress in 300 s while the nannies kept starting (4 GB, 19,999 open files). Refused above
# WORKERS_PER_CORE x os.cpu_count(), and above what the open-file limit allows: each local worker holds
# FILES_PER_WORKER descriptors in this process (measured: 24 open for 1 worker, 51 for 4, i.e. ~15 + 9 each).
WORKERS_PER_CORE = 4
FILES_PER_WORKER = 10
FILES_RESERVED = 64  # this process's own: images, the results folder, JAX's and OpenCV's

# Dask's address forms: [scheme://]host[:port], host a name, an IPv4 address or a bracketed IPv6 address.
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx", "inproc")
_ADDRESS = re.compile(r"^(?:(?P<scheme>[a-z]+)://)?(?P<host>[A-Za-z0-9][A-Za-z0-9._-]*|\[[0-9A-Fa-f:.]+\])"
                      r"(?::(?P<port>\d{1,5}))?/?$")


def check_workers(workers: int) -> None:
    """Refuse a local cluster larger than the machine can hold (WORKERS_PER_CORE, the open-file limit)."""
    import resource

    from dstereo.errors import DstereoError

    cores = os.cpu_count() or 1
    if workers > WORKERS_PER_CORE * cores:
        raise DstereoError(f"`workers` {workers}: at most {WORKERS_PER_CORE * cores} ({WORKERS_PER_CORE} x the "
                           f"{cores} cores here; more processes than that run no faster); for more, start a Dask "
                           "cluster and give its address with `scheduler`")
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    if soft != resource.RLIM_INFINITY and workers * FILES_PER_WORKER + FILES_RESERVED > soft:
        most = max((soft - FILES_RESERVED) // FILES_PER_WORKER, 1)
        raise DstereoError(f"`workers` {workers}: the open-file limit ({soft}, `ulimit -n`) allows at most {most} "
                           f"local workers (~{FILES_PER_WORKER} files each); give fewer or raise the limit")


def check_scheduler(address: str) -> None:
    """Refuse an address Dask cannot parse, before any work (Dask's own error is a traceback)."""
    from dstereo.errors import DstereoError

    m = _ADDRESS.match(address.strip())
    port = m and m.group("port")
    if m is None or (m.group("scheme") or "tcp") not in SCHEDULER_SCHEMES or (port and not 0 < int(port) < 65536):
        raise DstereoError(f"`scheduler` {address!r}: not a Dask scheduler address; write tcp://HOST:PORT (e.g. "
                           f"tcp://10.0.0.5:8786, schemes {', '.join(SCHEDULER_SCHEMES)}), as `dask scheduler` "
                           "prints it")


# Dask's statistical profiler samples every worker thread's stack every 10 ms: measured on a 640x480 frame, the
# worker process spent 0.62 s CPU of which the frame's own thread 0.50 s (one frame at a time here: 0.50 s). Off.
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}


@dataclass
class TaskDone:
    """One finished task: its index, value (None when it failed), why it failed ('' if it did not), its time on
    the worker (s), the worker process's peak resident memory so far (MB), the worker, and the CPU time its
    process spent on it (s: user + system of every thread; on a loaded machine the wall time also holds the
    waits for a core, the CPU time much less)."""

    index: int
    value: Any
    failed: str
    seconds: float
    peak_rss_mb: float
    worker: str
    cpu_seconds: float = float("nan")


def worker_env() -> dict:
    """Environment of local worker processes: one thread each, and the same JAX compilation cache as this
    process (dstereo enables it on import from DSTEREO_JAX_CACHE), so a worker loads compiled code instead of
    compiling it again."""
    import jax

    env = dict(SINGLE_THREAD_ENV)
    env["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + XLA_SINGLE_THREAD).strip()
    cache = jax.config.jax_compilation_cache_dir
    env["DSTEREO_JAX_CACHE"] = cache if cache else os.environ.get("DSTEREO_JAX_CACHE", "0")
    return env


def _timed(fn: Callable, arg):
    """Runs on the worker: the task's value, its wall time, this process's peak memory, its name and the CPU
    time the task took."""
    import socket

    if os.environ.get("DSTEREO_WORKER_THREADS") == "1":
        import cv2
        import jax

        cv2.setNumThreads(1)
        # A frame compiles many small functions (each under the 0.5 s dstereo caches by default, together
        # seconds): a worker caches them all, so the next run's workers start warm.
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    start, cpu = time.perf_counter(), time.process_time()
    value = fn(arg)
    return (value, time.perf_counter() - start, _peak_rss_mb(), f"{socket.gethostname()}:{os.getpid()}",
            time.process_time() - cpu)


def _task_fields(timed: tuple) -> tuple:
    """TaskDone's fields after the index from what `_timed` returned (a finished task: failed is '')."""
    value, seconds, rss, worker, cpu = timed
    return value, "", seconds, rss, worker, cpu


def _peak_rss_mb() -> float:
    """This process's peak resident memory: VmHWM (ru_maxrss of a spawned process can carry its parent's)."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class FrameRunner:
    """Where the frames run (module docstring). `workers=None` (auto): the machine's cores when the remaining
    frames pay for starting a cluster (PAYOFF_S, judged from the first frame's time here), else serial here."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None, retries: int = 2):
        from dstereo.errors import DstereoError

        if workers is not None and workers < 1:
            raise DstereoError(f"`workers` {workers}: need 1 or more (1 runs the frames one after another here)")
        if retries < 0:
            raise DstereoError(f"retries {retries}: need 0 or more")
        if scheduler is not None:
            check_scheduler(scheduler)
        elif workers is not None:
            check_workers(workers)
        self.auto = workers is None and scheduler is None
        self.workers = workers or os.cpu_count() or 1
        self.scheduler, self.retries = scheduler, retries
        self.decision = ""  # auto: why the frames ran where they did
        self.times: list[float] = []
        self.cpu_times: list[float] = []
        self.peak_rss_mb: dict[str, float] = {}

    @property
    def parallel(self) -> bool:
        return self.scheduler is not None or self.workers > 1

    def describe(self) -> dict:
        """What ran where, for summary['run'] (times and memory as measured)."""
        return {"mode": "dask scheduler " + self.scheduler if self.scheduler else
                ("local dask cluster" if self.workers > 1 else "serial, in process"),
                "decision": self.decision or None,
                "workers": None if self.scheduler else self.workers,
                "retries_after_worker_death": self.retries if self.parallel else None,
                "frames_timed": len(self.times),
                "seconds_per_frame_median": statistics.median(self.times) if self.times else None,
                "cpu_seconds_per_frame_median": statistics.median(self.cpu_times) if self.cpu_times else None,
                "worker_peak_rss_mb": {k: round(v, 1) for k, v in sorted(self.peak_rss_mb.items())}}

    def map(self, fn: Callable, items: list[tuple[int, Any]], on_done: Callable[[TaskDone], None],
            progress=None, stage: str = "frames", done: int = 0, total: int | None = None) -> None:
        """fn(arg) for every (index, arg); on_done(TaskDone) here, in finishing order. `done`/`total`: the
        progress count before these tasks and in all."""
        from dstereo.runtime.blas_threads import one_blas_thread

        total = done + len(items) if total is None else total
        ticker = _Ticker(progress, stage, done, total, self)
        if not items:
            return
        if self.auto and self.workers > 1:
            with one_blas_thread():
                items = self._auto_first(fn, items, on_done, ticker)
        if not items:
            return
        if not self.parallel:
            with one_blas_thread():  # one frame at a time here: BLAS as on a worker (`blas_threads`)
                for index, arg in items:
                    self._record(TaskDone(index, *_task_fields(_timed(fn, arg))), on_done, ticker)
            return
        self._map_dask(fn, items, on_done, ticker)

    def _auto_first(self, fn, items, on_done, ticker) -> list:
        """Run the first task here, timed; keep the rest here too when they would not pay for a cluster."""
        index, arg = items[0]
        task = TaskDone(index, *_task_fields(_timed(fn, arg)))
        seconds = task.seconds
        self._record(task, on_done, ticker)
        rest = items[1:]
        serial_s = seconds * len(rest)
        if serial_s < PAYOFF_S:
            self.workers = 1
            self.decision = (f"auto: serial here; {len(rest)} more frame(s) x {seconds:.2f} s = {serial_s:.1f} s, "
                             f"below the ~{PAYOFF_S:.0f} s a local cluster needs to pay for its ~{CLUSTER_START_S:.0f} s "
                             "start (--workers N forces one)")
        else:
            self.decision = (f"auto: local cluster of {self.workers}; {len(rest)} more frame(s) x {seconds:.2f} s = "
                             f"{serial_s:.1f} s serially (first frame timed here)")
        return rest

    def _record(self, task: TaskDone, on_done, ticker) -> None:
        if not task.failed:
            self.times.append(task.seconds)
            self.cpu_times.append(task.cpu_seconds)
            self.peak_rss_mb[task.worker] = max(task.peak_rss_mb, self.peak_rss_mb.get(task.worker, 0.0))
        on_done(task)
        ticker.tick(task)

    def _map_dask(self, fn, items, on_done, ticker) -> None:
        import logging

        import dask
        from distributed import Client, LocalCluster, as_completed
        from distributed.scheduler import KilledWorker

        from dstereo.errors import DstereoError

        cluster = client = None
        # Dask's workers default to MALLOC_TRIM_THRESHOLD_=65536, which (fixing glibc's thresholds) made a frame
        # 2.5x slower here (1.48 against 0.59 s at 320x240, in one process): the frames allocate many large
        # temporaries. Keep its one-thread settings only.
        spawn_env = {k: v for k, v in SINGLE_THREAD_ENV.items() if k != "DSTEREO_WORKER_THREADS"}
        with dask.config.set({"distributed.scheduler.allowed-failures": self.retries,
                              "distributed.nanny.pre-spawn-environ": spawn_env, **WORKER_CONFIG}):
            try:
                if self.scheduler is not None:
                    try:
                        client = Client(self.scheduler, timeout="20s")
                    except OSError as exc:
                        raise DstereoError(f"`scheduler` {self.scheduler}: no Dask scheduler answers there ({exc}); "
                                           "start one with `dask scheduler` and workers with `dask worker "
                                           "ADDRESS`, or drop `scheduler` to use this machine") from exc
                else:
                    cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=logging.ERROR, env=worker_env())
                    client = Client(cluster)
                futures = {}
                for index, arg in items:
                    fut = client.submit(_timed, fn, arg, pure=False, key=f"dstereo-frame-{index}-{os.getpid()}")
                    futures[fut.key] = (index, fut)
                for fut in as_completed([f for _, f in futures.values()]):
                    index = futures[fut.key][0]
                    try:
                        task = TaskDone(index, *_task_fields(fut.result()))
                    except KilledWorker:
                        task = TaskDone(index, None, f"the worker processes holding it died {self.retries + 1} "
                                        "time(s) (killed or out of memory; see the workers' logs); the frame "
                                        "is not in the results; --resume tries it again", float("nan"),
                                        float("nan"), "")
                    fut.release()
                    self._record(task, on_done, ticker)
            finally:
                if client is not None:
                    client.close()
                if cluster is not None:
                    cluster.close()


class _Ticker:
    """progress(stage, done, total) per finished task, and now and then a note with the per-frame time."""

    def __init__(self, progress, stage, done, total, runner):
        self.progress, self.stage, self.done, self.total, self.runner = progress, stage, done, total, runner
        self.start, self.last_note, self.finished = time.perf_counter(), None, 0

    def tick(self, task: TaskDone) -> None:
        self.done += 1
        self.finished += 1
        if self.progress is None:
            return
        self.progress(self.stage, self.done, self.total)
        now = time.perf_counter()
        note = getattr(self.progress, "note", None)
        if note is None or not self.runner.times:
            return
        if self.last_note is None or now - self.last_note >= NOTE_EVERY_S or self.done == self.total:
            self.last_note = now
            msg = (f"{self.stage}: {self.done}/{self.total}, {statistics.median(self.runner.times):.2f} s per frame "
                   f"on a worker (median), {self.finished / (now - self.start):.2f} frames/s")
            eta = eta_text(self.finished, self.finished + self.total - self.done, now - self.start)
            note(msg + (f", {eta}" if eta else ""))


def eta_text(done: int, total: int, elapsed: float) -> str:
    """'ETA 12 min' from the rate so far (empty before any progress)."""
    if done <= 0 or total <= done or elapsed <= 0:
        return ""
    left = elapsed / done * (total - done)
    if left < 90:
        return f"ETA {left:.0f} s"
    return f"ETA {left / 60:.0f} min" if left < 5400 else f"ETA {left / 3600:.1f} h"
