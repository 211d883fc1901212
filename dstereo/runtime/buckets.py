"""Shape buckets: the sizes a compiled program is built for, so that one program serves every data set in a bucket.

A compiled program is specialised to its arguments' shapes; a calibration's shapes follow the data set (views,
subset size, problems per call), so every new data set compiled its programs anew (seconds each, issue 33). The
solver already takes a weight per view (0: the view is carried but takes no part), so a problem of V views is
solved as one of `views(V)` views, the extra ones weighted 0, and its results cut back to V: one compiled program,
kept on disk (`runtime/aot.py`), then serves every V of the bucket. Per-view programs (a pose refit, an
undistortion) take copies of a real view as padding and drop their results (`pad_rows`, `cut_rows`).

The sizes (`VIEW_BUCKETS`) are chosen by measuring compile time against the cost of the padded work
(experiments/bucket_sizes.py; docs/validation.md): the padded views are computed like real ones, so a solve of V
views costs about views(V) / V of its unpadded time. DSTEREO_SHAPE_BUCKETS=0 turns padding off (exact shapes, as
before): a check, and the padding's cost measured side by side.
"""

from __future__ import annotations

import os

import numpy as np

# Views (frames of a rig) per problem: 1-4 exact (the smallest calibrations compile little), then steps of ~12 %
# (experiments/bucket_sizes.py: the largest padding a size meets is the step to its bucket), above the last a
# multiple of its step.
VIEW_BUCKETS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 18, 20, 22, 24, 27, 30, 34, 38, 42, 47, 52, 58, 64)
STEP_ABOVE = 8  # above the last bucket: the next multiple of this (at most 12 % padding there)


def enabled(env=None) -> bool:
    """Whether shapes are padded to buckets (DSTEREO_SHAPE_BUCKETS=0: exact shapes)."""
    env = os.environ if env is None else env
    return env.get("DSTEREO_SHAPE_BUCKETS", "") != "0"


def views(n: int) -> int:
    """The bucket of n views: the smallest VIEW_BUCKETS entry >= n, above them the next multiple of STEP_ABOVE;
    n itself with buckets off."""
    n = int(n)
    if not enabled() or n <= 0:
        return n
    for b in VIEW_BUCKETS:
        if b >= n:
            return b
    return -(-n // STEP_ABOVE) * STEP_ABOVE


def sizes_between(lo: int, hi: int) -> tuple[int, ...]:
    """The buckets that views lo..hi fall in (each once, ascending)."""
    return tuple(sorted({views(n) for n in range(max(1, lo), hi + 1)}))


def pad_axis(a, size: int, axis: int, fill=None):
    """numpy `a` padded along `axis` to `size`: with `fill` (a scalar) or, for None, copies of its first entry
    along that axis (a real view: finite values that every per-view computation handles). `a` unchanged when it
    already has `size` entries."""
    a = np.asarray(a)
    n = a.shape[axis]
    if n == size:
        return a
    if n > size:
        raise ValueError(f"pad_axis: {n} entries along axis {axis}, more than the bucket's {size}")
    shape = list(a.shape)
    shape[axis] = size - n
    if fill is None:
        first = np.take(a, [0], axis=axis)
        extra = np.broadcast_to(first, shape)
    else:
        extra = np.full(shape, fill, dtype=np.result_type(a, np.asarray(fill)))
    return np.concatenate([a, extra.astype(a.dtype, copy=False)], axis=axis)


def pad_rows(a, size: int):
    """`pad_axis` along the first axis with copies of the first row."""
    return pad_axis(a, size, 0)


def cut_rows(tree, n: int):
    """Every array of `tree` (a tuple, list or single array) cut to its first n rows."""
    if isinstance(tree, (tuple, list)):
        return type(tree)(cut_rows(t, n) for t in tree)
    return np.asarray(tree)[:n]


def _shape(a):
    """np.shape, and a tuple of them for a tuple or list of arrays (an argument may be a pair of arrays)."""
    return tuple(_shape(x) for x in a) if isinstance(a, (tuple, list)) else np.shape(a)


def per_row(fn, row_args: tuple[int, ...], kind: tuple | None = None):
    """`fn` whose positional arguments `row_args` (a leading axis of rows, the same length, each row computed on its
    own: a vmapped per-view program) are padded to their bucket with copies of the first row, and whose outputs are
    cut back to the rows given: one compiled `fn` serves every row count of a bucket. `kind` = (name, factory
    arguments): how jobs/prebuild.py makes `fn` again, to build it ahead for the other buckets (`note`)."""

    def padded(*args):
        n = len(args[row_args[0]])
        size = views(n)
        if kind is not None and enabled():
            shapes = tuple((np.shape(a)[1:] if i in row_args else _shape(a)) for i, a in enumerate(args))
            note(kind[0], (kind[1], tuple(np.asarray(a)[:1] if i in row_args else a for i, a in enumerate(args)),
                           row_args), tag=(kind[1], shapes), size=size)
        if size == n:
            return fn(*args)
        args = tuple(pad_rows(a, size) if i in row_args else a for i, a in enumerate(args))
        return cut_rows(fn(*args), n)

    padded.__wrapped__ = fn
    return padded


# --- what this process used, to build the other buckets ahead (runtime/prebuild.py, jobs/prebuild.py) --------------

_noted: dict = {}
_sizes: set[int] = set()


def note(kind: str, spec, tag=None, size: int | None = None) -> None:
    """Record that a program of `kind` (a name jobs/prebuild.py knows) was called with `spec` (picklable: what it
    needs besides the view count to call it again); once per distinct `tag` (hashable: what decides the program;
    default the pickled spec). A subset run calls its solver once per chunk: a tag is checked in ~1 us, a pickle
    takes ~50 us. `size`: the bucket it ran at (the builder starts next to the sizes used)."""
    if size is not None:
        _sizes.add(int(size))
    if tag is not None:
        tag = (kind, tag)
        if tag in _noted:
            return
    else:
        import pickle

        try:
            tag = kind + "\0" + repr(pickle.dumps(spec, protocol=4))
        except Exception:  # noqa: BLE001 - not picklable: not built ahead, nothing else changes
            return
    _noted.setdefault(tag, (kind, spec))


def noted() -> list[tuple[str, object]]:
    """The (kind, spec) recorded so far, in first-use order."""
    return list(_noted.values())


def noted_sizes() -> tuple[int, ...]:
    """The view buckets the noted programs ran at."""
    return tuple(sorted(_sizes))


def clear_noted() -> None:
    _noted.clear()
    _sizes.clear()


def nearest_first(sizes, used) -> list[int]:
    """`sizes` ordered by their distance (ratio) to the nearest of `used` (a data set of a similar size is the
    likeliest next one); as given without `used`."""
    used = [u for u in used if u > 0]
    if not used:
        return list(sizes)
    return sorted(sizes, key=lambda s: (min(abs(np.log(s / u)) for u in used), s))
