"""The thesis's step-wise robust filter of image subsets (section 4.2.2.1), over any named-column table.

Rows are subsets, columns are named parameters (mono: re, fx, fy, cx, cy, k1, ...; stereo: stereo_re, Tnorm,
Tx, ..., RVz). Steps run in order; each names parameters with a max error:
- absolute parameters (`re`, `stereo_re`): subsets whose value exceeds the max error are removed;
- every other parameter, with alpha its max error: Q1, Q3 and IQR = Q3 - Q1 of the surviving subsets,
  subsets outside [Q1 - alpha IQR, Q3 + alpha IQR] removed, quartiles recomputed, repeated until none is
  outside. Quartiles are the thesis's: medians of the lower and upper halves, the median of an odd count
  belonging to neither half.
Parameters of one step are filtered jointly: each pass removes every subset that fails any of them.
A minimum number of subsets stops a step before a pass that would leave fewer, and says so.

The table is read a column at a time (`SubsetTable`, possibly on disk): a step holds only its own columns,
and the statistics per step are computed column by column and kept (the stats files ask for each k often).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from dstereo.calib.subset_table import SubsetTable
from dstereo.config.calibration import ABSOLUTE_PARAMETERS, Step
from dstereo.errors import DstereoError

SURVIVES = 0  # `removed_at` value of a subset that passed every step
UNUSABLE = -1  # `removed_at` value of a subset excluded before the steps (its solve did not converge)


def thesis_quartiles(values: np.ndarray) -> tuple[float, float]:
    """(Q1, Q3): medians of the lower and upper halves; an odd count's median belongs to neither half."""
    x = np.sort(np.asarray(values, dtype=float))
    n = x.size
    if n == 0:
        return float("nan"), float("nan")
    if n == 1:
        return float(x[0]), float(x[0])
    half = n // 2
    return float(np.median(x[:half])), float(np.median(x[n - half:]))


@dataclass(frozen=True)
class StepOutcome:
    """What one step did: survivors before and after, passes, the last bounds per parameter."""

    number: int  # 1-based
    parameters: tuple[str, ...]
    max_error: tuple[float, ...]
    before: int
    after: int
    passes: int  # IQR passes that removed subsets
    bounds: dict[str, tuple[float, float]]  # at the last pass: [lo, hi] per parameter
    stopped_by_minimum: bool
    message: str

    @property
    def removed(self) -> int:
        return self.before - self.after


@dataclass
class FilterResult:
    """The table, which rows were usable, and at which step each row was removed (0: survives)."""

    columns: tuple[str, ...]
    table: SubsetTable  # C rows of the named columns (read a column at a time)
    usable: np.ndarray  # (C,) bool
    removed_at: np.ndarray  # (C,) int16: SURVIVES, step number k, or UNUSABLE
    steps: list[StepOutcome]
    _stats: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.table)

    def alive_after(self, k: int) -> np.ndarray:
        """(C,) bool: usable rows that survived steps 1..k (k = 0: before any step)."""
        return self.usable & ((self.removed_at == SURVIVES) | (self.removed_at > k))

    @property
    def survivors(self) -> np.ndarray:
        return self.alive_after(len(self.steps))

    def column(self, name: str) -> np.ndarray:
        return self.table.column(self.columns.index(name))

    def values(self, name: str, k: int) -> np.ndarray:
        """One column's values over the survivors of steps 1..k."""
        return self.column(name)[self.alive_after(k)]

    def stats(self, k: int) -> dict[str, dict[str, float]]:
        """Mean, standard deviation (population, as numpy's std) and error % = std / |mean| * 100 per column,
        plus min and max, over the survivors of steps 1..k (computed once per k)."""
        if k in self._stats:
            return self._stats[k]
        alive = self.alive_after(k)
        out = {}
        for j, name in enumerate(self.columns):
            col = self.table.column(j)[alive]
            mean, std = float(np.mean(col)), float(np.std(col))
            out[name] = {"mean": mean, "std": std, "error_percent": 100.0 * std / abs(mean) if mean else float("inf"),
                         "min": float(np.min(col)), "max": float(np.max(col)), "count": int(col.size)}
        self._stats[k] = out
        return out


def _bounds(col: np.ndarray, name: str, limit: float, absolute: Sequence[str]) -> tuple[float, float]:
    if name in absolute:
        return -np.inf, limit
    q1, q3 = thesis_quartiles(col)
    iqr = q3 - q1
    return q1 - limit * iqr, q3 + limit * iqr


def run_steps(
    table: np.ndarray | SubsetTable,
    columns: Sequence[str],
    steps: Sequence[Step],
    usable: np.ndarray | None = None,
    min_subsets: int | None = None,
    absolute: Sequence[str] = ABSOLUTE_PARAMETERS,
) -> FilterResult:
    """Apply `steps` in order to the rows of `table` (C, P), an array or a SubsetTable, whose `usable` flag is set.

    A step's own `min_subsets` overrides the argument. A pass that would leave no subset at all (possible only
    for absolute limits) raises DstereoError unless a minimum stops the step first.
    """
    columns = tuple(columns)
    if not isinstance(table, SubsetTable):
        table = np.asarray(table, dtype=float)
        if table.ndim != 2 or table.shape[1] != len(columns):
            raise DstereoError(f"subset table: shape {table.shape} does not match {len(columns)} columns {columns}")
        table = SubsetTable.from_rows(table, columns)
    elif table.columns != columns:
        raise DstereoError(f"subset table: columns {table.columns} are not {columns}")
    usable = np.ones(len(table), bool) if usable is None else np.asarray(usable, bool)
    removed_at = np.where(usable, SURVIVES, UNUSABLE).astype(np.int16)
    outcomes = []
    for k, step in enumerate(steps, 1):
        missing = [p for p in step.parameters if p not in columns]
        if missing:
            raise DstereoError(f"step {k}: parameter(s) {missing} are not among the subset results {list(columns)}")
        minimum = step.min_subsets if step.min_subsets is not None else min_subsets
        alive = removed_at == SURVIVES
        before, passes, stopped, bounds = int(alive.sum()), 0, False, {}
        while True:
            outside = np.zeros(len(table), bool)
            for name, limit in zip(step.parameters, step.max_error):
                col = table.column(columns.index(name))  # one column at a time (re-read per pass: bounded memory)
                lo, hi = _bounds(col[alive], name, limit, absolute)
                bounds[name] = (float(lo), float(hi))
                outside |= alive & ~((col >= lo) & (col <= hi))
            if not outside.any():
                break
            left = int((alive & ~outside).sum())
            if minimum is not None and left < minimum:
                stopped = True
                break
            if left == 0:
                raise DstereoError(
                    f"step {k} ({step.describe()}) would remove all {int(alive.sum())} remaining subsets; "
                    "raise its max error or set a minimum number of subsets"
                )
            removed_at[outside] = k
            alive &= ~outside
            passes += 1
        after = int(alive.sum())
        message = f"step {k} ({step.describe()}): {before} -> {after} subsets in {passes} pass(es)"
        if stopped:
            message += (f"; stopped before a pass that would leave {left} < minimum {minimum} subsets "
                        f"(kept {after}, some still outside the limits)")
        outcomes.append(
            StepOutcome(k, step.parameters, step.max_error, before, after, passes, bounds, stopped, message))
    return FilterResult(columns, table, usable, removed_at, outcomes)
