"""Which image subsets to solve: all C(N, m) when that is at most `cap`, else a seeded random sample."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from dstereo.errors import DstereoError


@dataclass(frozen=True)
class SubsetPlan:
    index: np.ndarray  # (C, m) image indices, each row sorted
    total: int  # C(N, m)
    exhaustive: bool  # False: a random sample of `len(index)` of the `total`
    seed: int

    def describe(self) -> str:
        if self.exhaustive:
            return f"all {self.total} subsets"
        return f"random sample of {len(self.index)} of {self.total} subsets (seed {self.seed})"


def plan_subsets(n_images: int, per_set: int, cap: int = 2000, seed: int = 0) -> SubsetPlan:
    if per_set < 3:
        raise DstereoError(f"per-set: m = {per_set} images per subset is too few; a calibration needs m >= 3")
    if per_set > n_images:
        raise DstereoError(
            f"per-set: m = {per_set} images per subset but only {n_images} usable images; lower --per-set "
            f"to at most {n_images} or add images"
        )
    if cap < 1:
        raise DstereoError(f"max-subsets: {cap} must be at least 1")
    total = math.comb(n_images, per_set)
    if total <= cap:
        index = np.array(list(itertools.combinations(range(n_images), per_set)), dtype=np.int32)
        return SubsetPlan(index, total, True, seed)
    rng = np.random.default_rng(seed)
    chosen: set[tuple[int, ...]] = set()
    while len(chosen) < cap:  # rejection sampling of distinct subsets; total > cap so this ends quickly
        chosen.add(tuple(sorted(rng.choice(n_images, per_set, replace=False).tolist())))
    return SubsetPlan(np.array(sorted(chosen), dtype=np.int32), total, False, seed)
