"""The per-subset table (C rows, named float64 columns) and solver status, in memory or in a file.

The robust steps and the statistics read it a column at a time; nothing needs all C rows of every column at
once. Below `MEMORY_LIMIT_BYTES` it is a plain (P, C) array. Above, it is a raw float64 file laid out column
after column (column j's C values contiguous), written with `os.pwrite` as solve blocks finish and read back
one column (or one block of rows) at a time; the file is unlinked as soon as it is created, so nothing
is left behind however the run ends: the values go through the page cache, not this process's
memory, so a run of 10 million subsets holds ~80 MB per column it is working on, not 10 columns x 80 MB.
Status (int16), 2 bytes a subset, stays in memory.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

MEMORY_LIMIT_BYTES = 256 * 2 ** 20  # above this the values go to a file (10 columns: ~3.3 million subsets)


class SubsetTable:
    """`count` rows of float64 `columns` plus an int16 `status` per row (solver status; > 0 converged)."""

    def __init__(self, columns: Sequence[str], count: int, folder: str | Path | None = None,
                 memory_limit: int | None = None):
        self.columns, self.count = tuple(columns), int(count)
        self.status = np.zeros(self.count, dtype=np.int16)
        self._values = self._file = self._remove_at_close = None
        nbytes = 8 * len(self.columns) * self.count
        if nbytes <= (MEMORY_LIMIT_BYTES if memory_limit is None else memory_limit):
            self._values = np.full((len(self.columns), self.count), np.nan)
            return
        parent = Path(folder) if folder is not None else Path(tempfile.gettempdir())
        parent.mkdir(parents=True, exist_ok=True)
        self._file, name = tempfile.mkstemp(prefix=".dstereo-subsets-", suffix=".f64", dir=parent)
        self._path = Path(name)
        try:  # unlinked at once (POSIX): the space is freed when the file closes, even if the process is killed
            os.unlink(name)
        except OSError:  # Windows: removed by close()
            self._remove_at_close = self._path
        os.ftruncate(self._file, nbytes)  # sparse: disk blocks are taken as rows arrive

    @classmethod
    def from_rows(cls, table: np.ndarray, columns: Sequence[str], status: np.ndarray | None = None) -> "SubsetTable":
        """An in-memory table holding `table` (C, P) as it is (a transposed view, no copy)."""
        table = np.asarray(table, dtype=float)
        out = cls(columns, 0)
        out.count, out._values = len(table), table.T
        out.status = np.ones(len(table), np.int16) if status is None else np.asarray(status).astype(np.int16)
        return out

    @property
    def on_disk(self) -> bool:
        return self._file is not None

    @property
    def path(self) -> Path | None:
        """Where the values file was created (already unlinked on POSIX systems)."""
        return self._path if self._file is not None else None

    def __len__(self) -> int:
        return self.count

    @property
    def shape(self) -> tuple[int, int]:
        return self.count, len(self.columns)

    def put(self, start: int, rows: np.ndarray, status: np.ndarray) -> None:
        """Rows start..start+len(rows)-1 (k, P) and their solver status."""
        rows = np.asarray(rows, dtype=np.float64)
        stop = start + len(rows)
        self.status[start:stop] = status
        if self._values is not None:
            self._values[:, start:stop] = rows.T
            return
        for j in range(len(self.columns)):
            os.pwrite(self._file, np.ascontiguousarray(rows[:, j]).tobytes(), 8 * (j * self.count + start))

    def column(self, j: int | str) -> np.ndarray:
        """(C,) float64 values of one column (a fresh array when on disk, a view in memory)."""
        j = self.columns.index(j) if isinstance(j, str) else int(j)
        if self._values is not None:
            return self._values[j]
        return self._read(j, 0, self.count)

    def rows(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, P) float64 rows."""
        stop = min(stop, self.count)
        if self._values is not None:
            return self._values[:, start:stop].T
        return np.stack([self._read(j, start, stop) for j in range(len(self.columns))], axis=1)

    def _read(self, j: int, start: int, stop: int) -> np.ndarray:
        out = np.empty(stop - start, dtype=np.float64)
        view, offset, done = memoryview(out).cast("B"), 8 * (j * self.count + start), 0
        while done < len(view):  # os.preadv may return short reads on big requests
            got = os.preadv(self._file, [view[done:]], offset + done)
            if got <= 0:
                raise OSError(f"subset table {self._path}: short read")
            done += got
        return out

    def close(self) -> None:
        """Delete the file (if any); the table is unusable afterwards when it was on disk."""
        if self._file is not None:
            os.close(self._file)
            self._file = None
            if self._remove_at_close is not None and self._remove_at_close.exists():
                self._remove_at_close.unlink()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: os may be gone
            pass
