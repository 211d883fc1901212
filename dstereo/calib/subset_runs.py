"""Solving a plan's subsets block by block into a `SubsetTable`: bounded memory, an estimate, a refusal.

A block of a few thousand subsets is solved, reduced to its table rows (reprojection error and parameters,
~100 bytes a subset) and solver status, and written to the table; the solver's own per-subset outputs
(Schur complements, poses: ~6 KB a subset) are dropped with the block. Memory then no longer grows with C
beyond a few bytes a subset (the plan's ranks, status, fates and the columns a step is working on), so the
run can say before it starts what it will need, and refuse when that is more than the machine has.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from dstereo.calib import subset_table
from dstereo.calib.subset_table import SubsetTable
from dstereo.errors import DstereoError

NOTE_ABOVE = 20_000  # runs of more subsets print their memory/disk/time estimate
BLOCK_TARGET = 4096  # subsets per block: seconds of work, a few MB of solver output
KEEP_SOLUTIONS = 20_000  # up to this many subsets the solver's per-subset outputs are kept whole (as before)
# Peak resident memory measured with /usr/bin/time -v on 29 views, m = 20, 10 columns: C = 1e4 0.48 GB,
# 1e5 0.55 GB (real solves), 1e7 0.84 GB (the since-removed experiments/huge_run_fake_solve.py: everything but the solves, whose
# blocks held a flat ~0.5 GB over the first 3 minutes of a real 1e7 run): ~30 bytes a subset over ~0.53 GB
# (plan ranks 8, status/fate/usable 5, a column and its masked and sorted copies while a step, a statistic or
# a figure works on it). The estimate adds a third for margin.
BYTES_PER_SUBSET = 40
BASE_BYTES = 600 * 2 ** 20
CSV_FLOAT_CHARS = 21  # repr of a float64 and its comma


def available_memory() -> int:
    """Bytes the kernel says can be allocated without swapping (MemAvailable), else physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 2 ** 62


def _size(n: float) -> str:
    for unit, scale in (("GB", 2 ** 30), ("MB", 2 ** 20), ("kB", 2 ** 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def _duration(s: float) -> str:
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


@dataclass(frozen=True)
class RunEstimate:
    """What a run of `subsets` subsets needs: resident memory, disk (table file + CSV), and where."""

    subsets: int
    columns: int
    ram_bytes: int
    disk_bytes: int
    table_on_disk: bool
    available_ram: int
    free_disk: int
    folder: Path

    def text(self) -> str:
        where = (f"the per-subset values streamed to a {_size(8 * self.columns * self.subsets)} file in {self.folder}"
                 if self.table_on_disk else "the per-subset values held in memory")
        return (f"subsets: {self.subsets} to solve; memory about {_size(self.ram_bytes)} (available "
                f"{_size(self.available_ram)}; {where}); disk about {_size(self.disk_bytes)} for the table and "
                f"the per-subset CSV (free {_size(self.free_disk)})")

    def check(self) -> None:
        """Refuse (DstereoError, with the figures) a run that cannot fit."""
        if self.ram_bytes > self.available_ram:
            fit = int((self.available_ram - BASE_BYTES) / BYTES_PER_SUBSET)
            what = (f"lower --max-subsets to at most about {fit}" if fit >= 2 else
                    f"free memory first (a run needs about {_size(BASE_BYTES)} before any subset)")
            raise DstereoError(f"max-subsets: {self.subsets} subsets need about {_size(self.ram_bytes)} of memory but "
                               f"{_size(self.available_ram)} is available; {what}")
        if self.disk_bytes > self.free_disk:
            per = self.disk_bytes / max(self.subsets, 1)
            raise DstereoError(f"max-subsets: {self.subsets} subsets need about {_size(self.disk_bytes)} of disk in "
                               f"{self.folder} but {_size(self.free_disk)} is free; lower `max_subsets` to at most "
                               f"about {int(self.free_disk / per)} or free disk space")


def estimate_run(subsets: int, columns: int, per_set: int, folder: str | Path | None,
                 memory_limit: int | None = None) -> RunEstimate:
    """Memory and disk a run will need (module docstring), with what the machine has."""
    folder = Path(folder) if folder is not None else Path(os.environ.get("TMPDIR", "/tmp"))
    probe = next((p for p in (folder, *folder.parents) if p.exists()), Path("/"))
    table = 8 * columns * subsets
    on_disk = table > (subset_table.MEMORY_LIMIT_BYTES if memory_limit is None else memory_limit)
    ram = BASE_BYTES + BYTES_PER_SUBSET * subsets + (0 if on_disk else table)
    csv_row = 12 + 3 * per_set + CSV_FLOAT_CHARS * (columns + 1) + 8
    disk = (table if on_disk else 0) + csv_row * subsets
    return RunEstimate(subsets, columns, ram, disk, on_disk, available_memory(), shutil.disk_usage(probe).free,
                       folder)


def check_subset_run(n_images: int, per_set: int, cap: int, columns: int, folder, note=None,
                     label: str = "") -> RunEstimate | None:
    """Estimate the run of min(C(n, m), cap) subsets, refuse it (DstereoError) if it cannot fit, and pass
    the estimate to `note` for runs above NOTE_ABOVE subsets. Call before planning: the plan itself costs memory."""
    import math

    if per_set < 1 or per_set > n_images:
        return None  # plan_subsets gives the message
    count = min(math.comb(n_images, per_set), cap)
    est = estimate_run(count, columns, per_set, folder)
    est.check()
    if note is not None and count > NOTE_ABOVE:
        note(label + est.text())
    return est


def block_size(chunk: int, workers: int = 2) -> int:
    """Subsets per block: a multiple of what the solver runs at once, near BLOCK_TARGET."""
    step = max(1, chunk * workers)
    return max(step, (BLOCK_TARGET // step) * step)


Block = Callable[[object, Callable[[int, int], None] | None], tuple[np.ndarray, np.ndarray, object]]


def fingerprint(key, plan, columns: Sequence[str], size: int) -> str:
    """sha256 naming a run's blocks: the caller's `key` (arrays and values its subsets are solved from), the plan
    (count, total, sampling seed, m), the columns and the block size (a resumed run reuses blocks of the same cut)."""
    import hashlib

    h = hashlib.sha256()
    for part in key if isinstance(key, (tuple, list)) else (key,):
        if isinstance(part, np.ndarray):
            h.update(f"{part.dtype}{part.shape}".encode() + np.ascontiguousarray(part).tobytes())
        else:
            h.update(repr(part).encode())
        h.update(b"\0")
    from dstereo.runtime.aot import source_digest  # blocks solved by other code are not reused

    h.update(repr((len(plan), plan.total, plan.exhaustive, plan.seed, plan.per_set, tuple(columns), size,
                   source_digest())).encode())
    return h.hexdigest()


def _solve_task(task):
    """On a worker (or here): one block, (start, stop, rows, status, solutions or None). One compiled call at a time:
    a worker has one core (`runtime.tasks`)."""
    solve_block, block, start, keep = task
    if os.environ.get("DSTEREO_WORKER_THREADS") == "1":
        os.environ["DSTEREO_THREADS"] = "1"
    rows, status, solutions = solve_block(block, None)
    return start, np.asarray(rows, float), np.asarray(status), solutions if keep else None


def solve_in_blocks(plan, columns: Sequence[str], solve_block: Block, chunk: int, folder: str | Path | None = None,
                    progress: Callable[[int, int], None] | None = None, note: Callable[[str], None] | None = None,
                    memory_limit: int | None = None, key=None) -> tuple[SubsetTable, list]:
    """Solve `plan` block by block: `solve_block(block_plan, progress)` returns (rows (k, P), status (k,),
    solutions). Returns the table and, up to KEEP_SOLUTIONS subsets, the blocks' solutions (else []).

    Where the blocks run is the command's placement (`runtime.placement`): here one after another (default), or on
    a Dask cluster, every block a task (`solve_block` must then pickle: a closure over arrays does); the results are
    the same, block for block (tests). With a store of finished blocks and the caller's `key` (what the subsets are
    solved from: `fingerprint`), each finished block is kept as it arrives and a resumed run loads those instead of
    solving them again; only runs of more than KEEP_SOLUTIONS subsets (the long ones, whose solutions are not kept)
    use it."""
    from dstereo.runtime import placement

    where = placement.current()
    n = len(plan)
    table = SubsetTable(columns, n, folder=folder, memory_limit=memory_limit)
    keep = n <= KEEP_SOLUTIONS
    workers = max(2, int(getattr(where.runner, "workers", 2) or 2))
    # Up to KEEP_SOLUTIONS the solutions are kept whole anyway: one block here (each block ends with a round that waits
    # for its slowest chunks and subsets, `subset_solve`: C = 4845 in blocks of 4080 + 765 took ~0.05 s longer); on
    # a cluster blocks of the same size as above, each a task.
    size = block_size(chunk, workers) if (not keep or where.parallel) else max(n, 1)
    starts = list(range(0, n, size))
    store = None
    if where.store is not None and key is not None and not keep:
        store = where.store(fingerprint(key, plan, columns, size))
    kept: dict[int, object] = {}
    t0, done = time.perf_counter(), 0

    def finished(start, rows, status, solutions, new=True):
        nonlocal done
        table.put(start, rows, status)
        if keep:
            kept[start] = solutions
        if store is not None and new:
            store.save(f"block{start:012d}", {"rows": rows, "status": status}, {"start": start, "count": len(rows)})
        done += len(rows)
        if progress is not None:
            progress(done, n)

    try:
        todo = []
        for start in starts:
            stored = None if store is None else store.load(f"block{start:012d}")
            if stored is not None and len(stored[0]["rows"]) == min(start + size, n) - start:
                finished(start, stored[0]["rows"], stored[0]["status"], None, new=False)
            else:
                todo.append(start)
        if todo and done and note is not None:
            note(f"subsets: {done} of {n} resumed from the blocks kept in {getattr(store, 'folder', 'the store')}")
        if where.parallel and todo:
            _on_cluster(where.runner, plan, solve_block, todo, size, n, keep, finished)
        else:
            for start in todo:
                stop = min(start + size, n)
                sub = None if progress is None else (lambda d, _n, a=done: progress(a + d, n))
                rows, status, solutions = solve_block(plan.block(start, stop), sub)
                finished(start, np.asarray(rows, float), np.asarray(status), solutions)
                if start == todo[0] and stop < n and note is not None:
                    rate = (stop - start) / max(time.perf_counter() - t0, 1e-9)
                    left = "all" if done == stop - start else f"the other {n - done + stop - start} of"
                    note(f"subsets: {rate:.0f} subsets/s on the first {stop - start}: about "
                         f"{_duration((n - done + stop - start) / rate)} for {left} {n}")
    except BaseException:
        table.close()
        raise
    return table, [kept[s] for s in sorted(kept)]


def _on_cluster(runner, plan, solve_block, starts, size, n, keep, finished) -> None:
    """Every block of `starts` a task of `runner` (a parallel `tasks.FrameRunner`), handed to `finished` as it
    comes back; a block whose task failed (its workers died `retries` + 1 times) ends the run with the reason."""
    failed = []

    def on_done(task):
        if task.failed:
            failed.append(task.failed)
            return
        start, rows, status, solutions = task.value
        finished(start, rows, status, solutions)

    items = [(i, (solve_block, plan.block(s, min(s + size, n)), s, keep)) for i, s in enumerate(starts)]
    runner.map(_solve_task, items, on_done, stage="subset blocks")
    if failed:
        raise DstereoError(f"subsets: {len(failed)} block(s) of {size} subsets failed on the cluster ({failed[0]}); "
                           "rerun with --resume to solve them again")
