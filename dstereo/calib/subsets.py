"""Which image subsets to solve: all C(N, m) when that is at most `cap`, else a seeded random sample.

A plan does not hold its (C, m) index table unless asked (`index`): 10 million subsets of 20 images would be
800 MB. It holds the subsets' lexicographic ranks (the position in `itertools.combinations` order) and turns
any block of them into index rows on demand (`rows`, `block`), so a huge run holds 8 bytes per sampled subset
and nothing per subset of an exhaustive one.

Sampling: up to `REJECTION_MAX` subsets with total >= 2 cap, distinct subsets are drawn by rejection, as
before this module streamed (same seed, same sample); beyond that, `cap` distinct ranks are drawn without
replacement (numpy's Generator.choice), which stays fast and small when the sample is most of the total.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from dstereo.errors import DstereoError

REJECTION_MAX = 100_000  # rejection sampling keeps a Python set of tuples (~250 B a subset): fine up to here
RANK_LIMIT = 2 ** 62  # ranks as int64; beyond, only rejection sampling (the total then dwarfs any cap)


class SubsetPlan:
    """C subsets of m of N images, rows sorted. Either an explicit `index` (C, m) or lazy ranks."""

    def __init__(self, index: np.ndarray | None, total: int, exhaustive: bool, seed: int,
                 ranks: np.ndarray | None = None, n_images: int | None = None, per_set: int | None = None):
        self._index = None if index is None else np.asarray(index, dtype=np.int32)
        self.total, self.exhaustive, self.seed = int(total), bool(exhaustive), int(seed)
        self._ranks = ranks  # None with an explicit index, or for an exhaustive plan (ranks 0..total-1)
        self.n_images = n_images
        self.per_set = int(self._index.shape[1]) if self._index is not None else int(per_set)
        self.count = len(self._index) if self._index is not None else (
            self.total if ranks is None else len(ranks))

    def __len__(self) -> int:
        return self.count

    @property
    def index(self) -> np.ndarray:
        """(C, m) int32: the whole table (built on demand; prefer `rows` for a huge plan)."""
        if self._index is None:
            return self.rows(0, self.count)
        return self._index

    def rows(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, m) int32 index rows of subsets start..stop-1."""
        stop = min(stop, self.count)
        if self._index is not None:
            return self._index[start:stop]
        ranks = np.arange(start, stop, dtype=np.int64) if self._ranks is None else self._ranks[start:stop]
        return unrank(ranks, self.n_images, self.per_set)

    def block(self, start: int, stop: int) -> "SubsetPlan":
        """The subsets start..stop-1 as a small plan with an explicit index (same total, seed)."""
        return SubsetPlan(self.rows(start, stop), self.total, self.exhaustive, self.seed)

    def describe(self) -> str:
        if self.exhaustive:
            return f"all {self.total} subsets"
        return f"random sample of {self.count} of {self.total} subsets (seed {self.seed})"


def _comb_table(n: int, m: int) -> np.ndarray:
    """comb[a, b] = C(a, b) for a <= n, b <= m, int64 (the plan's total is below RANK_LIMIT)."""
    table = np.zeros((n + 1, m + 1), dtype=np.int64)
    for a in range(n + 1):
        for b in range(min(a, m) + 1):
            table[a, b] = math.comb(a, b)
    return table


def unrank(ranks: np.ndarray, n: int, m: int) -> np.ndarray:
    """(len(ranks), m) int32: the combinations of m of range(n) at these lexicographic ranks
    (rank r is the r-th tuple of itertools.combinations(range(n), m))."""
    comb = _comb_table(n, m)
    r = np.array(ranks, dtype=np.int64)
    out = np.empty((len(r), m), dtype=np.int32)
    nxt = np.zeros(len(r), dtype=np.int64)  # smallest element allowed at this position
    for i in range(m):
        left = m - 1 - i  # elements still to place after this one
        chosen = np.full(len(r), -1, dtype=np.int64)
        for x in range(n - left):
            # Tuples with element x here (and larger ones after): C(n - 1 - x, left) of them.
            count = comb[n - 1 - x, left]
            here = (chosen < 0) & (x >= nxt)
            take = here & (r < count)
            chosen[take] = x
            skip = here & ~take
            r[skip] -= count
        out[:, i] = chosen
        nxt = chosen + 1
    return out


def plan_subsets(n_images: int, per_set: int, cap: int = 2000, seed: int = 0) -> SubsetPlan:
    if per_set < 3:
        raise DstereoError(f"per-set: m = {per_set} images per subset is too few; a calibration needs m >= 3")
    if per_set > n_images:
        raise DstereoError(
            f"per-set: m = {per_set} images per subset but only {n_images} usable images; lower `per_set` "
            f"to at most {n_images} or add images"
        )
    if cap < 1:
        raise DstereoError(f"max-subsets: {cap} must be at least 1")
    total = math.comb(n_images, per_set)
    if total <= cap:
        if total <= REJECTION_MAX:
            index = np.array(list(itertools.combinations(range(n_images), per_set)), dtype=np.int32)
            return SubsetPlan(index, total, True, seed)
        return SubsetPlan(None, total, True, seed, n_images=n_images, per_set=per_set)
    rng = np.random.default_rng(seed)
    if (cap <= REJECTION_MAX and total >= 2 * cap) or total >= RANK_LIMIT:
        chosen: set[tuple[int, ...]] = set()
        while len(chosen) < cap:  # rejection sampling of distinct subsets; total >= 2 cap so this ends quickly
            chosen.add(tuple(sorted(rng.choice(n_images, per_set, replace=False).tolist())))
        return SubsetPlan(np.array(sorted(chosen), dtype=np.int32), total, False, seed)
    ranks = np.sort(rng.choice(total, size=cap, replace=False).astype(np.int64))
    return SubsetPlan(None, total, False, seed, ranks=ranks, n_images=n_images, per_set=per_set)


@dataclass
class SubsetSolutions:
    """The subsets' solves of any rig (one camera's views: `mono.solve_subsets`; a rig's frames:
    `multiview.solve_view_subsets`), rows aligned with the subsets solved."""

    names: tuple[str, ...]
    values: np.ndarray  # (C, G)
    std: np.ndarray  # (C, G) Jacobian standard deviations of each subset's own solve
    rms: np.ndarray  # (C,)
    iterations: np.ndarray  # (C,)
    status: np.ndarray  # (C,)
    timings: dict = field(default_factory=dict)
    plan: SubsetPlan | None = None  # the plan whose subsets these are (one camera's)
    index: np.ndarray | None = None  # (C, m) each subset's frames (a rig's)
    poses: np.ndarray | None = None  # (C, m, 6) each subset's frame poses, in its `index` order (a rig's)

    @property
    def converged(self) -> np.ndarray:
        return self.status > 0
