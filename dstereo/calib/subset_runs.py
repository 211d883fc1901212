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


def solve_in_blocks(plan, columns: Sequence[str], solve_block: Block, chunk: int, folder: str | Path | None = None,
                    progress: Callable[[int, int], None] | None = None, note: Callable[[str], None] | None = None,
                    memory_limit: int | None = None) -> tuple[SubsetTable, list]:
    """Solve `plan` block by block: `solve_block(block_plan, progress)` returns (rows (k, P), status (k,),
    solutions). Returns the table and, up to KEEP_SOLUTIONS subsets, the blocks' solutions (else [])."""
    n = len(plan)
    table = SubsetTable(columns, n, folder=folder, memory_limit=memory_limit)
    # Up to KEEP_SOLUTIONS the solutions are kept whole anyway: one block (each block ends with a round that waits
    # for its slowest chunks and subsets, `subset_solve`: C = 4845 in blocks of 4080 + 765 took ~0.05 s longer)
    size, kept = (block_size(chunk) if n > KEEP_SOLUTIONS else max(n, 1)), []
    t0 = time.perf_counter()
    try:
        for start in range(0, n, size):
            stop = min(start + size, n)
            sub = None if progress is None else (lambda d, _n, a=start: progress(a + d, n))
            rows, status, solutions = solve_block(plan.block(start, stop), sub)
            table.put(start, rows, status)
            if n <= KEEP_SOLUTIONS:
                kept.append(solutions)
            if start == 0 and stop < n and note is not None:
                rate = stop / max(time.perf_counter() - t0, 1e-9)
                note(f"subsets: {rate:.0f} subsets/s on the first {stop}: about {_duration(n / rate)} for all {n}")
    except BaseException:
        table.close()
        raise
    return table, kept
